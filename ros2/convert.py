"""Pure mapping of arena poses to ROS 2: topic and frame names, stamps, quaternions, Zenoh keys.

No files, no clocks, no Zenoh, no ``rosbags``: plain Python over numbers and strings.

Conventions (see ``docs/ros2.md``):

- frame: every pose is in the ``arena`` frame (metres, x/y on the floor, z = 0 up, yaw counter-
  clockwise from +x, as the arena messages); a robot's TF child frame is its ROS name;
- ROS names: a robot's name when the tracker knows it, else ``track_<id>``; characters a ROS 2 name
  token cannot hold (``-``, ``.``) become ``_`` and a name starting with a digit gets ``robot_``
  in front (ROS 2 name tokens are ``[A-Za-z_][A-Za-z0-9_]*`` without repeated or trailing ``_``);
- topics: ``/arena/robots/<name>/pose`` (tracks), ``/arena/groundtruth/<name>/pose`` (webcam
  ground truth), ``/arena/sim/truth/<name>/pose`` (the simulator's exact poses), ``/tf``: the same
  layout as the arena's Zenoh keys, one level deeper;
- stamps: nanoseconds, ``t_us * 1000 + offset_ns`` (the files' own clock unless an offset is given).
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

#: frame of every pose, the TF parent of every robot
FRAME_ID = "arena"
#: the TF topic (zenoh-bridge-ros2dds maps it to the Zenoh key ``tf``)
TF_TOPIC = "/tf"
POSE_TYPE = "geometry_msgs/msg/PoseStamped"
TF_TYPE = "tf2_msgs/msg/TFMessage"

_BAD_CHARS = re.compile(r"[^A-Za-z0-9_]")
_RUNS = re.compile(r"_{2,}")


class RosNameError(ValueError):
    """A name that cannot become a ROS 2 name token."""


@dataclass(frozen=True)
class Pose:
    """One planar pose in the ``arena`` frame: ``name`` (ROS name), stamp in ns, metres, rad
    (``yaw`` NaN when the heading is unknown)."""

    name: str
    stamp_ns: int
    x: float
    y: float
    yaw: float


def ros_token(name: str) -> str:
    """``name`` as one ROS 2 name token: ``-``/``.`` and other characters become ``_``, runs of
    ``_`` collapse, leading/trailing ``_`` go, a leading digit gets ``robot_`` in front."""
    token = _RUNS.sub("_", _BAD_CHARS.sub("_", str(name))).strip("_")
    if not token:
        raise RosNameError(f"name {name!r} has no letter or digit to make a ROS 2 name from")
    if token[0].isdigit():
        token = f"robot_{token}"
    return token


def entity_name(robot: str | None, track_id: str | int) -> str:
    """ROS name of a track: its robot's name when known, else ``track_<id>``."""
    if robot:
        return ros_token(robot)
    return ros_token(f"track_{track_id}")


def pose_topic(name: str) -> str:
    """Topic of a robot's tracked pose: ``/arena/robots/<name>/pose``."""
    return f"/arena/robots/{ros_token(name)}/pose"


def groundtruth_topic(name: str) -> str:
    """Topic of a robot's webcam ground truth: ``/arena/groundtruth/<name>/pose``."""
    return f"/arena/groundtruth/{ros_token(name)}/pose"


def sim_truth_topic(name: str) -> str:
    """Topic of a robot's exact simulated pose: ``/arena/sim/truth/<name>/pose``."""
    return f"/arena/sim/truth/{ros_token(name)}/pose"


def quaternion_from_yaw(yaw: float) -> tuple[float, float, float, float]:
    """``(x, y, z, w)`` of a rotation by ``yaw`` rad about +z; all NaN for an unknown yaw."""
    if yaw is None or not math.isfinite(yaw):
        return (math.nan, math.nan, math.nan, math.nan)
    return (0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0))


def yaw_from_quaternion(x: float, y: float, z: float, w: float) -> float:
    """The rotation about +z of a quaternion (rad, in (-pi, pi])."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def split_stamp(stamp_ns: int) -> tuple[int, int]:
    """``(sec, nanosec)`` of a ``builtin_interfaces/msg/Time`` for a stamp in ns (>= 0)."""
    stamp_ns = int(stamp_ns)
    if stamp_ns < 0:
        raise ValueError(f"stamp {stamp_ns} ns is before 0: a ROS 2 time cannot hold it")
    return stamp_ns // 1_000_000_000, stamp_ns % 1_000_000_000


def stamp_ns(t_us: int, offset_ns: int = 0) -> int:
    """A file's ``t_us`` (µs) as a ROS stamp in ns, shifted by ``offset_ns``."""
    return int(t_us) * 1000 + int(offset_ns)


def clock_offset_ns(pairs: Iterable[tuple[int, int]]) -> int | None:
    """Offset (ns) from the sensor clock to the host wall clock, from ``(wall_ns, sensor_us)``
    pairs of the same instant seen from both sides (a message's publish time and the sensor time
    it carries): the smallest difference, i.e. the one with the least delay between the two
    (None for no pair). Sensor time + offset = wall time, late by that least delay."""
    best = None
    for wall_ns, sensor_us in pairs:
        d = int(wall_ns) - int(sensor_us) * 1000
        best = d if best is None or d < best else best
    return best


def tf_groups(poses: Sequence[Pose]) -> list[list[Pose]]:
    """The poses with a known yaw grouped by stamp (one ``TFMessage`` per tracker update), in
    stamp order. tf2 rejects NaN rotations, so a pose without a heading has no transform."""
    groups: dict[int, list[Pose]] = {}
    for p in poses:
        if math.isfinite(p.yaw):
            groups.setdefault(p.stamp_ns, []).append(p)
    return [groups[k] for k in sorted(groups)]


def bridge_key(topic: str, namespace: str = "/") -> str:
    """The Zenoh key zenoh-bridge-ros2dds uses for ROS 2 ``topic``: the topic without its leading
    ``/``, below the bridge's ``namespace`` when one is configured (``/lab`` -> ``lab/<topic>``).
    See ``ros2_name_to_key_expr`` in zenoh-plugin-ros2dds (``src/ros2_utils.rs``)."""
    if not topic.startswith("/"):
        raise RosNameError(f"topic {topic!r} is not a fully qualified ROS 2 name (starts with '/')")
    ns = namespace.strip("/")
    return f"{ns}/{topic[1:]}" if ns else topic[1:]


def rmw_zenoh_key(topic: str, msgtype: str, type_hash: str, domain_id: int = 0) -> str:
    """The Zenoh key rmw_zenoh (``rmw_zenoh_cpp``) uses for data on ``topic``:
    ``<domain>/<topic without leading '/'>/<DDS type name>/<type hash>``, e.g.
    ``0/arena/robots/zumo1/pose/geometry_msgs::msg::dds_::PoseStamped_/RIHS01_...``.
    Documentation only: not used by ``arena ros2``, and not tested against rmw_zenoh here (it also
    needs liveliness tokens and per-sample attachments, see ``docs/ros2.md``)."""
    pkg, kind, name = msgtype.split("/")
    return f"{int(domain_id)}/{topic.strip('/')}/{pkg}::{kind}::dds_::{name}_/{type_hash}"

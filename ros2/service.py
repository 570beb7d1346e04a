"""Zenoh side of ``arena ros2``: arena tracks in, ROS 2 CDR messages out, for zenoh-bridge-ros2dds.

One subscriber on ``arena/robots/*`` (and ``arena/groundtruth/*`` with ``groundtruth=True``); each
``Track`` is published again as a CDR ``geometry_msgs/msg/PoseStamped`` on the key that
zenoh-bridge-ros2dds maps to the ROS 2 topic ``/arena/robots/<name>/pose`` (``arena/robots/<name>/pose``,
below the bridge's namespace if it has one), and as a ``tf2_msgs/msg/TFMessage`` (``arena`` ->
``<name>``) on the key of ``/tf`` (``tf``). Header stamp: the track's ``stamp_us`` (sensor clock)
plus ``offset_ns``.

A sample that is not a valid message of the expected kind is counted (``bad``) and logged, and
the bridge keeps running; so does a publish that fails (``publish_failed``). Its key ``arena/robots/<name>/pose`` is one chunk below the tracks,
so no ``arena/robots/*`` subscriber (viewer, bridge, scorer) sees the CDR samples.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import zenoh

from arena.keys import ALL_GROUNDTRUTH, ALL_ROBOTS
from arena.messages import GroundTruthPose, MessageError, Track, decode
from arena.service import Service, wait_until_stopped
from ros2.cdr import Serializer
from ros2.convert import (TF_TOPIC, Pose, RosNameError, bridge_key, entity_name, groundtruth_topic, pose_topic,
                          ros_token, stamp_ns)


@dataclass
class BridgeResult:
    """What one run of :func:`run_bridge` did: messages in, CDR samples out, rejected samples."""

    tracks: int
    groundtruth: int
    published: int
    bad: int
    seconds: float


class Ros2Publisher:
    """Turns arena samples into CDR samples on the bridge's keys (no threads of its own; the
    Zenoh callback calls :meth:`on_sample`)."""

    def __init__(self, session: zenoh.Session, serializer: Serializer, svc: Service, *,
                 namespace: str = "/", offset_ns: int = 0, tf: bool = True) -> None:
        self.session, self.serializer, self.svc = session, serializer, svc
        self.namespace, self.offset_ns, self.tf = namespace, int(offset_ns), tf
        self._pubs: dict[str, zenoh.Publisher] = {}
        self._lock = threading.Lock()
        self.tf_key = bridge_key(TF_TOPIC, namespace)

    def _put(self, key: str, data: bytes) -> None:
        with self._lock:
            pub = self._pubs.get(key)
            if pub is None:
                pub = self._pubs[key] = self.session.declare_publisher(
                    key, congestion_control=zenoh.CongestionControl.DROP)
        pub.put(data)
        self.svc.count("published")

    def on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            msg = decode(sample.payload.to_bytes())
            if isinstance(msg, Track):
                name = entity_name(msg.robot, msg.track_id)
                pose = Pose(name, stamp_ns(msg.stamp_us, self.offset_ns), msg.x, msg.y,
                            float("nan") if msg.yaw is None else msg.yaw)
                pose_bytes = self.serializer.pose_cdr(pose)
                tf_bytes = self.serializer.tf_cdr([pose]) if (self.tf and msg.yaw is not None) else None
                self._put(bridge_key(pose_topic(name), self.namespace), pose_bytes)
                if tf_bytes is not None:
                    self._put(self.tf_key, tf_bytes)
                self.svc.count("tracks")
            elif isinstance(msg, GroundTruthPose) and msg.detector != "sim":
                name = ros_token(msg.robot)
                pose = Pose(name, stamp_ns(msg.stamp_us, self.offset_ns), msg.x, msg.y,
                            float("nan") if msg.yaw is None else msg.yaw)
                data = self.serializer.pose_cdr(pose)
                self._put(bridge_key(groundtruth_topic(name), self.namespace), data)
                self.svc.count("groundtruth")
            else:
                raise MessageError(f"a {msg.KIND} message, not a track or ground-truth pose")
        except (MessageError, RosNameError, ValueError) as exc:
            self.svc.count("bad")
            self.svc.error(f"{key}: sample not bridged to ROS 2: {exc}")
        except Exception as exc:  # noqa: BLE001 - zenoh.ZError from a put: count it, keep bridging
            self.svc.count("publish_failed")
            self.svc.error(f"{key}: cannot publish its ROS 2 sample: {exc}")

    def close(self) -> None:
        with self._lock:
            for pub in self._pubs.values():
                try:
                    pub.undeclare()
                except Exception:  # noqa: BLE001 - the session may be closing
                    pass
            self._pubs.clear()


def run_bridge(session: zenoh.Session, serializer: Serializer, stop: threading.Event, *,
               name: str = "ros2", namespace: str = "/", offset_ns: int = 0, groundtruth: bool = False,
               tf: bool = True, duration_s: float | None = None,
               on_ready: Callable[[], None] | None = None) -> BridgeResult:
    """Bridge arena tracks (and the webcam ground truth with ``groundtruth``) to CDR samples for
    zenoh-bridge-ros2dds until ``stop`` is set or ``duration_s`` passed. Publishes status and
    liveliness as ``ros2/<name>`` (counters ``tracks``, ``groundtruth``, ``published``, ``bad``)."""
    t0 = time.monotonic()
    with Service(session, "ros2", name) as svc:
        pub = Ros2Publisher(session, serializer, svc, namespace=namespace, offset_ns=offset_ns, tf=tf)
        keys = [ALL_ROBOTS] + ([ALL_GROUNDTRUTH] if groundtruth else [])
        subs = [session.declare_subscriber(k, pub.on_sample) for k in keys]
        try:
            if on_ready is not None:
                on_ready()
            wait_until_stopped(stop, duration_s)
        except KeyboardInterrupt:
            pass
        finally:
            for s in subs:
                s.undeclare()
            pub.close()
        return BridgeResult(int(svc.counter("tracks")), int(svc.counter("groundtruth")),
                            int(svc.counter("published")), int(svc.counter("bad")), time.monotonic() - t0)

"""ROS 2 messages of arena poses, serialized as CDR with the ``rosbags`` package (no ROS install).

``rosbags`` is optional (the ``ros2`` extra): :func:`load_typestore` imports it and raises
:class:`MissingRosbags`, whose text says what to install, when it is not there.

The typestore is ROS 2 Humble's: ``geometry_msgs/msg/PoseStamped`` and ``tf2_msgs/msg/TFMessage``
are the same in Humble, Iron, Jazzy and Kilted (same RIHS01 type hash), so the bytes are too.
The CDR bytes start with the 4-byte encapsulation header (``00 01 00 00``: little-endian CDR), as
a DDS sample, a rosbag2 message and a zenoh-bridge-ros2dds payload all do.
"""

from __future__ import annotations

from collections.abc import Sequence

from ros2.convert import FRAME_ID, POSE_TYPE, TF_TYPE, Pose, quaternion_from_yaw, split_stamp

#: the one line printed when rosbags is missing
INSTALL_HINT = "pip install 'arena-fleet[ros2]'   (or: pip install rosbags)"


class MissingRosbags(ImportError):
    """The optional ``rosbags`` package is not installed."""


def load_typestore():
    """The ROS 2 Humble typestore of ``rosbags``; raises :class:`MissingRosbags` without it."""
    try:
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise MissingRosbags(
            f"needs the Python package 'rosbags' (ROS 2 messages without a ROS install), which is not "
            f"installed: {INSTALL_HINT}") from None
    return get_typestore(Stores.ROS2_HUMBLE)


class Serializer:
    """Builds and CDR-serializes ``PoseStamped`` and ``TFMessage`` for :class:`~ros2.convert.Pose`."""

    def __init__(self, typestore=None) -> None:
        self.typestore = typestore if typestore is not None else load_typestore()
        t = self.typestore.types
        self._pose_stamped = t[POSE_TYPE]
        self._tf_message = t[TF_TYPE]
        self._transform_stamped = t["geometry_msgs/msg/TransformStamped"]
        self._transform = t["geometry_msgs/msg/Transform"]
        self._vector3 = t["geometry_msgs/msg/Vector3"]
        self._header = t["std_msgs/msg/Header"]
        self._time = t["builtin_interfaces/msg/Time"]
        self._pose = t["geometry_msgs/msg/Pose"]
        self._point = t["geometry_msgs/msg/Point"]
        self._quaternion = t["geometry_msgs/msg/Quaternion"]

    def _stamped_header(self, stamp_ns: int):
        sec, nanosec = split_stamp(stamp_ns)
        return self._header(stamp=self._time(sec=sec, nanosec=nanosec), frame_id=FRAME_ID)

    def pose_stamped(self, pose: Pose):
        """The ``geometry_msgs/msg/PoseStamped`` of ``pose`` (frame ``arena``, z = 0; orientation
        NaN when the yaw is unknown)."""
        qx, qy, qz, qw = quaternion_from_yaw(pose.yaw)
        return self._pose_stamped(
            header=self._stamped_header(pose.stamp_ns),
            pose=self._pose(position=self._point(x=float(pose.x), y=float(pose.y), z=0.0),
                            orientation=self._quaternion(x=qx, y=qy, z=qz, w=qw)))

    def tf_message(self, poses: Sequence[Pose]):
        """The ``tf2_msgs/msg/TFMessage`` with one transform ``arena`` -> ``<name>`` per pose."""
        transforms = []
        for p in poses:
            qx, qy, qz, qw = quaternion_from_yaw(p.yaw)
            transforms.append(self._transform_stamped(
                header=self._stamped_header(p.stamp_ns), child_frame_id=p.name,
                transform=self._transform(translation=self._vector3(x=float(p.x), y=float(p.y), z=0.0),
                                          rotation=self._quaternion(x=qx, y=qy, z=qz, w=qw))))
        return self._tf_message(transforms=transforms)

    def pose_cdr(self, pose: Pose) -> bytes:
        """CDR bytes of :meth:`pose_stamped`."""
        return bytes(self.typestore.serialize_cdr(self.pose_stamped(pose), POSE_TYPE))

    def tf_cdr(self, poses: Sequence[Pose]) -> bytes:
        """CDR bytes of :meth:`tf_message`."""
        return bytes(self.typestore.serialize_cdr(self.tf_message(poses), TF_TYPE))

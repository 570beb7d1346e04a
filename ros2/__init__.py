"""ROS 2 interoperability: ``arena export RUN --rosbag OUT`` and the live ``arena ros2`` bridge.

- :mod:`ros2.convert`: pure mapping of arena poses to ROS 2 names, frames, stamps, quaternions;
- :mod:`ros2.cdr`: the ROS 2 message types and their CDR serialization (the ``rosbags`` package,
  no ROS install needed);
- :mod:`ros2.bag`: reading a run folder and writing it as a rosbag2 (MCAP storage);
- :mod:`ros2.service`: the Zenoh side of ``arena ros2`` (tracks in, CDR ``PoseStamped`` and ``/tf``
  out on the keys zenoh-bridge-ros2dds maps to ROS 2 topics);
- :mod:`ros2.cli`: the two commands. See ``docs/ros2.md``.
"""

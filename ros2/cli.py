"""``arena export RUN --rosbag OUT`` and ``arena ros2`` (see ``docs/ros2.md``).

Both need the optional ``rosbags`` package (the ``ros2`` extra); it is imported when a command
runs, and without it the command prints one line naming what to install and exits 2.
"""

from __future__ import annotations

import os
import sys

from arena.clitools import formatter, session_or_exit
from arena.keys import InvalidKey, validate_name
from arena.session import add_zenoh_arguments


def register_export(sub) -> None:
    """Add ``arena export`` to the ``arena`` subparsers."""
    p = sub.add_parser(
        "export", help="export a run folder for other tools (a ROS 2 rosbag2)", formatter_class=formatter,
        description="Write a run folder of `arena demo` as a rosbag2 with MCAP storage that `ros2 bag play`\n"
                    "and Foxglove read, serialized with the rosbags package (no ROS install needed):\n"
                    "  /arena/robots/<name>/pose       geometry_msgs/msg/PoseStamped   tracks.csv\n"
                    "  /tf                             tf2_msgs/msg/TFMessage          arena -> <name>\n"
                    "  /arena/groundtruth/<name>/pose  geometry_msgs/msg/PoseStamped   groundtruth.csv (webcam)\n"
                    "  /arena/sim/truth/<name>/pose    geometry_msgs/msg/PoseStamped   truth.csv (simulator)\n"
                    "<name> is the robot's name, else track_<id> for a track not yet identified. Frame\n"
                    "`arena` (metres, z = 0). Stamps: the files' t_us (the sensor clock) unless --stamps wall.\n"
                    "Exit status: 0, or 2 for a folder that is not a run, an existing OUT, no track.",
        epilog="Examples:\n"
               "  arena export runs/demo-20261201-203658 --rosbag run_bag\n"
               "  arena export RUN --rosbag run_bag --stamps wall --force\n"
               "  ros2 bag info run_bag && ros2 bag play run_bag      # on a ROS 2 machine")
    p.add_argument("run", metavar="RUN", help="run folder (holds tracks.csv; truth.csv and groundtruth.csv when present)")
    p.add_argument("--rosbag", metavar="OUT", required=True, help="rosbag2 folder to write (must not exist)")
    p.add_argument("--force", action="store_true", help="replace OUT if it is an existing rosbag2")
    p.add_argument("--stamps", choices=("sensor", "wall"), default="sensor",
                   help="sensor: the files' t_us as stamps (default); wall: shifted to the host clock with "
                        "the offset seen in the run's arena.mcap (tracker publish time - sensor time)")
    p.set_defaults(func=run_export)


def register_ros2(sub) -> None:
    """Add ``arena ros2`` to the ``arena`` subparsers."""
    p = sub.add_parser(
        "ros2", help="publish the tracks for ROS 2 (through zenoh-bridge-ros2dds)", formatter_class=formatter,
        description="Subscribe to the tracks (arena/robots/*) and publish each as a CDR\n"
                    "geometry_msgs/msg/PoseStamped on the Zenoh key that zenoh-bridge-ros2dds maps to the ROS 2\n"
                    "topic /arena/robots/<name>/pose (key arena/robots/<name>/pose), and as tf2_msgs/msg/TFMessage\n"
                    "arena -> <name> on the key of /tf (tf). Run a zenoh-bridge-ros2dds connected to the same\n"
                    "router and ROS 2 nodes see the topics. Stops on Ctrl-C, SIGTERM or after --duration.",
        epilog="Examples:\n"
               "  arena ros2                                  # the lab's router on tcp/127.0.0.1:7447\n"
               "  arena ros2 --groundtruth                    # also /arena/groundtruth/<name>/pose\n"
               "  arena ros2 --namespace /lab                 # a bridge run with namespace /lab\n"
               "  zenoh-bridge-ros2dds -e tcp/127.0.0.1:7447  # then: ros2 topic echo /arena/robots/zumo1/pose")
    p.add_argument("--namespace", default="/",
                   help="the namespace zenoh-bridge-ros2dds is configured with (default /: none)")
    p.add_argument("--groundtruth", action="store_true",
                   help="also bridge the webcam ground truth (arena/groundtruth/*) to /arena/groundtruth/<name>/pose")
    p.add_argument("--no-tf", action="store_true", help="do not publish /tf")
    p.add_argument("--offset-ns", type=int, default=0,
                   help="added to every stamp (sensor clock µs x 1000); e.g. the offset to the host clock")
    p.add_argument("--duration", type=float, default=None, help="stop after this many seconds (default: until stopped)")
    p.add_argument("--name", default=None, help="service name in arena status (default ros2-<pid>)")
    add_zenoh_arguments(p)
    p.set_defaults(func=run_ros2)


def _serializer(command: str):
    """The CDR serializer, or None after printing the one-line install hint."""
    from ros2.cdr import MissingRosbags, Serializer

    try:
        return Serializer()
    except MissingRosbags as exc:
        print(f"arena {command}: {exc}", file=sys.stderr)
        return None


def run_export(args) -> int:
    """Run ``arena export``; returns the exit code."""
    from ros2.bag import ExportError, export_run
    from ros2.cdr import MissingRosbags

    serializer = _serializer("export")
    if serializer is None:
        return 2
    try:
        res = export_run(args.run, args.rosbag, serializer, force=args.force, stamps=args.stamps)
    except (ExportError, MissingRosbags) as exc:
        print(f"arena export: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"arena export: cannot write {args.rosbag}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    topics = sorted(res.messages)
    clock = "sensor clock" if res.stamps == "sensor" else f"host clock (sensor + {res.offset_ns / 1e9:.6f} s)"
    print(f"wrote {res.path}: {res.total} messages on {len(topics)} topics ({', '.join(topics)}), "
          f"{res.track_rows} track rows, stamps on the {clock}", flush=True)
    if res.unknown_yaw:
        print(f"  {res.unknown_yaw} track rows had no heading: their pose orientation is NaN and they have "
              "no transform in /tf", flush=True)
    if res.skipped_truth_rows:
        print(f"  {res.skipped_truth_rows} ground-truth rows without x/y (robot not seen) were left out", flush=True)
    return 0


def run_ros2(args) -> int:
    """Run ``arena ros2``; returns the exit code."""
    from arena.service import stop_on_signals
    from ros2.convert import RosNameError, bridge_key, ros_token
    from ros2.service import run_bridge

    try:
        name = validate_name(args.name or f"ros2-{os.getpid()}", "--name")
    except InvalidKey as exc:
        print(f"arena ros2: {exc}", file=sys.stderr)
        return 2
    ns = args.namespace.strip()
    try:
        ok = ns == "/" or (ns.startswith("/") and all(ros_token(t) == t for t in ns.strip("/").split("/")))
    except RosNameError:
        ok = False
    if not ok:
        print(f"arena ros2: --namespace {ns!r} is not a ROS 2 namespace: give it as the bridge's, e.g. /lab",
              file=sys.stderr)
        return 2
    if args.duration is not None and args.duration <= 0:
        print("arena ros2: --duration must be > 0 seconds", file=sys.stderr)
        return 2
    serializer = _serializer("ros2")
    if serializer is None:
        return 2
    stop = stop_on_signals()
    example = bridge_key("/arena/robots/NAME/pose", ns)
    with session_or_exit(args, "arena ros2", wait_s=None) as session:
        res = run_bridge(session, serializer, stop, name=name, namespace=ns, offset_ns=args.offset_ns,
                         groundtruth=args.groundtruth, tf=not args.no_tf, duration_s=args.duration,
                         on_ready=lambda: print(f"bridging arena/robots/* to ROS 2 CDR on {example}"
                                                f"{'' if args.no_tf else ' and ' + bridge_key('/tf', ns)}"
                                                " (Ctrl-C to stop)", flush=True))
    print(f"bridged {res.tracks} tracks and {res.groundtruth} ground-truth poses as {res.published} ROS 2 "
          f"samples in {res.seconds:.1f} s; rejected {res.bad}", flush=True)
    return 0

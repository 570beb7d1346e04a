"""``arena record`` and ``arena replay``."""

from __future__ import annotations

import importlib.util
import math
import os
import socket
import sys
import time

from arena.clitools import USAGE, formatter, session_or_exit
from arena.keys import EVERYTHING, InvalidKey, validate_name
from arena.session import add_zenoh_arguments, check_key_expressions

# Registered at every `arena` command's start: the MCAP library (~20 ms) and the service runtime
# are imported by the commands that use them. A machine without mcap still lists record/replay as
# unavailable with the pip command (arena.cli catches this ImportError), as when it was imported.
if importlib.util.find_spec("mcap") is None:
    raise ImportError("No module named 'mcap'", name="mcap")


def register_record(sub) -> None:
    """Add ``arena record`` to the ``arena`` subparsers."""
    p = sub.add_parser(
        "record", help="record arena messages into an MCAP file (Foxglove, ROS 2 tooling)",
        formatter_class=formatter,
        description="Subscribe to arena messages and write them into an MCAP file: one channel per key,\n"
                    "tracks/telemetry/ground truth/status as JSON with a JSON schema (Foxglove shows\n"
                    "them), event windows as their msgpack bytes (lossless). Also Foxglove's own schemas\n"
                    "(foxglove/... topics: robot poses, transforms, boxes with heading arrows, the arena\n"
                    "outline, the event image at --image-hz) for its 3D panel; `arena replay` skips them\n"
                    "(docs/foxglove.md). Log time = receive time, publish time = the sender's time when\n"
                    "the message has one. Stops at the end of --duration, on Ctrl-C or SIGTERM, and\n"
                    "always finishes the file. Commands to robots are Zenoh queries, not publications:\n"
                    "they are not recorded.\n"
                    "Exit status: 0, or 1 when samples were dropped (write queue full), 2 on errors.",
        epilog="Examples:\n"
               "  arena record run.mcap                                # everything, until Ctrl-C\n"
               "  arena record run.mcap --duration 30\n"
               "  arena record tracks.mcap --keys 'arena/robots/*' --keys 'arena/groundtruth/*'\n"
               "  arena record run.mcap --calibration cam0.calib.json  # event image placed in Foxglove's 3D view\n"
               "  arena replay run.mcap                                # publish it again\n"
               "Options not given as flags come from the lab config's [services.recorder] table (keys,\n"
               "queue), else the defaults.")
    p.add_argument("out", metavar="OUT.mcap", help="MCAP file to write (overwritten)")
    p.add_argument("--keys", action="append", default=None, metavar="KEYEXPR",
                   help=f"key expression to record, repeatable (default {EVERYTHING})")
    p.add_argument("--duration", type=float, default=None, help="stop after this many seconds (default: until stopped)")
    p.add_argument("--name", default=None, help="service name in arena status (default recorder-<pid>)")
    p.add_argument("--queue", type=int, default=None,
                   help="samples buffered before the file writer; beyond it samples are dropped and counted "
                        "(default 10000)")
    p.add_argument("--queue-mb", type=float, default=256.0,
                   help="megabytes of samples buffered before the file writer; beyond it samples are dropped "
                        "and counted (default 256)")
    _add_foxglove_arguments(p)
    p.add_argument("--no-foxglove", action="store_true",
                   help="do not write the Foxglove views (foxglove/... topics), only the arena messages")
    add_zenoh_arguments(p)
    p.set_defaults(func=run_record)


def register_replay(sub) -> None:
    """Add ``arena replay`` to the ``arena`` subparsers."""
    p = sub.add_parser(
        "replay", help="publish a recorded run again on Zenoh", formatter_class=formatter,
        description="Publish the messages of a run recorded by `arena record` (an .mcap file, or a run\n"
                    "folder of `arena demo` holding one) on their original keys with byte-identical\n"
                    "payloads, in order, at the recorded pace or faster. Viewers, scorers and trackers\n"
                    "cannot tell a replay from the live lab.",
        epilog="Examples:\n"
               "  arena replay runs/2026-11-23T08-30-00            # a demo run folder\n"
               "  arena replay run.mcap --speed 4                  # four times faster\n"
               "  arena replay run.mcap --speed 0                  # as fast as possible\n"
               "  arena replay run.mcap --keys 'arena/events/*' --loop   # feed a tracker forever")
    p.add_argument("run", metavar="RUN_DIR_or_FILE.mcap", help="recorded run: an .mcap file or a folder with one")
    p.add_argument("--speed", type=float, default=1.0,
                   help="playback rate: 1 real time (default), 2 twice as fast, 0 as fast as possible")
    p.add_argument("--keys", action="append", default=None, metavar="KEYEXPR",
                   help="only replay keys matching this expression, repeatable (default: all)")
    p.add_argument("--loop", action="store_true", help="start again at the end, until Ctrl-C")
    p.add_argument("--start-delay", type=float, default=1.0,
                   help="seconds to wait after connecting, so subscribers are known before the first "
                        "message (default 1.0)")
    p.add_argument("--name", default=None, help="service name in arena status (default replay-<pid>)")
    add_zenoh_arguments(p)
    p.set_defaults(func=run_replay)


def _name(value: str | None, command: str, prefix: str) -> str | None:
    """The service name (``--name`` or ``<prefix>-<pid>``); None after printing why it is invalid."""
    try:
        return validate_name(value or f"{prefix}-{os.getpid()}", "--name")
    except InvalidKey as exc:
        print(f"arena {command}: {exc}", file=sys.stderr)
        return None


def run_record(args) -> int:
    """Run ``arena record``; returns the exit code."""
    from arena.config import ConfigError, apply_service_options
    from arena.service import stop_on_signals
    from arena.session import load_lab_from_args
    from recorder.service import record

    name = _name(args.name, "record", "recorder")
    if name is None:
        return 2
    try:
        lab = load_lab_from_args(args)
    except ConfigError as exc:
        print(f"arena record: {exc}", file=sys.stderr)
        return 2
    apply_service_options(args, lab, "recorder")  # flags win, then [services.recorder], then the defaults
    if args.duration is not None and not 0 < args.duration < math.inf:
        print("arena record: --duration must be a number of seconds > 0", file=sys.stderr)
        return 2
    if args.queue < 1:
        print("arena record: --queue must be at least 1", file=sys.stderr)
        return 2
    if not 1 <= args.queue_mb <= 65536:
        print("arena record: --queue-mb must be 1 to 65536 (MB)", file=sys.stderr)
        return 2
    try:   # before the file is opened (it is overwritten) and before waiting for a router
        keys = check_key_expressions(args.keys or [EVERYTHING])
    except InvalidKey as exc:
        print(f"arena record: {exc}", file=sys.stderr)
        return 2
    out = os.path.abspath(args.out)
    if not os.path.isdir(os.path.dirname(out)):
        print(f"arena record: folder {os.path.dirname(out)} does not exist", file=sys.stderr)
        return 2
    if os.path.isdir(out) or not os.access(os.path.dirname(out), os.W_OK) or (
            os.path.exists(out) and not os.access(out, os.W_OK)):
        print(f"arena record: cannot write {out}: "
              f"{'a folder' if os.path.isdir(out) else 'permission denied'}", file=sys.stderr)
        return 2
    foxglove = None
    if not args.no_foxglove:
        foxglove = _foxglove_converter(args, lab, "record")
        if foxglove is None:
            return 2
    stop = stop_on_signals()
    meta = {"host": socket.gethostname(), "keys": ",".join(keys), "started_ns": str(time.time_ns()),
            "command": " ".join(sys.argv)}
    try:
        # waits for its router: only wrong settings (exit 2) end it here
        with session_or_exit(args, "arena record", lab=lab, wait_s=None) as session:
            res = record(session, out, keys, stop, duration_s=args.duration, name=name, queue_size=args.queue,
                         queue_bytes=int(args.queue_mb * 1e6), metadata=meta, foxglove=foxglove,
                         on_ready=lambda: print(f"recording {', '.join(keys)} to {out} (Ctrl-C to stop)",
                                                flush=True))
    except OSError as exc:
        print(f"arena record: cannot write {out}: {exc}", file=sys.stderr)
        return 2
    except Exception as exc:  # zenoh.ZError for an invalid key expression
        print(f"arena record: {exc}", file=sys.stderr)
        return 2
    views = f" (+{res.derived} Foxglove messages)" if foxglove is not None else ""
    no_view = (f"; no Foxglove view of {res.views_dropped} samples (views behind or stopping) and of "
               f"{res.views_skipped} windows (implausible size)"
               if foxglove is not None and (res.views_dropped or res.views_skipped) else "")
    print(f"recorded {res.messages} messages{views} ({res.bytes / 1e6:.1f} MB of payload) in {res.seconds:.1f} s "
          f"to {out}; dropped {res.dropped}{no_view}", flush=True)
    return 0 if res.dropped == 0 else 1


def run_replay(args) -> int:
    """Run ``arena replay``; returns the exit code."""
    from arena.service import Service, stop_on_signals
    from recorder.mcapio import RunFileError, find_run_file
    from recorder.service import replay, wait_stop

    name = _name(args.name, "replay", "replay")
    if name is None:
        return 2
    if args.speed < 0:
        print("arena replay: --speed must be >= 0 (0 means as fast as possible)", file=sys.stderr)
        return 2
    try:
        path = find_run_file(args.run)
        keys = check_key_expressions(args.keys) if args.keys else None
    except (RunFileError, InvalidKey) as exc:
        print(f"arena replay: {exc}", file=sys.stderr)
        return 2
    stop = stop_on_signals()
    try:
        # exit 2 as before even when no router answers (the policy's code for that would be 1)
        with session_or_exit(args, "arena replay", code=USAGE) as session, \
                Service(session, "recorder", name) as svc:
            if wait_stop(stop, max(0.0, args.start_delay)):
                return 0
            pace = "as fast as possible" if args.speed == 0 else f"at {args.speed:g}x"
            print(f"replaying {path} {pace}{' in a loop' if args.loop else ''}", flush=True)
            res = replay(session, path, stop, speed=args.speed, keys=keys, loop=args.loop,
                         on_message=lambda m: svc.count("messages"))
    except KeyboardInterrupt:
        return 0
    except RunFileError as exc:
        print(f"arena replay: {exc}", file=sys.stderr)
        return 2
    print(f"replayed {res.messages} messages in {res.seconds:.1f} s "
          f"({res.passes} pass{'es' if res.passes != 1 else ''}, max lag {res.max_lag_s * 1e3:.0f} ms)", flush=True)
    return 0


# ----------------------------------------------------------------------------- Foxglove views


def _add_foxglove_arguments(p) -> None:
    p.add_argument("--calibration", metavar="JSON", default=None,
                   help="camera calibration (pixel <-> arena m, as `arena view` takes) to place the event "
                        "image in Foxglove's 3D view (topic foxglove/events/<camera>/points); overrides the "
                        "lab config's cameras' calibrations. Without one the image is shown in its own frame only")
    p.add_argument("--image-hz", type=float, default=4.0,
                   help="event images a second (sensor time) for Foxglove (default 4)")
    p.add_argument("--accumulate-ms", type=float, default=100.0,
                   help="sensor time one event image shows (default 100 ms)")


def _read_json(path: str, what: str) -> dict:
    import json
    from pathlib import Path

    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"{what}: cannot read calibration {path}: {exc}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{what}: {path} is not a calibration JSON object")
    return data


def _foxglove_converter(args, lab, command: str):
    """The :class:`~recorder.foxglove_views.FoxgloveConverter` for ``args`` and the lab config (arena
    size, robot sizes and colours, camera calibrations); None after printing why it cannot be made."""
    try:
        from recorder.foxglove_views import (FoxgloveConverter, RobotShape, calibration_sizes,
                                             pixel_to_arena_homography)
    except ImportError as exc:
        print(f"arena {command}: the Foxglove views need {exc.name or 'a missing package'} "
              f"(pip install foxglove-schemas-protobuf){'; or pass --no-foxglove' if command == 'record' else ''}",
              file=sys.stderr)
        return None
    if not args.image_hz > 0 or not args.accumulate_ms > 0:
        print(f"arena {command}: --image-hz and --accumulate-ms must be > 0", file=sys.stderr)
        return None
    try:
        homographies, calibrations = {}, {}
        if args.calibration:
            calibrations["*"] = _read_json(args.calibration, "--calibration")
            homographies["*"] = pixel_to_arena_homography(calibrations["*"])
        elif lab is not None:
            for cam in lab.cameras:
                calib = cam.calibration
                if calib is None and cam.calibration_file:
                    calib = _read_json(cam.calibration_file, f"camera {cam.name}")
                if calib is not None:
                    homographies[cam.name] = pixel_to_arena_homography(calib)
                    calibrations[cam.name] = calib
    except ValueError as exc:
        print(f"arena {command}: {exc}", file=sys.stderr)
        return None
    robots = {r.name: RobotShape(r.length_m, r.width_m, color_rgb=tuple(r.color_rgb))
              for r in (lab.robots if lab is not None else [])}
    return FoxgloveConverter(arena_size_m=lab.arena.size_m if lab is not None else (1.83, 1.83), robots=robots,
                             image_period_us=max(1, int(1e6 / args.image_hz)),
                             accumulate_us=max(1, int(args.accumulate_ms * 1000)), pixel_to_arena=homographies,
                             sensor_sizes=calibration_sizes(calibrations))


def register_foxglove(sub) -> None:
    """Add ``arena foxglove`` to the ``arena`` subparsers."""
    p = sub.add_parser(
        "foxglove", help="serve the arena live to Foxglove (WebSocket): robots in 3D over the event image",
        formatter_class=formatter,
        description="Subscribe to the tracks and event windows and serve them over Foxglove's WebSocket\n"
                    "protocol (the official foxglove-sdk), as the same foxglove/... topics `arena record`\n"
                    "writes: robot poses, transforms, boxes with heading arrows and labels, the arena\n"
                    "outline, the accumulated event image. In Foxglove: Open connection -> Foxglove\n"
                    "WebSocket -> ws://HOST:PORT. Works the same for a live lab and for `arena replay`.\n"
                    "Needs the 'foxglove' extra (pip install foxglove-sdk). Loopback only by default.",
        epilog="Examples:\n"
               "  arena foxglove                                      # then connect to ws://127.0.0.1:8765\n"
               "  arena foxglove --calibration runs/demo-x/cam0.calib.json\n"
               "  arena foxglove --port 0                             # any free port (printed)\n"
               "  arena foxglove --host 0.0.0.0                       # reachable from other hosts (no auth!)")
    p.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=8765, help="TCP port (default 8765, Foxglove's; 0 = any free port)")
    _add_foxglove_arguments(p)
    p.add_argument("--name", default=None, help="service name in arena status (default foxglove-<pid>)")
    add_zenoh_arguments(p)
    p.set_defaults(func=run_foxglove)


def run_foxglove(args) -> int:
    """Run ``arena foxglove``; returns the exit code."""
    from arena.config import ConfigError
    from arena.service import stop_on_signals
    from arena.session import load_lab_from_args

    name = _name(args.name, "foxglove", "foxglove")
    if name is None:
        return 2
    if not 0 <= args.port <= 65535:
        print(f"arena foxglove: --port {args.port} is not a TCP port", file=sys.stderr)
        return 2
    try:
        lab = load_lab_from_args(args)
    except ConfigError as exc:
        print(f"arena foxglove: {exc}", file=sys.stderr)
        return 2
    converter = _foxglove_converter(args, lab, "foxglove")
    if converter is None:
        return 2
    try:
        from recorder.foxglove_live import FoxgloveServerError, LiveServer, serve
    except ImportError as exc:
        print(f"arena foxglove: {exc}", file=sys.stderr)
        return 2
    stop = stop_on_signals()
    try:
        live = LiveServer(args.host, args.port, name=f"arena {name}")  # before Zenoh: a busy port fails at once
    except FoxgloveServerError as exc:
        print(f"arena foxglove: {exc}", file=sys.stderr)
        return 2
    try:
        with live, session_or_exit(args, "arena foxglove", lab=lab, wait_s=None) as session:
            res = serve(session, converter, live, stop, name=name,
                        on_ready=lambda url: print(f"foxglove server on {url} (Ctrl-C to stop)", flush=True))
    except KeyboardInterrupt:
        return 0
    print(f"served {res.messages} Foxglove messages from {res.samples} samples", flush=True)
    return 0

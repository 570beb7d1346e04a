"""``arena record`` and ``arena replay``."""

from __future__ import annotations

import argparse
import os
import socket
import sys
import time

from arena.keys import EVERYTHING, InvalidKey, validate_name
from arena.service import stop_on_signals
from arena.session import SessionError, add_zenoh_arguments, open_session
from recorder.mcapio import RunFileError, find_run_file


def _formatter(prog: str) -> argparse.HelpFormatter:
    return argparse.RawDescriptionHelpFormatter(prog, max_help_position=32)


def register_record(sub) -> None:
    """Add ``arena record`` to the ``arena`` subparsers."""
    p = sub.add_parser(
        "record", help="record arena messages into an MCAP file (Foxglove, ROS 2 tooling)",
        formatter_class=_formatter,
        description="Subscribe to arena messages and write them into an MCAP file: one channel per key,\n"
                    "tracks/telemetry/ground truth/status as JSON with a JSON schema (Foxglove shows\n"
                    "them), event windows as their msgpack bytes (lossless). Log time = receive time,\n"
                    "publish time = the sender's time when the message has one. Stops at the end of\n"
                    "--duration, on Ctrl-C or SIGTERM, and always finishes the file. Commands to robots\n"
                    "are Zenoh queries, not publications: they are not recorded.\n"
                    "Exit status: 0, or 1 when samples were dropped (write queue full), 2 on errors.",
        epilog="Examples:\n"
               "  arena record run.mcap                                # everything, until Ctrl-C\n"
               "  arena record run.mcap --duration 30\n"
               "  arena record tracks.mcap --keys 'arena/robots/*' --keys 'arena/groundtruth/*'\n"
               "  arena replay run.mcap                                # publish it again")
    p.add_argument("out", metavar="OUT.mcap", help="MCAP file to write (overwritten)")
    p.add_argument("--keys", action="append", default=None, metavar="KEYEXPR",
                   help=f"key expression to record, repeatable (default {EVERYTHING})")
    p.add_argument("--duration", type=float, default=None, help="stop after this many seconds (default: until stopped)")
    p.add_argument("--name", default=None, help="service name in arena status (default recorder-<pid>)")
    p.add_argument("--queue", type=int, default=10_000,
                   help="samples buffered before the file writer; beyond it samples are dropped and counted")
    add_zenoh_arguments(p)
    p.set_defaults(func=run_record)


def register_replay(sub) -> None:
    """Add ``arena replay`` to the ``arena`` subparsers."""
    p = sub.add_parser(
        "replay", help="publish a recorded run again on Zenoh", formatter_class=_formatter,
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
    from recorder.service import record

    name = _name(args.name, "record", "recorder")
    if name is None:
        return 2
    if args.duration is not None and args.duration <= 0:
        print("arena record: --duration must be > 0 seconds", file=sys.stderr)
        return 2
    if args.queue < 1:
        print("arena record: --queue must be at least 1", file=sys.stderr)
        return 2
    out = os.path.abspath(args.out)
    if not os.path.isdir(os.path.dirname(out)):
        print(f"arena record: folder {os.path.dirname(out)} does not exist", file=sys.stderr)
        return 2
    keys = args.keys or [EVERYTHING]
    stop = stop_on_signals()
    meta = {"host": socket.gethostname(), "keys": ",".join(keys), "started_ns": str(time.time_ns()),
            "command": " ".join(sys.argv)}
    try:
        with open_session(args, wait_s=None) as session:
            res = record(session, out, keys, stop, duration_s=args.duration, name=name, queue_size=args.queue,
                         metadata=meta,
                         on_ready=lambda: print(f"recording {', '.join(keys)} to {out} (Ctrl-C to stop)",
                                                flush=True))
    except SessionError as exc:
        print(f"arena record: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"arena record: cannot write {out}: {exc}", file=sys.stderr)
        return 2
    except Exception as exc:  # zenoh.ZError for an invalid key expression
        print(f"arena record: {exc}", file=sys.stderr)
        return 2
    print(f"recorded {res.messages} messages ({res.bytes / 1e6:.1f} MB of payload) in {res.seconds:.1f} s "
          f"to {out}; dropped {res.dropped}", flush=True)
    return 0 if res.dropped == 0 else 1


def run_replay(args) -> int:
    """Run ``arena replay``; returns the exit code."""
    from arena.service import Service
    from recorder.service import replay, wait_stop

    name = _name(args.name, "replay", "replay")
    if name is None:
        return 2
    if args.speed < 0:
        print("arena replay: --speed must be >= 0 (0 means as fast as possible)", file=sys.stderr)
        return 2
    try:
        path = find_run_file(args.run)
    except RunFileError as exc:
        print(f"arena replay: {exc}", file=sys.stderr)
        return 2
    stop = stop_on_signals()
    try:
        with open_session(args) as session, Service(session, "recorder", name) as svc:
            if wait_stop(stop, max(0.0, args.start_delay)):
                return 0
            pace = "as fast as possible" if args.speed == 0 else f"at {args.speed:g}x"
            print(f"replaying {path} {pace}{' in a loop' if args.loop else ''}", flush=True)
            res = replay(session, path, stop, speed=args.speed, keys=args.keys, loop=args.loop,
                         on_message=lambda m: svc.count("messages"))
    except KeyboardInterrupt:
        return 0
    except SessionError as exc:
        print(f"arena replay: {exc}", file=sys.stderr)
        return 2
    except RunFileError as exc:
        print(f"arena replay: {exc}", file=sys.stderr)
        return 2
    print(f"replayed {res.messages} messages in {res.seconds:.1f} s "
          f"({res.passes} pass{'es' if res.passes != 1 else ''}, max lag {res.max_lag_s * 1e3:.0f} ms)", flush=True)
    return 0

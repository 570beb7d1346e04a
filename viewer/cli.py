"""``arena view``: the live web viewer."""

from __future__ import annotations

import json
import os
import sys
import threading
from pathlib import Path

from arena.clitools import formatter, session_or_exit
from arena.config import ConfigError
from arena.keys import InvalidKey, validate_name
from arena.session import add_zenoh_arguments, load_lab_from_args


def register(sub) -> None:
    """Add ``arena view`` to the ``arena`` subparsers."""
    p = sub.add_parser(
        "view", help="live web view: events, tracks, ground truth, telemetry, services",
        formatter_class=formatter,
        description="Serve one web page showing the arena live from Zenoh: the accumulated event image\n"
                    "(ON black, OFF blue, no event white), each track's box, id, heading arrow and trail\n"
                    "drawn on it and on an arena plot in metres, the ground truth, telemetry sparklines\n"
                    "(wheel speeds, gyro z, battery) and every service's status and liveliness.\n"
                    "Works the same for a live lab and for `arena replay`. Loopback only by default.",
        epilog="Examples:\n"
               "  arena view                                  # then open http://127.0.0.1:8080/\n"
               "  arena view --lab lab.toml --camera cam0     # draw tracks with the lab's calibration\n"
               "  arena view --calibration runs/demo-x/cam0.calib.json\n"
               "  arena view --port 0                         # any free port (printed)\n"
               "  arena view --host 0.0.0.0                   # reachable from other hosts (no auth!)\n"
               "  arena view --host 0.0.0.0 --allow-host viewer.lab   # also answer to that DNS name\n"
               "Options not given as flags come from the lab config's [services.viewer] table (host, port,\n"
               "accumulate_ms, rate), else the defaults. Malformed keys and messages are counted (status\n"
               "gauges bad_keys, bad) and ignored.")
    p.add_argument("--host", default=None, help="address to serve on (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=None, help="TCP port (default 8080; 0 = any free port)")
    p.add_argument("--camera", default=None,
                   help="camera whose events are shown (default: the lab's first camera, else the first seen)")
    p.add_argument("--calibration", metavar="JSON", default=None,
                   help="camera calibration file (pixel <-> arena m) used to draw tracks that carry no pixel "
                        "position; overrides the lab config's")
    p.add_argument("--accumulate-ms", type=float, default=None,
                   help="event image shows this much sensor time (default 100 ms)")
    p.add_argument("--rate", type=float, default=None, help="updates per second sent to the page (default 10)")
    p.add_argument("--name", default=None, help="service name in arena status (default view-<pid>)")
    p.add_argument("--allow-host", metavar="NAME", action="append", default=[],
                   help="also answer requests whose Host header is NAME (a DNS name of this host or a proxy's; "
                        "repeatable). Others than the address served on, localhost and 127.0.0.1 get 421")
    p.add_argument("--max-connections", type=int, default=64,
                   help="connections served at once, pages and event streams (default 64); when all are open, a\n"
                        "new one replaces the one waiting longest for its request, and gets 503 only if all are busy;\n"
                        "event streams take at most all but an eighth of them (at least one kept back), a stream\n"
                        "beyond that gets 503")
    p.add_argument("--idle-timeout", type=float, default=30.0, metavar="S",
                   help="close a connection that sends or reads nothing for S seconds (default 30)")
    p.add_argument("--header-timeout", type=float, default=10.0, metavar="S",
                   help="close a connection that has not sent a whole request (line and headers) S seconds\n"
                        "after it was accepted or answered, however slowly it trickles (default 10)")
    add_zenoh_arguments(p)
    p.set_defaults(func=run)


def _read_calibration(path: str, what: str) -> dict:
    from viewer.state import ViewerConfigError

    try:
        calib = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise ViewerConfigError(f"{what}: cannot read calibration {path}: {exc}") from None
    if not isinstance(calib, dict):
        raise ViewerConfigError(f"{what}: {path} is not a calibration JSON object")
    return calib


def _lab_view(args, lab):
    """(camera, homography arena->px, arena size m, robot size m) from --calibration and the lab config."""
    from viewer.state import arena_to_pixel_homography

    calib = _read_calibration(args.calibration, "--calibration") if args.calibration else None
    if lab is None:
        H = arena_to_pixel_homography(calib) if calib else None
        return args.camera, H, (1.83, 1.83), (0.10, 0.10)
    cam = lab.camera(args.camera) if lab.cameras else None
    if cam is not None and calib is None:
        calib = cam.calibration
        if calib is None and cam.calibration_file:
            calib = _read_calibration(cam.calibration_file, f"camera {cam.name}")
    H = arena_to_pixel_homography(calib) if calib else None
    size = (max(r.length_m for r in lab.robots), max(r.width_m for r in lab.robots)) if lab.robots else (0.1, 0.1)
    return (cam.name if cam else args.camera), H, lab.arena.size_m, size


def run(args) -> int:
    """Run ``arena view``; returns the exit code."""
    from viewer.server import ViewerServer
    from viewer.service import subscribe
    from arena.config import apply_service_options
    from arena.service import Service, stop_on_signals
    from viewer.state import ViewerConfigError, ViewerState

    try:
        name = validate_name(args.name or f"view-{os.getpid()}", "--name")
        if args.camera:
            validate_name(args.camera, "--camera")
        lab = load_lab_from_args(args)
        apply_service_options(args, lab, "viewer")  # flags win, then [services.viewer], then the defaults
        camera, H, arena_size, robot_size = _lab_view(args, lab)
    except (InvalidKey, ConfigError, ViewerConfigError) as exc:
        print(f"arena view: {exc}", file=sys.stderr)
        return 2
    if not 0 <= args.port <= 65535:
        print(f"arena view: --port {args.port} is not a TCP port", file=sys.stderr)
        return 2
    if args.accumulate_ms <= 0 or args.rate <= 0:
        print("arena view: --accumulate-ms and --rate must be > 0", file=sys.stderr)
        return 2
    if args.max_connections < 1 or not args.idle_timeout > 0 or not args.header_timeout > 0:
        print("arena view: --max-connections must be >= 1 and --idle-timeout > 0 and --header-timeout > 0",
              file=sys.stderr)
        return 2
    state = ViewerState(camera=camera, accumulate_us=int(args.accumulate_ms * 1000), H_arena_to_px=H,
                        arena_size_m=arena_size, robot_size_m=robot_size)
    try:
        server = ViewerServer(state, args.host, args.port, period_s=1.0 / args.rate,
                              allow_hosts=[h for item in args.allow_host for h in item.split(",")],
                              max_connections=args.max_connections, idle_timeout_s=args.idle_timeout,
                              header_timeout_s=args.header_timeout)
    except OSError as exc:
        print(f"arena view: cannot serve on {args.host}:{args.port}: {exc.strerror or exc}"
              " (is another viewer running? try --port 0)", file=sys.stderr)
        return 2
    stop = stop_on_signals()
    thread = threading.Thread(target=server.serve_forever, name="http", daemon=True)
    try:
        # waits for its router: only wrong settings (exit 2) end it here
        with session_or_exit(args, "arena view", lab=lab, wait_s=None) as session, \
                Service(session, "viewer", name) as svc:
            subs = subscribe(session, state, camera)
            svc.on_tick(lambda s: (s.gauge("clients", server.clients), s.gauge("tracks", state.track_count()),
                                   s.gauge("bad", state.counts["bad"]), s.gauge("bad_keys", state.counts["bad_keys"]),
                                   s.gauge("refused_host", server.refused["host"]),
                                   s.gauge("refused_busy", server.refused["busy"]),
                                   s.gauge("refused_slow", server.refused["slow"]),
                                   s.gauge("refused_streams", server.refused["streams"]),
                                   s.gauge("evicted_connections", server.refused["evicted"]),
                                   s.gauge("evicted_entries", state.counts["evicted"]),
                                   s.gauge("windows_subsampled", state.counts["subsampled"])))
            thread.start()
            print(f"viewer on {server.url} (Ctrl-C to stop)", flush=True)
            try:
                # short ticks: SIGTERM may land on another thread and its Python handler runs only
                # when the main thread wakes (an untimed wait could sleep through it)
                while not stop.wait(0.2):
                    pass
            except KeyboardInterrupt:
                pass
            finally:
                server.shutdown()
                for s in subs:
                    s.undeclare()
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()
    return 0

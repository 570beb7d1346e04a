"""``arena bridge``: run the robot bridge, or send it commands from any host.

Subcommands: ``run`` (the service), ``mission``, ``stop``, ``estop``, ``clear``, ``led``
(clients of the ``arena/cmd/<robot>/<verb>`` queryables). ``python -m robot_bridge`` is
the same command.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import time

from arena.clitools import exit_on_session_error, formatter, seconds
from arena.session import add_zenoh_arguments, open_session, resolve_settings

log = logging.getLogger("robot_bridge")

EXAMPLES = """\
Examples:
  # the service, one robot on Bluetooth and one simulated (arena sim prints the ports)
  arena bridge run --robot zumo1=/dev/rfcomm0 --robot zumo2=socket://127.0.0.1:5001
  arena bridge run --lab deploy/lab.toml          # robots and serial_url from the lab config

  # commands, from any host reaching the same Zenoh
  arena bridge mission zumo1 circle --radius 0.3 --power 50
  arena bridge mission all square --side 0.6 --power 100 --control closed --start-in 2
  arena bridge mission zumo2 waypoints --points 0.5,0.5 1.2,0.5 1.2,1.2
  arena bridge stop all
  arena bridge estop zumo1 && arena bridge clear zumo1
  arena bridge led zumo1 255 0 0

Exit codes: 0 done (or stopped by Ctrl-C/SIGTERM), 1 runtime failure (a refused command, no
bridge answered, a robot that could not be reached with --require-all), 2 usage or input error.
"""


def register(subparsers) -> None:
    """Add ``bridge`` and its subcommands to the ``arena`` parser."""
    p = subparsers.add_parser(
        "bridge", help="drive the robots: missions, telemetry, logs, safety", formatter_class=formatter,
        description="The robot bridge: serial links (Bluetooth SPP, USB, simulator socket://) to the\n"
                    "robots, missions (circle, square, ...) in paper or closed-loop mode, telemetry on\n"
                    "arena/telemetry/<robot>, CSV logs, and commands on arena/cmd/<robot>/<verb>.",
        epilog=EXAMPLES)
    sub = p.add_subparsers(dest="bridge_command", metavar="SUBCOMMAND")
    p.set_defaults(func=lambda args: (p.print_help(), 0)[1])

    r = sub.add_parser("run", help="run the bridge service", formatter_class=formatter, epilog=EXAMPLES,
                       description="Connect to every robot and serve missions and commands until Ctrl-C.\n"
                                   "Motors are stopped on exit, Ctrl-C, SIGTERM, link or router loss (client\n"
                                   "mode, the default). A robot whose link cannot be opened is an error in\n"
                                   "arena status and is retried with backoff (fatal with --require-all).")
    r.add_argument("--robot", metavar="NAME=URL", action="append", default=[],
                   help="robot and pyserial URL, repeatable (/dev/rfcomm0, /dev/ttyACM0, socket://HOST:PORT)")
    r.add_argument("--name", default=None, help="service name in arena status (default: bridge-<first robot>)")
    r.add_argument("--log-dir", default=None, help="mission logs directory (default [services.bridge] "
                                                   "telemetry_dir or ./bridge_logs)")
    r.add_argument("--geofence-margin", type=float, default=None, metavar="M",
                   help="stop a robot whose track comes closer than M metres to the arena edge (default 0.03)")
    r.add_argument("--low-battery-mv", type=int, default=None, help="stop missions below this battery voltage")
    r.add_argument("--track-delay", type=float, default=None, metavar="S",
                   help="extra age of track poses (the tracker's own lag), s (default 0)")
    r.add_argument("--baud", type=int, default=None, help="serial baud rate (default 57600, the firmware's)")
    r.add_argument("--link-timeout", type=float, default=None, metavar="S",
                   help="a robot's link is down after S seconds without a frame from it (its 50-100 Hz "
                        "telemetry is the heartbeat); default [services.bridge] link_timeout_s or 2.0, "
                        "which rides out Bluetooth SPP stalls. The robot's own 300 ms motor watchdog "
                        "stops it whenever motor commands stop, whatever this is")
    r.add_argument("--duration", type=float, default=None, help="stop after this many seconds (tests, demos)")
    r.add_argument("--require-all", action="store_true",
                   help="exit (code 1) if a robot's link cannot be opened at start-up, instead of retrying")
    add_zenoh_arguments(r)
    r.set_defaults(func=run_service)

    m = sub.add_parser("mission", help="start a mission on a robot (or all)", formatter_class=formatter,
                       epilog=EXAMPLES,
                       description="Patterns: circle (--radius, --direction, --laps), square (--side, --direction,\n"
                                   "--laps), figure8 (--radius, --laps), back_and_forth (--length, --laps),\n"
                                   "waypoints (--points x,y ...). Stop-and-go with --pause-s/--pause-every.\n"
                                   "Speed: --power 50|100 (percent) or --speed M/S. Lengths in metres.")
    m.add_argument("robot", help="robot name, or 'all'")
    m.add_argument("pattern", choices=("circle", "square", "figure8", "back_and_forth", "waypoints"))
    m.add_argument("--radius", type=float, help="circle/figure8 radius, m")
    m.add_argument("--side", type=float, help="square side, m")
    m.add_argument("--length", type=float, help="back_and_forth length, m")
    m.add_argument("--laps", type=int, help="number of laps (default 1)")
    m.add_argument("--direction", choices=("ccw", "cw"), help="turning direction (default ccw)")
    m.add_argument("--points", nargs="+", metavar="X,Y", help="waypoints in arena metres")
    m.add_argument("--pause-s", type=float, help="stop-and-go: pause this long ...")
    m.add_argument("--pause-every", type=float, metavar="M", help="... after every M metres (default: each phase)")
    g = m.add_mutually_exclusive_group()
    g.add_argument("--power", type=float, help="motor power in percent (the paper: 50 or 100)")
    g.add_argument("--speed", type=float, help="tread speed, m/s")
    m.add_argument("--start-pose", metavar="X,Y,YAW_DEG", default=None,
                   help="where the robot stands (arena m, degrees): lets --control closed start before "
                        "the camera has seen the robot move")
    m.add_argument("--control", choices=("paper", "closed"), default="paper",
                   help="paper: encoder PID only; closed: follow the robot's own track (default paper)")
    m.add_argument("--start-in", type=seconds(0.0, 600.0, lo_open=False), default=None, metavar="S",
                   help="start in S seconds, up to 600 (several robots start together)")
    _client_args(m)
    m.set_defaults(func=run_mission)

    for verb, text in (("stop", "stop the mission and the motors"), ("estop", "emergency stop, latched until clear"),
                       ("clear", "clear a latched e-stop")):
        c = sub.add_parser(verb, help=text, formatter_class=formatter, epilog=EXAMPLES, description=text + ".")
        c.add_argument("robot", help="robot name, or 'all'")
        _client_args(c)
        c.set_defaults(func=run_simple, verb=verb)
    c = sub.add_parser("led", help="set a robot's LED colour", formatter_class=formatter, epilog=EXAMPLES)
    c.add_argument("robot", help="robot name, or 'all'")
    c.add_argument("rgb", nargs=3, type=int, metavar="RGB", help="red, green and blue, 0-255 each")
    _client_args(c)
    c.set_defaults(func=run_simple, verb="led")


def _client_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--timeout", type=seconds(0.0, 600.0), default=3.0,
                   help="seconds to wait for the bridge's reply, up to 600 (default 3)")
    p.add_argument("--operator", default=None, help="who sends the command (recorded in the mission log)")
    add_zenoh_arguments(p)


# --------------------------------------------------------------------------------------------
class UsageError(ValueError):
    """Bad flags or config: ``arena bridge run`` prints it and exits with code 2."""


#: how long --require-all waits for every robot's first attempt to open its link, s
REQUIRE_WAIT_S = 10.0


def _robots_from(args, lab) -> list:
    from .core import RobotSetup
    from .odometry import WheelGeometry
    from .service import parse_robot_flag

    robots = []
    flags = {}
    for value in args.robot:
        try:
            name, url = parse_robot_flag(value)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
        flags[name] = url
    if lab is not None:
        for rc in lab.robots:
            url = flags.pop(rc.name, rc.serial_url)
            if url is None:
                continue
            robots.append(RobotSetup(rc.name, url, WheelGeometry(rc.sprocket_diameter_m, rc.track_width_m,
                                                                  rc.counts_per_rev)))
    robots += [RobotSetup(name, url) for name, url in flags.items()]
    return robots


def run_service(args) -> int:
    from arena.config import ConfigError
    from arena.service import Service, stop_on_signals, wait_until_stopped
    from arena.session import load_lab_from_args

    from .core import BridgeOptions
    from .service import Bridge

    try:
        lab = load_lab_from_args(args)
        robots = _robots_from(args, lab)
        # the same settings the session is opened with (flags > ARENA_ZENOH_* > lab > defaults)
        with exit_on_session_error("arena bridge run", code=2):
            settings = resolve_settings(args, lab)
    except (ConfigError, UsageError) as exc:
        print(f"arena bridge run: {exc}", file=sys.stderr)
        return 2
    if not robots:
        print("arena bridge run: no robots: give --robot NAME=URL or a --lab config whose robots have serial_url",
              file=sys.stderr)
        return 2
    opts = dict(lab.service("bridge")) if lab is not None else {}
    o = BridgeOptions()
    if lab is not None:
        o.arena_size_m = tuple(lab.arena.size_m)
    o.log_dir = args.log_dir or opts.get("telemetry_dir", o.log_dir)
    o.geofence_margin_m = args.geofence_margin if args.geofence_margin is not None else float(
        opts.get("geofence_margin_m", o.geofence_margin_m))
    o.low_battery_mv = args.low_battery_mv or int(opts.get("low_battery_mv", o.low_battery_mv))
    o.baudrate = args.baud or int(opts.get("baudrate", o.baudrate))
    o.track_delay_s = args.track_delay if args.track_delay is not None else float(
        opts.get("track_delay_s", o.track_delay_s))
    try:
        o.link_timeout_s = float(args.link_timeout if args.link_timeout is not None
                                 else opts.get("link_timeout_s", o.link_timeout_s))
    except (TypeError, ValueError):
        o.link_timeout_s = float("nan")
    if not 0.05 <= o.link_timeout_s <= 60:
        print(f"arena bridge run: --link-timeout (or [services.bridge] link_timeout_s) must be 0.05-60 s, "
              f"got {args.link_timeout if args.link_timeout is not None else opts.get('link_timeout_s')!r}",
              file=sys.stderr)
        return 2
    name = args.name or f"bridge-{robots[0].name}"
    # the router watchdog: in client mode every message goes through the router, so losing it
    # means no e-stop can reach the robots any more
    watch = settings.mode == "client"
    stop = stop_on_signals()
    try:
        with exit_on_session_error("arena bridge run", code=2), open_session(settings, wait_s=None) as session:
            svc = Service(session, "bridge", name)
            try:
                bridge = Bridge(session, robots, o, service=svc, watch_router=watch)
            except ValueError as exc:   # a robot name used twice or reserved
                print(f"arena bridge run: {exc}", file=sys.stderr)
                return 2
            bridge.start()
            try:
                if getattr(args, "require_all", False):
                    # before the liveliness token: a launcher waiting for it never sees this bridge ready
                    failed = _unreachable(bridge, REQUIRE_WAIT_S)
                    if failed:
                        for line in failed:
                            print(f"arena bridge run: {line} (--require-all)", file=sys.stderr)
                        return 1
                with svc:
                    try:
                        print(f"arena bridge {name}: {', '.join(f'{r.name}={r.url}' for r in robots)}; "
                              f"logs in {o.log_dir}; commands on arena/cmd/<robot>/<verb>; "
                              f"router watchdog {'on' if watch else 'off'} ({settings.mode} mode)", flush=True)
                        # in short ticks: an untimed wait can sleep through SIGTERM
                        wait_until_stopped(stop, getattr(args, "duration", None))
                    finally:
                        bridge.close()   # every robot stopped before the last status and the token go
            finally:
                bridge.close()
    except KeyboardInterrupt:
        pass
    return 0


def _unreachable(bridge, timeout_s: float) -> list[str]:
    """One line per robot whose link did not come up on its first attempt (within ``timeout_s``)."""
    deadline = time.monotonic() + timeout_s
    out = []
    for name, h in bridge.handles.items():
        done = h.link.wait_attempted(max(0.0, deadline - time.monotonic()))
        if h.link.connected:
            continue
        reason = h.link.last_error if done else f"not connected after {timeout_s:.0f} s ({h.link.last_error})"
        out.append(f"robot {name}: link to {h.link.url} cannot be opened: {reason}")
    return out


def _send(args, verb: str, payload: bytes) -> int:
    import zenoh

    from arena.config import ConfigError
    from arena.keys import InvalidKey, cmd_key
    from arena.messages import CommandReply, MessageError
    from arena.session import load_lab_from_args

    from .service import fmt_reply

    try:
        key = cmd_key(args.robot, verb)
    except InvalidKey as exc:
        print(f"arena bridge {verb}: {exc}", file=sys.stderr)
        return 2
    try:   # input errors (exit 2) apart from an unreachable Zenoh (exit 1)
        with exit_on_session_error(f"arena bridge {verb}", code=2):
            settings = resolve_settings(args, load_lab_from_args(args))
            settings.to_zenoh_config()
    except ConfigError as exc:
        print(f"arena bridge {verb}: {exc}", file=sys.stderr)
        return 2
    ok = True
    n = 0
    with exit_on_session_error(f"arena bridge {verb}", code=1):   # no router: a runtime failure
        with open_session(settings) as session:
            # no consolidation: 'all' gets one reply per robot on the same key
            for r in session.get(key, payload=payload, timeout=args.timeout,
                                 consolidation=zenoh.ConsolidationMode.NONE):
                if r.ok is None:
                    print(f"arena bridge {verb}: error reply: {r.err.payload.to_string()}", file=sys.stderr)
                    ok = False
                    continue
                try:
                    reply = CommandReply.decode(r.ok.payload.to_bytes())
                except MessageError as exc:
                    print(f"arena bridge {verb}: unreadable reply from {r.ok.key_expr}: {exc}", file=sys.stderr)
                    ok = False
                    continue
                n += 1
                ok = ok and reply.ok
                print(fmt_reply(reply), flush=True)
    if n == 0:
        print(f"arena bridge {verb}: no bridge answered for robot {args.robot!r} within {args.timeout} s "
              "(unknown robot, or no bridge running on this Zenoh)", file=sys.stderr)
        return 1
    return 0 if ok else 1


def run_mission(args) -> int:
    from arena.messages import MissionCommand

    params: dict = {}
    for flag, key in (("radius", "radius_m"), ("side", "side_m"), ("length", "length_m"), ("laps", "laps"),
                      ("direction", "direction"), ("pause_s", "pause_s"), ("pause_every", "pause_every_m")):
        v = getattr(args, flag)
        if v is not None:
            params[key] = v
    if args.points:
        pts = []
        for p in args.points:
            try:
                x, y = (float(c) for c in p.split(","))
            except ValueError:
                print(f"arena bridge mission: --points expects X,Y in metres, got {p!r}", file=sys.stderr)
                return 2
            if not (math.isfinite(x) and math.isfinite(y)):
                print(f"arena bridge mission: --points {p!r} is not finite", file=sys.stderr)
                return 2
            pts.append([x, y])
        params["points"] = pts
    power = None
    if args.power is not None:
        if not 0 < args.power <= 100:
            print(f"arena bridge mission: --power is a percentage in (0, 100], got {args.power}", file=sys.stderr)
            return 2
        power = args.power / 100.0
    if args.speed is not None and not 0 < args.speed <= 2:
        print(f"arena bridge mission: --speed is m/s in (0, 2], got {args.speed}", file=sys.stderr)
        return 2
    if args.start_pose is not None:
        try:
            x, y, yaw_deg = (float(c) for c in args.start_pose.split(","))
        except ValueError:
            print(f"arena bridge mission: --start-pose expects X,Y,YAW_DEG, got {args.start_pose!r}", file=sys.stderr)
            return 2
        if not all(math.isfinite(v) for v in (x, y, yaw_deg)):
            print(f"arena bridge mission: --start-pose {args.start_pose!r} is not finite", file=sys.stderr)
            return 2
        params["start_pose"] = [x, y, math.radians(yaw_deg)]
    start_ns = time.time_ns() + int(args.start_in * 1e9) if args.start_in else None
    cmd = MissionCommand(mission=args.pattern, params=params, power=power, speed_mps=args.speed,
                         control=args.control, start_ns=start_ns, operator=args.operator)
    return _send(args, "mission", cmd.encode())


def run_simple(args) -> int:
    from arena.messages import Command

    params = {"rgb": list(args.rgb)} if args.verb == "led" else {}
    return _send(args, args.verb, Command(verb=args.verb, params=params, operator=args.operator).encode())


def main(argv: list[str] | None = None) -> int:
    """``python -m robot_bridge``: the same as ``arena bridge``."""
    parser = argparse.ArgumentParser(prog="python -m robot_bridge", formatter_class=formatter)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    register(sub)
    args = parser.parse_args(["bridge", *(argv if argv is not None else sys.argv[1:])])
    logging.basicConfig(level=logging.INFO,
                        format="%(asctime)s %(name)s %(levelname)s: %(message)s")
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130

"""``arena sim``: the simulated arena with its device interfaces.

Runs the world in real time (or as fast as possible with ``--fast``) and serves the
ceiling event camera as an EVT 3.0 TCP stream, the webcam as MJPEG over HTTP and each
robot's firmware protocol on its own TCP port (pyserial ``socket://`` URL). Prints where
each device listens. Robots, sensor size and ports come from flags or a lab config.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import signal
import sys
import time
from contextlib import ExitStack
from pathlib import Path
from urllib.parse import urlparse

from arena.clitools import RUNTIME, fail, formatter, number, seconds
from arena.session import add_zenoh_arguments

log = logging.getLogger("simulator")

# The parser must not import numba/OpenCV (slow): `--help` and flag errors stay instant.
# Kept equal to simulator.autopilot.PATTERNS and simulator.world.LIGHTING_LEVELS (tested).
PATTERN_CHOICES = ("circle", "square", "stopgo", "cross", "figure8", "still")
LIGHTING_CHOICES = ("full", "dimmed", "dark")
#: Ids of the ArUco dictionary printed on the shells (DICT_4X4_50): 0..49.
MARKER_IDS = 50


EXAMPLES = """\
Examples:
  arena sim --robots 4                         # 4 robots, camera on tcp://127.0.0.1:9000
  arena sim --robots 4 --markers               # the same with ArUco markers on the shells
  arena sim --robots 2 --autopilot circle --power 0.5 --duration 20 \\
            --record-raw run.raw --truth-csv run.truth.csv
  arena sim --robots 8 --camera-port 0 --webcam-port 0 --robot-base-port 0   # free ports
  arena sim --lab deploy/lab.toml              # robots, sensor size and ports from the lab config
  arena sim --robots 3 --autopilot cross --fast --duration 10 --record-raw cross.raw --no-webcam
  arena sim --robots 4 --autopilot square --publish-truth -e tcp/127.0.0.1:7447   # truth on Zenoh
Then point the services at the printed addresses, e.g.
  arena edge tcp://127.0.0.1:9000 --camera cam0                                  # camera
  arena groundtruth --video http://127.0.0.1:8090/stream.mjpg --calibration http://127.0.0.1:8090/calibration.json \\
      --clock stream --detector hsv --robot black0=black --robot yellow1=yellow ...   # by colour
      (with --markers: --detector aruco --marker 0=black0 --marker 1=yellow1 ...)
  arena bridge run --robot black0=socket://127.0.0.1:9100                        # robot 0
(or cv2.VideoCapture("http://127.0.0.1:8090/stream.mjpg"), serial.serial_for_url("socket://127.0.0.1:9100"))"""

#: Blocks of simulated time handed to the camera per loop, s.
BLOCK_S = 0.010
#: Highest light flicker the simulator resolves, Hz: half its internal rate (DvsParams.step_us
#: = 1000 µs, 1 kHz); mains lighting flickers at 100 or 120 Hz.
FLICKER_MAX_HZ = 500.0
#: Longest --duration, s (24 h; 0 runs until Ctrl-C).
DURATION_MAX_S = 86_400.0
#: Seeds are unsigned 32-bit integers.
SEED_MAX = 2**32 - 1


PORT = number(0, 65535, note=" (a TCP port; 0 = a free one)", integer=True)


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``sim`` subcommand to an ``arena`` subparsers object."""
    p = subparsers.add_parser(
        "sim", help="simulated arena: event camera, webcam and robots on loopback",
        formatter_class=formatter,
        description=__doc__, epilog=EXAMPLES)
    add_arguments(p)
    p.set_defaults(func=run)
    return p


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The flags of ``arena sim`` (shared with ``python -m simulator``)."""
    p.add_argument("--robots", type=number(0, MARKER_IDS, "robots", integer=True), default=None, metavar="N",
                   help="number of robots (default 4, or the lab config's robots)")
    p.add_argument("--autopilot", choices=("none",) + PATTERN_CHOICES, default="none",
                   help="built-in driver (default none: robots obey their firmware link)")
    p.add_argument("--layout", choices=("circle", "square", "mixed"), default=None,
                   help="without autopilot: start poses for missions driven by the bridge: circle "
                        "(bottom of a centred circle, heading +x), square (bottom-left corner of a "
                        "centred square), mixed (circles and squares alternately); default circle")
    p.add_argument("--power", type=number(0.05, 1.0, "of full power"), default=1.0,
                   help="autopilot motor power, fraction of full (the paper: 0.5 or 1.0)")
    p.add_argument("--lighting", choices=LIGHTING_CHOICES, default="full", help="ceiling lighting")
    p.add_argument("--flicker", type=number(0, FLICKER_MAX_HZ, "Hz", note=" (0 = off)"), default=0.0,
                   metavar="HZ", help=f"light flicker, 0-{FLICKER_MAX_HZ:g} Hz (100 or 120 Hz: mains; default 0, "
                                      "off); simulates the full frame, not real time")
    p.add_argument("--seed", type=number(0, SEED_MAX, integer=True), default=0, help="seed of everything (default 0)")
    p.add_argument("--markers", action="store_true",
                   help="print ArUco markers (DICT_4X4_50, ids 0..N-1) on the shells (default: plain "
                        "coloured shells with a dark front window, as the lab's robots; a lab config's "
                        "marker_id values are kept either way)")
    p.add_argument("--width", type=number(16, 4096, "px", integer=True), default=None,
                   help="event sensor width, 16-4096 px (default 640)")
    p.add_argument("--height", type=number(16, 4096, "px", integer=True), default=None,
                   help="event sensor height, 16-4096 px (default 480)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default loopback)")
    p.add_argument("--camera-port", type=PORT, default=None,
                   help="EVT 3.0 TCP port (default 9000 or the lab's camera source; 0 = free port)")
    p.add_argument("--webcam-port", type=PORT, default=8090, help="MJPEG HTTP port (0 = free port)")
    p.add_argument("--no-webcam", action="store_true", help="do not serve the webcam")
    p.add_argument("--robot-base-port", type=PORT, default=9100,
                   help="robot i listens on BASE+i (0 = free ports; lab socket:// URLs win)")
    p.add_argument("--no-robots", action="store_true", help="do not serve the robot firmware links")
    p.add_argument("--telemetry-hz", type=number(1, 1000, "Hz"), default=50.0,
                   help="robot telemetry rate, Hz (default 50, as the reference firmware over Bluetooth)")
    p.add_argument("--duration", type=seconds(0.0, DURATION_MAX_S, lo_open=False), default=0.0, metavar="S",
                   help=f"stop after S simulated seconds, 0-{DURATION_MAX_S:g} (default 0: until Ctrl-C)")
    p.add_argument("--fast", action="store_true",
                   help="as fast as possible instead of real time (camera clients are not dropped)")
    p.add_argument("--record-raw", metavar="FILE", help="also write the events to a Prophesee RAW file")
    p.add_argument("--truth-csv", metavar="FILE", help="write truth poses (t_us,robot,x_m,...) to a CSV")
    p.add_argument("--calibration-out", metavar="FILE",
                   help="write the event camera calibration JSON (pixel <-> arena points)")
    p.add_argument("--publish-truth", action="store_true",
                   help="publish exact poses on arena/sim/truth/<robot> over Zenoh (for live scoring "
                        "only; also status and liveliness as role sim); --truth-csv keeps every step")
    p.add_argument("--publish-truth-hz", type=number(1, 100, "Hz"), default=25.0, metavar="HZ",
                   help="poses per second and robot published with --publish-truth, 1-100 (default 25: "
                        "a live error table's need, at a quarter of the CPU of every 10 ms block)")
    # --lab (robots, camera size, ports, Zenoh endpoints) and the Zenoh flags
    add_zenoh_arguments(p)


def _robots_from_args(args) -> tuple[list, dict]:
    """Robot specs and device options from the flags and the optional lab config."""
    from simulator.autopilot import make_plans
    from simulator.scenarios import Scenario
    from simulator.world import RobotSpec
    opts = {"width": args.width or 640, "height": args.height or 480,
            "camera_port": 9000 if args.camera_port is None else args.camera_port,
            "robot_ports": {}}
    pattern = args.autopilot if args.autopilot != "none" else "still"
    if args.lab:
        from arena.config import ConfigError, load_lab_config
        try:
            lab = load_lab_config(args.lab)
        except (ConfigError, OSError) as e:
            raise fail(f"arena sim: cannot read lab config {args.lab}: {e}")
        if lab.cameras:
            cam = lab.cameras[0]
            opts["width"], opts["height"] = args.width or cam.width, args.height or cam.height
            src = urlparse(cam.source or "")
            if args.camera_port is None and src.scheme == "tcp" and src.port:
                opts["camera_port"] = src.port
        for r in lab.robots:   # the camera prints DICT_4X4_50 markers: ids 0..49 (the lab check says so too)
            if r.marker_id is not None and not 0 <= r.marker_id < MARKER_IDS:
                raise fail(f"arena sim: lab config {args.lab}: robot {r.name!r} has marker_id {r.marker_id}; "
                           f"the ArUco dictionary DICT_4X4_50 has ids 0..{MARKER_IDS - 1}")
        n = args.robots if args.robots is not None else len(lab.robots)
        plans = make_plans(pattern, n, lab.arena.size_m[0])
        specs = []
        for i in range(n):
            if i < len(lab.robots):
                r = lab.robots[i]
                specs.append(RobotSpec(r.name, tuple(r.color_rgb), r.marker_id, r.length_m, r.width_m,
                                       r.track_width_m, r.sprocket_diameter_m, r.counts_per_rev,
                                       start=plans[i].start_pose()))
                u = urlparse(r.serial_url or "")
                if u.scheme == "socket" and u.port:
                    opts["robot_ports"][i] = u.port
            else:
                specs.append(Scenario(n_robots=n, pattern=pattern, markers=args.markers).robot_specs()[i])
        if args.markers:   # robots the lab gave no marker get the lowest free ids
            free = (i for i in range(50) if i not in {s.marker_id for s in specs})
            specs = [s if s.marker_id is not None else dataclasses.replace(s, marker_id=next(free, None))
                     for s in specs]
        return specs, opts
    n = 4 if args.robots is None else args.robots
    return Scenario(n_robots=n, pattern=pattern, seed=args.seed, markers=args.markers).robot_specs(), opts


def layout_poses(layout: str, n: int, arena_m: float) -> list[tuple[float, float, float]]:
    """Start poses (x m, y m, yaw rad) of ``n`` robots for missions started from where they stand:
    each robot gets a cell; a circle starts at its bottom heading +x (counter-clockwise around the
    cell centre), a square at its bottom-left corner heading +x."""
    from simulator.autopilot import make_plans

    circles, squares = make_plans("circle", n, arena_m), make_plans("square", n, arena_m)
    pick = {"circle": lambda i: circles[i], "square": lambda i: squares[i],
            "mixed": lambda i: circles[i] if i % 2 == 0 else squares[i]}[layout]
    return [pick(i).start_pose() for i in range(n)]


def _check_args(args) -> None:
    """Checks across flags and of the output paths (each number's range is its parser type's)."""
    for flag in ("calibration_out", "truth_csv", "record_raw"):   # checked before anything starts
        path = getattr(args, flag, None)
        if path:
            p = Path(path)
            if p.is_dir():
                raise fail(f"arena sim: --{flag.replace('_', '-')} {path} is a folder: give a file name")
            if not p.parent.is_dir():
                raise fail(f"arena sim: --{flag.replace('_', '-')} {path}: the folder {p.parent} does not exist")


def run(args) -> int:
    """Run the simulated arena until --duration or Ctrl-C / SIGTERM. Returns the exit code."""
    _check_args(args)
    from simulator.autopilot import Autopilot, make_plans
    from simulator.camera import CeilingCamera
    from simulator.dvs import DvsParams
    from simulator.evt3 import CameraServer, stream_header
    from arena.formats.tables import TruthCsvWriter
    from simulator.recording import RawWriter
    from simulator.simulation import Simulation, warm_up
    from simulator.world import World

    specs, opts = _robots_from_args(args)
    if not args.no_robots and args.robot_base_port and args.robot_base_port + len(specs) - 1 > 65535:
        raise fail(f"arena sim: --robot-base-port {args.robot_base_port} + {len(specs)} robots goes beyond TCP "
                   f"port 65535; give at most {65536 - len(specs)} (or 0: free ports)")
    if args.autopilot == "none" and args.layout:
        specs = [dataclasses.replace(spec, start=pose)
                 for spec, pose in zip(specs, layout_poses(args.layout, len(specs), 1.83))]
    world = World(specs, lighting=args.lighting, seed=args.seed)
    camera = CeilingCamera(opts["width"], opts["height"], seed=args.seed)
    pilot = None
    if args.autopilot != "none":
        pilot = Autopilot(world, make_plans(args.autopilot, len(specs), world.arena_m,
                                            args.duration or 1e9), args.power)
    dvs = DvsParams(flicker_hz=args.flicker)
    warm_up(world, camera, dvs)   # compile before serving: no stall once the robots' links are up
    sim = Simulation(world, camera, dvs, pilot, seed=args.seed + 1)
    stop = {"flag": False}

    def _terminate(signum, frame):
        stop["flag"] = True
    old = signal.signal(signal.SIGTERM, _terminate)
    try:
        with ExitStack() as stack:
            try:
                cam = stack.enter_context(CameraServer(args.host, opts["camera_port"],
                                                       drop_when_slow=not args.fast,
                                                       header=stream_header(camera.width, camera.height)))
            except OSError as e:
                raise fail(f"arena sim: cannot listen on camera port {opts['camera_port']}: {e}", RUNTIME)
            print(f"camera   {cam.url}   EVT 3.0, {camera.width}x{camera.height}", flush=True)
            if not args.no_webcam:
                _start_webcam(stack, world, args)
            if not args.no_robots:
                _start_robots(stack, world, args, opts)
            if args.calibration_out:
                Path(args.calibration_out).write_text(json.dumps(camera.calibration(), indent=1))
                print(f"calibration {args.calibration_out}", flush=True)
            raw = stack.enter_context(RawWriter(args.record_raw, camera.width, camera.height)) \
                if args.record_raw else None
            truth = stack.enter_context(TruthCsvWriter(args.truth_csv, [s.name for s in specs])) \
                if args.truth_csv else None
            truth_pub = _start_truth_publisher(stack, args, specs, camera) if args.publish_truth else None
            print(f"running  {len(specs)} robots, autopilot {args.autopilot}, lighting "
                  f"{args.lighting}, {'as fast as possible' if args.fast else 'real time'}"
                  f"{'' if not args.duration else f', {args.duration:g} s'} (Ctrl-C stops)", flush=True)
            _loop(sim, cam, raw, truth, args, stop, truth_pub)
    except KeyboardInterrupt:
        pass
    finally:
        signal.signal(signal.SIGTERM, old)
    print("stopped", flush=True)
    return 0


def _start_webcam(stack: ExitStack, world, args) -> None:
    try:
        from simulator.webcam import WebcamServer
    except ImportError as e:       # pragma: no cover - the module ships with the package
        print(f"webcam   unavailable ({e})", flush=True)
        return
    try:
        web = stack.enter_context(WebcamServer(world, host=args.host, port=args.webcam_port))
    except OSError as e:
        raise fail(f"arena sim: cannot listen on webcam port {args.webcam_port}: {e}", RUNTIME)
    print(f"webcam   {web.url}", flush=True)


def _start_robots(stack: ExitStack, world, args, opts) -> None:
    from simulator.robot_emulator import RobotEmulatorServer
    for i, spec in enumerate(world.robots):
        port = opts["robot_ports"].get(i, args.robot_base_port + i if args.robot_base_port else 0)
        try:
            emu = RobotEmulatorServer(world, i, host=args.host, port=port, seed=args.seed + 100 + i,
                                      telemetry_hz=args.telemetry_hz,
                                      clock=lambda: world.t)   # the robots' clocks run with the physics
            stack.enter_context(emu)
        except OSError as e:
            raise fail(f"arena sim: cannot listen on robot port {port} for {spec.name}: {e}", RUNTIME)
        print(f"robot    {spec.name:10s} {emu.url}", flush=True)


class _TruthPublisher:
    """Publishes the latest exact pose of every robot as a GroundTruthPose (detector "sim",
    sensor-clock stamp, arena frame) on ``arena/sim/truth/<robot>``, plus status counters."""

    def __init__(self, session, svc, specs, camera, hz: float = 25.0):
        from arena.keys import sim_truth_key
        self.svc = svc
        self.period_us = int(round(1e6 / hz))
        self._next_us: int | None = None
        self.camera = camera
        self.names = [s.name for s in specs]
        self.pubs = [session.declare_publisher(sim_truth_key(n)) for n in self.names]

    def publish(self, truth, n_events: int) -> None:
        import numpy as np

        from arena.messages import GroundTruthPose
        self.svc.count("events_out", n_events)
        if len(truth) == 0:
            return
        last = truth[-len(self.names):]
        t_us = int(last["t_us"][-1])
        if self._next_us is not None and t_us < self._next_us:
            return
        self._next_us = t_us + self.period_us if self._next_us is None or t_us - self._next_us > self.period_us \
            else self._next_us + self.period_us
        uv = self.camera.to_pixels(np.column_stack([last["x_m"], last["y_m"]]))
        for r, (u, v) in zip(last, uv):
            msg = GroundTruthPose(robot=self.names[r["robot"]], stamp_us=int(r["t_us"]),
                                  x=float(r["x_m"]), y=float(r["y_m"]), yaw=float(r["yaw_rad"]),
                                  u_px=float(u), v_px=float(v), detector="sim")
            self.pubs[r["robot"]].put(msg.encode())
        self.svc.count("truth_out", len(last))


def _start_truth_publisher(stack: ExitStack, args, specs, camera) -> _TruthPublisher:
    from arena.service import Service
    from arena.clitools import exit_on_session_error
    from arena.session import open_session
    with exit_on_session_error("arena sim: cannot open the Zenoh session for --publish-truth"):
        session = stack.enter_context(open_session(args, wait_s=None))
    svc = stack.enter_context(Service(session, "sim", "sim"))
    svc.set_state("running")
    print("truth    arena/sim/truth/<robot> (Zenoh)", flush=True)
    return _TruthPublisher(session, svc, specs, camera, hz=args.publish_truth_hz)


def _loop(sim, cam, raw, truth, args, stop, truth_pub=None) -> None:
    """Advance ``sim`` in BLOCK_S blocks, hand events to the camera and recorders, pace to
    the wall clock unless --fast."""
    from simulator.evt3 import canonical_order

    steps = max(1, int(round(BLOCK_S * 1e6 / sim.step_us)))
    total = math.inf if not args.duration else int(round(args.duration * 1e6 / sim.step_us))
    done = 0
    t0 = time.monotonic()
    last_report, n_events, behind_warned, max_lag, max_lag_t = t0, 0, 0.0, 0.0, 0.0
    while done < total and not stop["flag"]:
        k = int(min(steps, total - done))
        ev, _, tr = sim.run(k)
        done += k
        # the order EVT 3.0 is written in, sorted once for the camera's clients and the recording
        wire = canonical_order(ev) if raw is not None or cam.n_clients else ev
        cam.publish(wire, until_us=sim.t_us, ordered=True)
        if raw is not None:
            raw.write(wire, until_us=sim.t_us, ordered=True)
        if truth is not None:
            truth.write(tr)
        if truth_pub is not None:
            truth_pub.publish(tr, len(ev))
        n_events += len(ev)
        now = time.monotonic()
        sim_s = done * sim.step_us * 1e-6
        if not args.fast:
            lag = (t0 + sim_s) - now
            if -lag > max_lag:
                max_lag, max_lag_t = -lag, sim_s
            if lag > 0:
                time.sleep(lag)
            elif -lag > 0.5 and now - behind_warned > 10:
                behind_warned = now
                log.warning("simulation is %.1f s behind real time (too many robots for this CPU?)", -lag)
        if now - last_report >= 10:
            print(f"t={sim_s:7.1f} s  {n_events / (now - last_report):9.0f} ev/s  real-time factor "
                  f"{sim_s / (now - t0):.2f}  max lag {max_lag:.2f} s (t={max_lag_t:.1f} s)  camera clients {cam.n_clients}",
                  flush=True)
            last_report, n_events = now, 0
    if not args.fast and done:
        sim_s = done * sim.step_us * 1e-6
        print(f"real time: factor {sim_s / max(time.monotonic() - t0, 1e-9):.2f} over {sim_s:.1f} s simulated, "
              f"worst lag {max_lag:.2f} s (t={max_lag_t:.1f} s)", flush=True)


def main(argv: list[str] | None = None) -> int:
    """``python -m simulator``: the same as ``arena sim``."""
    p = argparse.ArgumentParser(prog="python -m simulator", description=__doc__, epilog=EXAMPLES,
                                formatter_class=formatter)
    add_arguments(p)
    p.add_argument("-v", "--verbose", action="store_true", help="log more")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    return run(args)


if __name__ == "__main__":   # pragma: no cover
    sys.exit(main())

"""``arena demo``: the whole lab in one command, on the built-in simulated arena.

It runs the real system, not a shortcut: the same processes, Zenoh keys and code paths a lab runs.
As separate processes: a router, the simulator (event camera over TCP, webcam over MJPEG, robots on
``socket://`` serial URLs), ``arena edge`` on the simulated camera, ``arena track``, ``arena bridge``
driving the missions on the emulated robots, ``arena groundtruth`` on the simulated webcam, a live
scorer and the MCAP recorder (and ``arena view`` with ``--view``).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import subprocess
import sys
import time
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

from arena.clitools import formatter
from demo.supervisor import ProcSpec, Supervisor, python_cmd

log = logging.getLogger("arena.demo")

MISSIONS = ("circle", "square", "mixed")
LIGHTING = ("full", "dimmed", "dark")
#: niceness added to the observers (recorder, ground truth, viewer). The simulator stands in for
#: the physical world, which never waits; the edge, tracker and bridge are the system under test.
#: On 2 cores the nine processes need about all of both, so when they compete (service start-up,
#: mission start) the observers, which queue what they receive, are the ones that wait.
OBSERVER_NICE = 10
#: Longest --duration of the demo's missions, s (24 h).
DURATION_MAX_S = 86_400.0
#: Seeds are unsigned 32-bit integers (as ``arena sim --seed``).
SEED_MAX = 2**32 - 1


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "demo", help="the whole lab in one command, on the built-in simulated arena",
        formatter_class=formatter, description=__doc__,
        epilog="Examples:\n"
               "  arena demo                                   # 4 robots, circles and squares, 30 s\n"
               "  arena demo --robots 2 --mission circle --power 0.5 --duration 20\n"
               "  arena demo --lighting dimmed --view         # and open http://127.0.0.1:8080\n"
               "  arena demo --duration 10 --out /tmp/runs --quiet\n"
               "  arena demo --markers                         # ArUco markers on the shells, webcam truth from them\n"
               "  arena demo --prepare                         # once after installing: compile, then exit\n"
               "Afterwards, to watch the recorded run again (the replay is its own router):\n"
               "  arena replay RUN_DIR --mode router --listen tcp/127.0.0.1:7447 --start-delay 3 \\\n"
               "      & arena view --calibration RUN_DIR/cam0.calib.json\n"
               "Exit code 0 when the run was ok; 1 when it was not (the results' first lines,\n"
               "summary.json's \"problems\" and report.md say why); 2 for bad options; 130 when interrupted.")
    p.add_argument("--robots", type=int, default=4, help="number of robots, 1-16 (default 4)")
    p.add_argument("--mission", choices=MISSIONS, default="mixed",
                   help="circle, square, or mixed: circles and squares alternately (default)")
    p.add_argument("--power", type=float, default=1.0, help="motor power fraction: 1.0 (~0.46 m/s) or 0.5 (default 1.0)")
    p.add_argument("--lighting", choices=LIGHTING, default="full", help="ceiling lighting (default full)")
    p.add_argument("--duration", type=float, default=30.0, help="seconds of missions (default 30)")
    p.add_argument("--seed", type=int, default=0, help="simulator seed (default 0)")
    p.add_argument("--markers", action="store_true",
                   help="print ArUco markers on the simulated shells and take the webcam ground truth from "
                        "them (default: plain coloured shells, as the lab's robots, and the webcam ground "
                        "truth by colour: HSV blobs, heading from the dark front window strip, else motion)")
    p.add_argument("--tracker", choices=("fleet", "idtrack"), default="fleet", help="tracker (default fleet)")
    p.add_argument("--control", choices=("closed", "paper"), default="closed",
                   help="closed: robots follow their path using their own tracks (default); paper: the "
                        "paper's encoder-only PID, whose shapes drift by ~10 cm a lap")
    p.add_argument("--out", default="runs", help="parent folder of the run folder (default ./runs)")
    p.add_argument("--view", action="store_true", help="also start the web viewer (arena view)")
    p.add_argument("--view-port", type=int, default=8080, help="viewer port (default 8080)")
    p.add_argument("--quiet", action="store_true", help="no live table, only the final summary")
    p.add_argument("--observer-nice", type=int, default=OBSERVER_NICE, metavar="N",
                   help=f"niceness added to the recorder, ground truth and viewer so the simulated world "
                        f"and the system under test get the CPU first (default {OBSERVER_NICE}; 0 = same "
                        f"priority; bench/bench_demo_realtime.py compares)")
    p.add_argument("--prepare", action="store_true",
                   help="compile the numba kernels into numba's on-disk cache (~15 s on 2 cores) and exit; "
                        "run once after installing so the first demo starts in seconds (the demo "
                        "otherwise does it itself on its first run)")
    p.set_defaults(func=run)


def _free_ports(n: int) -> int:
    """The first of ``n`` consecutive TCP ports free on loopback, below the kernel's ephemeral
    range (there no outgoing connection takes one before the services listen on them). A single
    free port from the kernel was not enough: the robots listen on consecutive ports, and the
    one after it was sometimes in use ("Address already in use", the demo failed)."""
    import random
    import socket

    try:
        low = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        low = 32768
    low = max(low, 10_000 + 2 * n)
    for _ in range(200):
        base = random.randrange(10_000, low - n)
        socks = []
        try:
            for port in range(base, base + n):
                sock = socket.socket()
                socks.append(sock)
                sock.bind(("127.0.0.1", port))
            return base
        except OSError:
            continue
        finally:
            for sock in socks:
                sock.close()
    raise RuntimeError(f"no {n} consecutive free TCP ports on 127.0.0.1 between 10000 and {low}")


def _mission_for(i: int, mission: str) -> str:
    if mission == "mixed":
        return "circle" if i % 2 == 0 else "square"
    return mission


def _robot_names(n: int) -> list[str]:
    """The simulator's robot names (colour + index), which the bridge and scorer use as well."""
    from simulator.scenarios import Scenario

    return [spec.name for spec in Scenario(n_robots=n).robot_specs()]


def _robot_specs(n: int, markers: bool) -> list:
    """The robots ``arena sim --robots n [--markers]`` simulates (names, shell colours, marker ids)."""
    from simulator.scenarios import Scenario

    return Scenario(n_robots=n, markers=markers).robot_specs()


#: how the demo's webcam ground truth finds the robots, by ``--markers``
GROUND_TRUTH = {
    False: ("colour", "colour blobs (HSV from each shell's colour); heading modulo 90 deg from the square "
                      "shell's outline, resolved by the dark front window strip, else by the direction of motion"),
    True: ("markers", "ArUco markers on the shells (unique ids; heading from each marker's orientation)"),
}


def _groundtruth_args(n: int, markers: bool) -> list[str]:
    """``arena groundtruth`` arguments that find the simulator's robots: by their ArUco markers
    (``--detector aruco --marker ID=NAME``) with ``markers``, else by their shell colours
    (``--detector hsv --robot NAME=#rrggbb``). Either way the webcam's poses carry the robots'
    names (the tracker names its tracks after them, and the bridge closes its loop on
    ``arena/robots/<name>``)."""
    specs = _robot_specs(n, markers)
    if markers:
        return ["--detector", "aruco", *[a for spec in specs if spec.marker_id is not None
                                         for a in ("--marker", f"{spec.marker_id}={spec.name}")]]
    return ["--detector", "hsv", *[a for spec in specs for a in
                                   ("--robot", f"{spec.name}=#" + "".join(f"{int(c):02x}" for c in spec.color_rgb))]]


def _colour_problem(n: int) -> str | None:
    """Why the webcam cannot find the first ``n`` simulated robots by colour (a near-white shell
    on the white mats), or None."""
    from groundtruth.rgb import colour_detectable

    for i, spec in enumerate(_robot_specs(n, False)):
        why = colour_detectable(spec.color_rgb)
        if why:
            fewer = f", or at most {i} robot{'s' if i != 1 else ''} (robot {i + 1} is {spec.name})" if i else ""
            return (f"robot {spec.name} cannot be found by colour for the webcam ground truth: {why}. "
                    f"Run with --markers (ArUco markers on the shells, ground truth from them){fewer}")
    return None


def _print_table(line: str, quiet: bool, t0: float | None, duration: float) -> None:
    if quiet or t0 is None or not line.startswith("TABLE "):
        return
    from demo.scorer import format_rows

    data = json.loads(line[6:])
    elapsed = time.monotonic() - t0
    text = format_rows(data["rows"], data["latency"])
    header = f"--- t = {elapsed:5.1f} s of {duration:.0f} s " + "-" * 40
    if sys.stdout.isatty():
        sys.stdout.write("\x1b[H\x1b[J")
    print(header + "\n" + text, flush=True)


def _usage_error(args) -> str | None:
    """What is wrong with the demo's flags, or None."""
    if not 1 <= args.robots <= 16:
        return "--robots must be between 1 and 16"
    if not 0.05 <= args.power <= 1.0:
        return f"--power must be a fraction of full power in [0.05, 1], e.g. 1.0 or 0.5; got {args.power}"
    if not (math.isfinite(args.duration) and args.duration > 0):
        return f"--duration must be a positive number of seconds, got {args.duration}"
    if not 0 <= args.observer_nice <= 19:
        return "--observer-nice must be in 0..19 (a process may only lower its priority)"
    if args.duration > DURATION_MAX_S:
        return f"--duration must be at most {DURATION_MAX_S:g} s (24 h) of missions, got {args.duration:g}"
    if not 0 <= args.seed <= SEED_MAX:
        return f"--seed must be an integer in 0..{SEED_MAX}, got {args.seed}"
    if not 1 <= args.view_port <= 65535:
        return f"--view-port must be a TCP port in 1..65535, got {args.view_port}"
    out = getattr(args, "out", "runs")
    if not str(out).strip():
        return "--out is empty: give the parent folder of the run folder (default ./runs)"
    existing = next((q for q in (Path(out), *Path(out).parents) if q.exists()), None)
    if existing is not None and not existing.is_dir():
        return (f"--out {out}: {existing} is a file, not a folder: give the parent folder of the run folder "
                f"(default ./runs)")
    if not getattr(args, "prepare", False) and not getattr(args, "markers", False):
        return _colour_problem(args.robots)
    return None


@dataclass
class _Run:
    """One demo run: its folder, endpoints and robots, and what happened so far (updated while it
    runs, so an exception keeps what was seen before it)."""

    run_dir: Path
    endpoint: str        # the router's
    cam_port: int
    web_port: int
    robot_base: int      # robot i's serial port is robot_base + i
    robots: list[str]
    t_start: float = field(default_factory=time.monotonic)
    t_missions: float | None = None  # start of the missions, for the live table (None: no table)
    first_track_s: float | None = None
    interrupted: bool = False

    @property
    def z(self) -> list[str]:
        return ["-e", self.endpoint]

    @property
    def logs(self) -> Path:
        return self.run_dir / "logs"

    @property
    def calib(self) -> Path:
        return self.run_dir / "cam0.calib.json"


def run(args) -> int:
    error = _usage_error(args)
    if error:
        print(f"arena demo: {error}", file=sys.stderr)
        return 2
    if args.prepare:
        return _prepare()
    from arena.service import stop_on_signals
    from arena.session import SessionError

    run_dir = Path(args.out) / datetime.now().strftime("demo-%Y%m%d-%H%M%S")
    run_dir.mkdir(parents=True, exist_ok=False)
    base = _free_ports(3 + args.robots)   # router, camera, webcam, one per robot
    demo = _Run(run_dir, f"tcp/127.0.0.1:{base}", base + 1, base + 2, base + 3, _robot_names(args.robots))
    print(f"arena demo: {args.robots} robots, {args.mission} missions at {args.power:.0%} power, "
          f"{args.lighting} light, {args.duration:.0f} s; run folder {run_dir}", flush=True)
    kind, how = GROUND_TRUTH[bool(args.markers)]
    print(f"webcam ground truth: {kind}: {how}", flush=True)
    stop = stop_on_signals()
    demo.t_start = time.monotonic()
    sup = Supervisor(demo.logs)
    code = 0
    failure = None
    try:
        _run_lab(sup, demo, args, stop)
    except KeyboardInterrupt:
        print("\narena demo: interrupted, stopping (robots first)...", flush=True)
        code = 130
        demo.interrupted = True
    except (RuntimeError, SessionError) as exc:
        print(f"arena demo: {exc}", file=sys.stderr)
        code = 1
        failure = str(exc)
    finally:
        codes = sup.stop_all(first=["bridge", "sim"])
    services = {name for name in sup.procs if not name.startswith("cmd-")}
    pids = {name: p.popen.pid for name, p in sup.procs.items()}
    summary = _finish(run_dir, args, demo.first_track_s, {n: c for n, c in codes.items() if n in services}, pids,
                      killed=[n for n in sup.killed() if n in services],
                      died={n: c for n, c in sup.died().items() if n in services},
                      failure=failure, interrupted=demo.interrupted)
    if code == 0 and not summary["ok"]:
        code = 1
    return code


def _run_lab(sup: Supervisor, demo: _Run, args, stop) -> None:
    """Compile, start every process, run the missions for ``args.duration`` and return (the
    caller stops the processes). Raises RuntimeError when a service dies or a mission is refused."""
    from arena.session import ZenohSettings, open_session

    _compile_kernels(sup)
    # router, simulator, recorder and scorer start together (each waits for the router); the
    # services that need the simulator's devices or calibration follow once it runs. Every
    # process imports numpy/numba/OpenCV (seconds of CPU), so overlapping them is what makes
    # the first track come early.
    early = _start_router_sim_scorer(sup, demo, args)
    early[0].wait_ready()
    with open_session(ZenohSettings(mode="client", connect=[demo.endpoint]), wait_s=10) as session:
        alive = _AliveSet(session)
        early[1].wait_ready()
        # the recorder starts once the simulator has written the camera's calibration, which
        # places the event image under the robots in Foxglove's 3D panel
        early.append(sup.start(ProcSpec("recorder", python_cmd("record", str(demo.run_dir / "arena.mcap"), "--name",
                                                               "demo", "--calibration", str(demo.calib), *demo.z),
                                        ready_check=alive.has("recorder", "demo"), ready_timeout_s=90,
                                        nice=args.observer_nice), wait=False))
        specs = _service_specs(demo, args, alive)
        for proc in early[2:] + [sup.start(spec, wait=False) for spec in specs]:
            proc.wait_ready()
        print(f"all services up ({time.monotonic() - demo.t_start:.1f} s after launch)"
              + (f"; viewer: http://127.0.0.1:{args.view_port}" if args.view else ""), flush=True)
        _start_missions(session, demo.robots, args)
        print(f"missions started ({time.monotonic() - demo.t_start:.1f} s after launch)", flush=True)
        _watch_missions(sup, demo, alive, args.duration, stop)


def _sim_cmd(demo: _Run, args) -> list[str]:
    """The ``arena sim`` command of the run (``--markers`` only when the demo was asked for them)."""
    return python_cmd("sim", "--robots", str(args.robots), "--lighting", args.lighting, "--seed", str(args.seed),
                      "--camera-port", str(demo.cam_port), "--webcam-port", str(demo.web_port),
                      "--robot-base-port", str(demo.robot_base), "--layout", _layout(args.mission),
                      "--truth-csv", str(demo.run_dir / "truth.csv"), "--calibration-out", str(demo.calib),
                      "--record-raw", str(demo.run_dir / "events.raw"), "--publish-truth",
                      *(["--markers"] if args.markers else []), *demo.z)


def _start_router_sim_scorer(sup: Supervisor, demo: _Run, args) -> list:
    """Start the router, the simulator and the live scorer without waiting for them."""
    sim = _sim_cmd(demo, args)
    return [sup.start(ProcSpec("router", python_cmd("router", "-l", demo.endpoint, "--name", "demo"),
                               ready="listening on"), wait=False),
            sup.start(ProcSpec("sim", sim, ready="running", ready_timeout_s=90), wait=False),
            sup.start(ProcSpec("scorer", [sys.executable, "-m", "demo.scorer", *demo.z], ready="scorer ready",
                               on_line=lambda ln: _print_table(ln, args.quiet, demo.t_missions, args.duration)),
                      wait=False)]


def _service_specs(demo: _Run, args, alive: _AliveSet) -> list[ProcSpec]:
    """The services that need the simulator's devices or calibration, in start order: edge,
    tracker, ground truth, viewer (with ``--view``), bridge."""
    z = demo.z
    specs = [ProcSpec("edge", python_cmd("edge", f"tcp://127.0.0.1:{demo.cam_port}", "--camera", "cam0", *z),
                      ready_check=alive.has("edge", "cam0"), ready_timeout_s=90)]
    specs.append(ProcSpec("tracker", python_cmd("track", "--camera", "cam0", "--calibration", str(demo.calib),
                                                 "--tracker", args.tracker, "--fleet-size", str(args.robots),
                                                 "--name", "cam0", "--tracks-out", str(demo.run_dir / "tracks.csv"),
                                                 "--state", str(demo.run_dir / "tracker-state.json"), *z),
                          ready_check=alive.has("tracker", "cam0"), ready_timeout_s=90))
    web = f"http://127.0.0.1:{demo.web_port}"
    specs.append(ProcSpec("groundtruth", python_cmd("groundtruth", "--video", f"{web}/stream.mjpg",
                                                     "--calibration", f"{web}/calibration.json", "--clock", "stream",
                                                     "--name", "webcam", "--csv", str(demo.run_dir / "groundtruth.csv"),
                                                     *_groundtruth_args(args.robots, args.markers), *z),
                          ready_check=alive.has("groundtruth", "webcam"), ready_timeout_s=90,
                          nice=args.observer_nice))
    if args.view:
        specs.append(ProcSpec("viewer", python_cmd("view", "--port", str(args.view_port), "--name", "demo",
                                                   "--calibration", str(demo.calib), *z), ready="viewer on",
                              nice=args.observer_nice))
    bridge = python_cmd("bridge", "run", *[a for i, r in enumerate(demo.robots)
                                           for a in ("--robot", f"{r}=socket://127.0.0.1:{demo.robot_base + i}")],
                        "--name", "demo", "--log-dir", str(demo.run_dir / "telemetry"), "--require-all", *z)
    specs.append(ProcSpec("bridge", bridge, ready_check=alive.has("bridge", "demo"), ready_timeout_s=90,
                          stop_timeout_s=5))
    return specs


def _watch_missions(sup: Supervisor, demo: _Run, alive: _AliveSet, duration: float, stop) -> None:
    """Let the missions run ``duration`` + 1 s (or until ``stop``), noting the first track; raise
    RuntimeError when a service stops."""
    demo.t_missions = time.monotonic()
    t_missions = demo.t_missions
    while time.monotonic() - t_missions < duration + 1 and not stop.is_set():
        dead = [n for n in sup.dead() if not n.startswith("cmd-")]
        if dead:
            raise RuntimeError(f"{', '.join(dead)} stopped unexpectedly; see {demo.logs}")
        if demo.first_track_s is None and alive.tracks_seen:
            demo.first_track_s = alive.tracks_seen - demo.t_start
            alive.stop_watching_tracks()
        stop.wait(0.2)
    demo.interrupted = stop.is_set()
    demo.t_missions = None   # the missions are over: no more live tables while stopping


def _prepare() -> int:
    """``arena demo --prepare``: the compile step of installing (the README's first command runs
    it between ``pip install`` and ``arena demo``). The compilers' logs are kept only on failure."""
    import shutil
    import tempfile

    logs = Path(tempfile.mkdtemp(prefix="arena-prepare-"))
    sup = Supervisor(logs)
    try:
        if not _compile_kernels(sup):
            print("arena demo --prepare: the numba kernels are already compiled (numba's cache); nothing to do",
                  flush=True)
    except RuntimeError as exc:
        print(f"arena demo --prepare: {exc}", file=sys.stderr)
        return 1
    finally:
        sup.stop_all()
    shutil.rmtree(logs, ignore_errors=True)
    return 0


def _compile_kernels(sup: Supervisor) -> bool:
    """On the first run after installing, compile the numba kernels of the simulator and of the
    edge and tracker in two processes side by side (~14 s on 2 cores) before any service starts:
    left to the services, the compiles competed with each other and with the running simulator,
    and the first track came after about a minute. Later runs load them from numba's cache.
    Returns whether it compiled anything."""
    from demo.warmup import PARTS, mark_warmed_up, warmed_up

    if warmed_up():
        return False
    print("compiling the numba kernels once after installing or updating (about 15 s on 2 cores, "
          "a few when numba's cache has most of them; later runs skip this)", flush=True)
    t0 = time.monotonic()
    procs = [sup.start(ProcSpec(f"cmd-compile-{part}", [sys.executable, "-m", "demo.warmup", part]), wait=False)
             for part in PARTS]
    for proc in procs:
        try:
            proc.popen.wait(timeout=600)
        except subprocess.TimeoutExpired:
            raise RuntimeError(f"compiling the kernels took over 10 minutes; see {proc.log_path}") from None
        if proc.popen.returncode != 0:
            raise RuntimeError(f"compiling the kernels failed ({proc.spec.name} exited with "
                               f"{proc.popen.returncode}); see {proc.log_path}")
    mark_warmed_up()
    print(f"kernels compiled in {time.monotonic() - t0:.0f} s", flush=True)
    return True


class _AliveSet:
    """Which services are alive (liveliness tokens), and when the first track arrived."""

    def __init__(self, session):
        import threading

        self.keys: set[str] = set()
        self.tracks_seen: float | None = None
        self._lock = threading.Lock()
        from arena.keys import ALL_ALIVE, ALL_ROBOTS

        session.liveliness().declare_subscriber(ALL_ALIVE, self._on_alive, history=True)
        self._track_sub = session.declare_subscriber(ALL_ROBOTS, self._on_track)

    def stop_watching_tracks(self) -> None:
        """Undeclare the tracks' subscriber once the first track is noted (it would otherwise take
        every track of the run: CPU the two cores of a demo machine do not have to spare)."""
        if self._track_sub is not None:
            self._track_sub.undeclare()
            self._track_sub = None

    def _on_alive(self, sample) -> None:
        import zenoh

        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self.keys.add(str(sample.key_expr))
            else:
                self.keys.discard(str(sample.key_expr))

    def _on_track(self, sample) -> None:
        if self.tracks_seen is None:
            self.tracks_seen = time.monotonic()

    def has(self, role: str, name: str):
        from arena.keys import alive_key

        key = alive_key(role, name)

        def check() -> bool:
            with self._lock:
                return key in self.keys
        return check


def _cell(n: int) -> float:
    return 1.83 / max(1, math.ceil(math.sqrt(n)))


def _layout(mission: str) -> str:
    return mission


def _mission(i: int, args, start_pose: tuple[float, float, float]):
    """Mission of robot ``i``, sized to its cell (as the simulator lays robots out), with enough laps."""
    from arena.messages import MissionCommand

    m = _mission_for(i, args.mission)
    cell = _cell(args.robots)
    speed = 0.46 * args.power
    if m == "circle":
        r = min(0.30, cell / 2 - 0.09)
        params = {"radius_m": round(r, 3), "laps": math.ceil(args.duration * speed / (2 * math.pi * r)) + 1}
    else:
        side = min(0.60, cell - 0.18)
        params = {"side_m": round(side, 3), "laps": math.ceil(args.duration * speed / (4 * side)) + 1}
    params["start_pose"] = [round(v, 5) for v in start_pose]  # the simulator's layout: closed loop starts at once
    return MissionCommand(mission=m, params=params, power=args.power, control=args.control, operator="arena demo")


def _start_missions(session, robots: list[str], args) -> None:
    """Send every robot its mission over Zenoh (as `arena bridge mission` does), to start together."""
    from dataclasses import replace

    from arena.keys import cmd_key
    from arena.messages import CommandReply, MessageError, decode

    from simulator.cli import layout_poses

    poses = layout_poses(_layout(args.mission), len(robots), 1.83)
    start_ns = time.time_ns() + 1_000_000_000
    for i, r in enumerate(robots):
        cmd = replace(_mission(i, args, poses[i]), start_ns=start_ns)
        replies = list(session.get(cmd_key(r, "mission"), payload=cmd.encode(), timeout=20.0))
        ok = [x.ok for x in replies if x.ok is not None]
        if not ok:
            raise RuntimeError(f"no bridge answered the mission for {r}")
        try:
            reply = decode(bytes(ok[0].payload))
        except MessageError as exc:
            raise RuntimeError(f"the bridge's reply for {r} is not readable: {exc}") from None
        if not isinstance(reply, CommandReply) or not reply.ok:
            raise RuntimeError(f"the bridge refused the mission for {r}: {getattr(reply, 'error', reply)}")


def _odometry_fallbacks(manifests: list[dict]) -> dict | None:
    """Per closed-loop robot, how often its loop lost its track while driving and fell back to
    odometry alone, for how long in all, and whether it was so at the end (the manifests'
    ``fusion``): ``{robot: {"fallbacks", "seconds", "before_first_track_s", "at_end"}}``: seconds
    from the last track (or from when it started to drive) until a track came back, the part of
    them before the mission's first track apart; None when no manifest says."""
    out = {}
    for m in manifests:
        fusion = m.get("fusion") or {}
        if m.get("control") == "closed" and "odometry_fallbacks" in fusion:
            out[str(m.get("robot"))] = {"fallbacks": int(fusion["odometry_fallbacks"]),
                                        "seconds": float(fusion.get("odometry_only_s") or 0.0),
                                        "before_first_track_s": float(fusion.get("odometry_before_first_track_s")
                                                                      or 0.0),
                                        "at_end": bool(fusion.get("on_odometry_at_end"))}
    return out or None


def _missions_end_us(telemetry_dir: Path) -> int | None:
    """When the first mission ended (stopped at the end of the demo), on the simulator's clock:
    the emulated robots' clocks are the simulator's, so the host time of the mission's end row
    maps through the last telemetry sample before it. None when no mission log says so."""
    import csv

    from robot_bridge.logs import MissionLog

    ends = []
    for path in sorted(Path(telemetry_dir).glob("*.csv")):
        last = None
        with open(path, newline="") as f:
            for row in csv.DictReader(f):
                if row["event"] == "sample":
                    last = (int(row["host_time_ns"]), int(row["robot_time_us"]))
                elif last is not None and row["event"] not in MissionLog.PROGRESS_EVENTS:   # its end (or its link's)
                    ends.append(last[1] + (int(row["host_time_ns"]) - last[0]) // 1000)
                    break
    return min(ends) if ends else None


def _sim_realtime(log_path: Path) -> dict | None:
    """The simulator's closing ``real time: factor F over S s simulated, worst lag L s (t=T s)``
    line from its log, as ``{"factor", "simulated_s", "worst_lag_s", "worst_lag_at_s"}``."""
    import re

    try:
        text = log_path.read_text(errors="replace")
    except OSError:
        return None
    m = None
    for m in re.finditer(r"real time: factor ([\d.]+) over ([\d.]+) s simulated, worst lag ([\d.]+) s "
                         r"\(t=([\d.]+) s\)", text):
        pass
    if m is None:
        return None
    return {"factor": float(m[1]), "simulated_s": float(m[2]), "worst_lag_s": float(m[3]),
            "worst_lag_at_s": float(m[4])}


def _latency(log_path: Path) -> dict | None:
    """The live scorer's closing ``SUMMARY {...}`` latency percentiles (edge publish -> track
    received), as ``{"n", "p50_ms", "p99_ms"}``."""
    try:
        lines = [ln for ln in log_path.read_text(errors="replace").splitlines() if ln.startswith("SUMMARY ")]
        lat = json.loads(lines[-1][8:])["latency"] if lines else None
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return lat if isinstance(lat, dict) and lat.get("n") else None


def _windows(mcap_path: Path, missions_ns: int | None = None) -> dict | None:
    """Event windows over the whole run from the edge's and the tracker's last status in the MCAP
    recording: how many the edge published and dropped (DROP policy), and how many the tracker
    took in, found missing on the way (sequence gaps) or dropped from its queue. With
    ``missions_ns`` (host ns when the missions started), ``"during_missions"`` holds the losses
    after it: the counters' growth since each service's last status before then."""
    lost_keys = {"edge": {"edge_dropped": "windows_dropped"},
                 "tracker": {"tracker_missed": "windows_missed", "tracker_queue_dropped": "windows_dropped_in_queue"}}
    try:
        from mcap.reader import make_reader

        from arena.keys import parse_key, status_key

        last: dict[str, dict] = {}
        before: dict[str, dict] = {}
        with open(mcap_path, "rb") as f:
            for _, ch, m in make_reader(f).iter_messages(topics=[status_key("edge", "cam0"),
                                                                  status_key("tracker", "cam0")]):
                role = parse_key(ch.topic).parts["role"]
                last[role] = json.loads(m.data).get("counters", {})
                if missions_ns is not None and m.log_time <= missions_ns:
                    before[role] = last[role]
    except Exception:  # noqa: BLE001 - an unreadable recording only loses this line of the report
        return None
    if set(last) != {"edge", "tracker"}:
        return None
    e, t = last["edge"], last["tracker"]
    out = {"edge_published": e.get("windows", 0), "edge_dropped": e.get("windows_dropped", 0),
           "tracker_in": t.get("windows_in", 0), "tracker_missed": t.get("windows_missed", 0),
           "tracker_queue_dropped": t.get("windows_dropped_in_queue", 0)}
    if missions_ns is not None:
        out["during_missions"] = {k: last[role].get(c, 0) - before.get(role, {}).get(c, 0)
                                  for role, keys in lost_keys.items() for k, c in keys.items()}
    return out


def _unseen(wins: dict) -> int:
    """Windows the edge published that the tracker's counters do not account for: sent before it
    subscribed (services start together) or after its last status (they stop one by one)."""
    return (wins["edge_published"] - wins["tracker_in"] - wins["tracker_missed"] - wins["tracker_queue_dropped"])


def _lost(wins: dict) -> int:
    return sum(int(wins.get(k) or 0) for k in ("edge_dropped", "tracker_missed", "tracker_queue_dropped"))


def _missions_start_ns(manifests: list[dict]) -> int | None:
    """When the first mission started (host ns, from the manifests' ``start_ns``), or None."""
    starts = [m["start_ns"] for m in manifests if isinstance(m.get("start_ns"), int)]
    return min(starts) if starts else None


def _webcam_scores(run_dir: Path, truth, end_us):
    """The webcam ground truth (``groundtruth.csv``) scored like a tracker against the exact poses
    ``truth`` until ``end_us``; None when the file is missing or has no rows."""
    from demo.report import webcam_as_tracks
    from arena.formats.tables import read_truth_csv
    from groundtruth.metrics import evaluate

    path = run_dir / "groundtruth.csv"
    if not path.exists():
        return None
    try:
        cam = read_truth_csv(path)
    except Exception:  # noqa: BLE001 - a header without rows (nothing detected) or an unreadable file
        return None
    if end_us is not None:
        cam = cam[cam["t_us"] <= end_us]
    return evaluate(webcam_as_tracks(cam), truth, gate_m=0.10)


def _heading_sources(log_path: Path) -> dict | None:
    """The colour ground truth's closing ``headings: N from the front mark, M from motion, K unknown``
    from its log, as ``{"front_mark", "motion", "unknown"}``."""
    import re

    try:
        found = re.findall(r"headings: (\d+) from the front mark, (\d+) from motion, (\d+) unknown",
                           log_path.read_text(errors="replace"))
    except OSError:
        return None
    if not found:
        return None
    return dict(zip(("front_mark", "motion", "unknown"), (int(v) for v in found[-1])))


def _report(run_dir: Path, args, summary: dict, scores, tracks, truth, manifests, webcam_scores=None) -> Path:
    """Write the run's ``report.md`` (with plots), with the webcam ground truth's scores."""
    from demo.report import replay_hint, run_files, write_demo_report

    setup = (f"{args.robots} robots, {args.mission} missions at {args.power:.0%} power, {args.lighting} light, "
             f"{args.duration:g} s of missions, seed {args.seed}, tracker `{args.tracker}`, control `{args.control}`, "
             f"shells {'with ArUco markers' if getattr(args, 'markers', False) else 'without markers'}.")
    return write_demo_report(run_dir, setup, summary, scores, tracks, truth, webcam_scores, manifests,
                             files=run_files(run_dir, also=("report.md", "report/", "summary.json")),
                             replay=replay_hint(run_dir, args.view_port))


def _finish(run_dir: Path, args, first_track_s, codes, pids, *, killed=(), died=None, failure=None,
            interrupted=False) -> dict:
    """Score the run, judge it (:func:`demo.verdict.verdict`), write the report and
    ``summary.json``, print the results: first whether the run was ok and why not."""
    from demo.report import read_manifests
    from demo.verdict import verdict

    facts: dict = {"run_dir": str(run_dir), "exit_codes": codes, "killed": list(killed), "died": dict(died or {}),
                   "pids": pids, "first_track_s": first_track_s}
    if failure:
        facts["failure"] = failure.strip().splitlines()[0] if failure.strip() else failure
    if interrupted:
        facts["interrupted"] = True
    gt_kind, gt_how = GROUND_TRUTH[bool(getattr(args, "markers", False))]
    facts["groundtruth"] = {"method": gt_kind, "how": gt_how}
    scored, webcam_scores = _score_run(run_dir, facts, gt_kind)
    manifests = read_manifests(run_dir / "telemetry")
    health = _run_health(run_dir, manifests, facts)

    def judge() -> tuple[bool, list[str]]:
        return verdict(exit_codes=codes, killed=killed, died=died, failure=facts.get("failure"),
                       interrupted=interrupted, manifests=manifests, robots=args.robots,
                       sim_realtime=health["sim_realtime"], windows=health["windows"],
                       truth_rows=facts.get("truth_rows"), scores=facts.get("scores"),
                       score_error=facts.get("score_error"), report_error=facts.get("report_error"),
                       webcam=facts.get("webcam"), webcam_method=gt_kind)

    ok, problems = judge()
    summary = {"ok": ok, "problems": problems, **facts}
    if scored is not None:
        try:
            summary["report"] = str(_report(run_dir, args, summary, *scored, manifests, webcam_scores))
        except Exception as exc:  # noqa: BLE001 - the scores stand without their report
            summary["report_error"] = facts["report_error"] = f"{type(exc).__name__}: {exc}"
            summary["ok"], summary["problems"] = judge()
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    _print_verdict_and_scores(summary, gt_kind, gt_how)
    _print_run_health(summary, first_track_s, health)
    _print_run_pointers(run_dir, args, summary)
    return summary


def _score_run(run_dir: Path, facts: dict, gt_kind: str):
    """Score ``tracks.csv`` (and the webcam ground truth) against ``truth.csv``, recording
    the scores, or why there are none, in ``facts``.

    Only the missions are scored, not the robots parked while the demo stops. A failure
    is recorded as ``score_error`` rather than raised: the run is judged either way.
    Returns ``(scores, tracks, truth)`` or None, and the webcam scores or None."""
    tracks, truth = run_dir / "tracks.csv", run_dir / "truth.csv"
    webcam_scores = None
    scored = None
    if tracks.exists() and truth.exists():
        from arena.formats.tables import read_tracks_csv, read_truth_csv
        from groundtruth.metrics import evaluate

        try:
            tr, gt = read_tracks_csv(tracks), read_truth_csv(truth)
            end_us = _missions_end_us(run_dir / "telemetry")
            if end_us is not None:   # score the missions, not the robots parked while stopping
                facts["scored_until_us"] = end_us
                tr, gt = tr[tr["t_us"] <= end_us], gt[gt["t_us"] <= end_us]
            facts["truth_rows"] = int(len(gt))
            scores = evaluate(tr, gt, gate_m=0.10)
            facts["scores"] = scores.to_dict()
            scored = (scores, tr, gt)
            webcam_scores = _webcam_scores(run_dir, gt, end_us) if len(gt) else None
            if webcam_scores is not None:
                w = webcam_scores.to_dict()
                facts["webcam"] = {"method": gt_kind,
                                   **{k: w[k] for k in ("precision", "recall", "mae_cm", "heading_mae_deg", "n_frames")}}
        except Exception as exc:  # noqa: BLE001 - report what failed rather than crash at the end
            facts["score_error"] = str(exc) or type(exc).__name__
    else:
        facts["score_error"] = ", ".join(p.name for p in (tracks, truth) if not p.exists()) + " missing"
    return scored, webcam_scores


def _run_health(run_dir: Path, manifests, facts: dict) -> dict:
    """Read how the run itself went from its logs, recording and telemetry: the
    simulator's real-time factor, the webcam's heading sources, the edge-to-track
    latency, the event windows published and lost, the odometry-only fallbacks.

    Each found is recorded in ``facts`` (absent ones are left out); returns them all
    (None where absent) for the verdict and the printout."""
    rt = _sim_realtime(run_dir / "logs" / "sim.log")
    if rt is not None:
        facts["sim_realtime"] = rt
    headings = _heading_sources(run_dir / "logs" / "groundtruth.log")
    if headings is not None:
        facts["groundtruth"]["headings"] = headings
    lat = _latency(run_dir / "logs" / "scorer.log")
    wins = _windows(run_dir / "arena.mcap", _missions_start_ns(manifests))
    if lat is not None:
        facts["latency"] = lat
    if wins is not None:
        facts["windows"] = wins
    fallbacks = _odometry_fallbacks(manifests)
    if fallbacks is not None:
        facts["odometry_fallbacks"] = fallbacks
    return {"sim_realtime": rt, "latency": lat, "windows": wins, "odometry_fallbacks": fallbacks}


def _fmt_or_na(values: dict, key: str, fmt: str, unit: str = "") -> str:
    """``values[key]`` formatted with ``fmt`` and ``unit``, or ``n/a`` if not a number."""
    v = values.get(key)
    return format(v, fmt) + unit if isinstance(v, (int, float)) else "n/a"


def _print_verdict_and_scores(summary: dict, gt_kind: str, gt_how: str) -> None:
    """Print first whether the run was ok and, if not, each problem; then the tracker's
    scores against the exact poses and the webcam ground truth's own scores."""
    from demo.report import OK_TEXT

    print("\n=== arena demo: results ===")
    if summary["ok"]:
        print(f"ok: {OK_TEXT}")
    else:
        print(f"NOT OK: {len(summary['problems'])} problem(s):")
        for line in summary["problems"]:
            print(f"  - {line}")
    s = summary.get("scores", {})
    if s:
        def f(key: str, fmt: str, unit: str = "") -> str:
            return _fmt_or_na(s, key, fmt, unit)
        print(f"precision {f('precision', '.3f')}  recall {f('recall', '.3f')}  MOTA {f('mota', '.3f')}  "
              f"IDF1 {f('idf1', '.3f')}  HOTA {f('hota', '.3f')}  MAE {f('mae_cm', '.2f', ' cm')}  "
              f"heading MAE {f('heading_mae_deg', '.1f', '°')}  ID switches {s.get('id_switches')}  "
              f"({s.get('n_frames', 0)} frames, {s.get('n_gt', 0)} robot positions)")
    else:
        print(f"no score: {summary.get('score_error', 'tracks or truth missing')}")
    print("scored against the simulator's exact poses (truth.csv)")
    cam = summary.get("webcam")
    if cam:
        def g(key: str, fmt: str, unit: str = "") -> str:
            return _fmt_or_na(cam, key, fmt, unit)
        hs = summary["groundtruth"].get("headings")
        print(f"webcam ground truth by {gt_kind} ({gt_how}) against the exact poses: precision "
              f"{g('precision', '.3f')}  recall {g('recall', '.3f')}  MAE {g('mae_cm', '.2f', ' cm')}  heading MAE "
              f"{g('heading_mae_deg', '.1f', '°')}  ({cam.get('n_frames', 0)} frames)"
              + (f"; headings: {hs['front_mark']} from the front mark, {hs['motion']} from motion, "
                 f"{hs['unknown']} unknown" if hs else ""))
    else:
        print(f"webcam ground truth by {gt_kind}: not scored (groundtruth.csv missing or without rows)")


def _print_run_health(summary: dict, first_track_s, health: dict) -> None:
    """Print how the run went: time to the first track, the simulator's real-time
    factor, the latency, the event windows lost and where, the odometry-only loops."""
    rt, lat, wins, fallbacks = (health[k] for k in ("sim_realtime", "latency", "windows", "odometry_fallbacks"))
    if first_track_s is not None:
        print(f"first track after {first_track_s:.1f} s")
    if rt is not None:
        print(f"simulator: {rt['factor']:.2f}x real time, worst lag {rt['worst_lag_s']:.2f} s"
              + ("" if rt["worst_lag_s"] < 0.5 else " (the CPU was short; the data follow the simulated clock)"))
    if lat is not None:
        print(f"latency edge -> track: p50 {lat['p50_ms']:.1f} ms, p99 {lat['p99_ms']:.1f} ms over {lat['n']} tracks")
    if wins is not None:
        print(f"event windows: the edge published {wins['edge_published']} and dropped {wins['edge_dropped']}; "
              f"the tracker processed {wins['tracker_in']}, found {wins['tracker_missed']} missing and dropped "
              f"{wins['tracker_queue_dropped']} from its queue"
              + (f" ({sum(wins['during_missions'].values())} of these lost while the missions ran)"
                 if "during_missions" in wins and _lost(wins) else "")
              + (f"; the other {_unseen(wins)} were published before the tracker's first window or after its "
                 f"last status" if _unseen(wins) > 0 else ""))
    if fallbacks is not None:
        print("closed loops on odometry alone (no track for > 0.5 s while driving): "
              + (", ".join(_fallback_words(r, v) for r, v in fallbacks.items() if v["fallbacks"]) or "none"))


def _fallback_words(robot: str, v: dict) -> str:
    """``black0 1x, 0.6 s (0.6 s before its first track)``: one robot's fallbacks to odometry."""
    first = float(v.get("before_first_track_s") or 0.0)
    notes = ([f"{first:.1f} s before its first track"] if first > 0 else []) + (["still at the end"] if v["at_end"] else [])
    return f"{robot} {v['fallbacks']}x, {v['seconds']:.1f} s" + (f" ({'; '.join(notes)})" if notes else "")


def _print_run_pointers(run_dir: Path, args, summary: dict) -> None:
    """Print where the results are: the report (or why there is none), the run folder
    and its files, and how to watch the run again."""
    from demo.report import replay_hint, run_files

    if "report" in summary:
        print(f"report: {summary['report']}  (scores, real time, missions, webcam ground truth, plots)")
    elif "report_error" in summary:
        print(f"no report: {summary['report_error']}")
    print(f"run folder: {run_dir}  ({', '.join(run_files(run_dir)) or 'empty'})")
    hint = replay_hint(run_dir, args.view_port)
    if hint:
        print(f"watch it again: {hint}\n  (then open http://127.0.0.1:{args.view_port}; the replay is its own "
              "Zenoh router, so nothing else needs to run; Ctrl-C stops the viewer)")
    else:
        print("watch it again: not possible, the run left no arena.mcap")


# --------------------------------------------------------------------------------------------
# arena experiment
# --------------------------------------------------------------------------------------------
def register_experiment(sub) -> None:
    """Add ``arena experiment``: rerun the paper's study on the simulator."""
    p = sub.add_parser(
        "experiment", help="rerun the paper's experiments on the simulator, with a report",
        formatter_class=formatter,
        description="Rerun the paper's study end to end on the simulated arena: the minPts sweep\n"
                    "(n_avg-clusters and A_ratio, full and partial clusters, 50 % and 100 % power), the\n"
                    "accumulation-time sweep (MAE vs t_a), 1-4 robots x circle/square x 50/100 % power\n"
                    "(the paper's table beside ours), lighting (full, dimmed, dark), for both trackers\n"
                    "(idtrack, fleet). Writes DIR/report.md with plots, tables and a JSON of every run.\n"
                    "Every run is seeded: the same --seed gives the same numbers.",
        epilog="Examples:\n"
               "  arena experiment paper --out study/               # the full study (< 30 min)\n"
               "  arena experiment paper --out /tmp/ci --quick      # a short version for CI (~2 min)\n"
               "  arena experiment paper --out study/ --seed 7 --only table,lighting\n"
               "Exit code 0 when every run succeeded, 1 when some failed (listed in the report), 2 for bad options.")
    p.add_argument("study", choices=["paper"], help="which study to run (the paper's)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder for the report")
    p.add_argument("--quick", action="store_true", help="short runs and coarse sweeps (CI)")
    p.add_argument("--seed", type=int, default=1, help="base random seed (default 1)")
    p.add_argument("--only", metavar="PARTS", default=None,
                   help="comma-separated subset of: minpts,ta,table,lighting (default all)")
    p.add_argument("--seconds", type=float, default=None, metavar="S",
                   help="simulated seconds per scenario, 0.5-120 (default 12, or 3 with --quick)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run_experiment)


def run_experiment(args: argparse.Namespace) -> int:
    """Run ``arena experiment``; returns the exit code."""
    from dataclasses import replace

    from demo.experiment import PARTS, ExperimentError, StudyPlan, check_output_folder, run_paper_study

    if args.seconds is not None and not 0.5 <= args.seconds <= 120:
        print(f"arena experiment: --seconds must be 0.5-120 s per scenario, got {args.seconds:g}", file=sys.stderr)
        return 2
    if not 0 <= args.seed <= SEED_MAX:
        print(f"arena experiment: --seed must be an integer in 0..{SEED_MAX}, got {args.seed}", file=sys.stderr)
        return 2
    try:
        check_output_folder(args.out)   # before any run: '' would be the current folder
    except ExperimentError as exc:
        print(f"arena experiment: --out: {exc}", file=sys.stderr)
        return 2
    plan = None
    if args.seconds is not None:
        plan = replace(StudyPlan.quick() if args.quick else StudyPlan.full(), duration_s=args.seconds)
    parts = PARTS if args.only is None else tuple(s.strip() for s in args.only.split(",") if s.strip())
    bad = [s for s in parts if s not in PARTS]
    if bad or not parts:
        print(f"arena experiment: unknown part(s) {', '.join(bad) or '(none)'}; choose from "
              f"{','.join(PARTS)}", file=sys.stderr)
        return 2
    try:
        study = run_paper_study(Path(args.out), quick=args.quick, seed=args.seed, parts=parts,
                                progress=not args.no_progress, plan=plan)
    except ExperimentError as exc:
        print(f"arena experiment: {exc}", file=sys.stderr)
        return 2
    print(f"report written to {study.report} ({study.seconds:.0f} s)")
    for f in study.failures:
        print(f"arena experiment: run failed: {f['step']}: {f['error']}", file=sys.stderr)
    return 1 if study.failures else 0

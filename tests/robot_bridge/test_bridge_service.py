"""The bridge over real Zenoh (loopback): commands and their errors, e-stop latency and latch,
geofence, telemetry published for every sample, closed loop on tracks, and the CLI client."""

from __future__ import annotations

import socket
import subprocess
import sys
import threading
import time

import pytest
import zenoh
from bridge_testkit import running_world, wait_for

from arena.messages import Command, CommandReply, MissionCommand, Telemetry, Track, decode
from arena.session import ZenohSettings, open_session
from robot_bridge.logs import read_log
from robot_bridge.core import BridgeOptions, RobotSetup
from robot_bridge.odometry import WheelGeometry
from robot_bridge.service import Bridge
from simulator.robot_emulator import RobotEmulatorServer


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def lab(tmp_path):
    """Two emulated robots, a bridge on a Zenoh peer session listening on loopback."""
    port = free_port()
    starts = [(0.9, 0.6, 1.5708), (0.5, 1.2, 0.0)]
    with running_world(2, starts=starts) as world, RobotEmulatorServer(world, 0) as e1, \
            RobotEmulatorServer(world, 1) as e2, \
            open_session(ZenohSettings(mode="peer", connect=[], listen=[f"tcp/127.0.0.1:{port}"])) as session:
        telemetry = []
        session.declare_subscriber("arena/telemetry/*", lambda s: telemetry.append(decode(s.payload.to_bytes())))
        robots = [RobotSetup("r1", e1.url, WheelGeometry(track_width_m=0.11)),
                  RobotSetup("r2", e2.url, WheelGeometry(track_width_m=0.11))]
        with Bridge(session, robots, BridgeOptions(log_dir=str(tmp_path))) as bridge:
            for h in bridge.handles.values():
                assert h.link.wait_connected(3), h.link.last_error
            yield {"world": world, "emus": (e1, e2), "session": session, "bridge": bridge,
                   "telemetry": telemetry, "endpoint": f"tcp/127.0.0.1:{port}", "dir": tmp_path}


def ask(session, robot, verb, msg=None) -> list[CommandReply]:
    payload = msg.encode() if msg is not None else b""
    out = []
    for r in session.get(f"arena/cmd/{robot}/{verb}", payload=payload, timeout=3.0,
                         consolidation=zenoh.ConsolidationMode.NONE):
        assert r.ok is not None
        out.append(CommandReply.decode(r.ok.payload.to_bytes()))
    return sorted(out, key=lambda r: r.robot)


def circle(**kw):
    return MissionCommand(mission="circle", params={"radius_m": 0.2, **kw.pop("params", {})}, power=0.5, **kw)


def test_mission_ack_busy_bad_parameter_and_telemetry(lab):
    s, world = lab["session"], lab["world"]
    (rep,) = ask(s, "r1", "mission", circle())
    assert rep.ok and rep.detail["phases"] == 1 and rep.detail["speed_mps"] == pytest.approx(0.23)
    assert wait_for(lambda: world.power(0) != (0, 0), 1.0)
    (busy,) = ask(s, "r1", "mission", circle())
    assert not busy.ok and busy.error.startswith("busy: r1 runs mission")
    (bad,) = ask(s, "r2", "mission", MissionCommand(mission="circle", params={"radius_m": -1}))
    assert not bad.ok and "bad parameter" in bad.error and "radius_m" in bad.error
    (closed,) = ask(s, "r2", "mission", circle(control="closed"))
    assert not closed.ok and "needs a track of r2" in closed.error
    (led,) = ask(s, "r2", "led", Command(verb="led", params={"rgb": [0, 255, 0]}))
    assert led.ok and wait_for(lambda: lab["emus"][1].led == (0, 255, 0), 1.0)
    (bad_led,) = ask(s, "r2", "led", Command(verb="led", params={"rgb": [0, 999, 0]}))
    assert not bad_led.ok and "bad parameter" in bad_led.error
    h = lab["bridge"].handles["r1"]
    assert wait_for(lambda: h.runner is None, 12.0), h.runner and h.runner.phase
    assert h.last_result["status"] == "finished"
    manifest, rows = read_log(lab["dir"], "r1", rep.detail["mission_id"])
    samples = [r for r in rows if r["event"] == "sample"]
    # every logged sample was also published on arena/telemetry/r1, same seq (the test's subscriber
    # gets them on Zenoh's thread, the last ones possibly after the mission's log is closed: polled)
    logged = {int(r["seq"]) for r in samples}

    def published():
        return {t.seq for t in list(lab["telemetry"]) if isinstance(t, Telemetry) and t.robot == "r1"}

    assert logged and wait_for(lambda: logged <= published(), 3.0), sorted(logged - published())[:10]
    assert manifest["link"]["missing"] == 0 and manifest["path_error_odometry"]["mean_m"] < 0.2
    assert world.power(0) == (0, 0)


def test_estop_stops_within_100ms_and_latches(lab):
    s, world = lab["session"], lab["world"]
    assert all(r.ok for r in ask(s, "all", "mission", circle(params={"laps": 3})))
    assert wait_for(lambda: world.power(0) != (0, 0) and world.power(1) != (0, 0), 1.0)
    time.sleep(0.3)
    t0 = time.monotonic()
    replies = []
    th = threading.Thread(target=lambda: replies.extend(ask(s, "all", "estop")))
    th.start()
    assert wait_for(lambda: world.power(0) == (0, 0) and world.power(1) == (0, 0), 1.0, step=0.001)
    latency = time.monotonic() - t0
    th.join()
    assert latency < 0.1, f"e-stop took {latency * 1000:.0f} ms"
    assert [r.robot for r in replies] == ["r1", "r2"] and all(r.ok and r.detail["latched"] for r in replies)
    (refused,) = ask(s, "r1", "mission", circle())
    assert not refused.ok and refused.error.startswith("e-stop latched on r1")
    time.sleep(0.4)
    assert world.power(0) == (0, 0)        # nothing restarted it
    assert ask(s, "r1", "clear")[0].ok
    assert ask(s, "r1", "mission", circle())[0].ok


def test_link_down_is_a_clear_error(lab):
    lab["emus"][1].stop()
    h = lab["bridge"].handles["r2"]
    assert wait_for(lambda: not h.link.connected, 2.0)
    (rep,) = ask(lab["session"], "r2", "mission", circle())
    assert not rep.ok and rep.error.startswith("link down: r2")


def publish_truth_tracks(session, world, stop, delay_s=0.05):
    """Stand-in for the tracker: the true pose of r1, stamped as seen ``delay_s`` ago."""
    pub = session.declare_publisher("arena/robots/1")
    history = []
    while not stop.is_set():
        now = time.time_ns()
        history.append((now, world.pose(0)))
        while len(history) > 1 and history[1][0] <= now - delay_s * 1e9:
            history.pop(0)
        t_pose, (x, y, yaw) = history[0]
        # edge published the window at t_pose (stamp == window end)
        pub.put(Track(track_id=1, robot="r1", stamp_us=1, x=x, y=y, yaw=yaw, window_end_us=1,
                      edge_publish_ns=t_pose).encode())
        stop.wait(0.02)


def test_closed_loop_on_tracks_and_geofence(lab):
    s, world = lab["session"], lab["world"]
    stop = threading.Event()
    th = threading.Thread(target=publish_truth_tracks, args=(s, world, stop), daemon=True)
    th.start()
    try:
        h = lab["bridge"].handles["r1"]
        assert wait_for(lambda: h.estimator.source(time.time_ns() / 1e9) == "track", 2.0)
        # half power: at full tread speed scrubbing treads cannot steer a 15 cm circle
        (rep,) = ask(s, "r1", "mission", MissionCommand(mission="circle", params={"radius_m": 0.15},
                                                        power=0.5, control="closed"))
        assert rep.ok, rep.error
        assert rep.detail["start_pose"][:2] == pytest.approx(world.pose(0)[:2], abs=0.02)
        assert wait_for(lambda: h.runner is None, 10.0)
        res = h.last_result
        assert res["status"] == "finished"
        # (the bench measures ~0.3 cm in simulated time; here the world runs in a thread on a loaded machine)
        assert res["path_error_tracks"]["mean_m"] < 0.02 and res["path_error_tracks"]["coverage_m"] < 0.03
        assert res["path_error_odometry"]["mean_m"] < 0.03     # dead reckoning in the same (arena) frame
        # a mission that would leave the arena is refused up front
        (out,) = ask(s, "r1", "mission", MissionCommand(mission="square", params={"side_m": 1.5}, power=0.5))
        assert not out.ok and "leaves the arena" in out.error
    finally:
        stop.set()
        th.join()
    # geofence: a track at the edge stops a running mission
    assert ask(s, "r2", "mission", circle())[0].ok
    assert wait_for(lambda: world.power(1) != (0, 0), 1.0)
    s.put("arena/robots/9", Track(track_id=9, robot="r2", x=0.01, y=1.2, yaw=0.0).encode())
    h2 = lab["bridge"].handles["r2"]
    assert wait_for(lambda: h2.runner is None and world.power(1) == (0, 0), 1.0)
    assert h2.last_result["status"].startswith("aborted: geofence")


def test_cli_client(lab):
    base = [sys.executable, "-m", "robot_bridge"]
    z = ["-m", "peer", "-e", lab["endpoint"], "--timeout", "3"]
    r = subprocess.run(base + ["mission", "r2", "square", "--side", "0.3", "--power", "50", *z],
                       capture_output=True, text=True, timeout=30)
    assert r.returncode == 0, r.stderr
    assert "r2: mission ok" in r.stdout and "mission_id=" in r.stdout
    r = subprocess.run(base + ["stop", "all", *z], capture_output=True, text=True, timeout=30)
    assert r.returncode == 0 and "r1: stop ok" in r.stdout and "r2: stop ok" in r.stdout
    # --start-pose (mission only) lets a closed loop start before any track came
    r = subprocess.run(base + ["mission", "r2", "circle", "--radius", "0.1", "--control", "closed",
                               "--start-pose", "0.5,1.2,0", *z], capture_output=True, text=True, timeout=30)
    assert r.returncode == 0 and "r2: mission ok" in r.stdout and "start_pose=[0.5, 1.2, 0.0]" in r.stdout, r.stderr
    r = subprocess.run(base + ["stop", "r2", *z], capture_output=True, text=True, timeout=30)
    assert r.returncode == 0 and "r2: stop ok" in r.stdout
    r = subprocess.run(base + ["stop", "nobody", *z[:4], "--timeout", "1"], capture_output=True, text=True, timeout=30)
    assert r.returncode == 1 and "no bridge answered for robot 'nobody'" in r.stderr and "Traceback" not in r.stderr
    r = subprocess.run(base + ["mission", "r1", "circle", "--power", "150", *z], capture_output=True, text=True,
                       timeout=30)
    assert r.returncode == 2 and "--power is a percentage" in r.stderr
    r = subprocess.run(base + ["mission", "r1", "circle", "--radius", "-1", *z], capture_output=True, text=True,
                       timeout=30)
    assert r.returncode == 1 and "REFUSED: bad parameter" in r.stdout


def test_losing_the_zenoh_router_stops_the_robots(tmp_path):
    port = free_port()
    router = subprocess.Popen([sys.executable, "-m", "arena", "router", "-l", f"tcp/127.0.0.1:{port}"],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert "listening" in router.stdout.readline()
        with running_world() as world, RobotEmulatorServer(world, 0) as emu, \
                open_session(ZenohSettings(mode="client", connect=[f"tcp/127.0.0.1:{port}"])) as session:
            with Bridge(session, [RobotSetup("r1", emu.url)], BridgeOptions(log_dir=str(tmp_path)),
                        watch_router=True) as bridge:
                h = bridge.handles["r1"]
                assert h.link.wait_connected(3)
                assert bridge.execute("r1", "mission", circle(params={"laps": 5}).encode()).ok
                assert wait_for(lambda: world.power(0) != (0, 0), 1.0)
                time.sleep(0.5)
                assert h.runner is not None            # a healthy router does not stop anything
                router.kill()
                router.wait(5)
                assert wait_for(lambda: h.runner is None and world.power(0) == (0, 0), 3.0)
                assert h.last_result["status"] == "aborted: Zenoh router lost"
    finally:
        if router.poll() is None:
            router.kill()
            router.wait()


def test_missions_start_together_at_start_ns(lab):
    s, world = lab["session"], lab["world"]
    start_ns = time.time_ns() + int(0.6e9)
    replies = ask(s, "all", "mission", circle(start_ns=start_ns))
    assert [r.ok for r in replies] == [True, True]
    moved = {}
    deadline = time.monotonic() + 2.0
    while len(moved) < 2 and time.monotonic() < deadline:
        for i in (0, 1):
            if i not in moved and world.power(i) != (0, 0):
                moved[i] = time.time_ns()
        time.sleep(0.001)
    assert len(moved) == 2
    assert all(m >= start_ns for m in moved.values())           # nobody jumped the gun
    assert abs(moved[0] - moved[1]) < 0.05e9                     # together, within a control period or two
    assert max(moved.values()) - start_ns < 0.1e9
    assert lab["bridge"].handles["r1"].mission_log is not None


def test_a_start_far_ahead_is_refused_and_the_robot_stays_free(lab):
    """A red team's mission with ``start_ns = 2**63 - 1`` was accepted: the robot stayed busy
    (for 292 years) until stopped. A start more than 600 s ahead is a bad parameter."""
    s, world = lab["session"], lab["world"]
    replies = ask(s, "r1", "mission", circle(start_ns=2**63 - 1))
    assert [r.ok for r in replies] == [False]
    assert "start_ns is" in replies[0].error and "at most 600 s ahead" in replies[0].error
    assert lab["bridge"].handles["r1"].runner is None
    later = time.time_ns() + int(599e9)              # 10 minutes ahead is still a start together
    assert lab["bridge"].handles["r1"].check(circle(start_ns=later)) is None


def test_shutdown_stops_every_robot_before_ending_any_mission_or_closing_any_link(lab):
    # closing a link joins its reader and ending a mission writes its log; stopping robot by
    # robot left the last one driving for 0.35 s per robot (over 1 s under load). All robots
    # get STOP first, then the missions end, then the links close.
    # (Checked on the order of calls, not on a clock, so the test cannot flake under load.)
    s, world, bridge = lab["session"], lab["world"], lab["bridge"]
    e1, _ = lab["emus"]
    assert all(r.ok for r in ask(s, "all", "mission", circle(params={"laps": 3})))
    assert wait_for(lambda: world.power(0) != (0, 0) and world.power(1) != (0, 0), 1.0)
    order = []                            # what the bridge did, in order, on the real links
    for name, h in bridge.handles.items():
        def spy(method, what, name=name):
            def call(*a, **k):
                order.append((what, name))
                return method(*a, **k)
            return call
        h.link.stop_motors = spy(h.link.stop_motors, "stop")
        h.link.set_motors = spy(h.link.set_motors, "motors")
        h.link.close = spy(h.link.close, "close")
        h.mission_log.close = spy(h.mission_log.close, "log")   # ending a mission: ~0.4 s each
    bridge.close()
    assert world.power(0) == (0, 0) and world.power(1) == (0, 0)
    assert not e1.connected
    for first in ("log", "close"):     # every robot got STOP before any mission ended or link closed
        i = next(i for i, (what, _) in enumerate(order) if what == first)
        assert {n for what, n in order[:i] if what == "stop"} == {"r1", "r2"}, (first, order)
    assert sorted(n for what, n in order if what == "log") == ["r1", "r2"], order
    # and once a robot got STOP, its mission's control steps commanded no motors any more
    for name in ("r1", "r2"):
        mine = [what for what, n in order if n == name]
        assert "motors" not in mine[mine.index("stop"):], (name, order)


@pytest.mark.parametrize("key", ["arena/cmd/**", "arena/cmd/*/x", "arena/cmd/*/stop", "arena/cmd/r1",
                                 "arena/cmd/r1/stop/now", "arena/cmd/r1/dance", "arena/**"])
def test_malformed_command_keys_get_an_error_reply_and_the_bridge_keeps_answering(lab, key):
    s, world = lab["session"], lab["world"]
    replies = list(s.get(key, timeout=3.0, consolidation=zenoh.ConsolidationMode.NONE))
    assert len(replies) == 1 and replies[0].ok is None, [(r.ok, r.err) for r in replies]
    text = replies[0].err.payload.to_string()
    assert text.startswith(f"{key!r} is not a command key ("), text
    assert "arena/cmd/<robot>/<verb>" in text and "'all'" in text and "mission, stop, estop, clear, led" in text
    assert lab["bridge"].handles["r1"].runner is None and world.power(0) == (0, 0)   # nothing was carried out
    (rep,) = ask(s, "r1", "mission", circle())
    assert rep.ok, rep.error
    assert [r.ok for r in ask(s, "all", "stop")] == [True, True]

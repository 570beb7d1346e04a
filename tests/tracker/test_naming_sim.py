"""Robot identity without the webcam, on the simulator: the LiveTracker names every track from
the robots' emulated telemetry (encoders, gyro) alone, through the fleet tracker's set_robot_name."""

from __future__ import annotations

import math

import numpy as np
import pytest

from arena.codec import encode
from arena.messages import EventWindow, Telemetry
from tests.tracker.synth import Counts

SENSOR_TO_HOST_NS = 1_700_000_000_000_000_000   # host epoch ns of sensor time 0
ROBOT_CLOCK_US = (123_456, 9_876_543, 55_555)   # each robot's clock at sensor time 0, µs


@pytest.fixture(scope="module")
def sim_run():
    """3 robots driving squares (zero-point turns, seeded pauses) for 4 s: 10 ms event windows and
    50 Hz telemetry per robot (tread speeds from encoder counts, the IMU's gyro), as the bridge
    would publish them, arriving 2-40 ms late, in order."""
    from simulator.autopilot import Autopilot, make_plans
    from simulator.scenarios import Scenario
    from simulator.simulation import Simulation
    from simulator.world import World

    sc = Scenario(n_robots=3, pattern="square", duration_s=4.0, seed=5)
    specs = sc.robot_specs()
    world = World(specs, arena_m=sc.arena_m, lighting=sc.lighting, seed=sc.seed)
    camera = sc.camera()
    pilot = Autopilot(world, make_plans("square", 3, sc.arena_m, sc.duration_s, sc.stagger_s), sc.power)
    sim = Simulation(world, camera, None, pilot, seed=sc.seed + 1)
    rng = np.random.default_rng(1)
    mpc = [math.pi * s.sprocket_diameter_m / s.counts_per_rev for s in specs]
    prev = [None] * len(specs)
    arrived = [0] * len(specs)
    windows, telemetry, truth = [], [], []
    steps = 10_000 // sim.step_us
    for k in range(int(sc.duration_s * 100)):
        ev, _, tr = sim.run(steps)   # events in (t - 10 ms, t]: the window ends 1 µs after t
        t_us = sim.t_us
        windows.append(EventWindow(camera="c0", seq=k, t_start_us=t_us - 9_999, t_end_us=t_us + 1, width=camera.width,
                                   height=camera.height, count=ev.size, codec="planes-zstd/1", data=encode(ev),
                                   publish_ns=SENSOR_TO_HOST_NS + t_us * 1000,
                                   sensor_to_host_ns=SENSOR_TO_HOST_NS))
        truth.append(tr)
        if k % 2:
            continue
        for i, spec in enumerate(specs):
            enc = world.encoder_counts(i)
            gyro = world.imu(i)["gyro"]
            if prev[i] is not None:
                dt = (t_us - prev[i][0]) / 1e6
                sl, sr = ((enc[0] - prev[i][1]) * mpc[i] / dt, (enc[1] - prev[i][2]) * mpc[i] / dt)
                arr = max(arrived[i], SENSOR_TO_HOST_NS + t_us * 1000 + int(rng.uniform(2e6, 40e6)))
                arrived[i] = arr
                telemetry.append(Telemetry(robot=spec.name, seq=k, robot_time_us=t_us + ROBOT_CLOCK_US[i],
                                           host_time_ns=arr, enc_left=enc[0], enc_right=enc[1],
                                           speed_left=sl, speed_right=sr, gyro=tuple(float(g) for g in gyro)))
            prev[i] = (t_us, enc[0], enc[1])
    return {"windows": windows, "telemetry": telemetry, "truth": np.concatenate(truth),
            "names": [s.name for s in specs], "calibration": camera.calibration()}


def run_live(sim_run, *, with_telemetry=True, webcam_lag_s=None):
    from tracker.calibration import Calibration
    from tracker.pipeline import Pipeline
    from tracker.service import LiveTracker

    svc = Counts()
    live = LiveTracker(Pipeline(Calibration.from_dict(sim_run["calibration"])), "c0", svc=svc)
    tel = sorted(sim_run["telemetry"], key=lambda m: m.host_time_ns)
    j = 0
    named_at: dict[str, float] = {}
    outs = []
    for win in sim_run["windows"]:
        now = win.sensor_to_host_ns + win.t_end_us * 1000 + 5_000_000   # the tracker handles it 5 ms later
        while with_telemetry and j < len(tel) and tel[j].host_time_ns <= now:
            live.observe_telemetry(tel[j])
            j += 1
        if webcam_lag_s is not None and win.seq % 3 == 0:   # a 33 Hz webcam, its poses arriving late
            t_cap = win.t_end_us - int(webcam_lag_s * 1e6)
            for name in sim_run["names"]:
                if t_cap > 0:
                    x, y = robot_at(sim_run["truth"], sim_run["names"], name, t_cap)
                    live.observe_groundtruth(name, x, y, SENSOR_TO_HOST_NS // 1000 + t_cap)
        out = live.handle(win.encode(), now)
        outs.append(out)
        for _, m, _ in out:
            if m.robot is not None:
                named_at.setdefault(m.robot, win.t_end_us / 1e6)
    return live, svc, outs, named_at


def robot_at(truth, names, robot: str, t_us: int):
    rows = truth[truth["robot"] == names.index(robot)]
    k = int(np.clip(np.searchsorted(rows["t_us"], t_us), 0, len(rows) - 1))
    return float(rows["x_m"][k]), float(rows["y_m"][k])


def test_every_track_is_named_from_telemetry_alone_within_a_few_seconds(sim_run):
    live, svc, outs, named_at = run_live(sim_run)
    names = sim_run["names"]
    assert set(named_at) == set(names), named_at
    for i, name in enumerate(names):   # robot i starts moving at 0.2 + 0.3 i s
        assert named_at[name] - (0.2 + 0.3 * i) <= 3.0, named_at
    assert svc.c.get("names_from_telemetry", 0) >= len(names)
    assert svc.c.get("names_from_groundtruth", 0) == 0
    # every named track is where its robot is, in every window after naming (no wrong name)
    wrong = 0
    for out in outs:
        seen = [m.robot for _, m, _ in out if m.robot is not None]
        assert len(seen) == len(set(seen)), "two tracks with one name"
        for _, m, _ in out:
            if m.robot is not None and m.state != "tentative":
                x, y = robot_at(sim_run["truth"], names, m.robot, m.stamp_us)
                wrong += math.hypot(m.x - x, m.y - y) > 0.1
    assert wrong == 0
    last = {m.robot for _, m, _ in next(o for o in reversed(outs) if o)}
    assert set(names) <= last


def test_without_telemetry_no_track_is_named(sim_run):
    _, svc, _, named_at = run_live(sim_run, with_telemetry=False)
    assert named_at == {} and svc.c.get("names_from_telemetry", 0) == 0


def test_a_lagging_webcam_names_tracks_by_the_stamp_of_its_poses(sim_run):
    """Webcam poses arrive 0.6 s after capture (a loaded host): matched to each track's pose at
    the capture stamp, they name every track, each the right one (the failure by arrival on
    continuous motion: tests/tracker/test_live_naming.py)."""
    _, svc, outs, named_at = run_live(sim_run, with_telemetry=False, webcam_lag_s=0.6)
    assert set(named_at) == set(sim_run["names"]), named_at
    assert svc.c.get("names_from_groundtruth", 0) >= 3 and svc.c.get("names_from_telemetry", 0) == 0
    for out in outs:
        for _, m, _ in out:
            if m.robot is not None:
                x, y = robot_at(sim_run["truth"], sim_run["names"], m.robot, m.stamp_us)
                assert math.hypot(m.x - x, m.y - y) < 0.1

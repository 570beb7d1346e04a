"""Control: odometry, wheel PID, pose fusion with latency, path error, paper vs closed loop
against the simulator's physics (simulated time, via the path benchmark's harness)."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest

from robot_bridge.control import PoseEstimator, WheelPID, path_error
from robot_bridge.odometry import (Odometry, WheelGeometry, calibrate_sprocket_diameter, calibrate_track_width,
                                   wrap_angle)

BENCH = Path(__file__).resolve().parents[2] / "bench" / "bench_bridge_paths.py"


def load_bench():
    spec = importlib.util.spec_from_file_location("bench_bridge_paths", BENCH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_odometry_straight_and_spin():
    g = WheelGeometry()
    odo = Odometry(g, (0.5, 0.5, 0.0))
    odo.update(0, 0)
    n = int(round(0.3 / g.m_per_count))
    x, y, yaw = odo.update(n, n)
    assert (x, y, yaw) == pytest.approx((0.8, 0.5, 0.0), abs=1e-4)
    quarter = int(round(math.pi / 2 * g.track_width_m / 2 / g.m_per_count))
    _, _, yaw = odo.update(n - quarter, n + quarter)
    assert yaw == pytest.approx(math.pi / 2, abs=1e-3)
    assert calibrate_track_width(-quarter, quarter, math.pi / 2 / 1.2, g) == pytest.approx(0.09 * 1.2, rel=1e-3)
    assert calibrate_sprocket_diameter(n, n, 0.3 * 0.98, g) == pytest.approx(0.038 * 0.98, rel=1e-3)  # 2 % slip
    with pytest.raises(ValueError, match="at least 30 degrees"):
        calibrate_track_width(0, 10, 0.1, g)


def test_wheel_pid_feedforward_and_integral():
    pid = WheelPID(0.46)
    assert pid.update((0.23, 0.23), (0.23, 0.23), 0.01) == (200, 200)
    for _ in range(50):
        left, right = pid.update((0.23, -0.23), (0.20, -0.20), 0.01)
    assert left > 200 + 0.03 * 500 and right < -200 - 0.03 * 500     # integral pushes on
    assert pid.update((0.0, 0.0), (0.1, 0.1), 0.01) == (0, 0)
    assert pid.update((1.0, -1.0), (0.0, 0.0), 0.01) == (400, -400)   # clipped


def test_pose_estimator_compensates_track_latency():
    est = PoseEstimator(pos_gain=1.0, along_gain=1.0, yaw_gain=1.0)
    # odometry says the robot drives +x at 0.2 m/s but reports 10 % short (slip)
    for k in range(101):
        t = k * 0.01
        est.add_odometry(t, (0.9 * 0.2 * t, 0.0, 0.0))
    # a track of where the robot truly was 100 ms ago arrives now (t = 1.0)
    est.add_track(0.9, 0.2 * 0.9 + 0.5, 0.1, 0.0)
    x, y, _ = est.pose()
    assert x == pytest.approx(0.2 * 0.9 + 0.5 + 0.9 * 0.2 * 0.1, abs=1e-6)   # propagated by odometry
    assert y == pytest.approx(0.1)
    assert est.source(1.0) == "track" and est.source(2.0) == "odometry"
    # a heading flipped by 180 degrees corrects the position only
    est.add_track(1.0, 0.7, 0.1, math.pi)
    assert abs(est.pose()[2]) < 1e-9


def test_path_error_of_a_shifted_circle():
    a = np.linspace(0, 2 * np.pi, 2000)
    cmd = np.c_[np.cos(a), np.sin(a)] * 0.3
    err = path_error(cmd + [0.0, 0.0], cmd)
    assert err.mean_m < 1e-3
    bigger = np.c_[np.cos(a), np.sin(a)] * 0.32
    err = path_error(bigger, cmd)
    assert err.mean_m == pytest.approx(0.02, abs=1e-3) and err.max_m == pytest.approx(0.02, abs=1e-3)
    half = bigger[: len(a) // 2]
    assert path_error(half, cmd).coverage_m > 0.1   # half a circle does not cover the shape


@pytest.mark.parametrize("pattern,params", [("circle", {"radius_m": 0.3}), ("square", {"side_m": 0.6})])
def test_closed_loop_beats_paper_mode_5x_in_the_simulator(pattern, params):
    bench = load_bench()
    paper, _, mission, _ = bench.simulate(pattern, params, 0.5, "paper", seed=2)
    closed, traced, _, t = bench.simulate(pattern, params, 0.5, "closed", seed=2)
    assert paper.mean_m > 0.02                       # the paper's imperfect shapes
    assert closed.mean_m * 5 <= paper.mean_m
    assert closed.coverage_m < 0.02                  # and the whole shape was traced
    assert t < 1.5 * mission.length_m / mission.speed_mps + 8


def test_gyro_heading_beats_skidding_treads_and_learns_bias():
    g = WheelGeometry()
    odo = Odometry(g, (0.0, 0.0, 0.0))
    bias = 0.02
    t = 0.0
    odo.update(0, 0, bias, t)
    for _ in range(200):          # 2 s standing still: the gyro reads only its bias
        t += 0.01
        odo.update(0, 0, bias, t)
    assert odo.gyro_bias == pytest.approx(bias, rel=0.05)
    assert abs(odo.yaw) < 0.02
    n = 400
    t += 0.01
    odo.update(n, n, 2.0, t)       # driving and turning fast ...
    t += 0.01
    odo.update(n, n, 2.0, t)       # ... a sample with stalled counts is not "standing still"
    assert odo.gyro_bias == pytest.approx(bias, rel=0.05)
    odo.reset((0.0, 0.0, 0.0))
    quarter = int(round(math.pi / 2 * g.track_width_m / 2 / g.m_per_count))
    for k in range(1, 101):       # treads say 90 degrees, the robot skids and turns 70
        t += 0.01
        odo.update(n - quarter * k // 100, n + quarter * k // 100, math.radians(70) + bias, t)
    assert odo.yaw == pytest.approx(math.radians(70), abs=math.radians(1.5))


def test_estimator_trusts_tracks_across_but_not_along_the_motion_and_drops_outliers():
    est = PoseEstimator()
    for k in range(101):
        est.add_odometry(k * 0.01, (0.2 * k * 0.01, 0.0, 0.0))   # driving +x
    est.set_pose((0.2, 0.0, 0.0))
    for _ in range(30):   # tracks 3 cm behind (lag) and 2 cm to the left
        est.add_track(1.0, 0.17, 0.02, None)
    x, y, _ = est.pose()
    assert y == pytest.approx(0.02, abs=1e-3)        # cross-track: follows the tracks
    assert x > 0.2 - 0.03 * 0.5                     # along-track: mostly odometry
    n = est.tracks_rejected
    assert not est.add_track(1.0, 0.6, 0.02, None)   # 40 cm away: an outlier
    assert est.tracks_rejected == n + 1


@pytest.mark.slow
def test_closed_loop_on_the_real_tracker_fed_by_the_simulated_event_camera():
    bench = load_bench()
    params = {"radius_m": 0.15}
    # half power: a tracked robot's scrubbing treads leave no room to steer a 15 cm circle at full
    # tread speed (the outer tread would need more than full power)
    paper = bench.simulate("circle", params, 0.5, "paper", seed=4)[0]
    closed, _, _, _ = bench.simulate("circle", params, 0.5, "closed", seed=4, tracker=True)
    assert closed.mean_m < 0.015 and closed.coverage_m < 0.02
    assert closed.mean_m * 5 <= paper.mean_m


def test_wrong_initial_heading_relocks_on_the_course_of_the_tracks():
    est = PoseEstimator()
    est.add_odometry(0.0, (0.0, 0.0, 0.0))
    est.set_pose((0.5, 0.5, math.pi / 2))      # told +y, but the robot drives +x
    for k in range(1, 301):
        t = k * 0.01
        est.add_odometry(t, (0.2 * t, 0.0, 0.0))
        if k % 2 == 0:
            est.add_track(t, 0.5 + 0.2 * t, 0.5, math.pi / 2)   # a tracker heading 90 degrees off, too
    assert est.heading_relocks >= 1
    assert abs(wrap_angle(est.pose()[2])) < math.radians(10)

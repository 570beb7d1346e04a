"""World physics: speeds from motor power, motor lag, encoders, walls, IMU, determinism."""

from __future__ import annotations

import math

import numpy as np
import pytest

from simulator.world import RobotSpec, World


def _drive(world: World, seconds: float, dt: float = 0.001) -> None:
    for _ in range(int(round(seconds / dt))):
        world.step(dt)


def _one(start=(0.3, 0.9, 0.0), seed=0) -> World:
    return World([RobotSpec("r", (20, 20, 20), start=start)], seed=seed)


@pytest.mark.parametrize("power,speed", [(400, 0.46), (200, 0.23)])
def test_straight_speed_follows_power(power, speed):
    w = _one()
    w.set_power(0, power, power)
    _drive(w, 1.0)
    vx, vy, _ = w.velocity(0)
    assert math.hypot(vx, vy) == pytest.approx(speed, rel=0.08)


def test_motor_lag_is_first_order_tens_of_ms():
    w = _one()
    w.set_power(0, 400, 400)
    _drive(w, 0.02)
    early = math.hypot(*w.velocity(0)[:2])
    _drive(w, 0.5)
    final = math.hypot(*w.velocity(0)[:2])
    assert 0.1 * final < early < 0.5 * final


def test_side_mismatch_curves_a_straight_command():
    w = _one(start=(0.2, 0.9, 0.0), seed=3)
    w.set_power(0, 300, 300)
    _drive(w, 2.0)
    assert abs(w.pose(0)[2]) > math.radians(0.5)     # not perfectly straight


def test_encoders_count_tread_travel_1807_per_rev():
    w = _one()
    w.set_power(0, 200, 200)
    _drive(w, 2.0)
    x, _, _ = w.pose(0)
    left, right = w.encoder_counts(0)
    expected = (x - 0.3) / (math.pi * 0.038) * 1807
    assert left == pytest.approx(expected, rel=0.1) and right == pytest.approx(expected, rel=0.1)


@pytest.mark.parametrize("spin_dps,min_turn_rad", [(None, 2.0), (150.0, 1.0)])
def test_zero_point_turn_slips_so_encoders_overestimate_rotation(spin_dps, min_turn_rad):
    # 1 s at half power: ~200 deg/s without tread scrubbing, ~75 deg/s with (the default)
    w = World([RobotSpec("r", (20, 20, 20), start=(0.9, 0.9, 0.0), spin_dps_full=spin_dps)])
    w.set_power(0, -200, 200)
    yaws = []
    for _ in range(1000):
        w.step(0.001)
        yaws.append(w.pose(0)[2])
    turned_true = np.unwrap(yaws)[-1]
    left, right = w.encoder_counts(0)
    assert left < 0 < right
    turned_enc = (right - left) / 1807 * math.pi * 0.038 / 0.09   # ideal differential drive
    x, y, _ = w.pose(0)
    assert math.hypot(x - 0.9, y - 0.9) < 0.03     # turned on the spot
    assert turned_true > min_turn_rad
    assert turned_enc > 1.1 * turned_true          # tracks skid: true rotation is smaller


def test_walls_keep_the_robot_inside():
    w = _one(start=(1.6, 0.9, 0.0))
    w.set_power(0, 400, 400)
    _drive(w, 3.0)
    x, y, _ = w.pose(0)
    half = 0.5 * math.hypot(0.1, 0.1)
    assert x <= 1.83 - half + 1e-9 and 0 < y < 1.83
    assert abs(w.velocity(0)[0]) < 1e-6           # pushing against the wall


def test_imu_gravity_gyro_and_noise():
    w = _one()
    rest = np.array([w.imu(0)["accel"] for _ in range(200)])
    assert rest[:, 2].mean() == pytest.approx(9.81, abs=0.2)
    assert rest[:, 2].std() > 0.005                # noisy
    w.set_power(0, -200, 200)
    _drive(w, 0.5)
    gz = np.mean([w.imu(0)["gyro"][2] for _ in range(100)])
    assert gz == pytest.approx(w.velocity(0)[2], abs=0.05)
    assert np.linalg.norm(w.imu(0)["mag"]) == pytest.approx(48.3, abs=12)


def test_battery_drains_under_load():
    w = _one()
    idle = w.battery_mv(0)
    w.set_power(0, 400, 400)
    _drive(w, 2.0)
    assert w.battery_mv(0) < idle


def test_same_seed_same_motion_and_different_seed_differs():
    def run(seed):
        w = World([RobotSpec("a", (0, 0, 0), start=(0.5, 0.5, 0.3)),
                   RobotSpec("b", (255, 255, 0), start=(1.2, 1.2, 1.0))], seed=seed)
        w.set_power(0, 300, 250)
        w.set_power(1, -100, 300)
        _drive(w, 1.0)
        return w.poses(), w.encoder_counts(1), w.imu(0)["gyro"]
    a, b, c = run(5), run(5), run(6)
    assert np.array_equal(a[0], b[0]) and a[1] == b[1] and np.array_equal(a[2], b[2])
    assert not np.array_equal(a[0], c[0])


def test_bad_input_raises_clear_errors():
    with pytest.raises(ValueError, match="lighting"):
        World([], lighting="disco")
    w = _one()
    with pytest.raises(IndexError, match="out of range"):
        w.pose(3)
    w.set_power(0, 9999, -9999)
    assert w.power(0) == (400, -400)

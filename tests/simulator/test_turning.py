"""Turning physics of tracked robots: tread scrubbing (slow zero-point turns, proportional to
power; straight driving unchanged; encoders see the treads, the gyro the body), the switch
back to the old kinematics, and the autopilot's pauses around zero-point turns."""

from __future__ import annotations

import math

import numpy as np
import pytest

from simulator.autopilot import Autopilot, make_plans
from simulator.world import RobotSpec, World

STARTS = [(0.4, 0.4, 0.0), (1.3, 0.5, 1.0), (0.6, 1.3, -2.0)]


def _world(spin_dps, seed=0, n=3):
    return World([RobotSpec(f"r{i}", (20, 20, 20), start=STARTS[i], spin_dps_full=spin_dps)
                  for i in range(n)], seed=seed)


def _settle(w: World, left: int, right: int, seconds: float = 0.8) -> np.ndarray:
    """Command every robot (left, right) for ``seconds``; velocities (vx, vy, omega) at the end."""
    for i in range(len(w.robots)):
        w.set_power(i, left, right)
    for _ in range(int(round(seconds / 0.002))):
        w.step(0.002)
    return w.velocities()


@pytest.mark.parametrize("power,want_dps", [(400, 150.0), (200, 75.0)])
def test_zero_point_turn_settles_at_150_dps_full_and_75_half_power(power, want_dps):
    for seed in (0, 1):
        w = _world(150.0, seed)
        rates = np.degrees(_settle(w, -power, power)[:, 2])
        # per-side gain mismatch (2.5 %) and tread noise remain
        assert rates == pytest.approx(np.full(3, want_dps), rel=0.12), (seed, rates)
        speeds = np.hypot(*_settle(w, -power, power, 0.1)[:, :2].T)
        assert speeds.max() < 0.03                     # on the spot


def test_scrubbing_slows_turns_but_not_straight_driving_and_arcs_lie_between():
    for left, right in ((400, 400), (200, 200)):
        v_new = np.hypot(*_settle(_world(150.0), left, right)[:, :2].T)
        v_old = np.hypot(*_settle(_world(None), left, right)[:, :2].T)
        assert v_new == pytest.approx(v_old, rel=0.01)
        assert v_new == pytest.approx(np.full(3, left / 400 * 0.46), rel=0.08)
    spin_new = _settle(_world(150.0), -400, 400)[:, 2]
    spin_old = _settle(_world(None), -400, 400)[:, 2]
    assert np.all(spin_new < 0.5 * spin_old)
    # an arc (one tread faster): its forward speed stays the mean tread speed, its yaw rate
    # drops below the unscrubbed one, and it turns slower than a spin
    arc_new, arc_old = _settle(_world(150.0), 200, 400), _settle(_world(None), 200, 400)
    assert np.hypot(*arc_new[:, :2].T) == pytest.approx(np.hypot(*arc_old[:, :2].T), rel=0.03)
    assert np.all(0 < arc_new[:, 2]) and np.all(arc_new[:, 2] < 0.75 * arc_old[:, 2])
    assert np.all(arc_new[:, 2] < spin_new)


def test_gyro_reads_the_slow_body_rate_and_encoders_the_skidding_treads():
    w = _world(150.0, n=1)
    _settle(w, -400, 400, 0.6)
    c0, t0 = w.encoder_counts(0), w.t
    yaws = [w.pose(0)[2]]
    gyro = []
    for _ in range(250):
        w.step(0.002)
        yaws.append(w.pose(0)[2])
        gyro.append(w.imu(0)["gyro"][2])
    dt = w.t - t0
    true_rate = np.unwrap(yaws)[-1] - yaws[0]
    true_rate /= dt
    assert math.degrees(true_rate) == pytest.approx(150, rel=0.12)
    assert np.mean(gyro) == pytest.approx(true_rate, abs=0.05)
    c1 = w.encoder_counts(0)
    m_per_count = math.pi * 0.038 / 1807
    enc_rate = ((c1[1] - c0[1]) - (c1[0] - c0[0])) * m_per_count / 0.09 / dt
    # treads skid: the encoders (sprockets) report 15-70 % more turning than the body does
    assert 1.15 * true_rate < enc_rate < 1.7 * true_rate


def test_spin_dps_none_is_the_old_kinematics_exactly():
    def run(spin):
        w = World([RobotSpec("r", (20, 20, 20), start=(0.9, 0.9, 0.0), spin_dps_full=spin)], seed=4)
        w.set_power(0, -300, 320)
        for _ in range(500):
            w.step(0.002)
        w.set_power(0, 250, 100)
        for _ in range(250):
            w.step(0.002)
        return w.pose(0), w.encoder_counts(0)
    # the same commands on the world before tread scrubbing existed (computed with it)
    pose, counts = run(None)
    assert pose == pytest.approx((0.9209060505211624, 0.8324110233127233, -1.5975275791660593), abs=1e-9)
    assert counts == (-3415, 6321)
    assert run(150.0)[0] != pytest.approx(pose, abs=1e-3)
    with pytest.raises(ValueError, match="spin_dps_full"):
        World([RobotSpec("r", (0, 0, 0), spin_dps_full=0.0)])


def _drive_square(power: float, seconds: float, seed: int = 0, pauses: bool = True, spin=150.0):
    plans = make_plans("square", 1, 1.83, seconds)
    w = World([RobotSpec("r", (20, 20, 20), start=plans[0].start_pose(), spin_dps_full=spin)],
              seed=seed)
    pilot = Autopilot(w, plans, power, pauses=pauses)
    t, yaw, xy, cmd = [], [], [], []
    for _ in range(int(round(seconds / 0.002))):
        pilot.update(w.t)
        w.step(0.002)
        x, y, a = w.pose(0)
        t.append(w.t)
        yaw.append(a)
        xy.append((x, y))
        cmd.append(w.power(0))
    return np.array(t), np.unwrap(yaw), np.array(xy), np.array(cmd)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(first, last) index of each run of True."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(int), [0]])))
    return [(int(a), int(b) - 1) for a, b in zip(edges[::2], edges[1::2])]


@pytest.fixture(scope="module")
def squares():
    return {(seed, pauses): _drive_square(1.0, 4.0, seed, pauses) for seed in (0, 1) for pauses in (True, False)}


def test_autopilot_pauses_before_and_after_each_zero_point_turn(squares):
    gaps = {}
    for (seed, pauses), (t, _, _, cmd) in squares.items():
        turning = cmd[:, 0] * cmd[:, 1] < 0
        still = (cmd[:, 0] == 0) & (cmd[:, 1] == 0)
        turns = _runs(turning)
        assert turns, (seed, pauses)
        out = []
        for a, b in turns:
            before = _runs(still[:a])[-1]
            assert before[1] == a - 1                 # stands still right before the turn ...
            out.append(t[a] - t[before[0]])
            if b + 1 < len(t) - 1 and still[b + 1]:
                after = next(r for r in _runs(still) if r[0] == b + 1)
                if after[1] < len(t) - 1:             # ... and right after it
                    out.append(t[after[1] + 1] - t[b + 1])
        gaps[seed, pauses] = out
        if pauses:
            assert len(out) >= 2 and all(0.19 <= g <= 0.43 for g in out), (seed, out)
        else:
            assert all(g < 0.1 for g in out), (seed, out)
    assert gaps[0, True] != gaps[1, True]             # jittered by the seed


def test_square_turns_end_on_the_side_heading_without_overshoot():
    for seed in (0, 1):
        for power, rate in ((1.0, 150.0), (0.5, 75.0)):
            t, yaw, xy, cmd = _drive_square(power, 6.0 if power == 1.0 else 10.0, seed)
            w = np.gradient(yaw, t)
            turning = cmd[:, 0] * cmd[:, 1] < 0
            turns = [r for r in _runs(turning) if r[1] - r[0] > 50 and r[1] + 150 < len(t)]
            assert len(turns) >= 2
            for a, b in turns:
                seg = w[a:b + 60]                      # the turn and its coasting
                assert np.degrees(np.abs(seg).max()) == pytest.approx(rate, rel=0.12)
                assert not (seg < -0.1).any()          # counter-clockwise square: never back
                settled = yaw[min(b + 100, len(yaw) - 1)]
                err = (settled + math.pi / 4) % (math.pi / 2) - math.pi / 4
                assert abs(math.degrees(err)) < 3.5, (seed, power, math.degrees(err))
            # the sides between the turns are whole (0.6 m less the corner approach)
            a0 = turns[0][1]
            b0 = turns[1][0]
            assert np.hypot(*(xy[b0] - xy[a0])) == pytest.approx(0.6, abs=0.03)


def test_autopilot_keeps_the_circle_radius_when_the_treads_scrub():
    plans = make_plans("circle", 1, 1.83, 4.0)
    out = {}
    for spin in (150.0, None):
        w = World([RobotSpec("r", (20, 20, 20), start=plans[0].start_pose(), spin_dps_full=spin)])
        pilot = Autopilot(w, plans, 1.0)
        xy, speed = [], []
        for k in range(2000):
            pilot.update(w.t)
            w.step(0.002)
            if k >= 750:                               # after 1.5 s
                xy.append(w.pose(0)[:2])
                speed.append(math.hypot(*w.velocity(0)[:2]))
        x, y = np.array(xy).T
        d, e, f = np.linalg.lstsq(np.column_stack([x, y, np.ones_like(x)]), -(x**2 + y**2), rcond=None)[0]
        out[spin] = math.sqrt(d**2 / 4 + e**2 / 4 - f), float(np.median(speed))
    assert out[150.0][0] == pytest.approx(0.3, abs=0.01) and out[None][0] == pytest.approx(0.3, abs=0.01)
    # a tight arc at full power scrubs too: the pursuit needs a larger tread-speed difference
    assert out[150.0][1] < 0.85 * out[None][1]

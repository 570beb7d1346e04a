"""Scenarios: the autopilot drives the paper's patterns; recordings carry truth, labels and
calibration; same seed gives the same recording."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from simulator.camera import apply_homography
from simulator.dvs import DvsParams
from arena.formats.tables import write_truth_csv
from simulator.recording import load_recording, save_recording, write_events
from simulator.scenarios import Scenario, generate

SMALL = dict(width=320, height=240)


def speed(tr):
    return np.hypot(tr["vx_mps"], tr["vy_mps"])


def test_circle_radius_speed_and_staggered_starts():
    # without tread scrubbing (spin_dps=None): the circle at nearly full tread speed; the
    # scrubbing robots' slower circle is in test_turning.py
    rec = generate(Scenario(n_robots=2, pattern="circle", power=1.0, duration_s=5.0, spin_dps=None,
                            **SMALL))
    first = rec.first_motion_us()
    assert list(first) == rec.robot_names
    assert 150_000 < first[rec.robot_names[0]] < first[rec.robot_names[1]]
    for i in range(2):
        tr = rec.truth_of(i)
        tr = tr[tr["t_us"] > 2_000_000]
        x, y = tr["x_m"], tr["y_m"]          # algebraic circle fit
        d, e, f = np.linalg.lstsq(np.column_stack([x, y, np.ones_like(x)]), -(x**2 + y**2),
                                  rcond=None)[0]
        radius = np.sqrt(d**2 / 4 + e**2 / 4 - f)
        assert radius == pytest.approx(0.3, abs=0.02)
        assert np.median(speed(tr)) == pytest.approx(0.43, abs=0.06)
    assert np.diff(rec.truth_of(0)["t_us"]).max() <= 5000          # >= 200 Hz


def test_square_has_zero_point_turns_at_corners():
    rec = generate(Scenario(n_robots=1, pattern="square", power=0.5, duration_s=10.0, **SMALL))
    tr = rec.truth_of(0)
    tr = tr[tr["t_us"] > 500_000]
    assert tr["x_m"].max() - tr["x_m"].min() == pytest.approx(0.6, abs=0.06)
    assert tr["y_m"].max() - tr["y_m"].min() == pytest.approx(0.6, abs=0.06)
    yaw_rate = np.diff(np.unwrap(tr["yaw_rad"])) / np.diff(tr["t_us"] * 1e-6)
    turning = np.abs(yaw_rate[1:]) > 1.0
    assert turning.any()
    assert speed(tr)[1:-1][turning].max() < 0.1                   # turning on the spot
    assert speed(tr).max() == pytest.approx(0.23, abs=0.03)        # 50 % power


def test_stopgo_two_robots_stop_for_two_seconds():
    rec = generate(Scenario(n_robots=3, pattern="stopgo", duration_s=6.0, **SMALL))
    for i, should_stop in ((0, True), (1, True), (2, False)):
        tr = rec.truth_of(i)
        late = tr[tr["t_us"] > 1_500_000]
        still = speed(late) < 0.005
        dt = np.diff(late["t_us"]).mean() * 1e-6
        assert (still.sum() * dt > 1.7) == should_stop


def test_cross_paths_meet_at_the_centre():
    rec = generate(Scenario(n_robots=3, pattern="cross", duration_s=6.0, **SMALL))
    for i in range(3):
        tr = rec.truth_of(i)
        d = np.hypot(tr["x_m"] - 0.915, tr["y_m"] - 0.915)
        assert d.min() < 0.05


def test_still_robots_never_move_and_give_only_noise():
    rec = generate(Scenario(n_robots=2, pattern="still", duration_s=1.0, **SMALL))
    assert all(v is None for v in rec.first_motion_us().values())
    assert rec.is_signal.sum() == 0 and len(rec.events) > 0


def test_events_are_sorted_labelled_and_near_the_robots():
    # background at 0.1 Hz/px without leak events, so that most events are the robots'
    rec = generate(Scenario(n_robots=2, pattern="figure8", duration_s=2.0,
                            dvs=DvsParams(noise_rate_hz=0.1, leak_rate_hz=0.0), **SMALL))
    ev, sig = rec.events, rec.is_signal
    assert np.all(np.diff(ev["t"]) >= 0) and len(sig) == len(ev)
    assert 0.5 < sig.mean() < 1.0
    # signal events lie within a robot's size of a robot
    s = ev[sig][::50]
    best = np.full(len(s), np.inf)
    for i in range(2):
        tr = rec.truth_of(i)
        k = np.clip(np.searchsorted(tr["t_us"], s["t"]), 0, len(tr) - 1)
        uv = apply_homography(rec.homography, np.column_stack([tr["x_m"][k], tr["y_m"][k]]))
        best = np.minimum(best, np.hypot(s["x"] - uv[:, 0], s["y"] - uv[:, 1]))
    px_per_m = 0.9 * 240 / 1.83
    assert np.percentile(best, 99) < 0.09 * px_per_m


def test_calibration_points_match_the_homography():
    rec = generate(Scenario(n_robots=1, duration_s=0.2, **SMALL))
    cal = rec.calibration
    assert cal["image_size"] == [320, 240] and len(cal["points"]) >= 8
    px = np.array([p["pixel"] for p in cal["points"]])
    m = np.array([p["arena_m"] for p in cal["points"]])
    assert np.abs(apply_homography(rec.homography, m) - px).max() < 0.01
    # not a perfect axis-aligned square: rotated and keystoned
    c = px[:4]
    assert abs(c[0, 1] - c[1, 1]) > 1.0
    assert abs(np.linalg.norm(c[1] - c[0]) - np.linalg.norm(c[2] - c[3])) > 1.0
    json.dumps(cal)


def test_same_seed_same_recording_other_seed_differs():
    a = generate(Scenario(n_robots=2, pattern="square", duration_s=1.5, seed=4, **SMALL))
    b = generate(Scenario(n_robots=2, pattern="square", duration_s=1.5, seed=4, **SMALL))
    c = generate(Scenario(n_robots=2, pattern="square", duration_s=1.5, seed=5, **SMALL))
    assert np.array_equal(a.events, b.events) and np.array_equal(a.truth, b.truth)
    assert np.array_equal(a.is_signal, b.is_signal)
    assert not np.array_equal(a.events, c.events)


def test_writers_csv_npz_and_truth(tmp_path):
    rec = generate(Scenario(n_robots=2, duration_s=0.5, **SMALL))
    write_events(tmp_path / "e.csv", rec.events, rec.width, rec.height)
    rows = np.loadtxt(tmp_path / "e.csv", delimiter=",", skiprows=1, dtype=np.int64)
    assert (tmp_path / "e.csv").read_text().startswith("x,y,p,t\n")
    assert np.array_equal(rows[:, 3], rec.events["t"]) and np.array_equal(rows[:, 0], rec.events["x"])
    save_recording(rec, tmp_path / "r.npz")
    z = np.load(tmp_path / "r.npz")
    assert np.array_equal(z["events"], rec.events) and np.array_equal(z["truth"], rec.truth)
    assert json.loads(str(z["calibration"])) == rec.calibration
    back = load_recording(tmp_path / "r.npz")
    assert np.array_equal(back.events, rec.events) and back.robot_names == rec.robot_names
    assert back.first_motion_us() == rec.first_motion_us() and back.calibration == rec.calibration
    with pytest.raises(ValueError, match="not a simulator recording"):
        load_recording(tmp_path / "e.csv")
    write_truth_csv(tmp_path / "t.csv", rec.truth, rec.robot_names)
    with open(tmp_path / "t.csv") as f:
        r = list(csv.DictReader(f))
    assert list(r[0]) == ["t_us", "robot", "x_m", "y_m", "yaw_rad", "vx_mps", "vy_mps"]
    assert {x["robot"] for x in r} == set(rec.robot_names) and len(r) == len(rec.truth)
    with pytest.raises(ValueError, match="extension"):
        write_events(tmp_path / "e.txt", rec.events, 320, 240)


def test_bad_scenarios_raise_clear_errors():
    with pytest.raises(ValueError, match="pattern"):
        generate(Scenario(pattern="zigzag"))
    with pytest.raises(ValueError, match="power"):
        generate(Scenario(power=2.0))
    with pytest.raises(ValueError, match="lighting"):
        generate(Scenario(lighting="disco"))


def test_dark_lighting_more_noise_fewer_robot_events():
    full = generate(Scenario(n_robots=1, duration_s=1.5, lighting="full", markers=False, **SMALL))
    dark = generate(Scenario(n_robots=1, duration_s=1.5, lighting="dark", markers=False, **SMALL))
    assert (~dark.is_signal).sum() > 3 * (~full.is_signal).sum()
    assert 0 < dark.is_signal.sum() < full.is_signal.sum()

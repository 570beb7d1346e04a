"""Event physics of the DVS model: polarity of edges, colour density, stillness, noise
rate, thresholds and refractory period. Poses are scripted directly (no autopilot)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from simulator.camera import CeilingCamera
from simulator.dvs import DvsParams, DvsSensor
from simulator.world import RobotSpec

CAM = CeilingCamera(320, 240)
BLACK, YELLOW = (25, 25, 25), (240, 215, 30)


def run_path(poses_fn, seconds, colour=BLACK, params=None, seed=0, marker=None, cam=CAM):
    """Run one robot along ``poses_fn(t_s) -> (x, y, yaw)``; return (events, is_signal, sensor)."""
    robot = RobotSpec("r", colour, marker_id=marker)
    params = params or DvsParams(noise_rate_hz=0.0, hot_pixels=0, leak_rate_hz=0.0)
    s = DvsSensor(cam, [robot], params=params, seed=seed)
    s.reset(np.array([poses_fn(0.0)]), 0)
    n = int(round(seconds * 1000))
    times = np.arange(1, n + 1, dtype=np.int64) * 1000
    poses = np.array([[poses_fn(t * 1e-6)] for t in times])
    evs, sigs = [], []
    for a in range(0, n, 100):
        e, g = s.advance(poses[a:a + 100], times[a:a + 100])
        evs.append(e)
        sigs.append(g)
    return np.concatenate(evs), np.concatenate(sigs), s


def straight(v=0.3, x0=0.6, y0=0.9, yaw=0.0, stop_s=None):
    def f(t):
        tt = t if stop_s is None else min(t, stop_s)
        return (x0 + v * tt * math.cos(yaw), y0 + v * tt * math.sin(yaw), yaw)
    return f


def test_dark_shell_off_on_leading_edge_on_on_trailing_edge():
    f = straight(v=0.3)
    ev, sig, _ = run_path(f, 0.5)
    ev = ev[sig]
    assert len(ev) > 1000
    # position of each event along the motion direction, relative to the robot centre
    t = ev["t"] * 1e-6
    centre = CAM.top_to_pixels(np.column_stack([0.6 + 0.3 * t, np.full(len(t), 0.9)]))
    ahead = CAM.top_to_pixels(np.column_stack([0.6 + 0.3 * t + 0.01, np.full(len(t), 0.9)]))
    d = (ahead - centre) / np.linalg.norm(ahead - centre, axis=1, keepdims=True)
    s = ((np.column_stack([ev["x"], ev["y"]]) - centre) * d).sum(axis=1)
    lead, trail = ev[s > 5], ev[s < -5]
    assert len(lead) > 200 and len(trail) > 200
    assert (lead["p"] == 0).mean() > 0.9, "leading edge of a dark shell must be OFF"
    assert (trail["p"] == 1).mean() > 0.9, "trailing edge of a dark shell must be ON"


def test_shell_colour_sets_event_density():
    # the shell alone (flat plate, no shadow): the 3-D body adds black treads to every colour
    cam = CeilingCamera(320, 240, body="flat", shadow=False)
    n_black = run_path(straight(), 0.4, BLACK, cam=cam)[1].sum()
    n_yellow = run_path(straight(), 0.4, YELLOW, cam=cam)[1].sum()
    assert n_yellow > 0
    assert n_black > 3 * n_yellow


def test_stopped_robot_gives_no_events():
    ev, sig, _ = run_path(straight(v=0.3, stop_s=0.2), 0.8)
    moving = sig & (ev["t"] < 200_000)
    still = sig & (ev["t"] > 350_000)
    assert moving.sum() > 500
    assert still.sum() == 0


def test_zero_point_turn_gives_few_events_compared_to_driving():
    turn = run_path(lambda t: (0.9, 0.9, 3.8 * t), 0.4)[1].sum()
    drive = run_path(straight(v=0.46), 0.4)[1].sum()
    assert 0 < turn < 0.6 * drive


@pytest.mark.parametrize("lighting,rate", [("full", None), ("dark", None), ("full", 0.5)])
def test_background_noise_rate_within_20_percent(lighting, rate):
    params = DvsParams(noise_rate_hz=rate, hot_pixels=0, leak_rate_hz=0.0)
    s = DvsSensor(CAM, [], lighting=lighting, params=params, seed=1)
    s.reset(np.zeros((0, 3)), 0)
    ev, sig = s.advance(np.zeros((1000, 0, 3)), np.arange(1, 1001) * 1000)
    expected = s.noise_rate_hz * CAM.width * CAM.height * 1.0
    assert not sig.any()
    assert len(ev) == pytest.approx(expected, rel=0.2)
    assert np.all(np.diff(ev["t"]) >= 0) and ev["t"].min() > 0 and ev["t"].max() <= 1_000_000


def test_more_noise_in_the_dark_and_hot_pixels_fire():
    full = DvsSensor(CAM, [], lighting="full", seed=1)
    dark = DvsSensor(CAM, [], lighting="dark", seed=1)
    assert dark.noise_rate_hz > 3 * full.noise_rate_hz
    full.reset(np.zeros((0, 3)), 0)
    ev, _ = full.advance(np.zeros((1000, 0, 3)), np.arange(1, 1001) * 1000)
    for u, v in full.hot_pixels:
        assert ((ev["x"] == u) & (ev["y"] == v)).sum() > 20


def test_events_account_for_the_log_intensity_change_per_threshold():
    """Per pixel, (ON - OFF) events x threshold equals the settled log-intensity change
    to within one threshold (no refractory period: no crossing is lost)."""
    robot = RobotSpec("r", BLACK)
    params = DvsParams(noise_rate_hz=0.0, hot_pixels=0, leak_rate_hz=0.0, refractory_us=0)
    s = DvsSensor(CAM, [robot], params=params, seed=2)
    f = straight(v=0.3, stop_s=0.15)
    s.reset(np.array([f(0.0)]), 0)
    before = s._llp.copy()
    times = np.arange(1, 501, dtype=np.int64) * 1000
    ev, sig = s.advance(np.array([[f(t * 1e-6)] for t in times]), times)
    change = s._llp - before
    net = np.zeros_like(change)
    on, off = ev[ev["p"] == 1], ev[ev["p"] == 0]
    np.add.at(net, (on["y"], on["x"]), s._thr_on[on["y"], on["x"]])
    np.add.at(net, (off["y"], off["x"]), -s._thr_off[off["y"], off["x"]])
    thr = np.maximum(s._thr_on, s._thr_off)
    assert np.abs(change).max() > 2.0                 # a black shell really moved
    assert np.all(np.abs(change - net) < thr + 1e-5)


def test_higher_threshold_fewer_events():
    lo = run_path(straight(), 0.3, params=DvsParams(threshold_on=0.2, threshold_off=0.2,
                                                     noise_rate_hz=0, hot_pixels=0))[1].sum()
    hi = run_path(straight(), 0.3, params=DvsParams(threshold_on=0.4, threshold_off=0.4,
                                                     noise_rate_hz=0, hot_pixels=0))[1].sum()
    assert 0.35 * lo < hi < 0.65 * lo


def test_refractory_period_is_honoured_per_pixel():
    params = DvsParams(refractory_us=10_000, noise_rate_hz=0, hot_pixels=0)
    ev, sig, _ = run_path(straight(v=0.46), 0.3, params=params)
    ev = ev[sig]
    key = ev["y"].astype(np.int64) * 10_000 + ev["x"]
    order = np.lexsort((ev["t"], key))
    k, t = key[order], ev["t"][order]
    same = k[1:] == k[:-1]
    assert same.sum() > 100
    assert np.diff(t)[same].min() >= 10_000
    free = run_path(straight(v=0.46), 0.3, params=DvsParams(refractory_us=0, noise_rate_hz=0,
                                                             hot_pixels=0))[1].sum()
    assert free > 1.5 * len(ev)


def test_timestamps_are_microseconds_inside_each_step_and_sorted():
    ev, sig, _ = run_path(straight(), 0.2)
    assert np.all(np.diff(ev["t"]) >= 0)
    assert len(np.unique(ev["t"] % 1000)) > 200       # sub-step timing, not on a 1 ms grid


def test_step_sort_is_stable_and_touches_only_its_segment():
    from simulator.dvs import _sort_segment
    rng = np.random.default_rng(3)
    n, a, b, t0, span = 400, 37, 351, 5_000, 1000
    ox = rng.integers(0, 1280, n).astype(np.uint16)
    oy = rng.integers(0, 720, n).astype(np.uint16)
    op = rng.integers(0, 2, n).astype(np.uint8)
    ot = t0 + rng.integers(1, 58, n).astype(np.int64) * 17     # many ties, within (t0, t0 + span]
    ot[a] = t0 + span
    ot[a + 1] = t0 + 1
    want = [c.copy() for c in (ox, oy, op, ot)]
    order = np.argsort(ot[a:b], kind="stable")
    for c in want:
        c[a:b] = c[a:b][order]
    _sort_segment(ox, oy, op, ot, a, b, t0, span)
    for got, exp in zip((ox, oy, op, ot), want):
        np.testing.assert_array_equal(got, exp)


def test_dim_light_slows_the_photoreceptor_and_lowers_contrast():
    full = run_path(straight(), 0.3)[1].sum()
    robot = RobotSpec("r", BLACK)
    s = DvsSensor(CAM, [robot], lighting="dark", params=DvsParams(noise_rate_hz=0, hot_pixels=0))
    f = straight()
    s.reset(np.array([f(0)]), 0)
    times = np.arange(1, 301, dtype=np.int64) * 1000
    _, sig = s.advance(np.array([[f(t * 1e-6)] for t in times]), times)
    assert 0 < sig.sum() < 0.8 * full


def test_bad_parameters_and_calls_raise_clear_errors():
    with pytest.raises(ValueError, match="step_us"):
        DvsParams(step_us=5000).validate()
    s = DvsSensor(CAM, [RobotSpec("r", BLACK)], params=DvsParams())
    with pytest.raises(RuntimeError, match="reset"):
        s.advance(np.zeros((1, 1, 3)), [1000])
    s.reset(np.array([[0.9, 0.9, 0.0]]))
    with pytest.raises(ValueError, match="steps"):
        s.advance(np.zeros((1, 1, 3)), [5000])


def test_roi_simulation_matches_full_frame_simulation():
    """Simulating only around the robots gives the events of simulating every pixel."""
    cam = CeilingCamera(160, 120)
    f = lambda t: (0.5 + 0.3 * t, 0.9 + 0.1 * t, 0.8 * t)          # drive and turn
    # the scene traced every step in both (a flickering light traces every pixel every step)
    roi, sig_roi, _ = run_path(f, 0.5, cam=cam, params=DvsParams(noise_rate_hz=0.0, hot_pixels=0, leak_rate_hz=0.0,
                                                                 trace_every=1))
    full_params = DvsParams(noise_rate_hz=0.0, hot_pixels=0, leak_rate_hz=0.0, flicker_hz=1.0,
                            flicker_depth=0.0)
    full, sig_full, _ = run_path(f, 0.5, cam=cam, params=full_params)
    assert len(roi) > 500
    assert len(roi) == pytest.approx(len(full), rel=0.02)
    key = lambda e: set(zip(e["x"].tolist(), e["y"].tolist(), e["p"].tolist(), (e["t"] // 1000).tolist()))
    a, b = key(roi), key(full)
    assert len(a & b) > 0.95 * max(len(a), len(b))


def test_flicker_makes_static_scene_fire_everywhere():
    cam = CeilingCamera(64, 48)
    params = DvsParams(noise_rate_hz=0.0, hot_pixels=0, leak_rate_hz=0.0, flicker_hz=100.0,
                       flicker_depth=0.5)
    ev, sig, _ = run_path(lambda t: (0.9, 0.9, 0.0), 0.1, cam=cam, params=params)
    assert sig.all() and len(np.unique(ev["y"].astype(int) * 64 + ev["x"])) > 0.5 * 64 * 48
    still, _, _ = run_path(lambda t: (0.9, 0.9, 0.0), 0.1, cam=cam)
    assert len(still) == 0


def test_shell_tops_appear_displaced_outwards_by_parallax():
    """A robot near an arena corner is seen further out than its floor position (the flat
    shell-top plate; the 3-D body: tests/simulator/test_realism.py)."""
    x, y = 0.25, 0.25
    ev, sig, _ = run_path(lambda t: (x + 0.2 * t, y, 0.0), 0.3,
                          cam=CeilingCamera(320, 240, body="flat", shadow=False))
    ev = ev[sig & (ev["t"] > 100_000)]
    t = ev["t"] * 1e-6
    floor = CAM.to_pixels(np.column_stack([x + 0.2 * t, np.full(len(t), y)]))
    top = CAM.top_to_pixels(np.column_stack([x + 0.2 * t, np.full(len(t), y)]))
    centre = CAM.to_pixels([[0.915, 0.915]])[0]
    mean_uv = np.column_stack([ev["x"], ev["y"]]).mean(axis=0)
    assert np.linalg.norm(top.mean(0) - centre) > np.linalg.norm(floor.mean(0) - centre)
    # events are centred on the top projection, not on the floor projection
    assert np.linalg.norm(mean_uv - top.mean(0)) < np.linalg.norm(mean_uv - floor.mean(0))


def test_warm_up_leaves_the_served_world_untouched():
    # `arena sim` compiles on a twin before serving: the real robots must not move or age
    from simulator.simulation import warm_up
    from simulator.world import World
    world = World([RobotSpec("a", BLACK, start=(0.5, 0.5, 0.0)), RobotSpec("b", BLACK, start=(1.2, 1.0, 1.0))])
    before = world.poses().copy()
    warm_up(world, CeilingCamera(320, 240), DvsParams())
    assert world.t == 0.0
    assert np.array_equal(world.poses(), before)
    assert world.power(0) == (0, 0) and world.power(1) == (0, 0)


def test_the_scene_traced_every_other_step_keeps_the_events_of_tracing_every_step():
    """trace_every=2 (the default) holds each pixel's reflectance for one step: the same edges,
    within a step of the same times, and nearly the same number of events."""
    cam = CeilingCamera(160, 120)
    f = lambda t: (0.5 + 0.46 * t, 0.9, 0.0)          # full speed, straight
    base = dict(noise_rate_hz=0.0, hot_pixels=0, leak_rate_hz=0.0)
    every, _, _ = run_path(f, 0.4, cam=cam, params=DvsParams(**base, trace_every=1))
    held, _, _ = run_path(f, 0.4, cam=cam, params=DvsParams(**base))
    assert DvsParams().trace_every == 2 and len(every) > 500
    assert len(held) == pytest.approx(len(every), rel=0.03)
    key = lambda e, dt: set(zip(e["x"].tolist(), e["y"].tolist(), e["p"].tolist(), ((e["t"] + dt) // 2000).tolist()))
    a = key(every, 0) | key(every, 1000)
    assert len(key(held, 0) & a) > 0.9 * len(key(held, 0))
    with pytest.raises(ValueError, match="trace_every"):
        DvsParams(trace_every=0).validate()

"""The fleet tracker: stops, crossings, touching robots, noise bursts, fleet size."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.tracker.synth import SCALE, line_pose, window
from tracker.detect import Detector
from tracker.fleet import FleetConfig, FleetTracker
from tracker.objects import Observation

DT = 10_000  # µs, 100 Hz


def ob(x, y, t, vx=math.nan, vy=math.nan):
    yaw = math.atan2(vy, vx) if math.isfinite(vx) and math.hypot(vx, vy) > 0.05 else math.nan
    return Observation(x=x, y=y, t_us=t, vx=vx, vy=vy, yaw=yaw, speed_sigma=0.01, t_vel_us=t)


def run(tracker, frames):
    """frames: list of lists of observations, one list per 10 ms step; returns all outputs."""
    out = []
    for k, obs in enumerate(frames):
        out.append(tracker.update(obs, (k + 1) * DT))
    return out


def test_new_track_is_tentative_then_confirmed_and_only_confirmed_are_reported():
    ft = FleetTracker()
    outs = run(ft, [[ob(0.5 + 0.003 * k, 0.5, (k + 1) * DT, 0.3, 0.0)] for k in range(5)])
    assert outs[0] == [] and outs[1] == []          # tentative: not reported
    assert [t.state for t in outs[2]] == ["confirmed"]
    assert {t.track_id for o in outs[2:] for t in o} == {1}
    assert outs[-1][0].age == 4 and outs[-1][0].hits == 5


def test_a_stopped_robot_keeps_its_id_where_it_stopped_and_resumes_with_it():
    ft = FleetTracker()
    frames = [[ob(0.5 + 0.004 * k, 0.5, (k + 1) * DT, 0.4, 0.0)] for k in range(50)]
    frames += [[] for _ in range(300)]               # 3 s without events: stopped
    x_stop = 0.5 + 0.004 * 49
    frames += [[ob(x_stop + 0.004 * k, 0.5, (351 + k) * DT, 0.4, 0.0)] for k in range(20)]
    outs = run(ft, frames)
    during = outs[60:349]
    assert all(len(o) == 1 and o[0].state == "coasting" and o[0].track_id == 1 for o in during)
    # braked to rest close to where it stopped (no drift at the old velocity)
    assert abs(during[-1][0].x - x_stop) < 0.03 and abs(during[-1][0].vx) < 1e-3
    assert all(o[0].track_id == 1 and o[0].state == "confirmed" for o in outs[352:])
    assert len(ft.tracks) == 1


def test_crossing_robots_keep_their_ids_through_a_merged_detection():
    ft = FleetTracker()
    frames = []
    for k in range(120):
        t = (k + 1) * DT
        a = (0.3 + 0.004 * k, 0.5)                   # to +x at 0.4 m/s
        b = (0.5, 0.3 + 0.004 * k)                   # to +y at 0.4 m/s; paths cross at (0.5, 0.5)
        if math.hypot(a[0] - b[0], a[1] - b[1]) < 0.09:
            # one merged cluster between the two robots
            frames.append([ob((a[0] + b[0]) / 2, (a[1] + b[1]) / 2, t)])
        else:
            frames.append([ob(*a, t, 0.4, 0.0), ob(*b, t, 0.0, 0.4)])
    outs = run(ft, frames)
    last = {t.track_id: (t.x, t.y) for t in outs[-1]}
    assert len(last) == 2
    by_x = max(last, key=lambda i: last[i][0])       # the robot now far along +x
    first = {t.track_id: (t.x, t.y) for t in outs[10]}
    assert first[by_x][1] == pytest.approx(0.5, abs=0.01)   # ... is the one that started on y = 0.5


def test_noise_bursts_never_become_robots():
    rng = np.random.default_rng(3)
    ft = FleetTracker()
    outs = []
    for k in range(300):
        t = (k + 1) * DT
        obs = [ob(0.9, 0.9 + 0.003 * k, t, 0.0, 0.3)]
        if k % 7 == 0:  # a burst: 5 spurious clusters, each seen once
            obs += [ob(*rng.uniform(0.0, 1.8, 2), t) for _ in range(5)]
        outs.append(ft.update(obs, t))
    assert {tr.track_id for o in outs for tr in o} == {1}


def test_no_new_track_within_a_chassis_of_another():
    ft = FleetTracker(FleetConfig(chassis_m=0.10))
    outs = run(ft, [[ob(0.5, 0.5, (k + 1) * DT, 0.0, 0.0), ob(0.56, 0.5, (k + 1) * DT)] for k in range(10)])
    assert {t.track_id for t in outs[-1]} == {1}


def test_fleet_size_caps_confirmed_tracks_and_a_lost_robot_is_found_elsewhere():
    ft = FleetTracker(FleetConfig(fleet_size=1, lost_s=0.5))
    frames = [[ob(0.3, 0.3 + 0.003 * k, (k + 1) * DT, 0.0, 0.3)] for k in range(20)]
    frames += [[ob(1.5, 1.5 + 0.003 * k, (21 + k) * DT, 0.0, 0.3)] for k in range(20)]   # not yet lost
    frames += [[] for _ in range(30)]
    frames += [[ob(1.5, 1.6 + 0.003 * k, (71 + k) * DT, 0.0, 0.3)] for k in range(20)]   # lost > 0.5 s
    outs = run(ft, frames)
    assert all(len(o) <= 1 for o in outs)
    assert all(t.track_id == 1 for o in outs for t in o)
    assert outs[-1][0].y > 1.6 and outs[-1][0].state == "confirmed"


def test_heading_follows_motion_and_stays_through_a_zero_point_turn():
    ft = FleetTracker()
    frames = [[ob(0.5 + 0.004 * k, 0.5, (k + 1) * DT, 0.4, 0.0)] for k in range(30)]
    out = run(ft, frames)
    assert out[-1][0].yaw == pytest.approx(0.0, abs=0.05)
    # turning in place: no motion heading, the shape orientation (mod 90 deg) turns to 90 deg
    x = 0.5 + 0.004 * 29
    for k in range(50):
        t = (31 + k) * DT
        o = ob(x, 0.5, t, 0.0, 0.0)
        o.shape_yaw = (math.pi / 2) * (k + 1) / 50 + math.pi / 2   # same orientation modulo 90 deg
        o.shape_order = 4
        last = ft.update([o], t)
    assert last[0].yaw == pytest.approx(math.pi / 2, abs=math.radians(5))


def test_touching_robots_are_split_by_the_predictions():
    rng = np.random.default_rng(5)
    # two robots side by side, 26 px apart (25 px chassis): one DBSCAN cluster
    poses = [line_pose(300, 200, 0.0, 100.0), line_pose(326, 200, 0.0, 100.0)]
    ev = window(rng, poses, 0, 100_000, noise_per_px_s=0.05)
    det = Detector(SCALE, 640, 480)
    merged = det.detect(ev, 100_000)
    assert len(merged) == 1
    split = det.detect(ev, 100_000, hints=np.array([[300.0, 210.0], [326.0, 210.0]]))
    assert len(split) == 2
    us = sorted(d.u for d in split)
    assert us[0] == pytest.approx(300, abs=3) and us[1] == pytest.approx(326, abs=3)
    assert all(d.v == pytest.approx(210, abs=3) for d in split)   # position at the window's end


def test_a_shape_that_keeps_disagreeing_with_the_motion_is_ignored():
    rng = np.random.default_rng(9)
    ft = FleetTracker()
    last = None
    for k in range(150):   # driving along +x; the "shape" orientation is noise (a round shell)
        o = ob(0.3 + 0.004 * k, 0.5, (k + 1) * DT, 0.4, 0.0)
        o.shape_yaw, o.shape_order = rng.uniform(-np.pi, np.pi), 4
        last = ft.update([o], (k + 1) * DT)
    assert last[0].yaw == pytest.approx(0.0, abs=math.radians(3))
    for k in range(150, 200):   # standing still: only the (noise) shape, which must not turn it
        o = ob(0.3 + 0.004 * 149, 0.5, (k + 1) * DT, 0.0, 0.0)
        o.shape_yaw, o.shape_order = rng.uniform(-np.pi, np.pi), 4
        last = ft.update([o], (k + 1) * DT)
    assert last[0].yaw == pytest.approx(0.0, abs=math.radians(3))

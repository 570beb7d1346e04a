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


def _drive_then_stand(ft, n_drive=30, n_stand=20):
    """A robot drives along +x for 0.3 s, then stands still (shape at 0 deg mod 90); returns where."""
    run(ft, [[ob(0.5 + 0.004 * k, 0.5, (k + 1) * DT, 0.4, 0.0)] for k in range(n_drive)])
    x = 0.5 + 0.004 * (n_drive - 1)
    for k in range(n_stand):
        t = (n_drive + 1 + k) * DT
        o = ob(x, 0.5, t, 0.0, 0.0)
        o.shape_yaw, o.shape_order = 0.0, 4
        ft.update([o], t)
    return x, (n_drive + n_stand + 1) * DT


@pytest.mark.parametrize("empty", [1, 12])
def test_empty_windows_at_rest_do_not_let_a_jittery_start_flip_the_heading(empty):
    # at the end of a square's corner the robot creeps with few events: windows come out empty
    # (no events: no motion), and the next cluster's centroid jumps, which looks like motion
    # the wrong way. The heading must not jump to it at once (it did after any empty window:
    # 180 degree flips)
    ft = FleetTracker()
    x, t = _drive_then_stand(ft)
    for _ in range(empty):
        ft.update([], t)
        t += DT
    for k in range(3):                                     # jitter "backwards" at 0.12 m/s
        o = ob(x - 0.0012 * (k + 1), 0.5, t, -0.12, 0.0)
        o.shape_yaw, o.shape_order = 0.0, 4
        last = ft.update([o], t)
        t += DT
        assert abs(math.remainder(last[0].yaw, 2 * math.pi)) < math.radians(20), (k, last[0].yaw)


def test_a_starting_robots_first_heading_waits_for_two_agreeing_motions():
    # a robot starting from rest: its cluster grows on the back side first, so the first
    # apparent motion points backwards (-x); then it drives along +x. The heading stays unknown
    # until two motions agree, and is never reported the wrong way (it was, 180 deg for 90 ms)
    ft = FleetTracker()
    frames = [[ob(0.5, 0.5, (k + 1) * DT, 0.0, 0.0)] for k in range(3)]      # confirmed, no motion yet
    frames += [[ob(0.5 - 0.0015, 0.5, 4 * DT, -0.15, 0.0)]]
    frames += [[ob(0.4985 + 0.004 * k, 0.5, (k + 5) * DT, 0.4, 0.0)] for k in range(12)]
    yaws = [o[0].yaw for o in run(ft, frames)[3:]]
    known = [y for y in yaws if math.isfinite(y)]
    assert len(yaws) - len(known) <= 2 and len(known) >= 10
    assert all(abs(math.remainder(y, 2 * math.pi)) < math.radians(20) for y in known), yaws


def test_a_fresh_wrong_heading_is_corrected_within_a_few_windows():
    # two agreeing wrong motions (-x) set a fresh heading; the robot then drives along +x: a
    # fresh heading restarts after 2 disagreeing motions (it took 8: 90 ms reported 180 deg off)
    ft = FleetTracker()
    frames = [[ob(0.5 - 0.0015 * k, 0.5, (k + 1) * DT, -0.15, 0.0)] for k in range(3)]
    frames += [[ob(0.4955 + 0.004 * k, 0.5, (k + 4) * DT, 0.4, 0.0)] for k in range(12)]
    yaws = [o[0].yaw for o in run(ft, frames)[3:] if o]           # from the first +x window on
    off = [not abs(math.remainder(y, 2 * math.pi)) < math.radians(60) for y in yaws]
    assert off[0] and sum(off) <= 2 and not any(off[2:]), [round(math.degrees(y)) for y in yaws]


def test_a_settled_heading_still_ignores_a_few_outlier_motions():
    # once motion has agreed with the heading a few times, 2-7 windows of backwards apparent
    # motion (a jumping centroid) do not restart it
    ft = FleetTracker()
    run(ft, [[ob(0.5 + 0.004 * k, 0.5, (k + 1) * DT, 0.4, 0.0)] for k in range(20)])
    x = 0.5 + 0.004 * 19
    for k in range(5):
        t = (21 + k) * DT
        last = ft.update([ob(x - 0.001 * (k + 1), 0.5, t, -0.2, 0.0)], t)
        assert abs(math.remainder(last[0].yaw, 2 * math.pi)) < math.radians(30), k


def test_a_robot_hidden_in_another_ones_cluster_takes_its_new_motion_heading_at_once():
    # hidden for 10 windows in a neighbour's cluster it kept moving and could have turned: its
    # first clear motion afterwards resets the heading at once
    ft = FleetTracker()
    x = 0.5 + 0.004 * 29
    nb = (x + 0.06, 0.5)                                   # a neighbour standing 6 cm from where it stops
    frames = [[ob(0.5 + 0.004 * k, 0.5, (k + 1) * DT, 0.4, 0.0), ob(*nb, (k + 1) * DT, 0.0, 0.0)]
              for k in range(30)]
    frames += [[ob(x, 0.5, (k + 31) * DT, 0.0, 0.0), ob(*nb, (k + 31) * DT, 0.0, 0.0)] for k in range(10)]
    frames += [[ob(*nb, (k + 41) * DT, 0.0, 0.0)] for k in range(10)]     # only the neighbour's cluster
    run(ft, frames)
    hidden = [tr for tr in ft.tracks if abs(tr.xy[0] - x) < 0.01]
    assert len(hidden) == 1 and hidden[0].hidden == 10 and hidden[0].yaw == pytest.approx(0.0, abs=0.05)
    t = 51 * DT
    out = ft.update([ob(x, 0.5 - 0.004, t, 0.0, -0.4), ob(*nb, t, 0.0, 0.0)], t)   # out again, along -y
    yaw = next(tr.yaw for tr in out if tr.track_id == hidden[0].id)
    assert yaw == pytest.approx(-math.pi / 2, abs=math.radians(5))


def test_a_spinning_robot_whose_centroid_drifts_sideways_keeps_its_heading():
    # a zero-point turn on real treads: the centroid slides sideways at ~6 cm/s, which looks
    # like a motion heading at 90 degrees to the chassis; the shape turns continuously
    ft = FleetTracker()
    run(ft, [[ob(0.5 + 0.004 * k, 0.5, (k + 1) * DT, 0.4, 0.0)] for k in range(30)])
    x, y = 0.5 + 0.004 * 29, 0.5
    for k in range(50):
        t = (31 + k) * DT
        yaw = (math.pi / 2) * (k + 1) / 50                 # 0 -> 90 deg in 0.5 s (3.1 rad/s)
        side = yaw - math.pi / 2                           # drifting to the robot's right
        y += 0.0006 * math.sin(side)
        x += 0.0006 * math.cos(side)
        o = ob(x, y, t, 0.06 * math.cos(side), 0.06 * math.sin(side))
        o.shape_yaw, o.shape_order = yaw + math.pi, 4      # same orientation modulo 90 deg
        last = ft.update([o], t)
        assert abs(math.remainder(last[0].yaw - yaw, 2 * math.pi)) < math.radians(20), (k, last[0].yaw, yaw)
    assert last[0].yaw == pytest.approx(math.pi / 2, abs=math.radians(8))


def test_a_robot_braking_out_of_a_turn_stops_turning_in_the_filter():
    # driving a 0.3 m circle at 0.4 m/s (1.33 rad/s), then stopping dead: the windows that
    # follow still hold its last events (activity ending before the window's end)
    ft = FleetTracker()
    w, r, cx, cy = 0.4 / 0.3, 0.3, 0.9, 0.9
    last = None
    for k in range(60):
        t = (k + 1) * DT
        a = w * t * 1e-6
        yaw = a + math.pi / 2
        o = ob(cx + r * math.cos(a), cy + r * math.sin(a), t, 0.4 * math.cos(yaw), 0.4 * math.sin(yaw))
        o.shape_yaw, o.shape_order = yaw, 4
        last = ft.update([o], t)
    t_stop = 60 * DT
    yaw_stop = w * t_stop * 1e-6 + math.pi / 2
    assert abs(math.remainder(last[0].yaw - yaw_stop, 2 * math.pi)) < math.radians(5)
    # 10 windows after the stop, each with the last 100 ms of motion (mean time 50 ms before the
    # stop): no clear motion any more, and the shape (mod 90 deg) of where the robot stopped
    a = w * t_stop * 1e-6
    for k in range(1, 11):
        t = t_stop + k * DT
        o = ob(cx + r * math.cos(a), cy + r * math.sin(a), t, 0.0, 0.0)   # no motion heading
        o.t_vel_us, o.t_act_us = t_stop - 50_000, t_stop
        o.shape_yaw, o.shape_order = yaw_stop - w * 0.05, 4   # the window's mean heading
        last = ft.update([o], t)
    assert abs(math.remainder(last[0].yaw - yaw_stop, 2 * math.pi)) < math.radians(4), math.degrees(last[0].yaw - yaw_stop)


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


def _drive(tracker, paths, k0, k1):
    """paths: functions k -> (x, y, vx, vy) or None (no detection); steps k0..k1-1."""
    out = []
    for k in range(k0, k1):
        t = (k + 1) * DT
        obs = [ob(*p(k)[:2], t, *p(k)[2:]) for p in paths if p(k) is not None]
        out.append(tracker.update(obs, t))
    return out


def _line(x0, y0, vx, vy, stop_k=None):
    def pose(k):
        kk = k if stop_k is None else min(k, stop_k)
        moving = stop_k is None or k < stop_k
        if not moving:
            return None  # a stopped robot makes no events: no detection
        return (x0 + vx * kk * DT * 1e-6, y0 + vy * kk * DT * 1e-6, vx, vy)
    return pose


def test_restore_brings_back_ids_names_and_headings_of_robots_that_stood_still_or_drove_on():
    import json
    first = FleetTracker()
    # robot A drives and stops at k=50; robot B drives on (+x at 0.3 m/s); robot C drives +y
    a = _line(0.3, 0.3, 0.2, 0.0, stop_k=50)
    b = _line(0.3, 1.0, 0.3, 0.0)
    c = _line(1.5, 0.3, 0.0, 0.3)
    outs = _drive(first, [a, b, c], 0, 80)
    ids = {round(t.y, 1) if t.x < 1.0 else "c": t.track_id for t in outs[-1]}
    assert len(outs[-1]) == 3
    first.set_robot_name(ids["c"], "zumo3")
    snap = json.loads(json.dumps(first.snapshot()))  # through JSON, as the live service stores it
    yaw_b = next(t.yaw for t in outs[-1] if t.track_id == ids[1.0])

    # a restart of 2 s: robot A is still where it stopped, B and C drove on meanwhile
    second = FleetTracker()
    assert sorted(second.restore(snap)) == sorted(ids.values())
    restored = second.update([], 81 * DT)
    assert {t.track_id for t in restored} == set(ids.values())
    assert all(t.state == "coasting" for t in restored)
    assert abs(next(t.yaw for t in restored if t.track_id == ids[1.0]) - yaw_b) < 1e-6
    a_moves = _line(0.3 + 0.2 * 0.5, 0.3, 0.2, 0.0)  # A starts again from where it stopped, at k=280
    after = _drive(second, [lambda k: a_moves(k - 280) if k >= 280 else None, b, c], 280, 320)
    final = {t.track_id: t for t in after[-1]}
    assert set(final) == set(ids.values()), "a new ID instead of the restored one"
    assert abs(final[ids[0.3]].x - a_moves(39)[0]) < 0.02
    assert abs(final[ids[1.0]].x - b(319)[0]) < 0.02
    assert final[ids["c"]].robot == "zumo3" and abs(final[ids["c"]].y - c(319)[1]) < 0.02
    # a robot that is new after the restart gets a fresh ID, not a restored one's
    d = _line(0.9, 1.6, -0.2, 0.0)
    more = _drive(second, [b, c, d], 320, 330)
    new = {t.track_id for t in more[-1]} - set(ids.values())
    assert len(new) == 1 and min(new) > max(ids.values())


def test_a_robot_that_drove_far_during_a_long_restart_gets_its_id_back():
    # the state file was 3.4 s old: the robot drove 1.36 m at 0.4 m/s meanwhile (more than
    # reclaim_m), which no robot of the fleet could have done in less time
    import json
    first = FleetTracker()
    a = _line(0.3, 0.2, 0.4, 0.0)
    b = _line(1.0, 1.4, 0.0, 0.0)   # a second robot standing still, to be kept apart
    outs = _drive(first, [a, lambda k: b(k) if k < 5 else None], 0, 40)
    ids = {round(t.y, 1): t.track_id for t in outs[-1]}
    snap = json.loads(json.dumps(first.snapshot()))
    second = FleetTracker()
    second.restore(snap)
    after = _drive(second, [a], 380, 400)            # back 3.4 s later, 1.36 m further on
    final = {t.track_id: t for t in after[-1]}
    assert set(final) == set(ids.values()), "a new ID instead of the restored one"
    assert final[ids[0.2]].state == "confirmed" and abs(final[ids[0.2]].x - a(399)[0]) < 0.02
    assert final[ids[1.4]].state == "coasting"       # the robot that stood still waits where it was


def test_restore_rejects_snapshots_it_cannot_read_and_rebases_a_restarted_clock():
    ft = FleetTracker()
    with pytest.raises(ValueError, match="version"):
        ft.restore({"v": 99, "tracks": []})
    with pytest.raises(ValueError, match="malformed"):
        ft.restore({"v": 1, "tracks": [{"id": 1}]})
    with pytest.raises(ValueError, match="finite"):
        ft.restore({"v": 1, "tracks": [{"id": 1, "x": float("nan"), "y": 0, "t_us": 0}]})
    assert ft.tracks == []
    # the snapshot's clock is ahead of the new stream (the camera restarted too): still coasting at rest
    ft.restore({"v": 1, "next_id": 3, "tracks": [{"id": 2, "x": 0.5, "y": 0.5, "vx": 0.3, "vy": 0.0,
                                                 "t_us": 50_000_000, "last_seen_us": 50_000_000}]})
    out = ft.update([], 1_000_000)
    assert [(t.track_id, round(t.x, 6), t.state) for t in out] == [(2, 0.5, "coasting")]
    out = ft.update([ob(0.52, 0.5, 1_010_000, 0.2, 0.0)], 1_010_000)
    assert [(t.track_id, t.state) for t in out] == [(2, "confirmed")]


def _drive_events(ft, frames, x0, y0, vx, vy, n_events, k0=0):
    """``frames`` detections of a robot driving at (vx, vy) m/s, ``n_events`` events each."""
    out = None
    for k in range(frames):
        t = (k0 + k + 1) * DT
        x, y = x0 + vx * (k + 1) * DT * 1e-6, y0 + vy * (k + 1) * DT * 1e-6
        o = Observation(x=x, y=y, t_us=t, vx=vx, vy=vy, yaw=math.atan2(vy, vx) if vx or vy else math.nan,
                        speed_sigma=0.01, t_vel_us=t, n_events=n_events)
        out = ft.update([o], t)
    return out, x, y


@pytest.mark.parametrize("sparse_fraction, held", [(0.3, True), (0.0, False)])
def test_a_sparse_cluster_at_the_end_of_a_turn_does_not_drag_the_position(sparse_fraction, held):
    # creeping out of a zero-point turn, a robot fires a few hundred events from part of its
    # outline: their centroid drifts up to 5 cm off the chassis centre, with an apparent motion
    ft = FleetTracker(FleetConfig(sparse_fraction=sparse_fraction))
    _, x0, y0 = _drive_events(ft, 40, 0.5, 0.5, 0.4, 0.0, 8000)
    for k in range(30):                                   # centroid slides 3 cm sideways, 500 events
        t = (41 + k) * DT
        o = Observation(x=x0, y=y0 + 0.001 * (k + 1), t_us=t, vx=0.0, vy=0.1, speed_sigma=0.01, t_vel_us=t,
                        n_events=500)
        out = ft.update([o], t)
    off = math.hypot(out[0].x - x0, out[0].y - y0)
    assert (off < 0.01) if held else (off > 0.02), off


def test_a_robot_that_keeps_driving_slowly_is_soon_tracked_closely_again():
    # a robot slowing from 0.4 to 0.06 m/s for good fires far fewer events: after a second the
    # track follows it as closely as before (the usual event count follows the moving robot)
    ft = FleetTracker()
    _, x0, y0 = _drive_events(ft, 40, 0.3, 0.5, 0.4, 0.0, 8000)
    out, x, y = _drive_events(ft, 200, x0, y0, 0.06, 0.0, 1200, k0=40)
    assert abs(out[0].x - x) < 0.003 and out[0].vx == pytest.approx(0.06, abs=0.01)
    assert ft.tracks[0].n_usual < 2400                    # below the fraction's reach of 1200


@pytest.mark.parametrize("sparse_fraction, held", [(0.3, True), (0.0, False)])
def test_a_sparse_clusters_apparent_motion_gives_no_heading(sparse_fraction, held):
    # creeping out of a turn, the partial outline's centroid slides "backwards" for 0.15 s: more
    # than the 8 disagreeing updates that would restart the heading on that motion (a flip)
    ft = FleetTracker(FleetConfig(sparse_fraction=sparse_fraction))
    _, x0, y0 = _drive_events(ft, 40, 0.5, 0.5, 0.4, 0.0, 8000)
    for k in range(15):
        t = (41 + k) * DT
        o = Observation(x=x0 - 0.0012 * (k + 1), y=y0, t_us=t, vx=-0.12, vy=0.0, yaw=math.pi, speed_sigma=0.01,
                        t_vel_us=t, n_events=500)
        out = ft.update([o], t)
    flipped = abs(math.remainder(out[0].yaw, 2 * math.pi)) > math.radians(90)
    assert flipped != held, out[0].yaw

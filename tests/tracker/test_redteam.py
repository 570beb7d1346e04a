"""An independent red team's findings on the live tracker (issue 20 items 3, 6, 10), each pinned:
one window stamped far off does not reset the tracker, windows refused as bad are not counted
again as missed, and a state file cannot plant duplicate names, unbounded or eternal tracks, or
hang the tracker's start (pure LiveTracker and FleetTracker: no Zenoh)."""

from __future__ import annotations

import json
import math
import os
import threading
import time

import numpy as np
import pytest

from arena.codec import encode
from arena.messages import EventWindow
from tests.tracker.synth import Counts, calibration_dict, line_pose, window
from tracker.calibration import Calibration
from tracker.fleet import FleetConfig, FleetTracker
from tracker.objects import Observation
from tracker.pipeline import Pipeline
from tracker.service import MAX_STATE_TRACKS, LiveTracker, _restore_state, check_state, load_state

DT = 10_000


def make():
    return Pipeline(Calibration.from_dict(calibration_dict()))


@pytest.fixture(scope="module")
def events():
    rng = np.random.default_rng(5)
    return window(rng, [line_pose(100, 150, 40.0, 0.0), line_pose(150, 350, 40.0, 0.0)], 0, 3_000_000)


def win(ev, k, t0=None, seq=None, **kw) -> bytes:
    """Window k of ``ev`` (10 ms), or an empty window starting at ``t0``."""
    a = k * DT if t0 is None else t0
    sl = ev[np.searchsorted(ev["t"], a):np.searchsorted(ev["t"], a + DT)] if t0 is None else ev[:0]
    return EventWindow(camera="c0", seq=k if seq is None else seq, t_start_us=a, t_end_us=a + DT, width=640,
                       height=480, count=sl.size, codec="planes-zstd/1", data=encode(sl), publish_ns=1,
                       **kw).encode()


def named_tracker(ev, n=100):
    """A LiveTracker that has tracked both robots for ``n`` windows and named them zumo1, zumo2."""
    svc = Counts()
    live = LiveTracker(make(), "c0", svc=svc, make_pipeline=make)
    for k in range(n):
        out = live.handle(win(ev, k), 1, newest_end_us=(k + 1) * DT)
    ids = sorted(m.track_id for _, m, _ in out)
    assert len(ids) == 2
    for tid, name in zip(ids, ("zumo1", "zumo2")):
        live.pipeline.tracker.set_robot_name(tid, name)
    return live, svc, ids


# -- item 10: one window far off -------------------------------------------------------------

@pytest.mark.parametrize("t0", [10 ** 12, 2 ** 63 - 20_000, -2 ** 62], ids=["1e12 ahead", "int64 max", "-2^62"])
def test_one_window_stamped_far_off_is_held_and_the_tracker_goes_on(events, t0):
    live, svc, ids = named_tracker(events)
    assert live.handle(win(events, 100, t0=t0), 1) == []            # held: nothing published with its stamp
    assert svc.c.get("windows_future" if t0 > 0 else "windows_past") == 1
    out = []
    for k in range(101, 130):
        out += live.handle(win(events, k), 1, newest_end_us=(k + 1) * DT)
    assert "stream_restarts" not in svc.c and "windows_missed" not in svc.c
    last = {m.track_id: m.robot for _, m, _ in out[-2:]}
    assert last == dict(zip(ids, ("zumo1", "zumo2")))               # IDs and names kept
    assert max(m.stamp_us for _, m, _ in out) == 130 * DT
    assert svc.c["windows_in"] == 129


def test_a_jump_or_a_restart_is_taken_when_three_windows_agree(events):
    live, svc, _ = named_tracker(events)
    # the camera's clock jumps 100 s ahead and stays there: two windows held, the third taken
    t = 100 * DT + 100_000_000
    assert live.handle(win(events, 100, t0=t), 1) == []
    assert live.handle(win(events, 101, t0=t + DT), 1) == []
    live.handle(win(events, 102, t0=t + 2 * DT), 1)
    assert svc.c["windows_future"] == 2 and live.pipeline.last_t_us == t + 3 * DT
    # ... then restarts at 0 (a looping replay): two held, the third starts afresh as before
    for k in range(3):
        live.handle(win(events, 103 + k, t0=k * DT), 1)
    assert svc.c["windows_past"] == 2 and svc.c["stream_restarts"] == 1
    assert live.pipeline.last_t_us == 3 * DT
    assert "windows_missed" not in svc.c


def test_a_jump_the_host_clock_or_the_newest_window_explains_is_taken_at_once(events):
    live, svc, _ = named_tracker(events, n=30)
    # the worker was stopped 5 s (host clock), the window now taken is 5 s on: a stall, not a jump
    live.handle(win(events, 30, t0=30 * DT + 5_000_000), 1 + 5_100_000_000)
    assert live.pipeline.last_t_us == 30 * DT + 5_000_000 + DT
    # catching up on a backlog: the newest window received is further on still
    live.handle(win(events, 31, t0=30 * DT + 8_000_000), 1 + 5_100_000_000, newest_end_us=30 * DT + 9_000_000)
    assert live.pipeline.last_t_us == 30 * DT + 8_000_000 + DT
    assert "windows_future" not in svc.c


def test_the_worker_does_not_take_a_far_future_window_as_the_newest_received(events):
    live, _, _ = named_tracker(events, n=30)
    assert live.window_end(win(events, 31), 1) == 32 * DT
    assert live.window_end(win(events, 31, t0=10 ** 12), 1) is None      # would make the queue look stale
    assert live.window_end(win(events, 31, t0=10 ** 12)) == 10 ** 12 + DT  # no host time: unchecked


# -- item 6: bad windows are not also missed ------------------------------------------------

def test_windows_refused_as_bad_are_not_counted_again_as_missed(events):
    svc = Counts()
    live = LiveTracker(make(), "c0", svc=svc, make_pipeline=make)
    for k in range(10):
        live.handle(win(events, k), 1)
    for _ in range(5):                                  # seq 10..14 arrive corrupt
        assert live.handle(b"\x93garbage", 1) == []
    live.handle(win(events, 15), 1)
    assert svc.c["windows_bad"] == 5 and "windows_missed" not in svc.c
    # two corrupt, five gone: three lost on the way
    for _ in range(2):
        live.handle(b"\x93garbage", 1)
    live.handle(win(events, 21), 1)
    assert svc.c["windows_bad"] == 7 and svc.c["windows_missed"] == 3


# -- item 3: state files ------------------------------------------------------------------

def _state(tracks, **kw) -> dict:
    return {"camera": "c0", "written_s": time.time() - 1, "fleet": {"v": 1, "next_id": 5000, "tracks": tracks}, **kw}


def _rec(i, robot=None, x=0.8, y=1.0):
    return {"id": i, "robot": robot, "x": x, "y": y, "t_us": 1_000_000}


def test_a_state_with_a_robot_name_twice_or_a_track_id_twice_is_refused():
    with pytest.raises(ValueError, match="'zumo1' is another track's name too"):
        check_state(_state([_rec(1, "zumo1"), _rec(2, "zumo1", x=1.5)]))
    with pytest.raises(ValueError, match="another track's ID too"):
        check_state(_state([_rec(1), _rec(1, x=1.5)]))
    assert check_state(_state([_rec(1, "zumo1"), _rec(2, "zumo2"), _rec(3), _rec(4)]))


def test_a_state_with_a_key_twice_is_refused(tmp_path):
    p = tmp_path / "s.json"
    p.write_text('{"camera":"c0","camera":"c0","written_s":%f,"fleet":{"v":1,"tracks":[],'
                 '"tracks":[{"id":1,"x":0.8,"y":1.0,"t_us":0}]}}' % (time.time() - 1))
    with pytest.raises(ValueError, match="the key 'tracks' appears twice"):
        load_state(p, "c0", 600)


def test_more_tracks_than_the_fleet_or_the_bound_are_refused_and_set_aside(tmp_path):
    assert MAX_STATE_TRACKS == 256
    with pytest.raises(ValueError, match="257 tracks, at most 256"):
        check_state(_state([_rec(i, x=0.001 * i) for i in range(257)]))
    p = tmp_path / "tracker-c0.json"
    p.write_text(json.dumps(_state([_rec(1, "zumo1"), _rec(2, x=1.2), _rec(3, x=1.5)])))
    svc = Counts()
    live = LiveTracker(Pipeline(Calibration.from_dict(calibration_dict()), fleet_size=2), "c0", svc=svc)
    _restore_state(live, p, 600.0, svc)                 # 3 tracks for a fleet of 2
    assert svc.c == {"state_rejected": 1} and (tmp_path / "tracker-c0.json.bad").exists() and not p.exists()
    assert live.pipeline.tracker.tracks == []


@pytest.mark.parametrize("kind", ["fifo", "directory"])
def test_a_state_path_that_is_not_a_regular_file_is_refused_without_waiting(tmp_path, kind):
    p = tmp_path / "tracker-c0.json"
    os.mkfifo(p) if kind == "fifo" else p.mkdir()
    got: list = []

    def load():
        try:
            got.append(load_state(p, "c0", 600))
        except ValueError as exc:
            got.append(exc)

    th = threading.Thread(target=load, daemon=True)
    th.start()
    th.join(30)   # a guard only: a blocking open of a FIFO without a writer never returns
    assert not th.is_alive(), "load_state waits on a FIFO"
    assert isinstance(got[0], ValueError) and "not a regular file" in str(got[0])


def test_restored_tracks_no_detection_confirms_are_lost_after_lost_s_and_still_reclaimable():
    ft = FleetTracker(FleetConfig())
    ft.restore({"v": 1, "next_id": 300, "tracks": [_rec(1, "zumo1", x=0.3, y=0.3)]
                + [_rec(10 + i, x=1.0 + 0.002 * i, y=1.5) for i in range(200)]})
    n_lost = int(FleetConfig().lost_s * 1e6 / DT)      # 2 s of windows
    for k in range(n_lost):
        out = ft.update([], 50_000_000 + (k + 1) * DT)
    assert len(out) == 201 and all(t.state == "coasting" for t in out)   # coasting for lost_s ...
    out = ft.update([], 50_000_000 + (n_lost + 1) * DT)
    assert out == [] and ft.snapshot()["tracks"] == [] and len(ft.dormant) == 201   # ... then lost
    # a robot that stood still through the restart moves off: its track confirms and takes the
    # restored one over (ID and name back)
    t = 50_000_000 + (n_lost + 1) * DT
    for k in range(5):
        t += DT
        x = 0.3 + 0.003 * (k + 1)
        out = ft.update([Observation(x=x, y=0.3, t_us=t, vx=0.3, vy=0.0, yaw=0.0, speed_sigma=0.01, t_vel_us=t)], t)
    assert [(m.track_id, m.robot, m.state) for m in out] == [(1, "zumo1", "confirmed")]
    assert len(ft.dormant) == 200 and math.isclose(out[0].x, 0.315, abs_tol=0.01)

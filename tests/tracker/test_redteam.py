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
from arena.events import EVENT_DTYPE, make_events
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


HOST0 = 10_000_000   # host clock (ns) of the jump tests' first window (named_tracker ran at 1 ns)


def test_a_jump_or_a_restart_is_taken_when_windows_agree_with_each_other_and_the_host_clock(events):
    live, svc, _ = named_tracker(events)
    # the camera's clock jumps 100 s ahead and streams on in real time (host 10 ms per window):
    # held until the run spans JUMP_HOST_SPAN_US (0.5 s) of host time, then taken
    assert LiveTracker.JUMP_HOST_SPAN_US == 500_000 and LiveTracker.JUMP_CONFIRM == 3
    t = 100 * DT + 100_000_000
    n_held = LiveTracker.JUMP_HOST_SPAN_US // DT          # 50 windows
    for j in range(n_held):
        assert live.handle(win(events, 100 + j, t0=t + j * DT), HOST0 + j * DT * 1000) == []
    assert live.pipeline.last_t_us == 100 * DT                # nothing of the jump processed yet
    live.handle(win(events, 100 + n_held, t0=t + n_held * DT), HOST0 + n_held * DT * 1000)
    assert svc.c["windows_future"] == n_held and live.pipeline.last_t_us == t + (n_held + 1) * DT
    # ... then restarts at 0 (a looping replay): held as long, then it starts afresh as before
    h = HOST0 + (n_held + 1) * DT * 1000
    for k in range(n_held + 1):
        live.handle(win(events, 200 + k, t0=k * DT), h + k * DT * 1000)
    assert svc.c["windows_past"] == n_held and svc.c["stream_restarts"] == 1
    assert live.pipeline.last_t_us == (n_held + 1) * DT
    assert "windows_missed" not in svc.c


@pytest.mark.parametrize("t0,n", [(10 ** 12, 3), (0, 3), (10 ** 12, 200), (-10_000_000, 200)],
                         ids=["3 at 1e12", "3 at 0 (2 s back)", "200 at 1e12", "200 at -10 s"])
def test_a_burst_of_agreeing_far_off_windows_is_held_and_names_are_kept(events, t0, n):
    """red team 2 item 2: 3 (or 200) agreeing windows stamped far off, sent at once (1 µs of host
    time apart), are all held: no restart, nothing published with their stamps, names kept."""
    live, svc, ids = named_tracker(events, n=200)
    base = HOST0
    for j in range(n):
        assert live.handle(win(events, 200 + j, t0=t0 + j * DT), base + j * 1000) == []
    assert live.pipeline.last_t_us == 200 * DT
    out = []
    for k in range(200, 230):
        out += live.handle(win(events, k, seq=200 + n + k - 200), base + n * 1000 + (k - 199) * DT * 1000,
                           newest_end_us=(k + 1) * DT)
    assert svc.c.get("windows_future" if t0 > 0 else "windows_past") == n
    assert "stream_restarts" not in svc.c
    assert max(m.stamp_us for _, m, _ in out) == 230 * DT
    assert {m.track_id: m.robot for _, m, _ in out[-2:]} == dict(zip(ids, ("zumo1", "zumo2")))


def test_windows_that_run_ahead_of_the_host_clock_do_not_confirm_a_jump(events):
    """Windows arriving 10 ms of host time apart but advancing 100 ms of sensor time each (a
    forger replaying fast) disagree with the host clock: never taken, however many."""
    live, svc, _ = named_tracker(events, n=30)
    for j in range(100):                                  # 1 s of host time, 10 s of sensor time
        assert live.handle(win(events, 30 + j, t0=10 ** 12 + j * 100_000), HOST0 + j * DT * 1000) == []
    assert svc.c["windows_future"] == 100 and live.pipeline.last_t_us == 30 * DT


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


# -- red team 2 item 1: a valid, tiny window of millions of events -----------------------------

def test_a_window_above_the_event_budget_is_subsampled_and_tracking_goes_on(events):
    """1.2 M events at one pixel row and one time in one 10 ms window (a flash, or a crafted window
    of a few kB): the pipeline gets an evenly strided subset of the budget (every pixel at 100 Hz:
    640 x 480 events per 10 ms), counted; the robots' tracks are published before and after."""
    live, svc, ids = named_tracker(events, n=100)
    pushed: list[int] = []
    push = live.pipeline.push

    def spy(ev, t_end_us):
        pushed.append(int(ev.size))
        return push(ev, t_end_us)

    live.pipeline.push = spy
    n = 1_200_000                                          # < EVENT_BUDGET_REFUSE (4) budgets
    flash = make_events(np.arange(n) % 128, np.zeros(n), np.ones(n), np.full(n, 100 * DT + 5000))  # x, y, p, t
    payload = EventWindow(camera="c0", seq=100, t_start_us=100 * DT, t_end_us=101 * DT, width=640, height=480,
                          count=n, codec="planes-zstd/1", data=encode(flash), publish_ns=1).encode()
    assert live.event_budget(EventWindow.decode(payload), live.pipeline.accumulation_us) == 640 * 480
    out = live.handle(payload, 1, newest_end_us=101 * DT)
    assert pushed == [640 * 480] and "events_late" not in svc.c
    assert svc.c["windows_subsampled"] == 1 and svc.c["events_subsampled"] == n - 640 * 480
    assert {m.track_id for _, m, _ in out} == set(ids)            # tracking went on through it
    out = []
    for k in range(101, 130):
        out += live.handle(win(events, k), 1, newest_end_us=(k + 1) * DT)
    assert max(pushed[1:]) < 640 * 480 and svc.c["windows_subsampled"] == 1   # real windows untouched
    assert {m.track_id: m.robot for _, m, _ in out[-2:]} == dict(zip(ids, ("zumo1", "zumo2")))
    assert max(m.stamp_us for _, m, _ in out) == 130 * DT


def test_the_event_budget_scales_with_the_window_and_is_capped_by_the_accumulation():
    live = LiveTracker(make(), "c0")
    acc = live.pipeline.accumulation_us
    w = lambda a, b: EventWindow(camera="c0", seq=1, t_start_us=a, t_end_us=b, width=640, height=480, count=0,
                                 codec="planes-zstd/1", data=encode(np.zeros(0, dtype=EVENT_DTYPE)), publish_ns=1)
    assert live.event_budget(w(0, 20_000), acc) == 2 * 640 * 480
    assert live.event_budget(w(0, 1_000), acc) == 640 * 480          # at least one 10 ms period
    assert live.event_budget(w(-2 ** 62, 10_000), acc) == 10 * 640 * 480   # a claimed huge span: capped


def test_a_backlog_delivered_late_after_a_stall_is_not_taken_for_a_jump(events):
    """A stopped tracker (SIGSTOP 2.4 s): on resuming it takes the window it was stopped on, then
    its transport delivers the newest second of the backlog in a burst (the rest dropped). Those
    windows lag the stream's relation to the host clock, they do not lead it: none is held as a
    jump (the old reference, the last window taken + the host time since, held them, and the
    host-clock rule would then hold them for seconds), the stale ones are processed unpublished
    as before, and tracks are published again."""
    svc = Counts()
    live = LiveTracker(make(), "c0", svc=svc, make_pipeline=make)
    host = lambda s: 10 ** 18 + int(s * 1e9)
    for k in range(50):                                    # real time: window k taken at host k * 10 ms
        live.handle(win(events, k), host(k * 0.01), newest_end_us=(k + 1) * DT)
    live.handle(win(events, 50), host(2.9), newest_end_us=51 * DT)     # resumed 2.4 s later
    newest = win(events, 289)
    out = []
    for j, k in enumerate(range(190, 290)):                # the newest 1 s, in a burst
        now = host(2.9 + 0.001 * (j + 1))
        out += live.handle(win(events, k), now, dropped_in_queue=139 if k == 190 else 0,
                           newest_end_us=live.window_end(newest, now))
    assert "windows_future" not in svc.c and "windows_past" not in svc.c
    assert svc.c.get("tracks_stale", 0) > 0 and live.pipeline.last_t_us == 290 * DT
    assert out and max(m.stamp_us for _, m, _ in out) == 290 * DT


def test_a_window_claiming_more_than_four_budgets_is_refused_undecoded(events):
    """The red team's 10 M-event window (9.3 kB): decoding it alone cost 0.3-0.5 s of CPU. Refused
    on its claimed count before decoding (here its data is not even a valid codec stream, so a
    decode would count it in windows_bad), not counted as missed; tracking goes on."""
    live, svc, ids = named_tracker(events, n=100)
    bomb = EventWindow(camera="c0", seq=100, t_start_us=100 * DT, t_end_us=101 * DT, width=640, height=480,
                       count=10_000_000, codec="planes-zstd/1", data=b"\x00" * 9000, publish_ns=1).encode()
    assert live.handle(bomb, 1, newest_end_us=101 * DT) == []
    assert svc.c["windows_over_budget"] == 1 and "windows_bad" not in svc.c
    out = []
    for k in range(101, 120):
        out += live.handle(win(events, k), 1, newest_end_us=(k + 1) * DT)
    assert "windows_missed" not in svc.c
    assert {m.track_id: m.robot for _, m, _ in out[-2:]} == dict(zip(ids, ("zumo1", "zumo2")))

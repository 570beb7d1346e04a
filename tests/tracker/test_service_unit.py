"""LiveTracker without Zenoh: bad, late and restarted windows; Track messages."""

from __future__ import annotations

import numpy as np

from arena.codec import encode
from arena.messages import EventWindow
from tests.tracker.synth import Counts, calibration_dict, line_pose, window
from tracker.calibration import Calibration
from tracker.pipeline import Pipeline
from tracker.service import Inbox, LiveTracker


def make():
    return Pipeline(Calibration.from_dict(calibration_dict()))


def win(ev, k, seq=None, t0=0):
    a, b = t0 + k * 10_000, t0 + (k + 1) * 10_000
    sl = ev[(ev["t"] >= a) & (ev["t"] < b)]
    return EventWindow(camera="c0", seq=k if seq is None else seq, t_start_us=a, t_end_us=b, width=640, height=480,
                       count=sl.size, codec="planes-zstd/1", data=encode(sl), publish_ns=1)


def test_bad_late_and_restarted_windows_are_skipped_and_tracking_goes_on():
    rng = np.random.default_rng(4)
    t0 = 2_000_000
    ev = window(rng, [line_pose(200, 200, 100.0, 0.0, t_start=t0)], t0, t0 + 600_000)
    live = LiveTracker(make(), "c0", make_pipeline=make)
    out = []
    for k in range(30):
        out += live.handle(win(ev, k, t0=t0).encode(), now_ns=5)
        if k == 10:
            assert live.handle(b"garbage", 5) == []
            w = win(ev, k, t0=t0)
            w.data = w.data[:-3]
            assert live.handle(w.encode(), 5) == []                     # corrupt payload
            assert live.handle(win(ev, k - 3, t0=t0).encode(), 5) == []  # late
            wrong = win(ev, k + 1, t0=t0)
            wrong.width = 320
            assert live.handle(wrong.encode(), 5) == []                 # not the calibrated sensor
    keys = {k for k, _, _ in out}
    assert keys == {"arena/robots/1"}
    m = out[-1][1]
    assert m.camera == "c0" and m.stamp_us == t0 + 300_000 and m.window_end_us == t0 + 300_000
    assert m.state == "confirmed"
    assert m.x == np.float64(m.x) and 0.6 < m.x < 1.0 and m.tracker_publish_ns == 5
    with live.lock:
        assert set(live.fleet) == {"arena/robots/1"}
    # the camera restarts its clock (a looping replay) and streams on in real time (host 10 ms per
    # window): once its windows have agreed with the host clock for JUMP_HOST_SPAN_US (0.5 s),
    # tracking starts afresh, no skipping
    ev2 = window(rng, [line_pose(200, 200, 100.0, 0.0)], 0, 600_000)
    for k in range(60):
        live.handle(win(ev2, k, seq=100 + k).encode(), now_ns=6 + k * 10_000_000)
    assert live.pipeline.last_t_us == 600_000


def test_tracks_take_the_names_of_ground_truth_poses_that_keep_falling_on_them():
    rng = np.random.default_rng(8)
    ev = window(rng, [line_pose(150, 200, 100.0, 0.0), line_pose(450, 300, -100.0, 0.0)], 0, 500_000)
    live = LiveTracker(make(), "c0")
    for k in range(20):
        out = live.handle(win(ev, k).encode(), now_ns=1)
    assert {key for key, _, _ in out} == {"arena/robots/1", "arena/robots/2"}
    by_id = {m.track_id: m for _, m, _ in out}
    for k in range(20, 30):
        m = by_id[2]
        live.observe_groundtruth("zumo-b", m.x + 0.02, m.y)      # near track 2, every time
        live.observe_groundtruth("bad name!", m.x, m.y)         # not a valid key name: ignored
        live.observe_groundtruth("far", m.x + 0.5, m.y)         # near no track: ignored
        out = live.handle(win(ev, k).encode(), now_ns=1)
        by_id = {m.track_id: m for _, m, _ in out}
    keys = {key for key, _, _ in out}
    assert keys == {"arena/robots/1", "arena/robots/zumo-b"}
    assert {m.robot for _, m, _ in out} == {None, "zumo-b"}
    assert {tr.robot for _, _, tr in out} == {None, "zumo-b"}


def test_state_file_round_trip_and_what_is_not_restored(tmp_path, monkeypatch):
    import json

    import pytest

    from tracker.service import default_state_path, load_state, save_state

    rng = np.random.default_rng(5)
    ev = window(rng, [line_pose(200, 200, 100.0, 0.0)], 0, 400_000)
    live = LiveTracker(make(), "c0", make_pipeline=make)
    out = []
    for k in range(40):
        out = live.handle(win(ev, k).encode(), 0)
    assert len(out) == 1
    tid = out[0][1].track_id
    path = tmp_path / "s" / "tracker-c0.json"
    save_state(path, live.snapshot())
    assert not path.with_name(path.name + ".tmp").exists()
    fleet, why = load_state(path, "c0", max_age_s=600)
    fresh = LiveTracker(make(), "c0", make_pipeline=make)
    assert fresh.restore(fleet) == [tid]
    # the restored track is published, with its ID, from the first window on
    first = fresh.handle(win(ev, 40).encode(), 0)
    assert [m.track_id for _, m, _ in first] == [tid]
    # another camera's state, a stale one, and no file at all are not restored
    assert load_state(path, "c1", 600)[0] is None
    assert load_state(path, "c0", 600, now_s=json.loads(path.read_text())["written_s"] + 601)[0] is None
    assert load_state(tmp_path / "none.json", "c0", 600)[0] is None
    path.write_text('{"camera": "c0", "fleet": ')
    with pytest.raises(ValueError, match="not JSON"):
        load_state(path, "c0", 600)
    # where it goes by default
    monkeypatch.setenv("ARENA_STATE_DIR", str(tmp_path / "x"))
    assert default_state_path("tracker-c0") == tmp_path / "x" / "tracker-c0.json"


def test_sequence_gaps_are_split_into_edge_drops_and_windows_lost_on_the_way():
    rng = np.random.default_rng(5)
    ev = window(rng, [line_pose(200, 200, 100.0, 0.0)], 0, 300_000)
    svc = Counts()
    live = LiveTracker(make(), "c0", svc=svc)
    dropped = 0
    for k in range(30):
        if k in (8, 9, 10):          # the edge dropped these three (its counter says so)
            dropped += 1
            continue
        if k in (20, 21):            # these two were lost after the edge published them
            continue
        if k in (25, 26, 27):        # our own full queue dropped these three (the inbox says so)
            continue
        w = win(ev, k)
        w.dropped = dropped
        live.handle(w.encode(), now_ns=5, dropped_in_queue=3 if k == 28 else 0)
    assert svc.c.get("windows_dropped_at_edge") == 3
    assert svc.c.get("windows_missed") == 2


def test_inbox_keeps_the_newest_counts_what_it_dropped_and_wakes_the_worker():
    import threading
    import time

    box = Inbox(3)
    for i in range(5):
        box.put(i)
    assert box.get(0.01) == (2, 2)          # 0 and 1 dropped, the oldest kept one comes first
    assert box.get(0.01) == (3, 0)
    assert box.get(0.01) == (4, 0)
    t0 = time.monotonic()
    assert box.get(0.05) == (None, 0)      # empty: returns after the timeout
    assert time.monotonic() - t0 >= 0.04
    threading.Timer(0.05, box.put, args=("late",)).start()
    t0 = time.monotonic()
    assert box.get(5.0) == ("late", 0)     # woken by the put, not by the timeout
    assert time.monotonic() - t0 < 2.0


def test_tracks_carry_the_host_capture_time_of_windows_that_know_it():
    import io

    from arena.formats.tables import TrackCsvWriter

    rng = np.random.default_rng(9)
    ev = window(rng, [line_pose(200, 200, 100.0, 0.0)], 0, 400_000)
    off = 1_700_000_000_123_456_789
    live = LiveTracker(make(), "c0")
    out = []
    for k in range(30):
        w = win(ev, k)
        if k >= 20:
            w.sensor_to_host_ns = off
        out = live.handle(w.encode(), now_ns=1) or out
        if k == 19:
            assert out and all(m.host_ns is None for _, m, _ in out)
    assert out and all(m.host_ns == m.stamp_us * 1000 + off for _, m, _ in out)
    buf = io.StringIO()
    TrackCsvWriter(buf).write([tr for _, _, tr in out], live.sensor_to_host_ns)
    header, row = buf.getvalue().splitlines()[:2]
    assert header.endswith(",host_ns")
    assert int(row.split(",")[-1]) == int(row.split(",")[0]) * 1000 + off

"""A tracker that stalled catches up instead of replaying its backlog: stale windows are skipped
(counted, logged), and only fresh tracks are published."""

from __future__ import annotations

import bisect
import json
import logging
import os
import signal
import subprocess
import threading
import time

import numpy as np
import pytest

from arena.codec import encode
from arena.messages import EventWindow, Status, Track, decode
from arena.session import open_session
from tests.conftest import arena_cmd
from tests.tracker.synth import Counts, calibration_dict, line_pose, window
from tracker.calibration import Calibration
from tracker.pipeline import Pipeline
from tracker.service import LiveTracker

ENV = {**os.environ, "PYTHONUNBUFFERED": "1"}


def _win(ev, k: int) -> bytes:
    a, b = k * 10_000, (k + 1) * 10_000
    sl = ev[np.searchsorted(ev["t"], a):np.searchsorted(ev["t"], b)]
    return EventWindow(camera="c0", seq=k, t_start_us=a, t_end_us=b, width=640, height=480, count=sl.size,
                       codec="planes-zstd/1", data=encode(sl), publish_ns=1).encode()


def test_after_a_stall_stale_windows_are_skipped_and_only_fresh_tracks_published(caplog):
    rng = np.random.default_rng(11)
    ev = window(rng, [line_pose(100, 200, 60.0, 0.0)], 0, 6_000_000)
    svc = Counts()
    live = LiveTracker(Pipeline(Calibration.from_dict(calibration_dict())), "c0", svc=svc)
    before = []
    for k in range(200):   # 2 s of normal tracking: no backlog, every window published
        before += live.handle(_win(ev, k), 1, newest_end_us=(k + 1) * 10_000)
    assert len(before) >= 190 and before[-1][1].state == "confirmed"
    # the worker stalled for 4 s: windows 200..599 are all waiting, the newest ends at 6 s
    newest = 600 * 10_000
    after = []
    with caplog.at_level(logging.WARNING, logger="tracker"):
        for k in range(200, 600):
            after += live.handle(_win(ev, k), 1, newest_end_us=newest, resumed=(k == 200))
    # windows ending before newest - (100 ms accumulation + 1 s) are skipped unprocessed: 200..488
    assert svc.c["windows_skipped_stale"] == 289
    assert svc.c["windows_in"] == 200 + 111
    # the 111 kept rebuild the 100 ms accumulation window (withheld), the stale ones among them are
    # processed but not published (tracks_stale), and the 16 fresh ones (ending within 150 ms of
    # the newest) are published
    assert svc.c["tracks_withheld"] >= 9 and svc.c["tracks_stale"] >= 80
    assert sorted({m.window_end_us for _, m, _ in after}) == [newest - 10_000 * i for i in range(15, -1, -1)]
    robot = [m for _, m, _ in after if m.state == "confirmed"]
    assert len(robot) == 16 and len({m.track_id for m in robot}) == 1     # the robot, tracked at once
    x_true = (100 + 60.0 * 6.0 - 20) / 250.0                                          # synth camera: u = 20 + 250 x
    assert abs(robot[-1].x - x_true) < 0.02
    said = [r.getMessage() for r in caplog.records if "caught up" in r.getMessage()]
    assert len(said) == 1 and "skipped 289 stale window(s), 2.89 s of sensor time" in said[0]


def test_a_small_backlog_is_processed_and_published_in_full():
    rng = np.random.default_rng(12)
    ev = window(rng, [line_pose(100, 200, 60.0, 0.0)], 0, 1_000_000)
    svc = Counts()
    live = LiveTracker(Pipeline(Calibration.from_dict(calibration_dict())), "c0", svc=svc)
    plain = LiveTracker(Pipeline(Calibration.from_dict(calibration_dict())), "c0")
    out, ref = [], []
    for k in range(100):   # always 140 ms behind the newest window received: not stale
        out += live.handle(_win(ev, k), 1, newest_end_us=(k + 1) * 10_000 + 140_000)
        ref += plain.handle(_win(ev, k), 1)
    assert len(out) == len(ref) > 90 and [m.x for _, m, _ in out] == [m.x for _, m, _ in ref]
    assert "windows_skipped_stale" not in svc.c and "tracks_withheld" not in svc.c


@pytest.mark.slow
def test_a_tracker_stopped_for_4_s_catches_up_and_publishes_no_stale_tracks(router, tmp_path):
    """SIGSTOP the live tracker for 4 s while the windows keep coming at real-time pace, then
    SIGCONT: it skips what is stale and publishes fresh tracks at once. (Before: it replayed
    the newest ~1 s of windows, publishing hundreds of tracks 1-1.5 s old.)"""
    from simulator.scenarios import Scenario, generate

    rec = generate(Scenario(n_robots=2, pattern="circle", power=1.0, duration_s=8.5, seed=7))
    (tmp_path / "calib.json").write_text(json.dumps(rec.calibration))
    ev = rec.events
    n_win = 800
    cut = np.searchsorted(ev["t"], np.arange(n_win + 1) * 10_000)
    data = [(int(cut[k + 1] - cut[k]), encode(ev[cut[k]:cut[k + 1]])) for k in range(n_win)]
    got: list[tuple[float, Track]] = []     # (monotonic s received, track)
    statuses: list[Status] = []
    lock = threading.Lock()

    def on_track(sample):
        m = decode(bytes(sample.payload))
        with lock:
            got.append((time.monotonic(), m))

    def on_status(sample):
        with lock:
            statuses.append(decode(bytes(sample.payload)))

    published: list[tuple[float, int]] = []   # (monotonic s just before the put, t_end_us)
    with open_session(router.settings("client")) as s:
        s.declare_subscriber("arena/robots/*", on_track)
        s.declare_subscriber("arena/status/tracker/tracker-cam0", on_status)
        proc = subprocess.Popen(arena_cmd("track", "--camera", "cam0", "--calibration", str(tmp_path / "calib.json"),
                                          "--no-state", "-m", "client", *router.args),
                                env=ENV, text=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        try:
            deadline = time.monotonic() + 60
            while not any(r.ok for r in s.liveliness().get("arena/alive/tracker/tracker-cam0", timeout=1.0)):
                assert time.monotonic() < deadline and proc.poll() is None, "the tracker never came up"
                time.sleep(0.2)
            pub = s.declare_publisher("arena/events/cam0")
            t0 = time.monotonic()
            t_stop = t_cont = None
            for k in range(n_win):                    # real-time pace, 10 ms windows
                if k == 200:
                    proc.send_signal(signal.SIGSTOP)
                    t_stop = time.monotonic()
                if k == 600:
                    t_cont = time.monotonic()
                    proc.send_signal(signal.SIGCONT)
                delay = t0 + k * 0.01 - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                count, blob = data[k]
                win = EventWindow(camera="cam0", seq=k, t_start_us=k * 10_000, t_end_us=(k + 1) * 10_000,
                                  width=rec.width, height=rec.height, count=count, codec="planes-zstd/1",
                                  data=blob, publish_ns=time.time_ns())
                published.append((time.monotonic(), win.t_end_us))
                pub.put(win.encode())
            # two status periods after the last window
            deadline = time.monotonic() + 10
            while time.monotonic() < deadline:
                with lock:
                    if statuses and statuses[-1].counters.get("windows_in", 0) > 300 and \
                            len(statuses) > 2 and got and got[-1][1].window_end_us == n_win * 10_000:
                        break
                time.sleep(0.1)
            time.sleep(1.2)
            assert proc.poll() is None, "the tracker died"
        finally:
            if proc.poll() is None:
                proc.send_signal(signal.SIGCONT)
                proc.terminate()
            _, err = proc.communicate(timeout=20)
    assert t_cont - t_stop > 3.5, "the publisher could not keep pace: the stop was too short to test"
    with lock:
        msgs = list(got)
        st = list(statuses)
    pub_t = [t for t, _ in published]
    stale = []
    for t_rx, m in msgs:
        if t_rx < t_cont:
            continue
        i = bisect.bisect_right(pub_t, t_rx) - 1        # the newest window published before this track came
        newest = published[i][1]
        if m.window_end_us < newest - 200_000:
            stale.append((m.track_id, (newest - m.window_end_us) / 1e3))
    assert len(stale) <= 4, f"{len(stale)} stale tracks after the resume (id, ms behind): {stale[:20]}\n{err}"
    # and it tracks the two robots again, up to the last window
    late = {m.track_id for _, m in msgs if m.window_end_us > (n_win - 50) * 10_000 and m.state == "confirmed"}
    assert len(late) == 2, err
    last = st[-1].counters
    # its full queue kept the newest ~1 s (dropping the rest), which it processed without publishing
    assert last.get("windows_dropped_in_queue", 0) >= 100 and last.get("tracks_stale", 0) >= 50, last

"""The edge service in-process on a real Zenoh session: windows published only while someone
subscribes, every event of a file delivered in order, status with the edge's counters."""

from __future__ import annotations

import threading
import time

import numpy as np

from arena.codec import decode as decode_events
from arena.events import make_events
from arena.formats import write_events
from arena.messages import Status, decode
from arena.session import ZenohSettings, open_session
from camera_edge.filters import HotPixelFilter, RoiFilter
from camera_edge.pipeline import EdgePipeline
from camera_edge.service import run_edge
from camera_edge.sources import FileSource


def _file(tmp_path, n=20_000):
    rng = np.random.default_rng(3)
    ev = make_events(rng.integers(0, 320, n), rng.integers(0, 240, n), rng.integers(0, 2, n),
                     np.sort(rng.integers(5_000_000, 5_500_000, n)))
    write_events(tmp_path / "r.raw", ev, 320, 240)
    return ev


def _session():
    return open_session(ZenohSettings(mode="peer", connect=[], listen=[]))


def test_no_subscriber_means_no_encoding(tmp_path):
    _file(tmp_path)
    with _session() as s:
        res = run_edge(s, FileSource(tmp_path / "r.raw", speed=0), EdgePipeline(slice_us=10_000), "lonely",
                       "planes-zstd/1")
    assert res["windows"] == 50 and res["windows_unsubscribed"] == 50 and res["windows_dropped"] == 0


def test_file_events_all_delivered_with_filter_counts_and_status(tmp_path):
    ev = _file(tmp_path)
    got, status = [], []
    lock = threading.Lock()
    with _session() as s:
        s.declare_subscriber("arena/events/cam9", lambda smp: (lock.acquire(), got.append(decode(bytes(smp.payload))),
                                                               lock.release()))
        s.declare_subscriber("arena/status/edge/cam9", lambda smp: status.append(decode(bytes(smp.payload))))
        roi = RoiFilter(320, 240, [(0, 0), (160, 0), (160, 240), (0, 240)])  # left half
        res = run_edge(s, FileSource(tmp_path / "r.raw", speed=0), EdgePipeline([roi], slice_us=10_000), "cam9",
                       "planes-zstd/1")
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and len(got) < res["windows"]:
            time.sleep(0.02)
    assert res["windows_unsubscribed"] == 0
    with lock:
        msgs = sorted(got, key=lambda m: m.seq)
    assert [m.seq for m in msgs] == list(range(50))
    out = np.concatenate([decode_events(m.codec, m.data, m.count) for m in msgs])
    np.testing.assert_array_equal(out, ev[ev["x"] < 161])
    assert sum(m.filtered for m in msgs) == ev.size - out.size
    final = [st for st in status if isinstance(st, Status)][-1]
    assert final.counters["events_in"] == ev.size
    assert final.counters["events_filtered"] == ev.size - out.size
    assert final.counters["events_out"] == out.size and final.counters["bytes_out"] > 0


def test_learnt_hot_pixels_are_reported_in_status_and_log_and_saved(tmp_path, caplog):
    rng = np.random.default_rng(5)
    n = 20_000
    ev = make_events(rng.integers(0, 320, n), rng.integers(0, 240, n), rng.integers(0, 2, n),
                     np.sort(rng.integers(0, 1_500_000, n)))
    hot = make_events(np.full(3000, 17), np.full(3000, 9), np.ones(3000), np.linspace(0, 1_499_000, 3000))
    ev = np.concatenate([ev, hot])
    ev = ev[np.argsort(ev["t"], kind="stable")]
    write_events(tmp_path / "h.raw", ev, 320, 240)
    status = []
    caplog.set_level("INFO", logger="camera_edge.service")
    with _session() as s:
        s.declare_subscriber("arena/status/edge/cam8", lambda smp: status.append(decode(bytes(smp.payload))))
        f = HotPixelFilter(320, 240, learn_us=500_000)
        run_edge(s, FileSource(tmp_path / "h.raw", speed=0), EdgePipeline([f], slice_us=10_000), "cam8",
                 "planes-zstd/1", hot_save=tmp_path / "hot.txt")
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and not status:
            time.sleep(0.02)
    final = [st for st in status if isinstance(st, Status)][-1]
    assert final.gauges["hot_pixels"] == 1
    assert "1 hot pixel(s) masked: 17,9" in caplog.text
    assert (tmp_path / "hot.txt").read_text().split() == ["17,9"]          # for --hot-pixels FILE
    assert HotPixelFilter.load(tmp_path / "hot.txt").tolist() == [[17, 9]]
    after_learning = int((hot["t"] >= 500_000).sum())
    assert final.gauges["filter_hot_pixel_in"] - final.gauges["filter_hot_pixel_out"] == after_learning


def test_a_slow_publisher_drops_the_oldest_windows_and_keeps_the_newest():
    # windows of 1 M events take ~25 ms each to encode: submitted at once from a live source
    # (no waiting), the bounded queue drops the oldest, counts them and numbers the rest in order
    from arena.service import Service
    from camera_edge.pipeline import Window
    from camera_edge.service import WindowPublisher

    rng = np.random.default_rng(2)
    n = 1_000_000
    big = make_events(rng.integers(0, 320, n), rng.integers(0, 240, n), rng.integers(0, 2, n),
                      np.sort(rng.integers(0, 10_000, n)))
    got = []
    with _session() as s:
        s.declare_subscriber("arena/events/slow", lambda smp: got.append(decode(bytes(smp.payload))))
        time.sleep(0.2)
        with Service(s, "edge", "slow") as svc:
            pub = WindowPublisher(s, "slow", 320, 240, svc, "planes-zstd/1", queue_size=8)
            windows = [Window(k * 10_000, (k + 1) * 10_000, big, 0) for k in range(30)]
            for k in range(0, 30, 3):
                pub.submit(windows[k:k + 3], block=False)
            pub.close(timeout_s=20)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and len(got) < 30 - pub.dropped:
            time.sleep(0.05)
    assert 0 < pub.dropped < 30 and len(got) == 30 - pub.dropped
    seqs = [m.seq for m in got]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    starts = [m.t_start_us // 10_000 for m in got]
    assert starts[-8:] == list(range(22, 30))           # the newest queue's worth all published
    assert [m.seq for m in got] == starts                # seq counts dropped windows too
    assert got[-1].dropped == pub.dropped

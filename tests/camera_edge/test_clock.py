"""The sensor -> host clock offset: a sliding minimum of host - sensor time, published with every
window of a live (or real-paced) source, absent for a file replayed as fast as possible."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from arena.events import make_events
from arena.formats import write_events
from arena.messages import decode
from arena.session import ZenohSettings, open_session
from camera_edge.clock import SensorClock
from camera_edge.pipeline import EdgePipeline
from camera_edge.service import run_edge
from camera_edge.sources import FileSource


def test_the_offset_is_the_least_delayed_sample_of_the_last_window_and_restarts_when_time_goes_back():
    c = SensorClock(window_s=1.0)
    assert c.offset_ns is None and c.host_ns(5) is None
    true = 1_700_000_000_000_000_000  # host ns at sensor time 0
    delays_ms = [3.0, 0.4, 7.0, 2.0]
    for i, d in enumerate(delays_ms):
        c.observe(i * 100_000, true + i * 100_000_000 + int(d * 1e6))
    assert c.offset_ns == true + 400_000                       # the 0.4 ms sample
    assert c.host_ns(250_000) == true + 250_000_000 + 400_000
    # 1.2 s later the 0.4 ms sample has aged out: the least delay within the last second wins
    for i, d in enumerate([5.0, 1.5, 6.0], start=12):
        c.observe(i * 100_000, true + i * 100_000_000 + int(d * 1e6))
    assert c.offset_ns == true + 1_500_000
    c.observe(0, true + 2_000_000_000)                         # a restarted camera
    assert c.resets == 1 and c.offset_ns == true + 2_000_000_000
    with pytest.raises(ValueError):
        SensorClock(window_s=0)


def _run(tmp_path, speed):
    rng = np.random.default_rng(2)
    n = 4000
    t0 = 7_000_000
    ev = make_events(rng.integers(0, 64, n), rng.integers(0, 48, n), rng.integers(0, 2, n),
                     np.sort(rng.integers(t0, t0 + 300_000, n)))
    write_events(tmp_path / "c.raw", ev, 64, 48)
    got, lock = [], threading.Lock()

    def on(smp):
        with lock:
            got.append((decode(bytes(smp.payload)), time.time_ns()))

    with open_session(ZenohSettings(mode="peer", connect=[], listen=[])) as s:
        s.declare_subscriber("arena/events/clk", on)
        t_start = time.time_ns()
        res = run_edge(s, FileSource(tmp_path / "c.raw", speed=speed), EdgePipeline(slice_us=10_000), "clk",
                       "planes-zstd/1")
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            with lock:
                if len(got) >= res["windows"]:
                    break
            time.sleep(0.01)
    return t_start, got


def test_a_real_paced_file_carries_host_capture_times_a_fast_replay_none(tmp_path):
    t_start, got = _run(tmp_path, speed=1.0)
    assert len(got) >= 25
    for msg, arrived_ns in got:
        assert msg.sensor_to_host_ns is not None
        host_end = msg.t_end_us * 1000 + msg.sensor_to_host_ns
        # the window's end happened on the host after the replay started and before it arrived
        assert t_start - 20e6 <= host_end <= arrived_ns + 20e6
    fast = _run(tmp_path, speed=0)[1]
    assert fast and all(m.sensor_to_host_ns is None for m, _ in fast)

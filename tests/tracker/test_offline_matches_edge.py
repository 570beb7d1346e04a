"""The offline tracker sees the windows the live tracker sees (issue 21): `arena edge FILE`
publishes through a real `arena router` on loopback, a subscriber decodes every window
(arena.codec), and they equal, window by window (t_start, t_end, every event in order), the
slices of the same file by :func:`tracker.pipeline.iter_slices`, which `arena track --input` uses."""

from __future__ import annotations

import json
import os
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from arena.codec import decode as decode_events
from arena.formats import iter_events, write_events
from arena.messages import EventWindow
from arena.session import open_session
from arena.slicing import Slicer
from tests.conftest import arena_cmd
from tracker.pipeline import iter_slices

ENV = {**os.environ, "PYTHONUNBUFFERED": "1"}
SLICE_US = 10_000


def _wait(cond, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return
        time.sleep(0.05)
    raise AssertionError(f"{what} within {timeout} s")


def edge_windows(router, path: Path, camera: str) -> list[tuple[int, int, np.ndarray]]:
    """Every window `arena edge PATH --speed 0` publishes, decoded, in order of seq."""
    got: dict[int, EventWindow] = {}
    lock = threading.Lock()

    def on_window(sample) -> None:
        msg = EventWindow.decode(bytes(sample.payload))
        with lock:
            got[msg.seq] = msg

    key = f"arena/events/{camera}"
    with open_session(router.settings("client")) as s, open_session(router.settings("client")) as probe:
        s.declare_subscriber(key, on_window)
        # the router knows our subscriber once another client's publisher matches it; the edge,
        # connecting later, then learns of it when its session opens (it skips encoding otherwise)
        pub = probe.declare_publisher(key)
        _wait(lambda: pub.matching_status.matching, 10, "the router never matched the subscriber")
        pub.undeclare()
        r = subprocess.run(arena_cmd("edge", str(path), "--camera", camera, "--speed", "0", "--codec",
                                     "planes-zstd/1", *router.args), env=ENV, capture_output=True, text=True,
                           timeout=120)
        assert r.returncode == 0, r.stderr
        n = int(r.stderr.split(" windows,")[0].rsplit(" ", 1)[1])   # "... N windows, D dropped ..."
        assert " 0 dropped" in r.stderr, r.stderr
        _wait(lambda: len(got) >= n, 10, f"the subscriber did not get all {n} windows (got {len(got)})")
    with lock:
        msgs = [got[k] for k in sorted(got)]
    assert [m.seq for m in msgs] == list(range(n)), "windows missing (unsubscribed at the edge?)"
    return [(m.t_start_us, m.t_end_us, decode_events(m.codec, bytes(m.data), m.count)) for m in msgs]


def offline_windows(path: Path) -> tuple[list[tuple[int, np.ndarray]], Slicer]:
    slicer = Slicer(SLICE_US)
    with iter_events(path) as reader:
        return [(t_end, ev.copy()) for t_end, ev in iter_slices(reader, SLICE_US, slicer=slicer)], slicer


def assert_same_windows(edge, offline) -> None:
    assert len(edge) == len(offline), f"edge published {len(edge)} windows, offline cut {len(offline)}"
    for k, ((t0, t1, ev_edge), (t_end, ev_off)) in enumerate(zip(edge, offline)):
        assert (t1, t1 - t0) == (t_end, SLICE_US), f"window {k}: edge [{t0}, {t1}), offline ends {t_end}"
        assert t1 % SLICE_US == 0
        np.testing.assert_array_equal(ev_edge, ev_off, err_msg=f"window {k} ending {t1} µs")


@pytest.fixture(scope="module")
def jittered(tmp_path_factory):
    """A simulated 2-robot recording starting off the 10 ms grid (12 345 µs) with 40 events
    arriving up to 15 ms late, written as .npz (which keeps the order)."""
    from simulator.scenarios import Scenario, generate

    rec = generate(Scenario(n_robots=2, pattern="circle", power=1.0, duration_s=1.0, seed=21))
    ev = rec.events.copy()
    ev["t"] += 12_345 - int(ev["t"][0])
    rng = np.random.default_rng(21)
    idx = rng.choice(np.arange(1_000, ev.size - 1_000), 40, replace=False)
    ev["t"][idx] -= rng.integers(1, 15_000, idx.size)
    d = tmp_path_factory.mktemp("jitter")
    write_events(d / "rec.npz", ev, rec.width, rec.height)
    (d / "calib.json").write_text(json.dumps(rec.calibration))
    return d, ev


@pytest.mark.slow
def test_offline_windows_equal_the_edges_on_a_recording_with_late_events(router, jittered):
    d, ev = jittered
    edge = edge_windows(router, d / "rec.npz", "cmp")
    offline, slicer = offline_windows(d / "rec.npz")
    assert_same_windows(edge, offline)
    assert edge[0][0] == 10_000 and edge[0][2]["t"][0] == 12_345          # on the sensor clock's grid
    assert sum(w[2].size for w in edge) == ev.size                         # nothing dropped, late ones too
    late_edge = sum(int(np.count_nonzero(w[2]["t"] < w[0])) for w in edge)
    assert slicer.late == late_edge and 10 <= late_edge <= 40
    # and `arena track --input` says how many came late
    r = subprocess.run(arena_cmd("track", "--input", str(d / "rec.npz"), "--calibration", str(d / "calib.json"),
                                 "--tracks-out", str(d / "t.csv")), capture_output=True, text=True, timeout=240)
    assert r.returncode == 0, r.stderr
    assert f"{len(offline)} slices" in r.stderr and f"{late_edge} late event(s)" in r.stderr, r.stderr


@pytest.mark.slow
def test_offline_windows_equal_the_edges_on_the_shared_real_recording(router, shared_data):
    path = shared_data / "evt3_sample.raw"
    if not path.is_file():
        pytest.skip(f"{path} not found (the shared real EVT 3.0 sample)")
    edge = edge_windows(router, path, "real")
    offline, slicer = offline_windows(path)
    assert_same_windows(edge, offline)
    # 8.8 ms of a real camera from 11 718 656 µs: two windows on the 10 ms grid, not one from the first event
    assert [(w[0], w[1]) for w in edge] == [(11_710_000, 11_720_000), (11_720_000, 11_730_000)]
    assert slicer.late == 0

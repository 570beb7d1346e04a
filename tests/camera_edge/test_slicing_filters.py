"""The edge's filters on labelled simulator data, and the edge pipeline (slice, then filter).

The Slicer itself is shared with the offline tracker: tests/arena/test_slicing.py."""

from __future__ import annotations

import json

import numpy as np
import pytest

from arena.events import make_events
from camera_edge.filters import BackgroundActivityFilter, HotPixelFilter, RoiFilter
from camera_edge.pipeline import EdgePipeline


@pytest.fixture(scope="module")
def labelled():
    from simulator.scenarios import Scenario, generate

    rec = generate(Scenario(n_robots=3, pattern="circle", duration_s=1.5, seed=3))
    return rec


def test_background_filter_keeps_signal_drops_noise(labelled):
    ev, sig = labelled.events, labelled.is_signal
    assert (~sig).sum() > 1000, "the scenario should contain noise"
    f = BackgroundActivityFilter(labelled.width, labelled.height, dt_us=10_000)
    keep = np.zeros(ev.size, bool)
    # filter in chunks, as the edge does, and find which events were kept
    idx = np.arange(ev.size)
    for a in range(0, ev.size, 50_000):
        chunk = ev[a:a + 50_000]
        kept = f(chunk)
        keep[idx[a:a + 50_000][np.isin(chunk, kept)]] = True
    signal_kept = keep[sig].mean()
    noise_dropped = 1 - keep[~sig].mean()
    assert signal_kept >= 0.95, signal_kept
    assert noise_dropped >= 0.90, noise_dropped
    assert f.n_in == ev.size and f.n_out == keep.sum()


def test_hot_pixels_are_learned_and_saved(tmp_path):
    rng = np.random.default_rng(1)
    n = 50_000
    ev = make_events(rng.integers(0, 320, n), rng.integers(0, 240, n), rng.integers(0, 2, n),
                     np.sort(rng.integers(0, 3_000_000, n)))
    hot = make_events(np.full(3000, 17), np.full(3000, 9), np.ones(3000), np.linspace(0, 3_000_000, 3000))
    ev = np.concatenate([ev, hot])
    ev = ev[np.argsort(ev["t"], kind="stable")]
    f = HotPixelFilter(320, 240, learn_us=1_000_000)
    out = np.concatenate([f(ev[a:a + 7000]) for a in range(0, ev.size, 7000)])
    assert f.hot_pixels_.tolist() == [[17, 9]]
    late = out[out["t"] > 1_000_000]
    assert not ((late["x"] == 17) & (late["y"] == 9)).any()
    f.save(tmp_path / "hot.txt")
    g = HotPixelFilter(320, 240, path=tmp_path / "hot.txt")
    assert not g.learning and g(hot).size == 0


def test_hot_pixels_are_learned_on_a_scene_with_moving_robots(labelled):
    # the simulator's hot pixels (50 Hz) are its noise pixels with many events; the robots' busy
    # paths must neither hide them (a threshold on the mean rate of active pixels did: it learnt
    # none) nor be taken for hot pixels themselves
    ev, sig = labelled.events, labelled.is_signal
    w = labelled.width
    noisy = np.bincount(ev["y"][~sig].astype(np.int64) * w + ev["x"][~sig], minlength=w * labelled.height)
    truth = sorted((int(k % w), int(k // w)) for k in np.flatnonzero(noisy >= 20))
    assert len(truth) == 5
    f = HotPixelFilter(w, labelled.height, learn_us=1_000_000)
    out = np.concatenate([f(ev[a:a + 50_000]) for a in range(0, ev.size, 50_000)])
    assert sorted(map(tuple, f.hot_pixels_.tolist())) == truth
    late = out[out["t"] >= ev["t"][0] + 1_000_000]
    hot_key = set(y * w + x for x, y in truth)
    assert not np.isin(late["y"].astype(np.int64) * w + late["x"], list(hot_key)).any()
    after = ev["t"] >= ev["t"][0] + 1_000_000
    assert (ev[after & sig].size - np.isin(ev[after & sig], out).sum()) == 0   # no signal event lost


def test_roi_from_calibration_keeps_inside_only(labelled):
    f = RoiFilter.from_calibration(json.loads(json.dumps(labelled.calibration)))
    inside = make_events([320], [240], [1], [0])
    outside = make_events([2], [2], [1], [0])
    assert f(inside).size == 1 and f(outside).size == 0
    assert f.n_in == 2 and f.n_out == 1


def test_pipeline_counts_filtered_events_per_window():
    f = RoiFilter(100, 100, [(0, 0), (50, 0), (50, 50), (0, 50)])
    p = EdgePipeline([f], slice_us=1000)
    ev = make_events([10, 90, 20, 95], [10, 90, 20, 95], [1, 1, 1, 1], [0, 100, 1500, 2500])
    wins = p.push(ev) + p.flush()
    assert [(w.events.size, w.filtered) for w in wins] == [(1, 1), (1, 0), (0, 1)]
    assert (p.n_in, p.n_out) == (4, 2)


def test_concat_events_joins_bytes_of_contiguous_arrays_and_falls_back_otherwise():
    from arena.events import concat_events, make_events
    rng = np.random.default_rng(4)
    ev = make_events(rng.integers(0, 640, 500), rng.integers(0, 480, 500), rng.integers(0, 2, 500),
                     np.sort(rng.integers(0, 10_000, 500)))
    parts = [ev[:120], ev[120:121], ev[121:]]
    assert np.array_equal(concat_events(parts), ev)
    strided = [ev[::2], ev[1::2]]            # not contiguous: numpy's concatenate
    assert np.array_equal(concat_events(strided), np.concatenate(strided))
    assert concat_events([]).size == 0 and concat_events([ev]) is ev


def test_select_events_equals_boolean_indexing():
    from arena.events import make_events, select_events
    rng = np.random.default_rng(6)
    ev = make_events(rng.integers(0, 640, 700), rng.integers(0, 480, 700), rng.integers(0, 2, 700),
                     np.sort(rng.integers(0, 10_000, 700)))
    keep = rng.random(700) < 0.7
    assert np.array_equal(select_events(ev, keep), ev[keep])
    assert np.array_equal(select_events(ev[::3], keep[::3]), ev[::3][keep[::3]])   # strided
    assert select_events(ev, np.zeros(700, bool)).size == 0
    order = np.random.default_rng(1).permutation(700)[:500]      # an index array too
    assert np.array_equal(select_events(ev, order), ev[order])

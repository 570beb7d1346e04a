"""Incremental DBSCAN: the neighbour index and the detector give exactly the full-window
grid DBSCAN's results at every slice of realistic noisy streams."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.ndimage import correlate

from arena.events import make_events
from tests.tracker.synth import calibration_dict, line_pose, window
from tracker.accumulate import PixelWindow
from tracker.calibration import Calibration
from tracker.dbscan import core_mask, dbscan_from_cores, dbscan_grid, disk_half_widths
from tracker.density import TILE, NeighbourIndex
from tracker.detect import Detector, DetectorConfig
from tracker.pipeline import Pipeline, iter_slices

W, H = 640, 480


def noisy_stream(seed: int, bg_hz: float, seconds: float = 0.6, hot: int = 20, n_robots: int = 4,
                 meet: bool = False):
    """Robots crossing the sensor, uniform background at bg_hz per pixel, hot pixels at 200 Hz
    and bursts (shot noise): events sorted by t, µs from 0. ``meet``: two more robots drive
    head-on into each other (one cluster from ~0.33 s to ~0.47 s)."""
    rng = np.random.default_rng(seed)
    t1 = int(seconds * 1e6)
    poses = [line_pose(80 + 110 * k, 90 + 70 * k, 180.0 * (-1) ** k, 90.0 - 40 * k) for k in range(n_robots)]
    if meet:
        poses += [line_pose(200, 440, 200.0, 0.0), line_pose(360, 440, -200.0, 0.0)]
    ev = window(rng, poses, 0, t1, noise_per_px_s=bg_hz)
    hx, hy = rng.integers(0, W, hot), rng.integers(0, H, hot)
    nh = rng.poisson(200 * seconds, hot)
    hot_ev = make_events(np.repeat(hx, nh), np.repeat(hy, nh), rng.integers(0, 2, nh.sum()),
                         rng.integers(0, t1, nh.sum()))
    nb = int(60 * seconds * 10)     # bursts: 3-8 events at one pixel within 1 ms
    bx, by, bt = rng.integers(0, W, nb), rng.integers(0, H, nb), rng.integers(0, t1 - 1000, nb)
    k = rng.integers(3, 9, nb)
    burst = make_events(np.repeat(bx, k), np.repeat(by, k), rng.integers(0, 2, k.sum()),
                        np.repeat(bt, k) + rng.integers(0, 1000, k.sum()))
    allev = np.concatenate([ev, hot_ev, burst])
    return allev[np.argsort(allev["t"], kind="stable")]


def direct_neighbours(u, v, eps):
    occ = np.zeros((H, W), np.int64)
    occ[v, u] = 1
    half = disk_half_widths(eps)
    rad = (half.size - 1) // 2
    disk = np.zeros((2 * rad + 1, 2 * rad + 1), np.int64)
    for r, w in enumerate(half):
        disk[r, rad - w:rad + w + 1] = 1
    return correlate(occ, disk, mode="constant")


def incremental_labels(index, pw, min_samples):
    """Labels over pw.pixels()' order from the index (pixels it leaves out are noise)."""
    pix, slots, core = index.select(pw.slot_map, pw.n_active, min_samples)
    labels = np.full(pw.n_active, -1, np.int64)
    if core.any():
        labels[slots] = dbscan_from_cores(pix % W, pix // W, core, index.eps)
    return labels


@settings(max_examples=150, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 300), st.integers(3, 60),
       st.sampled_from([1.0, 1.5, 2.0, 2.9, 4.5, 5.88, 7.3]), st.integers(1, 15))
def test_labels_from_cores_equal_grid_dbscan(seed, n, extent, eps, min_samples):
    rng = np.random.default_rng(seed)
    pts = np.unique(rng.integers(0, extent, size=(n, 2)), axis=0)
    pts = pts[rng.permutation(len(pts))]
    u, v = pts[:, 0], pts[:, 1]
    core = core_mask(u, v, eps, min_samples)
    full = dbscan_grid(u, v, eps, min_samples)
    assert np.array_equal(dbscan_from_cores(u, v, core, eps), full)
    # leaving out pixels farther than eps from every core changes no other label
    if core.any():
        d2 = ((pts[:, None, :] - pts[None, core, :]) ** 2).sum(-1).min(1)
        keep = d2 <= eps * eps
        assert np.array_equal(dbscan_from_cores(u[keep], v[keep], core[keep], eps), full[keep])
        assert np.all(full[~keep] == -1)


@pytest.mark.parametrize("flip", [False, True])
def test_border_tie_goes_to_the_core_listed_first(flip):
    """A border pixel equidistant from cores of two clusters: the grid rule (the core of
    smallest index) decides, for both backends alike."""
    blob = [(dx, dy) for dx in (-2, -1, 0) for dy in (-1, 0, 1)]
    left = [(x, y) for x, y in blob]
    right = [(4 - x, y) for x, y in blob]
    pts = np.array((right + left if flip else left + right) + [(2, 0)])
    u, v = pts[:, 0], pts[:, 1]
    core = core_mask(u, v, 2.0, 5)
    assert not core[-1] and core[:-1].all()
    got = dbscan_from_cores(u, v, core, 2.0)
    assert np.array_equal(got, dbscan_grid(u, v, 2.0, 5))
    assert got[-1] == 0          # cluster 0 holds the first-listed core: (0, 0) or (4, 0)


@pytest.mark.parametrize("bg_hz", [0.5, 2.0])
def test_neighbour_counts_follow_the_window(bg_hz):
    ev = noisy_stream(3, bg_hz, seconds=0.35)
    pw = PixelWindow(W, H, 100_000)
    idx = NeighbourIndex(W, H, 5.88, noise_cell=24)
    pw.attach(idx)
    for k, (t_end, sl) in enumerate(iter_slices([ev], 10_000, start_us=0)):
        pw.push(sl, t_end)
        if k % 5 != 4:
            continue
        u, v = pw.pixels()[:2]
        every = np.arange(W * H)
        assert np.array_equal(idx.neighbours(every), direct_neighbours(u, v, 5.88).ravel())
        gw = W // 24 + 1
        assert np.array_equal(idx.noise_counts, np.bincount((v // 24) * gw + u // 24, minlength=gw * (H // 24 + 1)))


@pytest.mark.parametrize("bg_hz", [0.5, 2.0])
@pytest.mark.parametrize("eps,min_samples", [(5.88, 21), (5.88, 14), (4.0, 9), (7.3, 40)])
def test_incremental_labels_equal_full_grid_dbscan_every_slice(bg_hz, eps, min_samples):
    ev = noisy_stream(int(eps * 10) + min_samples, bg_hz, seconds=0.4)   # 3 window turnovers, 37 slices
    pw = PixelWindow(W, H, 100_000)
    idx = NeighbourIndex(W, H, eps, noise_cell=24)
    attached = False
    n_clusters = 0
    for k, (t_end, sl) in enumerate(iter_slices([ev], 10_000, start_us=0)):
        pw.push(sl, t_end)
        if k == 3:          # attached to a window already holding pixels: rebuilt from them
            pw.attach(idx)
            attached = True
        if not attached:
            continue
        u, v = pw.pixels()[:2]
        full = dbscan_grid(u, v, eps, min_samples)
        assert np.array_equal(incremental_labels(idx, pw, min_samples), full), f"slice ending {t_end} µs"
        n_clusters += int(full.max()) + 1
    assert n_clusters > 100   # the robots were found: the comparison was not between empty results


def test_background_tiles_are_not_scanned_every_slice():
    """0.5 Hz/px of background alone: a query scans only a small share of the tiles."""
    rng = np.random.default_rng(5)
    pw = PixelWindow(W, H, 100_000)
    idx = NeighbourIndex(W, H, 5.88, noise_cell=24)
    pw.attach(idx)
    n_tiles = ((W + TILE - 1) // TILE) * ((H + TILE - 1) // TILE)
    due = []
    for k in range(60):
        n = rng.poisson(0.5 * W * H * 0.01)
        sl = make_events(rng.integers(0, W, n), rng.integers(0, H, n), rng.integers(0, 2, n),
                         np.sort(rng.integers(k * 10_000, (k + 1) * 10_000, n)))
        pw.push(sl, (k + 1) * 10_000)
        if k >= 20:
            due.append(idx.tiles_due(21))
        idx.select(pw.slot_map, pw.n_active, 21)
    assert np.mean(due) < 0.3 * n_tiles, (np.mean(due), n_tiles)


def _key(d) -> str:
    return repr(dataclasses.astuple(d))


def test_detector_incremental_equals_full_recompute_every_slice():
    """The default pipeline (incremental) and the full re-clustering give the same detections,
    splits by predictions included, on crossing robots in realistic noise; after a time
    re-base too (the window re-bases its clock after 20 s)."""
    ev = noisy_stream(11, 0.5, seconds=1.2, n_robots=4, meet=True)
    late = ev[ev["t"] >= 600_000].copy()
    late["t"] += 20_000_000      # a 20 s gap: everything expires and the window re-bases
    ev = np.concatenate([ev[ev["t"] < 600_000], late])
    cal = Calibration.from_dict(calibration_dict())
    inc, full = Pipeline(cal, fleet_size=6), Pipeline(cal, fleet_size=6)
    full.detector.config.incremental = False
    n_det = 0
    splits = []
    real_split = inc.detector._split

    def counting_split(labels, k, *args):
        out = real_split(labels, k, *args)
        splits.append(out[1] - k)
        return out

    inc.detector._split = counting_split
    for t_end, sl in iter_slices([ev], 10_000, start_us=0):
        inc.push(sl, t_end)
        full.push(sl, t_end)
        assert [_key(d) for d in inc.detections_] == [_key(d) for d in full.detections_], f"slice ending {t_end} µs"
        assert inc.detector.min_samples_ == full.detector.min_samples_
        n_det += len(inc.detections_)
    assert isinstance(inc.pixels.index, NeighbourIndex)
    assert full.pixels.index is None
    assert n_det > 300
    assert sum(1 for k in splits if k > 0) >= 3      # clusters were split by the predictions
    assert inc.pixels.t_ref_us >= 20_000_000         # and the window re-based its clock


def test_index_validation_and_reattach():
    with pytest.raises(ValueError, match="too large"):
        NeighbourIndex(W, H, 120.0, noise_cell=24)
    with pytest.raises(ValueError, match="noise_cell"):
        NeighbourIndex(W, H, 5.0, noise_cell=0)
    with pytest.raises(ValueError, match="incremental"):
        DetectorConfig(incremental="yes").validate()
    # a detector with other parameters replaces the window's index (and still agrees)
    ev = noisy_stream(2, 0.5, seconds=0.25)
    pw = PixelWindow(W, H, 100_000)
    a, b = Detector(250.0, W, H), Detector(250.0, W, H, DetectorConfig(eps_chassis=0.3))
    ref_b = Detector(250.0, W, H, DetectorConfig(eps_chassis=0.3, incremental=False))
    for t_end, sl in iter_slices([ev], 10_000, start_us=0):
        pw.push(sl, t_end)
        a.detect_window(pw, t_end)
    got = b.detect_window(pw, t_end)
    assert pw.index.eps == b.eps_px != a.eps_px
    assert [_key(d) for d in got] == [_key(d) for d in ref_b.detect_window(pw, t_end)]

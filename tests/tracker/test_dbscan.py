"""The grid DBSCAN backend gives scikit-learn's clusters (property-based and on windows)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from sklearn.cluster import DBSCAN

from tests.tracker.synth import line_pose, window
from tracker.dbscan import core_mask, dbscan_grid, dbscan_sklearn


def assert_same_as_sklearn(pts: np.ndarray, eps: float, min_samples: int) -> None:
    ref = DBSCAN(eps=eps, min_samples=min_samples).fit(pts.astype(float))
    core = np.zeros(len(pts), bool)
    core[ref.core_sample_indices_] = True
    got = dbscan_grid(pts[:, 0], pts[:, 1], eps, min_samples)
    assert np.array_equal(core_mask(pts[:, 0], pts[:, 1], eps, min_samples), core)
    # core pixels: identical labels (same numbering); noise: identical
    assert np.array_equal(got[core], ref.labels_[core])
    assert np.array_equal(got < 0, ref.labels_ < 0)
    # border pixels: a cluster of one of the cores within eps (DBSCAN's order decides which)
    border = np.flatnonzero(~core & (got >= 0))
    if border.size:
        from scipy.spatial import cKDTree

        core_labels = ref.labels_[core]
        near = cKDTree(pts[core].astype(float)).query_ball_point(pts[border].astype(float), eps + 1e-9)
        for i, js in zip(border, near):
            assert got[i] in set(core_labels[js].tolist())


@settings(max_examples=150, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 300), st.integers(3, 60),
       st.sampled_from([1.0, 1.5, 2.0, 2.9, 4.5, 6.0, 7.3, 15.0]), st.integers(1, 15))
def test_grid_equals_sklearn_on_random_pixels(seed, n, extent, eps, min_samples):
    rng = np.random.default_rng(seed)
    pts = np.unique(rng.integers(0, extent, size=(n, 2)), axis=0)
    assert_same_as_sklearn(pts, eps, min_samples)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("eps,min_samples", [(15.0, 170), (6.0, 50), (6.25, 14)])
def test_grid_equals_sklearn_on_event_windows(seed, eps, min_samples):
    rng = np.random.default_rng(seed)
    poses = [line_pose(100 + 90 * k, 120 + 60 * k, 100.0 * (-1) ** k, 60.0) for k in range(4)]
    ev = window(rng, poses, 0, 100_000, noise_per_px_s=0.2)
    pts = np.unique(np.column_stack([ev["x"], ev["y"]]).astype(np.int64), axis=0)
    assert_same_as_sklearn(pts, eps, min_samples)


@pytest.mark.parametrize("noise_hz", [0.5, 2.0])
@pytest.mark.parametrize("eps,min_samples", [(5.88, 21), (6.25, 40)])
def test_grid_equals_sklearn_on_realistic_background(noise_hz, eps, min_samples):
    """Sensor background of real cameras (0.5-2 Hz per pixel over a 100 ms window)."""
    rng = np.random.default_rng(int(noise_hz * 10) + min_samples)
    poses = [line_pose(100 + 90 * k, 120 + 60 * k, 100.0 * (-1) ** k, 60.0) for k in range(4)]
    ev = window(rng, poses, 0, 100_000, noise_per_px_s=noise_hz)
    pts = np.unique(np.column_stack([ev["x"], ev["y"]]).astype(np.int64), axis=0)
    assert len(pts) > 0.04 * noise_hz * 640 * 480
    assert_same_as_sklearn(pts, eps, min_samples)


def test_simulated_window_matches_sklearn():
    from simulator.scenarios import Scenario, generate

    rec = generate(Scenario(n_robots=3, pattern="cross", power=1.0, duration_s=1.0, seed=11))
    ev = rec.events[(rec.events["t"] >= 800_000) & (rec.events["t"] < 900_000)]
    pts = np.unique(np.column_stack([ev["x"], ev["y"]]).astype(np.int64), axis=0)
    for eps, ms in ((15.0, 170), (6.0, 50), (5.9, 14)):
        assert_same_as_sklearn(pts, eps, ms)


def test_backends_agree_and_validate_input():
    pts = np.array([[0, 0], [0, 1], [1, 0], [9, 9]])
    assert list(dbscan_grid(pts[:, 0], pts[:, 1], 1.0, 3)) == list(dbscan_sklearn(pts[:, 0], pts[:, 1], 1.0, 3))
    assert dbscan_grid(np.empty(0), np.empty(0), 2.0, 3).size == 0
    with pytest.raises(ValueError, match="eps"):
        dbscan_grid(pts[:, 0], pts[:, 1], 0.0, 3)
    with pytest.raises(ValueError, match="min_samples"):
        dbscan_grid(pts[:, 0], pts[:, 1], 2.0, 0)
    with pytest.raises(ValueError, match="equal length"):
        dbscan_grid(pts[:, 0], pts[:2, 1], 2.0, 3)

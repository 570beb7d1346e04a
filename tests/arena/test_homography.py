"""The one homography fitter (arena.homography): exact on exact points, least squares on noisy
ones, the calibration JSON read in one place, clear errors."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from arena.homography import (CalibrationError, apply_homography, calibration_points, fit_homography,
                              read_calibration_json)

#: a ceiling camera's view of the arena, arena m -> px, with some perspective
ARENA_TO_PX = np.array([[180.0, 12.0, 40.0], [-8.0, -190.0, 420.0], [0.02, -0.03, 1.0]])
PX_TO_ARENA = np.linalg.inv(ARENA_TO_PX) / np.linalg.inv(ARENA_TO_PX)[2, 2]
GRID = np.array([[x, y] for x in np.linspace(0, 1.83, 4) for y in np.linspace(0, 1.83, 4)])


def _px(arena):
    return apply_homography(ARENA_TO_PX, arena)


@pytest.mark.parametrize("n", [4, 16])
def test_exact_points_give_the_true_homography(n):
    arena = GRID[[0, 3, 12, 15]] if n == 4 else GRID
    px = _px(arena)
    H = fit_homography(px, arena)
    assert H[2, 2] == 1.0
    assert np.abs(H - PX_TO_ARENA).max() / np.abs(PX_TO_ARENA).max() < 1e-12
    assert np.abs(apply_homography(H, px) - arena).max() < 1e-12      # metres
    back = fit_homography(arena, px)                                   # either direction
    assert np.abs(back - ARENA_TO_PX).max() / np.abs(ARENA_TO_PX).max() < 1e-12


def test_the_known_mat_corners_map_exactly():
    """Four clicked mat corners (px) onto the 1.83 m mat: each lands on its corner."""
    pix = [[85.2, 454.3], [551.5, 474.8], [553.6, 9.9], [107.8, 5.4]]
    mat = [[0, 0], [1.83, 0], [1.83, 1.83], [0, 1.83]]
    H = fit_homography(pix, mat)
    assert np.abs(apply_homography(H, np.array(pix)) - mat).max() < 1e-12
    assert apply_homography(H, np.array(pix[2])).shape == (2,)
    # a homography keeps lines: where the image's diagonals cross is the mat's centre
    (p0, p1, p2, p3) = np.array(pix)
    t = np.linalg.solve(np.column_stack([p2 - p0, p1 - p3]), p1 - p0)[0]
    assert apply_homography(H, p0 + t * (p2 - p0)) == pytest.approx([0.915, 0.915], abs=1e-12)


def test_noisy_points_are_fitted_by_least_squares_over_all_of_them():
    px = _px(GRID) + np.random.default_rng(0).normal(0, 0.5, (len(GRID), 2))
    H = fit_homography(px, GRID)

    def sse(h):
        return float(((apply_homography(h, px) - GRID) ** 2).sum())

    # no homography fits these points better: not the true one, not OpenCV's own unpolished
    # result, not any small change of this one
    raw, _ = cv2.findHomography(px, GRID, 0)
    assert sse(H) <= sse(PX_TO_ARENA) and sse(H) <= sse(raw / raw[2, 2]) * (1 + 1e-12)
    rng = np.random.default_rng(1)
    for _ in range(20):
        nudged = H * (1 + 1e-6 * rng.standard_normal((3, 3)))
        assert sse(H) <= sse(nudged)
    # every point counts (no outlier rejection): moving one point moves the fit
    moved = px.copy()
    moved[5] += 20.0
    assert np.abs(fit_homography(moved, GRID) - H).max() > 1e-4


@pytest.mark.parametrize("src, dst, match", [
    (GRID[:3], GRID[:3], "at least 4 points, got 3"),
    (GRID[:5], GRID[:4], "5 pixel points but 4 arena points"),
    ([[0, 0], [1, 1], [2, 2], [3, 3]], GRID[:4], "degenerate"),
    (_px(GRID[[0, 3, 12, 15]]), [[0, 0], [0.5, 0], [1, 0], [1.5, 0]], "collinear"),
    ([[np.nan, 0]] + GRID[1:4].tolist(), GRID[:4], "finite"),
])
def test_bad_points_are_clear_errors(src, dst, match):
    with pytest.raises(CalibrationError, match=match):
        fit_homography(src, dst)


def test_calibration_json_is_read_in_one_place(tmp_path):
    cal = {"image_size": [640, 480], "points": [{"pixel": list(map(float, p)), "arena_m": list(map(float, a))}
                                                for p, a in zip(_px(GRID[:5]), GRID[:5])],
           "floor_points": [{"pixel": [1, 2], "arena_m": [0, 0]}]}
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(cal))
    px, am = calibration_points(read_calibration_json(path))
    assert px.shape == am.shape == (5, 2) and np.allclose(am, GRID[:5])
    assert calibration_points(cal, "floor_points")[0].tolist() == [[1.0, 2.0]]
    for text, match in [("{not json", "not a readable JSON file"), ('{"image_size": [1, 1]}', "no 'points'"),
                        ('{"points": [{"pixel": [1, 2]}]}', "arena_m"),
                        ('{"points": [{"pixel": [1, 2, 3], "arena_m": [0, 0]}]}', "2 numbers"),
                        ("[1, 2]", "JSON object")]:
        path.write_text(text)
        with pytest.raises(CalibrationError, match=match):
            calibration_points(read_calibration_json(path))
    with pytest.raises(CalibrationError, match="not found"):
        read_calibration_json(tmp_path / "missing.json")

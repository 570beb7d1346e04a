"""Homographies pixel <-> arena: fit, round trip, calibration JSON, errors, parallax."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from groundtruth.homography import (CalibrationError, Homography, homography_from_calibration,
                                    load_calibration, parallax_shift_m, save_calibration)
from simulator.webcam import WebcamModel
from simulator.world import World

PIX = [[85.2, 454.3], [551.5, 474.8], [553.6, 9.9], [107.8, 5.4]]
ARENA = [[0, 0], [1.83, 0], [1.83, 1.83], [0, 1.83]]


def test_four_points_fit_exactly_and_round_trip():
    h = Homography.from_points(PIX, ARENA, height_m=0.045, image_size=(640, 480))
    assert np.allclose(h.to_arena(PIX), ARENA, atol=1e-9)
    assert np.allclose(h.to_pixel(ARENA), PIX, atol=1e-7)
    assert h.reprojection_error_m(PIX, ARENA).max() < 1e-9
    assert h.to_arena(np.array(PIX[0])).shape == (2,)


@settings(max_examples=50, deadline=None)
@given(st.floats(0, 1.83), st.floats(0, 1.83))
def test_round_trip_any_arena_point(x, y):
    h = Homography.from_points(PIX, ARENA)
    assert np.allclose(h.to_arena(h.to_pixel([x, y])), [x, y], atol=1e-9)


def test_least_squares_with_more_points_against_a_real_camera():
    m = WebcamModel(World([]))
    grid = np.array([[x, y] for x in np.linspace(0, 1.83, 5) for y in np.linspace(0, 1.83, 5)])
    px = m.project(np.column_stack([grid, np.full(len(grid), 0.045)]))
    noisy = px + np.random.default_rng(0).normal(0, 0.3, px.shape)
    h = Homography.from_points(noisy, grid, 0.045)
    assert np.median(h.reprojection_error_m(px, grid)) < 0.002


@pytest.mark.parametrize("pix, arena, match", [
    (PIX[:3], ARENA[:3], "at least 4"),
    (PIX, ARENA[:3], "3 arena"),
    ([[0, 0], [1, 1], [2, 2], [3, 3]], ARENA, "collinear"),
    (PIX, [[0, 0], [0.5, 0], [1, 0], [1.5, 0]], "collinear"),
    ([[np.nan, 0]] + PIX[1:], ARENA, "finite"),
])
def test_bad_points_give_clear_errors(pix, arena, match):
    with pytest.raises(CalibrationError, match=match):
        Homography.from_points(pix, arena)


def test_save_and_load_calibration(tmp_path):
    path = tmp_path / "cal.json"
    save_calibration(path, PIX, ARENA, (640, 480), height_m=0.045, camera="webcam")
    data = json.loads(path.read_text())
    assert data["image_size"] == [640, 480] and data["camera"] == "webcam"
    assert data["points"][1] == {"pixel": PIX[1], "arena_m": ARENA[1]}
    h = load_calibration(path)
    assert h.height_m == 0.045 and h.image_size == (640, 480)
    assert np.allclose(h.to_arena(PIX), ARENA, atol=1e-9)


@pytest.mark.parametrize("text, match", [
    ("{not json", "cannot read"),
    ('{"image_size": [640, 480]}', "no 'points'"),
    ('{"points": [{"pixel": [1, 2]}]}', "arena_m"),
    ('{"points": [{"pixel": [1, 2, 3], "arena_m": [0, 0]}]}', "2 numbers"),
])
def test_bad_calibration_files(tmp_path, text, match):
    path = tmp_path / "cal.json"
    path.write_text(text)
    with pytest.raises(CalibrationError, match=match):
        load_calibration(path)
    with pytest.raises(CalibrationError, match="not found"):
        load_calibration(tmp_path / "missing.json")


def test_webcam_calibration_parallax_matches_the_formula():
    """Shell tops mapped with the floor homography move away from the nadir by h/(H-h)*d."""
    m = WebcamModel(World([]))
    cal = m.calibration
    floor = homography_from_calibration(cal, "floor_points")
    top = homography_from_calibration(cal)
    assert top.height_m == pytest.approx(0.045) and floor.height_m == 0.0
    p = np.array([0.2, 1.6])                          # a shell-top point far from the nadir
    uv = m.project(np.array([[*p, 0.045]]))[0]
    assert np.allclose(top.to_arena(uv), p, atol=1e-6)
    err = np.linalg.norm(floor.to_arena(uv) - p)
    # camera centre: the null space of the projection matrix
    c = np.linalg.svd(m.P)[2][-1]
    c = c[:3] / c[3]
    d = np.linalg.norm(p - c[:2])
    assert err == pytest.approx(parallax_shift_m(0.045, c[2], d), rel=0.02)
    assert err > 0.02
    with pytest.raises(ValueError):
        parallax_shift_m(3.0, 2.5, 1.0)

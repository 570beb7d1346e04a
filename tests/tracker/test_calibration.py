"""Calibration: homography round trip, files, the lab config, `arena calibrate`."""

from __future__ import annotations

import json
import subprocess

import cv2
import numpy as np
import pytest

from tests.conftest import arena_cmd
from tests.tracker.synth import SCALE, calibration_dict
from tracker.calibration import Calibration, CalibrationError, find_mat_corners, load_calibration


def test_round_trip_pixel_arena_pixel_and_scale():
    cal = Calibration.from_dict(calibration_dict())
    uv = np.array([[20.0, 460.0], [470.0, 10.0], [321.5, 200.25]])
    xy = cal.to_arena(uv)
    assert xy[0] == pytest.approx([0.0, 0.0], abs=1e-7)
    assert np.allclose(cal.to_pixel(xy), uv, atol=1e-6)
    assert cal.px_per_m() == pytest.approx(SCALE, rel=1e-6)
    # the sensor's v axis points down, the arena's y up: heading +u is yaw 0, +v is yaw -90 deg
    assert cal.heading_to_arena(300, 200, 0.0) == pytest.approx(0.0, abs=1e-6)
    assert cal.heading_to_arena(300, 200, np.pi / 2) == pytest.approx(-np.pi / 2, abs=1e-6)
    assert cal.vector_to_arena(300, 200, SCALE, 0.0) == pytest.approx((1.0, 0.0))


def test_perspective_homography_round_trip_and_file(tmp_path):
    H = np.array([[180.0, 12.0, 40.0], [-8.0, -190.0, 420.0], [0.02, -0.03, 1.0]])  # arena -> px
    arena = np.array([[0, 0], [1.83, 0], [1.83, 1.83], [0, 1.83], [0.9, 0.4], [0.3, 1.2]])
    q = np.c_[arena, np.ones(len(arena))] @ H.T
    px = q[:, :2] / q[:, 2:]
    cal = Calibration.from_points(px, arena, (640, 480))
    assert cal.reprojection_error_m() < 1e-6
    path = tmp_path / "calib.json"
    cal.save(path)
    data = json.loads(path.read_text())
    assert data["image_size"] == [640, 480] and len(data["points"]) == 6
    again = load_calibration(path)
    grid = np.random.default_rng(0).uniform(0, 1.83, (50, 2))
    assert np.allclose(again.to_arena(again.to_pixel(grid)), grid, atol=1e-7)


def test_calibration_inside_a_lab_config(tmp_path):
    d = calibration_dict()
    pts = ", ".join(f"{{ pixel = [{p['pixel'][0]}, {p['pixel'][1]}], arena_m = [{p['arena_m'][0]}, "
                    f"{p['arena_m'][1]}] }}" for p in d["points"])
    lab = tmp_path / "lab.toml"
    lab.write_text(f'[[cameras]]\nname = "cam0"\nwidth = 640\nheight = 480\npoints = [{pts}]\n')
    cal = load_calibration(lab, "cam0")
    assert cal.px_per_m() == pytest.approx(SCALE)


@pytest.mark.parametrize("bad,msg", [
    ({"image_size": [640, 480], "points": [{"pixel": [0, 0], "arena_m": [0, 0]}] * 3}, "at least 4"),
    ({"image_size": [640, 480], "points": [{"pixel": [i, i], "arena_m": [i, i]} for i in range(4)]}, "degenerate"),
    ({"points": []}, "image_size"),
    ([1, 2], "JSON object"),
])
def test_bad_calibrations_say_what_is_wrong(tmp_path, bad, msg):
    path = tmp_path / "c.json"
    path.write_text(json.dumps(bad))
    with pytest.raises(CalibrationError, match=msg):
        load_calibration(path)


def _mat_image(corners):
    img = np.full((480, 640), 40, np.uint8)
    cv2.fillConvexPoly(img, np.round(corners).astype(np.int32), 230)
    return img


def test_find_mat_corners_in_a_frame():
    corners = np.array([[102.0, 452.0], [560.0, 440.0], [548.0, 20.0], [95.0, 35.0]])  # bl, br, tr, tl
    found = find_mat_corners(_mat_image(corners))
    assert np.allclose(found, corners, atol=2.5)
    with pytest.raises(CalibrationError, match="no mat|bright"):
        find_mat_corners(np.full((480, 640), 40, np.uint8))


def test_arena_calibrate_cli_points_and_image(tmp_path):
    out = tmp_path / "c.json"
    r = subprocess.run(arena_cmd("calibrate", "--size", "640x480", "--points", "20,460:0,0", "470,460:1.8,0",
                                 "470,10:1.8,1.8", "20,10:0,1.8", "-o", str(out)), capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert load_calibration(out).px_per_m() == pytest.approx(SCALE)
    assert (tmp_path / "c.png").is_file()
    png = tmp_path / "frame.png"
    cv2.imwrite(str(png), _mat_image(np.array([[102.0, 452.0], [560.0, 440.0], [548.0, 20.0], [95.0, 35.0]])))
    r = subprocess.run(arena_cmd("calibrate", "--image", str(png), "-o", str(tmp_path / "img.json"),
                                 "--preview", str(tmp_path / "prev.png")), capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    cal = load_calibration(tmp_path / "img.json")
    assert cal.to_arena((102.0, 452.0)) == pytest.approx([0.0, 0.0], abs=0.01)
    assert cal.to_arena((548.0, 20.0)) == pytest.approx([1.83, 1.83], abs=0.01)
    assert cv2.imread(str(tmp_path / "prev.png")) is not None
    # bad input: a clear message, no traceback
    r = subprocess.run(arena_cmd("calibrate", "--points", "1,2:0,0", "-o", str(out)), capture_output=True, text=True)
    assert r.returncode != 0 and "--size" in r.stderr and "Traceback" not in r.stderr
    r = subprocess.run(arena_cmd("calibrate", "--size", "640x480", "--points", "1,2:0,0", "3,4:1,1", "-o", str(out)),
                       capture_output=True, text=True)
    assert r.returncode != 0 and "at least 4" in r.stderr and "Traceback" not in r.stderr


def test_parallax_factor_from_the_heights():
    d = calibration_dict()
    cal = Calibration.from_dict(d)
    assert cal.parallax_factor(0.045, 2.5) == pytest.approx((2.5 - 0.045) / 2.5)
    assert cal.nadir_m() == pytest.approx(cal.to_arena((320, 240)))
    # points clicked on the shell tops: nothing to correct
    top = Calibration.from_dict({**d, "height_m": 0.045, "camera_height_m": 2.4})
    assert top.parallax_factor(0.045, 2.4) == pytest.approx(1.0)
    assert Calibration.from_dict(top.to_dict()).camera_height_m == 2.4
    with pytest.raises(CalibrationError, match="above"):
        Calibration.from_dict({**d, "height_m": 3.0, "camera_height_m": 2.4})
    from tracker.pipeline import Pipeline

    assert Pipeline(top, robot_height_m=0.045).parallax == pytest.approx(1.0)
    assert Pipeline(cal).parallax == pytest.approx(1 - 0.032 / 2.5)  # default: a Zumo's event cloud, 2.5 m assumed
    assert Pipeline(cal, detector="paper", tracker="idtrack").parallax == 1.0  # the paper's plain homography


def test_arena_calibrate_from_events_under_flickering_light(tmp_path):
    # the simulator's ceiling camera over an empty mat lit by 100 Hz flickering light
    raw, truth_cal = tmp_path / "mat.raw", tmp_path / "sim.json"
    r = subprocess.run(arena_cmd("sim", "--no-robots", "--no-webcam", "--camera-port", "0", "--duration", "0.15",
                                 "--fast", "--flicker", "100", "--record-raw", str(raw), "--calibration-out",
                                 str(truth_cal), "-m", "peer"), capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    out = tmp_path / "ev.json"
    r = subprocess.run(arena_cmd("calibrate", "--events", str(raw), "--seconds", "0.15", "-o", str(out)),
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    found, truth = load_calibration(out), load_calibration(truth_cal)
    for px in ((320.0, 240.0), (150.0, 400.0), (500.0, 60.0)):
        assert found.to_arena(px) == pytest.approx(truth.to_arena(px), abs=0.01)


def test_arena_calibrate_from_events_of_a_still_mat_says_what_to_do(tmp_path):
    # under steady light a still mat makes no events: only sensor noise, which must not be
    # taken for a mat (speckle can close into a four-cornered blob)
    from arena.events import make_events
    from arena.formats import write_events

    rng = np.random.default_rng(1)
    n = 5000
    ev = make_events(rng.integers(0, 640, n), rng.integers(0, 480, n), rng.integers(0, 2, n),
                     np.sort(rng.integers(0, 2_000_000, n)))
    raw = tmp_path / "noise.raw"
    write_events(raw, ev, 640, 480)
    r = subprocess.run(arena_cmd("calibrate", "--events", str(raw), "--seconds", "2", "-o", str(tmp_path / "c.json")),
                       capture_output=True, text=True, timeout=120)
    assert r.returncode != 0 and "flicker" in r.stderr and "--image" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr and not (tmp_path / "c.json").exists()


def test_arena_calibrate_into_a_missing_folder_is_one_clear_line(tmp_path):
    r = subprocess.run(arena_cmd("calibrate", "--size", "640x480", "--points", "112,431:0,0", "528,431:1.83,0",
                                 "528,15:1.83,1.83", "112,15:0,1.83", "-o", str(tmp_path / "no" / "c.json")),
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "cannot write" in r.stderr and "Traceback" not in r.stderr, r.stderr

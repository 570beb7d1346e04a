"""What an outsider trying `arena calibrate` and `arena track` found accepted silently: pixel points
off the sensor, arena points in cm, a lens estimate disagreeing with the measured height, a typo'd
key in the calibration JSON, and an event file with no events."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from tracker.calibration import Calibration, CalibrationError, lens_height_disagreement, load_calibration

D = {"image_size": [640, 480],
     "points": [{"pixel": [112.0, 431.0], "arena_m": [0.0, 0.0]}, {"pixel": [528.0, 431.0], "arena_m": [1.83, 0.0]},
                {"pixel": [528.0, 15.0], "arena_m": [1.83, 1.83]}, {"pixel": [112.0, 15.0], "arena_m": [0.0, 1.83]}]}
POINTS = ["112,431:0,0", "528,431:1.83,0", "528,15:1.83,1.83", "112,15:0,1.83"]


def _with_point(i, pixel=None, arena_m=None):
    pts = [dict(p) for p in D["points"]]
    pts[i] = {"pixel": pixel or pts[i]["pixel"], "arena_m": arena_m or pts[i]["arena_m"]}
    return {**D, "points": pts}


def _calibrate(tmp_path, *argv):
    from tracker.cli import register_calibrate, run_calibrate
    import argparse

    ap = argparse.ArgumentParser()
    register_calibrate(ap.add_subparsers())
    args = ap.parse_args(["calibrate", *argv, "-o", str(tmp_path / "c.json")])
    return run_calibrate(args)


# -- 1. pixels off the sensor, arena points in cm ------------------------------------------

@pytest.mark.parametrize("pixel,bad", [([1700.0, 15.0], "1700, 15"), ([112.0, -3000.0], "112, -3000"),
                                        ([43.1, 52800.0], "43.1, 52800")])   # the last: a lost decimal point
def test_a_pixel_far_off_the_sensor_in_a_file_is_refused_naming_the_point(pixel, bad):
    with pytest.raises(CalibrationError, match=rf"cal: points\[2\]: pixel \({bad}\) is outside the 640x480 px "
                                               r"sensor by more than 640 px"):
        Calibration.from_dict(_with_point(2, pixel=pixel), "cal")


def test_a_file_keeps_points_computed_just_out_of_view():
    """A model's projection of the mat corners (the simulator's, or a layout measured on the
    floor) may put a corner just off the sensor of an off-centre camera: that file loads."""
    cal = Calibration.from_dict(_with_point(2, pixel=[700.0, 15.0]), "cal")
    assert cal.pixels[2].tolist() == [700.0, 15.0]


def test_pixels_on_the_sensor_edges_still_load():
    cal = Calibration.from_dict({**D, "points": [{"pixel": p, "arena_m": a} for p, a in
                                                  zip([[0, 480], [640, 480], [640, 0], [-0.4, 0]],
                                                      [[0, 0], [1.83, 0], [1.83, 1.83], [0, 1.83]])]})
    assert cal.to_arena(np.array([640.0, 0.0])) == pytest.approx([1.83, 1.83], abs=1e-9)


def test_arena_points_in_cm_are_refused():
    cm = {**D, "points": [{"pixel": p["pixel"], "arena_m": [100 * c for c in p["arena_m"]]} for p in D["points"]]}
    with pytest.raises(CalibrationError, match=r"span 183 x 183 m: are these in cm\? arena coordinates are metres"):
        Calibration.from_dict(cm)
    # a 40 m hall is a (large) lab: kept
    big = {**D, "points": [{"pixel": p["pixel"], "arena_m": [40 / 1.83 * c for c in p["arena_m"]]}
                           for p in D["points"]]}
    assert Calibration.from_dict(big).px_per_m() == pytest.approx(416 / 40, rel=1e-6)


def test_arena_calibrate_refuses_a_point_off_the_sensor_and_cm(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        _calibrate(tmp_path, "--size", "640x480", "--points", *POINTS[:2], "700,15:1.83,1.83", POINTS[3])
    assert e.value.code != 0
    assert "--points 3 (700,15:1.83,1.83): pixel (700, 15) is outside the 640x480 px sensor" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        _calibrate(tmp_path, "--size", "640x480", "--points", "112,431:0,0", "528,431:183,0", "528,15:183,183",
                   "112,15:0,183")
    assert "are these in cm? arena coordinates are metres" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        _calibrate(tmp_path, "--size", "640x480", "--points", *POINTS, "--arena-size", "183")
    assert "--arena-size 183: is it in cm?" in capsys.readouterr().err
    assert not (tmp_path / "c.json").exists()


def test_arena_calibrate_refuses_a_mat_corner_found_off_the_sensor(tmp_path, capsys, monkeypatch):
    """What `arena track` would refuse to read, `arena calibrate --image` does not write."""
    import cv2

    import tracker.calibration as tc

    cv2.imwrite(str(tmp_path / "f.png"), np.zeros((480, 640), np.uint8))
    monkeypatch.setattr(tc, "find_mat_corners", lambda img: np.array([[112, 431], [528, 431], [528, -9.0], [112, 15]]))
    with pytest.raises(SystemExit):
        _calibrate(tmp_path, "--image", str(tmp_path / "f.png"))
    assert "mat corner 3 found: pixel (528, -9) is outside the 640x480 px sensor (u 0-640, v 0-480); the mat's " \
           "corners must all be in view" in capsys.readouterr().err
    assert not (tmp_path / "c.json").exists()


# -- 2. lens estimate vs measured height ---------------------------------------------------

def test_lens_estimate_far_from_the_measured_height_warns_with_both(tmp_path, capsys):
    # 416 px for 1.83 m at the centre; a 4.5 mm lens on 15 µm pixels (300 px) puts the lens 1.32 m up
    assert _calibrate(tmp_path, "--size", "640x480", "--points", *POINTS, "--focal-length-mm", "4.5",
                      "--pixel-pitch-um", "15", "--camera-height-m", "2.45") == 0
    err = capsys.readouterr().err
    assert "the lens gives the camera 1.32 m above the mats but --camera-height-m is 2.45 m (46 % apart); " \
           "using the measured 2.45 m" in err
    assert json.loads((tmp_path / "c.json").read_text())["camera_height_m"] == 2.45
    # an 8.3 mm lens gives 2.43 m: agrees, no warning
    assert _calibrate(tmp_path, "--size", "640x480", "--points", *POINTS, "--focal-length-mm", "8.3",
                      "--pixel-pitch-um", "15", "--camera-height-m", "2.45") == 0
    assert "apart" not in capsys.readouterr().err


def test_lens_height_disagreement_tolerance():
    assert lens_height_disagreement(2.9, 2.45) is None          # 18 %
    assert "2.99 m" in lens_height_disagreement(2.99, 2.45)     # 22 %
    assert lens_height_disagreement(2.0, 2.45) is None          # 18 %
    assert "using the measured 2.45 m" in lens_height_disagreement(1.9, 2.45)


# -- 3. unknown keys -----------------------------------------------------------------------

def test_a_typo_in_a_key_is_refused_naming_it_and_the_known_keys(tmp_path):
    p = tmp_path / "cam0.json"
    p.write_text(json.dumps({**D, "camera_heigth_m": 2.45}))
    with pytest.raises(CalibrationError) as exc:
        load_calibration(p)
    msg = str(exc.value)
    assert msg.startswith(f"{p}: unknown key(s) 'camera_heigth_m' (did you mean 'camera_height_m'?); known keys: ")
    assert "image_size" in msg and "nadir_m" in msg


def test_the_keys_the_project_writes_still_load():
    extra = {"camera": "webcam", "floor_points": D["points"], "height_m": 0.04, "camera_height_m": 2.45,
             "nadir_m": [0.9, 0.9], "nadir_px": [320.0, 240.0]}
    assert Calibration.from_dict({**D, **extra}).camera_height_m == 2.45


# -- 4. an event file with no events -------------------------------------------------------

def _track(tmp_path, name, content):
    from tracker.cli import run_offline

    (tmp_path / "cal.json").write_text(json.dumps(D))
    inp = tmp_path / name
    if isinstance(content, bytes):
        inp.write_bytes(content)
    else:
        np.save(inp, content)
    out = tmp_path / "t.csv"
    args = SimpleNamespace(input=str(inp), calibration=str(tmp_path / "cal.json"), tracks_out=str(out),
                           tracker="fleet", detector="default", backend="grid", slice_ms=10.0, accumulation_ms=100.0,
                           chassis_cm=10.0, robot_height_cm=3.2, camera_height_m=2.45, fleet_size=None)
    try:
        return run_offline(args), out
    except SystemExit as exc:
        return exc.code, out


@pytest.mark.parametrize("name,content", [("empty.raw", b""), ("hdr.csv", b"t,x,y,p\n"),
                                          ("none.npy", np.zeros(0, [("t", "<i8"), ("x", "<u2"), ("y", "<u2"),
                                                                    ("p", "i1")]))])
def test_track_says_the_file_has_no_events(tmp_path, capsys, name, content):
    rc, out = _track(tmp_path, name, content)
    err = capsys.readouterr().err
    assert rc == 2   # an input error, as `arena convert` and `arena edge` on the same file
    assert f"arena track: no events in {tmp_path / name}" in err
    assert ("(0-byte file)" in err) == (isinstance(content, bytes) and not content)
    assert out.read_text().count("\n") == 1 and out.read_text().startswith("t_us,track_id")

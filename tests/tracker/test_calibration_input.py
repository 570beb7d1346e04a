"""The calibration JSON loader names the key that is wrong and refuses absurd geometry
(issue 20): lens heights outside 0.3-20 m, nadirs far from the arena, and lens values no
pinhole camera has (a 0.3 mm lens was stored as a 0.08 m high camera)."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import pytest

from tracker.calibration import Calibration, CalibrationError, load_calibration

D = {"image_size": [640, 480],
     "points": [{"pixel": [20.0, 460.0], "arena_m": [0.0, 0.0]}, {"pixel": [470.0, 460.0], "arena_m": [1.8, 0.0]},
                {"pixel": [470.0, 10.0], "arena_m": [1.8, 1.8]}, {"pixel": [20.0, 10.0], "arena_m": [0.0, 1.8]}]}


def _pts(i, **p):
    pts = [dict(q) for q in D["points"]]
    pts[i] = p
    return pts


@pytest.mark.parametrize("change,expected", [
    ({"image_size": [640, "480"]}, r"image_size: expected \[w, h\]"),
    ({"image_size": None}, r"image_size: expected \[w, h\]"),
    ({"points": "four"}, r"points: expected a list"),
    ({"points": _pts(2, pixel=[470.0, "ten"], arena_m=[1.8, 1.8])}, r"points\[2\]\.pixel: expected \[u, v\]"),
    ({"points": _pts(1, pixel=[470.0, 460.0])}, r"points\[1\]\.arena_m: .*key missing"),
    ({"points": _pts(3, pixel=[20.0, 10.0], arena_m=[0.0, math.nan])}, r"points\[3\]\.arena_m"),
    ({"height_m": "0.045"}, r"height_m: expected .* \[0, 2\] m"),
    ({"height_m": -0.1}, r"height_m: expected"),
    ({"camera_height_m": "2.5"}, r"camera_height_m: expected the lens height above the mats in \[0\.3, 20\] m"),
    ({"camera_height_m": math.inf}, r"camera_height_m: expected"),
    ({"camera_height_m": 0.08}, r"camera_height_m: camera height 0\.08 m is outside \[0\.3, 20\] m"),
    ({"camera_height_m": 250}, r"camera_height_m: camera height 250 m is outside"),
    ({"nadir_m": [50.0, 0.9]}, r"nadir_m: the arena point under the lens \(50\.000, 0\.900\) m is 48\.20 m from the arena"),
    ({"nadir_m": ["0.9", 0.9]}, r"nadir_m: expected \[x, y\]"),
    ({"nadir_px": [1e6, 240.0]}, r"nadir_px .* within 2 arena sides"),
    ({"nadir_px": "centre"}, r"nadir_px: expected \[u, v\] in sensor pixels"),
])
def test_each_bad_key_is_named(tmp_path, change, expected):
    p = tmp_path / "cam0.json"
    p.write_text(json.dumps({**D, **change}))
    with pytest.raises(CalibrationError, match=expected) as exc:
        load_calibration(p)
    assert str(exc.value).startswith(str(p))


def test_physical_geometry_still_loads():
    cal = Calibration.from_dict({**D, "image_size": [640.0, 480.0], "height_m": 0.045, "camera_height_m": 0.3,
                                 "nadir_m": [-3.5, 0.9]})
    assert cal.image_size == (640, 480) and cal.camera_height_m == 0.3 and cal.nadir == (-3.5, 0.9)
    assert Calibration.from_dict({**D, "camera_height_m": 20}).camera_height_m == 20.0
    cal = Calibration.from_dict(D)
    with pytest.raises(CalibrationError, match="outside"):
        cal.with_geometry(camera_height_m=25.0)
    with pytest.raises(CalibrationError, match="nadir_m"):
        cal.with_geometry(nadir_m=(-9.0, 0.0))
    assert cal.with_geometry(2.5, (0.9, 0.9)).camera_height_m == 2.5


def test_lens_values_below_the_physical_minimum_are_refused():
    from tracker.calibration import lens_focal_px

    with pytest.raises(CalibrationError, match=r"focal length 0\.3 mm .* 174 deg field of view .* >= 1\.61 mm"):
        lens_focal_px(0.3, 15.0, (640, 480))
    with pytest.raises(CalibrationError, match="pixel pitch"):
        lens_focal_px(4.5, 0.015, (640, 480))   # mm given for µm
    with pytest.raises(CalibrationError, match="focal length"):
        lens_focal_px(math.nan, 15.0, (640, 480))
    assert lens_focal_px(4.5, 15.0, (640, 480)) == pytest.approx(300.0)


def test_arena_calibrate_refuses_the_estimate_of_a_0_3_mm_lens(tmp_path):
    """What the outside tester saw: a 0.3 mm lens estimated a camera 0.08 m above the mats and
    stored it. Now one line, exit 2, nothing written."""
    out = tmp_path / "c.json"
    pts = ["20,460:0,0", "470,460:1.8,0", "470,10:1.8,1.8", "20,10:0,1.8"]
    r = subprocess.run([sys.executable, "-m", "arena", "calibrate", "--size", "640x480", "--points", *pts,
                        "--focal-length-mm", "0.3", "--pixel-pitch-um", "15", "-o", str(out)],
                       capture_output=True, text=True)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr and "field of view" in r.stderr, r.stderr
    assert not out.exists()
    # 1.2 mm: a 161 deg lens, which gave a plausible-looking 0.32 m camera: refused by the lens check
    r = subprocess.run([sys.executable, "-m", "arena", "calibrate", "--size", "640x480", "--points", *pts,
                        "--focal-length-mm", "1.2", "--pixel-pitch-um", "15", "-o", str(out)],
                       capture_output=True, text=True)
    assert r.returncode == 2 and "field of view" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert not out.exists()

"""Parallax correction from the real geometry: the lens height and nadir stored in the
calibration (or the lab file), the robots' visible height per [[robots]], and a warning (not a
silent default) when the height is unknown."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from arena.config import parse_lab_config
from arena.events import EVENT_DTYPE
from arena.formats import write_events
from tests.tracker.synth import calibration_dict
from tracker.calibration import (DEFAULT_ROBOT_HEIGHT_M, FALLBACK_CAMERA_HEIGHT_M, Calibration,
                                 CalibrationError, camera_calibration, load_calibration)
from tracker.detect import Detection
from tracker.pipeline import Pipeline


def _detection(cal: Calibration, x: float, y: float) -> Detection:
    u, v = cal.to_pixel(np.array([x, y]))
    return Detection(u=float(u), v=float(v), t_us=0, n_events=100, n_pixels=50)


def test_the_correction_scales_distances_from_the_calibrations_off_centre_nadir():
    cal = Calibration.from_dict({**calibration_dict(), "camera_height_m": 2.0, "nadir_m": [0.4, 1.3]})
    pipe = Pipeline(cal, robot_height_m=0.04)
    k = (2.0 - 0.04) / 2.0
    obs = pipe._observation(_detection(cal, 1.6, 0.2))
    assert (obs.x, obs.y) == pytest.approx((0.4 + 1.2 * k, 1.3 - 1.1 * k), abs=1e-6)
    obs = pipe._observation(_detection(cal, 0.4, 1.3))  # under the lens: no shift
    assert (obs.x, obs.y) == pytest.approx((0.4, 1.3), abs=1e-6)
    assert pipe.parallax == pytest.approx(k) and pipe.camera_height_source == "calibration"
    assert pipe.parallax_warning is None
    # a height given to the pipeline wins over the calibration's
    assert Pipeline(cal, robot_height_m=0.04, camera_height_m=4.0).parallax == pytest.approx(0.99)


def test_calibration_round_trip_with_height_and_nadir(tmp_path):
    cal = Calibration.from_dict({**calibration_dict(), "camera_height_m": 2.35, "nadir_m": [0.8, 1.05]})
    cal.save(tmp_path / "c.json")
    data = json.loads((tmp_path / "c.json").read_text())
    assert data["camera_height_m"] == 2.35 and data.get("nadir_m") == [0.8, 1.05]
    back = load_calibration(tmp_path / "c.json")
    assert back.camera_height_m == 2.35 and back.nadir_m() == (0.8, 1.05)
    cal = Calibration.from_dict(calibration_dict())
    assert cal.camera_height_m is None and cal.nadir is None
    assert cal.nadir_m() == pytest.approx(cal.to_arena((320, 240)))  # unknown: the image centre's point
    cal.with_geometry(2.0, (0.1, 0.2))
    assert Calibration.from_dict(cal.to_dict()).nadir_m() == (0.1, 0.2)
    for bad in ({"nadir_m": [1.0]}, {"nadir_m": "centre"}, {"nadir_m": [0.0, math.nan]}):
        with pytest.raises(CalibrationError, match="nadir_m"):
            Calibration.from_dict({**calibration_dict(), **bad})


def test_the_pose_estimated_from_the_lens_gives_the_height_and_an_off_centre_nadir():
    """A pinhole camera 2.3 m up, 0.7 m / 1.1 m over the arena, tilted a few degrees."""
    f, (w, h) = 600.0, (640, 480)
    a, b = math.radians(4.0), math.radians(2.0)
    rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    R = rx @ ry @ np.diag([1.0, -1.0, -1.0])  # arena (z up) -> camera (looking down, v down)
    t = -R @ np.array([0.7, 1.1, 2.3])
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]])
    arena = np.array([[0, 0], [1.83, 0], [1.83, 1.83], [0, 1.83], [0.9, 0.9]])
    q = (K @ (R[:, :2] @ arena.T + t[:, None])).T
    cal = Calibration.from_points(q[:, :2] / q[:, 2:], arena, (w, h))
    pose = cal.estimate_pose(f)
    assert pose.camera_height_m == pytest.approx(2.3, abs=1e-6)
    assert pose.nadir_m == pytest.approx((0.7, 1.1), abs=1e-6)
    assert pose.consistency == pytest.approx(1.0, abs=1e-6) and 4.0 < pose.tilt_deg < 5.0
    assert np.hypot(*np.subtract(cal.nadir_m(), (0.7, 1.1))) > 0.05  # the image centre is not the nadir


def test_unknown_height_warns_and_names_the_option():
    cal = Calibration.from_dict(calibration_dict())
    pipe = Pipeline(cal)
    assert pipe.parallax == pytest.approx(1 - DEFAULT_ROBOT_HEIGHT_M / FALLBACK_CAMERA_HEIGHT_M)
    assert getattr(pipe, "parallax_warning", None) is not None
    assert pipe.camera_height_source == "assumed" and pipe.camera_height_m == FALLBACK_CAMERA_HEIGHT_M
    assert "camera height unknown" in pipe.parallax_warning and "--camera-height-m" in pipe.parallax_warning
    assert "2.5 m" in pipe.parallax_warning
    assert Pipeline(cal, camera_height_m=2.5).parallax_warning is None
    assert Pipeline(cal, detector="paper").parallax_warning is None  # no correction in paper mode


LAB = """
[[cameras]]
name = "cam0"
calibration = "{calib}"
camera_height_m = {cam_h}
nadir_m = [0.5, 0.6]

[[robots]]
name = "zumo1"
robot_height_cm = 3.6

[[robots]]
name = "zumo2"
robot_height_cm = 3.6
"""


def test_lab_file_camera_geometry_and_robot_height(tmp_path):
    (tmp_path / "c.json").write_text(json.dumps({**calibration_dict(), "camera_height_m": 3.0}))
    import tomllib

    lab = parse_lab_config(tomllib.loads(LAB.format(calib=tmp_path / "c.json", cam_h=2.2)), "lab.toml")
    assert lab.robot_height_cm() == pytest.approx(3.6)
    assert lab.cameras[0].camera_height_m == 2.2 and lab.cameras[0].nadir_m == (0.5, 0.6)
    cal = camera_calibration(lab.camera("cam0"), "lab.toml")  # the camera table's values win
    assert cal.camera_height_m == 2.2 and cal.nadir_m() == (0.5, 0.6)
    # old lab files (none of the new keys) still load, and leave the heights unknown
    old = parse_lab_config({"cameras": [{"name": "cam0"}], "robots": [{"name": "zumo1"}]}, "old.toml")
    assert old.robot_height_cm() is None and old.cameras[0].camera_height_m is None
    from arena.config import ConfigError

    with pytest.raises(ConfigError, match="robots\\[0\\].robot_height_cm"):
        parse_lab_config({"robots": [{"name": "z", "robot_height_cm": -1}]}, "bad.toml")
    with pytest.raises(ConfigError, match="cameras\\[0\\].camera_height_m"):
        parse_lab_config({"cameras": [{"name": "c", "camera_height_m": 0}]}, "bad.toml")


@pytest.fixture()
def tiny_recording(tmp_path):
    ev = np.zeros(20, dtype=EVENT_DTYPE)
    ev["x"], ev["y"], ev["p"], ev["t"] = 100, 100, 1, np.arange(20) * 1000
    write_events(tmp_path / "rec.npz", ev, 640, 480)
    (tmp_path / "c.json").write_text(json.dumps(calibration_dict()))
    return tmp_path


def _track(d, monkeypatch, *args):
    """Run `arena track` in process; returns (exit code, the kwargs its Pipeline got, the Pipeline)."""
    import tracker.pipeline
    from arena.cli import main

    seen = {}

    class Spy(tracker.pipeline.Pipeline):
        def __init__(self, *a, **kw):
            super().__init__(*a, **kw)
            seen.update(kw, pipe=self)

    monkeypatch.setattr(tracker.pipeline, "Pipeline", Spy)
    monkeypatch.delenv("ARENA_LAB", raising=False)
    rc = main(["track", "--input", str(d / "rec.npz"), "--tracks-out", str(d / "t.csv"), *args])
    return rc, seen


def test_lab_robot_height_reaches_the_pipeline_and_a_flag_wins(tiny_recording, monkeypatch, capsys):
    d = tiny_recording
    lab = d / "lab.toml"
    lab.write_text(LAB.format(calib=d / "c.json", cam_h=2.2))
    rc, seen = _track(d, monkeypatch, "--lab", str(lab))
    assert rc == 0
    assert seen["robot_height_m"] == pytest.approx(0.036)
    assert seen["pipe"].camera_height_m == 2.2 and seen["pipe"]._nadir == (0.5, 0.6)
    assert "camera height unknown" not in capsys.readouterr().err
    rc, seen = _track(d, monkeypatch, "--lab", str(lab), "--robot-height-cm", "2")
    assert rc == 0 and seen["robot_height_m"] == pytest.approx(0.02)


def test_arena_track_warns_once_when_the_height_is_unknown(tiny_recording, monkeypatch, capsys):
    d = tiny_recording
    rc, seen = _track(d, monkeypatch, "--calibration", str(d / "c.json"))
    assert rc == 0 and seen["robot_height_m"] == pytest.approx(DEFAULT_ROBOT_HEIGHT_M)
    err = capsys.readouterr().err
    warnings = [ln for ln in err.splitlines() if "camera height unknown" in ln]
    assert len(warnings) == 1 and "--camera-height-m" in warnings[0], err
    rc, seen = _track(d, monkeypatch, "--calibration", str(d / "c.json"), "--camera-height-m", "2.4")
    assert rc == 0 and seen["pipe"].camera_height_m == 2.4
    assert "camera height unknown" not in capsys.readouterr().err


def test_arena_calibrate_stores_the_camera_height_and_nadir(tmp_path, capsys):
    from arena.cli import main

    pts = ["112,431:0,0", "528,431:1.83,0", "528,15:1.83,1.83", "112,15:0,1.83"]
    out = tmp_path / "c.json"
    assert main(["calibrate", "--size", "640x480", "--points", *pts, "--camera-height-m", "2.45",
                 "--nadir", "0.9,0.95", "-o", str(out)]) == 0
    data = json.loads(out.read_text())
    assert data["camera_height_m"] == 2.45 and data["nadir_m"] == [0.9, 0.95]
    assert "camera height unknown" not in capsys.readouterr().err
    # without: none stored, and a clear warning naming the option
    assert main(["calibrate", "--size", "640x480", "--points", *pts, "-o", str(out)]) == 0
    data = json.loads(out.read_text())
    assert "camera_height_m" not in data and "nadir_m" not in data
    err = capsys.readouterr().err
    assert "camera height unknown" in err and "--camera-height-m" in err
    # estimated from the lens: a top-down camera of 416 px / 1.83 m with a 600 px focal length
    assert main(["calibrate", "--size", "640x480", "--points", *pts, "--focal-length-mm", "9",
                 "--pixel-pitch-um", "15", "-o", str(out)]) == 0
    data = json.loads(out.read_text())
    assert data["camera_height_m"] == pytest.approx(600 * 1.83 / 416, rel=1e-6)
    assert data["nadir_m"] == pytest.approx([(320 - 112) / 416 * 1.83, (431 - 240) / 416 * 1.83], abs=1e-6)

"""Webcam model: geometry, rendering, the MJPEG stream through cv2.VideoCapture, recording."""

from __future__ import annotations

import json
import urllib.error
import urllib.request

import cv2
import numpy as np
import pytest

from simulator.webcam import WebcamModel, WebcamServer
from simulator.world import RobotSpec, World


def _world(lighting="full", **kw):
    robots = [RobotSpec("red", (220, 40, 40), start=(0.6, 0.6, 0.0), **kw),
              RobotSpec("blue", (40, 80, 220), marker_id=7, start=(1.3, 1.2, 1.0))]
    return World(robots, lighting=lighting, seed=3)


def _pixel(model, x, y, z):
    return model.project(np.array([[x, y, z]]))[0]


def test_render_shape_and_same_seed_same_frame():
    a = WebcamModel(_world(), seed=5).render()
    b = WebcamModel(_world(), seed=5).render()
    assert a.shape == (480, 640, 3) and a.dtype == np.uint8
    assert np.array_equal(a, b)
    c = WebcamModel(_world(), seed=6).render()
    assert not np.array_equal(a, c)        # the noise is seeded


def test_shell_colour_mat_and_lighting():
    m = WebcamModel(_world(), noise=False)
    img = m.render()
    u, v = _pixel(m, 0.6 - 0.02, 0.6, m.shell_height_m)        # behind the front mark
    b, g, r = img[int(round(v)), int(round(u))].astype(int)
    assert r > 150 and g < 90 and b < 90                        # red shell (BGR image)
    u, v = _pixel(m, 0.3, 1.5, 0.0)
    mat = img[int(round(v)), int(round(u))].astype(int)
    assert mat.min() > 170                                      # white mat
    dark = WebcamModel(_world("dark"), noise=False).render()
    assert dark[int(round(v)), int(round(u))].max() < 0.3 * mat.min()


def test_front_mark_is_at_the_front():
    m = WebcamModel(_world(), noise=False)
    img = m.render()
    u, v = _pixel(m, 0.6 + 0.03, 0.6, m.shell_height_m)        # robot 0 faces +x
    assert img[int(round(v)), int(round(u))].max() < 80
    u, v = _pixel(m, 0.6 - 0.03, 0.6, m.shell_height_m)
    assert img[int(round(v)), int(round(u))].max() > 150


def test_aruco_marker_rendered_with_its_id():
    m = WebcamModel(_world(), noise=False)
    d = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50))
    _, ids, _ = d.detectMarkers(cv2.cvtColor(m.render(), cv2.COLOR_BGR2GRAY))
    assert ids is not None and ids.ravel().tolist() == [7]


def test_calibration_points_and_parallax():
    m = WebcamModel(_world())
    cal = m.calibration
    assert cal["image_size"] == [640, 480] and cal["height_m"] == pytest.approx(0.045)
    assert len(cal["points"]) == 4 and len(cal["floor_points"]) == 4
    quad = np.array([p["pixel"] for p in cal["floor_points"]])
    assert np.all((quad >= 0) & (quad <= [640, 480]))           # the whole arena is in view
    sides = np.linalg.norm(quad - np.roll(quad, -1, axis=0), axis=1)
    assert sides.max() - sides.min() > 5                        # not a perfect square
    shift = np.linalg.norm(np.array([p["pixel"] for p in cal["points"]]) - quad, axis=1)
    assert np.all(shift > 2)                                    # shell-top corners: parallax
    # the 3x3 floor homography agrees with the projection at z = 0
    uv = m.plane_homography(0.0) @ np.array([1.83, 0.0, 1.0])
    assert np.allclose(uv[:2] / uv[2], cal["floor_points"][1]["pixel"], atol=1e-2)


def test_explicit_homography_and_bad_arguments():
    h = np.array([[200.0, 0, 100], [0, -200.0, 420], [0, 0, 1]])
    m = WebcamModel(_world(), homography=h)
    assert np.allclose(_pixel(m, 1.0, 1.0, 0.0), [300, 220])
    assert np.allclose(_pixel(m, 1.0, 1.0, 0.045), [300, 220])  # 3x3: no parallax
    with pytest.raises(ValueError, match="3x3"):
        WebcamModel(_world(), homography=np.eye(2))
    with pytest.raises(ValueError, match="fps"):
        WebcamModel(_world(), fps=0)


def test_motion_blur_smears_a_moving_robot():
    w = _world("dimmed")                # 20 ms exposure: ~9 mm of travel at full speed
    w.set_power(0, 400, 400)
    w.step(0.5)
    sharp = WebcamModel(w, blur=False, noise=False).render()
    blurred = WebcamModel(w, blur=True, noise=False).render()
    x, y, _ = w.pose(0)
    u, v = (int(round(c)) for c in _pixel(WebcamModel(w), x, y, 0.045))
    roi = (slice(v - 25, v + 25), slice(u - 25, u + 25))
    # blur spreads the edges across the direction of travel: pixels change there
    diff = np.abs(sharp[roi].astype(int) - blurred[roi].astype(int)).max(axis=2)
    assert diff.max() > 15
    off = WebcamModel(w, blur=False, noise=False).render()
    assert np.array_equal(off, sharp)


def test_mjpeg_stream_opens_in_videocapture(tmp_path):
    w = _world()
    with WebcamServer(w, fps=30) as cam:
        assert cam.url == f"http://127.0.0.1:{cam.port}/stream.mjpg"
        cap = cv2.VideoCapture(cam.url, cv2.CAP_FFMPEG)
        try:
            assert cap.isOpened()
            frames = []
            for _ in range(5):
                w.step(0.05)
                ok, frame = cap.read()
                assert ok
                frames.append(frame)
        finally:
            cap.release()
        assert frames[-1].shape == (480, 640, 3)
        # the streamed frame is the rendered scene (JPEG-compressed)
        ref = WebcamModel(w, noise=False).render()
        assert np.abs(frames[-1].astype(int) - ref.astype(int)).mean() < 6
        cal = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{cam.port}/calibration.json",
                                                timeout=5).read())
        assert cal["points"] == WebcamModel(w).calibration["points"]
        snap = urllib.request.urlopen(f"http://127.0.0.1:{cam.port}/snapshot.jpg", timeout=5).read()
        assert cv2.imdecode(np.frombuffer(snap, np.uint8), cv2.IMREAD_COLOR).shape == (480, 640, 3)
        with pytest.raises(urllib.error.HTTPError):
            urllib.request.urlopen(f"http://127.0.0.1:{cam.port}/nope", timeout=5)
        assert cam.frames_served >= 5


def test_record_writes_a_readable_video(tmp_path):
    w = _world()
    w.set_power(0, 300, 300)
    m = WebcamModel(w, fps=24)
    path = tmp_path / "run.avi"
    assert m.record(path, seconds=0.5) == 12
    assert w.t == pytest.approx(11 / 24)
    cap = cv2.VideoCapture(str(path))
    n = 0
    while cap.read()[0]:
        n += 1
    cap.release()
    assert n == 12


def test_light_flicker_changes_brightness_between_frames():
    w = _world("full")          # 8 ms exposure (dimmed: 20 ms = 2 periods, no ripple, like anti-flicker)
    m = WebcamModel(w, noise=False, flicker_hz=100.0, flicker_depth=0.3)
    steady = WebcamModel(w, noise=False)
    means, ref = [], []
    for _ in range(6):
        w.step(1 / 24)
        means.append(m.render().mean())
        ref.append(steady.render().mean())
    assert np.ptp(ref) < 0.5                                    # static scene, steady light
    assert np.ptp(means) > 1.0                                  # flicker: frame-to-frame ripple
    with pytest.raises(ValueError, match="flicker"):
        WebcamModel(w, flicker_hz=-1)

"""`arena groundtruth`: real Zenoh on loopback, the simulator's MJPEG stream, files, user errors."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

from arena.cli import main
from arena.messages import GroundTruthPose, Status, decode
from arena.session import ZenohSettings, open_session
from groundtruth.homography import homography_from_calibration
from groundtruth.rgb import HsvDetector, MarkerDetector
from groundtruth.service import SetupError, build_detector, detection_to_message
from simulator.webcam import WebcamModel, WebcamServer
from simulator.world import RobotSpec, World


def _world(markers=True):
    return World([RobotSpec("zumo1", (220, 40, 40), marker_id=3 if markers else None, start=(0.5, 0.9, 0.5)),
                  RobotSpec("zumo2", (40, 80, 220), marker_id=4 if markers else None, start=(1.3, 1.1, 2.0))])


def gt(*args, timeout=90):
    return subprocess.run([sys.executable, "-m", "groundtruth", *args], capture_output=True, text=True,
                          timeout=timeout)


def test_publishes_poses_liveliness_and_status_over_zenoh(router, tmp_path):
    w = _world()
    w.step(2.0)                                      # robots stand still; the clock runs
    got, alive, status = [], [], []
    lock = threading.Lock()
    with WebcamServer(w) as cam, open_session(ZenohSettings(mode="client", connect=[router.endpoint])) as s:
        def on_pose(sample):
            with lock:
                got.append((str(sample.key_expr), decode(bytes(sample.payload))))

        def on_status(sample):
            with lock:
                status.append(decode(bytes(sample.payload)))

        s.declare_subscriber("arena/groundtruth/*", on_pose)
        s.declare_subscriber("arena/status/groundtruth/*", on_status)
        s.liveliness().declare_subscriber("arena/alive/groundtruth/*",
                                          lambda smp: alive.append(str(smp.key_expr)), history=True)
        base = cam.url.rsplit("/", 1)[0]
        r = gt("--video", cam.url, "--calibration", f"{base}/calibration.json", "--marker", "3=zumo1",
               "--marker", "4=zumo2", "--max-frames", "30", "--csv", str(tmp_path / "gt.csv"),
               "--name", "cam1", "--clock", "stream", "-m", "client", "-e", router.endpoint)
        assert r.returncode == 0, r.stderr
        assert "30 frames" in r.stdout and "zumo1, zumo2" in r.stdout
        deadline = time.monotonic() + 5.0            # let the last samples arrive (loaded CI)
        while time.monotonic() < deadline:
            with lock:
                if status and status[-1].counters.get("frames") == 30:
                    break
            time.sleep(0.05)
    with lock:
        keys = {k for k, _ in got}
        assert keys == {"arena/groundtruth/zumo1", "arena/groundtruth/zumo2"}
        assert len(got) >= 50                        # ~2 robots x 30 frames (a few may be in flight)
        poses = [m for k, m in got if k.endswith("zumo1")]
        assert all(isinstance(m, GroundTruthPose) and m.detector == "aruco" for m in poses)
        assert poses[-1].x == pytest.approx(0.5, abs=0.005) and poses[-1].y == pytest.approx(0.9, abs=0.005)
        assert poses[-1].yaw == pytest.approx(0.5, abs=0.05)
        assert poses[-1].stamp_us == 2_000_000           # --clock stream: the simulator's time
        assert "arena/alive/groundtruth/cam1" in alive
        assert status and isinstance(status[-1], Status) and status[-1].counters["frames"] == 30
        assert status[-1].counters["detections"] == 60
    rows = list(csv.DictReader(open(tmp_path / "gt.csv")))
    assert len(rows) == 60 and {r["robot"] for r in rows} == {"zumo1", "zumo2"}


def test_hsv_from_a_video_file_without_zenoh_writes_csv_and_pngs(tmp_path):
    w = _world(markers=False)
    w.set_power(0, 300, 300)
    m = WebcamModel(w)
    (tmp_path / "cal.json").write_text(json.dumps(m.calibration))
    m.record(tmp_path / "run.avi", seconds=1.0)
    r = gt("--video", str(tmp_path / "run.avi"), "--calibration", str(tmp_path / "cal.json"),
           "--detector", "hsv", "--robot", "zumo1=#dc2828", "--robot", "zumo2=#2850dc", "--no-zenoh",
           "--csv", str(tmp_path / "gt.csv"), "--annotate", str(tmp_path / "png"))
    assert r.returncode == 0, r.stderr
    rows = list(csv.DictReader(open(tmp_path / "gt.csv")))
    assert len(rows) == 48 and all(r["detector"] == "hsv" for r in rows)
    last = [r for r in rows if r["robot"] == "zumo1"][-1]
    assert float(last["x_m"]) == pytest.approx(w.pose(0)[0], abs=0.015)
    assert float(last["t_us"]) == pytest.approx(23 / 24 * 1e6, abs=100)   # media time of frame 23
    assert len(list((tmp_path / "png").glob("frame_*.png"))) == 24


def test_sample_hsv_prints_a_range_for_the_lab_config(tmp_path):
    w = _world(markers=False)
    m = WebcamModel(w)
    m.record(tmp_path / "still.avi", seconds=0.1)
    u, v = m.project([[0.5 - 0.02, 0.9, m.shell_height_m]])[0]
    r = gt("--video", str(tmp_path / "still.avi"), "--sample-hsv", f"{u:.0f},{v:.0f}")
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("hsv_range = [[")


@pytest.mark.parametrize("args, message", [
    (["--calibration", "x.json"], "no video source"),
    (["--video", "missing.avi", "--calibration", "x.json"], "not found"),
    (["--video", "{video}"], "no calibration"),
    (["--video", "{video}", "--calibration", "missing.json"], "calibration file not found"),
    (["--video", "{video}", "--calibration", "{cal}", "--detector", "hsv"], "needs robot colours"),
    (["--video", "{video}", "--calibration", "{cal}", "--robot", "zumo1"], "NAME=COLOUR"),
    (["--video", "{video}", "--calibration", "{cal}", "--marker", "x=zumo1"], "integer ID"),
    (["--video", "{video}", "--sample-hsv", "9999,9999"], "outside"),
    (["--video", "{video}", "--calibration", "{cal}", "--clock", "stream"], "http:// URL"),
])
def test_user_errors_are_clear_and_exit_2(tmp_path, capsys, args, message):
    m = WebcamModel(_world())
    (tmp_path / "cal.json").write_text(json.dumps(m.calibration))
    m.record(tmp_path / "v.avi", seconds=0.1)
    args = [a.format(video=tmp_path / "v.avi", cal=tmp_path / "cal.json") for a in args]
    assert main(["groundtruth", *args, "--no-zenoh"]) == 2      # in-process: fast, same code path
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_build_detector_from_lab_robots():
    h = homography_from_calibration(WebcamModel(_world()).calibration)
    robots = [SimpleNamespace(name="a", marker_id=5, color_rgb=(220, 40, 40), hsv_range=None,
                              length_m=0.1, width_m=0.1),
              SimpleNamespace(name="b", marker_id=None, color_rgb=(240, 240, 240),
                              hsv_range=((100, 100, 50), (130, 255, 255)), length_m=0.1, width_m=0.1),
              SimpleNamespace(name="white", marker_id=None, color_rgb=(240, 240, 240), hsv_range=None,
                              length_m=0.1, width_m=0.1)]
    aruco = build_detector("aruco", h, robots, markers={6: "c"})
    assert isinstance(aruco, MarkerDetector) and aruco.ids == {5: "a", 6: "c"}
    hsv = build_detector("hsv", h, robots)
    assert isinstance(hsv, HsvDetector) and set(hsv.ranges) == {"a", "b"}   # white is skipped
    assert hsv.ranges["b"].lo == (100, 100, 50)
    with pytest.raises(SetupError, match="unknown detector"):
        build_detector("yolo", h, robots)


def test_detection_message_round_trip():
    from groundtruth.rgb import Detection

    d = Detection(12, "zumo1", 0.5, 0.6, float("nan"), 100.0, 200.0, "hsv")
    msg = decode(detection_to_message(d).encode())
    assert msg.robot == "zumo1" and msg.yaw is None and msg.stamp_us == 12 and msg.x == 0.5


def test_reconnects_when_the_live_stream_drops(tmp_path):
    """The webcam server restarts on the same port: the runner reopens the URL and goes on."""
    from groundtruth.rgb import FrameSource
    from groundtruth.service import GroundTruthRunner

    w = _world()
    m = WebcamModel(w)
    h = homography_from_calibration(m.calibration)
    cam = WebcamServer(m).start()
    port = cam.port
    runner = GroundTruthRunner(None, FrameSource(cam.url), MarkerDetector({3: "zumo1"}, h),
                               csv_path=tmp_path / "gt.csv")
    assert runner.run(max_frames=5) == 5
    cam.stop()
    second = WebcamServer(m, port=port)
    restarted = threading.Timer(0.5, second.start)
    restarted.start()
    try:
        assert runner.run(max_frames=10, duration_s=30) == 10
    finally:
        restarted.join()
        second.stop()
        runner.close()
        runner.source.close()
    assert runner.detections == 10


def test_runs_from_the_lab_config(tmp_path):
    """[webcam] gives source, calibration and detector; [[robots]] give names and colours."""
    w = _world(markers=False)
    m = WebcamModel(w)
    (tmp_path / "cal.json").write_text(json.dumps(m.calibration))
    m.record(tmp_path / "run.avi", seconds=0.5)
    (tmp_path / "lab.toml").write_text(
        '[webcam]\nsource = "run.avi"\ncalibration = "cal.json"\ndetector = "hsv"\n\n'
        '[[robots]]\nname = "zumo1"\ncolor = "#dc2828"\n\n'
        '[[robots]]\nname = "zumo2"\ncolor = [40, 80, 220]\n')
    r = subprocess.run([sys.executable, "-m", "groundtruth", "--lab", "lab.toml", "--no-zenoh", "--csv", "gt.csv"],
                       capture_output=True, text=True, timeout=90, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "hsv detector" in r.stdout and "robots seen: zumo1, zumo2" in r.stdout
    assert len(list(csv.DictReader(open(tmp_path / "gt.csv")))) == 24


def test_calibrate_at_shell_height_from_markers_at_known_spots(tmp_path, capsys):
    """Four marker robots at known positions give the shell-top homography (vs the camera's exact one)."""
    spots = {0: (0.15, 0.15), 1: (1.68, 0.2), 2: (1.6, 1.7), 3: (0.2, 1.65)}
    w = World([RobotSpec(f"c{i}", (200, 200, 200), marker_id=i, start=(*xy, 0.3 * i)) for i, xy in spots.items()])
    m = WebcamModel(w)
    m.record(tmp_path / "calib.avi", seconds=0.5)
    at = [a for i, (x, y) in spots.items() for a in ("--at", f"{i}={x},{y}")]
    out = tmp_path / "cal.json"
    assert main(["groundtruth", "--video", str(tmp_path / "calib.avi"), "--calibrate-out", str(out), *at]) == 0
    assert "calibration written" in capsys.readouterr().out
    mine = homography_from_calibration(json.loads(out.read_text()))
    exact = homography_from_calibration(m.calibration)
    grid = np.array([[x, y] for x in np.linspace(0.1, 1.7, 5) for y in np.linspace(0.1, 1.7, 5)])
    err = np.linalg.norm(mine.to_arena(exact.to_pixel(grid)) - grid, axis=1)
    assert np.median(err) < 0.003 and err.max() < 0.008
    # a marker that is not in view: a clear error
    assert main(["groundtruth", "--video", str(tmp_path / "calib.avi"), "--calibrate-out", str(out),
                 *at[:6], "--at", "9=1,1"]) == 2
    assert "[9] not seen" in capsys.readouterr().err
    assert main(["groundtruth", "--video", str(tmp_path / "calib.avi"), "--calibrate-out", str(out),
                 "--at", "0=1"]) == 2
    assert "ID=X,Y" in capsys.readouterr().err

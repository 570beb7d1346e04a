"""ViewerState and ViewerServer without a browser: colours, projection, routes, SSE, CLI errors."""

from __future__ import annotations

import json
import socket
import threading
import time
import urllib.error
import urllib.request

import cv2
import numpy as np
import pytest

from arena import codec
from arena.events import make_events
from arena.messages import EventWindow, GroundTruthPose, Status, Telemetry, Track
from arena.cli import main
from tests.viewer.feed import CALIBRATION, to_px
from viewer.server import ViewerServer
from viewer.png import encode_indexed_png
from viewer.state import (BACKGROUND_RGB, OFF_RGB, ON_RGB, PALETTE, ViewerConfigError, ViewerState,
                          arena_to_pixel_homography)


def _win(seq, t_end, x, y, p, t=None, camera="cam0"):
    t = np.full(len(x), t_end - 1) if t is None else np.asarray(t)
    ev = make_events(x, y, p, t)
    return EventWindow(camera=camera, seq=seq, t_start_us=t_end - 10_000, t_end_us=t_end, width=8, height=4,
                       count=ev.size, codec=codec.DEFAULT_CODEC, data=codec.encode(ev))


def test_event_image_colours_last_event_wins_and_accumulation_window():
    st = ViewerState(accumulate_us=30_000)
    assert st.render_frame() is None
    st.on_window(_win(0, 10_000, [1, 2, 3], [0, 0, 0], [1, 0, 1], t=[9_000, 9_000, 9_000]))
    st.on_window(_win(1, 20_000, [3], [0], [0]))  # pixel 3 turns OFF later
    st.on_window(_win(0, 5_000, [1], [1], [1], camera="cam1"))  # another camera: ignored
    img = st.render_frame()
    assert img.shape == (4, 8, 3)
    assert tuple(img[0, 1]) == ON_RGB and tuple(img[0, 2]) == OFF_RGB and tuple(img[0, 3]) == OFF_RGB
    assert tuple(img[1, 1]) == BACKGROUND_RGB and tuple(img[3, 7]) == BACKGROUND_RGB
    st.on_window(_win(2, 45_000, [5], [2], [1]))  # window 0 ends 35 ms before: out of the 30 ms
    img = st.render_frame()
    assert tuple(img[0, 1]) == BACKGROUND_RGB and tuple(img[0, 3]) == OFF_RGB and tuple(img[2, 5]) == ON_RGB
    png = cv2.imdecode(np.frombuffer(encode_indexed_png(st.render_index(), PALETTE), np.uint8), cv2.IMREAD_COLOR)
    assert png.shape == (4, 8, 3) and (png[:, :, ::-1] == img).all()  # OpenCV reads our palette PNG as BGR
    st.on_window(_win(0, 10_000, [7], [3], [1]))  # sensor time went back (looping replay): start again
    img = st.render_frame()
    assert tuple(img[2, 5]) == BACKGROUND_RGB and tuple(img[3, 7]) == ON_RGB


def test_tracks_projected_with_the_calibration_when_they_carry_no_pixels():
    H = arena_to_pixel_homography(CALIBRATION)
    st = ViewerState(H_arena_to_px=H)
    st.on_track("arena/robots/a", Track(track_id=1, robot="a", x=1.0, y=0.5, yaw=0.0))
    st.on_track("arena/robots/a", Track(track_id=1, robot="a", x=1.1, y=0.5, yaw=0.0))
    st.on_track("arena/robots/7", Track(track_id=7, x=0.2, y=0.2, u_px=10.0, v_px=20.0,
                                        edge_publish_ns=time.time_ns() - 25_000_000))
    snap = {t["key"]: t for t in st.snapshot()["tracks"]}
    a = snap["arena/robots/a"]
    assert a["uv"] == pytest.approx(to_px(1.1, 0.5), abs=0.2)
    assert [list(p) for p in a["trail_m"]] == [[1.0, 0.5], [1.1, 0.5]]
    assert len(a["trail_px"]) == 2 and a["heading_px"][0] > a["uv"][0]  # yaw 0 points to +u here
    xs = [c[0] for c in a["box_px"]]
    assert max(xs) - min(xs) == pytest.approx(0.10 * 130, abs=0.5)  # 10 cm robot at 130 px/m
    assert snap["arena/robots/7"]["uv"] == [10.0, 20.0] and snap["arena/robots/7"]["label"] == "#7"
    assert 25 <= snap["arena/robots/7"]["latency_ms"] < 5_000 and a["latency_ms"] is None
    nocal = ViewerState()
    nocal.on_track("arena/robots/a", Track(track_id=1, x=1.0, y=0.5))
    t = nocal.snapshot()["tracks"][0]
    assert t["uv"] is None and t["box_px"] is None and t["trail_m"]


def test_bad_calibration_is_a_clear_error():
    with pytest.raises(ViewerConfigError, match="at least 4"):
        arena_to_pixel_homography({"points": [{"pixel": [0, 0], "arena_m": [0, 0]}]})
    with pytest.raises(ViewerConfigError, match="pixel"):
        arena_to_pixel_homography({"points": "nope"})


def _get(url):
    with urllib.request.urlopen(url, timeout=5) as r:
        return r.status, r.headers.get("Content-Type"), r.read()


def test_server_routes_and_event_stream():
    st = ViewerState()
    st.on_status(Status(role="edge", name="cam0", rates={"events": 1e6}, gauges={"latency_ms": 2.5}))
    st.on_alive("edge", "cam0", True)
    st.on_telemetry(Telemetry(robot="z1", seq=0, robot_time_us=0, host_time_ns=0, enc_left=0, enc_right=0,
                              speed_left=0.2, gyro=(0, 0, 0.5), battery_mv=4700))
    srv = ViewerServer(st, "127.0.0.1", 0, period_s=0.05)
    th = threading.Thread(target=srv.serve_forever, daemon=True)
    th.start()
    try:
        status, ctype, body = _get(srv.url)
        assert status == 200 and ctype.startswith("text/html") and b"/static/viewer.js" in body
        assert b"http://" not in body and b"https://" not in body  # no CDN
        for name in ("viewer.js", "viewer.css"):
            assert _get(srv.url + "static/" + name)[0] == 200
        with pytest.raises(urllib.error.HTTPError) as e:
            _get(srv.url + "frame.png")
        assert e.value.code == 503  # nothing to draw yet
        with pytest.raises(urllib.error.HTTPError) as e:
            _get(srv.url + "static/../cli.py")
        assert e.value.code == 404
        st.on_window(_win(0, 10_000, [1], [1], [1]))
        status, ctype, png = _get(srv.url + "frame.png")
        assert ctype == "image/png" and png.startswith(b"\x89PNG")
        snap = json.loads(_get(srv.url + "state.json")[2])
        assert snap["services"][0]["alive"] and snap["telemetry"]["z1"]["gyro_z"] == [0.5]
        with urllib.request.urlopen(srv.url + "events", timeout=5) as r:
            assert r.headers["Content-Type"] == "text/event-stream"
            datas = []
            while len(datas) < 2:
                line = r.readline().decode()
                if line.startswith("data: {\"time_ns\""):
                    datas.append(json.loads(line[6:]))
        assert datas[1]["time_ns"] > datas[0]["time_ns"] and datas[0]["image"]["width"] == 8
    finally:
        srv.shutdown()
        srv.server_close()


def test_cli_errors_are_clear(tmp_path, capsys):
    def view(*args: str) -> tuple[int, str]:
        rc = main(["view", *args])
        return rc, capsys.readouterr().err

    rc, err = view("--camera", "cam/0")
    assert rc == 2 and "--camera" in err
    lab = tmp_path / "lab.toml"
    lab.write_text('[[cameras]]\nname = "cam0"\ncalibration = "missing.json"\n')
    rc, err = view("--lab", str(lab))
    assert rc == 2 and "missing.json" in err
    rc, err = view("--calibration", str(tmp_path / "nope.json"))
    assert rc == 2 and "nope.json" in err
    bad = tmp_path / "bad.json"
    bad.write_text('{"points": []}')
    rc, err = view("--calibration", str(bad))
    assert rc == 2 and "at least 4" in err
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        rc, err = view("--port", str(s.getsockname()[1]))
    assert rc == 2 and "--port 0" in err


def test_pixels_of_other_cameras_are_not_used():
    H = arena_to_pixel_homography(CALIBRATION)
    st = ViewerState(camera="cam0", H_arena_to_px=H)
    st.on_track("arena/robots/a", Track(track_id=1, camera="cam1", x=1.0, y=0.5, u_px=1.0, v_px=2.0))
    st.on_groundtruth(GroundTruthPose(robot="a", stamp_us=0, x=1.0, y=0.5, u_px=900.0, v_px=700.0, detector="aruco"))
    snap = st.snapshot()
    assert snap["tracks"][0]["uv"] == pytest.approx(to_px(1.0, 0.5), abs=0.2)  # projected, not cam1's pixel
    assert snap["groundtruth"][0]["uv"] == pytest.approx(to_px(1.0, 0.5), abs=0.2)  # not the webcam's pixel


def test_frame_rendered_once_per_new_window_for_all_pages():
    st = ViewerState()
    srv = ViewerServer(st, "127.0.0.1", 0)
    try:
        assert srv.frame_url(0) is None
        st.on_window(_win(0, 10_000, [1], [1], [1]))
        url = srv.frame_url(1)
        assert url.startswith("data:image/png;base64,")
        frames = st.frame_no
        assert srv.frame_url(1) is url and st.frame_no == frames  # a second page: no new render
        st.on_window(_win(1, 20_000, [2], [2], [0]))
        assert srv.frame_url(2) != url and st.frame_no == frames + 1
    finally:
        srv.server_close()


def test_viewer_stops_on_sigterm_delivered_to_another_thread(router):
    import os
    import subprocess

    from tests.conftest import arena_cmd, wait_for_line
    from tests.recorder.signals import term_other_thread

    view = subprocess.Popen(arena_cmd("view", "--port", "0", *router.args), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        wait_for_line(view, "viewer on", timeout=60)
        try:
            term_other_thread(view.pid)
        except RuntimeError as exc:
            pytest.skip(str(exc))
        out = view.communicate(timeout=15)[0]
    finally:
        if view.poll() is None:
            view.kill()
            view.wait()
    assert view.returncode == 0, out


def test_windows_of_one_end_time_are_bounded_by_count_and_events():
    """A flood of windows stamped with one end time (a broken or hostile camera) cannot grow the
    accumulated image without bound: the oldest windows go first, the newest are drawn."""
    s = ViewerState(max_windows=50, max_events=120)
    for i in range(5000):
        s.on_window(_win(i, 1_000_000, [i % 8], [0], [1]))
    snap = s.snapshot()
    assert s.counts["windows"] == 5000
    assert snap["image"]["windows"] == 50 and snap["image"]["events"] == 50
    s2 = ViewerState(max_windows=1000, max_events=120)
    for i in range(300):
        s2.on_window(_win(i, 1_000_000, [0] * 10, [0] * 10, [1] * 10))
    assert s2.snapshot()["image"]["events"] == 120 and s2.snapshot()["image"]["windows"] == 12
    # the newest window is drawn
    s.on_window(_win(9999, 1_000_000, [3], [2], [0]))
    assert s.render_index()[2, 3] == 2

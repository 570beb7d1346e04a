"""The viewer in headless Chromium (driven through chromedriver's W3C WebDriver HTTP API, stdlib
only): a publisher process feeds synthetic events and moving tracks through a real router to a real
`arena view` process; two screenshots must show the tracks moved. With ARENA_UPDATE_DOCS=1 the
second one is saved as docs/viewer.png (the README's screenshot); otherwise a test run leaves the
checkout as it was."""

from __future__ import annotations

import base64
import json
import math
import os
import shutil
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.conftest import REPO, arena_cmd, free_port, wait_for_line
from tests.viewer.feed import CALIBRATION

CHROMIUM = "/usr/bin/chromium"
CHROMEDRIVER = "/usr/bin/chromedriver"
CHROME_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
               "--disable-background-networking", "--disable-component-update", "--disable-sync",
               "--disable-dev-shm-usage", "--window-size=1400,1250"]


@pytest.fixture(scope="session")
def chromium():
    """Paths of chromium and chromedriver; installs the Debian packages when missing and root."""
    if not (os.path.exists(CHROMIUM) and os.path.exists(CHROMEDRIVER)):
        if os.geteuid() != 0 or shutil.which("apt-get") is None:
            pytest.skip("chromium/chromium-driver missing and not root with apt-get to install them")
        env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
        for cmd in (["apt-get", "update", "-q"], ["apt-get", "install", "-y", "-q", "chromium", "chromium-driver"]):
            r = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=900)
            if r.returncode != 0:
                pytest.skip(f"could not install chromium ({' '.join(cmd)}): {r.stderr[-500:]}")
    return CHROMIUM, CHROMEDRIVER


class WebDriver:
    """The few W3C WebDriver commands the test needs, over HTTP to a chromedriver process."""

    def __init__(self, driver: str, binary: str, user_data_dir: Path):
        self.port = free_port()
        self.proc = subprocess.Popen([driver, f"--port={self.port}"], stdout=subprocess.DEVNULL,
                                     stderr=subprocess.DEVNULL)
        self.base = f"http://127.0.0.1:{self.port}"
        deadline = time.monotonic() + 30
        while True:
            try:
                if self._call("GET", "/status")["ready"]:
                    break
            except OSError:
                pass
            if time.monotonic() > deadline:
                self.quit()
                raise AssertionError("chromedriver did not become ready in 30 s")
            time.sleep(0.2)
        caps = {"capabilities": {"alwaysMatch": {"browserName": "chrome", "goog:chromeOptions": {
            "binary": binary, "args": [*CHROME_ARGS, f"--user-data-dir={user_data_dir}"]}}}}
        self.session = self._call("POST", "/session", caps)["sessionId"]

    def _call(self, method: str, path: str, body: dict | None = None):
        data = None if body is None else json.dumps(body).encode()
        req = urllib.request.Request(self.base + path, data=data, method=method,
                                     headers={"Content-Type": "application/json"})
        with urllib.request.urlopen(req, timeout=60) as r:
            return json.loads(r.read())["value"]

    def cmd(self, method: str, path: str, body: dict | None = None):
        return self._call(method, f"/session/{self.session}{path}", body)

    def get(self, url: str) -> None:
        self.cmd("POST", "/url", {"url": url})

    def js(self, script: str):
        return self.cmd("POST", "/execute/sync", {"script": script, "args": []})

    def screenshot(self) -> bytes:
        return base64.b64decode(self.cmd("GET", "/screenshot"))

    def quit(self) -> None:
        try:
            if getattr(self, "session", None):
                self._call("DELETE", f"/session/{self.session}")
        except OSError:
            pass
        self.proc.terminate()
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(timeout=10)


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=5)


STATE_JS = """
const s = window.arenaState;
if (!s) return null;
return {frames: window.arenaFrames,
        tracks: s.tracks.map(t => ({label: t.label, x: t.x, y: t.y, uv: t.uv, box: t.box_px, trail: t.trail_px.length})),
        rows: Array.from(document.querySelectorAll('#tracks tbody tr td:first-child')).map(td => td.textContent),
        errors: Array.from(document.querySelectorAll('#tracks tbody tr td:nth-child(8)')).map(td => td.textContent),
        services: Array.from(document.querySelectorAll('#services tbody tr')).map(tr => tr.textContent),
        sparks: document.querySelectorAll('#telemetry canvas').length,
        gt: s.groundtruth.length, conn: document.getElementById('conn').textContent};
"""


def _wait_state(wd: WebDriver, ok, timeout: float = 45.0) -> dict:
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        last = wd.js(STATE_JS)
        if last and ok(last):
            return last
        time.sleep(0.25)
    raise AssertionError(f"page did not reach the expected state in {timeout}s; last: {last}")


@pytest.mark.slow
def test_viewer_in_headless_chromium_shows_moving_tracks(chromium, router, tmp_path):
    binary, driver = chromium
    calib = tmp_path / "calib.json"
    calib.write_text(json.dumps(CALIBRATION))
    lab = tmp_path / "lab.toml"
    lab.write_text(f'[[cameras]]\nname = "cam0"\nwidth = 320\nheight = 240\ncalibration = "{calib}"\n')
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    view = subprocess.Popen(arena_cmd("view", "--port", "0", "--lab", str(lab), "--name", "v1", *router.args),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    feed = None
    wd = None
    try:
        url = wait_for_line(view, "viewer on", timeout=60).split()[2]
        feed = subprocess.Popen([sys.executable, "-m", "tests.viewer.feed", router.endpoint, "60"],
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, cwd=REPO)
        wait_for_line(feed, "feeding", timeout=60)
        wd = WebDriver(driver, binary, tmp_path / "chrome-profile")
        wd.get(url)
        ready = lambda s: (s["frames"] > 0 and len(s["tracks"]) == 2 and all(t["uv"] and t["box"] for t in s["tracks"])
                           and all(t["trail"] >= 3 for t in s["tracks"]))
        s1 = _wait_state(wd, ready)
        shot1 = wd.screenshot()
        time.sleep(2.0)
        s2 = _wait_state(wd, lambda s: ready(s) and s["frames"] > s1["frames"])
        shot2 = wd.screenshot()
    finally:
        if wd is not None:
            wd.quit()
        if feed is not None:
            _stop(feed)
        _stop(view)
    assert view.returncode == 0, view.stdout.read()  # SIGTERM (as arena demo stops it) is a clean exit

    # the page's own state: both robots, drawn with boxes, moved between the two screenshots
    assert sorted(s2["rows"]) == ["zumo1", "zumo2"] and s2["conn"] == "live"
    # the feed's ground truth is 1 cm off in x at the tracks' own stamps: the error column says 1 cm
    assert s2["errors"] == ["0.010", "0.010"], s2["errors"]
    p1 = {t["label"]: t for t in s1["tracks"]}
    for t in s2["tracks"]:
        moved_m = math.hypot(t["x"] - p1[t["label"]]["x"], t["y"] - p1[t["label"]]["y"])
        moved_px = math.hypot(t["uv"][0] - p1[t["label"]]["uv"][0], t["uv"][1] - p1[t["label"]]["uv"][1])
        assert moved_m > 0.1 and moved_px > 10, (t, p1[t["label"]])
    assert s2["gt"] == 2 and s2["sparks"] == 8  # 2 robots x (2 wheels, gyro z, battery)
    assert any("viewer" in r and "v1" in r for r in s2["services"])
    assert any("sim" in r and "feed" in r for r in s2["services"])

    # the pixels: the event image (black ON / blue OFF on white) is there and the picture changed
    a = cv2.imdecode(np.frombuffer(shot1, np.uint8), cv2.IMREAD_COLOR)
    b = cv2.imdecode(np.frombuffer(shot2, np.uint8), cv2.IMREAD_COLOR)
    assert a.shape == b.shape and a.shape[0] > 600
    blue = (b[:, :, 0] > 200) & (b[:, :, 1] < 60) & (b[:, :, 2] < 60)
    assert blue.sum() > 50, "no OFF (blue) event pixels in the screenshot"
    changed = np.abs(a.astype(int) - b.astype(int)).sum(axis=2) > 60
    assert changed.sum() > 500, "the two screenshots are (nearly) the same"
    if os.environ.get("ARENA_UPDATE_DOCS") == "1":
        (REPO / "docs" / "viewer.png").write_bytes(shot2)

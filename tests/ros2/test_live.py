"""`arena ros2`: tracks published on a real router come out as CDR PoseStamped / TFMessage on the
keys zenoh-bridge-ros2dds maps to /arena/robots/<name>/pose and /tf, read back with rosbags."""

from __future__ import annotations

import math
import os
import re
import signal
import subprocess
import sys
import threading
import time

import pytest

pytest.importorskip("rosbags")
from rosbags.typesys import Stores, get_typestore  # noqa: E402

from arena.messages import GroundTruthPose, Status, Track  # noqa: E402
from arena.session import ZenohSettings, open_session  # noqa: E402
from ros2.cdr import Serializer  # noqa: E402
from ros2.convert import yaw_from_quaternion  # noqa: E402
from ros2.service import run_bridge  # noqa: E402
from tests.conftest import REPO  # noqa: E402

TS = get_typestore(Stores.ROS2_HUMBLE)


class Collector:
    """Subscribes to the bridge's output keys and keeps every sample (key -> list of payloads)."""

    def __init__(self, session, keys):
        self.got: dict[str, list[bytes]] = {}
        self.lock = threading.Lock()
        self.subs = [session.declare_subscriber(k, self._on) for k in keys]

    def _on(self, sample):
        with self.lock:
            self.got.setdefault(str(sample.key_expr), []).append(sample.payload.to_bytes())

    def has(self, *keys) -> bool:
        with self.lock:
            return all(self.got.get(k) for k in keys)

    def first(self, key) -> bytes:
        with self.lock:
            return self.got[key][0]


def _publish_until(pub_session, samples, done, timeout=20.0):
    """Publish ``samples`` every 100 ms until ``done()`` (subscriptions propagate asynchronously)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for key, payload in samples:
            pub_session.put(key, payload)
        if done():
            return
        time.sleep(0.1)
    raise AssertionError("the bridge's CDR samples did not arrive within 20 s")


def _stamp_ns(header) -> int:
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def test_tracks_become_cdr_pose_stamped_and_tf_on_the_bridge_keys(router):
    settings = ZenohSettings(mode="client", connect=[router.endpoint])
    stop = threading.Event()
    result, col = {}, None
    with open_session(settings) as bridge_s, open_session(settings) as pub_s, open_session(settings) as sub_s:
        ready = threading.Event()
        th = threading.Thread(target=lambda: result.setdefault("r", run_bridge(
            bridge_s, Serializer(), stop, name="t1", groundtruth=True, offset_ns=5, on_ready=ready.set)))
        th.start()
        try:
            assert ready.wait(10)
            col = Collector(sub_s, ["arena/robots/*/pose", "arena/groundtruth/*/pose", "tf"])
            named = Track(track_id=1, robot="zumo1", camera="cam0", stamp_us=2_500_000, x=0.75, y=0.5, yaw=1.2)
            unnamed = Track(track_id=7, robot=None, stamp_us=2_510_000, x=1.25, y=0.125, yaw=None)
            webcam = GroundTruthPose(robot="zumo1", stamp_us=2_400_000, x=0.74, y=0.51, yaw=1.1, detector="aruco")
            samples = [("arena/robots/zumo1", named.encode()), ("arena/robots/7", unnamed.encode()),
                       ("arena/groundtruth/zumo1", webcam.encode()),
                       ("arena/robots/zumo9", b"\xc1 not msgpack"),
                       ("arena/robots/zumo8", Status(role="edge", name="x", time_ns=1).encode())]
            _publish_until(pub_s, samples, lambda: col.has("arena/robots/zumo1/pose", "arena/robots/track_7/pose",
                                                           "arena/groundtruth/zumo1/pose", "tf"))
        finally:
            stop.set()
            th.join(10)
            for s in (col.subs if col is not None else []):
                s.undeclare()
    raw = col.first("arena/robots/zumo1/pose")
    assert raw[:4] == b"\x00\x01\x00\x00"                      # CDR little-endian encapsulation header
    m = TS.deserialize_cdr(raw, "geometry_msgs/msg/PoseStamped")
    assert m.header.frame_id == "arena" and _stamp_ns(m.header) == 2_500_000_000 + 5
    assert (m.pose.position.x, m.pose.position.y, m.pose.position.z) == (0.75, 0.5, 0.0)
    q = m.pose.orientation
    assert (q.x, q.y) == (0.0, 0.0) and q.z == pytest.approx(math.sin(0.6)) and q.w == pytest.approx(math.cos(0.6))

    u = TS.deserialize_cdr(col.first("arena/robots/track_7/pose"), "geometry_msgs/msg/PoseStamped")
    assert (u.pose.position.x, u.pose.position.y) == (1.25, 0.125) and math.isnan(u.pose.orientation.w)

    tf = TS.deserialize_cdr(col.first("tf"), "tf2_msgs/msg/TFMessage")
    [tr] = tf.transforms                                        # only the track with a heading
    assert tr.header.frame_id == "arena" and tr.child_frame_id == "zumo1"
    assert (tr.transform.translation.x, tr.transform.translation.y) == (0.75, 0.5)
    assert yaw_from_quaternion(tr.transform.rotation.x, tr.transform.rotation.y, tr.transform.rotation.z,
                               tr.transform.rotation.w) == pytest.approx(1.2)
    with col.lock:
        assert all(TS.deserialize_cdr(b, "tf2_msgs/msg/TFMessage").transforms[0].child_frame_id == "zumo1"
                   for b in col.got["tf"])

    g = TS.deserialize_cdr(col.first("arena/groundtruth/zumo1/pose"), "geometry_msgs/msg/PoseStamped")
    assert (g.pose.position.x, g.pose.position.y, _stamp_ns(g.header)) == (0.74, 0.51, 2_400_000_005)

    r = result["r"]
    assert r.tracks >= 2 and r.groundtruth >= 1 and r.bad >= 2      # bad samples counted, bridge kept going
    assert r.published >= r.tracks + r.groundtruth                   # a sample each (and /tf for zumo1)


_CLI = ("import sys\n"
        "import argparse\n"
        "from ros2.cli import register_ros2\n"
        "p = argparse.ArgumentParser(prog='arena'); register_ros2(p.add_subparsers(dest='command'))\n"
        "a = p.parse_args(sys.argv[1:])\n"
        "sys.exit(a.func(a))\n")


class Lines:
    """Reads a process's output on a thread, so waiting for a line is bounded in time even when
    the process prints nothing more (``readline`` alone would block)."""

    def __init__(self, proc):
        self.lines: list[str] = []
        self.thread = threading.Thread(target=lambda: self.lines.extend(iter(proc.stdout.readline, "")), daemon=True)
        self.thread.start()

    def wait_for(self, needle: str, timeout: float = 30.0) -> str:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            hit = next((ln for ln in list(self.lines) if needle in ln), None)
            if hit is not None:
                return hit
            time.sleep(0.05)
        raise AssertionError(f"{needle!r} not printed within {timeout} s; got {''.join(self.lines)!r}")


def test_arena_ros2_process_with_a_namespace_stops_on_sigterm(router):
    """The command as its own process (through its register function, as `arena` calls it)."""
    proc = subprocess.Popen([sys.executable, "-c", _CLI, "ros2", "--namespace", "/lab", "--name", "r1",
                             "-e", router.endpoint], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        out = Lines(proc)
        out.wait_for("bridging arena/robots/* to ROS 2 CDR on lab/arena/robots/NAME/pose and lab/tf", 30)
        settings = ZenohSettings(mode="client", connect=[router.endpoint])
        with open_session(settings) as pub_s, open_session(settings) as sub_s:
            col = Collector(sub_s, ["lab/arena/robots/zumo-x/pose", "lab/arena/robots/zumo_x/pose"])
            t = Track(track_id=2, robot="zumo-x", stamp_us=10, x=0.25, y=0.5, yaw=0.0)
            _publish_until(pub_s, [("arena/robots/zumo-x", t.encode())], lambda: col.has("lab/arena/robots/zumo_x/pose"))
            for s in col.subs:
                s.undeclare()
        m = TS.deserialize_cdr(col.first("lab/arena/robots/zumo_x/pose"), "geometry_msgs/msg/PoseStamped")
        assert (m.pose.position.x, m.pose.position.y, _stamp_ns(m.header)) == (0.25, 0.5, 10_000)
        assert not col.got.get("lab/arena/robots/zumo-x/pose")
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=20)
        out.thread.join(10)
        text = "".join(out.lines)
        assert proc.returncode == 0, text
        m = re.search(r"bridged (\d+) tracks and 0 ground-truth poses as (\d+) ROS 2 samples .* rejected 0", text)
        assert m and int(m.group(1)) >= 1 and int(m.group(2)) >= 2 * int(m.group(1)), text   # pose + /tf each
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)


def test_arena_ros2_bad_namespace_is_one_line_exit_2():
    out = subprocess.run([sys.executable, "-c", _CLI, "ros2", "--namespace", "lab"], cwd=REPO,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1
    assert "--namespace 'lab' is not a ROS 2 namespace" in out.stderr

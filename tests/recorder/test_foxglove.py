"""Foxglove views of the arena: converted from real messages, written to MCAP, decoded with the
official readers (``mcap`` + ``mcap-protobuf-support``) against the schemas stored in the file;
`arena record` from another process; the live WebSocket server of the official ``foxglove-sdk``
read by a WebSocket client speaking Foxglove's protocol."""

from __future__ import annotations

import base64
import json
import math
import os
import signal
import struct
import subprocess
import sys
import textwrap
import threading
import time

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader

from arena import codec
from arena.events import make_events
from arena.messages import EventWindow, Track
from arena.session import open_session
from recorder.foxglove_views import FoxgloveConverter, RobotShape, pixel_to_arena_homography, schema_data
from recorder.mcapio import RunWriter, read_run
from tests.conftest import arena_cmd, wait_for_line

mcap_protobuf = pytest.importorskip("mcap_protobuf.decoder")

#: a calibration like the simulator's (pixel -> arena m): 1 px = 5 mm, origin at pixel (10, 20)
CALIB = {"image_size": [64, 48], "points": [{"pixel": [10 + x / 0.005, 20 + y / 0.005], "arena_m": [x, y]}
                                            for x, y in ((0, 0), (0.2, 0), (0.2, 0.1), (0, 0.1), (0.1, 0.05))]}


def _window(seq: int, xs, ys, ps, camera: str = "cam0") -> EventWindow:
    t0 = seq * 10_000
    ev = make_events(np.asarray(xs), np.asarray(ys), np.asarray(ps), t0 + np.arange(len(xs)) * 10)
    return EventWindow(camera=camera, seq=seq, t_start_us=t0, t_end_us=t0 + 10_000, width=64, height=48,
                       count=len(xs), codec=codec.DEFAULT_CODEC, data=codec.encode(ev),
                       publish_ns=1_700_000_000_000_000_000 + t0 * 1000)


def _write(path, samples, converter):
    """Record ``samples`` [(key, payload, log ns)] with their Foxglove views, as ``arena record`` does."""
    with RunWriter(path) as w:
        for key, payload, log_ns in samples:
            w.add(key, payload, log_ns)
            for m in converter.convert(key, payload, log_ns):
                w.add_derived(m.topic, m.schema, schema_data(m.schema), m.data, m.log_time_ns, m.publish_time_ns)


def _decoded(path) -> list[tuple[str, str, object, int]]:
    """(topic, schema name, decoded message, log time) of every Foxglove message in ``path``,
    decoded by mcap-protobuf-support against the schema stored in the file."""
    out = []
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[mcap_protobuf.DecoderFactory()])
        summary = reader.get_summary()
        topics = sorted({c.topic for c in summary.channels.values()
                         if summary.schemas[c.schema_id].name.startswith("foxglove.")})
        derived = {c.topic for c in summary.channels.values() if c.metadata.get("derived_from")}
        assert derived == set(topics)
        for schema, channel, message, decoded in reader.iter_decoded_messages(topics=topics, log_time_order=True):
            assert schema.encoding == "protobuf" and channel.message_encoding == "protobuf"
            assert channel.metadata == {"derived_from": "arena"}
            assert type(decoded).DESCRIPTOR.full_name == schema.name
            out.append((channel.topic, schema.name, decoded, message.log_time))
        assert len(out) == sum(summary.statistics.channel_message_counts[c.id]
                               for c in summary.channels.values() if c.topic in derived)
    return out


def test_track_views_pose_transform_box_arrow_label_and_a_topic_that_survives_the_name(tmp_path):
    t0 = 1_800_000_000_000_000_000
    unnamed = Track(track_id=3, robot=None, stamp_us=5, x=0.5, y=0.25, yaw=math.pi / 2, tracker_publish_ns=t0)
    named = Track(track_id=3, robot="yellow1", stamp_us=6, x=0.6, y=0.3, yaw=-0.5, tracker_publish_ns=t0 + 10**8)
    again = Track(track_id=3, robot="yellow1", stamp_us=7, x=0.61, y=0.3, yaw=-0.5, tracker_publish_ns=t0 + 2 * 10**8)
    samples = [("arena/robots/3", unnamed.encode(), t0 + 1000),
               ("arena/robots/yellow1", named.encode(), t0 + 10**8 + 1000),
               ("arena/robots/yellow1", again.encode(), t0 + 2 * 10**8 + 1000),
               ("arena/robots/junk", b"\xc1 not msgpack", t0 + 2 * 10**8 + 2000)]
    conv = FoxgloveConverter(arena_size_m=(1.5, 1.2),
                             robots={"yellow1": RobotShape(0.12, 0.09, color_rgb=(235, 200, 40))})
    path = tmp_path / "run.mcap"
    _write(path, samples, conv)
    got = _decoded(path)
    assert conv.rejected == 1 and "junk" in conv.last_error

    poses = [d for topic, s, d, _ in got if s == "foxglove.PoseInFrame"]
    assert {topic for topic, s, _, _ in got if s == "foxglove.PoseInFrame"} == {"foxglove/robots/track-3/pose"}
    assert len(poses) == 3 and all(p.frame_id == "arena" for p in poses)
    q = poses[0].pose.orientation
    assert (q.x, q.y) == (0, 0)
    assert q.z == pytest.approx(math.sin(math.pi / 4)) and q.w == pytest.approx(math.cos(math.pi / 4))
    assert poses[1].pose.orientation.z == pytest.approx(math.sin(-0.25))
    assert (poses[1].pose.position.x, poses[1].pose.position.y) == (0.6, 0.3)
    assert poses[0].timestamp.ToNanoseconds() == t0   # the tracker's publish time

    tfs = [d.transforms[0] for _, s, d, _ in got if s == "foxglove.FrameTransforms"]
    assert [(tf.parent_frame_id, tf.child_frame_id) for tf in tfs] == [("arena", "robot/track-3")] * 3
    assert tfs[2].translation.x == 0.61 and tfs[2].rotation.w == pytest.approx(math.cos(-0.25))

    scenes = [(topic, d.entities[0]) for topic, s, d, _ in got
              if s == "foxglove.SceneUpdate" and topic != "foxglove/arena"]
    assert {topic for topic, _ in scenes} == {"foxglove/robots/track-3/scene"}   # the name did not move it
    first, second = scenes[0][1], scenes[1][1]
    assert first.frame_id == "arena" and first.id == "robot/track-3"
    assert first.texts[0].text == "track 3" and second.texts[0].text == "yellow1"   # relabelled
    assert (first.cubes[0].size.x, first.cubes[0].size.y) == (0.10, 0.10)           # default robot
    assert (second.cubes[0].size.x, second.cubes[0].size.y) == (0.12, 0.09)         # the lab's yellow1
    assert second.cubes[0].color.r == pytest.approx(235 / 255)
    assert second.cubes[0].pose.position.x == 0.6
    assert second.arrows[0].pose.orientation.z == pytest.approx(math.sin(-0.25))
    assert first.arrows[0].pose.orientation.z == pytest.approx(math.sin(math.pi / 4))
    assert second.lifetime.ToNanoseconds() == 1_000_000_000

    outline = [d.entities[0] for topic, s, d, _ in got if topic == "foxglove/arena"]
    assert outline and outline[0].frame_id == "arena"
    assert [(p.x, p.y) for p in outline[0].lines[0].points] == [(0, 0), (1.5, 0), (1.5, 1.2), (0, 1.2)]

    # arena replay: the arena samples only, byte for byte
    assert [(m.key, m.payload) for m in read_run(path)] == [(k, p) for k, p, _ in samples]


def test_a_robot_reacquired_under_a_new_track_id_keeps_its_topic():
    conv = FoxgloveConverter(max_rate_hz=0)
    conv.convert("arena/robots/1", Track(track_id=1, x=0.1, y=0.1).encode(), 1)
    conv.convert("arena/robots/blue2", Track(track_id=1, robot="blue2", x=0.1, y=0.1).encode(), 2)
    out = conv.convert("arena/robots/blue2", Track(track_id=9, robot="blue2", x=0.1, y=0.1).encode(), 3)
    assert {m.topic for m in out if m.schema == "foxglove.PoseInFrame"} == {"foxglove/robots/track-1/pose"}
    out = conv.convert("arena/robots/red1", Track(track_id=4, robot="red1", x=0.1, y=0.1).encode(), 4)
    assert {m.topic for m in out if m.schema == "foxglove.PoseInFrame"} == {"foxglove/robots/red1/pose"}


def test_a_track_without_heading_has_no_arrow():
    conv = FoxgloveConverter()
    out = conv.convert("arena/robots/1", Track(track_id=1, x=0.2, y=0.3, yaw=None).encode(), 1)
    scene = [m for m in out if m.topic == "foxglove/robots/track-1/scene"][0]
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

    entity = SceneUpdate.FromString(scene.data).entities[0]
    assert len(entity.cubes) == 1 and len(entity.arrows) == 0 and entity.cubes[0].pose.orientation.w == 1.0


def test_track_updates_are_thinned_to_max_rate_but_name_changes_always_pass():
    conv = FoxgloveConverter(max_rate_hz=10)
    t = Track(track_id=1, x=0.1, y=0.1, yaw=0.0)
    n = [len(conv.convert("arena/robots/1", t.encode(), 10**9 + i * 10**7)) for i in range(30)]  # 100 Hz, 0.3 s
    assert sum(1 for k in n if k >= 3) == 3
    named = conv.convert("arena/robots/a", Track(track_id=1, robot="a", x=0.1, y=0.1).encode(), 10**9 + 30 * 10**7 + 1)
    assert len(named) == 3


def test_event_image_and_its_placement_in_the_arena(tmp_path):
    conv = FoxgloveConverter(image_period_us=30_000, accumulate_us=20_000,
                             pixel_to_arena={"cam0": pixel_to_arena_homography(CALIB)})
    samples = []
    for seq in range(7):   # one ON event at (10 + seq, 20), one OFF event at (30, 40) in every window
        w = _window(seq, [10 + seq, 30], [20, 40], [1, 0])
        samples.append(("arena/events/cam0", w.encode(), w.publish_ns + 500))
    path = tmp_path / "ev.mcap"
    _write(path, samples, conv)
    got = _decoded(path)
    images = [(d, t) for topic, s, d, t in got if s == "foxglove.CompressedImage"]
    assert [topic for topic, s, _, _ in got if s == "foxglove.CompressedImage"][0] == "foxglove/events/cam0/image"
    # frames at the first window's end, then every 30 ms of sensor time: windows 0, 3, 6
    assert len(images) == 3
    img, log_time = images[1]
    assert img.frame_id == "cam0" and img.format == "png"
    assert img.timestamp.ToNanoseconds() == _window(3, [0], [0], [0]).publish_ns and log_time == samples[3][2]
    bgr = cv2.imdecode(np.frombuffer(img.data, np.uint8), cv2.IMREAD_COLOR)
    assert bgr.shape == (48, 64, 3)
    rgb = bgr[..., ::-1]
    # window 3 shows windows 2 and 3 (20 ms): ON at x = 12, 13; OFF at (30, 40); everything else white
    assert rgb[20, 12].tolist() == [0, 0, 0] and rgb[20, 13].tolist() == [0, 0, 0]
    assert rgb[40, 30].tolist() == [30, 60, 200]
    assert rgb[20, 11].tolist() == [255, 255, 255] and rgb[20, 14].tolist() == [255, 255, 255]
    assert int((rgb.sum(axis=2) < 765).sum()) == 3

    clouds = [d for _, s, d, _ in got if s == "foxglove.PointCloud"]
    assert len(clouds) == 3 and clouds[1].frame_id == "arena" and clouds[1].point_stride == 16
    fields = {f.name: (f.offset, f.type) for f in clouds[1].fields}
    assert fields["x"] == (0, 7) and fields["red"] == (12, 1)
    pts = np.frombuffer(clouds[1].data, np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"),
                                                  ("g", "u1"), ("b", "u1"), ("a", "u1")]))
    placed = sorted((round(float(p["x"]), 4), round(float(p["y"]), 4), int(p["b"])) for p in pts)
    # pixel (u, v) -> arena ((u - 10) * 5 mm, (v - 20) * 5 mm)
    assert placed == [(0.01, 0.0, 0), (0.015, 0.0, 0), (0.1, 0.1, 200)]


def test_without_calibration_the_image_is_not_placed():
    conv = FoxgloveConverter()
    out = conv.convert("arena/events/cam0", _window(0, [1], [1], [1]).encode(), 5)
    assert [m.schema for m in out] == ["foxglove.SceneUpdate", "foxglove.CompressedImage"]


PUBLISHER = textwrap.dedent("""
    import sys, time
    from arena.session import ZenohSettings, open_session
    from arena.messages import Track
    from tests.recorder.test_foxglove import _window
    with open_session(ZenohSettings(mode="peer", connect=[sys.argv[1]])) as s:
        time.sleep(1.0)
        for i in range(60):
            name = "zumo1" if i >= 20 else None
            key = "arena/robots/zumo1" if name else "arena/robots/1"
            s.put(key, Track(track_id=1, robot=name, stamp_us=i * 10_000, x=0.01 * i, y=0.5, yaw=0.02 * i,
                             tracker_publish_ns=time.time_ns()).encode())
            s.put("arena/events/cam0", _window(i, [10 + i % 40, 20], [20, 30], [1, 0]).encode())
            time.sleep(0.01)
        time.sleep(0.5)
    print("published", flush=True)
""")


def test_arena_record_writes_foxglove_views_every_one_decodes(router, tmp_path):
    calib = tmp_path / "cam0.calib.json"
    calib.write_text(json.dumps(CALIB))
    out = tmp_path / "run.mcap"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    rec = subprocess.Popen(arena_cmd("record", str(out), "--name", "rec1", "--calibration", str(calib),
                                     "--image-hz", "10", *router.args),
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    try:
        wait_for_line(rec, "recording arena/**", timeout=30)
        pub = subprocess.run([sys.executable, "-c", PUBLISHER, router.endpoint], capture_output=True, text=True,
                             timeout=60, cwd=os.getcwd(), env=env)
        assert pub.returncode == 0, pub.stderr
        rec.send_signal(signal.SIGTERM)
        tail = rec.communicate(timeout=30)[0]
    finally:
        if rec.poll() is None:
            rec.kill()
    assert rec.returncode == 0, tail
    assert "Foxglove messages" in tail and "dropped 0" in tail

    got = _decoded(out)   # every Foxglove message decodes against its schema
    by_schema: dict[str, set] = {}
    for topic, schema, _, _ in got:
        by_schema.setdefault(schema, set()).add(topic)
    assert by_schema["foxglove.PoseInFrame"] == {"foxglove/robots/track-1/pose"}
    assert by_schema["foxglove.FrameTransforms"] == {"foxglove/tf"}
    assert by_schema["foxglove.SceneUpdate"] == {"foxglove/robots/track-1/scene", "foxglove/arena"}
    assert by_schema["foxglove.CompressedImage"] == {"foxglove/events/cam0/image"}
    assert by_schema["foxglove.PointCloud"] == {"foxglove/events/cam0/points"}
    labels = [d.entities[0].texts[0].text for t, _, d, _ in got if t == "foxglove/robots/track-1/scene"]
    assert labels[0] == "track 1" and labels[-1] == "zumo1"
    images = [d for t, _, d, _ in got if t == "foxglove/events/cam0/image"]
    assert 4 <= len(images) <= 7   # 0.6 s of sensor time at 10 Hz
    assert cv2.imdecode(np.frombuffer(images[-1].data, np.uint8), cv2.IMREAD_COLOR).shape == (48, 64, 3)

    # arena replay reads back the arena channels only
    keys = {m.key for m in read_run(out)}
    assert {"arena/robots/1", "arena/robots/zumo1", "arena/events/cam0"} <= keys
    assert not any(k.startswith("foxglove/") for k in keys)


def test_arena_record_no_foxglove_and_a_bad_calibration(router, tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text('{"points": [{"pixel": [0, 0], "arena_m": [0, 0]}]}')
    r = subprocess.run(arena_cmd("record", str(tmp_path / "x.mcap"), "--calibration", str(bad), *router.args),
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "at least 4 points" in r.stderr and "Traceback" not in r.stderr
    r = subprocess.run(arena_cmd("record", str(tmp_path / "x.mcap"), "--image-hz", "0", *router.args),
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "--image-hz" in r.stderr
    # --no-foxglove: the arena channels only (the recorder's own status included)
    out = tmp_path / "plain.mcap"
    r = subprocess.run(arena_cmd("record", str(out), "--no-foxglove", "--duration", "2.5", "--name", "plain",
                                 *router.args), capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    with open(out, "rb") as f:
        topics = {c.topic for c in make_reader(f).get_summary().channels.values()}
    assert "arena/status/recorder/plain" in topics and not any(t.startswith("foxglove/") for t in topics)


def test_lab_config_gives_arena_size_robot_boxes_and_camera_placement():
    import argparse
    from pathlib import Path

    from arena.config import load_lab_config
    from recorder.cli import _foxglove_converter

    lab = load_lab_config(Path(__file__).resolve().parents[2] / "deploy" / "lab.example.toml")
    conv = _foxglove_converter(argparse.Namespace(calibration=None, image_hz=4.0, accumulate_ms=100.0), lab, "record")
    assert conv.arena_size_m == tuple(lab.arena.size_m)
    r = lab.robots[1]
    assert (conv.robots[r.name].length_m, conv.robots[r.name].width_m, conv.robots[r.name].color_rgb) == (
        r.length_m, r.width_m, tuple(r.color_rgb))
    assert set(conv.pixel_to_arena) == {c.name for c in lab.cameras if c.calibration or c.calibration_file}


# ----------------------------------------------------------------------------- live server


def test_live_server_serves_the_same_views_over_foxglove_websocket(router):
    pytest.importorskip("foxglove")
    ws_client = pytest.importorskip("websockets.sync.client")
    from google.protobuf import descriptor_pool, message_factory
    from google.protobuf.descriptor_pb2 import FileDescriptorSet

    from recorder.foxglove_live import LiveServer, serve

    stop = threading.Event()
    ready: list[str] = []
    result: list = []
    with open_session(router.settings("client")) as session, LiveServer(port=0) as live:
        th = threading.Thread(target=lambda: result.append(
            serve(session, FoxgloveConverter(), live, stop, name="fx-test", on_ready=ready.append)), daemon=True)
        th.start()
        deadline = time.monotonic() + 20
        while not ready and time.monotonic() < deadline and th.is_alive():
            time.sleep(0.05)
        assert ready, "the server did not start"
        decoded = None
        with ws_client.connect(ready[0], subprotocols=["foxglove.sdk.v1"], open_timeout=10) as ws, \
                open_session(router.settings("client")) as pub_session:
            info = json.loads(ws.recv(timeout=10))
            assert info["op"] == "serverInfo"
            channels: dict[str, dict] = {}
            sub_ids: list[int] = []
            subscribed_at = 0.0
            deadline = time.monotonic() + 30
            while decoded is None and time.monotonic() < deadline:
                pub_session.put("arena/robots/1", Track(track_id=1, x=0.25, y=0.5, yaw=1.0).encode())
                try:
                    msg = ws.recv(timeout=0.2)
                except TimeoutError:
                    msg = ""
                if isinstance(msg, str) and msg:
                    m = json.loads(msg)
                    if m["op"] == "advertise":
                        channels.update({c["topic"]: c for c in m["channels"]})
                if "foxglove/robots/track-1/pose" in channels and time.monotonic() - subscribed_at > 2:
                    # (again after 2 s without data: under load the SDK once answered a subscription
                    # sent right after the advertisement with "unknown channel")
                    sub_ids.append(7 + len(sub_ids))
                    c = channels["foxglove/robots/track-1/pose"]
                    ws.send(json.dumps({"op": "subscribe",
                                        "subscriptions": [{"id": sub_ids[-1], "channelId": c["id"]}]}))
                    subscribed_at = time.monotonic()
                if isinstance(msg, str):
                    continue
                assert msg[0] == 0x01   # binary opcode: message data
                sub_id, _log_ns = struct.unpack_from("<IQ", msg, 1)
                assert sub_id in sub_ids
                c = channels["foxglove/robots/track-1/pose"]
                assert (c["encoding"], c["schemaName"], c.get("schemaEncoding")) == ("protobuf", "foxglove.PoseInFrame",
                                                                                   "protobuf")
                fds = FileDescriptorSet.FromString(base64.b64decode(c["schema"]))
                assert fds.SerializeToString() == schema_data("foxglove.PoseInFrame")
                pool = descriptor_pool.DescriptorPool()
                for fd in fds.file:
                    pool.Add(fd)
                cls = message_factory.GetMessageClass(pool.FindMessageTypeByName("foxglove.PoseInFrame"))
                decoded = cls.FromString(msg[13:])
        stop.set()
        th.join(timeout=20)
    assert decoded is not None, f"no pose message; channels advertised: {sorted(channels)}"
    assert decoded.frame_id == "arena" and decoded.pose.position.x == 0.25
    assert decoded.pose.orientation.z == pytest.approx(math.sin(0.5))
    assert result and result[0].messages >= 3


#: ``arena foxglove`` through its registration function (the same one the ``arena.commands``
#: entry point names), so the test runs whether or not the installed metadata lists it yet
FOXGLOVE_CLI = textwrap.dedent("""
    import argparse, sys
    from recorder.cli import register_foxglove
    p = argparse.ArgumentParser(prog="arena")
    register_foxglove(p.add_subparsers())
    args = p.parse_args(sys.argv[1:])
    sys.exit(args.func(args))
""")


def test_arena_foxglove_command_serves_until_sigterm_and_rejects_a_busy_port(router):
    pytest.importorskip("foxglove")
    ws_client = pytest.importorskip("websockets.sync.client")
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-c", FOXGLOVE_CLI, "foxglove", "--port", "0", "--name", "fx1",
                             *router.args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    try:
        line = wait_for_line(proc, "foxglove server on ws://127.0.0.1:", timeout=60)
        url = line.split(" on ")[1].split()[0]
        port = int(url.rsplit(":", 1)[1])
        with ws_client.connect(url, subprotocols=["foxglove.sdk.v1"], open_timeout=10) as ws:
            assert json.loads(ws.recv(timeout=10))["op"] == "serverInfo"
        busy = subprocess.run([sys.executable, "-c", FOXGLOVE_CLI, "foxglove", "--port", str(port), *router.args],
                              capture_output=True, text=True, timeout=60, env=env)
        assert busy.returncode == 2 and "cannot serve on 127.0.0.1" in busy.stderr and "try --port 0" in busy.stderr
        assert "Traceback" not in busy.stderr
        proc.send_signal(signal.SIGTERM)
        tail = proc.communicate(timeout=30)[0]
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, tail
    assert "served 0 Foxglove messages" in tail

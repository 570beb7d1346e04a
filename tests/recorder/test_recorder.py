"""`arena record` / `arena replay`: real router, real processes, MCAP read back with mcap.reader."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time

import msgpack
import numpy as np
import pytest
from mcap.reader import make_reader

from arena import codec
from arena.events import make_events
from arena.messages import EventWindow, GroundTruthPose, Status, Telemetry, Track
from arena.session import ZenohSettings, open_session
from recorder.mcapio import RunFileError, RunWriter, read_run
from tests.conftest import arena_cmd, wait_for_line


def _window(seq: int) -> EventWindow:
    rng = np.random.default_rng(seq)
    n = 500
    ev = make_events(rng.integers(0, 64, n), rng.integers(0, 48, n), rng.integers(0, 2, n),
                     np.sort(rng.integers(seq * 10_000, (seq + 1) * 10_000, n)))
    return EventWindow(camera="cam0", seq=seq, t_start_us=seq * 10_000, t_end_us=(seq + 1) * 10_000,
                       width=64, height=48, count=n, codec=codec.DEFAULT_CODEC, data=codec.encode(ev),
                       publish_ns=1_700_000_000_000_000_000 + seq)


SAMPLES = [
    ("arena/robots/zumo1", Track(track_id=1, robot="zumo1", stamp_us=5, x=0.5, y=0.25, yaw=0.1,
                                 tracker_publish_ns=42).encode()),
    ("arena/telemetry/zumo1", Telemetry(robot="zumo1", seq=1, robot_time_us=10, host_time_ns=77,
                                        enc_left=3, enc_right=-4, gyro=(0.0, 0.0, 0.5), battery_mv=4800).encode()),
    ("arena/groundtruth/zumo1", GroundTruthPose(robot="zumo1", stamp_us=9, x=0.4, y=0.3, detector="sim").encode()),
    ("arena/status/edge/cam0", Status(role="edge", name="cam0", time_ns=99, counters={"windows": 3}).encode()),
    ("arena/events/cam0", _window(0).encode()),
    # not canonical for Python's msgpack (float32): must come back byte for byte anyway
    ("arena/robots/zumo1", msgpack.packb({"v": 1, "kind": "track", "track_id": 1, "x": 0.5}, use_single_float=True)),
    ("arena/robots/junk", b"\xc1 not msgpack"),
]


def test_layout_json_for_small_messages_msgpack_for_windows_and_lossless_roundtrip(tmp_path):
    path = tmp_path / "run.mcap"
    with RunWriter(path) as w:
        for i, (key, payload) in enumerate(SAMPLES):
            w.add(key, payload, 1_000 + i)
    with open(path, "rb") as f:
        reader = make_reader(f)
        assert reader.get_header().profile == "arena"
        rows = [(s, c, m) for s, c, m in reader.iter_messages()]
    assert len(rows) == len(SAMPLES)
    by_topic = {}
    for schema, channel, message in rows:
        by_topic.setdefault(channel.topic, []).append((schema, channel, message))
    schema, channel, message = by_topic["arena/robots/zumo1"][0]
    assert channel.message_encoding == "json" and schema.name == "arena.Track"
    assert schema.encoding == "jsonschema" and json.loads(schema.data)["properties"]["x"]["type"] == "number"
    assert json.loads(message.data)["x"] == 0.5 and message.publish_time == 42
    schema, channel, message = by_topic["arena/events/cam0"][0]
    assert (channel.message_encoding, schema.name) == ("msgpack", "arena.EventWindow")
    assert message.publish_time == _window(0).publish_ns
    assert by_topic["arena/telemetry/zumo1"][0][2].publish_time == 77
    assert by_topic["arena/groundtruth/zumo1"][0][2].publish_time == 1_002  # no own time: receive time
    raw = by_topic["arena/robots/zumo1"][1]
    assert (raw[1].message_encoding, raw[0].name) == ("msgpack", "arena.Raw")

    back = list(read_run(path))
    assert [(m.key, m.payload) for m in back] == SAMPLES
    assert [m.log_time_ns for m in back] == list(range(1_000, 1_000 + len(SAMPLES)))
    only = list(read_run(tmp_path, keys=["arena/robots/*"]))  # a run folder works too
    assert [m.key for m in only] == ["arena/robots/zumo1", "arena/robots/zumo1", "arena/robots/junk"]


def test_unreadable_runs_give_clear_errors(tmp_path):
    with pytest.raises(RunFileError, match="no .mcap file"):
        list(read_run(tmp_path))
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"not an mcap file at all")
    with pytest.raises(RunFileError, match="not a readable MCAP"):
        list(read_run(bad))
    r = subprocess.run(arena_cmd("replay", str(tmp_path / "missing.mcap")), capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 2 and "no such file" in r.stderr and "Traceback" not in r.stderr


PUBLISHER = textwrap.dedent("""
    import sys, time
    import numpy as np
    from arena.session import ZenohSettings, open_session
    from tests.recorder.test_recorder import SAMPLES, _window
    from arena.messages import Track
    with open_session(ZenohSettings(mode="peer", connect=[sys.argv[1]])) as s:
        time.sleep(1.0)
        for i in range(40):
            s.put("arena/robots/zumo1", Track(track_id=1, robot="zumo1", stamp_us=i, x=0.01 * i, y=0.5).encode())
            if i % 4 == 0:
                s.put("arena/events/cam0", _window(i).encode())
            time.sleep(0.01)
        for key, payload in SAMPLES:
            s.put(key, payload)
        time.sleep(0.5)
    print("published", flush=True)
""")


def _collect(got: list, lock: threading.Lock):
    def on_sample(sample):
        if str(sample.key_expr).startswith("arena/status/"):
            return
        with lock:
            got.append((str(sample.key_expr), sample.payload.to_bytes()))
    return on_sample


def test_record_from_another_process_then_replay_identical_payloads(router, tmp_path):
    out = tmp_path / "run.mcap"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    rec = subprocess.Popen(arena_cmd("record", str(out), "--name", "rec1", *router.args), stdout=subprocess.PIPE,
                           stderr=subprocess.STDOUT, text=True, env=env)
    try:
        wait_for_line(rec, "recording arena/**", timeout=30)
        pub = subprocess.run([sys.executable, "-c", PUBLISHER, router.endpoint], capture_output=True, text=True,
                             timeout=60, cwd=os.getcwd(), env=env)
        assert pub.returncode == 0, pub.stderr
        rec.send_signal(signal.SIGTERM)  # how `arena demo` stops it
        tail = rec.communicate(timeout=30)[0]
    finally:
        if rec.poll() is None:
            rec.kill()
    assert rec.returncode == 0, tail
    assert "recorded" in tail and "dropped 0" in tail

    with open(out, "rb") as f:  # finished file: summary with statistics
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics.message_count > 50
    recorded = [(m.key, m.payload) for m in read_run(out) if not m.key.startswith("arena/status/")]
    tracks = [p for k, p in recorded if k == "arena/robots/zumo1"]
    assert len(tracks) == 42 and len([1 for k, _ in recorded if k == "arena/events/cam0"]) == 11
    assert [Track.decode(p).stamp_us for p in tracks[:40]] == list(range(40))
    assert any(k == "arena/status/recorder/rec1" for k, _ in ((m.key, 0) for m in read_run(out)))

    # Replay as fast as possible while a subscriber in this process listens (both clients of the router).
    got, lock = [], threading.Lock()
    with open_session(ZenohSettings(mode="client", connect=[router.endpoint])) as s:
        s.declare_subscriber("arena/**", _collect(got, lock))  # one subscriber: one callback order
        r = subprocess.run(arena_cmd("replay", str(tmp_path), "--speed", "0", "--keys", "arena/robots/**",
                                     "--keys", "arena/events/*", "--keys", "arena/telemetry/*",
                                     "--keys", "arena/groundtruth/*", "-m", "client", *router.args),
                           capture_output=True, text=True, timeout=60, env=env)
        assert r.returncode == 0, r.stderr
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and len(got) < len(recorded):
            time.sleep(0.05)
    with lock:
        assert got == recorded  # same count, same bytes, same order
    assert f"replayed {len(recorded)} messages" in r.stdout


def test_replay_keeps_the_recorded_pace(router, tmp_path):
    path = tmp_path / "paced.mcap"
    with RunWriter(path) as w:
        for i in range(5):
            w.add("arena/robots/a", Track(track_id=1, stamp_us=i).encode(), 1_000_000_000 + i * 200_000_000)
    stamps = []
    with open_session(ZenohSettings(mode="peer", connect=[router.endpoint])) as s:
        s.declare_subscriber("arena/robots/a", lambda sample: stamps.append(time.monotonic()))
        r = subprocess.run(arena_cmd("replay", str(path), "--speed", "2", *router.args),
                           capture_output=True, text=True, timeout=60)
        time.sleep(0.3)
    assert r.returncode == 0, r.stderr
    assert len(stamps) == 5
    span = stamps[-1] - stamps[0]
    assert 0.3 < span < 0.9, span  # 0.8 s recorded at 2x = 0.4 s


def test_replay_loop_stops_cleanly_on_sigterm(router, tmp_path):
    path = tmp_path / "loop.mcap"
    with RunWriter(path) as w:
        for i in range(10):
            w.add("arena/robots/a", Track(track_id=1, stamp_us=i).encode(), 1_000_000_000 + i * 50_000_000)
    got = []
    with open_session(ZenohSettings(mode="peer", connect=[router.endpoint])) as s:
        s.declare_subscriber("arena/robots/a", lambda sample: got.append(1))
        proc = subprocess.Popen(arena_cmd("replay", str(path), "--loop", "--start-delay", "0.5", *router.args),
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                env={**os.environ, "PYTHONUNBUFFERED": "1"})
        try:
            wait_for_line(proc, "in a loop", timeout=60)
            deadline = time.monotonic() + 20
            while len(got) < 15 and time.monotonic() < deadline:  # more than one pass of 10
                time.sleep(0.05)
            proc.send_signal(signal.SIGTERM)
            out = proc.communicate(timeout=15)[0]
        finally:
            if proc.poll() is None:
                proc.kill()
    assert len(got) >= 15
    assert proc.returncode == 0 and "replayed" in out and "1 pass" in out, out


def test_cli_input_errors_exit_2_with_a_message(tmp_path, capsys):
    from arena.cli import main

    assert main(["record", str(tmp_path / "missing" / "run.mcap")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["record", str(tmp_path / "run.mcap"), "--duration", "0"]) == 2
    assert "--duration" in capsys.readouterr().err
    assert main(["record", str(tmp_path / "run.mcap"), "--name", "a/b"]) == 2
    assert "--name" in capsys.readouterr().err
    (tmp_path / "run.mcap").write_bytes(b"")
    assert main(["replay", str(tmp_path / "run.mcap"), "--speed", "-1"]) == 2
    assert "--speed" in capsys.readouterr().err


def test_sigterm_delivered_to_another_thread_still_stops_and_finishes_the_file(router, tmp_path):
    from tests.recorder.signals import term_other_thread

    out = tmp_path / "run.mcap"
    rec = subprocess.Popen(arena_cmd("record", str(out), *router.args), stdout=subprocess.PIPE,
                           stderr=subprocess.STDOUT, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        wait_for_line(rec, "recording", timeout=60)
        time.sleep(1.5)  # a status or two recorded
        try:
            term_other_thread(rec.pid)
        except RuntimeError as exc:
            pytest.skip(str(exc))
        tail = rec.communicate(timeout=15)[0]
    finally:
        if rec.poll() is None:
            rec.kill()
            rec.wait()
    assert rec.returncode == 0, tail
    assert list(read_run(out)), "the file was not finished"


def test_a_recording_cut_short_is_read_up_to_its_last_complete_chunk(tmp_path):
    path = tmp_path / "cut.mcap"
    with RunWriter(path, chunk_size=4096) as w:
        for i in range(400):
            w.add("arena/robots/a", Track(track_id=1, stamp_us=i, x=0.001 * i).encode(), 1_000 + i)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])  # as if the recorder was killed half way
    got = [Track.decode(m.payload).stamp_us for m in read_run(path)]
    assert 50 < len(got) < 400 and got == list(range(len(got)))


def test_record_counts_every_sample_as_written_or_dropped_when_its_queue_is_full(tmp_path, monkeypatch):
    # a burst far larger than the write queue: the writer drains it every 50 ms, so most of the
    # burst is dropped, and every sample is either in the file or counted as dropped
    import recorder.service as service
    from recorder.service import record

    # Zenoh hands a session's own subscriber its puts on another thread, after put returns: the
    # burst stops the recording only once the recorder's callback has seen all of them
    arrived = []
    on_sample = service._Recording.on_sample

    def counting(self, sample):
        on_sample(self, sample)
        arrived.append(1)

    monkeypatch.setattr(service._Recording, "on_sample", counting)
    stop = threading.Event()
    with open_session(ZenohSettings(mode="peer", connect=[], listen=[])) as s:
        pub = s.declare_publisher("arena/robots/zumo1")

        def burst():
            for i in range(2000):
                pub.put(Track(track_id=1, robot="zumo1", stamp_us=i, x=0.001 * i).encode())
            deadline = time.monotonic() + 20
            while len(arrived) < 2000 and time.monotonic() < deadline:
                threading.Event().wait(0.005)   # polling a condition: every sample handed over
            stop.set()

        res = record(s, tmp_path / "burst.mcap", ["arena/robots/*"], stop, queue_size=50,
                     on_ready=lambda: threading.Thread(target=burst, daemon=True).start())
    assert res.dropped > 0 and res.messages >= 50, (res.messages, res.dropped)
    assert res.messages + res.dropped == 2000, (res.messages, res.dropped)
    from arena.messages import decode
    stamps = [decode(m.payload).stamp_us for m in read_run(tmp_path / "burst.mcap")]
    assert len(stamps) == res.messages and stamps == sorted(stamps) and stamps[0] == 0, stamps[:5]

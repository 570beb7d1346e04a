"""The published JSON Schemas (docs/schemas/*.json): up to date with arena/messages.py, agreeing
with the project's own decoder on real encoded messages (valid and broken ones), and validating
every message recorded from real services; the worked example of docs/codec.md decodes as written."""

from __future__ import annotations

import json
import os
import re
import signal
import struct
import subprocess
import sys
import time
from dataclasses import MISSING, dataclass, fields
from pathlib import Path

import jsonschema
import msgpack
import numpy as np
import pytest

from arena import codec
from arena.events import make_events
from arena.messages import (MESSAGE_TYPES, Command, CommandReply, EventWindow, GroundTruthPose, MessageError,
                            MissionCommand, Status, Telemetry, Track, _spec, decode)
from arena.schemas import FIELD_DOCS, json_schemas, json_view, main, schema_files
from tests.conftest import REPO, arena_cmd, wait_for_line

SCHEMA_DIR = REPO / "docs" / "schemas"


def _published() -> dict[str, dict]:
    """The committed schemas, by kind (the ``const`` of their ``kind`` property)."""
    out = {}
    for path in sorted(SCHEMA_DIR.glob("*.json")):
        s = json.loads(path.read_text(encoding="utf-8"))
        out[s["properties"]["kind"]["const"]] = s
    return out


def _validator(kind: str) -> jsonschema.Draft202012Validator:
    schema = _published()[kind]
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema, format_checker=jsonschema.FormatChecker())


def _wire(msg) -> dict:
    """The message as it goes on the wire, decoded by plain msgpack (no project code)."""
    return msgpack.unpackb(msg.encode(), raw=False)


# --------------------------------------------------------------------------------------------
# (a) the committed files are what the generator writes now
# --------------------------------------------------------------------------------------------
def test_committed_schemas_are_what_the_generator_writes():
    committed = {p.name: p.read_text(encoding="utf-8") for p in SCHEMA_DIR.glob("*.json")}
    assert committed == schema_files(), "docs/schemas is stale: run `python -m arena.schemas --out docs/schemas`"
    assert set(_published()) == set(MESSAGE_TYPES)


def test_a_field_added_to_a_message_makes_the_committed_schemas_stale(monkeypatch, tmp_path, capsys):
    @dataclass
    class TrackPlus(Track):
        z: float = _spec("float", default=0.0)

    monkeypatch.setitem(MESSAGE_TYPES, "track", TrackPlus)
    now = schema_files()
    assert "z" in json.loads(now["track.json"])["properties"]
    committed = {p.name: p.read_text(encoding="utf-8") for p in SCHEMA_DIR.glob("*.json")}
    assert committed["track.json"] != now["track.json"]
    assert {n for n in now if now[n] != committed[n]} == {"track.json"}
    # the command's --check says so too, naming the file
    assert main(["--out", str(SCHEMA_DIR), "--check"]) == 1
    assert "track.json differs" in capsys.readouterr().err


def test_every_field_is_described_and_no_description_is_stale():
    for kind, cls in MESSAGE_TYPES.items():
        names = {f.name for f in fields(cls)}
        assert set(FIELD_DOCS[cls.__name__]) == names, cls.__name__
        props = json_schemas()[kind]["properties"]
        assert list(props) == ["v", "kind", *[f.name for f in fields(cls)]]  # the wire order
    assert set(FIELD_DOCS) == {cls.__name__ for cls in MESSAGE_TYPES.values()}


def test_the_command_writes_and_checks_a_folder(tmp_path, capsys):
    out = tmp_path / "s"
    assert main(["--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == sorted(schema_files())
    assert main(["--out", str(out), "--check"]) == 0
    (out / "track.json").write_text("{}")
    (out / "old.json").write_text("{}")
    assert main(["--out", str(out), "--check"]) == 1
    err = capsys.readouterr().err
    assert "track.json differs" in err and "old.json" in err
    # as a process, through the __main__ guard
    r = subprocess.run([sys.executable, "-m", "arena.schemas", "--out", str(SCHEMA_DIR), "--check"],
                       capture_output=True, text=True, timeout=60, cwd=REPO)
    assert r.returncode == 0 and "8 schemas" in r.stdout, r.stderr
    blocked = tmp_path / "file"
    blocked.write_text("")
    r = subprocess.run([sys.executable, "-m", "arena.schemas", "--out", str(blocked / "x")],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "cannot write" in r.stderr and "Traceback" not in r.stderr


# --------------------------------------------------------------------------------------------
# (b) real encoded messages validate; broken ones fail both the schema and the decoder
# --------------------------------------------------------------------------------------------
def _window() -> EventWindow:
    ev = make_events([3, 4, 5, 100], [10, 10, 10, 11], [1, 1, 1, 0], [1_000, 1_000, 1_000, 1_007])
    return EventWindow(camera="cam0", seq=7, t_start_us=1_000, t_end_us=11_000, width=640, height=480,
                       count=ev.size, codec=codec.DEFAULT_CODEC, data=codec.encode(ev), dropped=1, filtered=2,
                       publish_ns=1_700_000_000_000_000_000)


#: one message of every kind with every field set, and one with only its required fields
FULL = {
    "event_window": _window(),
    "track": Track(track_id=3, robot="zumo1", camera="cam0", stamp_us=1_000, x=0.5, y=-0.4, yaw=0.1, vx=0.2,
                   vy=-0.1, u_px=320.5, v_px=240.25, state="coasting", n_events=812, window_end_us=1_000,
                   edge_publish_ns=1_700_000_000_000_000_000, tracker_publish_ns=1_700_000_000_000_100_000),
    "telemetry": Telemetry(robot="zumo1", seq=9, robot_time_us=123_456, host_time_ns=1_700_000_000_000_000_000,
                           enc_left=-120, enc_right=130, speed_left=0.25, speed_right=-0.25, accel=(0.0, 0.1, 9.81),
                           gyro=(0, 0, 1), mag=(20.5, -3.0, 41.0), battery_mv=4800, power_left=-400,
                           power_right=400, mission="circle", phase="run"),
    "groundtruth": GroundTruthPose(robot="zumo1", stamp_us=5, x=1.0, y=2.0, yaw=-3.1, u_px=1.0, v_px=2.0,
                                   detector="aruco"),
    "mission": MissionCommand(mission="circle", params={"radius_m": 0.3, "laps": 2, "direction": "ccw",
                                                        "pts": [1, 2.5, None, "a", True]},
                              power=0.5, speed_mps=0.3, control="closed", start_ns=5, operator="ana"),
    "command": Command(verb="led", params={"on": True}, operator="ana"),
    "reply": CommandReply(ok=False, robot="zumo1", verb="mission", error="robot is in estop; send clear",
                          detail={"phase": None}),
    "status": Status(role="edge", name="cam0", host="h", pid=42, time_ns=1, uptime_s=3.5, state="running",
                     counters={"windows": 3}, rates={"windows": 100.0}, gauges={"latency_ms": 1.5}, errors=1,
                     last_error="boom"),
}
MINIMAL = {
    "event_window": EventWindow(camera="c", seq=0, t_start_us=-5, t_end_us=-5, width=1, height=1, count=0,
                                codec=codec.RAW_CODEC, data=b""),
    "track": Track(track_id=0),
    "telemetry": Telemetry(robot="r", seq=0, robot_time_us=0, host_time_ns=0, enc_left=0, enc_right=0),
    "groundtruth": GroundTruthPose(robot="r", stamp_us=0, x=0, y=0),
    "mission": MissionCommand(mission="square"),
    "command": Command(verb="stop"),
    "reply": CommandReply(ok=True),
    "status": Status(role="tracker", name="t"),
}


def test_the_examples_cover_every_kind_and_decode():
    assert set(FULL) == set(MINIMAL) == set(MESSAGE_TYPES)
    for kind in MESSAGE_TYPES:
        assert decode(FULL[kind].encode()) == FULL[kind]
        assert decode(MINIMAL[kind].encode()) == MINIMAL[kind]


@pytest.mark.parametrize("kind", list(MESSAGE_TYPES))
def test_real_encoded_messages_validate(kind):
    val = _validator(kind)
    for msg in (FULL[kind], MINIMAL[kind]):
        d = _wire(msg)
        assert list(d)[:2] == ["v", "kind"] and d["kind"] == kind
        val.validate(json_view(d))
        # only the required fields (what another sender may send) validate too
        required = {k: d[k] for k in _published()[kind]["required"]}
        val.validate(json_view(required))
        decode(msgpack.packb(required))
    # a newer sender's extra field is ignored by both
    val.validate(json_view({**_wire(FULL[kind]), "new_field": 1}))


def test_a_waypoint_mission_validates_and_deeper_nesting_does_not():
    """Waypoints are rows of numbers in a mission's params: the decoder and the schema agree."""
    val = _validator("mission")
    msg = MissionCommand(mission="waypoints", params={"points": [[0.5, 1.2], [0.8, 1.2], [0.8, 0.9]]})
    assert decode(msg.encode()).params["points"] == [[0.5, 1.2], [0.8, 1.2], [0.8, 0.9]]
    val.validate(json_view(_wire(msg)))
    deeper = {**_wire(msg), "params": {"points": [[[0.5, 1.2]]]}}
    with pytest.raises(jsonschema.ValidationError):
        val.validate(json_view(deeper))
    with pytest.raises(MessageError):
        decode(msgpack.packb(deeper))


def test_bytes_are_msgpack_bin_and_validate_as_base64():
    payload = FULL["event_window"].encode()
    d = msgpack.unpackb(payload, raw=False)
    assert isinstance(d["data"], bytes) and d["data"] == FULL["event_window"].data  # a bin, not a str
    val = _validator("event_window")
    assert not val.is_valid(d)  # the raw bytes are no JSON string: present them as base64
    view = json_view(d)
    val.validate(view)
    import base64
    assert base64.b64decode(view["data"]) == d["data"]
    assert _published()["event_window"]["properties"]["data"]["contentEncoding"] == "base64"


_WRONG_TYPE = {"int": "7", "float": "0.5", "bool": 1, "str": 5, "bytes": 5, "vec": "abc", "map": [1]}


def _mutations():
    """(kind, what, mutate) for every field: wrong type, missing (if required), out of range, not a choice."""
    for kind, cls in MESSAGE_TYPES.items():
        for f in fields(cls):
            meta = f.metadata
            yield kind, f"{f.name}: wrong type", (lambda d, n=f.name, v=_WRONG_TYPE[meta["kind"]]: d.__setitem__(n, v))
            if f.default is MISSING and f.default_factory is MISSING:  # a required field
                yield kind, f"{f.name}: missing", (lambda d, n=f.name: d.pop(n))
            if not meta["optional"]:
                yield kind, f"{f.name}: null", (lambda d, n=f.name: d.__setitem__(n, None))
            if meta["lo"] is not None:
                yield kind, f"{f.name}: below {meta['lo']}", (lambda d, n=f.name, v=meta["lo"] - 1: d.__setitem__(n, v))
            if meta["hi"] is not None:
                yield kind, f"{f.name}: above {meta['hi']}", (lambda d, n=f.name, v=meta["hi"] + 1: d.__setitem__(n, v))
            if meta["choices"]:
                yield kind, f"{f.name}: not a choice", (lambda d, n=f.name: d.__setitem__(n, "nope"))
            if meta["kind"] == "map":
                yield kind, f"{f.name}: nested map", (lambda d, n=f.name: d.__setitem__(n, {"a": {"b": 1}}))
                yield kind, f"{f.name}: long key", (lambda d, n=f.name: d.__setitem__(n, {"k" * 129: 1}))
            if meta["kind"] == "vec":
                yield kind, f"{f.name}: wrong length", (lambda d, n=f.name: d.__setitem__(n, [1.0, 2.0]))
                yield kind, f"{f.name}: not numbers", (lambda d, n=f.name: d.__setitem__(n, ["a", 1.0, 2.0]))
            if meta["kind"] == "str":
                yield kind, f"{f.name}: too long", (lambda d, n=f.name: d.__setitem__(n, "s" * 4097))
        yield kind, "v: newer", (lambda d: d.__setitem__("v", 2))
        yield kind, "v: missing", (lambda d: d.pop("v"))
        other = "track" if kind != "track" else "status"
        yield kind, "kind: other", (lambda d, other=other: d.__setitem__("kind", other))


MUTATIONS = list(_mutations())


@pytest.mark.parametrize("kind,what,mutate", MUTATIONS, ids=[f"{k}-{w}" for k, w, _ in MUTATIONS])
def test_broken_messages_fail_the_schema_and_the_decoder_alike(kind, what, mutate):
    d = _wire(FULL[kind])
    mutate(d)
    assert not _validator(kind).is_valid(json_view(d)), what
    with pytest.raises(MessageError):
        MESSAGE_TYPES[kind].decode(msgpack.packb(d, use_bin_type=True))


def test_there_are_mutations_of_every_kind():
    assert {k for k, _, _ in MUTATIONS} == set(MESSAGE_TYPES)
    assert len(MUTATIONS) > 150


# --------------------------------------------------------------------------------------------
# (c) every message recorded from real services validates
# --------------------------------------------------------------------------------------------
ENV = {**os.environ, "PYTHONUNBUFFERED": "1"}


def _sim(tmp_path: Path, router) -> tuple[subprocess.Popen, dict[str, str]]:
    proc = subprocess.Popen(arena_cmd("sim", "--robots", "1", "--autopilot", "circle", "--camera-port", "0",
                                      "--no-webcam", "--robot-base-port", "0", "--publish-truth",
                                      "--calibration-out", str(tmp_path / "calib.json"), *router.args),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=ENV)
    urls: dict[str, str] = {}
    deadline = time.monotonic() + 90
    seen = []
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        seen.append(line)
        m = re.match(r"(camera|robot)\s+(?:(\S+)\s+)?((?:tcp|socket)://\S+)", line)
        if m:
            urls[m.group(1) if m.group(1) == "camera" else f"robot {m.group(2)}"] = m.group(3)
        if line.startswith("running"):
            return proc, urls
    proc.kill()
    raise AssertionError(f"arena sim did not start: {''.join(seen)!r}")


@pytest.mark.slow
def test_every_message_recorded_from_real_services_validates(router, tmp_path):
    """`arena sim` (one robot on autopilot, truth published) + `arena edge` + `arena track` +
    `arena bridge`, recorded by `arena record` for a few seconds; every recorded message of every
    kind validates against the published schema of its kind."""
    from recorder.mcapio import read_run

    out = tmp_path / "run.mcap"
    procs: list[subprocess.Popen] = []

    def start(*args: str) -> subprocess.Popen:
        p = subprocess.Popen(arena_cmd(*args, *router.args), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                             text=True, env=ENV)
        procs.append(p)
        return p

    sim, urls = _sim(tmp_path, router)
    rec = None
    try:
        rec = subprocess.Popen(arena_cmd("record", str(out), "--name", "schemas", *router.args),
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=ENV)
        wait_for_line(rec, "recording arena/**", timeout=60)
        (robot, url), = [(k.split()[1], v) for k, v in urls.items() if k.startswith("robot")]
        start("edge", urls["camera"], "--camera", "cam0")
        start("track", "--camera", "cam0", "--calibration", str(tmp_path / "calib.json"), "--name", "cam0")
        start("bridge", "run", "--robot", f"{robot}={url}", "--name", "schemas")
        from arena.session import open_session
        seen: dict[str, int] = {}

        def on_sample(sample) -> None:
            kind = decode(bytes(sample.payload)).KIND
            seen[kind] = seen.get(kind, 0) + 1

        # enough of every kind (the recorder subscribed first, so it has them too)
        want = {"event_window": 60, "track": 30, "telemetry": 30, "groundtruth": 1, "status": 1}
        with open_session(router.settings("client")) as s:
            s.declare_subscriber("arena/**", on_sample)
            deadline = time.monotonic() + 120   # numba compiles in every process on a shared 2-core host
            while time.monotonic() < deadline and not all(seen.get(k, 0) >= n for k, n in want.items()):
                assert all(p.poll() is None for p in procs + [sim]), [p.stderr.read() for p in procs if p.poll()]
                time.sleep(0.1)
            assert all(seen.get(k, 0) >= n for k, n in want.items()), seen
        rec.send_signal(signal.SIGTERM)
        tail = rec.communicate(timeout=30)[0]
        assert rec.returncode == 0, tail
    finally:
        for p in procs + [sim] + ([rec] if rec else []):
            if p.poll() is None:
                p.terminate()
        for p in procs + [sim] + ([rec] if rec else []):
            try:
                p.communicate(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.communicate(timeout=5)

    validators = {kind: _validator(kind) for kind in MESSAGE_TYPES}
    counts: dict[str, int] = {}
    for m in read_run(out):
        d = msgpack.unpackb(m.payload, raw=False)
        errors = [e.message for e in validators[d["kind"]].iter_errors(json_view(d))]
        assert not errors, (m.key, errors)
        counts[d["kind"]] = counts.get(d["kind"], 0) + 1
    assert {"event_window", "track", "telemetry", "groundtruth", "status"} <= set(counts), counts
    assert counts["event_window"] > 50 and counts["track"] > 20 and counts["telemetry"] > 20, counts


# --------------------------------------------------------------------------------------------
# docs/codec.md: the worked example's bytes
# --------------------------------------------------------------------------------------------
def _doc_hex(name: str) -> bytes:
    """The hex block after the ``<!-- example: NAME -->`` marker in docs/codec.md (``#`` starts a comment)."""
    text = (REPO / "docs" / "codec.md").read_text(encoding="utf-8")
    m = re.search(rf"<!-- example: {re.escape(name)} -->\s*```[a-z]*\n(.*?)```", text, re.S)
    assert m, f"no example {name!r} in docs/codec.md"
    return bytes.fromhex("".join(line.split("#")[0] for line in m.group(1).splitlines()))


DOC_EVENTS = make_events([5, 6, 9, 300, 300, 7], [2, 2, 2, 2, 1, 40], [1, 1, 1, 1, 0, 1],
                         [1000, 1000, 1000, 1000, 1003, 998])


def test_the_documented_example_bytes_decode_to_the_documented_events():
    data = _doc_hex("planes-zstd/1")
    assert np.array_equal(codec.decode(codec.DEFAULT_CODEC, data, DOC_EVENTS.size), DOC_EVENTS)
    assert struct.unpack_from("<4sIqII", data) == (b"EVW1", 6, 1000, 2, 2)  # the header as documented
    # the streams inside the zstd frames are the documented planes (the frames' own bytes may
    # differ with another zstd version; the planes may not)
    import zstandard
    sizes = struct.unpack_from("<IIII", data, 24)
    pos, planes = 40, b""
    for size, raw in zip(sizes, (6, 6, 2, 2)):
        planes += zstandard.ZstdDecompressor().decompress(data[pos:pos + size], max_output_size=raw)
        pos += size
    assert pos == len(data)
    raw = _doc_hex("raw/1")
    assert raw == DOC_EVENTS.tobytes()
    assert np.array_equal(codec.decode(codec.RAW_CODEC, raw, DOC_EVENTS.size), DOC_EVENTS)
    documented = _doc_hex("planes-zstd/1 planes")  # the four streams before zstd, as the doc lists them
    assert documented == planes == _planes_reference(DOC_EVENTS)
    assert np.array_equal(codec.decode(codec.DEFAULT_CODEC, codec.encode(DOC_EVENTS), 6), DOC_EVENTS)


def _planes_reference(ev: np.ndarray) -> bytes:
    """The four uncompressed streams of planes-zstd/1 (control, low, dt escapes, dy escapes),
    written from the specification in docs/codec.md, not from arena/codec.py."""
    def varint(u: int) -> bytes:
        out = bytearray()
        while u >= 0x80:
            out.append(u & 0x7F | 0x80)
            u >>= 7
        out.append(u)
        return bytes(out)

    def zigzag(n: int) -> int:
        return (n << 1) ^ (n >> 63) if n < 0 else n << 1

    ctrl, low, dts, dys = bytearray(), bytearray(), bytearray(), bytearray()
    px = py = pp = 0
    pt = int(ev["t"][0])
    for i, (x, y, p, t) in enumerate(ev.tolist()):
        if i > 0 and t == pt and y == py and p == pp and x > px:
            gap = x - px - 1
            ctrl.append(gap >> 7)
            low.append(gap & 127)
        else:
            dtc = int(t != pt)
            if dtc:
                dts += varint(zigzag(t - pt) & (2**64 - 1))
            dyc = {0: 0, -1: 1}.get(y - py, 2)
            if dyc == 2:
                dys += varint(zigzag(y - py) & (2**64 - 1))
            ctrl.append(16 + ((p * 2 + dtc) * 3 + dyc) * 16 + (x >> 7))
            low.append(x & 127)
        px, py, pp, pt = x, y, p, t
    return bytes(ctrl + low + dts + dys)


def test_the_independent_plane_writer_matches_the_codec_on_random_windows():
    """The spec-derived reference above produces the planes the codec compresses (checked by
    decompressing the codec's own streams), so the document describes the real bytes."""
    import zstandard

    rng = np.random.default_rng(5)
    for trial in range(20):
        n = int(rng.integers(1, 400))
        ev = make_events(rng.integers(0, 2048, n), rng.integers(0, 2000, n), rng.integers(0, 2, n),
                         np.sort(rng.integers(-10**6, 10**6, n)) if trial % 2 else rng.integers(-10**9, 10**9, n))
        if trial % 3 == 0:  # runs: same t, y, p and increasing x
            ev["t"][:] = ev["t"][0]
            ev["y"][:] = 7
            ev["p"][:] = 1
            ev["x"] = np.sort(ev["x"])
        data = codec.encode(ev)
        magic, count, base, ndt, ndy, *sizes = struct.unpack_from("<4sIqIIIIII", data)
        pos, planes = 40, b""
        for size, raw in zip(sizes, (count, count, ndt, ndy)):
            planes += zstandard.ZstdDecompressor().decompress(data[pos:pos + size], max_output_size=raw) if raw else b""
            pos += size
        assert planes == _planes_reference(ev), trial


def test_the_documented_limits_are_the_codecs():
    """docs/codec.md states the decoder's limits as numbers: they must be the code's."""
    from arena import codec_names
    from arena.messages import DEFAULT_LIMITS

    text = " ".join((REPO / "docs" / "codec.md").read_text(encoding="utf-8").split())
    assert f"above {codec_names.MAX_WINDOW_EVENTS:,} events".replace(",", " ") in text
    assert f"n > {codec_names.MAX_EVENTS_PER_BYTE} · len(data)" in text
    assert f"longer than {DEFAULT_LIMITS.max_window_bytes // 2**20} MiB" in text
    assert struct.Struct("<4sIqIIIIII").size == 40 and codec._HEADER.format == "<4sIqIIIIII"
    assert codec._MAGIC == b"EVW1" and codec.CODECS == ("planes-zstd/1", "planes-zstd-ms/1", "raw/1")


def test_the_other_languages_example_reads_tracks_with_only_zenoh_and_msgpack(router, tmp_path):
    """docs/other-languages.md's Python program, as written there, against a real router: it
    prints the fleet and the tracks published, and skips other kinds and newer versions."""
    import ast
    import threading

    from arena.session import open_session

    text = (REPO / "docs" / "other-languages.md").read_text(encoding="utf-8")
    code = re.search(r"<!-- example: read-tracks -->\s*```python\n(.*?)```", text, re.S).group(1)
    imported = {a.name.split(".")[0] for node in ast.walk(ast.parse(code)) if isinstance(node, ast.Import)
                for a in node.names}
    imported |= {node.module.split(".")[0] for node in ast.walk(ast.parse(code)) if isinstance(node, ast.ImportFrom)}
    assert imported <= {"json", "sys", "threading", "msgpack", "zenoh"}, imported
    script = tmp_path / "read_tracks.py"
    script.write_text(code)
    stop = threading.Event()
    with open_session(router.settings("client")) as s:
        s.declare_queryable("arena/robots/*", lambda q: q.reply("arena/robots/7", Track(track_id=7, x=1.5).encode()))
        proc = subprocess.Popen([sys.executable, str(script), router.endpoint, "3"], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True, cwd=tmp_path,
                                env={k: v for k, v in ENV.items() if k != "PYTHONPATH"})

        def publish():
            i = 0
            while not stop.is_set() and i < 600:   # until the reader has had its 3 (bounded: 30 s)
                s.put("arena/robots/zumo1", msgpack.packb({"v": 2, "kind": "track", "x": 9.0}))
                s.put("arena/robots/zumo1", Status(role="x", name="y").encode())
                s.put("arena/robots/zumo1", Track(track_id=1, robot="zumo1", stamp_us=i, x=0.5, y=0.25,
                                                  yaw=0.1).encode())
                i += 1
                stop.wait(0.05)

        t = threading.Thread(target=publish, daemon=True)
        t.start()
        try:
            out, err = proc.communicate(timeout=60)
        finally:
            stop.set()
            t.join(timeout=5)
            if proc.poll() is None:
                proc.kill()
    assert proc.returncode == 0, err
    lines = out.splitlines()
    assert lines[0] == "fleet arena/robots/7 robot=None x=1.500 m y=0.000 m yaw=? rad t=0 us confirmed", lines
    tracks = lines[1:]
    assert len(tracks) == 3 and all(ln.startswith("arena/robots/zumo1 robot=zumo1 x=0.500 m y=0.250 m yaw=+0.10")
                                    for ln in tracks), lines


def test_register_adds_the_arena_schemas_command(tmp_path, capsys):
    """What the `arena.commands` entry point `schemas = "arena.schemas:register"` adds."""
    import argparse

    from arena.schemas import register

    p = argparse.ArgumentParser(prog="arena")
    register(p.add_subparsers(dest="command"))
    args = p.parse_args(["schemas", "--out", str(tmp_path / "s")])
    assert args.func(args) == 0 and "wrote 8 schemas" in capsys.readouterr().out
    args = p.parse_args(["schemas", "--out", str(tmp_path / "s"), "--check"])
    assert args.func(args) == 0

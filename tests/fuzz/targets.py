"""Fuzz targets: a valid seed input per decoder, a mutator that knows the hostile values decoders
trip on (sizes of 2^31, 2^40, -1, 65636, polarity 2, ...), and the contract each decoder must
keep on any input: raise only its declared error type, and return only valid values.

* ``messages``: :func:`arena.messages.decode` raises only ``MessageError``;
* ``codec-*``: :func:`arena.codec.decode` raises only ``CodecError``, returns ``count`` events;
* ``file-*``: :func:`arena.formats.read_events` raises only ``FormatError`` and returns events
  inside a 1..65535 px sensor with polarity 0/1;
* ``robot-protocol``: the serial link's :class:`arena.robot_protocol.StreamDecoder` never raises
  (bad frames are counted), returns the same frames however the bytes are chunked, only frames
  whose packet :func:`~arena.robot_protocol.decode_packet` accepts (which raises only
  ``ProtocolError``), with every field inside its physical range; the bridge's frame handler
  then publishes telemetry that a receiver decodes;
* ``mission``: a ``MissionCommand`` query payload through the bridge's own path (decode, the
  pure checks, the layout, the geofence, the controller) raises only ``MessageError`` /
  ``CommandError`` and lays out at most the phases and the path length its limits allow;
* ``tracker-state``: :func:`tracker.service.load_state` raises only ``ValueError``; a state it
  accepts is restored by the fleet tracker (ValueError at most) and tracked on with finite poses;
* ``calibration-json``: :func:`tracker.calibration.load_calibration` raises only ``CalibrationError``;
* ``lab-config-toml`` / ``lab-config-tree``: :func:`arena.config.load_lab_config` (bytes) and
  :func:`arena.config.parse_lab_config` (a parsed document) raise only ``ConfigError``.

The structured targets (JSON, msgpack, TOML documents) mutate the parsed document
(:func:`tree_mutations`: hostile values such as null, NaN, Infinity, 2**64, 1e308, wrong types,
deleted and added keys) and then, sometimes, its bytes (:func:`mutations`).

Memory and time are bounded by the runner (:mod:`tests.fuzz.runner`).
"""

from __future__ import annotations

import copy
import json
import math
import struct
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import msgpack
import numpy as np
from hypothesis import strategies as st

#: integers that size fields, counts and coordinates go wrong with
HOSTILE_INTS = (0, 1, 2, 3, -1, -2, 0x7F, 0x80, 0xFF, 0x7FFF, 0x8000, 0xFFFF, 65535, 65536, 65636, 2047, 2048,
                2**31 - 1, 2**31, 2**32 - 1, 2**40, 2**62, 2**63 - 1, -2**31, -2**63)
#: text that CSV lines and npy headers go wrong with
HOSTILE_TEXT = (b"65636", b"-5", b"2", b"3", b"-1", b"99999999999999999999", b"1e9", b"nan", b"(1099511627776,)",
                b"(0,)", b"((", b"'<U5'", b"'O'", b"\n", b",", b",,", b"\x00", b"True", b"-0", b"0x10",
                b"4_80", b"+640", b"\xff\xff\xff\xff")    # int() takes "4_80"; 0xFFFF.. words: no known type


@dataclass
class Target:
    name: str
    seed: Callable[[], bytes]          # a valid input (built once)
    check: Callable[[bytes], None]     # raises AssertionError (or anything undeclared) on a contract break
    #: (draw, seed) -> an input; default :func:`mutations` of the seed's bytes
    generate: Callable[[Callable, bytes], bytes] | None = None

    def make_input(self, draw, data: bytes) -> bytes:
        return (self.generate or mutations)(draw, data)


def mutations(draw, data: bytes) -> bytes:
    """Apply 1-4 random mutations (hypothesis-drawn, so failures shrink) to ``data``."""
    buf = bytearray(data)
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(["flip", "int", "text", "cut", "insert", "dup"]))
        i = draw(st.integers(0, max(0, len(buf) - 1)))
        if op == "flip" and buf:
            buf[i] ^= 1 << draw(st.integers(0, 7))
        elif op == "int":
            width, fmt = draw(st.sampled_from([(1, "<b"), (2, "<h"), (4, "<i"), (8, "<q")]))
            v = draw(st.sampled_from(HOSTILE_INTS))
            lo, hi = -(1 << (8 * width - 1)), 1 << (8 * width - 1)
            v = (v - lo) % (hi - lo) + lo        # wrap into the field's width
            if i + width <= len(buf):
                struct.pack_into(fmt, buf, i, v)
        elif op == "text":
            tok = draw(st.sampled_from(HOSTILE_TEXT))
            buf[i:i + draw(st.integers(0, len(tok)))] = tok
        elif op == "cut" and buf:
            buf = buf[:i] if draw(st.booleans()) else buf[:i] + buf[i + draw(st.integers(1, 64)):]
        elif op == "insert":
            buf[i:i] = draw(st.binary(min_size=1, max_size=16))
        elif op == "dup" and buf:
            j = draw(st.integers(i, min(len(buf), i + 256)))
            buf[j:j] = buf[i:j]
    return bytes(buf)


def _events(n: int = 300, seed: int = 0, width: int = 640, height: int = 480):
    from arena.events import make_events

    rng = np.random.default_rng(seed)
    t = 1_000_000 + np.cumsum(rng.integers(0, 40, n))
    return make_events(rng.integers(0, width, n), rng.integers(0, height, n), rng.integers(0, 2, n), t)


# --- messages and the codec ---

def _message_seed() -> bytes:
    from arena.codec import encode
    from arena.messages import EventWindow

    ev = _events(50)
    return EventWindow(camera="cam0", seq=7, t_start_us=1_000_000, t_end_us=1_010_000, width=640, height=480,
                       count=ev.size, codec="planes-zstd/1", data=encode(ev), dropped=1).encode()


def _check_message(data: bytes) -> None:
    from arena import messages as m
    from arena.codec import CodecError, decode

    try:
        msg = m.decode(data)
    except m.MessageError:
        return
    assert isinstance(msg, m.Message)
    if isinstance(msg, m.EventWindow):          # as the tracker does with it
        try:
            ev = decode(msg.codec, msg.data, msg.count)
        except CodecError:
            return
        assert ev.size == msg.count


def _codec_seed(codec: str) -> Callable[[], bytes]:
    def seed() -> bytes:
        from arena.codec import encode

        ev = _events(300)
        return struct.pack("<I", ev.size) + encode(ev, codec)
    return seed


def _codec_check(codec: str) -> Callable[[bytes], None]:
    def check(data: bytes) -> None:
        from arena.codec import CodecError, decode

        if len(data) < 4:
            return
        count = struct.unpack_from("<I", data)[0]
        try:
            ev = decode(codec, data[4:], count)
        except CodecError:
            return
        assert ev.size == count
    return check


def _zero_frame(n: int) -> bytes:
    """A zstd frame of ``n`` zero bytes that declares no content size (zstd cannot then size its
    output from the frame: the decoder must bound it)."""
    import zstandard

    return zstandard.ZstdCompressor(level=1, write_content_size=False).compress(b"\0" * n) if n else b""


def _codec_generate(draw, data: bytes) -> bytes:
    """Mutations of the seed, or (one time in six) a decompression bomb: zero-filled streams that
    declare no content size behind a header whose count (up to 2 M events, inside 2048 per byte
    once padded) and escape lengths (up to 10 n and 3 n, or beyond) are hostile: windows over the
    codec's one-shot size are decoded in chunks."""
    if draw(st.integers(0, 5)):
        return mutations(draw, data)
    n = draw(st.sampled_from([1, 300, 4096, 100_000, 1_000_000, 2_000_000]))
    ndt = draw(st.sampled_from([0, n, 10 * n, 10 * n + 1, 2**31]))
    ndy = draw(st.sampled_from([0, n, 3 * n, 3 * n + 1]))
    ctrl = draw(st.sampled_from([b"\x10", b"\x30", b"\x00", b"\x50"]))     # plain, dt escape, run, dy escape
    import zstandard

    streams = [zstandard.ZstdCompressor(level=1, write_content_size=False).compress(ctrl * n), _zero_frame(n),
               _zero_frame(min(ndt, 20 * n)), _zero_frame(min(ndy, 4 * n))]
    total = 36 + sum(map(len, streams))
    if draw(st.booleans()) and n > 2048 * total:
        streams[3] += b"\0" * (n // 2048 + 1 - total)
    head = struct.pack("<4sIqIIIIII", b"EVW1", n, 0, ndt, ndy, *(len(x) for x in streams))
    out = struct.pack("<I", n) + head + b"".join(streams)
    return mutations(draw, out) if draw(st.integers(0, 3)) == 0 else out


# --- files ---

def _file_seed(ext: str, **opts) -> Callable[[], bytes]:
    def seed() -> bytes:
        from arena.formats import open_writer

        with tempfile.TemporaryDirectory() as d:
            path = Path(d) / f"seed{ext}"
            ev = _events(300)
            if opts.get("evt") == "2.1":
                from arena.formats.evt2 import encode_evt21

                path.write_bytes(b"% evt 2.1\n% format EVT21;height=480;width=640\n% end\n" + encode_evt21(ev))
            else:
                with open_writer(path, 640, 480, **opts) as w:
                    w.write(ev)
            return path.read_bytes()
    return seed


def _file_check(ext: str) -> Callable[[bytes], None]:
    def check(data: bytes) -> None:
        from arena.formats import FormatError, read_events
        from arena.formats.base import SkippedData

        with tempfile.TemporaryDirectory() as d:
            path = Path(d) / f"in{ext}"
            path.write_bytes(data)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", SkippedData)
                try:
                    ev, w, h = read_events(path)
                except FormatError:
                    return
        assert 1 <= w <= 65535 and 1 <= h <= 65535, (w, h)
        if ev.size:
            assert int(ev["x"].max()) < w and int(ev["y"].max()) < h
            assert int(ev["p"].max()) <= 1
    return check


def _npz_generate(draw, data: bytes) -> bytes:
    """Mutations of the seed, or (one time in six) an npz decompression bomb: columns of one
    repeated value (deflate ~1030:1) of up to 4 M events, of hostile dtypes, or a structured
    ``events`` array, with or without a sensor size."""
    if draw(st.integers(0, 5)):
        return mutations(draw, data)
    import io
    import zipfile

    n = draw(st.sampled_from([0, 1, 1000, 1_000_000, 4_000_000]))
    dtype = draw(st.sampled_from(["u1", "<u2", "<i8", "<f8", "|b1", ">i4"]))
    fill = draw(st.sampled_from([0, 1, 2, 65636, -1]))
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED, compresslevel=draw(st.sampled_from([1, 9]))) as zf:
        def put(name, arr):
            b = io.BytesIO()
            np.save(b, arr)
            zf.writestr(name + ".npy", b.getvalue())
        with np.errstate(over="ignore"):
            if draw(st.booleans()):
                for name in "xypt":
                    put(name, np.full(n, fill).astype(dtype))
            else:
                put("events", np.zeros(n, [("x", dtype), ("y", "<u2"), ("p", "u1"), ("t", "<i8")]))
        if draw(st.booleans()):
            put("width", np.array(draw(st.sampled_from([640, 0, -1, 2**40]))))
            put("height", np.array(480))
    out = buf.getvalue()
    return mutations(draw, out) if draw(st.integers(0, 3)) == 0 else out


# --- structured documents (JSON, msgpack, TOML) ---

#: values that validators of parsed documents go wrong with (None is JSON's null; NaN and the
#: infinities are what Python's json writes and reads as NaN / Infinity)
HOSTILE_VALUES = (None, True, False, 0, 1, -1, 2, 0.5, -0.0, 1e-320, 2**31, 2**53, 2**53 + 1, 2**63, 2**64 + 1,
                  -2**63 - 1, 10**30, -10**30, 10**400, 1e308, -1e308, math.inf, -math.inf, math.nan, "", "x",
                  "0", "nan", "cam0", "zumo1", "a" * 300, "../../etc/passwd", "bad name", "\u00e9\u0000",
                  [], [0], [1, 2], [1.0, 2.0, 3.0], [[1, 2]], ["x", None], {}, {"a": 1}, {"v": 1})


def _paths(obj, prefix=(), out=None, limit=400):
    """Paths (tuples of keys/indices) of every node of ``obj`` (at most ``limit``)."""
    out = [] if out is None else out
    if len(out) >= limit:
        return out
    out.append(prefix)
    if isinstance(obj, dict):
        for k, v in obj.items():
            _paths(v, prefix + (k,), out, limit)
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            _paths(v, prefix + (i,), out, limit)
    return out


def _get(obj, path):
    for k in path:
        obj = obj[k]
    return obj


def tree_mutations(draw, doc, values=HOSTILE_VALUES, keys=()):
    """Apply 1-4 random mutations (hypothesis-drawn) to a copy of the parsed document ``doc``:
    replace a node by a hostile value (or a random number or string), delete a key or an item,
    add a key (of ``keys`` or a random one), duplicate an item, nest a node in a list or a map."""
    doc = copy.deepcopy(doc)
    for _ in range(draw(st.integers(1, 4))):
        paths = _paths(doc)
        path = paths[draw(st.integers(0, len(paths) - 1))]
        op = draw(st.sampled_from(["value", "value", "number", "text", "delete", "add", "dup", "wrap"]))
        if op in ("value", "number", "text"):
            if op == "value":
                new = draw(st.sampled_from(values))
            elif op == "number":
                new = draw(st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                                     st.integers(-2**70, 2**70)))
            else:
                new = draw(st.text(max_size=20))
            if not path:
                doc = copy.deepcopy(new)
            else:
                _get(doc, path[:-1])[path[-1]] = copy.deepcopy(new)
            continue
        node = _get(doc, path)
        if op == "delete" and path:
            parent = _get(doc, path[:-1])
            del parent[path[-1]]
        elif op == "add" and isinstance(node, dict):
            key = draw(st.sampled_from(keys)) if keys and draw(st.booleans()) else draw(st.text(max_size=8))
            node[key] = copy.deepcopy(draw(st.sampled_from(values)))
        elif op == "add" and isinstance(node, list):
            node.insert(draw(st.integers(0, len(node))), copy.deepcopy(draw(st.sampled_from(values))))
        elif op == "dup" and isinstance(node, list) and node:
            k = draw(st.integers(0, len(node) - 1))
            node.extend(copy.deepcopy(node[k]) for _ in range(draw(st.sampled_from([1, 2, 300, 1100]))))
        elif op == "wrap" and path:
            parent = _get(doc, path[:-1])
            parent[path[-1]] = [node] if draw(st.booleans()) else {"x": node}
    return doc


def _json_generate(keys=()):
    def generate(draw, data: bytes) -> bytes:
        """Mutate the parsed JSON document, write it back (NaN and Infinity as Python writes them),
        then, one time in four, mutate the bytes too."""
        doc = tree_mutations(draw, json.loads(data), keys=keys)
        out = json.dumps(doc).encode()
        return mutations(draw, out) if draw(st.integers(0, 3)) == 0 else out
    return generate


# --- the robot serial protocol ---

def _protocol_messages():
    from arena import robot_protocol as P

    return [
        P.Hello(), P.HelloReply(3, 50, 1807, 300, "zumo1"), P.SetMotors(-400, 400), P.SetLed(255, 0, 7), P.Stop(),
        P.Telemetry(-5, 2**31 - 1, (1, -2, 16384), (-32768, 0, 32767), (100, 200, -300), 4800, 400, -400, 3),
        P.Telemetry(1807, 1805, (0, 0, 16384), (0, 0, 10), (0, 0, 0), 5200, 200, 200, 0),
        P.Ping(2**32 - 1), P.Pong(7), P.Error(P.ERR_BAD_VALUE, P.SET_MOTORS, "power out of range"),
    ]


def _protocol_seed() -> bytes:
    """Unframed packets without their CRC, each behind its length byte: the check computes the
    CRC and the COBS framing of each, so mutations reach the body checks and the clamping (a
    mutated framed stream almost never passes the CRC); the raw bytes are fed as a stream too."""
    from arena import robot_protocol as P

    out = bytearray()
    for k, msg in enumerate(_protocol_messages()):
        packet = P.encode_packet(msg, seq=65530 + 3 * k, time_us=2**32 - 20_000 + 10_000 * k)[:-2]
        out += bytes([len(packet)]) + packet
    return bytes(out)


def _protocol_records(data: bytes) -> list[bytes]:
    records, i = [], 0
    while i < len(data):
        n = data[i]
        records.append(data[i + 1:i + 1 + n])
        i += 1 + n
    return records


_CHUNKINGS = (1, 7, 64)


_SCRATCH: tempfile.TemporaryDirectory | None = None


def _scratch(name: str) -> Path:
    """A path in this process's scratch directory (made once: a directory per input costs more
    than the structured checks themselves)."""
    global _SCRATCH
    if _SCRATCH is None:
        _SCRATCH = tempfile.TemporaryDirectory(prefix="arena-fuzz-")
    path = Path(_SCRATCH.name) / name
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


def _feed(stream: bytes, step: int):
    from arena import robot_protocol as P

    dec = P.StreamDecoder()
    frames = []
    for i in range(0, len(stream), step):
        frames += dec.feed(stream[i:i + step])
    return frames, dec


def _check_frames(frames) -> None:
    from arena import robot_protocol as P

    for fr in frames:
        assert type(fr.msg) in P.MESSAGE_TYPES.values(), fr
        assert 0 <= fr.seq <= 0xFFFF and 0 <= fr.time_us <= 0xFFFFFFFF and fr.version == P.PROTOCOL_VERSION, fr
        for name, lo, hi in P.PHYSICAL_RANGES.get(type(fr.msg), ()):
            assert lo <= getattr(fr.msg, name) <= hi, (name, fr)
        # what the bridge sends back or logs re-encodes: no field is outside its wire range
        again = P.decode_packet(P.encode_packet(fr.msg, fr.seq, fr.time_us))
        assert again.clamped == 0, again


def _bridge_handle():
    """A fresh :class:`robot_bridge.core.RobotHandle` (per input, so that a finding replays)
    that is never started (no serial port, no threads); its ``publish`` decodes what it is given,
    as a receiver of ``arena/telemetry`` does."""
    from arena import messages as m
    from robot_bridge.core import BridgeOptions, RobotHandle, RobotSetup

    def publish(robot, msg):
        got = m.decode(msg.encode())        # MessageError here: the bridge publishes garbage
        assert isinstance(got, m.Telemetry)

    return RobotHandle(RobotSetup("zumo1", "loop://"), BridgeOptions(), publish=publish)


def _check_protocol(data: bytes) -> None:
    from arena import robot_protocol as P

    # 1. the bytes as they come off the serial line: never an exception, chunking does not matter
    ref = None
    for step in _CHUNKINGS:
        frames, dec = _feed(data, step)
        s = dec.stats
        assert s.frames == len(frames) and s.bytes_in == len(data), s
        assert len(dec._buf) <= dec.max_packet + 1, len(dec._buf)
        assert s.clamped == sum(fr.clamped for fr in frames), s
        if ref is None:
            ref = frames
            _check_frames(frames)
        assert frames == ref, (step, frames, ref)
    # 2. each record with a good CRC and framing: the decoder returns exactly the packets
    #    decode_packet accepts (it raises only ProtocolError) that fit in MAX_PACKET
    stream, expected = bytearray(b"\x00"), []
    for rec in _protocol_records(data):
        packet = rec + P.crc16(rec).to_bytes(2, "little")
        try:
            fr = P.decode_packet(packet)
        except P.ProtocolError:
            fr = None
        framed = P.cobs_encode(packet)
        assert P.cobs_decode(framed) == packet
        if fr is not None and len(framed) <= P.MAX_PACKET + 1:
            expected.append(fr)
        stream += framed + b"\x00"
    for step in (3,):
        frames, dec = _feed(bytes(stream), step)
        assert frames == expected, (step, frames, expected)
    _check_frames(expected)
    # 3. the bridge's handler of the frames (odometry, speeds, the telemetry it publishes)
    h = _bridge_handle()
    for fr in ref + expected:
        h._on_frame(fr, 1_700_000_000_000_000_000, 0)


# --- mission commands ---

_PARAM_KEYS = ("radius_m", "side_m", "length_m", "direction", "laps", "points", "pause_s", "pause_every_m",
               "start_pose", "speed", "power")
_MISSION_VALUES = HOSTILE_VALUES + ("ccw", "cw", "left", "right", "circle", "square", "figure8", "back_and_forth",
                                    "waypoints", "paper", "closed", 0.05, 0.3, 0.6, 1.8, 2.5, 5.0, 100, 101, 1e9,
                                    1e-6, 0.049, 60.0, 60.1, 500.0, [0.5, 0.5, 0.0], [[0.2, 0.2], [1.5, 1.5]])


def _mission_docs() -> list[dict]:
    from arena.messages import MissionCommand

    cmds = [
        MissionCommand(mission="circle", params={"radius_m": 0.3, "direction": "cw", "laps": 2}, power=0.5),
        MissionCommand(mission="square", params={"side_m": 0.6, "laps": 3, "pause_s": 0.5, "pause_every_m": 0.1},
                       speed_mps=0.2),
        MissionCommand(mission="figure8", params={"radius_m": 0.25, "laps": 1, "start_pose": [0.9, 0.9, 0.0]},
                       control="closed"),
        MissionCommand(mission="back_and_forth", params={"length_m": 0.6, "laps": 4, "pause_s": 1.0},
                       start_ns=1, operator="fuzz"),
        MissionCommand(mission="waypoints", params={"points": [[0.3, 0.3], [1.5, 0.3], [1.5, 1.5], [0.3, 0.3]],
                                                    "start_pose": [0.2, 0.2, 1.0]}),
    ]
    return [msgpack.unpackb(c.encode()) for c in cmds]


_MISSION_DOCS: list | None = None


def _mission_seed() -> bytes:
    return msgpack.packb(_mission_docs()[1], use_bin_type=True)


def _mission_generate(draw, data: bytes) -> bytes:
    """A MissionCommand payload: one of the valid commands with its parsed map mutated (mostly its
    ``params``: hostile values, wrong types, unknown and missing keys, long waypoint lists), or a
    random one; then, one time in eight, its bytes mutated too."""
    global _MISSION_DOCS
    if _MISSION_DOCS is None:
        _MISSION_DOCS = _mission_docs()
    if draw(st.integers(0, 3)) == 0:           # a fresh, random command
        num = st.one_of(st.sampled_from(_MISSION_VALUES), st.floats(-10, 10), st.integers(-5, 300),
                        st.floats(allow_nan=True, allow_infinity=True))
        pts = st.lists(st.lists(num, min_size=0, max_size=3), max_size=300)
        params = draw(st.dictionaries(st.sampled_from(_PARAM_KEYS), st.one_of(num, pts), max_size=6))
        doc = {"v": 1, "kind": "mission", "mission": draw(st.sampled_from(("circle", "square", "figure8",
                                                                           "back_and_forth", "waypoints", "spiral"))),
               "params": params, "power": draw(st.one_of(st.none(), st.none(), num)),
               "speed_mps": draw(st.one_of(st.none(), st.none(), num)),
               "control": draw(st.sampled_from(("paper", "closed", "open")))}
    else:
        doc = copy.deepcopy(_MISSION_DOCS[draw(st.integers(0, len(_MISSION_DOCS) - 1))])
        if draw(st.integers(0, 3)):            # mostly the parameters: the message layer has its own target
            doc["params"] = tree_mutations(draw, doc["params"], values=_MISSION_VALUES, keys=_PARAM_KEYS)
        else:
            doc = tree_mutations(draw, doc, values=_MISSION_VALUES, keys=_PARAM_KEYS)
    try:
        out = msgpack.packb(doc, use_bin_type=True)
    except (OverflowError, ValueError, TypeError):   # an int beyond 64 bits has no msgpack form
        out = data
    return mutations(draw, out) if draw(st.integers(0, 7)) == 0 else out


_MISSION_HANDLE_CLS = None


def _mission_handle():
    """A fresh (per input: its pose estimator keeps a given start pose), never-started RobotHandle
    whose link counts as up and whose mission log writes nothing: :meth:`RobotHandle.start_mission`
    then runs all of its pure work on the fuzzed command."""
    global _MISSION_HANDLE_CLS
    import robot_bridge.core as svc

    if _MISSION_HANDLE_CLS is None:
        class NullLog:
            def __init__(self, *a, manifest=None, **kw):
                json.dumps(manifest)                # the manifest the real log writes must serialise

            def close(self, *a, **kw):
                pass

        class Handle(svc.RobotHandle):
            def _refuse_if_not_ready(self):
                pass

        svc.MissionLog = NullLog     # this fuzz process only
        _MISSION_HANDLE_CLS = Handle
    return _MISSION_HANDLE_CLS(svc.RobotSetup("zumo1", "loop://"), svc.BridgeOptions())


def _check_mission(data: bytes) -> None:
    from arena.messages import MessageError, MissionCommand
    from robot_bridge.missions import check_mission
    from robot_bridge.core import CommandError

    try:
        cmd = MissionCommand.decode(data)
    except MessageError:
        return
    h = _mission_handle()
    try:
        h.check(cmd)                               # what the query callback runs first
    except CommandError:
        return
    try:
        detail = h.start_mission(cmd)              # what the robot's worker then runs
    except CommandError:
        return
    runner = h.runner
    lim = h.limits
    mission = runner.mission
    params = {k: v for k, v in cmd.params.items() if k != "start_pose"}
    size = check_mission(cmd.mission, params, lim, mission.start)
    assert 1 <= len(mission.segments) <= min(size.segments, lim.max_segments), (len(mission.segments), size)
    assert mission.length_m <= lim.max_path_m * (1 + 1e-9), mission.length_m
    assert abs(mission.length_m - size.length_m) <= 1e-6 * max(1.0, size.length_m), (mission.length_m, size)
    for seg in mission.segments:
        vals = (*seg.start, seg.length_m, seg.curvature, seg.turn_rad, seg.duration_s)
        assert all(math.isfinite(v) for v in vals), seg
        assert seg.length_m >= 0 and 0 <= seg.duration_s <= lim.max_pause_s, seg
    assert all(math.isfinite(v) for v in mission.bounds())
    assert 0 < detail["speed_mps"] <= h.geometry.max_speed_mps + 1e-12, detail


# --- tracker state files ---

def _state_seed() -> bytes:
    tracks = [{"id": 3, "robot": "zumo1", "x": 0.5, "y": 0.6, "vx": 0.1, "vy": -0.05, "yaw": 1.2, "u": 320.5,
               "v": 240.0, "t_us": 12_000_000, "last_seen_us": 11_990_000, "hits": 40},
              {"id": 7, "robot": None, "x": 1.5, "y": 0.2, "vx": 0.0, "vy": 0.0, "yaw": None, "u": None, "v": None,
               "t_us": 12_000_000, "last_seen_us": 11_000_000, "hits": 5},
              {"id": 9, "robot": "zumo2", "x": 0.05, "y": 1.7, "vx": 0.3, "vy": 0.3, "yaw": -3.1, "u": 10.0,
               "v": 470.0, "t_us": 12_010_000, "last_seen_us": 12_010_000, "hits": 2}]
    return json.dumps({"camera": "cam0", "written_s": STATE_NOW_S - 5.0,
                       "fleet": {"v": 1, "next_id": 10, "tracks": tracks}}).encode()


#: the wall clock the state target loads at (the seed was written 5 s before)
STATE_NOW_S = 1_700_000_000.0
_STATE_KEYS = ("camera", "written_s", "fleet", "v", "next_id", "tracks", "id", "robot", "x", "y", "vx", "vy", "yaw",
               "u", "v", "t_us", "last_seen_us", "hits")


def _check_state(data: bytes) -> None:
    from tracker.fleet import FleetTracker
    from tracker.objects import Observation
    from tracker.service import load_state

    path = _scratch("state/tracker-cam0.json")
    path.write_bytes(data)
    try:
        fleet, _why = load_state(path, "cam0", max_age_s=3600.0, now_s=STATE_NOW_S)
    except ValueError:
        return
    if fleet is None:
        return
    ft = FleetTracker()
    try:
        ids = ft.restore(fleet)
    except ValueError:
        return
    assert ids == sorted(set(ids)) and len(ids) == len(fleet["tracks"]), ids
    # the tracker goes on from the restored fleet: predictions and updates stay finite
    t = max([tr.t_us for tr in ft.tracks], default=0) + 10_000
    assert np.isfinite(ft.predictions(t)).all()
    ob = Observation(x=0.9, y=0.9, t_us=t)
    for k, obs in enumerate(([], [ob])):
        for tr in ft.update(obs, t + k * 10_000):
            assert math.isfinite(tr.x) and math.isfinite(tr.y), tr


# --- calibration and the lab config ---

def _calibration_seed() -> bytes:
    s = 1.83
    arena = [[0, 0], [s, 0], [s, s], [0, s], [0.61, 0.61], [1.22, 1.22]]
    pixel = [[113.6, 465.2], [545.2, 446.4], [523.1, 14.9], [98.0, 33.5], [251.5, 313.6], [388.0, 163.5]]
    return json.dumps({"image_size": [640, 480], "height_m": 0.05, "camera_height_m": 2.4, "nadir_m": [0.9, 0.9],
                       "points": [{"pixel": p, "arena_m": a} for p, a in zip(pixel, arena)]}).encode()


def _check_calibration(data: bytes) -> None:
    from tracker.calibration import CalibrationError, load_calibration

    path = _scratch("calibration/cam0.calib.json")
    path.write_bytes(data)
    try:
        cal = load_calibration(path)
    except CalibrationError:
        return
    assert np.isfinite(cal.H).all(), cal.H
    assert cal.image_size[0] > 0 and cal.image_size[1] > 0, cal.image_size


def _lab_seed() -> bytes:
    from tests.fuzz.harness import REPO

    return (REPO / "deploy" / "lab.example.toml").read_bytes()


HOSTILE_TOML = (b" = nan", b" = inf", b" = -inf", b" = 1e999", b" = -1", b" = 0", b" = 99999999999999999999",
                b" = []", b" = {}", b' = ""', b" = true", b"\n[[robots]]\n", b"\n[[cameras]]\n", b"\n[arena]\n",
                b"[[", b"]]", b'"""', b"'", b"\\u0000", b"\n", b"=", b"#", b"1979-05-27T07:32:00Z")


def _lab_bytes_generate(draw, data: bytes) -> bytes:
    buf = bytearray(mutations(draw, data))
    for _ in range(draw(st.integers(0, 2))):
        i = draw(st.integers(0, len(buf)))
        tok = draw(st.sampled_from(HOSTILE_TOML))
        buf[i:i + draw(st.integers(0, len(tok)))] = tok
    return bytes(buf)


def _check_lab_bytes(data: bytes) -> None:
    from arena.config import ConfigError, load_lab_config

    path = _scratch("lab-toml/lab.toml")
    path.write_bytes(data)
    try:
        load_lab_config(path)
    except ConfigError:
        return


def _lab_tree_seed() -> bytes:
    import tomllib

    return json.dumps(tomllib.loads(_lab_seed().decode())).encode()


_LAB_KEYS = ("arena", "zenoh", "cameras", "webcam", "robots", "services", "name", "size_m", "calibration",
             "serial_url", "marker_id", "hsv_range", "color", "width", "height", "edge", "tracker", "bridge",
             "track_width_m", "counts_per_rev", "mode", "connect", "listen")
_LAB_VALUES = tuple(v for v in HOSTILE_VALUES if v is not None)    # TOML has no null


def _lab_tree_generate(draw, data: bytes) -> bytes:
    doc = tree_mutations(draw, json.loads(data), values=_LAB_VALUES, keys=_LAB_KEYS)
    return json.dumps(doc).encode()


def _check_lab_tree(data: bytes) -> None:
    from arena.config import ConfigError, parse_lab_config

    doc = json.loads(data)
    if not isinstance(doc, dict) or _has_null(doc):    # a TOML document is a table, with no nulls
        return
    try:
        parse_lab_config(doc, base_dir=_scratch("lab-tree/none").parent)
    except ConfigError:
        return


def _has_null(obj) -> bool:
    if obj is None:
        return True
    if isinstance(obj, dict):
        return any(_has_null(v) for v in obj.values())
    if isinstance(obj, list):
        return any(_has_null(v) for v in obj)
    return False


TARGETS: dict[str, Target] = {t.name: t for t in [
    Target("messages", _message_seed, _check_message),
    Target("codec-planes", _codec_seed("planes-zstd/1"), _codec_check("planes-zstd/1"), _codec_generate),
    Target("codec-lossy", _codec_seed("planes-zstd-ms/1"), _codec_check("planes-zstd-ms/1"), _codec_generate),
    Target("codec-raw", _codec_seed("raw/1"), _codec_check("raw/1")),
    Target("file-evt3", _file_seed(".raw", evt=3), _file_check(".raw")),
    Target("file-evt2", _file_seed(".raw", evt=2), _file_check(".raw")),
    Target("file-evt21", _file_seed(".raw", evt="2.1"), _file_check(".raw")),
    Target("file-dat", _file_seed(".dat"), _file_check(".dat")),
    Target("file-aedat4-lz4", _file_seed(".aedat4", compression="lz4", packet_events=64), _file_check(".aedat4")),
    Target("file-aedat4-zstd", _file_seed(".aedat4", compression="zstd", packet_events=64), _file_check(".aedat4")),
    Target("file-aedat4-none", _file_seed(".aedat4", compression="none", packet_events=64), _file_check(".aedat4")),
    Target("file-csv", _file_seed(".csv"), _file_check(".csv")),
    Target("file-npy", _file_seed(".npy"), _file_check(".npy")),
    Target("file-npz", _file_seed(".npz"), _file_check(".npz"), _npz_generate),
    Target("robot-protocol", _protocol_seed, _check_protocol),
    Target("mission", _mission_seed, _check_mission, _mission_generate),
    Target("tracker-state", _state_seed, _check_state, _json_generate(_STATE_KEYS)),
    Target("calibration-json", _calibration_seed, _check_calibration, _json_generate(("image_size", "points", "pixel",
                                                                                      "arena_m", "height_m",
                                                                                      "camera_height_m", "nadir_m"))),
    Target("lab-config-toml", _lab_seed, _check_lab_bytes, _lab_bytes_generate),
    Target("lab-config-tree", _lab_tree_seed, _check_lab_tree, _lab_tree_generate),
]}

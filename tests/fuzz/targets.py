"""Fuzz targets: a valid seed input per decoder, a mutator that knows the hostile values decoders
trip on (sizes of 2^31, 2^40, -1, 65636, polarity 2, ...), and the contract each decoder must
keep on any input: raise only its declared error type, and return only valid values.

* ``messages``: :func:`arena.messages.decode` raises only ``MessageError``;
* ``codec-*``: :func:`arena.codec.decode` raises only ``CodecError``, returns ``count`` events;
* ``file-*``: :func:`arena.formats.read_events` raises only ``FormatError`` and returns events
  inside a 1..65535 px sensor with polarity 0/1.

Memory and time are bounded by the runner (:mod:`tests.fuzz.runner`).
"""

from __future__ import annotations

import struct
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
from hypothesis import strategies as st

#: integers that size fields, counts and coordinates go wrong with
HOSTILE_INTS = (0, 1, 2, 3, -1, -2, 0x7F, 0x80, 0xFF, 0x7FFF, 0x8000, 0xFFFF, 65535, 65536, 65636, 2047, 2048,
                2**31 - 1, 2**31, 2**32 - 1, 2**40, 2**62, 2**63 - 1, -2**31, -2**63)
#: text that CSV lines and npy headers go wrong with
HOSTILE_TEXT = (b"65636", b"-5", b"2", b"3", b"-1", b"99999999999999999999", b"1e9", b"nan", b"(1099511627776,)",
                b"(0,)", b"((", b"'<U5'", b"'O'", b"\n", b",", b",,", b"\x00", b"True", b"-0", b"0x10")


@dataclass
class Target:
    name: str
    seed: Callable[[], bytes]          # a valid input (built once)
    check: Callable[[bytes], None]     # raises AssertionError (or anything undeclared) on a contract break


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


TARGETS: dict[str, Target] = {t.name: t for t in [
    Target("messages", _message_seed, _check_message),
    Target("codec-planes", _codec_seed("planes-zstd/1"), _codec_check("planes-zstd/1")),
    Target("codec-lossy", _codec_seed("planes-zstd-ms/1"), _codec_check("planes-zstd-ms/1")),
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
    Target("file-npz", _file_seed(".npz"), _file_check(".npz")),
]}

"""The firmware's C framing (robot_bridge/firmware/arena_robot/arena_proto.c), compiled on
the host with gcc and loaded with ctypes, agrees byte for byte with arena.robot_protocol."""

from __future__ import annotations

import ctypes
import shutil
import subprocess
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from arena import robot_protocol as P

FW = Path(__file__).resolve().parents[2] / "robot_bridge" / "firmware" / "arena_robot"

SHIM = r"""
#include "arena_proto.h"
#include <stdlib.h>
#include <string.h>
ap_decoder *shim_new(void) { ap_decoder *d = malloc(sizeof *d); ap_decoder_init(d); return d; }
void shim_free(ap_decoder *d) { free(d); }
/* Feed n bytes; copy each good packet, length-prefixed (1 byte), into out. Returns bytes written. */
size_t shim_feed(ap_decoder *d, const uint8_t *in, size_t n, uint8_t *out) {
  size_t o = 0;
  for (size_t i = 0; i < n; i++) {
    if (ap_decoder_feed(d, in[i]) == AP_FRAME) { out[o++] = (uint8_t)d->len; memcpy(out + o, d->packet, d->len); o += d->len; }
  }
  return o;
}
uint32_t shim_rejected(ap_decoder *d) { return d->crc_errors + d->frame_errors + d->version_errors; }
"""


@pytest.fixture(scope="module")
def lib(tmp_path_factory):
    gcc = shutil.which("gcc")
    if gcc is None:
        pytest.skip("gcc not found: cannot build the firmware's C protocol code on the host")
    d = tmp_path_factory.mktemp("fw")
    (d / "shim.c").write_text(SHIM)
    so = d / "libarena_proto.so"
    subprocess.run([gcc, "-std=c99", "-Wall", "-Wextra", "-Werror", "-O2", "-shared", "-fPIC", f"-I{FW}",
                    str(FW / "arena_proto.c"), str(d / "shim.c"), "-o", str(so)], check=True)
    lib = ctypes.CDLL(str(so))
    lib.ap_crc16.restype = ctypes.c_uint16
    lib.ap_crc16.argtypes = [ctypes.c_char_p, ctypes.c_size_t]
    lib.ap_encode_frame.restype = ctypes.c_size_t
    lib.ap_encode_frame.argtypes = [ctypes.c_uint8, ctypes.c_uint16, ctypes.c_uint32, ctypes.c_char_p,
                                    ctypes.c_size_t, ctypes.c_char_p]
    lib.shim_new.restype = ctypes.c_void_p
    lib.shim_free.argtypes = [ctypes.c_void_p]
    lib.shim_feed.restype = ctypes.c_size_t
    lib.shim_feed.argtypes = [ctypes.c_void_p, ctypes.c_char_p, ctypes.c_size_t, ctypes.c_char_p]
    lib.shim_rejected.restype = ctypes.c_uint32
    lib.shim_rejected.argtypes = [ctypes.c_void_p]
    return lib


def c_feed(lib, wire: bytes) -> tuple[list[bytes], int]:
    dec = lib.shim_new()
    try:
        out = ctypes.create_string_buffer(len(wire) + 16)
        n = lib.shim_feed(dec, wire, len(wire), out)
        raw = out.raw[:n]
        packets, i = [], 0
        while i < n:
            ln = raw[i]
            packets.append(raw[i + 1:i + 1 + ln])
            i += 1 + ln
        return packets, lib.shim_rejected(dec)
    finally:
        lib.shim_free(dec)


@given(st.binary(max_size=120))
def test_crc_matches(lib, data):
    assert lib.ap_crc16(data, len(data)) == P.crc16(data)


telemetry = st.builds(
    P.Telemetry, st.integers(-(2**31), 2**31 - 1), st.integers(-(2**31), 2**31 - 1),
    st.tuples(*[st.integers(-32768, 32767)] * 3), st.tuples(*[st.integers(-32768, 32767)] * 3),
    st.tuples(*[st.integers(-32768, 32767)] * 3), st.integers(0, 65535), st.integers(-400, 400),
    st.integers(-400, 400), st.integers(0, 255))
any_msg = st.one_of(telemetry, st.builds(P.SetMotors, st.integers(-400, 400), st.integers(-400, 400)),
                    st.builds(P.Ping, st.integers(0, 2**32 - 1)), st.builds(P.Stop),
                    st.builds(P.SetLed, st.integers(0, 255), st.integers(0, 255), st.integers(0, 255)))


@given(any_msg, st.integers(0, 65535), st.integers(0, 2**32 - 1))
@settings(max_examples=200, deadline=None)
def test_c_encoder_emits_python_bytes(lib, msg, seq, t):
    body = msg.pack()
    out = ctypes.create_string_buffer(80)
    n = lib.ap_encode_frame(msg.TYPE, seq, t, body, len(body), out)
    assert out.raw[:n] == P.encode_frame(msg, seq, t)


@given(st.lists(st.tuples(any_msg, st.integers(0, 65535), st.integers(0, 2**32 - 1), st.binary(max_size=30)),
                max_size=10))
@settings(max_examples=150, deadline=None)
def test_c_decoder_accepts_python_frames_and_rejects_garbage(lib, items):
    wire = b"".join(g + b"\x00" + P.encode_frame(m, s, t) for m, s, t, g in items)
    packets, _ = c_feed(lib, wire)
    py = P.StreamDecoder()
    expected = [P.encode_packet(f.msg, f.seq, f.time_us) for f in py.feed(wire)]
    # The C decoder checks framing, CRC and version (type/length are the sketch's job), so it
    # returns at least what Python returns and every real frame in order.
    real = [P.encode_packet(m, s, t) for m, s, t, _ in items]
    it = iter(packets)
    assert all(any(p == r for p in it) for r in real)
    assert set(expected) <= set(packets)


def test_c_decoder_rejects_corruption(lib):
    frame = P.encode_frame(P.SetMotors(123, -321), 9, 99)
    for i in range(len(frame) - 1):
        bad = bytearray(frame)
        bad[i] ^= 0x10
        packets, rejected = c_feed(lib, b"\x00" + bytes(bad) + b"\x00")
        assert packets == [] and rejected >= 1
    packets, rejected = c_feed(lib, b"\x01" * 300 + b"\x00" + frame)
    assert len(packets) == 1 and rejected == 1

"""Wire protocol: framing, CRC, COBS, streaming decoder (property-based)."""

from __future__ import annotations

import dataclasses
import random
import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from arena import robot_protocol as P

i16 = st.integers(-32768, 32767)
power = st.integers(-400, 400)
vec3 = st.tuples(i16, i16, i16)

messages = st.one_of(
    st.builds(P.Hello),
    st.builds(P.HelloReply, st.integers(0, 65535), st.integers(0, 65535), st.integers(0, 65535),
              st.integers(0, 65535), st.text("abcdefghijklmnopqrstuvwxyz0123456789-_", max_size=16)),
    st.builds(P.SetMotors, power, power),
    st.builds(P.SetLed, st.integers(0, 255), st.integers(0, 255), st.integers(0, 255)),
    st.builds(P.Stop),
    st.builds(P.Telemetry, st.integers(-(2**31), 2**31 - 1), st.integers(-(2**31), 2**31 - 1), vec3, vec3, vec3,
              st.integers(0, 65535), power, power, st.integers(0, 255)),
    st.builds(P.Ping, st.integers(0, 2**32 - 1)),
    st.builds(P.Pong, st.integers(0, 2**32 - 1)),
    st.builds(P.Error, st.integers(0, 255), st.integers(0, 255), st.text("abc XYZ", max_size=24)),
)
frames = st.tuples(messages, st.integers(0, 65535), st.integers(0, 2**32 - 1))


def test_crc_check_value():
    assert P.crc16(b"123456789") == 0x29B1
    assert P.crc16_ccitt_false(b"123456789") == 0x29B1


@given(st.binary(max_size=700))
def test_cobs_roundtrip_has_no_zero(data):
    enc = P.cobs_encode(data)
    assert 0 not in enc
    assert P.cobs_decode(enc) == data


@given(st.binary(max_size=200))
def test_fast_crc_matches_bitwise(data):
    assert P.crc16(data) == P.crc16_ccitt_false(data)


@given(st.lists(frames, max_size=20), st.data())
@settings(max_examples=150, deadline=None)
def test_stream_split_anywhere(items, data):
    wire = b"".join(P.encode_frame(m, s, t) for m, s, t in items)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(wire)), max_size=10)))
    dec = P.StreamDecoder()
    out = []
    prev = 0
    for c in cuts + [len(wire)]:
        out += dec.feed(wire[prev:c])
        prev = c
    assert [(f.msg, f.seq, f.time_us) for f in out] == [(m, s, t) for m, s, t in items]
    assert dec.stats.rejected == 0
    assert dec.stats.frames == len(items)


@given(st.lists(st.tuples(frames, st.binary(max_size=40)), min_size=1, max_size=15))
@settings(max_examples=150, deadline=None)
def test_garbage_between_frames_is_counted_not_returned(items):
    wire = b""
    for (m, s, t), garbage in items:
        wire += garbage + b"\x00" + P.encode_frame(m, s, t)
    dec = P.StreamDecoder()
    out = dec.feed(wire)
    expected = [(m, s, t) for (m, s, t), _ in items]
    got = [(f.msg, f.seq, f.time_us) for f in out]
    # Every real frame comes through in order; garbage may (with ~2**-16 odds per chunk)
    # form an extra valid frame, never corrupt a real one.
    it = iter(got)
    assert all(any(g == e for g in it) for e in expected)
    n_garbage_chunks = sum(1 for _, g in items if g.replace(b"\x00", b""))
    assert dec.stats.frames + dec.stats.rejected >= len(items)
    assert dec.stats.rejected <= n_garbage_chunks + sum(g.count(b"\x00") for _, g in items)


def test_every_single_bit_flip_is_rejected():
    frame = P.encode_frame(P.Telemetry(1234, -99, (1, 2, 3), (4, 5, 6), (7, 8, 9), 7400, 200, -200, 0), 7, 123456)
    for i in range(len(frame) - 1):
        for bit in range(8):
            bad = bytearray(frame)
            bad[i] ^= 1 << bit
            dec = P.StreamDecoder()
            out = dec.feed(b"\x00" + bytes(bad) + b"\x00")
            assert out == [], (i, bit)
            assert dec.stats.rejected >= 1


def test_random_corruption_never_yields_data():
    rng = random.Random(1)
    msg = P.SetMotors(100, -100)
    bad_frames = 0
    dec = P.StreamDecoder()
    wire = bytearray()
    for seq in range(2000):
        f = bytearray(P.encode_frame(msg, seq, seq * 10))
        if rng.random() < 0.05:
            i = rng.randrange(len(f) - 1)
            f[i] = (f[i] + rng.randrange(1, 256)) % 256
            bad_frames += 1
        wire += f
    out = dec.feed(bytes(wire))
    assert all(fr.msg == msg for fr in out)
    assert len(out) == 2000 - bad_frames
    # A corrupted byte that became 0x00 splits a frame in two: both halves are rejected.
    assert dec.stats.rejected >= bad_frames


def test_wrong_version_and_unknown_type_counted():
    dec = P.StreamDecoder()
    out = dec.feed(P.encode_frame(P.Stop(), 1, 1, version=9))
    pkt = bytearray(P.encode_packet(P.Stop(), 1, 1))
    pkt[1] = 0x55
    pkt[-2:] = P.crc16(bytes(pkt[:-2])).to_bytes(2, "little")
    out += dec.feed(P.cobs_encode(bytes(pkt)) + b"\x00")
    assert out == []
    assert dec.stats.version_errors == 1 and dec.stats.unknown_type == 1


def test_oversized_run_is_discarded_and_decoder_recovers():
    dec = P.StreamDecoder()
    out = dec.feed(b"\x01" * 500)
    out += dec.feed(b"\x01" * 500 + b"\x00" + P.encode_frame(P.Ping(5), 1, 2))
    assert [f.msg for f in out] == [P.Ping(5)]
    assert dec.stats.framing_errors == 1


@pytest.mark.parametrize("bad", [
    lambda: P.SetMotors(401, 0), lambda: P.SetMotors(0, -401), lambda: P.SetLed(256, 0, 0),
    lambda: P.Ping(-1), lambda: P.SetMotors(1.5, 0), lambda: P.HelloReply(1, 1, 1, 1, "x" * 17),
])
def test_out_of_range_fields_raise_clear_error(bad):
    with pytest.raises(P.ProtocolError, match="range|integer|longer"):
        P.encode_frame(bad(), 0, 0)


def test_imu_scales_roundtrip():
    a, g, m = P.imu_to_raw((0.0, 0.0, 9.80665), (0.0, 0.0, 3.0), (20.0, -5.0, 40.0))
    t = P.Telemetry(0, 0, a, g, m, 7000, 0, 0)
    assert t.accel_si[2] == pytest.approx(9.80665, abs=0.01)
    assert t.gyro_si[2] == pytest.approx(3.0, abs=0.002)
    assert t.mag_si[0] == pytest.approx(20.0, abs=0.02)
    # saturation instead of overflow
    assert P.imu_to_raw((1000.0, 0, 0), (0, 0, 0), (0, 0, 0))[0][0] == 32767


def test_seq_gap_and_unwrap():
    assert P.seq_gap(5, 6) == 0
    assert P.seq_gap(65535, 0) == 0
    assert P.seq_gap(65534, 2) == 3
    u = P.Unwrapper(32)
    assert [u(v) for v in (2**32 - 10, 2**32 - 1, 5, 100)] == [2**32 - 10, 2**32 - 1, 2**32 + 5, 2**32 + 100]


def crafted_frame(mtype: int, body: bytes, seq: int = 1, time_us: int = 0) -> bytes:
    """A well-formed frame whose body the encoder would refuse (out-of-range fields)."""
    data = P.HEADER.pack(P.PROTOCOL_VERSION, mtype, seq, time_us) + body
    return P.cobs_encode(data + struct.pack("<H", P.crc16(data))) + b"\x00"


def test_out_of_range_fields_are_clamped_to_their_physical_range_and_counted():
    dec = P.StreamDecoder()
    tel = P.Telemetry(1, 2, (0, 0, 0), (0, 0, 0), (0, 0, 0), 5000, 0, 0)
    tel_body = bytearray(tel.pack())
    struct.pack_into("<hh", tel_body, 28, 9999, -400)            # motor_left out, motor_right at the limit
    frames = dec.feed(crafted_frame(P.SET_MOTORS, struct.pack("<hh", -5750, 32767))
                      + crafted_frame(P.SET_MOTORS, struct.pack("<hh", 400, -400), seq=2)
                      + crafted_frame(P.TELEMETRY, bytes(tel_body), seq=3))
    assert [f.msg for f in frames] == [P.SetMotors(-400, 400), P.SetMotors(400, -400),
                                       dataclasses.replace(tel, motor_left=400, motor_right=-400)]
    assert [f.clamped for f in frames] == [2, 0, 1]
    assert dec.stats.clamped == 3 and dec.stats.frames == 3 and dec.stats.rejected == 0
    assert P.decode_packet(P.cobs_decode(crafted_frame(P.SET_MOTORS, struct.pack("<hh", -5750, 0))[:-1])).msg \
        == P.SetMotors(-400, 0)

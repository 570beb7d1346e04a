"""Event-window codec: lossless round trips (property based), lossy ms mode, size on the
shared sample, and clear errors on corrupt or mismatched payloads."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from arena.codec import CODECS, DEFAULT_CODEC, LOSSY_CODEC, CodecError, decode, encode
from arena.events import as_events, make_events

REFERENCE = Path(__file__).resolve().parents[3] / "shared" / "data" / "evt3_sample.reference.npy"


@st.composite
def event_arrays(draw):
    n = draw(st.integers(0, 300))
    xs = draw(arrays(np.uint16, n, elements=st.integers(0, 2047)))
    ys = draw(arrays(np.uint16, n, elements=st.integers(0, 65535)))
    ps = draw(arrays(np.uint8, n, elements=st.integers(0, 1)))
    ts = draw(arrays(np.int64, n, elements=st.integers(-(1 << 62), 1 << 62)))
    if draw(st.booleans()):
        ts = np.sort(ts % 100_000)
    return make_events(xs, ys, ps, ts)


@settings(max_examples=200, deadline=None)
@given(ev=event_arrays(), ref=st.one_of(st.none(), st.integers(-(1 << 40), 1 << 40)))
def test_lossless_round_trip_any_events(ev, ref):
    data = encode(ev, DEFAULT_CODEC, t_ref_us=ref)
    out = decode(DEFAULT_CODEC, data, ev.size)
    np.testing.assert_array_equal(out, ev)


@settings(max_examples=50, deadline=None)
@given(ev=event_arrays())
def test_lossy_keeps_every_event_with_its_millisecond(ev):
    ev = ev[np.argsort(ev["t"], kind="stable")]
    ev["t"] = np.abs(ev["t"]) % 10**9
    out = decode(LOSSY_CODEC, encode(ev, LOSSY_CODEC, t_ref_us=0), ev.size)
    expected = ev.copy()
    expected["t"] = ev["t"] // 1000 * 1000

    def canon(a):
        return a[np.lexsort((a["x"], a["p"], a["y"], a["t"]))]

    np.testing.assert_array_equal(canon(out), canon(expected))
    assert np.all(np.diff(out["t"]) >= 0)


@settings(max_examples=50, deadline=None)
@given(ev=event_arrays(), span_ms=st.sampled_from([10, 511, 513]), tall=st.booleans())
def test_lossy_windows_short_or_long_tall_or_not_keep_every_event(ev, span_ms, tall):
    # a window under 512 ms with y < 2048 takes 32-bit sort keys; a longer one, or a taller
    # sensor, 64-bit keys: the same events either way
    ev = ev.copy()
    ev["t"] = np.sort(np.abs(ev["t"]) % (span_ms * 1000))
    ev["y"] = ev["y"] % 2048 + (2048 if tall else 0)
    out = decode(LOSSY_CODEC, encode(ev, LOSSY_CODEC, t_ref_us=0), ev.size)
    expected = ev.copy()
    expected["t"] = ev["t"] // 1000 * 1000
    np.testing.assert_array_equal(out, expected[np.lexsort((ev["x"], ev["p"], ev["y"], expected["t"]))])


def test_lossy_handles_a_span_too_long_to_pack_and_refuses_wide_sensors():
    # times more than 2^35 ms apart do not fit the packed sort key: sorted the slow way
    ev = make_events([5, 3, 4], [1, 1, 0], [1, 0, 1], [7_000, (1 << 36) * 1000 + 5, 7_999])
    out = decode(LOSSY_CODEC, encode(ev, LOSSY_CODEC, t_ref_us=0), 3)
    assert out.tolist() == [(4, 0, 1, 7_000), (5, 1, 1, 7_000), (3, 1, 0, (1 << 36) * 1000)]
    with pytest.raises(CodecError, match="x < 2048"):
        encode(make_events([3000], [1], [1], [0]), LOSSY_CODEC)


def test_lossy_is_compact_on_scattered_events():
    rng = np.random.default_rng(1)
    n = 20_000  # scattered, µs-distinct times: hard for the lossless coder
    ev = make_events(rng.integers(200, 260, n), rng.integers(100, 160, n), rng.integers(0, 2, n),
                     np.sort(rng.choice(10_000, n, replace=True)))
    assert len(encode(ev, LOSSY_CODEC)) < 0.6 * len(encode(ev))


def test_runs_of_a_row_are_coded_compactly():
    x = np.arange(0, 1200, 3)
    ev = make_events(x, np.full(x.size, 7), np.ones(x.size), np.full(x.size, 10_000))
    assert len(encode(ev)) < 0.3 * ev.size + 60


@pytest.mark.skipif(not REFERENCE.exists(), reason=f"{REFERENCE} absent")
def test_sample_is_at_most_1_6_bytes_per_event():
    ev = as_events(np.load(REFERENCE))
    data = encode(ev)
    assert len(data) / ev.size <= 1.6
    np.testing.assert_array_equal(decode(DEFAULT_CODEC, data, ev.size), ev)


def test_all_codecs_round_trip_and_unknown_codec_is_refused():
    ev = make_events([1, 2], [3, 4], [0, 1], [5, 6])
    for codec in (c for c in CODECS if c != LOSSY_CODEC):
        np.testing.assert_array_equal(decode(codec, encode(ev, codec), 2), ev)
    with pytest.raises(CodecError, match="unknown codec"):
        encode(ev, "gzip/9")
    with pytest.raises(CodecError, match="unknown codec"):
        decode("gzip/9", b"", 0)


def test_x_beyond_2047_is_refused():
    with pytest.raises(CodecError, match="x < 2048"):
        encode(make_events([2048], [0], [0], [0]))


def test_corrupt_payloads_raise_codec_error():
    rng = np.random.default_rng(0)
    ev = make_events(rng.integers(0, 1280, 5000), rng.integers(0, 720, 5000), rng.integers(0, 2, 5000),
                     np.sort(rng.integers(0, 10_000, 5000)))
    data = encode(ev)
    with pytest.raises(CodecError, match="message says"):
        decode(DEFAULT_CODEC, data, 4999)
    with pytest.raises(CodecError, match="outside"):
        decode(DEFAULT_CODEC, data, 5000, max_events=100)
    with pytest.raises(CodecError):
        decode(DEFAULT_CODEC, data[:-10], 5000)
    with pytest.raises(CodecError, match="header"):
        decode(DEFAULT_CODEC, data[:10], 5000)
    for _ in range(200):  # random byte flips: a clean error or (rarely) other valid events, never a crash
        bad = bytearray(data)
        for i in rng.integers(0, len(bad), 3):
            bad[i] ^= int(rng.integers(1, 256))
        try:
            out = decode(DEFAULT_CODEC, bytes(bad), 5000)
            assert out.size == 5000
        except CodecError:
            pass


# --- hostile windows (issue 20): nothing a window claims is allocated before it is checked ---

def _window_with_streams(n: int, streams: list[bytes], ndt: int = 0, ndy: int = 0) -> bytes:
    """A planes-zstd/1 payload of ``n`` events made of the given four compressed streams."""
    import struct

    return struct.pack("<4sIqIIIIII", b"EVW1", n, 0, ndt, ndy, *(len(s) for s in streams)) + b"".join(streams)


def _bomb_frame(raw_len: int, declared: int) -> bytes:
    """A zstd frame of ``raw_len`` zero bytes whose header declares ``declared`` bytes (4-byte
    frame content size field, single segment)."""
    import struct

    import zstandard

    frame = zstandard.ZstdCompressor(level=1).compress(b"\0" * raw_len)
    fhd = frame[4]
    fcs_len = (1, 2, 4, 8)[fhd >> 6] if fhd & 0x20 else (0, 2, 4, 8)[fhd >> 6]
    return frame[:4] + bytes([0xA0 | (fhd & 0x1F)]) + struct.pack("<I", declared) + frame[5 + fcs_len:]


def test_a_frame_declaring_2_gib_is_refused_before_zstd_allocates_it():
    # zstandard allocates a frame's declared content size whatever max_output_size says: under
    # an address-space limit of 256 MB over the baseline the unchecked decode was a MemoryError
    from tests.fuzz.harness import run_bounded

    r = run_bounded(
        """
        import numpy as np
        from arena.codec import DEFAULT_CODEC, CodecError, decode, encode
        from arena.events import make_events
        from tests.arena.test_codec import _bomb_frame, _window_with_streams
        ev = make_events(np.arange(1000) % 2000, np.zeros(1000), np.ones(1000), np.zeros(1000))
        decode(DEFAULT_CODEC, encode(ev), 1000)          # warm up the kernels
        bomb = _window_with_streams(1000, [_bomb_frame(1000, 2**31), _bomb_frame(1000, 1000), b"", b""])
        """,
        """
        try:
            decode(DEFAULT_CODEC, bomb, 1000)
        except CodecError as exc:
            print("CodecError:", exc)
        """)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "CodecError" in r.stdout and "declares 2147483648 bytes" in r.stdout, r.stdout


def test_a_window_claiming_10m_events_from_a_few_hundred_bytes_is_refused_without_allocating():
    # an 848-byte window expanded to 10 M events (130 MB) before anything was checked
    import tracemalloc

    import zstandard

    n = 10_000_000
    z = zstandard.ZstdCompressor(level=19)
    data = _window_with_streams(n, [z.compress(b"\x10" + b"\0" * (n - 1)), z.compress(b"\0" * n), b"", b""])
    assert len(data) < 2000
    tracemalloc.start()
    try:
        with pytest.raises(CodecError, match="per byte"):
            decode(DEFAULT_CODEC, data, n)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 1 << 20, f"{peak / 1e6:.0f} MB allocated for a refused window"


def test_every_pixel_firing_at_once_still_decodes():
    # the densest real window (a flash: every pixel of the sensor in one µs) is far inside the ratio bound
    yy, xx = np.mgrid[0:720, 0:1280]
    ev = make_events(xx.ravel(), yy.ravel(), np.ones(xx.size), np.full(xx.size, 123))
    for codec in (DEFAULT_CODEC, LOSSY_CODEC):
        np.testing.assert_array_equal(decode(codec, encode(ev, codec), ev.size), ev)


def test_one_event_limit_shared_by_the_codec_and_the_messages():
    from arena import messages as m
    from arena.codec_names import MAX_WINDOW_EVENTS

    assert m.DEFAULT_LIMITS.max_window_events == MAX_WINDOW_EVENTS == 10_000_000
    win = m.EventWindow(camera="c", seq=0, t_start_us=0, t_end_us=1, width=1, height=1,
                        count=MAX_WINDOW_EVENTS + 1, codec=DEFAULT_CODEC, data=b"")
    with pytest.raises(m.MessageError, match="cap"):   # was accepted up to 20 M, then refused by the codec
        m.EventWindow.decode(win.encode())
    with pytest.raises(CodecError, match="outside"):
        decode(DEFAULT_CODEC, b"", MAX_WINDOW_EVENTS + 1)


def test_bytes_in_a_stream_the_header_says_is_empty_are_refused():
    import struct

    ev = make_events([1, 5, 9], [0, 0, 0], [0, 1, 1], [10, 10, 20])
    data = encode(ev, t_ref_us=0)
    _, n, _, ndt, ndy, *sizes = struct.unpack_from("<4sIqIIIIII", data)
    cuts = np.cumsum([40, *sizes])
    streams = [data[a:b] for a, b in zip(cuts[:-1], cuts[1:])]
    assert ndy == 0 and streams[3] == b""
    np.testing.assert_array_equal(decode(DEFAULT_CODEC, _window_with_streams(n, streams, ndt, ndy), 3), ev)
    # bytes in the dy escape stream, which the header says is empty (they were ignored)
    with pytest.raises(CodecError, match="empty"):
        decode(DEFAULT_CODEC, _window_with_streams(n, [*streams[:3], b"\x28\xb5\x2f\xfd"], ndt, ndy), 3)

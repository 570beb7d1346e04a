"""Red team round 2 on the AEDAT4 and .npy readers: a packet decompressing to a gigabyte is
skipped in bounded memory and a maximal real packet is read in chunks of ``chunk_events``; an
AEDAT4 ``on`` byte or a .npy bool polarity byte other than 0/1 is an invalid event; a .npy shape
with a negative dimension is refused up front."""

from __future__ import annotations

import struct
import tracemalloc
import warnings

import lz4.frame
import numpy as np
import pytest
import zstandard

from arena.events import make_events
from arena.formats import FormatError, SkippedData, iter_events
from arena.formats import aedat4
from tests.fuzz.harness import run_bounded


def _elements(n: int) -> np.ndarray:
    """``n`` AEDAT4 events at (1, 1), every 256th ON with a random t: compressible enough to be
    small, not so much that the reader's ratio cap refuses the packet."""
    raw = np.zeros(n, aedat4._AEDAT_EVENT)
    raw["x"] = raw["y"] = 1
    raw["on"][::256] = 1
    raw["t"][::256] = np.random.default_rng(n).integers(0, 1 << 62, raw["t"][::256].size)
    return raw


def _packet_head(n: int) -> bytes:
    """The 32 bytes of EventPacket FlatBuffer before ``n`` elements (as :func:`aedat4._packet_buffer`)."""
    head = bytearray(32)
    struct.pack_into("<II", head, 0, 32 + 16 * n - 4, 16)
    head[8:12] = b"EVTS"
    struct.pack_into("<HHH", head, 12, 6, 8, 4)
    struct.pack_into("<iII", head, 20, 8, 4, n)
    return bytes(head)


def _compressed(n: int, codec: str, piece: np.ndarray | None = None) -> bytes:
    """A packet of ``n`` events compressed with ``codec`` ("zstd" declaring its size, "zstd-stream"
    without, "lz4"), its elements ``piece`` repeated (never held whole)."""
    piece = _elements(min(n, 1 << 19)) if piece is None else piece
    if codec == "lz4":
        c = lz4.frame.LZ4FrameCompressor()
        out = [c.begin(), c.compress(_packet_head(n))]
        add, end = c.compress, c.flush
    else:
        z = zstandard.ZstdCompressor(level=1, write_content_size=codec == "zstd")
        c = z.compressobj(size=32 + 16 * n if codec == "zstd" else -1)
        out = [c.compress(_packet_head(n))]
        add, end = c.compress, c.flush
    left = n
    while left:
        k = min(left, piece.size)
        out.append(add(piece[:k].view(np.uint8)))
        left -= k
    out.append(end())
    return b"".join(out)


def _aedat4_file(path, bodies: list[bytes], compression: str) -> None:
    """An AEDAT4 file (320 x 240) of the packet ``bodies`` (already compressed), stream 0."""
    aedat4.Aedat4Writer(path, 320, 240, compression=compression).close()
    with open(path, "ab") as f:
        for body in bodies:
            f.write(struct.pack("<ii", 0, len(body)) + body)


_COMPRESSION = {"zstd": "zstd", "zstd-stream": "zstd", "lz4": "lz4"}


# --- 1. one packet's size ---

@pytest.mark.parametrize("codec", ["zstd", "zstd-stream", "lz4"])
def test_a_packet_decompressing_to_200_mb_is_skipped_under_the_fuzz_address_limit(tmp_path, codec):
    # the red team's 1.1 MB file of one valid ~1 GiB packet peaked at 2.13 GB: the packet was
    # held twice (zstd pieces, then joined) and yielded as one chunk; 200 MiB shows it (400 MB)
    n = (200 << 20) // 16
    body = _compressed(n, codec)
    assert len(body) * aedat4._MAX_RATIO > 32 + 16 * n      # within the ratio cap: a "valid" packet
    _aedat4_file(tmp_path / "bomb.aedat4", [body], _COMPRESSION[codec])
    r = run_bounded(
        f"""
        import sys, warnings
        from arena.formats import iter_events, write_events
        from arena.events import make_events
        ev = make_events([1, 2], [1, 1], [0, 1], [5, 6])
        write_events(sys.argv[1] + ".small.aedat4", ev, 320, 240, compression={_COMPRESSION[codec]!r})
        with iter_events(sys.argv[1] + ".small.aedat4") as reader:
            reader.read_all()
        """,
        """
        warnings.simplefilter("ignore")
        with iter_events(sys.argv[1]) as reader:
            n = sum(c.size for c in reader)
        print("events", n, "skipped", reader.skipped, reader.skipped_packets)
        """, args=[str(tmp_path / "bomb.aedat4")])
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.split() == ["events", "0", "skipped", "1", "1"], r.stdout


@pytest.mark.parametrize("codec", ["zstd", "zstd-stream", "lz4"])
def test_a_maximal_packet_is_held_once_and_read_in_chunks_of_chunk_events(tmp_path, codec):
    n = aedat4._MAX_PACKET_EVENTS
    raw = _elements(n)
    _aedat4_file(tmp_path / "max.aedat4", [_compressed(n, codec, raw)], _COMPRESSION[codec])
    want_t, want_p = raw["t"].copy(), raw["on"].astype(np.uint8)
    del raw
    sizes, seen, ok = [], 0, True
    with iter_events(tmp_path / "max.aedat4", chunk_events=1 << 16) as reader:
        tracemalloc.start()
        try:
            for c in reader:
                sizes.append(c.size)
                ok &= bool(np.array_equal(c["t"], want_t[seen:seen + c.size])
                           and np.array_equal(c["p"], want_p[seen:seen + c.size]))
                seen += c.size
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
    assert seen == n and ok and reader.skipped == reader.invalid == 0
    # the decompressed 64 MiB once and a chunk (was 128 MiB and more: zstd pieces joined, LZ4's
    # output copied, then the packet's events converted whole)
    assert peak < 80e6, f"{peak / 1e6:.0f} MB"
    assert max(sizes) == 1 << 16, max(sizes)        # was one chunk of 4 Mi events


def test_chunks_are_at_most_chunk_events_and_never_span_packets(tmp_path):
    ev = make_events(np.arange(2500) % 320, np.zeros(2500), np.arange(2500) % 2, np.arange(2500))
    with aedat4.Aedat4Writer(tmp_path / "a.aedat4", 320, 240, packet_events=1000) as w:
        w.write(ev)
    with iter_events(tmp_path / "a.aedat4", chunk_events=300) as reader:
        parts = list(reader)
    assert [p.size for p in parts] == [300, 300, 300, 100] * 2 + [300, 200]
    np.testing.assert_array_equal(np.concatenate(parts), ev)


def test_the_writer_never_writes_a_packet_the_reader_refuses(tmp_path, monkeypatch):
    monkeypatch.setattr(aedat4, "_MAX_PACKET_EVENTS", 100)
    ev = make_events(np.arange(250), np.zeros(250), np.ones(250), np.arange(250))
    with aedat4.Aedat4Writer(tmp_path / "a.aedat4", 320, 240, packet_events=10**9) as w:
        w.write(ev)
    with iter_events(tmp_path / "a.aedat4", chunk_events=10**6) as reader:
        assert [p.size for p in reader] == [100, 100, 50]


def test_an_uncompressed_packet_over_the_cap_is_skipped_unread(tmp_path, monkeypatch):
    small, big = _elements(10), _elements(100)
    _aedat4_file(tmp_path / "a.aedat4", [_packet_head(10) + small.tobytes(), _packet_head(100) + big.tobytes()],
                 "none")
    monkeypatch.setattr(aedat4, "_MAX_PACKET", 1024)   # the 100 events are 1632 bytes
    with pytest.warns(SkippedData, match="over the 1024 bytes") as caught:
        with iter_events(tmp_path / "a.aedat4") as reader:
            got = reader.read_all()
    np.testing.assert_array_equal(got["t"], small["t"])
    assert (reader.skipped, reader.skipped_packets, reader.invalid) == (1, 1, 0)
    assert [w.message.unit for w in caught] == ["corrupt packets"]


# --- 2. the on byte ---

@pytest.mark.parametrize("compression", ["none", "lz4", "zstd"])
@pytest.mark.parametrize("byte", [2, 0x80, 0xFF])
def test_an_on_byte_other_than_0_or_1_is_an_invalid_event(tmp_path, compression, byte):
    # dv-processing writes a bool; 0x80 read as ON, silently
    ev = make_events([1, 2, 3, 4], [5, 5, 5, 5], [0, 0, 1, 1], [10, 20, 30, 40])
    packet = bytearray(aedat4._packet_buffer(ev))
    packet[32 + 16 * 0 + 12] = byte
    packet[32 + 16 * 2 + 12] = byte
    writer = aedat4.Aedat4Writer(tmp_path / "on.aedat4", 320, 240, compression=compression)
    writer.close()
    _aedat4_file(tmp_path / "on.aedat4", [writer._compress(bytes(packet))], compression)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with iter_events(tmp_path / "on.aedat4") as reader:
            got = reader.read_all()
    assert got["x"].tolist() == [2, 4] and got["p"].tolist() == [0, 1]
    assert (reader.invalid, reader.skipped) == (2, 0)
    assert [(w.category, w.message.count, w.message.unit) for w in caught] == [(SkippedData, 2, "invalid events")]


# --- 3. .npy ---

_EVENT_DESCR = "[('x', '<u2'), ('y', '<u2'), ('p', '|u1'), ('t', '<i8')]"


def _npy(path, descr: str, shape: str, body: bytes) -> None:
    """A version 1.0 ``.npy`` file of header ``descr`` and ``shape`` (as written, unchecked)."""
    h = f"{{'descr': {descr}, 'fortran_order': False, 'shape': {shape}, }}".encode("latin1")
    h += b" " * (-(10 + len(h) + 1) % 64) + b"\n"
    path.write_bytes(b"\x93NUMPY\x01\x00" + struct.pack("<H", len(h)) + h + body)


@pytest.mark.parametrize("shape", ["(-1,)", "(-2, -2)", f"({1 << 62}, -4)", "(0, -1)", "(-4, 1)"])
def test_a_npy_shape_with_a_negative_dimension_is_refused_first(tmp_path, shape):
    # (-2, -2) read as 4 events; (-1,) first warned of "65 bytes after the -1 elements"
    body = np.zeros(4, [("x", "<u2"), ("y", "<u2"), ("p", "u1"), ("t", "<i8")]).tobytes()
    _npy(tmp_path / "neg.npy", _EVENT_DESCR, shape, body)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(FormatError, match="negative dimension"):
            iter_events(tmp_path / "neg.npy")
    assert caught == []


def test_a_npy_bool_polarity_byte_other_than_0_or_1_is_an_invalid_event(tmp_path):
    dt = np.dtype([("x", "<u2"), ("y", "<u2"), ("p", "u1"), ("t", "<i8")])
    rows = np.array([(1, 1, 0, 5), (2, 1, 1, 6), (3, 1, 7, 7), (4, 1, 2, 8), (5, 1, 1, 9)], dt)
    _npy(tmp_path / "b.npy", "[('x', '<u2'), ('y', '<u2'), ('p', '|b1'), ('t', '<i8')]", "(5,)", rows.tobytes())
    with pytest.warns(SkippedData, match="invalid values") as caught:
        with iter_events(tmp_path / "b.npy", width=320, height=240) as reader:
            got = reader.read_all()
    assert got["x"].tolist() == [1, 2, 5] and got["p"].tolist() == [0, 1, 1]
    assert (reader.invalid, reader.skipped) == (2, 0)
    assert [w.message.count for w in caught] == [2]


def _npz_columns(path, n=50, **extra):
    ev = make_events(np.arange(n) % 320, np.arange(n) % 240, np.arange(n) % 2, np.arange(n) * 10)
    np.savez(path, x=ev["x"], y=ev["y"], p=ev["p"], t=ev["t"], width=320, height=240, **extra)
    return ev


def test_an_npz_member_of_no_known_name_is_reported_not_silently_ignored(tmp_path):
    # a damaged member name (width.npy -> wiath.npy) had made the sensor size fall back to the
    # events' extent without a word
    import zipfile
    src = tmp_path / "a.npz"
    _npz_columns(src)
    data = src.read_bytes().replace(b"width.npy", b"wiath.npy")
    (tmp_path / "b.npz").write_bytes(data)
    with pytest.warns(SkippedData, match=r"npz members \['wiath.npy'\] are not event arrays"):
        with iter_events(tmp_path / "b.npz") as r:
            n = sum(c.size for c in r)
            assert r.skipped == 1 and (r.width, r.height) == (50, 240)   # the extent, now said
    assert n == 50
    with zipfile.ZipFile(src) as zf:
        assert sorted(zf.namelist()) == ["height.npy", "p.npy", "t.npy", "width.npy", "x.npy", "y.npy"]


def test_a_simulator_recording_npz_reads_without_a_word(tmp_path):
    from simulator.recording import save_recording
    from simulator.scenarios import Scenario, generate
    rec = generate(Scenario(1, "circle", 0.5, 0.2, seed=1))
    save_recording(rec, tmp_path / "sim.npz")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with iter_events(tmp_path / "sim.npz") as r:
            assert sum(c.size for c in r) == rec.events.size and r.skipped == 0


def test_an_npz_with_two_members_of_one_name_or_a_damaged_scalar_is_refused(tmp_path):
    import zipfile
    src = tmp_path / "a.npz"
    _npz_columns(src)
    dup = tmp_path / "dup.npz"
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dup, "w") as zout, warnings.catch_warnings():
        warnings.simplefilter("ignore")   # zipfile warns of the duplicate name it is asked to write
        for info in zin.infolist():
            zout.writestr(info, zin.read(info))
        zout.writestr("x.npy", zin.read("x.npy"))
    with pytest.raises(FormatError, match="more than one member named x.npy"):
        iter_events(dup)
    bad = tmp_path / "w.npz"
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(bad, "w") as zout:
        for info in zin.infolist():
            zout.writestr(info, zin.read(info) + (b"\0" * 8 if info.filename == "width.npy" else b""))
    with pytest.raises(FormatError, match="width has 8 bytes after its one value"):
        iter_events(bad)

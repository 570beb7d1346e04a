"""Decompression bombs (issue 20, red team round 3): an event window or an .npz that claims far
more than it holds is refused, or decoded in bounded memory, and only with the declared error."""

from __future__ import annotations

import io
import struct
import tracemalloc
import zipfile

import numpy as np
import pytest

from arena import codec
from arena.codec import DEFAULT_CODEC, CodecError, decode, encode
from arena.events import make_events
from arena.formats import FormatError, iter_events, read_events
from tests.fuzz.harness import run_bounded

N_BOMB = 10_000_000


def escape_bomb(n: int = N_BOMB) -> bytes:
    """The red team's window: four zstd frames without a content size, ``n`` events claimed
    (just inside MAX_EVENTS_PER_BYTE), escape streams of 10 n and 3 n bytes, all zeros."""
    import zstandard

    ndt, ndy = 10 * n, 3 * n
    z = zstandard.ZstdCompressor(level=3, write_content_size=False)
    parts = [z.compress(b"\x10" * n), z.compress(b"\0" * n), z.compress(b"\0" * ndt), z.compress(b"\0" * ndy)]
    total = 36 + sum(map(len, parts))
    if n > 2048 * total:
        parts[3] += b"\0" * (n // 2048 + 1 - total)   # trailing bytes after the frame
    return struct.pack("<4sIqIIIIII", b"EVW1", n, 0, ndt, ndy, *(len(p) for p in parts)) + b"".join(parts)


@pytest.fixture(scope="module")
def bomb() -> bytes:
    return escape_bomb()


def test_escape_stream_bomb_is_a_codec_error_under_the_fuzz_address_limit():
    # was MemoryError under limit_address_space (zstd allocated 10 + 10 + 100 + 30 MB of
    # max_output_size up front, then the 130 MB of events)
    r = run_bounded(
        """
        import numpy as np
        from arena.codec import DEFAULT_CODEC, CodecError, decode, encode
        from arena.events import make_events
        from tests.arena.test_bombs import escape_bomb
        ev = make_events(np.arange(1000) % 2000, np.zeros(1000), np.ones(1000), np.zeros(1000))
        decode(DEFAULT_CODEC, encode(ev), 1000)
        data = escape_bomb()
        """,
        """
        try:
            decode(DEFAULT_CODEC, data, len(data) and 10_000_000)
        except CodecError as exc:
            print("CodecError:", exc)
        """)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "CodecError" in r.stdout, r.stdout


def test_escape_stream_bomb_is_refused_without_decompressing_its_streams_whole(bomb):
    assert len(bomb) < 20_000
    decode(DEFAULT_CODEC, encode(make_events([1], [1], [1], [1])), 1)
    tracemalloc.start()
    try:
        with pytest.raises(CodecError):
            decode(DEFAULT_CODEC, bomb, N_BOMB)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    # the event array is reserved (130 MB of address space, lazily mapped); what is written and
    # decompressed stays a few chunks: the leftover escape bytes are noticed after the first one
    assert peak < 150e6, f"{peak / 1e6:.0f} MB"   # was 290 MB


def _events(rng, n: int):
    t = np.cumsum(rng.integers(-5, 1 << int(rng.integers(1, 40)), n))
    return make_events(rng.integers(0, 2048, n), rng.integers(0, 60000, n), rng.integers(0, 2, n), t)


def _decode_either(data: bytes, n: int):
    try:
        return decode(DEFAULT_CODEC, data, n)
    except CodecError:
        return None


@pytest.mark.parametrize("chunk", [1, 7, 4096])
def test_chunked_decoding_is_the_one_shot_decoding(monkeypatch, chunk):
    # windows over _ONE_SHOT_BYTES of streams are decoded in chunks: the same events, the same
    # refusals, with varints cut at every chunk boundary
    rng = np.random.default_rng(chunk)
    cases = []
    for _ in range(30):
        n = int(rng.integers(1, 300))
        ev = _events(rng, n)
        data = encode(ev)
        bad = bytearray(data)
        k = int(rng.integers(36, len(bad)))
        bad[k] ^= int(rng.integers(1, 256))
        cases.append((ev, data, bytes(bad), _decode_either(bytes(bad), n)))
    monkeypatch.setattr(codec, "_ONE_SHOT_BYTES", 0)
    monkeypatch.setattr(codec, "_CHUNK", chunk)
    for ev, data, bad, expected in cases:
        np.testing.assert_array_equal(decode(DEFAULT_CODEC, data, ev.size), ev)
        got = _decode_either(bad, ev.size)
        assert (got is None) == (expected is None)
        if got is not None:
            np.testing.assert_array_equal(got, expected)


def test_a_memory_error_inside_decode_is_a_codec_error(monkeypatch):
    class Starved:
        def decompress(self, *a, **k):
            raise MemoryError

    data = encode(make_events(np.arange(100), np.zeros(100), np.ones(100), np.arange(100)))
    monkeypatch.setattr(codec, "_decompressor", lambda: Starved())
    with pytest.raises(CodecError, match="memory"):
        decode(DEFAULT_CODEC, data, 100)


# --- .npz ---

def npz_bomb(path, n: int) -> None:
    """Four zero-filled uint8 columns of ``n`` events, each deflated ~1030:1 (inside the
    per-member ratio), and a sensor size."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as zf:
        for name in "xypt":
            buf = io.BytesIO()
            np.save(buf, np.zeros(n, np.uint8))
            zf.writestr(name + ".npy", buf.getvalue())
        for name, v in (("width", 640), ("height", 480)):
            buf = io.BytesIO()
            np.save(buf, np.array(v))
            zf.writestr(name + ".npy", buf.getvalue())


@pytest.fixture(scope="module")
def bomb_npz(tmp_path_factory):
    path = tmp_path_factory.mktemp("npz") / "bomb.npz"
    npz_bomb(path, 20_000_000)
    return path


def test_an_npz_expanding_over_100_to_one_in_all_is_refused(bomb_npz):
    # 79 KB -> 80 MB of columns (and 260 MB of events) read with exit 0
    assert bomb_npz.stat().st_size < 100_000
    with pytest.raises(FormatError, match="decompression bomb"):
        read_events(bomb_npz)


def test_an_npz_is_read_in_chunks_whatever_it_expands_to(bomb_npz, monkeypatch):
    from arena.formats import numpy_files

    monkeypatch.setattr(numpy_files, "_MAX_ARCHIVE_RATIO", 10_000, raising=False)
    tracemalloc.start()
    try:
        with iter_events(bomb_npz) as reader:
            n = sum(c.size for c in reader)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert n == 20_000_000 and (reader.width, reader.height) == (640, 480)
    assert peak < 40e6, f"{peak / 1e6:.0f} MB for 20 M events read in chunks of 262 144"


def test_npz_chunks_are_the_whole_file_read_at_once(tmp_path):
    rng = np.random.default_rng(5)
    ev = make_events(rng.integers(0, 640, 1000), rng.integers(0, 480, 1000), rng.integers(0, 2, 1000),
                     np.sort(rng.integers(0, 10**9, 1000)))
    np.savez_compressed(tmp_path / "c.npz", x=ev["x"], y=ev["y"], p=ev["p"], t=ev["t"])
    np.savez(tmp_path / "s.npz", events=ev)
    for path in (tmp_path / "c.npz", tmp_path / "s.npz"):
        with iter_events(path, chunk_events=77) as reader:
            parts = list(reader)
        assert len(parts) == 13 and (reader.width, reader.height) == (ev["x"].max() + 1, ev["y"].max() + 1)
        np.testing.assert_array_equal(np.concatenate(parts), ev)


def test_a_memory_error_reading_an_npz_is_a_format_error(tmp_path, monkeypatch):
    ev = make_events(np.arange(100), np.zeros(100), np.ones(100), np.arange(100))
    np.savez_compressed(tmp_path / "m.npz", x=ev["x"], y=ev["y"], p=ev["p"], t=ev["t"], width=640, height=480)

    def starved(self, *a, **k):
        raise MemoryError

    monkeypatch.setattr(zipfile.ZipExtFile, "read", starved)
    with pytest.raises(FormatError, match="memory"):
        read_events(tmp_path / "m.npz")

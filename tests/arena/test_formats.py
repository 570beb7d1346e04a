"""Event file formats: reference decode of the shared EVT 3.0 sample, streaming with odd chunk
boundaries, time wraps, round trips through every writer and reader, bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from arena.events import make_events
from arena.formats import FormatError, iter_events, read_events, write_events
from arena.formats.evt2 import Evt2Decoder, Evt21Decoder, encode_evt2, encode_evt21
from arena.formats.evt3 import Evt3Decoder, encode_evt3
from arena.formats.raw import parse_raw_header

DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
SAMPLE = DATA / "evt3_sample.raw"
REFERENCE = DATA / "evt3_sample.reference.npy"
needs_sample = pytest.mark.skipif(not SAMPLE.exists(), reason=f"{SAMPLE} absent")


def _random_events(n: int, seed: int = 0, t0: int = 0, width: int = 1280, height: int = 720) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = t0 + np.cumsum(rng.integers(0, 40, n))
    return make_events(rng.integers(0, width, n), rng.integers(0, height, n), rng.integers(0, 2, n), t)


@needs_sample
def test_evt3_sample_matches_reference_exactly():
    ev, w, h = read_events(SAMPLE)
    ref = np.load(REFERENCE)
    assert (w, h) == (1280, 720)
    assert ev.size == ref.size
    for f in "xypt":
        np.testing.assert_array_equal(ev[f], ref[f])


@needs_sample
@settings(max_examples=20, deadline=None)
@given(cuts=st.lists(st.integers(min_value=0, max_value=600_000), max_size=12))
def test_evt3_sample_any_chunk_boundaries(cuts):
    raw = SAMPLE.read_bytes()
    body = raw[parse_raw_header(raw).size:]
    edges = sorted({0, len(body), *[min(c, len(body)) for c in cuts]})
    dec = Evt3Decoder()
    ev = np.concatenate([dec.feed(body[a:b]) for a, b in zip(edges[:-1], edges[1:])])
    ref = np.load(REFERENCE)
    np.testing.assert_array_equal(ev["t"], ref["t"])
    np.testing.assert_array_equal(ev["x"], ref["x"])


def test_evt3_time_high_repeat_keeps_time_low():
    # TIME_HIGH 1, TIME_LOW 5, Y 3, X 7; TIME_HIGH 1 again, X 8 -> both at t = 4096 + 5
    words = np.array([0x8001, 0x6005, 0x0003, 0x2007, 0x8001, 0x2808], dtype="<u2")
    ev = Evt3Decoder().feed(words.tobytes())
    assert ev["t"].tolist() == [4101, 4101]
    assert ev["x"].tolist() == [7, 8] and ev["p"].tolist() == [0, 1]


def test_evt3_vectors_expand_in_order_and_y_system_bit_is_ignored():
    # Y=10 with system bit 11 set; base x 100 pol 1; VECT_12 mask 0b101; VECT_8 mask 0b1
    words = np.array([0x8000, 0x6000, 0x0800 | 10, 0x3800 | 100, 0x4005, 0x5001], dtype="<u2")
    ev = Evt3Decoder().feed(words.tobytes())
    assert ev["x"].tolist() == [100, 102, 112]
    assert set(ev["y"].tolist()) == {10} and set(ev["p"].tolist()) == {1}



def test_evt3_vect8_ignores_mask_bits_above_8_in_count_and_decode():
    # VECT_8 0x5F01: bits 0 and 8-11 set, only bit 0 is an event; VECT_12 0x4801: bits 0, 11
    words = np.array([0x8000, 0x6000, 0x0003, 0x3000 | 100, 0x5F01, 0x4801], dtype="<u2")
    ev = Evt3Decoder().feed(words.tobytes())
    assert ev["x"].tolist() == [100, 108, 119]

def test_evt3_24bit_wrap_is_extended():
    ev = _random_events(3000, seed=1, t0=(1 << 24) - 20_000)
    ev["t"] += np.arange(ev.size) * 20  # crosses the 2**24 µs wrap
    dec = Evt3Decoder()
    out = dec.feed(encode_evt3(ev))
    np.testing.assert_array_equal(out["t"], ev["t"])
    assert out["t"][-1] > 1 << 24


def test_evt3_events_before_first_time_high_are_counted():
    dec = Evt3Decoder()
    out = dec.feed(np.array([0x0001, 0x2005, 0x8000, 0x2006], dtype="<u2").tobytes())
    assert out["x"].tolist() == [6] and dec.skipped_words == 1


def test_evt3_writer_codes_sparse_rows_without_empty_vector_words():
    # one row, time and polarity: a dense stretch of 12 px (one VECT_BASE_X + one VECT_12 word
    # instead of 12 EVT_ADDR_X), then 3 events 150 px apart (3 EVT_ADDR_X, no empty VECT_12
    # words walking the base across the gaps)
    x = np.array(list(range(100, 112)) + [300, 450, 600])
    ev = make_events(x, np.full(x.size, 7), np.ones(x.size, int), np.full(x.size, 5000))
    words = np.frombuffer(encode_evt3(ev), "<u2")
    kinds = (words >> 12).tolist()
    assert kinds.count(0x3) == 1 and kinds.count(0x4) == 1 and kinds.count(0x2) == 3
    assert len(words) == 3 + 1 + 1 + 3          # TIME_HIGH, TIME_LOW, ADDR_Y; vector; 3 ADDR_X
    np.testing.assert_array_equal(Evt3Decoder().feed(words.tobytes()), ev)


@needs_sample
def test_evt3_writer_is_no_larger_than_the_camera_on_the_real_sample():
    raw = SAMPLE.read_bytes()
    body = raw[parse_raw_header(raw).size:]
    ev, _, _ = read_events(SAMPLE)
    data = encode_evt3(ev)
    assert len(data) <= len(body)               # 575 kB vs the camera's 618 kB (was 1.24 MB)
    np.testing.assert_array_equal(Evt3Decoder().feed(data), ev)


def test_evt2_and_evt21_round_trip_with_odd_chunks_and_wrap():
    ev = _random_events(5000, seed=2, t0=(1 << 34) - 50_000)
    for encode, dec in ((encode_evt2, Evt2Decoder()), (encode_evt21, Evt21Decoder())):
        data = encode(ev)
        parts = [dec.feed(data[i:i + 13]) for i in range(0, len(data), 13)]
        out = np.concatenate(parts)
        np.testing.assert_array_equal(out, ev)


def test_evt21_vector_mask_expands():
    hi = (1 << 28) | (3 << 22) | (64 << 11) | 5  # POS, t low 3, x 64, y 5
    words = np.array([(8 << 60) | (2 << 32), (hi << 32) | 0b1001], dtype="<u8")
    out = Evt21Decoder().feed(words.tobytes())
    assert out["x"].tolist() == [64, 67] and out["t"].tolist() == [2 * 64 + 3] * 2


@pytest.mark.parametrize("name", ["a.raw", "b.dat", "c.aedat4", "d.csv", "e.npz", "f.npy"])
def test_every_format_round_trips(tmp_path, name):
    ev = _random_events(20_000, seed=3, t0=123_456_789)
    path = tmp_path / name
    write_events(path, ev, 1280, 720)
    out, w, h = read_events(path)
    np.testing.assert_array_equal(out, ev)
    assert (w, h) == (1280, 720)


@pytest.mark.parametrize("opts", [{"evt": 2}, {"evt": 3}])
def test_raw_writer_versions_and_header(tmp_path, opts):
    ev = _random_events(1000, seed=4, width=640, height=480)
    write_events(tmp_path / "x.raw", ev, 640, 480, **opts)
    with iter_events(tmp_path / "x.raw", chunk_events=100) as reader:
        assert reader.header.version == f"{opts['evt']}.0" and (reader.width, reader.height) == (640, 480)
        np.testing.assert_array_equal(reader.read_all(), ev)


@pytest.mark.parametrize("compression", ["lz4", "zstd", "none"])
def test_aedat4_compressions(tmp_path, compression):
    ev = _random_events(70_000, seed=5)
    write_events(tmp_path / "x.aedat4", ev, 1280, 720, compression=compression)
    out, w, h = read_events(tmp_path / "x.aedat4")
    np.testing.assert_array_equal(out, ev)


def test_aedat4_agrees_with_the_aedat_package(tmp_path):
    aedat = pytest.importorskip("aedat")
    ev = _random_events(5000, seed=6)
    write_events(tmp_path / "x.aedat4", ev, 1280, 720, compression="zstd")
    packets = [p["events"] for p in aedat.Decoder(tmp_path / "x.aedat4") if "events" in p]
    theirs = np.concatenate(packets)
    np.testing.assert_array_equal(theirs["t"], ev["t"])
    np.testing.assert_array_equal(theirs["x"], ev["x"])


def test_csv_with_and_without_header_and_column_order(tmp_path):
    (tmp_path / "a.csv").write_text("1,2,1,100\n3,4,0,200\n")
    (tmp_path / "b.csv").write_text("t,x,y,polarity\n100,1,2,1\n200,3,4,-1\n")
    a, _, _ = read_events(tmp_path / "a.csv")
    b, _, _ = read_events(tmp_path / "b.csv")
    np.testing.assert_array_equal(a, b)
    assert a["p"].tolist() == [1, 0] and a["t"].tolist() == [100, 200]


def test_dat_32bit_wrap_is_extended(tmp_path):
    ev = _random_events(1000, seed=7, t0=(1 << 32) - 10_000)
    write_events(tmp_path / "x.dat", ev, 1280, 720)
    out, _, _ = read_events(tmp_path / "x.dat")
    np.testing.assert_array_equal(out["t"] - out["t"][0], ev["t"] - ev["t"][0])


@pytest.mark.parametrize("name,content,match", [
    ("x.foo", b"123", "unknown extension"),
    ("x.raw", b"% evt 9.9\n% end\n\x00\x00", "EVT version"),
    ("x.aedat4", b"#!AER-DAT4.0\r\n\x40\x00", "truncated"),
    ("x.aedat4", b"hello", "magic"),
    ("x.csv", b"1,2,1,100\n3,4,zero,200\n", "non-numeric"),
    ("x.csv", b"1,2,1\n3,4,0\n", "4 columns"),
    ("x.npz", b"not a zip", "numpy"),
])
def test_bad_files_give_clear_errors(tmp_path, name, content, match):
    (tmp_path / name).write_bytes(content)
    with pytest.raises(FormatError, match=match):
        read_events(tmp_path / name)


def test_truncated_aedat4_packet_is_an_error(tmp_path):
    ev = _random_events(1000, seed=8)
    write_events(tmp_path / "x.aedat4", ev, 1280, 720)
    data = (tmp_path / "x.aedat4").read_bytes()
    (tmp_path / "y.aedat4").write_bytes(data[:-100])
    with pytest.raises(FormatError, match="truncated"):
        read_events(tmp_path / "y.aedat4")


def test_raw_garbage_outside_sensor_is_counted(tmp_path):
    ev = _random_events(100, seed=9)
    write_events(tmp_path / "x.raw", ev, 1280, 720)
    data = bytearray((tmp_path / "x.raw").read_bytes())
    data += np.array([0x2000 | 2000], dtype="<u2").tobytes()  # x = 2000 > width
    (tmp_path / "x.raw").write_bytes(bytes(data))
    with iter_events(tmp_path / "x.raw") as reader:
        out = reader.read_all()
        assert reader.invalid == 1 and out.size == 100


@pytest.mark.parametrize("ext", [".raw", ".csv", ".npz"])
def test_files_the_simulator_writes(tmp_path, ext):
    from simulator.recording import save_recording, write_events as sim_write
    from simulator.scenarios import Scenario, generate

    rec = generate(Scenario(n_robots=2, pattern="circle", duration_s=0.6, seed=11))
    path = tmp_path / f"sim{ext}"
    if ext == ".npz":
        save_recording(rec, path)
    else:
        sim_write(path, rec.events, rec.width, rec.height)
    ev, w, h = read_events(path, **({"width": rec.width, "height": rec.height} if ext == ".csv" else {}))
    order = np.lexsort((rec.events["x"], rec.events["p"], rec.events["y"], rec.events["t"]))
    expected = rec.events[order] if ext == ".raw" else rec.events  # the camera's (t, y, p, x) order
    np.testing.assert_array_equal(ev, expected)
    assert (w, h) == (rec.width, rec.height)


def test_simulator_raw_across_the_24bit_wrap(tmp_path):
    from simulator.recording import write_events as sim_write

    ev = _random_events(4000, seed=12, t0=(1 << 24) - 100_000)
    ev["t"] += np.arange(ev.size) * 60  # ~0.4 s across the 16.7 s wrap
    ev = ev[np.lexsort((ev["x"], ev["p"], ev["y"], ev["t"]))]
    sim_write(tmp_path / "w.raw", ev, 1280, 720)
    out, _, _ = read_events(tmp_path / "w.raw")
    np.testing.assert_array_equal(out["t"], ev["t"])


@pytest.mark.parametrize("compression", ["lz4", "lz4high", "zstd", "zstdhigh", "none"])
def test_aedat4_files_cross_read_with_inivations_dv_processing(tmp_path, compression):
    # our writer -> iniVation's reader, and iniVation's writer -> our reader, event for event
    # (dv-processing refused our files until their IOHeader carried its "IOHE" identifier)
    dv = pytest.importorskip("dv_processing", reason="dv-processing (the 'inivation' extra) is not installed")
    ev = _random_events(20_000, seed=9, t0=1 << 33, width=346, height=260)
    write_events(tmp_path / "ours.aedat4", ev, 346, 260, compression=compression)
    rec = dv.io.MonoCameraRecording(str(tmp_path / "ours.aedat4"))
    assert tuple(rec.getEventResolution()) == (346, 260)
    got = []
    while rec.isRunning():
        batch = rec.getNextEventBatch()
        if batch is None:
            break
        got.append(batch.numpy())
    theirs = np.concatenate(got)
    for ours_f, their_f in (("t", "timestamp"), ("x", "x"), ("y", "y"), ("p", "polarity")):
        np.testing.assert_array_equal(theirs[their_f].astype(np.int64), ev[ours_f].astype(np.int64))

    cfg = dv.io.MonoCameraWriter.EventOnlyConfig("DVXplorer_test", (346, 260))
    cfg.compression = {"lz4": dv.CompressionType.LZ4, "lz4high": dv.CompressionType.LZ4_HIGH,
                       "zstd": dv.CompressionType.ZSTD, "zstdhigh": dv.CompressionType.ZSTD_HIGH,
                       "none": dv.CompressionType.NONE}[compression]
    writer = dv.io.MonoCameraWriter(str(tmp_path / "theirs.aedat4"), cfg)
    store = dv.EventStore()
    for t, x, y, p in zip(ev["t"].tolist(), ev["x"].tolist(), ev["y"].tolist(), ev["p"].tolist()):
        store.push_back(t, x, y, bool(p))
    writer.writeEvents(store)
    del writer                                  # closes the file (writes its data table)
    back, w, h = read_events(tmp_path / "theirs.aedat4")
    assert (w, h) == (346, 260)
    np.testing.assert_array_equal(back, ev)


@needs_sample
def test_evt2_and_dat_files_cross_read_with_expelliarmus(tmp_path):
    # an independent reader and writer of Prophesee EVT 2.0 RAW and DAT files (open-neuromorphic's
    # expelliarmus, C): our files read back event for event there, and its DAT files here. (Its
    # EVT 3.0 decoder is not used as a reference: on the shared sample it puts 91 % of the events
    # 4096 µs late, disagreeing with the reference decode.)
    expelliarmus = pytest.importorskip("expelliarmus", reason="expelliarmus (test extra) is not installed")
    ev, w, h = read_events(SAMPLE)
    for encoding, name, opts in (("evt2", "ours.raw", {"evt": 2}), ("dat", "ours.dat", {})):
        write_events(tmp_path / name, ev, w, h, **opts)
        theirs = expelliarmus.Wizard(encoding=encoding).read(str(tmp_path / name))
        for f in "txyp":
            np.testing.assert_array_equal(theirs[f].astype(np.int64), ev[f].astype(np.int64))
    arr = np.empty(ev.size, dtype=[("t", "<i8"), ("x", "<i2"), ("y", "<i2"), ("p", "u1")])
    for f in "txyp":
        arr[f] = ev[f]
    expelliarmus.Wizard(encoding="dat").save(str(tmp_path / "theirs.dat"), arr)
    back, bw, bh = read_events(tmp_path / "theirs.dat")
    assert (bw, bh) == (1280, 720)
    np.testing.assert_array_equal(back, ev)


@needs_sample
def test_our_evt3_files_decode_identically_in_the_pypi_evt3_decoder(tmp_path):
    # the writer behind `arena convert x.raw`, vectors included, against an independent decoder
    evt3 = pytest.importorskip("evt3", reason="evt3 (test extra) is not installed")
    ev, w, h = read_events(SAMPLE)
    write_events(tmp_path / "ours.raw", ev, w, h)
    f = evt3.decode_file(str(tmp_path / "ours.raw"))
    for ours, theirs in (("x", f.x), ("y", f.y), ("p", f.p), ("t", f.t)):
        np.testing.assert_array_equal(np.asarray(theirs).astype(np.int64), ev[ours].astype(np.int64))


@pytest.mark.parametrize("content,message", [
    (bytes(range(256)) * 40, "binary data, not a text CSV"),        # 10 KB, its first line ~4 KB of bytes
    (b"a" * 20_000, "first line is longer than 4096 bytes"),          # no newline at all
    (b"xx,yy,foo," + b"b" * 3000 + b"\n1,2,3,4\n", "must name columns x, y, p, t"),
])
def test_a_file_that_is_not_a_csv_is_one_short_error(tmp_path, content, message):
    """A binary or garbled .csv gives one short line (it printed a 4 KB header back), and a file
    with no newline is not read whole to find its first line."""
    import subprocess

    from tests.conftest import arena_cmd

    path = tmp_path / "in.csv"
    path.write_bytes(content)
    with pytest.raises(FormatError, match=message) as err:
        read_events(path)
    assert len(str(err.value)) < len(str(path)) + 200
    r = subprocess.run(arena_cmd("convert", str(path), str(tmp_path / "out.npz")), capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 2 and message in r.stderr and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and len(r.stderr) < 400


# --- hostile recordings (issue 20): one error type, no allocation beyond the file, values
# range-checked, anything skipped counted and reported ---

import struct  # noqa: E402
import subprocess  # noqa: E402
import warnings  # noqa: E402

from arena.formats.base import SkippedData  # noqa: E402


def _read_quietly(path, **opts):
    """``(events, reader)`` with the reader's SkippedData warnings collected in ``reader.warned``."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", SkippedData)
        with iter_events(path, **opts) as reader:
            ev = reader.read_all()
    reader.warned = [w.message for w in caught if issubclass(w.category, SkippedData)]
    return ev, reader


def _npy_with_header(path, header: str, body: bytes = b"") -> None:
    h = header.encode("latin-1")
    h += b" " * (-(10 + len(h) + 1) % 64) + b"\n"
    path.write_bytes(b"\x93NUMPY\x01\x00" + struct.pack("<H", len(h)) + h + body)


def test_npy_header_claiming_2_to_the_40_events_is_a_format_error(tmp_path):
    # np.load allocated shape x itemsize (13 TB) before reading: MemoryError
    descr = "[('x', '<u2'), ('y', '<u2'), ('p', 'u1'), ('t', '<i8')]"
    _npy_with_header(tmp_path / "big.npy", f"{{'descr': {descr}, 'fortran_order': False, 'shape': ({1 << 40},), }}",
                     bytes(13 * 10))
    with pytest.raises(FormatError, match="larger than"):
        read_events(tmp_path / "big.npy")
    _npy_with_header(tmp_path / "tok.npy", "{'descr': ((")     # numpy's header tokenizer: TokenError
    with pytest.raises(FormatError, match="numpy"):
        read_events(tmp_path / "tok.npy")


@pytest.mark.parametrize("shape", ["(0,)", "(200,)"])
def test_npy_header_shape_smaller_than_its_data_is_reported_not_silent(tmp_path, shape):
    # a damaged digit of the shape ("(2000,)" -> "(-000,)" or "(200 ,)") read 0 or 200 of 2000
    # events with exit 0 and no word
    ev = _random_events(2000, seed=24)
    write_events(tmp_path / "ok.npy", ev, 1280, 720)
    data = (tmp_path / "ok.npy").read_bytes()
    assert b"'shape': (2000,)" in data
    (tmp_path / "bad.npy").write_bytes(data.replace(b"'shape': (2000,)", b"'shape': " + shape.encode().ljust(7)))
    out, reader = _read_quietly(tmp_path / "bad.npy")
    kept = int(shape[1:-2])
    np.testing.assert_array_equal(out, ev[:kept] if kept else out[:0])
    assert reader.skipped == 13 * (2000 - kept)
    assert [(w.count, w.unit) for w in reader.warned] == [(13 * (2000 - kept), "bytes")]
    assert "not read" in str(reader.warned[0])
    out, reader = _read_quietly(tmp_path / "ok.npy")   # numpy's own file: nothing after its data
    assert out.size == 2000 and reader.skipped == 0 and reader.warned == []


def test_damaged_npz_files_are_format_errors(tmp_path):
    ev = _random_events(2000, seed=20)
    write_events(tmp_path / "ok.npz", ev, 1280, 720)
    data = bytearray((tmp_path / "ok.npz").read_bytes())
    for i, pos in enumerate((200, 600, 1500)):             # inside compressed members: zlib / CRC errors
        bad = data.copy()
        bad[pos:pos + 8] = b"\xff" * 8
        (tmp_path / f"b{i}.npz").write_bytes(bytes(bad))
        with pytest.raises(FormatError):
            read_events(tmp_path / f"b{i}.npz")
    np.savez(tmp_path / "w.npz", x=ev["x"], y=ev["y"], p=ev["p"], t=ev["t"], width=np.array([1, 2, 3]), height=720)
    with pytest.raises(FormatError, match="width must be one integer"):   # int() of it: TypeError
        read_events(tmp_path / "w.npz")
    np.savez(tmp_path / "neg.npz", x=ev["x"], y=ev["y"], p=ev["p"], t=ev["t"], width=-1280, height=720)
    with pytest.raises(FormatError, match="outside 1..65535"):
        read_events(tmp_path / "neg.npz")


def test_npz_member_declaring_more_than_deflate_can_expand_is_refused(tmp_path):
    import zipfile

    ev = _random_events(100, seed=21)
    write_events(tmp_path / "ok.npz", ev, 1280, 720)
    data = bytearray((tmp_path / "ok.npz").read_bytes())
    with zipfile.ZipFile(tmp_path / "ok.npz") as zf:
        info = zf.getinfo("x.npy")
    # the uncompressed size in the central directory entry of x.npy
    cd = data.rfind(b"PK\x01\x02", 0, data.find(b"x.npy", data.find(b"PK\x01\x02")) + 1)
    struct.pack_into("<I", data, cd + 24, 1 << 31)
    (tmp_path / "bomb.npz").write_bytes(bytes(data))
    with pytest.raises(FormatError, match="decompression bomb"):
        read_events(tmp_path / "bomb.npz")
    assert info.compress_size < 1000


@pytest.mark.parametrize("ext", [".npz", ".npy", ".csv"])
def test_coordinates_beyond_16_bits_and_polarity_2_are_dropped_and_counted_not_wrapped(tmp_path, ext):
    x = np.array([1, 65636, 3, 5, -4], np.int64)    # 65636 wrapped to x = 100
    y = np.array([2, 2, 4, 6, 1], np.int64)
    p = np.array([1, 1, 2, 0, 1], np.int64)         # polarity 2 passed through (RAW: a vector word)
    t = np.array([100, 200, 300, 400, 500], np.int64)
    path = tmp_path / f"in{ext}"
    if ext == ".npz":
        np.savez(path, x=x, y=y, p=p, t=t, width=1280, height=720)
    elif ext == ".npy":
        arr = np.empty(5, [("x", "<i8"), ("y", "<i8"), ("p", "<i8"), ("t", "<i8")])
        arr["x"], arr["y"], arr["p"], arr["t"] = x, y, p, t
        np.save(path, arr)
    else:
        path.write_text("x,y,p,t\n" + "".join(f"{a},{b},{c},{d}\n" for a, b, c, d in zip(x, y, p, t)))
    ev, reader = _read_quietly(path, width=1280, height=720)
    assert ev.tolist() == [(1, 2, 1, 100), (5, 6, 0, 400)]
    assert reader.invalid == 3 and sum(w.count for w in reader.warned) == 3
    write_events(tmp_path / "out.raw", ev, 1280, 720)
    np.testing.assert_array_equal(read_events(tmp_path / "out.raw")[0], ev)


def test_csv_value_beyond_64_bits_is_a_format_error(tmp_path):
    (tmp_path / "big.csv").write_text("1,2,1,100\n3,4,0,99999999999999999999\n")
    with pytest.raises(FormatError, match="64 bits"):
        read_events(tmp_path / "big.csv")


def _aedat4(tmp_path, name="x.aedat4", n=3000, compression="lz4", packet_events=1000, width=1280):
    ev = _random_events(n, seed=22)
    from arena.formats.aedat4 import Aedat4Writer

    with Aedat4Writer(tmp_path / name, width, 720, compression=compression, packet_events=packet_events) as w:
        w.write(ev)
    return tmp_path / name, ev


def _aedat4_packets(data: bytes) -> list[tuple[int, int]]:
    """(offset, size) of each packet of an AEDAT4 file our writer made."""
    pos = 14 + 4 + struct.unpack_from("<I", data, 14)[0]
    out = []
    while pos < len(data):
        size = struct.unpack_from("<i", data, pos + 4)[0]
        out.append((pos, size))
        pos += 8 + size
    return out


def test_aedat4_negative_packet_size_is_a_format_error(tmp_path):
    path, _ = _aedat4(tmp_path)
    data = bytearray(path.read_bytes())
    pos, _ = _aedat4_packets(bytes(data))[1]
    struct.pack_into("<i", data, pos + 4, -5)          # f.read(-5): ValueError from chunks()
    path.write_bytes(bytes(data))
    with pytest.raises(FormatError, match="truncated AEDAT4 packet"):
        read_events(path)
    struct.pack_into("<i", data, pos + 4, 2**31 - 1)   # read() allocated the 2 GB first
    path.write_bytes(bytes(data))
    with pytest.raises(FormatError, match="truncated AEDAT4 packet"):
        read_events(path)


@pytest.mark.parametrize("compression", ["lz4", "zstd"])
def test_aedat4_packet_that_does_not_decompress_is_counted_and_reported(tmp_path, compression):
    path, ev = _aedat4(tmp_path, compression=compression)
    data = bytearray(path.read_bytes())
    pos, size = _aedat4_packets(bytes(data))[1]
    data[pos + 8: pos + 12] = b"\xa5" * 4         # the compressed frame's magic
    path.write_bytes(bytes(data))
    out, reader = _read_quietly(path)
    np.testing.assert_array_equal(out, np.concatenate([ev[:1000], ev[2000:]]))
    assert reader.skipped == reader.skipped_packets == 1
    assert [(w.count, w.unit) for w in reader.warned] == [(1, "corrupt packets")]
    assert f"byte {pos}" in str(reader.warned[0])


def test_aedat4_damaged_packet_fields_are_counted_not_silent(tmp_path):
    # found by flipping every header and first-packet byte of an uncompressed file: each of these
    # read fewer events with no word (a damaged stream id dropped the packet as "another stream",
    # a lowered element count or a damaged table read 0..999 of 1000 events)
    path, ev = _aedat4(tmp_path, compression="none")
    clean = path.read_bytes()
    pos, size = _aedat4_packets(clean)[1]
    body = pos + 8                                  # the packet's FlatBuffer (uncompressed)
    cases = [
        # (byte offset, int32 value, warning unit, events kept)
        (pos, 7, "packets of undescribed streams", "skip"),      # stream id 7: not in the header
        (body, struct.unpack_from("<I", clean, body)[0] + 16, "corrupt packets", "skip"),  # size prefix
        (body + 4, 0, "corrupt packets", "skip"),                # root offset: no elements field
        (body + 28, 990, "corrupt packets", "skip"),             # element count 990 of 1000
    ]
    assert struct.unpack_from("<I", clean, body + 28)[0] == 1000     # the layout our writer makes
    for offset, value, unit, _ in cases:
        data = bytearray(clean)
        struct.pack_into("<I", data, offset, value)
        path.write_bytes(bytes(data))
        out, reader = _read_quietly(path)
        np.testing.assert_array_equal(out, np.concatenate([ev[:1000], ev[2000:]]))
        assert reader.skipped == 1 and [(w.count, w.unit) for w in reader.warned] == [(1, unit)], (offset, value)
        assert f"byte {pos}" in str(reader.warned[0])
    path.write_bytes(clean)                         # and the clean file reads whole, with no word
    out, reader = _read_quietly(path)
    np.testing.assert_array_equal(out, ev)
    assert reader.skipped == 0 and reader.warned == []


def _xxh32(data: bytes, seed: int = 0) -> int:
    """xxHash32 (LZ4 frame header checksums)."""
    p1, p2, p3, p4, p5, m = 2654435761, 2246822519, 3266489917, 668265263, 374761393, 0xFFFFFFFF

    def rotl(x, r):
        return ((x << r) | (x >> (32 - r))) & m

    n, i = len(data), 0
    if n >= 16:
        v = [(seed + p1 + p2) & m, (seed + p2) & m, seed & m, (seed - p1) & m]
        while i + 16 <= n:
            for k in range(4):
                v[k] = rotl((v[k] + struct.unpack_from("<I", data, i)[0] * p2) & m, 13) * p1 & m
                i += 4
        h = (rotl(v[0], 1) + rotl(v[1], 7) + rotl(v[2], 12) + rotl(v[3], 18)) & m
    else:
        h = (seed + p5) & m
    h = (h + n) & m
    while i + 4 <= n:
        h = rotl((h + struct.unpack_from("<I", data, i)[0] * p3) & m, 17) * p4 & m
        i += 4
    while i < n:
        h = rotl((h + data[i] * p5) & m, 11) * p1 & m
        i += 1
    h ^= h >> 15
    h = h * p2 & m
    h ^= h >> 13
    h = h * p3 & m
    return h ^ (h >> 16)


def test_aedat4_packet_declaring_a_huge_size_is_skipped_without_allocating_it(tmp_path):
    import lz4.frame

    path, ev = _aedat4(tmp_path, compression="lz4")
    data = path.read_bytes()
    pos, size = _aedat4_packets(data)[0]
    # an LZ4 frame whose header declares 2^40 bytes of content: lz4.frame.decompress allocated it
    frame = bytearray(lz4.frame.compress(b"\0" * 64, store_size=True))
    assert frame[14] == _xxh32(bytes(frame[4:14])) >> 8 & 0xFF      # the header checksum
    struct.pack_into("<Q", frame, 6, 1 << 40)
    frame[14] = _xxh32(bytes(frame[4:14])) >> 8 & 0xFF
    body = bytes(frame)
    bomb = data[:pos] + struct.pack("<ii", 0, len(body)) + body + data[pos + 8 + size:]
    path.write_bytes(bomb)
    out, reader = _read_quietly(path)
    assert reader.skipped == 1 and out.size == 2000


def test_aedat4_damaged_data_table_position_is_an_error_not_zero_events(tmp_path):
    path, _ = _aedat4(tmp_path)
    data = bytearray(path.read_bytes())
    i = data.find(struct.pack("<q", -1))                 # the header's dataTablePosition
    for value, match in ((20, "before the first packet"), (len(data) + 100, "truncated")):
        struct.pack_into("<q", data, i, value)
        path.write_bytes(bytes(data))
        with pytest.raises(FormatError, match=match):
            read_events(path)
    pos, _ = _aedat4_packets(bytes(data))[1]
    struct.pack_into("<q", data, i, pos + 5)             # inside a packet
    path.write_bytes(bytes(data))
    with pytest.raises(FormatError, match="runs over"):
        read_events(path)


@pytest.mark.parametrize("ext", [".aedat4", ".raw", ".dat"])
def test_negative_or_absurd_sensor_sizes_are_format_errors(tmp_path, ext):
    path = tmp_path / f"x{ext}"
    ev = _random_events(100, seed=23)
    if ext == ".aedat4":
        _aedat4(tmp_path, name=path.name, width=-5)      # the writer puts sizeX -5 in the XML
    elif ext == ".raw":
        write_events(path, ev, 1280, 720)
        path.write_bytes(path.read_bytes().replace(b"width=1280", b"width=-1280"))
    else:
        write_events(path, ev, 1280, 720)
        path.write_bytes(path.read_bytes().replace(b"% Width 1280", b"% Width 99999999"))
    with pytest.raises(FormatError, match="outside 1..65535"):
        read_events(path)


def test_dat_polarity_nibble_other_than_0_or_1_is_dropped_and_counted(tmp_path):
    ev = _random_events(100, seed=24)
    write_events(tmp_path / "x.dat", ev, 1280, 720)
    data = bytearray((tmp_path / "x.dat").read_bytes())
    start = len(data) - 100 * 8
    struct.pack_into("<I", data, start + 4, struct.unpack_from("<I", data, start + 4)[0] | (3 << 28))
    (tmp_path / "x.dat").write_bytes(bytes(data))
    out, reader = _read_quietly(tmp_path / "x.dat")
    assert reader.invalid == 1
    np.testing.assert_array_equal(out, ev[1:])


def test_evt3_vector_run_past_x_2047_is_not_wrapped_into_the_sensor():
    # 5462 empty VECT_12 words move the vector base past 65535: x wrapped to 8
    words = np.array([0x8000, 0x6000, 0x0001, 0x3000] + [0x4000] * 5462 + [0x4001], "<u2")
    ev = Evt3Decoder().feed(words.tobytes())
    assert ev.size == 1 and ev["x"][0] >= 2048


def test_raw_words_before_time_and_a_cut_off_word_are_counted_and_reported(tmp_path):
    ev = _random_events(50, seed=25)
    write_events(tmp_path / "x.raw", ev, 1280, 720)
    data = (tmp_path / "x.raw").read_bytes()
    hsize = parse_raw_header(data).size
    early = np.array([0x0003, 0x2005, 0x2006], "<u2").tobytes()    # Y, two events before any TIME_HIGH
    (tmp_path / "x.raw").write_bytes(data[:hsize] + early + data[hsize:] + b"\x01")
    out, reader = _read_quietly(tmp_path / "x.raw")
    np.testing.assert_array_equal(out, ev)
    assert reader.skipped == 3
    assert sorted((w.unit, w.count) for w in reader.warned) == [("bytes of a cut-off word", 1),
                                                                ("event words without a time", 2)]


def test_arena_convert_reports_skipped_packets_and_strict_fails(tmp_path):
    from tests.conftest import arena_cmd

    path, ev = _aedat4(tmp_path)
    data = bytearray(path.read_bytes())
    pos, size = _aedat4_packets(bytes(data))[1]
    data[pos + 8: pos + 12] = b"\xa5" * 4         # the compressed frame's magic
    path.write_bytes(bytes(data))
    out = tmp_path / "out.npz"
    r = subprocess.run(arena_cmd("convert", str(path), str(out)), capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert "2000 events" in r.stdout and "1 corrupt packets skipped" in r.stdout
    assert "warning" in r.stderr and "Traceback" not in r.stderr
    assert read_events(out)[0].size == 2000
    out.unlink()
    r = subprocess.run(arena_cmd("convert", str(path), str(out), "--strict"), capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 2 and "--strict" in r.stderr and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not out.exists()


# --- the CSV reader at disk speed (issue 22): one numba kernel over the bytes, streaming in
# blocks of whole lines, every error naming its line ---

def _csv_reference(text: str) -> list[tuple[int, int, int, int]]:
    """Events of a header-less ``x,y,p,t`` CSV parsed line by line in Python (p -1 read as 0)."""
    rows = []
    for line in text.splitlines():
        if line.strip():
            x, y, p, t = (int(v) for v in line.split(","))
            rows.append((x, y, 1 if p > 0 else 0, t))
    return rows


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**32), st.integers(1, 3000), st.sampled_from(["\n", "\r\n"]),
       st.booleans(), st.integers(1, 40))
def test_csv_reader_matches_a_line_by_line_parse_across_block_boundaries(seed, n, eol, loose, chunk_events):
    """Spaces around fields, signs, leading zeros, blank lines and CRLF: the same events as a
    Python parse of each line, whatever the block size (8 KiB blocks here: lines are cut
    at every position)."""
    rng = np.random.default_rng(seed)
    x, y = rng.integers(0, 65535, n), rng.integers(0, 65535, n)
    p, t = rng.integers(-1, 2, n), rng.integers(-2**63, 2**63 - 1, n, dtype=np.int64, endpoint=True)
    lines = []
    for a, b, c, d in zip(x, y, p, t):
        if loose and rng.random() < 0.3:
            lines.append(f" {a:05d} ,\t+{b}, {c} ,{d} ")
        else:
            lines.append(f"{a},{b},{c},{d}")
        if loose and rng.random() < 0.05:
            lines.append("")
    text = eol.join(lines) + (eol if rng.random() < 0.5 else "")
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "in.csv"
        path.write_bytes(text.encode())
        ev, reader = _read_quietly(path, chunk_events=chunk_events, width=65535, height=65535)
    assert ev.tolist() == _csv_reference(text) and reader.invalid == 0


def test_csv_error_names_the_exact_line_in_any_block(tmp_path):
    good = "".join(f"{i % 640},{i % 480},{i % 2},{i * 10}\n" for i in range(3000))
    (tmp_path / "a.csv").write_text("x,y,p,t\n" + good + "1,2,x,4\n" + good)
    with pytest.raises(FormatError, match=r"line 3002 of the CSV has a non-numeric or empty value"):
        read_events(tmp_path / "a.csv", chunk_events=1, width=640, height=480)
    (tmp_path / "b.csv").write_text(good + "1,2,1,99999999999999999999\n")
    with pytest.raises(FormatError, match=r"line 3001 of the CSV has a value beyond 64 bits"):
        read_events(tmp_path / "b.csv", chunk_events=7, width=640, height=480)


@pytest.mark.parametrize("content,line", [
    (b"1,2,1\n3,4,0,200,5\n", 1),        # 8 values in all: read as 2 (wrong) events before
    (b"1,2,1,100\n3,4,0,200,\n", 2),    # a trailing comma: an empty fifth column
    (b"1,2,1,100\n\n5,6\n", 3),
])
def test_csv_every_line_must_have_4_columns(tmp_path, content, line):
    (tmp_path / "in.csv").write_bytes(content)
    with pytest.raises(FormatError, match=rf"line {line} of the CSV does not have 4 columns"):
        read_events(tmp_path / "in.csv", width=640, height=480)
    (tmp_path / "empty.csv").write_bytes(b"1,2,1,100\n3,4,,200\n")
    with pytest.raises(FormatError, match=r"line 2 of the CSV has a non-numeric or empty value"):
        read_events(tmp_path / "empty.csv", width=640, height=480)


def test_csv_line_longer_than_a_block_is_an_error_not_read_whole(tmp_path):
    """Memory stays bounded by the block: a line that never ends (spaces are legal around a
    field) is refused at the block's size instead of being gathered."""
    (tmp_path / "in.csv").write_bytes(b"1,2,1,3\n4,5,0,6" + b" " * 100_000 + b"\n7,8,1,9\n")
    with pytest.raises(FormatError, match=r"line 2 of the CSV is longer than 8192 bytes"):
        read_events(tmp_path / "in.csv", chunk_events=1, width=640, height=480)


def test_csv_writer_output_is_the_papers_text_for_extreme_values(tmp_path):
    ev = make_events([0, 65534, 7, 8], [479, 0, 1, 2], [1, 0, 1, 0], [-2**63, -1, 0, 2**63 - 1])
    write_events(tmp_path / "x.csv", ev, 65535, 480)
    expected = "x,y,p,t_us\n0,479,1,-9223372036854775808\n65534,0,0,-1\n7,1,1,0\n8,2,0,9223372036854775807\n"
    assert (tmp_path / "x.csv").read_text() == expected
    assert read_events(tmp_path / "x.csv", width=65535, height=480)[0].tolist() == ev.tolist()


def test_csv_reader_reads_at_disk_speed(tmp_path):
    """1 M events (18 MB) in well under a quarter of a second of CPU: the numpy text split it
    replaced took ~0.8 s (1.2 M ev/s), the kernel ~0.05 s (20+ M ev/s) on this machine."""
    import time

    ev = _random_events(1_000_000, seed=31)
    write_events(tmp_path / "big.csv", ev, 1280, 720)
    read_events(tmp_path / "big.csv", width=1280, height=720)           # numba's cache, the page cache
    best = float("inf")
    for _ in range(3):
        c0 = time.process_time()
        out, _, _ = read_events(tmp_path / "big.csv", width=1280, height=720)
        best = min(best, time.process_time() - c0)
    np.testing.assert_array_equal(out, ev)
    assert best < 0.25, f"{best:.3f} s of CPU for 1 M events"


def test_csv_kernels_are_compiled_by_the_demo_warmup(tmp_path, monkeypatch):
    """``arena demo --prepare`` (demo.warmup) compiles the CSV kernels too, so `arena track
    --input X.csv` compiles nothing at start once it ran."""
    import os
    import subprocess
    import sys

    from demo.warmup import KERNELS, kernels_cached

    csv_kernels = ("arena.formats.csvfile:_parse_lines", "arena.formats.csvfile:_format_lines")
    assert set(csv_kernels) <= set(KERNELS)
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    assert not kernels_cached(csv_kernels)
    subprocess.run([sys.executable, "-c", "from demo.warmup import compile_csv; compile_csv()"], check=True,
                   timeout=300, env={**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)})
    assert kernels_cached(csv_kernels)


# --- readers that said nothing (issue 20, red team round 3) ---

@pytest.mark.parametrize("evt", [3, 2])
def test_raw_words_of_no_known_type_are_counted_and_reported(tmp_path, evt):
    ev = _random_events(100, seed=40)
    write_events(tmp_path / "ok.raw", ev, 1280, 720, evt=evt)
    data = (tmp_path / "ok.raw").read_bytes()
    hdr = data.split(b"% end\n")[0] + b"% end\n"
    (tmp_path / "ff.raw").write_bytes(hdr + b"\xff" * 100_000)      # orphan CONTINUED words only
    out, reader = _read_quietly(tmp_path / "ff.raw")
    words = 100_000 * 8 // (16 if evt == 3 else 32)
    assert out.size == 0 and reader.skipped == words
    assert sum(w.count for w in reader.warned if w.unit == "words of no known type") == words
    # after the events, an undefined type (EVT 3.0 0x1, EVT 2.0 0x3) and an OTHERS word with
    # its CONTINUED word (read by no decoder, but defined: not counted)
    word = "<u2" if evt == 3 else "<u4"
    sh = 12 if evt == 3 else 28
    undefined = 0x1 if evt == 3 else 0x3
    tail = np.array([undefined << sh, 0xE << sh, 0xF << sh, 0xF << sh], word).tobytes()
    (tmp_path / "tail.raw").write_bytes(data + tail)
    out, reader = _read_quietly(tmp_path / "tail.raw")
    np.testing.assert_array_equal(out, read_events(tmp_path / "ok.raw")[0])
    assert reader.skipped == 1
    _, ok = _read_quietly(tmp_path / "ok.raw")
    assert ok.skipped == 0 and not ok.warned


def test_the_real_evt3_sample_has_no_unknown_words():
    path = Path(__file__).resolve().parents[3] / "shared" / "data" / "evt3_sample.raw"
    if not path.exists():
        pytest.skip("no shared sample")
    out, reader = _read_quietly(path)
    assert out.size == 219_596 and reader.skipped == 0


@pytest.mark.parametrize("ext,old,new,match", [
    (".dat", b"% Width 1280", b"% Width 0", "outside 1..65535"),        # was 1280 x 720
    (".dat", b"% Height 720", b"% Height 7_20", "not integers"),        # was 720
    (".dat", b"% Height 720\n", b"", "Width without Height"),
    (".raw", b"width=1280", b"width=0", "outside 1..65535"),            # was the geometry line's
    (".raw", b"EVT3;height=720;width=1280\n% geometry 1280x720", b"EVT3\n% geometry 1280x720x3", "WIDTHxHEIGHT"),
])
def test_header_sizes_that_are_zero_or_not_plain_decimals_are_refused(tmp_path, ext, old, new, match):
    path = tmp_path / f"x{ext}"
    write_events(path, _random_events(50, seed=41), 1280, 720)
    data = path.read_bytes()
    assert old in data
    path.write_bytes(data.replace(old, new, 1))
    with pytest.raises(FormatError, match=match):
        read_events(path)


def test_raw_width_height_lines_must_be_plain_decimals():
    with pytest.raises(FormatError, match="not a number"):
        parse_raw_header(b"% evt 3.0\n% width 640\n% height 4_80\n")     # int() took it: 480
    assert (parse_raw_header(b"% evt 3.0\n% width 640\n% height 480 \n").height) == 480


def test_csv_times_going_backwards_are_counted_and_reported_or_refused_with_strict(tmp_path):
    lines = [(1, 2, 1, 100), (3, 4, 0, 200), (5, 6, 1, 150), (7, 8, 0, 300), (9, 9, 1, 10)]
    path = tmp_path / "back.csv"
    path.write_text("x,y,p,t\n" + "".join(f"{a},{b},{c},{d}\n" for a, b, c, d in lines))
    ev, reader = _read_quietly(path, chunk_events=2)     # one step back inside a block, one across
    assert ev.tolist() == lines and reader.unordered == 2
    assert sum(w.count for w in reader.warned if w.unit.startswith("events out of time order")) == 2
    with warnings.catch_warnings():
        warnings.simplefilter("error", SkippedData)
        with pytest.raises(FormatError, match="backwards"):
            read_events(path)
    path.write_text("".join(f"{a},{b},{c},{d}\n" for a, b, c, d in sorted(lines, key=lambda r: r[3])))
    _, ok = _read_quietly(path)
    assert ok.unordered == 0 and not ok.warned

"""Event-window codec: bytes per event and M events/s (encode, decode) of ``planes-zstd/1``
against EVT 3.0 as the camera sends it, an AEDAT4-ZSTD packet and plain zstd of the event array.

Data: the shared real sample (one dense 8.8 ms burst, 219 596 events) and simulator recordings
(3 robots driving circles, 640 x 480) cut into the edge's 10 ms windows, as recorded and after the
edge's background-activity filter. Run: ``python bench/bench_codec.py [--seconds S]``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
import zstandard

from arena.codec import DEFAULT_CODEC, LOSSY_CODEC, decode, encode
from arena.events import EVENT_DTYPE, as_events
from arena.formats.aedat4 import _AEDAT_EVENT, _packet_buffer
from arena.formats.raw import parse_raw_header

SAMPLE = Path(__file__).resolve().parents[2] / "shared" / "data" / "evt3_sample.raw"


def windows_of(ev: np.ndarray, slice_us: int = 10_000) -> list[np.ndarray]:
    t = ev["t"]
    edges = np.arange(int(t[0]) - int(t[0]) % slice_us, int(t[-1]) + slice_us, slice_us)
    idx = np.searchsorted(t, edges)
    return [ev[a:b] for a, b in zip(idx[:-1], idx[1:])]


def measure(windows, enc, dec=None, repeat=5):
    """(bytes/event, encode M ev/s, decode M ev/s) over all windows, best of ``repeat`` CPU times."""
    n = sum(w.size for w in windows)
    blobs = [enc(w) for w in windows]
    size = sum(len(b) for b in blobs)
    te = td = float("inf")
    for _ in range(repeat):
        c = time.process_time()
        for w in windows:
            enc(w)
        te = min(te, time.process_time() - c)
        if dec is not None:
            c = time.process_time()
            for b, w in zip(blobs, windows):
                dec(b, w)
            td = min(td, time.process_time() - c)
    return size / n, n / te / 1e6, (n / td / 1e6 if dec is not None else float("nan"))


def aedat4_zstd(w):
    return zstandard.ZstdCompressor(level=3).compress(_packet_buffer(w))


def aedat4_zstd_dec(b, w):
    buf = zstandard.ZstdDecompressor().decompressobj().decompress(b)
    return np.frombuffer(buf, _AEDAT_EVENT, offset=32)


def zstd_array(w):
    return zstandard.ZstdCompressor(level=3).compress(w.tobytes())


def zstd_array_dec(b, w):
    return np.frombuffer(zstandard.ZstdDecompressor().decompressobj().decompress(b), EVENT_DTYPE)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=2.0, help="simulated seconds (default 2)")
    args = ap.parse_args()

    datasets: list[tuple[str, list[np.ndarray], float | None]] = []
    if SAMPLE.exists():
        raw = SAMPLE.read_bytes()
        hdr = parse_raw_header(raw)
        from arena.formats.evt3 import decode_evt3

        ev = decode_evt3(raw[hdr.size:])
        datasets.append(("real sample", [ev], (len(raw) - hdr.size) / ev.size))
    from simulator.evt3 import canonical_order, encode_evt3
    from simulator.scenarios import Scenario, generate

    from camera_edge.filters import BackgroundActivityFilter

    rec = generate(Scenario(n_robots=3, pattern="circle", duration_s=args.seconds, seed=1))
    sim = canonical_order(as_events(rec.events))
    evt3_bpe = len(encode_evt3(sim)) / sim.size
    datasets.append(("sim 10 ms", windows_of(sim), evt3_bpe))
    filt = BackgroundActivityFilter(rec.width, rec.height, dt_us=10_000)(sim)
    datasets.append(("sim 10 ms, denoised", windows_of(filt), len(encode_evt3(filt)) / filt.size))

    ok = True
    print(f"codec benchmark, CPU time of one thread (machine: {os.cpu_count()} cores, "
          f"load {os.getloadavg()[0]:.1f})")
    hdr = f"{'data':<22}{'codec':<20}{'B/ev':>7}{'enc M/s':>9}{'dec M/s':>9}   {'ours B/ev / theirs':>18}"
    print(hdr)
    for name, wins, evt3_bpe in datasets:
        for w in wins:
            assert np.array_equal(decode(DEFAULT_CODEC, encode(w, t_ref_us=int(w["t"][0]) if w.size else 0),
                                         w.size), w)
        ours = measure(wins, lambda w: encode(w), lambda b, w: decode(DEFAULT_CODEC, b, w.size))
        lossy = measure(wins, lambda w: encode(w, LOSSY_CODEC), lambda b, w: decode(LOSSY_CODEC, b, w.size))
        rows = [(DEFAULT_CODEC, ours), (LOSSY_CODEC + " (lossy)", lossy),
                ("EVT 3.0 (camera)", (evt3_bpe, float("nan"), float("nan"))),
                ("AEDAT4 packet+zstd", measure(wins, aedat4_zstd, aedat4_zstd_dec)),
                ("zstd(event array)", measure(wins, zstd_array, zstd_array_dec))]
        for codec, (bpe, e, d) in rows:
            ratio = "" if codec.startswith("planes") else f"{ours[0] / bpe:17.2f}x"
            print(f"{name:<22}{codec:<20}{bpe:7.3f}{e:9.1f}{d:9.1f}   {ratio:>18}")
        ok &= ours[0] <= 1.6 and ours[1] >= 30 and ours[2] >= 30
    print("target: <= 1.6 B/ev, encode and decode >= 30 M ev/s per core:", "met" if ok else "NOT met on every data set")
    return 0


if __name__ == "__main__":
    sys.exit(main())

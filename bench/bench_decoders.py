"""Decoder throughput on one core: ours (numba, streaming) vs the PyPI `evt3` decoder and a naive
Python loop (EVT 3.0), and vs a plain numpy decoder and a naive loop (EVT 2.0).

Data: the shared real EVT 3.0 sample (../shared/data/evt3_sample.raw, 219 596 events) and the
same events written as EVT 2.0. Run: ``python bench/bench_decoders.py [--repeat N]``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

from arena.events import EVENT_DTYPE, as_events
from arena.formats.evt2 import Evt2Decoder, encode_evt2
from arena.formats.evt3 import Evt3Decoder
from arena.formats.raw import parse_raw_header

SAMPLE = Path(__file__).resolve().parents[2] / "shared" / "data" / "evt3_sample.raw"


def best_rate(fn, n_events: int, repeat: int) -> float:
    """Best-of-``repeat`` throughput in M events/s of CPU time (one thread)."""
    best = float("inf")
    for _ in range(repeat):
        c0 = time.process_time()
        fn()
        best = min(best, time.process_time() - c0)
    return n_events / max(best, 1e-9) / 1e6


def naive_evt3(words) -> list:
    """Straightforward per-word Python decoder (the baseline a lab writes first)."""
    out = []
    y = th = tl = bx = pol = 0
    for w in words:
        typ = w >> 12
        if typ == 0:
            y = w & 0x7FF
        elif typ == 2:
            out.append(((w & 0x7FF), y, (w >> 11) & 1, (th << 12) | tl))
        elif typ == 3:
            bx, pol = w & 0x7FF, (w >> 11) & 1
        elif typ in (4, 5):
            nb = 12 if typ == 4 else 8
            for b in range(nb):
                if (w >> b) & 1:
                    out.append((bx + b, y, pol, (th << 12) | tl))
            bx += nb
        elif typ == 6:
            tl = w & 0xFFF
        elif typ == 8:
            th = w & 0xFFF
    return out


def naive_evt2(words) -> list:
    out = []
    th = 0
    for w in words:
        typ = w >> 28
        if typ <= 1:
            out.append(((w >> 11) & 0x7FF, w & 0x7FF, typ, (th << 6) | ((w >> 22) & 0x3F)))
        elif typ == 8:
            th = w & 0xFFFFFFF
    return out


def numpy_evt2(data: bytes) -> np.ndarray:
    """A vectorised numpy EVT 2.0 decoder (no streaming state, no wraps)."""
    w = np.frombuffer(data, "<u4")
    typ = w >> 28
    is_th = typ == 8
    th_idx = np.maximum.accumulate(np.where(is_th, np.arange(w.size), 0))
    th = (w[th_idx] & 0xFFFFFFF).astype(np.int64)
    cd = typ <= 1
    ev = np.empty(int(cd.sum()), EVENT_DTYPE)
    wc = w[cd]
    ev["x"] = (wc >> 11) & 0x7FF
    ev["y"] = wc & 0x7FF
    ev["p"] = typ[cd]
    ev["t"] = (th[cd] << 6) | ((wc >> 22) & 0x3F)
    return ev


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=10, help="timing repeats (best is kept)")
    args = ap.parse_args()
    if not SAMPLE.exists():
        print(f"shared sample not found at {SAMPLE}", file=sys.stderr)
        return 2
    raw = SAMPLE.read_bytes()
    body = raw[parse_raw_header(raw).size:]
    ours = Evt3Decoder().feed(body)
    n = ours.size
    rows = []

    r_ours3 = best_rate(lambda: Evt3Decoder().feed(body), n, args.repeat)
    try:
        import evt3

        theirs = evt3.decode_bytes(body)
        assert np.array_equal(np.asarray(theirs.t), ours["t"]) and np.array_equal(np.asarray(theirs.x), ours["x"])
        r_evt3 = best_rate(lambda: evt3.decode_bytes(body), n, args.repeat)
    except ImportError:
        r_evt3 = float("nan")
    words3 = np.frombuffer(body, "<u2").tolist()
    k = len(words3) // 10
    n_naive = len(naive_evt3(words3[:k]))
    r_naive3 = best_rate(lambda: naive_evt3(words3[:k]), n_naive, 1)
    rows.append(("EVT 3.0", r_ours3, [("PyPI evt3", r_evt3), ("python loop", r_naive3)]))

    body2 = encode_evt2(as_events(ours))
    assert np.array_equal(Evt2Decoder().feed(body2), ours)
    r_ours2 = best_rate(lambda: Evt2Decoder().feed(body2), n, args.repeat)
    assert np.array_equal(numpy_evt2(body2), ours)
    r_np2 = best_rate(lambda: numpy_evt2(body2), n, args.repeat)
    words2 = np.frombuffer(body2, "<u4").tolist()
    k2 = len(words2) // 10
    n_naive2 = len(naive_evt2(words2[:k2]))
    r_naive2 = best_rate(lambda: naive_evt2(words2[:k2]), n_naive2, 1)
    rows.append(("EVT 2.0", r_ours2, [("numpy vectorised", r_np2), ("python loop", r_naive2)]))

    print(f"decoders, {n} events of the shared sample, CPU time of one thread "
          f"(machine: {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f})")
    print(f"{'format':<8} {'ours M ev/s':>12}   {'baseline':<18} {'M ev/s':>8} {'ours/baseline':>14}")
    for fmt, ours_rate, bases in rows:
        for name, rate in bases:
            print(f"{fmt:<8} {ours_rate:12.1f}   {name:<18} {rate:8.2f} {ours_rate / rate:13.1f}x")
    print("target: >= 30 M ev/s per core for EVT 3.0 and EVT 2.0")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Decoder and reader throughput on one core, ours vs baselines, in one run.

1. Decoders (CPU time of one thread): ours (numba, streaming) vs the PyPI `evt3` decoder and a
   naive Python loop (EVT 3.0), and vs a plain numpy decoder and a naive loop (EVT 2.0), on the
   shared real EVT 3.0 sample (../shared/data/evt3_sample.raw, 219 596 events) and the same
   events written as EVT 2.0.
2. Readers (CPU time, file in the page cache): every format's reader (``arena.formats``) on a
   realistic paper-format recording (12 s, 4 robots driving circles, the sensor's background
   noise: ~4.1 M events, 74 MB of CSV; simulated once and kept in bench/out/), beside
   baselines: for the CSV ``pandas.read_csv``, ``numpy.loadtxt``, ``pyarrow.csv`` (when
   installed) and our previous reader (numpy text split); for RAW the PyPI ``evt3`` decoder;
   for AEDAT4 iniVation's ``dv_processing``; for DAT a vectorised numpy decoder of the whole file.
3. ``arena convert`` as a whole command (wall time of the process, start-up included):
   CSV -> RAW, RAW -> CSV, CSV -> npz.

Run: ``python bench/bench_decoders.py [--repeat N] [--file-repeat N] [--skip-files]``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from arena.events import EVENT_DTYPE, as_events
from arena.formats.evt2 import Evt2Decoder, encode_evt2
from arena.formats.evt3 import Evt3Decoder
from arena.formats.raw import parse_raw_header

SAMPLE = Path(__file__).resolve().parents[2] / "shared" / "data" / "evt3_sample.raw"
OUT = Path(__file__).resolve().parent / "out"
#: the paper-format recording of the reader rows (cached in bench/out/, which git ignores)
PAPER = OUT / "paper_4robots_12s.csv"


def paper_csv() -> tuple[Path, Path]:
    """The paper-format CSV (``x,y,p,t_us`` with a header) of 12 s of 4 robots driving circles
    with the sensor's noise, and its calibration JSON; simulated on first use (~15 s)."""
    cal = PAPER.with_suffix(".calibration.json")
    if not (PAPER.exists() and cal.exists()):
        from arena.formats import write_events
        from simulator.scenarios import Scenario, generate

        OUT.mkdir(parents=True, exist_ok=True)
        rec = generate(Scenario(n_robots=4, pattern="circle", duration_s=12.0, seed=3))
        write_events(PAPER.with_suffix(".tmp.csv"), rec.events, rec.width, rec.height)
        PAPER.with_suffix(".tmp.csv").replace(PAPER)
        cal.write_text(json.dumps(rec.calibration))
    return PAPER, cal


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


def old_csv_reader(path: Path) -> np.ndarray:
    """Our CSV reader before the numba kernel: blocks of lines split by numpy (1.2 M ev/s)."""
    from arena.formats.base import EventReader

    cols = EventReader()
    cols.path = str(path)
    parts = []
    with open(path, "rb") as f:
        f.readline()
        pending = b""
        while True:
            data = pending + f.read(6 << 20)
            if not data:
                break
            cut = data.rfind(b"\n") + 1
            block, pending = (data, b"") if len(data) < (6 << 20) or cut == 0 else (data[:cut], data[cut:])
            v = np.array(block.replace(b",", b" ").split(), dtype=np.int64).reshape(-1, 4)
            parts.append(cols._columns(v[:, 0], v[:, 1], v[:, 2], v[:, 3]))
    return np.concatenate(parts)


def pandas_csv(path: Path, **opts) -> np.ndarray:
    import pandas as pd

    df = pd.read_csv(path, dtype="int64", **opts)
    ev = np.empty(len(df), EVENT_DTYPE)
    for name, col in zip("xypt", df.columns):
        ev[name] = df[col].to_numpy()
    return ev


def pyarrow_csv(path: Path) -> int:
    """pyarrow's streaming CSV reader (blocks of 16 MB), columns to numpy; returns the events."""
    import pyarrow as pa
    from pyarrow import csv

    n = 0
    opts = csv.ReadOptions(block_size=16 << 20, use_threads=False)
    conv = csv.ConvertOptions(column_types={c: pa.int64() for c in ("x", "y", "p", "t_us")})
    for batch in csv.open_csv(path, read_options=opts, convert_options=conv):
        ev = np.empty(batch.num_rows, EVENT_DTYPE)
        for name, col in zip("xypt", batch.columns):
            ev[name] = col.to_numpy()
        n += ev.size
    return n


def loadtxt_csv(path: Path, max_rows: int) -> np.ndarray:
    return np.loadtxt(path, dtype=np.int64, delimiter=",", skiprows=1, max_rows=max_rows)


def numpy_dat(path: Path) -> np.ndarray:
    """A vectorised numpy DAT decoder: skip the header, one 64-bit word pair per event."""
    data = path.read_bytes()
    pos = 0
    while data[pos:pos + 1] == b"%":
        pos = data.index(b"\n", pos) + 1
    w = np.frombuffer(data[pos + 2:], "<u4").reshape(-1, 2)
    ev = np.empty(w.shape[0], EVENT_DTYPE)
    ev["t"] = w[:, 0]
    ev["x"] = w[:, 1] & 0x3FFF
    ev["y"] = (w[:, 1] >> 14) & 0x3FFF
    ev["p"] = (w[:, 1] >> 28) & 1
    return ev


def read_file(path: Path, **opts) -> int:
    from arena.formats import iter_events

    n = 0
    with iter_events(path, **opts) as reader:
        for chunk in reader:
            n += chunk.size
    return n


def wall_run(cmd: list[str]) -> float:
    """Wall seconds of one whole command (a fresh process)."""
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True, timeout=600)
    return time.perf_counter() - t0


def file_rows(repeat: int) -> list:
    """(what, ours M ev/s, [(baseline, M ev/s)]) of every reader and of ``arena convert``."""
    from arena.formats import read_events, write_events

    csv_path, _ = paper_csv()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ev, w, h = read_events(csv_path, width=640, height=480)
    n = ev.size
    files = {}
    for ext in (".raw", ".dat", ".aedat4", ".npz"):
        files[ext] = OUT / f"paper_4robots_12s{ext}"
        if not files[ext].exists():
            write_events(files[ext], ev, w, h)
    rows = []
    r_ours = best_rate(lambda: read_file(csv_path, width=640, height=480), n, repeat)
    assert np.array_equal(old_csv_reader(csv_path), ev)
    bases = [("our numpy split (before)", best_rate(lambda: old_csv_reader(csv_path), n, 1))]
    try:
        assert np.array_equal(pandas_csv(csv_path), ev)
        bases.append(("pandas.read_csv (C)", best_rate(lambda: pandas_csv(csv_path), n, repeat)))
    except ImportError:
        pass
    try:
        assert pyarrow_csv(csv_path) == n
        bases.append(("pyarrow.csv stream", best_rate(lambda: pyarrow_csv(csv_path), n, repeat)))
    except ImportError:
        bases.append(("pyarrow.csv stream", float("nan")))
    k = n // 20
    assert np.array_equal(loadtxt_csv(csv_path, k)[:, 3], ev["t"][:k])
    bases.append(("numpy.loadtxt", best_rate(lambda: loadtxt_csv(csv_path, k), k, 1)))
    rows.append(("CSV", r_ours, bases))

    r_raw = best_rate(lambda: read_file(files[".raw"]), n, repeat)
    try:
        import evt3

        assert np.array_equal(np.asarray(evt3.decode_file(str(files[".raw"])).t), np.sort(ev["t"], kind="stable"))
        rows.append(("RAW EVT3", r_raw, [("PyPI evt3 file", best_rate(lambda: evt3.decode_file(str(files[".raw"])),
                                                                          n, repeat))]))
    except ImportError:
        rows.append(("RAW EVT3", r_raw, [("PyPI evt3 file", float("nan"))]))
    r_dat = best_rate(lambda: read_file(files[".dat"]), n, repeat)
    assert np.array_equal(numpy_dat(files[".dat"]), ev)
    rows.append(("DAT", r_dat, [("numpy whole file", best_rate(lambda: numpy_dat(files[".dat"]), n, repeat))]))
    r_aedat = best_rate(lambda: read_file(files[".aedat4"]), n, repeat)
    try:
        import dv_processing as dv

        def dv_read() -> int:
            rd = dv.io.MonoCameraRecording(str(files[".aedat4"]))
            m = 0
            while (batch := rd.getNextEventBatch()) is not None:
                m += len(batch.numpy())
            return m
        assert dv_read() == n
        rows.append(("AEDAT4", r_aedat, [("dv_processing", best_rate(dv_read, n, repeat))]))
    except ImportError:
        rows.append(("AEDAT4", r_aedat, [("dv_processing", float("nan"))]))
    r_npz = best_rate(lambda: read_file(files[".npz"]), n, repeat)
    rows.append(("npz", r_npz, [("numpy.load", best_rate(lambda: dict(np.load(files[".npz"])), n, repeat))]))

    arena = [sys.executable, "-m", "arena", "convert"]
    for src, dst in ((csv_path, OUT / "convert_out.raw"), (files[".raw"], OUT / "convert_out.csv"),
                     (csv_path, OUT / "convert_out.npz")):
        wall_run(arena + [str(src), str(dst)])            # warm
        t = min(wall_run(arena + [str(src), str(dst)]) for _ in range(max(1, repeat // 2)))
        rows.append((f"convert {src.suffix[1:]}->{dst.suffix[1:]}", n / t / 1e6, []))
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=10, help="timing repeats (best is kept)")
    ap.add_argument("--file-repeat", type=int, default=3, help="timing repeats of the file readers")
    ap.add_argument("--skip-files", action="store_true", help="only the decoders on the shared sample")
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
    if args.skip_files:
        return 0
    frows = file_rows(args.file_repeat)
    print()
    print(f"readers, {PAPER.name} (12 s, 4 robots, noise) in every format, CPU time of the process, "
          f"file in the page cache; `arena convert`: wall time of the whole command")
    print(f"{'reader':<16} {'ours M ev/s':>12}   {'baseline':<26} {'M ev/s':>8} {'ours/baseline':>14}")
    for fmt, ours_rate, bases in frows:
        if not bases:
            print(f"{fmt:<16} {ours_rate:12.1f}   {'(whole command)':<26}")
        for name, rate in bases:
            print(f"{fmt:<16} {ours_rate:12.1f}   {name:<26} {rate:8.2f} {ours_rate / rate:13.1f}x")
    print("target: the CSV reader >= 20 M ev/s")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""End to end on one paper-format CSV: ``arena track`` vs the paper's pipeline, per track update.

The file: the paper-format recording of ``bench/bench_decoders.py`` (``paper_csv()``: ``x,y,p,t_us``
with a header, 640x480, 12 s of 4 robots driving circles at full power, seed 3, the simulator's
default sensor model: background activity 0.5 Hz/px spread by brightness, 0.15 Hz/px leak
events, 5 hot pixels at 50 Hz; ~4.1 M events, ~74 MB; simulated once and cached in bench/out/),
or any paper-format CSV with ``--csv`` and ``--calibration``. The event count, duration and
event rate printed are measured on the file used.

Both pipelines run as fresh processes, so both include the interpreter start, the imports,
reading the CSV, tracking and writing a tracks CSV:

- ``ours``: ``python -m arena track --input CSV --calibration CAL --tracks-out T`` (the default
  pipeline: 10 ms slices, t_a = 100 ms, fleet tracker).
- ``paper``: this script's ``--paper-child`` mode: ``pandas.read_csv`` of the whole file (the
  paper's code is Python; pandas is the project's declared ``bench`` extra; without pandas,
  ``numpy.loadtxt``), then consecutive 100 ms windows (t_a = 100 ms, the paper's best), each one
  track update: ``PaperDetector`` with the scikit-learn backend (DBSCAN three times: all / ON /
  OFF events, centroids, ON/OFF heading) and the k-d tree ``IDTrack`` (Algorithm 1), as
  ``bench/bench_tracker_speed.py`` times them; the window's events are cut by a binary search on
  the sorted times (cheaper than the DataFrame masks a straightforward port would use: this
  favours the paper). Tracks are written with the same CSV writer as ours.

Wall time is from the start of the process to its exit; CPU time is its user + system time
(``resource.getrusage(RUSAGE_CHILDREN)`` deltas, so it counts all of its threads). A track update
is a time step at which the pipeline wrote at least one track: the distinct ``t_us`` of its
tracks CSV (ours: a 10 ms slice; the paper: a 100 ms window). "ms/update" is the median wall (or
CPU) time of the whole process divided by its track updates; "paper/ours" is the ratio of those.
With ``--paper-windows K`` below the file's window count, the paper runs on the first K windows
only and its time and updates are extrapolated per window (said in the output; the first
windows hold the robots' start, so they are not a typical sample).

One untimed warm-up run of each comes first (numba's cache, the page cache), unless ``--no-warmup``.

    python bench/bench_end_to_end.py                   # the 12 s file, 3 runs each (~1.5 min)
    python bench/bench_end_to_end.py --quick           # its first 3 s, 1 run each (~15 s)
    python bench/bench_end_to_end.py --csv rec.csv --calibration cal.json --runs 5

Target (issue 22): ours >= 50x faster per track update than the paper's pipeline on the same file.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import platform
import re
import resource
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
WINDOW_US = 100_000          # the paper's t_a (its best accumulation time)
TARGET = 50.0                # issue 22: paper/ours per track update


# ----------------------------------------------------------------------------- the paper, in a child


def paper_child(args) -> int:
    """``--paper-child``: the paper's pipeline on ``args.csv``; prints one JSON line of counts."""
    import numpy as np

    from arena.events import EVENT_DTYPE
    from tracker.calibration import Calibration
    from tracker.detect import PaperConfig, PaperDetector
    from tracker.idtrack import IDTrack
    from arena.formats.tables import TrackCsvWriter
    from tracker.pipeline import PAPER_SIGMA_PX, Pipeline

    w0, c0 = time.perf_counter(), time.process_time()
    try:
        import pandas as pd

        df = pd.read_csv(args.csv)
        cols = [df[c].to_numpy() for c in df.columns[:4]]
        reader = f"pandas.read_csv (pandas {pd.__version__})"
    except ImportError:
        a = np.loadtxt(args.csv, dtype=np.int64, delimiter=",", skiprows=1)
        cols = [a[:, i] for i in range(4)]
        reader = f"numpy.loadtxt (numpy {np.__version__}; pandas not installed)"
    ev = np.empty(cols[0].size, EVENT_DTYPE)
    for name, col in zip("xypt", cols):
        ev[name] = col
    read_wall, read_cpu = time.perf_counter() - w0, time.process_time() - c0

    cal = Calibration.from_dict(json.loads(Path(args.calibration).read_text()))
    width, height = cal.image_size
    det = PaperDetector(PaperConfig(backend="sklearn"), width, height)
    track = IDTrack(PAPER_SIGMA_PX / cal.px_per_m())
    obs_of = Pipeline(cal, tracker="idtrack", detector="paper")._observation   # pixel -> arena (paper: no parallax)
    t = ev["t"]
    k0 = int(t[0]) // WINDOW_US if t.size else 0
    n_total = (int(t[-1]) // WINDOW_US - k0 + 1) if t.size else 0
    n_run = n_total if args.paper_windows is None else min(n_total, args.paper_windows)
    rows = 0
    w1, c1 = time.perf_counter(), time.process_time()
    with open(args.tracks_out, "w", newline="") as fh:
        writer = TrackCsvWriter(fh)
        for k in range(k0, k0 + n_run):
            t_end = (k + 1) * WINDOW_US
            a, b = np.searchsorted(t, [t_end - WINDOW_US, t_end])
            dets = det.detect(ev[a:b], t_end)
            rows += writer.write(track.update([obs_of(d) for d in dets], t_end))
    win_wall, win_cpu = time.perf_counter() - w1, time.process_time() - c1
    print(json.dumps(dict(reader=reader, events=int(ev.size), windows_total=n_total, windows_run=n_run, rows=rows,
                          read_wall=read_wall, read_cpu=read_cpu, windows_wall=win_wall, windows_cpu=win_cpu)))
    return 0


# ----------------------------------------------------------------------------- the parent


@dataclass
class Run:
    wall: float
    cpu: float
    rows: int
    updates: int
    steps: int
    info: dict = field(default_factory=dict)


def timed(cmd: list[str]) -> tuple[float, float, subprocess.CompletedProcess]:
    """Wall and CPU seconds (user + system of the child and its threads) of one process."""
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=1800, cwd=REPO)
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise SystemExit(f"failed ({proc.returncode}): {' '.join(cmd)}\n{proc.stderr[-3000:]}")
    return wall, (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime), proc


def track_counts(path: Path) -> tuple[int, int]:
    """(rows, distinct t_us) of a tracks CSV."""
    with open(path, newline="") as fh:
        rd = csv.reader(fh)
        next(rd)
        times = [row[0] for row in rd]
    return len(times), len(set(times))


def run_ours(csv_path: Path, cal: Path, out: Path) -> Run:
    tracks = out / "ours_tracks.csv"
    wall, cpu, proc = timed([sys.executable, "-m", "arena", "track", "--input", str(csv_path),
                             "--calibration", str(cal), "--tracks-out", str(tracks)])
    m = re.search(r"(\d+) slices", proc.stderr)
    loop = re.search(r"\(([\d.]+) s, [\d.]+ ms per slice\)", proc.stderr)   # its own timing of the slice loop
    rows, updates = track_counts(tracks)
    return Run(wall, cpu, rows, updates, int(m.group(1)) if m else -1,
               {"loop_wall": float(loop.group(1)) if loop else math.nan})


def run_paper(csv_path: Path, cal: Path, out: Path, windows: int | None) -> Run:
    tracks = out / "paper_tracks.csv"
    cmd = [sys.executable, str(Path(__file__).resolve()), "--paper-child", "--csv", str(csv_path),
           "--calibration", str(cal), "--tracks-out", str(tracks)]
    if windows is not None:
        cmd += ["--paper-windows", str(windows)]
    wall, cpu, proc = timed(cmd)
    info = json.loads(proc.stdout.strip().splitlines()[-1])
    rows, updates = track_counts(tracks)
    return Run(wall, cpu, rows, updates, info["windows_run"], info)


def extrapolate(r: Run) -> Run:
    """The paper's run on its first K windows, extrapolated per window to the whole file."""
    k, n = r.info["windows_run"], r.info["windows_total"]
    if k >= n or k == 0:
        return r
    f = (n - k) / k
    return Run(r.wall + f * r.info["windows_wall"], r.cpu + f * r.info["windows_cpu"],
               round(r.rows * n / k), round(r.updates * n / k), n, r.info)


def first_seconds(src: Path, seconds: float, dst: Path) -> Path:
    """The prefix of the paper-format CSV ``src`` up to its first event ``seconds`` after the start."""
    with open(src) as fi, open(dst, "w") as fo:
        fo.write(fi.readline())
        first = fi.readline()
        fo.write(first)
        t_stop = int(first.rsplit(",", 1)[1]) + seconds * 1e6
        for line in fi:
            if int(line.rsplit(",", 1)[1]) >= t_stop:
                break
            fo.write(line)
    return dst


def file_facts(path: Path) -> tuple[int, float]:
    """(events, seconds from the first to the last event) of a paper-format CSV."""
    n = 0
    with open(path, "rb") as fh:
        fh.readline()
        first = fh.readline()
        n = 1 if first.strip() else 0
        while block := fh.read(16 << 20):
            n += block.count(b"\n")
        fh.seek(max(0, fh.tell() - 200))
        last = fh.read().strip().splitlines()[-1]
    return n, (int(last.rsplit(b",", 1)[1]) - int(first.rsplit(b",", 1)[1])) / 1e6


def med(xs: list[float]) -> float:
    s = sorted(xs)
    m = len(s) // 2
    return s[m] if len(s) % 2 else 0.5 * (s[m - 1] + s[m])


def versions() -> str:
    from importlib.metadata import PackageNotFoundError, version

    out = [f"Python {platform.python_version()}"]
    for pkg in ("numpy", "numba", "scikit-learn", "pandas"):
        try:
            out.append(f"{pkg} {version(pkg)}")
        except PackageNotFoundError:
            out.append(f"{pkg} absent")
    return ", ".join(out)


def load() -> str:
    return "/".join(f"{x:.2f}" for x in os.getloadavg())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=None, help="timed runs of each pipeline (default 3; --quick 1)")
    ap.add_argument("--paper-windows", type=int, default=None, metavar="K",
                    help="run the paper on the first K 100 ms windows only and extrapolate per window "
                         "(default: all: ~20 s per run on the 12 s file)")
    ap.add_argument("--seconds", type=float, default=None,
                    help="use only the first S seconds of the CSV (a cut copy; default: the whole file; --quick 3)")
    ap.add_argument("--quick", action="store_true", help="the first 3 s of the file, 1 run each")
    ap.add_argument("--no-warmup", action="store_true", help="skip the untimed warm-up run of each pipeline")
    ap.add_argument("--csv", type=Path, default=None,
                    help="a paper-format CSV (x,y,p,t_us with a header; default: bench_decoders.paper_csv())")
    ap.add_argument("--calibration", type=Path, default=None, help="its calibration JSON (needed with --csv)")
    ap.add_argument("--out-dir", type=Path, default=None,
                    help="keep the tracks CSVs (and a cut CSV) here (default: a temporary folder, removed)")
    ap.add_argument("--paper-child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--tracks-out", type=Path, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.paper_child:
        return paper_child(args)
    runs = args.runs if args.runs is not None else (1 if args.quick else 3)
    seconds = args.seconds if args.seconds is not None else (3.0 if args.quick else None)
    if runs < 1 or (args.paper_windows is not None and args.paper_windows < 1) \
            or (seconds is not None and seconds <= 0):
        print("--runs and --paper-windows must be >= 1 and --seconds > 0", file=sys.stderr)
        return 2
    if (args.csv is None) != (args.calibration is None):
        print("--csv and --calibration go together", file=sys.stderr)
        return 2
    if args.csv is None:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from bench_decoders import paper_csv

        src, cal = paper_csv()
        made = ("bench_decoders.paper_csv(): simulated, 4 robots driving circles at full power, seed 3, the "
                "default sensor model (background 0.5 Hz/px by brightness, leak 0.15 Hz/px, 5 hot px at 50 Hz)")
    else:
        src, cal, made = args.csv, args.calibration, "given with --csv"
    with tempfile.TemporaryDirectory(prefix="bench_e2e_") as tmp:
        out = args.out_dir or Path(tmp)
        out.mkdir(parents=True, exist_ok=True)
        csv_path = src if seconds is None else first_seconds(src, seconds, out / f"{src.stem}.first{seconds:g}s.csv")
        n_ev, dur = file_facts(csv_path)
        mb = csv_path.stat().st_size / 1e6
        made += time.strftime(", file of %Y-%m-%d %H:%M", time.localtime(src.stat().st_mtime))
        load0 = load()
        if not args.no_warmup:
            run_ours(csv_path, cal, out)
            run_paper(csv_path, cal, out, 1)
        ours = [run_ours(csv_path, cal, out) for _ in range(runs)]
        paper_raw = [run_paper(csv_path, cal, out, args.paper_windows) for _ in range(runs)]
        load1 = load()
    paper = [extrapolate(r) for r in paper_raw]
    info = paper_raw[0].info
    extra = info["windows_run"] < info["windows_total"]
    cores = os.cpu_count()
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else cores

    print("end to end, one paper-format CSV -> a tracks CSV; each pipeline a fresh process (interpreter start, "
          "imports, reading, tracking, writing)")
    print(f"conditions: {platform.node() or 'host'} {platform.machine()}, {cores} cores ({usable} usable), "
          f"load average (1/5/15 min) {load0} before, {load1} after; {versions()}; "
          f"{runs} timed run(s) each{'' if args.no_warmup else ' after 1 warm-up run each'}")
    print(f"file: {csv_path} ({'first ' + format(seconds, 'g') + ' s of ' + src.name + ', ' if seconds else ''}"
          f"{made}): {mb:.1f} MB, {n_ev} events over {dur:.2f} s = {n_ev / max(dur, 1e-9) / 1e3:.0f} k ev/s")
    print(f"ours: python -m arena track (10 ms slices, t_a 100 ms, default detector, fleet tracker); "
          f"paper: {info['reader']}, {info['windows_total']} windows of 100 ms, sklearn DBSCAN x3 + "
          f"centroids + k-d tree IDTrack"
          + (f"; RUN ON THE FIRST {info['windows_run']} OF {info['windows_total']} WINDOWS, time and updates "
             f"EXTRAPOLATED per window" if extra else ""))
    print(f"inside ours' process (median, its own report): slice loop (reading included) "
          f"{med([r.info['loop_wall'] for r in ours]):.1f} s wall; "
          f"inside the paper's process (median): read {med([r.info['read_wall'] for r in paper_raw]):.2f} s, "
          f"{info['windows_run']} windows {med([r.info['windows_wall'] for r in paper_raw]):.2f} s wall = "
          f"{1e3 * med([r.info['windows_wall'] for r in paper_raw]) / max(1, info['windows_run']):.1f} ms per window")
    head = (f"{'pipeline':<9} {'wall s min':>10} {'med':>6} {'CPU s min':>9} {'med':>6} {'steps':>6} "
            f"{'updates':>7} {'rows':>6} {'ms/update wall':>14} {'CPU':>6} {'paper/ours wall':>15} {'CPU':>6}")
    print(head)
    print("-" * len(head))
    per = {}
    for name, rs in (("ours", ours), ("paper", paper)):
        r = rs[0]
        mw, mc = med([x.wall for x in rs]), med([x.cpu for x in rs])
        per[name] = (1e3 * mw / r.updates if r.updates else math.nan, 1e3 * mc / r.updates if r.updates else math.nan)
        ratio = (per[name][0] / per["ours"][0], per[name][1] / per["ours"][1])
        mark = "~" if name == "paper" and extra else " "
        print(f"{name:<9} {min(x.wall for x in rs):10.2f} {mw:6.2f} {min(x.cpu for x in rs):9.2f} {mc:6.2f} "
              f"{r.steps:6d} {r.updates:7d} {r.rows:6d} {per[name][0]:14.2f} {per[name][1]:6.2f} "
              f"{ratio[0]:14.1f}x {ratio[1]:5.1f}x{mark}")
    print("-" * len(head))
    ratio = per["paper"][0] / per["ours"][0]
    verdict = "MET" if ratio >= TARGET else "NOT MET"
    print(f"target (issue 22): paper/ours >= {TARGET:g}x per track update (wall): {ratio:.1f}x -> {verdict}"
          + (" (~: the paper extrapolated from its first windows)" if extra else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())

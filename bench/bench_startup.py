"""Start-up of ``arena track --input X.csv``: seconds from the process's start to its first
processed slice (warm caches: numba's kernels already compiled, files in the page cache).

Each run is a fresh ``python`` process running ``arena track --input FILE --calibration C
--tracks-out T``; a wrapper marks the end of the first ``Pipeline.push`` (the first slice) with
``time.monotonic()`` (one clock for the whole machine) and exits there, so a run costs about a
second. The parent takes its own ``time.monotonic()`` just before starting the process. Also
printed: the same process's time to its first line of Python (the interpreter alone); the CPU
time (user + system, ``resource.getrusage``) the child has used by the end of its first slice,
which a loaded machine inflates far less than the wall time; and the slowest imports of one such
run (``python -X importtime``: wall µs, so inflated by load too) -- top-level cumulative, and self
time summed per top-level package. numba's first call of a cached kernel refreshes its target
(importing numba.np.arraymath, which imports scipy.linalg for BLAS): those show as top-level
imports of their own.

Run: ``python bench/bench_startup.py [--runs 5] [--input X.csv --calibration C.json]``; without
``--input``, the paper-format CSV of ``bench/bench_decoders.py`` (bench/out/, made on first use).
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: the child: mark the first processed slice, then leave at once (no need to track the rest)
_WRAPPER = """
import os, sys, time
print(f"ARENA_T_PYTHON {time.monotonic()!r}", file=sys.stderr, flush=True)
import resource
import tracker.pipeline as _tp
_push = _tp.Pipeline.push
def _first_push(self, *a, **k):
    out = _push(self, *a, **k)
    print(f"ARENA_T_FIRST_SLICE {time.monotonic()!r}", file=sys.stderr, flush=True)
    ru = resource.getrusage(resource.RUSAGE_SELF)
    print(f"ARENA_T_CPU {ru.ru_utime + ru.ru_stime!r}", file=sys.stderr, flush=True)
    os._exit(0)
_tp.Pipeline.push = _first_push
from arena.cli import main
sys.exit(main(sys.argv[1:]))
"""


def first_slice_s(argv: list[str], timeout: float = 120.0) -> tuple[float, float, float]:
    """(seconds to the first Python line, seconds to the end of the first slice, CPU seconds
    used by then) of one run."""
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-c", _WRAPPER, *argv], capture_output=True, text=True,
                       timeout=timeout, cwd=ROOT)
    marks = dict(line.split() for line in r.stderr.splitlines() if line.startswith("ARENA_T_"))
    if "ARENA_T_FIRST_SLICE" not in marks:
        raise RuntimeError(f"no slice was processed (exit {r.returncode}): {r.stderr[-1000:]}")
    return float(marks["ARENA_T_PYTHON"]) - t0, float(marks["ARENA_T_FIRST_SLICE"]) - t0, float(marks["ARENA_T_CPU"])


def slowest_imports(argv: list[str], n: int = 12) -> tuple[list[tuple[float, str]], list[tuple[float, str]]]:
    """The imports of one run of ``arena ARGV`` to its first slice (``python -X importtime``):
    the ``n`` slowest top-level ones (cumulative s, module) and the ``n`` top-level packages
    with the most self time (s, package)."""
    r = subprocess.run([sys.executable, "-X", "importtime", "-c", _WRAPPER, *argv],
                       capture_output=True, text=True, timeout=120, cwd=ROOT)
    rows, per_package = [], {}
    for line in r.stderr.splitlines():
        if not line.startswith("import time:") or "|" not in line:
            continue
        own, cum, name = line[len("import time:"):].split("|")
        if not cum.strip().isdigit():                               # the header line
            continue
        top = name.strip().split(".")[0]
        per_package[top] = per_package.get(top, 0.0) + int(own) / 1e6
        if not name.startswith("  "):   # top level only: its own share
            rows.append((int(cum) / 1e6, name.strip()))
    return sorted(rows, reverse=True)[:n], sorted(((s, p) for p, s in per_package.items()), reverse=True)[:n]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=5, help="runs (the median is reported)")
    ap.add_argument("--input", default=None, help="event file (default: the bench's paper-format CSV)")
    ap.add_argument("--calibration", default=None, help="calibration JSON of --input")
    args = ap.parse_args()
    if args.input is None:
        sys.path.insert(0, str(ROOT / "bench"))
        from bench_decoders import paper_csv

        args.input, args.calibration = (str(p) for p in paper_csv())
    elif args.calibration is None:
        ap.error("--calibration is needed with --input")
    with tempfile.TemporaryDirectory() as d:
        argv = ["track", "--input", args.input, "--calibration", args.calibration,
                "--tracks-out", os.path.join(d, "tracks.csv")]
        first_slice_s(argv)                     # warm: numba's cache, the page cache
        runs = [first_slice_s(argv) for _ in range(args.runs)]
        top, per_package = slowest_imports(argv)
    py = statistics.median(r[0] for r in runs)
    first = statistics.median(r[1] for r in runs)
    cpu = statistics.median(r[2] for r in runs)
    print(f"arena track --input {Path(args.input).name}: process start -> first processed slice, "
          f"median of {args.runs} (machine: {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f})")
    print(f"  interpreter up      {py:6.3f} s")
    print(f"  first slice done    {first:6.3f} s   (runs: {', '.join(f'{r[1]:.3f}' for r in runs)})")
    print(f"  CPU by then         {cpu:6.3f} s   (runs: {', '.join(f'{r[2]:.3f}' for r in runs)}; user + system)")
    print("  target: <= 0.5 s")
    print("slowest top-level imports of one run to its first slice (cumulative, wall):")
    for s, name in top:
        print(f"  {s:6.3f} s  {name}")
    print("import self time per top-level package (wall):")
    for s, name in per_package:
        print(f"  {s:6.3f} s  {name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Longer fuzzing of every decoder of untrusted bytes (messages, the window codec, every event
file reader, the robot serial protocol, mission commands, the tracker's state file, calibration
JSON, the lab config) than CI's.

``python bench/fuzz.py --minutes N [--targets a,b] [--seed K]``: the time is split evenly over
the targets; each runs in rounds of 200 hypothesis-mutated inputs with a new seed per round.

``python bench/fuzz.py --examples-per-target N [--targets a,b] [--seed K]``: each target runs
until it has had N inputs (in rounds of ``--round`` inputs, a new seed per round), going on
after a finding (``findings`` counts the failed rounds).

Every target runs in a child process of its own whose address space is capped at 256 MiB over
its warmed-up baseline (see ``tests/fuzz/``), so each one's peak is its own. Prints per target:
inputs run, wall time, the slowest input, findings, peak address space and resident size over
the baseline; then a table of the same; exits 1 on any finding (the shrunk input and the traceback
are printed; rerun one round with ``--seed``).
"""

from __future__ import annotations

import argparse
import os
import random
import re
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tests.fuzz.targets import TARGETS  # noqa: E402

_LINE = re.compile(r"^(ok  |FAIL) (\S+): (\d+) inputs in ([\d.]+) s, slowest (\d+) ms, findings (\d+), "
                   r"peak \+([\d.]+) MiB address space \+([\d.]+) MiB resident")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=5.0, help="total fuzzing time (default 5)")
    ap.add_argument("--examples-per-target", type=int, default=None, metavar="N",
                    help="instead of --minutes: stop each target after N inputs")
    ap.add_argument("--round", type=int, default=1000, help="inputs per hypothesis round with "
                    "--examples-per-target (default 1000)")
    ap.add_argument("--max-minutes-per-target", type=float, default=None, metavar="M",
                    help="with --examples-per-target: stop a target after the round that passes M minutes "
                         "(its line then says so and gives the inputs it reached)")
    ap.add_argument("--targets", default=",".join(TARGETS), help=f"comma-separated, of: {', '.join(TARGETS)}")
    ap.add_argument("--seed", type=int, default=None, help="seed of the first round (default: random)")
    ap.add_argument("--max-mb", type=int, default=256, help="address space over the baseline, MiB (default 256)")
    args = ap.parse_args()
    names = [n for n in args.targets.split(",") if n]
    unknown = [n for n in names if n not in TARGETS]
    if unknown:
        ap.error(f"unknown target(s) {unknown}; known: {', '.join(TARGETS)}")
    seed = args.seed if args.seed is not None else random.randrange(1 << 30)
    if args.examples_per_target is not None:
        print(f"fuzzing {len(names)} target(s) to {args.examples_per_target} inputs each, first seed {seed}",
              flush=True)
        budget = ["--examples", str(args.round), "--total", str(args.examples_per_target), "--keep-going"]
        if args.max_minutes_per_target is not None:
            budget += ["--max-seconds", str(args.max_minutes_per_target * 60)]
        timeout = None
    else:
        per_target_s = args.minutes * 60 / max(1, len(names))
        print(f"fuzzing {len(names)} target(s) for {per_target_s:.0f} s each, first seed {seed}", flush=True)
        budget = ["--examples", "200", "--seconds", str(per_target_s)]
        timeout = per_target_s * 2 + 300
    rows, rc = [], 0
    for n in names:
        cmd = [sys.executable, "-m", "tests.fuzz.runner", "--targets", n, *budget, "--seed", str(seed),
               "--max-mb", str(args.max_mb)]
        t0 = time.monotonic()
        try:
            r = subprocess.run(cmd, cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, timeout=timeout,
                               capture_output=True, text=True)
        except subprocess.TimeoutExpired:
            print(f"FAIL {n}: timed out after {time.monotonic() - t0:.0f} s", flush=True)
            rows.append((n, "timeout", "", "", "", "", ""))
            rc = 1
            continue
        sys.stdout.write(r.stdout)
        sys.stderr.write(r.stderr)
        m = next((_LINE.match(line) for line in r.stdout.splitlines() if _LINE.match(line)), None)
        if m is None:
            print(f"FAIL {n}: the runner ended with status {r.returncode} and no summary", flush=True)
            rows.append((n, "crashed", "", "", "", "", ""))
            rc = 1
            continue
        rows.append((n, m[3] + ("*" if "stopped by --max-seconds" in m.string else ""), m[6], m[7], m[8], m[4], m[5]))
        rc |= r.returncode != 0
    print(f"\n{'target':<18} {'inputs':>8} {'findings':>8} {'peak AS MiB':>11} {'peak RSS MiB':>12} "
          f"{'wall s':>8} {'slowest ms':>10}")
    for row in rows:
        print(f"{row[0]:<18} {row[1]:>8} {row[2]:>8} {row[3]:>11} {row[4]:>12} {row[5]:>8} {row[6]:>10}")
    if any(str(row[1]).endswith("*") for row in rows):
        print("(* stopped by --max-minutes-per-target before --examples-per-target)")
    return int(rc)


if __name__ == "__main__":
    sys.exit(main())

"""Longer fuzzing of every decoder of untrusted bytes (messages, the window codec, every event
file reader) than CI's: ``python bench/fuzz.py --minutes N [--targets a,b] [--seed K]``.

The time is split evenly over the targets; each runs in rounds of 200 hypothesis-mutated inputs
with a new seed per round, in a child process whose address space is capped at 256 MiB over its
warmed-up baseline (see ``tests/fuzz/``). Prints one line per target and exits 1 on any finding
(the shrunk input and the traceback are printed; rerun one round with ``--seed``).
"""

from __future__ import annotations

import argparse
import os
import random
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tests.fuzz.targets import TARGETS  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=5.0, help="total fuzzing time (default 5)")
    ap.add_argument("--targets", default=",".join(TARGETS), help=f"comma-separated, of: {', '.join(TARGETS)}")
    ap.add_argument("--seed", type=int, default=None, help="seed of the first round (default: random)")
    ap.add_argument("--max-mb", type=int, default=256, help="address space over the baseline, MiB (default 256)")
    args = ap.parse_args()
    names = [n for n in args.targets.split(",") if n]
    seed = args.seed if args.seed is not None else random.randrange(1 << 30)
    per_target_s = args.minutes * 60 / max(1, len(names))
    print(f"fuzzing {len(names)} target(s) for {per_target_s:.0f} s each, first seed {seed}", flush=True)
    cmd = [sys.executable, "-m", "tests.fuzz.runner", "--targets", ",".join(names), "--examples", "200",
           "--seconds", str(per_target_s), "--seed", str(seed), "--max-mb", str(args.max_mb)]
    r = subprocess.run(cmd, cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)},
                       timeout=args.minutes * 60 * 2 + 300)
    return r.returncode


if __name__ == "__main__":
    sys.exit(main())

"""Run fuzz targets (:mod:`tests.fuzz.targets`) under an address-space limit and a time limit.

``python -m tests.fuzz.runner [--targets a,b] [--examples N] [--seconds S | --total T] [--seed K]``: builds
each target's seed input, warms the decoders up (numba loads its kernels), caps the address space
at 256 MiB over what is mapped then, and feeds each target hypothesis-mutated inputs. A target
fails if its decoder raises anything but its declared error, returns invalid values, runs out of
memory (``MemoryError`` under the cap) or takes longer than ``--max-example-s`` on one input.
Prints one line per target (inputs, wall time, slowest input, findings, and the process's peak
address space and resident size over the warmed-up baseline: ``VmPeak``/``VmHWM`` of
``/proc/self/status``, cumulative over the targets run before in the same process); exit status 1
if any failed (with the shrunk input and traceback). ``--keep-going`` goes on after a finding with
the next round, so that ``findings`` counts the failed rounds.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
import traceback
import warnings

from hypothesis import HealthCheck, Phase, given, seed, settings
from hypothesis import strategies as st

from tests.fuzz.harness import LIMIT_MB, limit_address_space
from tests.fuzz.targets import TARGETS, Target


def run_target(target: Target, data: bytes, examples: int, rng_seed: int, max_example_s: float,
               stats: dict | None = None) -> dict:
    """Feed ``examples`` mutated inputs to ``target``; returns counts (``stats``, updated in place:
    also what ran before a finding); raises on a contract break."""
    stats = {"inputs": 0, "slowest_s": 0.0} if stats is None else stats

    @seed(rng_seed)
    @settings(max_examples=examples, deadline=None, database=None, phases=[Phase.generate, Phase.shrink],
              suppress_health_check=list(HealthCheck), report_multiple_bugs=False)
    @given(st.data())
    def fuzz(draw_data):
        payload = target.make_input(draw_data.draw, data)
        t0 = time.perf_counter()
        target.check(payload)
        took = time.perf_counter() - t0
        stats["inputs"] += 1
        stats["slowest_s"] = max(stats["slowest_s"], took)
        assert took < max_example_s, f"one input took {took:.1f} s (limit {max_example_s} s)"

    fuzz()
    return stats


def _status_kib(*keys: str) -> dict[str, int]:
    """Fields of ``/proc/self/status`` in KiB (e.g. VmSize, VmPeak, VmRSS, VmHWM)."""
    out = {}
    with open("/proc/self/status") as f:
        for line in f:
            k, _, v = line.partition(":")
            if k in keys:
                out[k] = int(v.split()[0])
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--targets", default=",".join(TARGETS), help=f"comma-separated, of: {', '.join(TARGETS)}")
    ap.add_argument("--examples", type=int, default=100, help="inputs per target (default 100)")
    ap.add_argument("--seconds", type=float, default=None,
                    help="instead: keep fuzzing each target this long, in rounds of --examples")
    ap.add_argument("--total", type=int, default=None,
                    help="instead: fuzz each target until it has run this many inputs, in rounds of --examples")
    ap.add_argument("--max-seconds", type=float, default=None,
                    help="with --total: stop a target after the round that passes this wall time, and say so")
    ap.add_argument("--keep-going", action="store_true",
                    help="after a finding go on with the next round (until --seconds / --total)")
    ap.add_argument("--seed", type=int, default=0, help="hypothesis seed of the first round (default 0)")
    ap.add_argument("--max-mb", type=int, default=LIMIT_MB, help=f"address space over the baseline (default {LIMIT_MB})")
    ap.add_argument("--max-example-s", type=float, default=10.0, help="time limit of one input (default 10 s)")
    args = ap.parse_args(argv)
    names = [n for n in args.targets.split(",") if n]
    unknown = [n for n in names if n not in TARGETS]
    if unknown:
        ap.error(f"unknown target(s) {unknown}; known: {', '.join(TARGETS)}")
    warnings.simplefilter("ignore")      # what readers skip (SkippedData) and numpy's notes are not findings
    logging.disable(logging.CRITICAL)    # nor a header's missing sensor size
    seeds = {}
    for n in names:                      # build the seeds and warm every decoder up before the cap
        seeds[n] = TARGETS[n].seed()
        TARGETS[n].check(seeds[n])
    cap = limit_address_space(args.max_mb)
    base = _status_kib("VmSize", "VmRSS")
    print(f"fuzz: address space capped at {cap >> 20} MiB ({args.max_mb} MiB over the warmed-up baseline)",
          flush=True)
    failed = []
    for n in names:
        t0, inputs, slowest, rnd, findings, stopped = time.monotonic(), 0, 0.0, 0, 0, ""
        while True:
            examples = args.examples if args.total is None else max(1, min(args.examples, args.total - inputs))
            stats = {"inputs": 0, "slowest_s": 0.0}
            try:
                run_target(TARGETS[n], seeds[n], examples, args.seed + rnd, args.max_example_s, stats)
            except BaseException as exc:  # noqa: BLE001 - any undeclared error, MemoryError included, is the finding
                if isinstance(exc, KeyboardInterrupt):
                    raise
                findings += 1
                print(f"FAIL {n} (round seed {args.seed + rnd}): {type(exc).__name__}: {str(exc)[:500]}", flush=True)
                traceback.print_exc(limit=-8)
                if not args.keep_going:
                    break
            finally:
                inputs += stats["inputs"]            # the inputs run, shrinking's included
                slowest = max(slowest, stats["slowest_s"])
            rnd += 1
            if args.total is not None:
                if inputs >= args.total:
                    break
                if args.max_seconds is not None and time.monotonic() - t0 >= args.max_seconds:
                    stopped = f" (stopped by --max-seconds {args.max_seconds:g} before --total {args.total})"
                    break
            elif args.seconds is None or time.monotonic() - t0 >= args.seconds:
                break
        peak = _status_kib("VmPeak", "VmHWM")
        line = (f"{n}: {inputs} inputs in {time.monotonic() - t0:.1f} s, slowest {slowest * 1e3:.0f} ms, "
                f"findings {findings}, peak +{(peak['VmPeak'] - base['VmSize']) / 1024:.1f} MiB address space "
                f"+{max(0, peak['VmHWM'] - base['VmRSS']) / 1024:.1f} MiB resident over the baseline{stopped}")
        if findings:
            failed.append(n)
            print(f"FAIL {line}", flush=True)
        else:
            print(f"ok   {line}", flush=True)
    if failed:
        print(f"fuzz: {len(failed)} target(s) failed: {', '.join(failed)}", flush=True)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

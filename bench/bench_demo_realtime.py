"""Does the 4-robot demo keep real time on this machine? Runs ``arena demo`` several times,
alternating the observers' priority: ours (recorder, ground truth and viewer at nice +10, the
default) against the baseline (every process at the same priority, ``--observer-nice 0``).

Per run it prints the simulator's own account (real-time factor and worst lag behind the wall
clock, from ``summary.json``), the first track, the tracking scores, the CPU the whole demo
used (all its processes, in cores), the latency from the edge publishing a slice to its track
arriving (p50, p99) and the event windows lost (dropped by the edge, missing at the tracker or
dropped from its queue). The runs alternate so that a change in the machine's load hits
both sides alike; the summary prints the mean worst lag of each side and their ratio.

    python bench/bench_demo_realtime.py                 # 2 pairs of 20 s demos, ~3 min
    python bench/bench_demo_realtime.py --pairs 5 --duration 30
    python bench/bench_demo_realtime.py --load 0.9      # with another process busy 90 % of a core

``--load F`` runs, beside every demo, a process that keeps F of one core busy (100 ms cycles of
busy looping and sleeping, at normal priority, ended with the run): the head-room the demo has
left on this machine. The ``cores`` column is the CPU the demo itself used; on a VM whose host is
busy the same work costs more CPU seconds. The ``ref ms`` column times a fixed pure-Python loop
just before each run (best of 5): when it and ``cores`` are both up, the machine was slow, not
the demo. Compare runs only at similar ``ref ms``.

The drill (every run, whatever ``--load``): each robot's mission must have run closed-loop on
its tracks, or the demo's own summary must say which did not. Per run a ``closed loop`` line
gives each robot's tracks used and the seconds it drove on odometry alone; a mission that drove
without tracks, fell back to odometry, or left no manifest, and that the summary (``problems``,
``odometry_fallbacks``) does not name, fails the drill: the bench then exits 1.

    python bench/bench_demo_realtime.py --load 1.0 --pairs 1   # the drill beside a busy core
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


#: a competing process: busy for ``load`` of every 100 ms, asleep for the rest, for at most ``limit_s``
_HOG = ("import sys, time\n"
        "load, end = float(sys.argv[1]), time.monotonic() + float(sys.argv[2])\n"
        "while time.monotonic() < end:\n"
        "    t = time.monotonic()\n"
        "    while time.monotonic() - t < 0.1 * load:\n"
        "        pass\n"
        "    time.sleep(0.1 * (1.0 - load))\n")


def reference_ms() -> float:
    """Best of 5 timings of a fixed single-threaded Python loop: this machine's current speed."""
    best = float("inf")
    for _ in range(5):
        t = time.perf_counter()
        acc = 0
        for i in range(300_000):
            acc += i * i % 7
        best = min(best, time.perf_counter() - t)
    return best * 1e3


def _num(v) -> float:
    """A score for the table: n/a (None: nothing measured) prints as nan."""
    return float("nan") if v is None else float(v)


def closed_loop_drill(manifests: list[dict], summary: dict, robots: int) -> tuple[bool, str]:
    """Did every one of the ``robots`` missions run closed-loop on its tracks, or does the demo's
    ``summary`` name the ones that did not? Returns (passed, a one-line account)."""
    said = set((summary.get("odometry_fallbacks") or {}).keys())
    problems = " ".join(str(p) for p in summary.get("problems") or [])
    parts, unsaid = [], []
    for m in manifests:
        robot = str(m.get("robot"))
        fusion = m.get("fusion") or {}
        used = int(fusion.get("tracks_used") or 0)
        odo_s = float(fusion.get("odometry_only_s") or 0.0)
        first_s = float(fusion.get("odometry_before_first_track_s") or 0.0)
        closed = m.get("control") == "closed"
        parts.append(f"{robot} {m.get('control', '?')}, {used} tracks, odometry {odo_s:.1f} s"
                     + (f" ({first_s:.1f} s before the first track)" if first_s > 0 else "")
                     + (" at the end" if fusion.get("on_odometry_at_end") else ""))
        if not closed or used == 0:   # not closed-loop at all: the problems must name it
            if robot not in problems:
                unsaid.append(f"{robot} ({'open loop' if not closed else 'no tracks'}) not in the problems")
        elif odo_s > 0 and robot not in said and robot not in problems:
            unsaid.append(f"{robot} ({odo_s:.1f} s on odometry) not in odometry_fallbacks")
    if len(manifests) < robots and not problems:
        unsaid.append(f"{robots - len(manifests)} mission(s) left no manifest and the run is called ok")
    line = "; ".join(parts) or "no mission manifests"
    return not unsaid, line + ("" if not unsaid else " -- DRILL FAILED: " + "; ".join(unsaid))


def one_run(nice: int, duration: float, out: Path, load: float = 0.0) -> dict:
    limit_s = duration + 180
    ref = reference_ms()
    hog = subprocess.Popen([sys.executable, "-c", _HOG, str(load), str(limit_s)]) if load > 0 else None
    try:
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.monotonic()
        proc = subprocess.run([sys.executable, "-m", "arena", "demo", "--duration", str(duration), "--quiet",
                               "--observer-nice", str(nice), "--out", str(out)],
                              capture_output=True, text=True, timeout=limit_s)
        wall = time.monotonic() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
    finally:
        if hog is not None:
            hog.kill()
            hog.wait()
    runs = sorted(out.glob("demo-*/summary.json"), key=lambda p: p.stat().st_mtime)
    if proc.returncode not in (0, 1) or not runs:   # 1 with a summary: a run that was not ok (it says why)
        raise SystemExit(f"arena demo failed ({proc.returncode}):\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}")
    summary = json.loads(runs[-1].read_text())
    from demo.report import read_manifests
    drill_ok, drill = closed_loop_drill(read_manifests(runs[-1].parent / "telemetry"), summary, robots=4)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"nice": nice, "ok": summary.get("ok"), "problems": summary.get("problems") or [],
            "rt": summary.get("sim_realtime") or {}, "scores": summary.get("scores") or {},
            "first_track_s": summary.get("first_track_s"), "cores": cpu / wall, "ref_ms": ref,
            "latency": summary.get("latency") or {}, "windows": summary.get("windows") or {},
            "drill_ok": drill_ok, "drill": drill}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pairs", type=int, default=2, help="pairs of runs, ours then baseline (default 2)")
    ap.add_argument("--duration", type=float, default=20.0, help="seconds of missions per run (default 20)")
    ap.add_argument("--nice", type=int, default=10, help="observers' niceness of 'ours' (default 10)")
    ap.add_argument("--load", type=float, default=0.0,
                    help="fraction of one core a competing process keeps busy during every run (default 0)")
    args = ap.parse_args(argv)
    if not 0 <= args.load <= 1:
        ap.error(f"--load is a fraction of one core in [0, 1], got {args.load}")
    print(f"arena demo, 4 robots, {args.duration:g} s missions, {args.pairs} pair(s) of runs "
          f"(machine: {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f})"
          + (f", another process busy {args.load:.0%} of a core" if args.load else ""))
    print(f"{'run':<26}{'RTF':>6}{'worst lag s':>13}{'at t s':>8}{'first track s':>15}{'MOTA':>7}"
          f"{'MAE cm':>8}{'cores':>7}{'ref ms':>8}{'lat p50 ms':>12}{'p99 ms':>8}{'windows lost':>14}")
    lags: dict[int, list[float]] = {args.nice: [], 0: []}
    drills: list[bool] = []
    with tempfile.TemporaryDirectory(prefix="bench-demo-") as tmp:
        for i in range(args.pairs):
            for nice in (args.nice, 0):
                r = one_run(nice, args.duration, Path(tmp), args.load)
                rt, s, lat, w = r["rt"], r["scores"], r["latency"], r["windows"]
                # dropped by the edge, found missing by the tracker or dropped from its queue
                lost = (str(w["edge_dropped"] + w["tracker_missed"] + w["tracker_queue_dropped"]) if w else "n/a")
                lags[nice].append(rt.get("worst_lag_s", float("nan")))
                label = f"{'ours' if nice else 'baseline'} (observers +{nice}) #{i + 1}"
                print(f"{label:<26}{rt.get('factor', float('nan')):6.2f}{rt.get('worst_lag_s', float('nan')):13.2f}"
                      f"{rt.get('worst_lag_at_s', float('nan')):8.1f}{r['first_track_s'] or float('nan'):15.1f}"
                      f"{_num(s.get('mota')):7.3f}{_num(s.get('mae_cm')):8.2f}{r['cores']:7.2f}{r['ref_ms']:8.1f}"
                      f"{lat.get('p50_ms', float('nan')):12.1f}{lat.get('p99_ms', float('nan')):8.1f}{lost:>14}",
                      flush=True)
                if not r["ok"]:
                    print(f"{'':<26}NOT OK: " + "; ".join(r["problems"]), flush=True)
                print(f"{'':<26}closed loop: {r['drill']}", flush=True)
                drills.append(r["drill_ok"])
    ours, base = statistics.mean(lags[args.nice]), statistics.mean(lags[0])
    print(f"mean worst lag: ours {ours:.2f} s, baseline {base:.2f} s -> baseline/ours {base / ours:.1f}x"
          if ours > 0 else f"mean worst lag: ours {ours:.2f} s, baseline {base:.2f} s")
    print(f"drill: {sum(drills)} of {len(drills)} runs had every mission closed-loop or named in the summary")
    return 0 if all(drills) else 1


if __name__ == "__main__":
    sys.exit(main())

"""Tracker accuracy on simulated scenarios mirroring the paper, beside the paper's numbers.

For each scenario (1-4 robots x circle/square x 50/100 % power, 12 s; 8 robots; dimmed
light; stop-and-go; crossing paths) the simulator records events with exact truth, the
tracker runs offline (10 ms slices, t_a = 100 ms) with ONE configuration, and
``groundtruth.metrics.evaluate`` scores it (10 cm gate, a robot counting from its first
motion). Rows are printed for ``fleet`` (default detector) and ``idtrack`` (the paper's
detector and Algorithm 1), with the paper's table (DESIGN.md) beside them.

    python bench/bench_tracker_accuracy.py                 # everything (several minutes)
    python bench/bench_tracker_accuracy.py --quick         # 1 and 4 robots, 6 s
    python bench/bench_tracker_accuracy.py --only "4 square 1.0" --trackers fleet
    python bench/bench_tracker_accuracy.py --run runs/demo-20261124-004500 --trackers fleet

``--run RUN_DIR`` (repeatable) replays a recorded ``arena demo`` run instead: its ``events.raw``
through the tracker offline, scored against its ``truth.csv`` until the missions ended (as the
demo scores it). The demo's robots drive closed-loop, so their corners (slow creeping, few
events) differ from the scripted scenarios. ``flips %`` is the share of matched frames whose
heading is more than 60 degrees off; ``p99 cm`` the 99th percentile of the position error.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from groundtruth.metrics import TRACK_DTYPE, TRUTH_DTYPE, evaluate
from simulator.scenarios import Scenario, generate
from tracker.calibration import Calibration
from tracker.pipeline import Pipeline, iter_slices

#: The paper's table (DESIGN.md): (n, pattern) -> ((precision, recall, MAE cm, MOTA) at 100 %, at 50 %)
PAPER = {
    (1, "circle"): ((1, 1, 1.22, 1), (1, 1, 2.16, 1)),
    (2, "circle"): ((1, 1, 2.00, 1), (1, 1, 2.82, 1)),
    (3, "circle"): ((1, 1, 2.05, 1), (1, 1, 3.78, 1)),
    (4, "circle"): ((1, 0.94, 4.32, 0.94), (1, 0.93, 5.92, 0.93)),
    (1, "square"): ((1, 1, 2.36, 1), (1, 1, 3.5, 1)),
    (2, "square"): ((1, 1, 3.85, 1), (1, 1, 3.2, 1)),
    (3, "square"): ((1, 1, 2.9, 1), (1, 1, 4.96, 1)),
    (4, "square"): ((1, 0.95, 4.31, 0.95), (1, 1, 6.77, 1)),
}
MODES = {"fleet": dict(tracker="fleet", detector="default"),
         "idtrack": dict(tracker="idtrack", detector="paper")}


def scenarios(quick: bool) -> list[tuple[str, Scenario]]:
    dur = 6.0 if quick else 12.0
    out = []
    for n in ((1, 4) if quick else (1, 2, 3, 4)):
        for pattern in ("circle", "square"):
            for power in (1.0, 0.5):
                out.append((f"{n} {pattern} {power}", Scenario(n, pattern, power, dur, seed=n)))
    out.append(("8 circle 1.0", Scenario(8, "circle", 1.0, dur, seed=8)))
    out.append(("4 square 1.0 dimmed", Scenario(4, "square", 1.0, dur, lighting="dimmed", seed=4)))
    out.append(("2 stopgo 1.0", Scenario(2, "stopgo", 1.0, dur, seed=2)))
    out.append(("3 cross 1.0", Scenario(3, "cross", 1.0, dur, seed=3)))
    return out


def truth_table(rec) -> np.ndarray:
    tr = np.empty(rec.truth.size, dtype=TRUTH_DTYPE)
    for name in ("t_us", "x_m", "y_m", "yaw_rad", "vx_mps", "vy_mps"):
        tr[name] = rec.truth[name]
    tr["robot"] = np.asarray(rec.robot_names, dtype=object)[rec.truth["robot"]]
    return tr


def run_tracker(rec, tracker: str, detector: str, slice_us: int = 10_000) -> tuple[np.ndarray, float]:
    """Tracks (TRACK_DTYPE) of one recording and the median per-slice time (ms)."""
    cal = Calibration.from_dict(rec.calibration)
    pipe = Pipeline(cal, tracker=tracker, detector=detector)
    rows, times = [], []
    chunks = (rec.events[i:i + 50_000] for i in range(0, rec.events.size, 50_000))
    for t_end, ev in iter_slices(chunks, slice_us, start_us=0):
        t0 = time.perf_counter()
        tracks = pipe.push(ev, t_end)
        times.append(time.perf_counter() - t0)
        for t in tracks:
            rows.append((t.t_us, str(t.track_id), t.robot or "", t.x, t.y, t.yaw, t.vx, t.vy, t.u, t.v,
                         t.state, t.n_events))
    return np.array(rows, dtype=TRACK_DTYPE), float(np.median(times) * 1e3)


def recorded_runs(dirs: list[str]) -> list[tuple[str, SimpleNamespace, np.ndarray]]:
    """(label, recording with ``events`` and ``calibration``, truth) of recorded demo runs."""
    from arena.formats import read_events
    from groundtruth.metrics import read_truth_csv

    out = []
    for d in map(Path, dirs):
        missing = [f for f in ("events.raw", "truth.csv", "cam0.calib.json") if not (d / f).is_file()]
        if missing:
            raise SystemExit(f"bench_tracker_accuracy: {d} is not an arena demo run folder (no {', '.join(missing)})")
        events, _, _ = read_events(d / "events.raw")
        truth = read_truth_csv(d / "truth.csv")
        summary = json.loads((d / "summary.json").read_text()) if (d / "summary.json").exists() else {}
        if summary.get("scored_until_us"):
            truth = truth[truth["t_us"] <= summary["scored_until_us"]]
        rec = SimpleNamespace(events=events, calibration=json.loads((d / "cam0.calib.json").read_text()))
        out.append((d.name[-22:], rec, truth))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fewer, shorter scenarios")
    ap.add_argument("--only", action="append", help="run only this scenario label (repeatable)")
    ap.add_argument("--trackers", default="fleet,idtrack", help="comma list of fleet,idtrack")
    ap.add_argument("--run", action="append", metavar="RUN_DIR",
                    help="replay a recorded arena demo run folder instead of the scenarios (repeatable)")
    args = ap.parse_args(argv)
    modes = [m for m in args.trackers.split(",") if m]
    for m in modes:
        if m not in MODES:
            print(f"unknown tracker {m!r}; choose from {', '.join(MODES)}", file=sys.stderr)
            return 2
    rows = []
    runs = recorded_runs(args.run) if args.run else None   # read first: a wrong folder fails at once
    hdr = (f"{'scenario':<22} {'tracker':<8} {'prec':>6} {'rec':>6} {'MAE cm':>7} {'p99 cm':>7} {'hdg deg':>8} {'flips %':>8} "
           f"{'MOTA':>6} {'IDsw':>4} {'ms/sl':>6} | paper prec/rec/MAE/MOTA")
    print(hdr)
    print("-" * len(hdr))

    def cases():
        if runs is not None:
            yield from ((label, rec, truth, None) for label, rec, truth in runs)
            return
        for label, sc in scenarios(args.quick):
            if not args.only or label in args.only:
                rec = generate(sc)
                yield label, rec, truth_table(rec), sc

    for label, rec, truth, sc in cases():
        for m in modes:
            tracks, ms = run_tracker(rec, **MODES[m])
            s = evaluate(tracks, truth, gate_m=0.10)
            err = np.abs(s.matches["yaw_err_rad"]) if s.matches is not None else np.zeros(0)
            err = err[np.isfinite(err)]
            flips = 100.0 * float(np.mean(err > np.radians(60))) if err.size else float("nan")
            p99 = float(np.percentile(s.matches["err_m"], 99)) * 100 if s.matches is not None and len(s.matches) \
                else float("nan")
            paper = ""
            if sc is not None and (sc.n_robots, sc.pattern) in PAPER and sc.lighting == "full":
                p = PAPER[(sc.n_robots, sc.pattern)][0 if sc.power == 1.0 else 1]
                paper = f"{p[0]:.2f}/{p[1]:.2f}/{p[2]:.2f}/{p[3]:.2f}"
            elif sc is not None and sc.lighting == "dimmed" and sc.n_robots == 4:
                paper = "1.00/0.73/10.05/0.72"
            print(f"{label:<22} {m:<8} {s.precision:6.3f} {s.recall:6.3f} {s.mae_cm:7.2f} "
                  f"{p99:7.2f} {s.heading_mae_deg:8.1f} {flips:8.2f} {s.mota:6.3f} {s.id_switches:4d} {ms:6.2f} | {paper}",
                  flush=True)
            rows.append((label, m, s))
    for m in modes:
        sel = [s for _, mm, s in rows if mm == m]
        if sel:
            print(f"{m}: mean MOTA {np.mean([s.mota for s in sel]):.3f}, worst MOTA "
                  f"{min(s.mota for s in sel):.3f}, ID switches {sum(s.id_switches for s in sel)}, "
                  f"mean MAE {np.nanmean([s.mae_cm for s in sel]):.2f} cm")
    return 0


if __name__ == "__main__":
    sys.exit(main())

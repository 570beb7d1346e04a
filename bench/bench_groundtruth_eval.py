"""Scorer benchmark: groundtruth.metrics.evaluate vs motmetrics (the baseline) on the same scene.

A synthetic 4-robot, 60 s run at 100 Hz (24 000 track rows) with noise, misses, ID switches and
false positives; truth sampled at the frame times so both scorers see identical distances.
Prints MOTA/IDF1 of both (must agree to 4 decimals) and the time of each, with the ratio.
motmetrics gets CLEAR MOT + IDF1 only; ours also computes HOTA, heading and per-robot figures.

    python bench/bench_groundtruth_eval.py [--robots 4] [--seconds 60]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from arena.formats.tables import TRACK_DTYPE, TRUTH_DTYPE
from groundtruth.metrics import evaluate


def scene(n_robots: int, seconds: float, seed: int = 0):
    rng = np.random.default_rng(seed)
    n_frames = int(seconds * 100)
    pos = rng.uniform(0.2, 1.6, size=(n_robots, 2))
    ids = [str(i + 1) for i in range(n_robots)]
    nxt = n_robots + 1
    truth, tracks = [], []
    for k in range(n_frames):
        t = k * 10_000
        pos = np.clip(pos + rng.normal(0, 0.004, pos.shape), 0.05, 1.78)
        for i in range(n_robots):
            truth.append((t, f"r{i}", pos[i, 0], pos[i, 1], 0.0, 0.3, 0.0))
            if rng.random() < 0.002:
                ids[i], nxt = str(nxt), nxt + 1
            if rng.random() < 0.03:
                continue
            e = rng.normal(0, 0.02, 2)
            tracks.append((t, ids[i], "", pos[i, 0] + e[0], pos[i, 1] + e[1], rng.normal(0, 0.1),
                           np.nan, np.nan, np.nan, np.nan, "confirmed", 100))
        if rng.random() < 0.02:
            x, y = rng.uniform(0, 1.83, 2)
            tracks.append((t, "999", "", x, y, np.nan, np.nan, np.nan, np.nan, np.nan, "confirmed", 50))
    return np.array(tracks, dtype=TRACK_DTYPE), np.array(truth, dtype=TRUTH_DTYPE)


def run_motmetrics(tracks, truth, gate):
    np.asfarray = getattr(np, "asfarray", lambda a, dtype=float: np.asarray(a, dtype=dtype))  # numpy 2
    import motmetrics as mm

    gid = {r: i for i, r in enumerate(np.unique(truth["robot"]))}
    hid = {h: 1000 + i for i, h in enumerate(np.unique(tracks["track_id"]))}
    acc = mm.MOTAccumulator(auto_id=False)
    t_tr = np.split(tracks, np.flatnonzero(np.diff(tracks["t_us"])) + 1)
    by_t = {int(c["t_us"][0]): c for c in t_tr}
    for k, t in enumerate(np.unique(truth["t_us"])):
        g = truth[truth["t_us"] == t]
        h = by_t.get(int(t), tracks[:0])
        d = np.hypot(g["x_m"][:, None] - h["x_m"][None, :], g["y_m"][:, None] - h["y_m"][None, :])
        d[d > gate] = np.nan
        acc.update([gid[r] for r in g["robot"]], [hid[i] for i in h["track_id"]], d, frameid=k)
    summary = mm.metrics.create().compute(acc, metrics=["mota", "idf1"], name="x").iloc[0]
    return float(summary["mota"]), float(summary["idf1"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--robots", type=int, default=4)
    ap.add_argument("--seconds", type=float, default=60.0)
    a = ap.parse_args()
    tracks, truth = scene(a.robots, a.seconds)
    t0 = time.perf_counter()
    s = evaluate(tracks, truth, gate_m=0.10, moved_only=False)
    t_ours = time.perf_counter() - t0
    t0 = time.perf_counter()
    mota, idf1 = run_motmetrics(tracks, truth, 0.10)
    t_mm = time.perf_counter() - t0
    print(f"scene: {a.robots} robots, {a.seconds:g} s at 100 Hz, {len(tracks)} track rows, "
          f"{s.n_frames} frames, {s.id_switches} ID switches, {s.n_fp} FP")
    print(f"{'':22}{'ours':>12}{'motmetrics':>14}{'ratio':>9}")
    print(f"{'MOTA':22}{s.mota:12.4f}{mota:14.4f}")
    print(f"{'IDF1':22}{s.idf1:12.4f}{idf1:14.4f}")
    print(f"{'HOTA':22}{s.hota:12.4f}{'-':>14}")
    print(f"{'time (s)':22}{t_ours:12.2f}{t_mm:14.2f}{t_mm / t_ours:8.1f}x")
    agree = round(s.mota, 4) == round(mota, 4) and round(s.idf1, 4) == round(idf1, 4)
    print(f"agreement to 4 decimals: {'yes' if agree else 'NO'}")


if __name__ == "__main__":
    main()

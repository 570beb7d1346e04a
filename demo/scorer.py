"""Live scorer: match the tracks to the ground truth as they arrive and print a live table.

Subscribes to ``arena/robots/*`` (tracks), ``arena/groundtruth/*`` (webcam poses) and
``arena/sim/truth/*`` (the simulator's exact poses, when present) and, once a second, prints one
line per robot: position, heading, speed, state, error against the webcam ground truth and the
exact truth, and the end-to-end latency (edge publish -> track received here). At the end it prints
a JSON summary line (``SUMMARY {...}``) with latency percentiles.

Run by ``arena demo``; also usable against a live lab: ``python -m demo.scorer -e tcp/HOST:7447``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import threading
import time

import numpy as np
from scipy.optimize import linear_sum_assignment

from arena.messages import GroundTruthPose, MessageError, Track, decode
from arena.service import Service, stop_on_signals
from arena.session import add_zenoh_arguments, open_session

FRESH_S = 0.5  # a track or pose older than this (receive time) is not shown as current


class LiveScorer:
    """Latest tracks and truths, matched on demand (pure state; fed by the subscriber callbacks)."""

    def __init__(self, gate_m: float = 0.20):
        self.gate_m = gate_m
        self.lock = threading.Lock()
        self.tracks: dict[int, tuple[float, Track]] = {}
        self.truth: dict[str, tuple[float, GroundTruthPose]] = {}
        self.gt: dict[str, tuple[float, GroundTruthPose]] = {}
        self.latency_ms: list[float] = []
        self.bad = 0
        self.errors_cm: list[float] = []

    def on_track(self, payload: bytes, now_ns: int) -> None:
        try:
            t = decode(payload)
        except MessageError:
            self.bad += 1
            return
        if not isinstance(t, Track):
            return
        with self.lock:
            self.tracks[t.track_id] = (now_ns / 1e9, t)
            if t.edge_publish_ns:
                self.latency_ms.append((now_ns - t.edge_publish_ns) / 1e6)
                if len(self.latency_ms) > 200_000:
                    del self.latency_ms[:100_000]

    def on_pose(self, payload: bytes, now_ns: int, exact: bool) -> None:
        try:
            p = decode(payload)
        except MessageError:
            self.bad += 1
            return
        if isinstance(p, GroundTruthPose):
            with self.lock:
                (self.truth if exact else self.gt)[p.robot] = (now_ns / 1e9, p)

    def rows(self, now_s: float) -> list[dict]:
        """One row per robot known from the truth (or ground truth), with its matched track."""
        with self.lock:
            ref = {r: p for r, (ts, p) in (self.truth or self.gt).items() if now_s - ts < FRESH_S}
            gt = {r: p for r, (ts, p) in self.gt.items() if now_s - ts < FRESH_S}
            tracks = [t for ts, t in self.tracks.values() if now_s - ts < FRESH_S]
        robots = sorted(ref)
        match: dict[str, Track] = {}
        if robots and tracks:
            d = np.array([[math.hypot(t.x - ref[r].x, t.y - ref[r].y) for t in tracks] for r in robots])
            for i, j in zip(*linear_sum_assignment(d)):
                if d[i, j] <= self.gate_m:
                    match[robots[i]] = tracks[j]
        rows = []
        for r in robots:
            t = match.get(r)
            row = {"robot": r, "track": None}
            if t is not None:
                err = math.hypot(t.x - ref[r].x, t.y - ref[r].y) * 100
                self.errors_cm.append(err)
                row.update(track=t.track_id, x=t.x, y=t.y, yaw=t.yaw, state=t.state,
                           speed=math.hypot(t.vx or 0.0, t.vy or 0.0), err_truth_cm=err if self.truth else None)
                if r in gt:
                    row["err_gt_cm"] = math.hypot(t.x - gt[r].x, t.y - gt[r].y) * 100
            rows.append(row)
        return rows

    def latency_percentiles(self) -> dict:
        with self.lock:
            lat = np.array(self.latency_ms)
        if lat.size == 0:
            return {"n": 0}
        return {"n": int(lat.size), "p50_ms": float(np.percentile(lat, 50)), "p99_ms": float(np.percentile(lat, 99))}


def format_rows(rows: list[dict], lat: dict) -> str:
    """The live table as text (cm and degrees for people)."""
    head = f"{'robot':<8} {'track':>5} {'x cm':>7} {'y cm':>7} {'head°':>6} {'m/s':>5} {'state':<10} {'err truth':>9} {'err webcam':>10}"
    lines = [head]
    for r in rows:
        if r["track"] is None:
            lines.append(f"{r['robot']:<8} {'-':>5}  (no track within the gate)")
            continue
        yaw = f"{math.degrees(r['yaw']):6.0f}" if r.get("yaw") is not None else f"{'-':>6}"
        et = f"{r['err_truth_cm']:7.1f}cm" if r.get("err_truth_cm") is not None else f"{'-':>9}"
        eg = f"{r['err_gt_cm']:8.1f}cm" if r.get("err_gt_cm") is not None else f"{'-':>10}"
        lines.append(f"{r['robot']:<8} {r['track']:>5} {r['x'] * 100:7.1f} {r['y'] * 100:7.1f} {yaw} "
                     f"{r['speed']:5.2f} {r['state']:<10} {et} {eg}")
    if lat.get("n"):
        lines.append(f"latency edge->here: p50 {lat['p50_ms']:.1f} ms, p99 {lat['p99_ms']:.1f} ms over {lat['n']} tracks")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m demo.scorer", description=__doc__.split("\n\n")[0])
    p.add_argument("--period", type=float, default=1.0, help="seconds between table prints")
    p.add_argument("--gate-cm", type=float, default=20.0, help="match distance for the live table")
    add_zenoh_arguments(p)
    args = p.parse_args(argv)
    stop = stop_on_signals()
    scorer = LiveScorer(gate_m=args.gate_cm / 100)
    try:
        with open_session(args, wait_s=None) as session, Service(session, "scorer", "live") as svc:
            session.declare_subscriber("arena/robots/*", lambda s: scorer.on_track(bytes(s.payload), time.time_ns()))
            session.declare_subscriber("arena/groundtruth/*",
                                       lambda s: scorer.on_pose(bytes(s.payload), time.time_ns(), False))
            session.declare_subscriber("arena/sim/truth/*",
                                       lambda s: scorer.on_pose(bytes(s.payload), time.time_ns(), True))
            print("scorer ready", flush=True)
            while not stop.wait(args.period):
                rows = scorer.rows(time.time())
                lat = scorer.latency_percentiles()
                print("TABLE " + json.dumps({"rows": rows, "latency": lat}), flush=True)
                if lat.get("n"):
                    svc.gauge("latency_p50_ms", round(lat["p50_ms"], 2))
                    svc.gauge("latency_p99_ms", round(lat["p99_ms"], 2))
                svc.count("rejected", 0)
    except KeyboardInterrupt:
        pass
    print("SUMMARY " + json.dumps({"latency": scorer.latency_percentiles(), "rejected": scorer.bad}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

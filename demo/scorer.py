"""Live scorer: match the tracks to the ground truth as they arrive and print a live table.

Subscribes to ``arena/robots/*`` (tracks), ``arena/groundtruth/*`` (webcam poses) and
``arena/sim/truth/*`` (the simulator's exact poses, when present) and, once a second, prints one
line per robot: position, heading, speed, state, error against the webcam ground truth and the
exact truth (each truth pose against the track interpolated at that pose's time stamp, on one
clock: see :class:`LiveScorer`), and the end-to-end latency (edge publish -> track received
here). At the end it prints a JSON summary line (``SUMMARY {...}``) with latency percentiles.

Run by ``arena demo``; also usable against a live lab: ``python -m demo.scorer -e tcp/HOST:7447``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import threading
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from arena.messages import GroundTruthPose, MessageError, Track, decode
from arena.service import Service, stop_on_signals
from arena.session import add_zenoh_arguments, open_session
from arena.timematch import NO_OVERLAP, PoseHistory, TimedError, timed_error

FRESH_S = 0.5  # a track or pose older than this (receive time) is not shown as current
STALE_S = 10.0  # a track or robot not heard from for this long is forgotten (with its pose history)


@dataclass
class _Seen:
    """The latest message of a track or robot, when it was received (s), and its poses by stamp."""

    seen_s: float
    msg: Track | GroundTruthPose
    hist: PoseHistory = field(default_factory=PoseHistory)  # by stamp_us
    hist_host: PoseHistory | None = None  # tracks: by host_ns // 1000, when known


class LiveScorer:
    """Recent tracks and truths, matched on demand (pure state; fed by the subscriber callbacks).

    Errors are taken at one time stamp: each truth pose against the track interpolated at the
    pose's stamp (:func:`viewer.state.timed_error`; the simulator's truth is on the tracks' sensor
    clock, the webcam's on ``gt_clock``), never between the latest messages received, which
    differ by however late each arrived. No common time: no figure (``err_*_cm`` None with
    ``err_*_note`` saying so).
    """

    def __init__(self, gate_m: float = 0.20, gt_clock: str = "auto"):
        if gt_clock not in ("auto", "sensor", "host"):
            raise ValueError(f"gt_clock must be 'auto', 'sensor' or 'host', got {gt_clock!r}")
        self.gate_m = gate_m
        self.gt_clock = gt_clock
        self.lock = threading.Lock()
        self.tracks: dict[int, _Seen] = {}
        self.truth: dict[str, _Seen] = {}
        self.gt: dict[str, _Seen] = {}
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
            s = self.tracks.get(t.track_id)
            if s is None:
                s = self.tracks[t.track_id] = _Seen(now_ns / 1e9, t, hist_host=PoseHistory())
            s.seen_s, s.msg = now_ns / 1e9, t
            s.hist.add(t.stamp_us, t.x, t.y)
            if t.host_ns is not None:
                s.hist_host.add(t.host_ns // 1000, t.x, t.y)
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
                poses = self.truth if exact else self.gt
                s = poses.get(p.robot)
                if s is None:
                    s = poses[p.robot] = _Seen(now_ns / 1e9, p)
                s.seen_s, s.msg = now_ns / 1e9, p
                s.hist.add(p.stamp_us, p.x, p.y)

    def rows(self, now_s: float) -> list[dict]:
        """One row per robot known from the truth (or ground truth), with its matched track.

        Robots and tracks are paired (within ``gate_m``) by their time-matched distance; a pair
        with no common time falls back to the distance between the latest poses for the pairing
        only (its error is then not given)."""
        with self.lock:
            for d in (self.tracks, self.truth, self.gt):
                for k in [k for k, s in d.items() if now_s - s.seen_s > STALE_S]:
                    del d[k]
            exact = bool(self.truth)
            ref = {r: s for r, s in (self.truth or self.gt).items() if now_s - s.seen_s < FRESH_S}
            gt = {r: s for r, s in self.gt.items() if now_s - s.seen_s < FRESH_S}
            tracks = [s for s in self.tracks.values() if now_s - s.seen_s < FRESH_S]
            robots = sorted(ref)
            # the simulator's truth is on the tracks' sensor clock; the webcam's on gt_clock
            ref_clock = "sensor" if exact else self.gt_clock
            timed = [[timed_error(t.hist, t.hist_host, ref[r].hist, ref_clock) for t in tracks] for r in robots]
            match: dict[str, int] = {}
            if robots and tracks:
                d = np.array([[te.err_m if te is not None else
                               math.hypot(t.msg.x - ref[r].msg.x, t.msg.y - ref[r].msg.y) for te, t in zip(row, tracks)]
                              for r, row in zip(robots, timed)])
                for i, j in zip(*linear_sum_assignment(d)):
                    if d[i, j] <= self.gate_m:
                        match[robots[i]] = j
            rows = []
            for i, r in enumerate(robots):
                j = match.get(r)
                row = {"robot": r, "track": None}
                if j is not None:
                    s, t = tracks[j], tracks[j].msg
                    te = timed[i][j]
                    row.update(track=t.track_id, x=t.x, y=t.y, yaw=t.yaw, state=t.state,
                               speed=math.hypot(t.vx or 0.0, t.vy or 0.0), err_truth_cm=None, err_gt_cm=None)
                    if exact:
                        row.update(_err_fields("truth", te))
                    if r in gt:
                        row.update(_err_fields("gt", te if not exact else
                                               timed_error(s.hist, s.hist_host, gt[r].hist, self.gt_clock)))
                    if te is not None:
                        self.errors_cm.append(te.err_m * 100)
                rows.append(row)
        return rows

    def latency_percentiles(self) -> dict:
        with self.lock:
            lat = np.array(self.latency_ms)
        if lat.size == 0:
            return {"n": 0}
        return {"n": int(lat.size), "p50_ms": float(np.percentile(lat, 50)), "p99_ms": float(np.percentile(lat, 99))}


def _err_fields(what: str, te: TimedError | None) -> dict:
    """A row's error figure against ``what`` (truth, gt): cm at one stamp, or why there is none."""
    if te is None:
        return {f"err_{what}_cm": None, f"err_{what}_note": NO_OVERLAP}
    return {f"err_{what}_cm": te.err_m * 100, f"err_{what}_clock": te.clock,
            f"err_{what}_behind_ms": te.behind_us / 1000}


def _err_cell(row: dict, what: str, width: int) -> str:
    v = row.get(f"err_{what}_cm")
    if v is not None:
        return f"{v:{width - 2}.1f}cm"
    return f"{row.get(f'err_{what}_note') or '-':>{width}}"


def format_rows(rows: list[dict], lat: dict) -> str:
    """The live table as text (cm and degrees for people). The errors compare the track at each
    truth pose's own time stamp; "n/a (no overlap)": no common time (on one clock) yet."""
    w = len(NO_OVERLAP)
    head = (f"{'robot':<8} {'track':>5} {'x cm':>7} {'y cm':>7} {'head°':>6} {'m/s':>5} {'state':<10} "
            f"{'err truth':>{w}} {'err webcam':>{w}}")
    lines = [head]
    for r in rows:
        if r["track"] is None:
            lines.append(f"{r['robot']:<8} {'-':>5}  (no track within the gate)")
            continue
        yaw = f"{math.degrees(r['yaw']):6.0f}" if r.get("yaw") is not None else f"{'-':>6}"
        lines.append(f"{r['robot']:<8} {r['track']:>5} {r['x'] * 100:7.1f} {r['y'] * 100:7.1f} {yaw} "
                     f"{r['speed']:5.2f} {r['state']:<10} {_err_cell(r, 'truth', w)} {_err_cell(r, 'gt', w)}")
    if lat.get("n"):
        lines.append(f"latency edge->here: p50 {lat['p50_ms']:.1f} ms, p99 {lat['p99_ms']:.1f} ms over {lat['n']} tracks")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m demo.scorer", description=__doc__.split("\n\n")[0])
    p.add_argument("--period", type=float, default=1.0, help="seconds between table prints")
    p.add_argument("--gate-cm", type=float, default=20.0, help="match distance for the live table")
    p.add_argument("--gt-clock", choices=("auto", "sensor", "host"), default="auto",
                   help="clock of the webcam's stamps: the tracks' sensor clock (arena groundtruth --clock\n"
                        "stream on the simulator), the host clock (compared with the tracks' host_ns), or\n"
                        "auto: whichever of the two the stamps fall in (default)")
    add_zenoh_arguments(p)
    args = p.parse_args(argv)
    stop = stop_on_signals()
    scorer = LiveScorer(gate_m=args.gate_cm / 100, gt_clock=args.gt_clock)
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

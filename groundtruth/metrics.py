"""Scoring tracks against ground truth: the one scorer every benchmark in the project uses.

Pure numpy/scipy: no files, no clocks, no Zenoh. The tracks and truth CSVs, their dtypes
(``TRACK_DTYPE``, ``TRUTH_DTYPE``), readers and writers are :mod:`arena.formats.tables`.

Inputs (arena frame: metres, yaw in rad counter-clockwise from +x; times in µs):

* tracks, from ``read_tracks_csv`` (header ``t_us,track_id,robot,x_m,y_m,yaw_rad,vx_mps,vy_mps,
  u_px,v_px,state,n_events,host_ns``, empty where unknown), one row per track per tracker update;
* truth, from ``read_truth_csv``: the simulator's exact truth (``t_us,robot,x_m,y_m,yaw_rad,vx_mps,
  vy_mps`` at >= 200 Hz) or the webcam ground truth (``t_us,robot,x_m,y_m,yaw_rad,u_px,v_px,
  detector`` at ~24 fps).

How a run is scored (``evaluate``):

1. **Frames** are the tracks' distinct update times (rows within ``merge_us`` of each other form one
   frame). Gaps longer than 2.5 update periods between the first and last update are filled with
   empty frames, so a tracker that goes silent is charged with misses. Frames outside the truth's
   time span are dropped (counted in ``n_frames_dropped``).
2. **Truth** is interpolated at each track row's own time (linear x/y, circular yaw); a robot is
   present at a frame inside its truth span unless its truth has a hole longer than ``max_gap_us``
   there. A robot **counts** from the first time it has moved (speed > ``move_speed_mps`` or
   displaced > ``move_dist_m`` from its first pose). Before that it is a *don't-care* object: a
   track matched to it within the gate is removed from the frame (neither TP nor FP), as in the
   MOTChallenge distractor rule.
3. **CLEAR MOT** (Bernardin & Stiefelhagen 2008): a robot's previous track is kept if it is still
   within the gate, the rest is matched by the Hungarian algorithm on Euclidean distance with the
   gate; an ID switch is a robot matched to another track than the one it was last matched to;
   fragmentations = per robot, tracked segments - 1 (TrackEval's definition).
   ``MOTA = 1 - (FN + FP + IDSW) / n_gt``; ``MOTP`` is TrackEval's: mean similarity over matches,
   similarity ``s = max(0, 1 - d / gate)`` (1 = perfect); ``mae_cm`` is the mean distance.
   With no ground truth (``n_gt = 0``: no truth rows, no frame inside their span, or no robot
   that moved) MOTA, IDF1, HOTA and every other ratio over it are NaN (``None`` in
   :meth:`Scores.to_dict`, "n/a" in reports): nothing was measured, so nothing is claimed.
4. **IDF1** (Ristani et al. 2016): global one-to-one matching of robot and track ids maximising the
   number of frames in which the pair is within the gate.
5. **HOTA** (Luiten et al. 2021): implemented here, following the paper and TrackEval's reference
   code step for step, with the distance similarity ``s`` above instead of IoU (alpha = 0.05 ...
   0.95: at alpha = 0.5 a match must be within half the gate). TrackEval 1.3 imports with numpy 2
   but pulls ``opencv-python`` (which clobbers our ``opencv-python-headless``), so it is not a
   dependency; the tests check this implementation against it when it is installed.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Iterable, Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment

from arena.messages import TENTATIVE

HOTA_ALPHAS = np.arange(0.05, 0.99, 0.05)


# ----------------------------------------------------------------------------------------------
# Alignment: frames, interpolated truth, don't-care filtering


@dataclass
class Frame:
    """One scoring frame after alignment (only counted robots and kept tracks).

    ``gt`` and ``trk`` index ``Alignment.robots`` / ``Alignment.track_ids``; ``dist_m`` is
    (len(gt), len(trk)) Euclidean distance in metres between each track row and the robot's truth
    interpolated at that row's time; ``gt_yaw``/``trk_yaw`` in rad (NaN if unknown).
    """

    t_us: int
    gt: np.ndarray
    trk: np.ndarray
    dist_m: np.ndarray
    gt_xy: np.ndarray
    trk_xy: np.ndarray
    gt_yaw: np.ndarray
    trk_yaw: np.ndarray


@dataclass
class Alignment:
    """Tracks and truth put on common frames: the input every metric function takes."""

    robots: list[str]
    track_ids: list[str]
    frames: list[Frame]
    gate_m: float
    n_frames_dropped: int = 0
    n_ignored: int = 0  # track rows matched to robots that had not moved yet


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _frame_groups(times: np.ndarray, merge_us: int) -> tuple[np.ndarray, np.ndarray]:
    """Group sorted-unique times: returns (frame time per group, group index per input time)."""
    uniq = np.unique(times)
    starts = [0]
    for i in range(1, len(uniq)):
        if uniq[i] - uniq[starts[-1]] > merge_us:
            starts.append(i)
    starts = np.asarray(starts)
    group_of_uniq = np.searchsorted(starts, np.arange(len(uniq)), side="right") - 1
    return uniq[starts], group_of_uniq[np.searchsorted(uniq, times)]


def _fill_gaps(frame_t: np.ndarray) -> np.ndarray:
    if len(frame_t) < 3:
        return frame_t
    dt = float(np.median(np.diff(frame_t)))
    if dt <= 0:
        return frame_t
    extra = []
    for a, b in zip(frame_t[:-1], frame_t[1:]):
        if b - a > 2.5 * dt:
            extra.extend(np.arange(a + dt, b - 0.5 * dt, dt).astype(np.int64))
    return np.sort(np.concatenate([frame_t, np.asarray(extra, dtype=np.int64)])) if extra else frame_t


class _RobotTruth:
    """Truth of one robot, interpolable in time (µs -> m, rad)."""

    def __init__(self, rows: np.ndarray, move_speed_mps: float, move_dist_m: float, max_gap_us: int):
        rows = rows[np.isfinite(rows["x_m"]) & np.isfinite(rows["y_m"])]
        rows = rows[np.argsort(rows["t_us"], kind="stable")]
        self.t = rows["t_us"].astype(np.int64)
        self.x = rows["x_m"]
        self.y = rows["y_m"]
        yaw = rows["yaw_rad"]
        self.has_yaw = bool(np.all(np.isfinite(yaw))) and len(yaw) > 0
        self.yaw_unwrapped = np.unwrap(yaw) if self.has_yaw else yaw
        self.max_gap_us = max_gap_us
        self.t_moved = self._first_motion(rows, move_speed_mps, move_dist_m)

    def _first_motion(self, rows, v_min, d_min) -> float:
        if len(self.t) == 0:
            return math.inf
        moved = np.hypot(self.x - self.x[0], self.y - self.y[0]) > d_min
        if np.any(np.isfinite(rows["vx_mps"])):
            speed = np.hypot(np.nan_to_num(rows["vx_mps"]), np.nan_to_num(rows["vy_mps"]))
            moved |= speed > v_min
        elif len(self.t) > 1:
            # speed over a >= 0.2 s baseline, so measurement noise at high rate is not mistaken for motion
            j = np.searchsorted(self.t, self.t - 200_000, side="right") - 1
            ok = j >= 0
            dt = (self.t[ok] - self.t[j[ok]]) * 1e-6
            sp = np.hypot(self.x[ok] - self.x[j[ok]], self.y[ok] - self.y[j[ok]]) / np.maximum(dt, 1e-9)
            moved[np.flatnonzero(ok)[sp > v_min]] = True
        idx = np.flatnonzero(moved)
        return float(self.t[idx[0]]) if len(idx) else math.inf

    def present(self, t: np.ndarray) -> np.ndarray:
        """True where ``t`` (µs) is inside the truth span and not inside a hole > max_gap_us."""
        if len(self.t) == 0:
            return np.zeros(len(t), dtype=bool)
        inside = (t >= self.t[0]) & (t <= self.t[-1])
        k = np.clip(np.searchsorted(self.t, t, side="left"), 0, len(self.t) - 1)
        exact = self.t[k] == t
        gap = self.t[k] - self.t[np.maximum(k - 1, 0)]
        return inside & (exact | (gap <= self.max_gap_us))

    def at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        tf = t.astype(np.float64)
        tt = self.t.astype(np.float64)
        x = np.interp(tf, tt, self.x)
        y = np.interp(tf, tt, self.y)
        yaw = _wrap(np.interp(tf, tt, self.yaw_unwrapped)) if self.has_yaw else np.full(len(t), np.nan)
        return x, y, yaw


def align(tracks: np.ndarray, truth: np.ndarray, gate_m: float = 0.10, *, moved_only: bool = True,
          move_speed_mps: float = 0.01, move_dist_m: float = 0.01, merge_us: int = 1000,
          max_gap_us: int = 500_000, exclude_states: Iterable[str] = (TENTATIVE,)) -> Alignment:
    """Put tracks and truth on common frames (see the module docstring for the rules).

    ``exclude_states``: track rows in these states are not scored (a tentative track is not yet a
    claim that a robot is there). If there are no tracks at all, the truth's own times are the frames (everything is a miss).
    """
    if gate_m <= 0:
        raise ValueError(f"gate must be positive, got {gate_m} m")
    tracks = _scored_rows(np.asarray(tracks), exclude_states)
    truth = np.asarray(truth)
    robots = sorted(set(truth["robot"].tolist()))
    rt = {r: _RobotTruth(truth[truth["robot"] == r], move_speed_mps, move_dist_m, max_gap_us)
          for r in robots}
    track_ids = sorted(set(tracks["track_id"].tolist()), key=_natural_key) if len(tracks) else []
    tid_index = {t: i for i, t in enumerate(track_ids)}

    frame_t, row_frame = _frame_times(tracks, truth, merge_us)
    tracks, row_frame, frame_t, n_dropped = _inside_truth_span(tracks, row_frame, frame_t, truth)
    gt = _TruthOnFrames([rt[r] for r in robots], frame_t, tracks, moved_only)

    order = np.argsort(row_frame, kind="stable")
    bounds = np.searchsorted(row_frame[order], np.arange(len(frame_t) + 1))
    frames: list[Frame] = []
    n_ignored = 0
    for f in range(len(frame_t)):
        frame, ignored = _frame(f, int(frame_t[f]), order[bounds[f]:bounds[f + 1]], tracks, gt, tid_index, gate_m)
        frames.append(frame)
        n_ignored += ignored
    return Alignment(robots=robots, track_ids=track_ids, frames=frames, gate_m=float(gate_m),
                     n_frames_dropped=n_dropped, n_ignored=n_ignored)


def _scored_rows(tracks: np.ndarray, exclude_states: Iterable[str]) -> np.ndarray:
    """The track rows that are scored: not in ``exclude_states``, with a finite position."""
    excl = set(exclude_states)
    if excl and len(tracks):
        tracks = tracks[~np.isin(tracks["state"], list(excl))]
    return tracks[np.isfinite(tracks["x_m"]) & np.isfinite(tracks["y_m"])] if len(tracks) else tracks


def _frame_times(tracks: np.ndarray, truth: np.ndarray, merge_us: int) -> tuple[np.ndarray, np.ndarray]:
    """(frame times µs, frame index of each track row): the tracks' update times, merged within
    ``merge_us`` and with long silences filled; the truth's own times when there are no tracks."""
    if len(tracks):
        frame_t, row_frame = _frame_groups(tracks["t_us"], merge_us)
        filled = _fill_gaps(frame_t)
        return filled, np.searchsorted(filled, frame_t)[row_frame]
    frame_t = np.unique(truth["t_us"]) if len(truth) else np.zeros(0, np.int64)
    return frame_t, np.zeros(0, dtype=np.int64)


def _inside_truth_span(tracks: np.ndarray, row_frame: np.ndarray, frame_t: np.ndarray,
                       truth: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Drop the frames outside the truth's time span and their rows: ``(tracks, row_frame,
    frame_t, number of frames dropped)``."""
    if len(truth) and len(frame_t):
        t0, t1 = truth["t_us"].min(), truth["t_us"].max()
        keep = (frame_t >= t0) & (frame_t <= t1)
        new_index = np.cumsum(keep) - 1
        row_keep = keep[row_frame]
        return tracks[row_keep], new_index[row_frame[row_keep]], frame_t[keep], int(np.count_nonzero(~keep))
    if not len(truth):
        return tracks[:0], row_frame[:0], frame_t[:0], len(frame_t)
    return tracks, row_frame, frame_t, 0


class _TruthOnFrames:
    """The robots' truth at each frame (presence, counted, pose: (robots, frames) arrays) and at
    each track row's own time (position: (robots, rows) arrays)."""

    def __init__(self, robots: list[_RobotTruth], frame_t: np.ndarray, tracks: np.ndarray, moved_only: bool):
        n_r, n_f = len(robots), len(frame_t)
        self.present = np.zeros((n_r, n_f), dtype=bool)
        self.counted = np.zeros((n_r, n_f), dtype=bool)
        self.x = np.full((n_r, n_f), np.nan)
        self.y = np.full((n_r, n_f), np.nan)
        self.yaw = np.full((n_r, n_f), np.nan)
        self.row_x = np.full((n_r, len(tracks)), np.nan)
        self.row_y = np.full((n_r, len(tracks)), np.nan)
        for i, r in enumerate(robots):
            self.present[i] = r.present(frame_t)
            self.counted[i] = self.present[i] & ((frame_t >= r.t_moved) if moved_only else True)
            if len(r.t):
                self.x[i], self.y[i], self.yaw[i] = r.at(frame_t)
                if len(tracks):
                    self.row_x[i], self.row_y[i], _ = r.at(tracks["t_us"])


def _frame(f: int, t_us: int, rows: np.ndarray, tracks: np.ndarray, gt: _TruthOnFrames,
           tid_index: dict[str, int], gate_m: float) -> tuple[Frame, int]:
    """Frame ``f`` from its track ``rows``; returns it and how many rows it ignored (tracks on
    robots that have not moved yet are neither TP nor FP)."""
    pres = np.flatnonzero(gt.present[:, f])
    d = np.hypot(gt.row_x[np.ix_(pres, rows)] - tracks["x_m"][rows][None, :],
                 gt.row_y[np.ix_(pres, rows)] - tracks["y_m"][rows][None, :])
    keep_rows = np.ones(len(rows), dtype=bool)
    dontcare = ~gt.counted[pres, f]
    n_ignored = 0
    if dontcare.any() and len(rows):
        ri, ci = _gated_assignment(d, gate_m)
        drop = ci[dontcare[ri]]
        keep_rows[drop] = False
        n_ignored = len(drop)
    gsel = pres[~dontcare]
    rows = rows[keep_rows]
    return Frame(
        t_us=t_us,
        gt=gsel.astype(np.int64),
        trk=np.asarray([tid_index[t] for t in tracks["track_id"][rows]], dtype=np.int64),
        dist_m=d[np.ix_(~dontcare, keep_rows)],
        gt_xy=np.stack([gt.x[gsel, f], gt.y[gsel, f]], axis=1),
        trk_xy=np.stack([tracks["x_m"][rows], tracks["y_m"][rows]], axis=1),
        gt_yaw=gt.yaw[gsel, f],
        trk_yaw=tracks["yaw_rad"][rows].astype(np.float64),
    ), n_ignored


def _natural_key(s: str):
    return (0, int(s), "") if s.lstrip("-").isdigit() else (1, 0, s)


def _gated_assignment(dist: np.ndarray, gate_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Hungarian assignment on distance keeping only pairs within the gate (max matches, then min cost)."""
    if dist.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    ok = dist <= gate_m
    if not ok.any():
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    big = 1e6 * (gate_m + 1.0)
    cost = np.where(ok, dist, big)
    r, c = linear_sum_assignment(cost)
    good = ok[r, c]
    return r[good], c[good]


# ----------------------------------------------------------------------------------------------
# Metrics


@dataclass
class RobotScores:
    """Per-robot breakdown (frames where the robot counts)."""

    n_gt: int
    n_tp: int
    n_fn: int
    recall: float
    id_switches: int
    fragmentations: int
    mae_cm: float
    heading_mae_deg: float
    main_track: str  # the track id matched to this robot by the IDF1 assignment ("" if none)


@dataclass
class Scores:
    """Everything ``evaluate`` measures. Distances in cm, angles in degrees, ratios in [0, 1]."""

    precision: float
    recall: float
    mae_cm: float
    heading_mae_deg: float
    mota: float
    motp: float
    id_switches: int
    fragmentations: int
    idf1: float
    idp: float
    idr: float
    hota: float
    deta: float
    assa: float
    n_frames: int
    n_gt: int
    n_tp: int
    n_fp: int
    n_fn: int
    n_heading: int
    gate_cm: float
    n_robots: int
    n_tracks: int
    n_frames_dropped: int
    n_ignored: int
    per_robot: dict[str, RobotScores] = field(default_factory=dict)
    #: matched pairs: t_us, robot, track_id, err_m, yaw_err_rad (NaN if unknown); for plots
    matches: np.ndarray | None = field(default=None, repr=False)

    def to_dict(self) -> dict:
        """JSON-ready dict (without the per-match array)."""
        d = asdict(self)
        d.pop("matches")
        for k, v in d.items():
            if isinstance(v, float) and not math.isfinite(v):
                d[k] = None
        for r in d["per_robot"].values():
            for k, v in r.items():
                if isinstance(v, float) and not math.isfinite(v):
                    r[k] = None
        return d


MATCH_DTYPE = np.dtype([("t_us", "<i8"), ("robot", "U64"), ("track_id", "U64"),
                        ("err_m", "<f8"), ("yaw_err_rad", "<f8")])


@dataclass
class ClearMot:
    """CLEAR MOT counts and the matches they came from."""

    n_gt: int
    n_tp: int
    n_fp: int
    n_fn: int
    id_switches: int
    fragmentations: int
    mota: float
    motp: float
    matches: np.ndarray  # MATCH_DTYPE
    per_robot_counts: dict[int, dict[str, int]]


def clear_mot(al: Alignment) -> ClearMot:
    """CLEAR MOT on an :class:`Alignment` (Bernardin & Stiefelhagen 2008; see module docstring)."""
    gate = al.gate_m
    last_match: dict[int, int] = {}          # robot -> last matched track (ever)
    tracked_prev: dict[int, bool] = {}       # robot -> tracked in its previous counted frame
    segs: dict[int, int] = {}
    per = {i: {"n_gt": 0, "n_tp": 0, "idsw": 0} for i in range(len(al.robots))}
    tp = fp = fn = idsw = 0
    sim_sum = 0.0
    out = []
    for fr in al.frames:
        ng, nt = len(fr.gt), len(fr.trk)
        pairs: list[tuple[int, int]] = []
        used_g = np.zeros(ng, bool)
        used_t = np.zeros(nt, bool)
        # 1. keep previous correspondences still within the gate
        for gi, g in enumerate(fr.gt):
            prev = last_match.get(int(g))
            if prev is None:
                continue
            cand = np.flatnonzero((fr.trk == prev) & ~used_t)
            if len(cand) and fr.dist_m[gi, cand[0]] <= gate:
                pairs.append((gi, int(cand[0])))
                used_g[gi] = used_t[cand[0]] = True
        # 2. Hungarian on the rest
        rg, rt = np.flatnonzero(~used_g), np.flatnonzero(~used_t)
        r, c = _gated_assignment(fr.dist_m[np.ix_(rg, rt)], gate)
        pairs.extend(zip(rg[r].tolist(), rt[c].tolist()))
        matched_g = set()
        for gi, ti in pairs:
            g, t = int(fr.gt[gi]), int(fr.trk[ti])
            matched_g.add(gi)
            if g in last_match and last_match[g] != t:
                idsw += 1
                per[g]["idsw"] += 1
            last_match[g] = t
            d = float(fr.dist_m[gi, ti])
            sim_sum += max(0.0, 1.0 - d / gate)
            yerr = float(_wrap(fr.trk_yaw[ti] - fr.gt_yaw[gi]))
            out.append((fr.t_us, al.robots[g], al.track_ids[t], d, yerr))
        tp += len(pairs)
        fp += nt - len(pairs)
        fn += ng - len(pairs)
        for gi, g in enumerate(fr.gt):
            g = int(g)
            per[g]["n_gt"] += 1
            now = gi in matched_g
            if now:
                per[g]["n_tp"] += 1
                if not tracked_prev.get(g, False):
                    segs[g] = segs.get(g, 0) + 1
            tracked_prev[g] = now
    n_gt = tp + fn
    frag = sum(max(0, s - 1) for s in segs.values())
    for g in per:
        per[g]["frag"] = max(0, segs.get(g, 0) - 1)
    matches = np.array(out, dtype=MATCH_DTYPE) if out else np.zeros(0, MATCH_DTYPE)
    return ClearMot(
        n_gt=n_gt, n_tp=tp, n_fp=fp, n_fn=fn, id_switches=idsw, fragmentations=frag,
        mota=1.0 - (fn + fp + idsw) / n_gt if n_gt else (0.0 if fp else 1.0),
        motp=sim_sum / tp if tp else float("nan"),
        matches=matches, per_robot_counts=per)


@dataclass
class Identity:
    """IDF1 and the id assignment (robot index -> track index)."""

    idf1: float
    idp: float
    idr: float
    idtp: int
    assignment: dict[int, int]


def identity(al: Alignment) -> Identity:
    """IDF1 (Ristani et al. 2016): one-to-one robot/track id matching maximising gated co-occurrences."""
    nR, nT = len(al.robots), len(al.track_ids)
    co = np.zeros((nR, nT))
    n_gt = n_trk = 0
    for fr in al.frames:
        n_gt += len(fr.gt)
        n_trk += len(fr.trk)
        if fr.dist_m.size:
            gi, ti = np.nonzero(fr.dist_m <= al.gate_m)
            np.add.at(co, (fr.gt[gi], fr.trk[ti]), 1)
    if co.size:
        r, c = linear_sum_assignment(-co)
        keep = co[r, c] > 0
        r, c = r[keep], c[keep]
        idtp = int(co[r, c].sum())
    else:
        r = c = np.zeros(0, np.int64)
        idtp = 0
    denom = n_gt + n_trk
    return Identity(
        idf1=2 * idtp / denom if denom else 1.0,
        idp=idtp / n_trk if n_trk else float("nan"),
        idr=idtp / n_gt if n_gt else float("nan"),
        idtp=idtp, assignment=dict(zip(r.tolist(), c.tolist())))


@dataclass
class Hota:
    """HOTA, DetA, AssA averaged over alpha, and per alpha (arrays over :data:`HOTA_ALPHAS`)."""

    hota: float
    deta: float
    assa: float
    hota_alpha: np.ndarray
    deta_alpha: np.ndarray
    assa_alpha: np.ndarray


def similarity(dist_m: np.ndarray, gate_m: float) -> np.ndarray:
    """Distance similarity used by MOTP and HOTA: ``max(0, 1 - d / gate)``."""
    return np.clip(1.0 - np.asarray(dist_m, dtype=np.float64) / gate_m, 0.0, 1.0)


def hota(al: Alignment) -> Hota:
    """HOTA (Luiten et al. 2021) with the distance similarity (see module docstring)."""
    nR, nT = len(al.robots), len(al.track_ids)
    nA = len(HOTA_ALPHAS)
    eps = np.finfo(float).eps
    n_gt = sum(len(f.gt) for f in al.frames)
    n_trk = sum(len(f.trk) for f in al.frames)
    if n_gt == 0 or n_trk == 0:
        z = np.zeros(nA)
        return Hota(0.0, 0.0, 0.0, z, z, z)
    potential = np.zeros((nR, nT))
    gt_count = np.zeros((nR, 1))
    trk_count = np.zeros((1, nT))
    sims = []
    for fr in al.frames:
        s = similarity(fr.dist_m, al.gate_m)
        sims.append(s)
        if s.size:
            denom = s.sum(0)[None, :] + s.sum(1)[:, None] - s
            iou = np.zeros_like(s)
            m = denom > eps
            iou[m] = s[m] / denom[m]
            potential[fr.gt[:, None], fr.trk[None, :]] += iou
        gt_count[fr.gt] += 1
        trk_count[0, fr.trk] += 1
    with np.errstate(invalid="ignore", divide="ignore"):
        gas = np.nan_to_num(potential / (gt_count + trk_count - potential))
    pg, pt, ps = [], [], []  # every frame's optimal pairs: robot, track, similarity
    for fr, s in zip(al.frames, sims):
        if not len(fr.gt) or not len(fr.trk):
            continue
        r, c = linear_sum_assignment(-(gas[fr.gt[:, None], fr.trk[None, :]] * s))
        pg.append(fr.gt[r])
        pt.append(fr.trk[c])
        ps.append(s[r, c])
    pg, pt, ps = (np.concatenate(a) if a else np.zeros(0) for a in (pg, pt, ps))
    tp = np.zeros(nA)
    mcounts = np.zeros((nA, nR, nT))
    for a, alpha in enumerate(HOTA_ALPHAS):
        ok = ps >= alpha - eps
        tp[a] = np.count_nonzero(ok)
        np.add.at(mcounts[a], (pg[ok].astype(np.int64), pt[ok].astype(np.int64)), 1)
    fn = n_gt - tp
    fp = n_trk - tp
    assa = np.zeros(nA)
    for a in range(nA):
        mc = mcounts[a]
        ass = mc / np.maximum(1, gt_count + trk_count - mc)
        assa[a] = np.sum(mc * ass) / max(1.0, tp[a])
    deta = tp / np.maximum(1, tp + fn + fp)
    h = np.sqrt(deta * assa)
    return Hota(float(h.mean()), float(deta.mean()), float(assa.mean()), h, deta, assa)


def evaluate(tracks: np.ndarray, truth: np.ndarray, gate_m: float = 0.10, moved_only: bool = True,
             **align_options) -> Scores:
    """Score tracks against truth (arrays from the CSV readers). See the module docstring.

    ``gate_m``: match distance gate in metres (default 10 cm). ``moved_only``: a robot counts only
    from its first motion. Further options (``merge_us``, ``max_gap_us``, ``exclude_states``,
    ``move_speed_mps``, ``move_dist_m``) go to :func:`align`.
    """
    al = align(tracks, truth, gate_m, moved_only=moved_only, **align_options)
    return scores_from_alignment(al)


def scores_from_alignment(al: Alignment) -> Scores:
    """All metrics of an :class:`Alignment` in one :class:`Scores`."""
    cm = clear_mot(al)
    idm = identity(al)
    hm = hota(al)
    m = cm.matches
    yaw_ok = np.isfinite(m["yaw_err_rad"])
    per_robot = {}
    for g, name in enumerate(al.robots):
        c = cm.per_robot_counts[g]
        sel = m["robot"] == name
        ysel = sel & yaw_ok
        t = idm.assignment.get(g)
        per_robot[name] = RobotScores(
            n_gt=c["n_gt"], n_tp=c["n_tp"], n_fn=c["n_gt"] - c["n_tp"],
            recall=c["n_tp"] / c["n_gt"] if c["n_gt"] else float("nan"),
            id_switches=c["idsw"], fragmentations=c["frag"],
            mae_cm=float(m["err_m"][sel].mean() * 100) if sel.any() else float("nan"),
            heading_mae_deg=float(np.degrees(np.abs(m["yaw_err_rad"][ysel])).mean()) if ysel.any() else float("nan"),
            main_track=al.track_ids[t] if t is not None else "")
    n_det = cm.n_tp + cm.n_fp
    # no ground truth scored (no truth rows, no frame inside their span, or no robot that moved):
    # the ratios that divide by it are undefined, not perfect (MOTA 1 - 0/0, IDF1 0/0) nor 0 (HOTA)
    na = float("nan")
    has_gt = cm.n_gt > 0
    return Scores(
        precision=cm.n_tp / n_det if n_det else na,
        recall=cm.n_tp / cm.n_gt if has_gt else na,
        mae_cm=float(m["err_m"].mean() * 100) if len(m) else na,
        heading_mae_deg=float(np.degrees(np.abs(m["yaw_err_rad"][yaw_ok])).mean()) if yaw_ok.any() else na,
        mota=cm.mota if has_gt else na, motp=cm.motp, id_switches=cm.id_switches,
        fragmentations=cm.fragmentations,
        idf1=idm.idf1 if has_gt else na, idp=idm.idp if has_gt else na, idr=idm.idr,
        hota=hm.hota if has_gt else na, deta=hm.deta if has_gt else na, assa=hm.assa if has_gt else na,
        n_frames=len(al.frames), n_gt=cm.n_gt, n_tp=cm.n_tp, n_fp=cm.n_fp, n_fn=cm.n_fn,
        n_heading=int(np.count_nonzero(yaw_ok)), gate_cm=al.gate_m * 100,
        n_robots=len(al.robots), n_tracks=len(al.track_ids),
        n_frames_dropped=al.n_frames_dropped, n_ignored=al.n_ignored,
        per_robot=per_robot, matches=m)


# ----------------------------------------------------------------------------------------------
# The paper's clustering metrics


def n_avg_clusters(clusters_per_window: Sequence[Sequence], n_robots: int) -> float:
    """The paper's n_avg-clusters: mean over windows of (clusters found / robots in view).

    ``clusters_per_window``: for each accumulation window, the list of its clusters (any objects,
    e.g. arrays of pixel coordinates) or directly the number of clusters. 1.0 is ideal: one cluster
    per robot; above 1 robots split (or noise clusters), below 1 robots are missed.
    """
    if n_robots <= 0:
        raise ValueError(f"n_robots must be positive, got {n_robots}")
    counts = [c if isinstance(c, (int, np.integer)) else len(c) for c in clusters_per_window]
    if not counts:
        return float("nan")
    return float(np.mean(counts) / n_robots)


def a_ratio(clusters_per_window: Sequence[Sequence[np.ndarray]], n_robots: int,
            robot_area_px: float) -> float:
    """The paper's A_ratio: detected cluster area over the robots' real chassis area.

    Each cluster is an (N, 2) array of pixel coordinates (u, v); its detected area A_d is its
    axis-aligned bounding box in px² (the paper's rectangle, counting whole pixels: (du+1)(dv+1)).
    Per window the ratio is sum(A_d) / (n_robots * robot_area_px); the result is the mean over
    windows (a window with no cluster gives 0). 1.0 is ideal.
    """
    if n_robots <= 0 or robot_area_px <= 0:
        raise ValueError("n_robots and robot_area_px must be positive")
    ratios = []
    for clusters in clusters_per_window:
        area = 0.0
        for c in clusters:
            c = np.asarray(c)
            if len(c) == 0:
                continue
            span = c.max(axis=0) - c.min(axis=0) + 1
            area += float(span[0]) * float(span[1])
        ratios.append(area / (n_robots * robot_area_px))
    return float(np.mean(ratios)) if ratios else float("nan")

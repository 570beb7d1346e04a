"""Motion capture (or any pose source on its own clock and frame) as ground truth for ``arena eval``.

A lab's mocap system stamps poses on its own clock (often the host's wall clock) in its own frame;
the tracks are on the event camera's sensor clock in the arena frame. This module puts such truth
on the tracks' clock and frame:

* **time**: ``truth time + offset = track time`` (µs). Either given, or estimated
  (:func:`estimate_offset`): the speed profiles |v|(t) of the fleet (the sum over robots, so no
  identity is needed; speed is the same in every rigid frame) are cross-correlated on a 5 ms grid
  (normalised, masked where either side has no data), then the offset is refined to a few µs by
  minimising the position residual of the frame fit over the offset (Brent), with a standard error
  from the residual and the robots' speeds.
* **frame**: a 2-D rigid (Kabsch) or similarity (Umeyama 1991) fit ``arena = s R(theta) mocap + t``
  of truth positions to track positions at the same (offset) times (:func:`fit_transform`),
  pairs by robot name when tracks and truth share names, else each track row with the nearest
  truth body after a fit hypothesised from one (body, track) pair (the one most rows agree with).
  Pairs farther than the gate after a fit are dropped and the fit repeated.

The core (:func:`fit_transform`, :func:`speed_on_grid`, :func:`estimate_offset`,
:func:`align_truth`) is pure numpy/scipy on :data:`~arena.formats.tables.TRUTH_DTYPE` /
:data:`~arena.formats.tables.TRACK_DTYPE` arrays. The readers at the bottom read a rosbag2 folder
or an ``.mcap`` file of ``geometry_msgs/msg/PoseStamped`` (``rosbags``, the optional ``ros2``
extra, imported when called) and a CSV of timestamped poses (:func:`read_pose_csv`).

Units: times in µs (bag stamps are ns), metres, radians; mocap z is up (ROS REP 103), the floor
is its x-y plane, yaw is the rotation about z.
"""

from __future__ import annotations

import csv
import fnmatch
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from arena.formats.tables import TRUTH_DTYPE

POSE_TYPE = "geometry_msgs/msg/PoseStamped"
#: the one line printed when rosbags is missing
INSTALL_HINT = "pip install 'arena-fleet[ros2]'   (or: pip install rosbags)"

ALIGN_MODES = ("none", "rigid", "similarity")


class MocapError(ValueError):
    """Truth that cannot be read or aligned; the message says what to do (one line)."""


class MissingRosbags(MocapError):
    """Reading a bag needs the optional ``rosbags`` package."""


# ----------------------------------------------------------------------------------------------
# frames


@dataclass(frozen=True)
class Transform2D:
    """``arena = scale * R(rotation_rad) @ source + (tx_m, ty_m)``; yaw: ``+ rotation_rad``."""

    rotation_rad: float = 0.0
    tx_m: float = 0.0
    ty_m: float = 0.0
    scale: float = 1.0

    def apply(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c, s = math.cos(self.rotation_rad), math.sin(self.rotation_rad)
        x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        return (self.scale * (c * x - s * y) + self.tx_m, self.scale * (s * x + c * y) + self.ty_m)

    def apply_yaw(self, yaw: np.ndarray) -> np.ndarray:
        return (np.asarray(yaw, dtype=np.float64) + self.rotation_rad + np.pi) % (2 * np.pi) - np.pi

    def to_dict(self) -> dict:
        return {"rotation_deg": math.degrees(self.rotation_rad), "translation_m": [self.tx_m, self.ty_m],
                "scale": self.scale}


IDENTITY = Transform2D()


def fit_transform(src: np.ndarray, dst: np.ndarray, mode: str = "rigid") -> Transform2D:
    """Least-squares ``dst ~ s R src + t`` of (N, 2) point pairs (Umeyama 1991; ``rigid``: s = 1,
    ``similarity``: s fitted, ``none``: identity). Needs >= 2 distinct points for a rotation."""
    if mode == "none":
        return IDENTITY
    if mode not in ALIGN_MODES:
        raise ValueError(f"mode must be one of {ALIGN_MODES}, got {mode!r}")
    src, dst = np.asarray(src, dtype=np.float64), np.asarray(dst, dtype=np.float64)
    if len(src) < 2:
        raise MocapError(f"a {mode} fit needs at least 2 pose pairs, got {len(src)}")
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - mu_s, dst - mu_d
    cov = b.T @ a / len(src)
    u, d, vt = np.linalg.svd(cov)
    sign = np.diag([1.0, np.sign(np.linalg.det(u) * np.linalg.det(vt)) or 1.0])
    r = u @ sign @ vt
    var_s = float((a ** 2).sum() / len(src))
    scale = float(np.trace(np.diag(d) @ sign) / var_s) if mode == "similarity" and var_s > 0 else 1.0
    t = mu_d - scale * r @ mu_s
    return Transform2D(float(math.atan2(r[1, 0], r[0, 0])), float(t[0]), float(t[1]), scale)


@dataclass
class FrameFit:
    """A fitted frame and how well it fits: residuals in metres over ``n_pairs`` pairs."""

    mode: str
    transform: Transform2D
    pairing: str            # "name" or "nearest"
    n_pairs: int
    n_rejected: int         # pairs farther than the gate after the fit (not used)
    rms_m: float
    max_m: float
    pairs_per_robot: dict[str, int] = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"mode": self.mode, **self.transform.to_dict(), "pairing": self.pairing,
                "n_pairs": self.n_pairs, "n_rejected": self.n_rejected,
                "rms_mm": self.rms_m * 1e3, "max_mm": self.max_m * 1e3,
                "pairs_per_robot": dict(self.pairs_per_robot)}


# ----------------------------------------------------------------------------------------------
# time


@dataclass
class OffsetEstimate:
    """``truth time + offset_us = track time``, as estimated by :func:`estimate_offset`.

    ``coarse_us``: the speed cross-correlation's peak (5 ms grid, parabolic sub-sample);
    ``correlation``: its normalised correlation (1 = identical speed profiles); ``next_best``: the
    highest correlation more than 0.5 s away from the peak (close to ``correlation``: ambiguous);
    ``stderr_us``: standard error of the refined offset (inf if nothing moved); ``refined``: whether
    the position refinement ran.
    """

    offset_us: float
    coarse_us: float
    correlation: float
    next_best: float
    stderr_us: float
    refined: bool

    def to_dict(self) -> dict:
        return {"offset_s": self.offset_us * 1e-6, "coarse_s": self.coarse_us * 1e-6,
                "correlation": self.correlation, "next_best_correlation": self.next_best,
                "stderr_ms": self.stderr_us * 1e-3 if math.isfinite(self.stderr_us) else None,
                "refined": self.refined}


def _interp_ok(t: np.ndarray, q: np.ndarray, max_gap_us: float) -> np.ndarray:
    """Where ``q`` lies inside the samples ``t`` (sorted) and not in a hole longer than ``max_gap_us``."""
    if len(t) < 2:
        return np.zeros(len(q), dtype=bool)
    k = np.clip(np.searchsorted(t, q, side="right"), 1, len(t) - 1)
    return (q >= t[0]) & (q <= t[-1]) & ((t[k] - t[k - 1]) <= max_gap_us)


def speed_on_grid(t_us: np.ndarray, x: np.ndarray, y: np.ndarray, grid_us: np.ndarray,
                  half_window_us: float = 50_000.0, max_gap_us: float = 100_000.0
                  ) -> tuple[np.ndarray, np.ndarray]:
    """|v| (m/s) of one body at ``grid_us`` by central differences over ``2 half_window_us`` of the
    linearly interpolated positions; returns (speed, valid). Times in µs, any common origin."""
    t = np.asarray(t_us, dtype=np.float64)
    lo, hi = grid_us - half_window_us, grid_us + half_window_us
    ok = _interp_ok(t, lo, max_gap_us) & _interp_ok(t, hi, max_gap_us) & _interp_ok(t, grid_us, max_gap_us)
    dx = np.interp(hi, t, x) - np.interp(lo, t, x)
    dy = np.interp(hi, t, y) - np.interp(lo, t, y)
    speed = np.hypot(dx, dy) / (2 * half_window_us * 1e-6)
    return np.where(ok, speed, 0.0), ok


def _fleet_speed(groups: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]], t0: int, n: int, dt_us: float,
                 half_window_us: float) -> tuple[np.ndarray, np.ndarray]:
    grid = np.arange(n) * dt_us
    total, valid = np.zeros(n), np.zeros(n, dtype=bool)
    for t, x, y in groups:
        sp, ok = speed_on_grid((t - t0).astype(np.float64), x, y, grid, half_window_us)
        total += sp
        valid |= ok
    return total, valid


def _masked_ncc(a: np.ndarray, ma: np.ndarray, b: np.ndarray, mb: np.ndarray, min_overlap: int
                ) -> np.ndarray:
    """Normalised cross-correlation r[k] of a[i] with b[i + k] over samples valid in both
    (k = index - (len(a) - 1)); NaN where fewer than ``min_overlap`` samples overlap."""
    from scipy.signal import correlate

    a, b = np.where(ma, a, 0.0), np.where(mb, b, 0.0)
    fa, fb = ma.astype(np.float64), mb.astype(np.float64)

    def c(u, v):
        return correlate(v, u, mode="full", method="fft")

    n = np.rint(c(fa, fb))
    sa, sb, sab = c(a, fb), c(fa, b), c(a, b)
    saa, sbb = c(a * a, fb), c(fa, b * b)
    with np.errstate(invalid="ignore", divide="ignore"):
        num = sab - sa * sb / n
        den = np.sqrt(np.maximum(saa - sa * sa / n, 0) * np.maximum(sbb - sb * sb / n, 0))
        r = num / den
    scale = max(float(np.max(np.abs(sbb))), 1e-12) * max(float(np.max(np.abs(saa))), 1e-12)
    r[(n < min_overlap) | ~(den > 1e-9 * math.sqrt(scale))] = np.nan
    return r


def correlate_speeds(truth_groups, track_groups, dt_us: float = 5000.0, half_window_us: float = 50_000.0,
                     min_overlap_s: float = 1.0) -> tuple[float, float, float]:
    """Coarse offset (µs, truth + offset = track) from the fleet speed profiles; returns
    (offset_us, peak correlation, best correlation > 0.5 s away from the peak).

    Each group is (t_us int64 sorted, x, y) of one body / one track id, in any frame."""
    ta0 = min(int(g[0][0]) for g in truth_groups)
    tb0 = min(int(g[0][0]) for g in track_groups)
    na = int((max(int(g[0][-1]) for g in truth_groups) - ta0) // dt_us) + 1
    nb = int((max(int(g[0][-1]) for g in track_groups) - tb0) // dt_us) + 1
    if na * nb == 0 or max(na, nb) > 20_000_000:
        raise MocapError(f"cannot correlate speeds over {na} x {nb} samples: give --time-offset S")
    a, ma = _fleet_speed(truth_groups, ta0, na, dt_us, half_window_us)
    b, mb = _fleet_speed(track_groups, tb0, nb, dt_us, half_window_us)
    min_overlap = max(int(min_overlap_s * 1e6 / dt_us), int(0.25 * min(ma.sum(), mb.sum())), 3)
    r = _masked_ncc(a, ma, b, mb, min_overlap)
    if not np.any(np.isfinite(r)):
        raise MocapError("the truth's and the tracks' speeds never overlap long enough or never change "
                         "(robots standing still carry no timing): give --time-offset S")
    m = int(np.nanargmax(r))
    frac = 0.0
    if 0 < m < len(r) - 1 and np.isfinite(r[m - 1]) and np.isfinite(r[m + 1]):
        den = r[m - 1] - 2 * r[m] + r[m + 1]
        frac = float(0.5 * (r[m - 1] - r[m + 1]) / den) if den < 0 else 0.0
    far = np.abs(np.arange(len(r)) - m) * dt_us > 500_000
    next_best = float(np.nanmax(r[far])) if np.any(far & np.isfinite(r)) else float("nan")
    k = m - (na - 1) + frac
    return float(tb0 - ta0 + k * dt_us), float(r[m]), next_best


# ----------------------------------------------------------------------------------------------
# pairing tracks with truth bodies


class _Bodies:
    """Truth per body, interpolable at track times (after the integer part of the offset)."""

    def __init__(self, truth: np.ndarray, shift_us: int, max_gap_us: float = 100_000.0) -> None:
        self.names: list[str] = sorted(set(truth["robot"]))
        self.t, self.x, self.y = {}, {}, {}
        for n in self.names:
            rows = truth[(truth["robot"] == n) & np.isfinite(truth["x_m"]) & np.isfinite(truth["y_m"])]
            rows = rows[np.argsort(rows["t_us"], kind="stable")]
            self.t[n] = (rows["t_us"] + shift_us).astype(np.float64)
            self.x[n], self.y[n] = rows["x_m"], rows["y_m"]
        self.max_gap_us = max_gap_us

    def at(self, name: str, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = self.t[name]
        ok = _interp_ok(t, q, self.max_gap_us)
        return np.interp(q, t, self.x[name]), np.interp(q, t, self.y[name]), ok


@dataclass
class _Pairs:
    rows: np.ndarray    # index into the scored track rows
    body: np.ndarray    # index into _Bodies.names


def _pair_xy(bodies: _Bodies, pairs: _Pairs, t: np.ndarray, delta_us: float):
    src = np.zeros((len(pairs.rows), 2))
    ok = np.zeros(len(pairs.rows), dtype=bool)
    for b, name in enumerate(bodies.names):
        sel = pairs.body == b
        if np.any(sel):
            x, y, o = bodies.at(name, t[pairs.rows[sel]] - delta_us)
            src[sel, 0], src[sel, 1], ok[sel] = x, y, o
    return src, ok


def _nearest_pairs(bodies: _Bodies, t: np.ndarray, xy: np.ndarray, tf: Transform2D, gate_m: float) -> _Pairs:
    best_d = np.full(len(t), np.inf)
    best_b = np.full(len(t), -1)
    for b, name in enumerate(bodies.names):
        x, y, ok = bodies.at(name, t)
        ax, ay = tf.apply(x, y)
        d = np.where(ok, np.hypot(ax - xy[:, 0], ay - xy[:, 1]), np.inf)
        better = d < best_d
        best_d[better], best_b[better] = d[better], b
    keep = best_d <= gate_m
    return _Pairs(np.flatnonzero(keep), best_b[keep])


def _hypothesis(bodies: _Bodies, t, xy, ids, mode: str, gate_m: float) -> Transform2D:
    """The transform from one (body, track id) pair that the most track rows agree with."""
    if mode == "none":
        return IDENTITY
    rng = np.random.default_rng(0)
    probe = np.sort(rng.choice(len(t), size=min(len(t), 4000), replace=False))
    best, best_n = None, -1
    for tid in np.unique(ids):
        rows = np.flatnonzero(ids == tid)
        for name in bodies.names:
            x, y, ok = bodies.at(name, t[rows])
            if ok.sum() < 10:
                continue
            src = np.column_stack([x[ok], y[ok]])
            if np.ptp(src, axis=0).max() < 0.05:     # a body that stood still fixes no rotation
                continue
            tf = fit_transform(src, xy[rows[ok]], mode)
            n = len(_nearest_pairs(bodies, t[probe], xy[probe], tf, gate_m).rows)
            if n > best_n:
                best, best_n = tf, n
    if best is None:
        raise MocapError("no track overlaps a moving truth body in time: check --time-offset "
                         "(or use auto), or name the tracks' robots as the truth's bodies (--body NAME=TOPIC)")
    return best


def _residuals(src, dst, tf: Transform2D) -> np.ndarray:
    x, y = tf.apply(src[:, 0], src[:, 1])
    return np.hypot(x - dst[:, 0], y - dst[:, 1])


def _robust_fit(src, dst, mode: str, gate_m: float, rounds: int = 3) -> tuple[Transform2D, np.ndarray]:
    keep = np.ones(len(src), dtype=bool)
    tf = fit_transform(src, dst, mode)
    for _ in range(rounds):
        new = _residuals(src, dst, tf) <= gate_m
        if new.sum() < 2 or np.array_equal(new, keep):
            break
        keep = new
        tf = fit_transform(src[keep], dst[keep], mode)
    return tf, _residuals(src, dst, tf) <= gate_m


# ----------------------------------------------------------------------------------------------
# the whole alignment


@dataclass
class TruthAlignment:
    """Truth put on the tracks' clock and frame, and how it was done (see :func:`align_truth`)."""

    truth: np.ndarray                 # TRUTH_DTYPE, track clock, arena frame
    offset_us: float                  # truth time + offset = track time
    offset_source: str                # "given" or "auto"
    estimate: OffsetEstimate | None
    fit: FrameFit | None

    def to_dict(self) -> dict:
        return {"time_offset_s": self.offset_us * 1e-6, "time_offset_source": self.offset_source,
                "time_offset_estimate": self.estimate.to_dict() if self.estimate else None,
                "frame": self.fit.to_dict() if self.fit else None}


def _groups(t: np.ndarray, x: np.ndarray, y: np.ndarray, key: np.ndarray):
    out = []
    for k in np.unique(key):
        sel = np.flatnonzero((key == k) & np.isfinite(x) & np.isfinite(y))
        if len(sel) >= 2:
            sel = sel[np.argsort(t[sel], kind="stable")]
            out.append((t[sel].astype(np.int64), x[sel], y[sel]))
    return out


def align_truth(tracks: np.ndarray, truth: np.ndarray, *, time_offset_us: float | None = 0.0,
                align: str = "rigid", gate_m: float = 0.10, exclude_states: Iterable[str] = ("tentative",),
                search_us: float = 60_000.0) -> TruthAlignment:
    """Put ``truth`` (TRUTH_DTYPE in its own clock and frame) on the clock and frame of ``tracks``.

    ``time_offset_us``: truth time + offset = track time; ``None`` estimates it (speed
    cross-correlation, then refined within ``search_us`` of it on the positions). ``align``:
    ``none`` (truth already in the arena frame), ``rigid`` or ``similarity``. Pairs farther than
    ``gate_m`` after a fit are not used. Raises :class:`MocapError` when nothing overlaps.
    """
    if align not in ALIGN_MODES:
        raise ValueError(f"align must be one of {ALIGN_MODES}, got {align!r}")
    excl = set(exclude_states)
    trk = tracks[~np.isin(tracks["state"], list(excl))] if excl else tracks
    trk = trk[np.isfinite(trk["x_m"]) & np.isfinite(trk["y_m"])]
    if len(trk) == 0:
        raise MocapError("the tracks have no scored row to align the truth with")
    truth = truth[np.isfinite(truth["x_m"]) & np.isfinite(truth["y_m"])]
    if len(truth) == 0:
        raise MocapError("the truth has no pose with a position")
    estimate = None
    if time_offset_us is None:
        coarse, corr, nxt = correlate_speeds(_groups(truth["t_us"], truth["x_m"], truth["y_m"], truth["robot"]),
                                             _groups(trk["t_us"], trk["x_m"], trk["y_m"], trk["track_id"]))
        shift = int(round(coarse))
    else:
        shift = int(round(time_offset_us))
    bodies = _Bodies(truth, shift)
    t = trk["t_us"].astype(np.float64)
    xy = np.column_stack([trk["x_m"], trk["y_m"]])
    named = np.isin(trk["robot"], bodies.names)
    pairing = "name" if np.any(named) else "nearest"

    def pairs_at(delta: float, tf: Transform2D | None) -> tuple[_Pairs, Transform2D]:
        if pairing == "name":
            rows = np.flatnonzero(named)
            return _Pairs(rows, np.searchsorted(bodies.names, trk["robot"][rows])), tf or IDENTITY
        if tf is None:
            tf = _hypothesis(bodies, t - delta, xy, trk["track_id"], align, gate_m)
        return _nearest_pairs(bodies, t - delta, xy, tf, gate_m), tf

    def fit_at(pairs: _Pairs, delta: float):
        src, ok = _pair_xy(bodies, pairs, t, delta)
        if ok.sum() < 2:
            raise MocapError("no track row overlaps the truth in time (give --time-offset S, or auto) "
                             "or the frames differ by more than the gate (use --align rigid)")
        dst = xy[pairs.rows[ok]]
        tf, inl = _robust_fit(src[ok], dst, align, gate_m)
        return tf, src[ok], dst, inl, ok

    # initial pairs and fit at the integer offset; for nearest pairing the pairs follow the fit
    pairs, tf = pairs_at(0.0, None)
    for _ in range(3 if pairing == "nearest" else 1):
        tf, _, _, _, _ = fit_at(pairs, 0.0)
        if pairing == "nearest":
            pairs, _ = pairs_at(0.0, tf)
    delta = 0.0
    if time_offset_us is None:
        _, _, _, inl, ok = fit_at(pairs, 0.0)
        delta, stderr = _refine_offset(bodies, pairs, inl, ok, t, xy, align, search_us)
        estimate = OffsetEstimate(shift + delta, coarse, corr, nxt, stderr, True)
        if pairing == "nearest":
            pairs, _ = pairs_at(delta, tf)
    tf, src, dst, inl, ok = fit_at(pairs, delta)
    if pairing == "nearest":        # pairs once more with the final fit
        pairs, _ = pairs_at(delta, tf)
        tf, src, dst, inl, ok = fit_at(pairs, delta)
    fit = _frame_fit(align, tf, pairing, bodies, pairs, src, dst, inl, ok)
    offset_us = shift + delta
    out = _truth_in_track_frame(truth, tf, offset_us)
    return TruthAlignment(out, offset_us, "auto" if time_offset_us is None else "given", estimate, fit)


def _refine_offset(bodies: _Bodies, pairs: _Pairs, inl: np.ndarray, ok: np.ndarray, t: np.ndarray,
                   xy: np.ndarray, align: str, search_us: float) -> tuple[float, float]:
    """Refine the time offset on the positions, within ``search_us`` of the coarse one: the
    inlier pairs (``ok``, then ``inl``) that stay inside the truth over the whole search are
    fixed, the mean squared residual of a fresh fit is scanned every 2 ms then minimised.

    Returns ``(delta, stderr)``: the refinement (µs, to add to the coarse offset) and its
    standard error, var(residual per axis) / sum |dp/dt|^2 over the pairs."""
    from scipy.optimize import minimize_scalar

    # refine on the positions: pairs fixed (those inside the truth over the whole search)
    keep = np.flatnonzero(ok)[inl]
    fixed = _Pairs(pairs.rows[keep], pairs.body[keep])
    both = _pair_xy(bodies, fixed, t, -search_us)[1] & _pair_xy(bodies, fixed, t, search_us)[1]
    fixed = _Pairs(fixed.rows[both], fixed.body[both])
    if len(fixed.rows) < 10:
        raise MocapError("too few track rows near the truth to refine the time offset: give --time-offset S")

    def cost(d: float) -> float:
        src, _ = _pair_xy(bodies, fixed, t, d)
        dst = xy[fixed.rows]
        return float(np.mean(_residuals(src, dst, fit_transform(src, dst, align)) ** 2))

    scan = np.arange(-search_us, search_us + 1, 2000.0)
    costs = [cost(d) for d in scan]
    d0 = float(scan[int(np.argmin(costs))])
    res = minimize_scalar(cost, bounds=(d0 - 2000.0, d0 + 2000.0), method="bounded",
                          options={"xatol": 0.5, "maxiter": 100})
    delta = float(res.x)
    # standard error: var(residual per axis) / sum |dp/dt|^2 over the pairs
    src0, _ = _pair_xy(bodies, fixed, t, delta)
    src1, _ = _pair_xy(bodies, fixed, t, delta + 1000.0)
    dst = xy[fixed.rows]
    tf_d = fit_transform(src0, dst, align)
    v2 = np.sum(((src0 - src1) * tf_d.scale / 1000.0) ** 2)    # (m/µs)^2
    sigma2 = np.sum(_residuals(src0, dst, tf_d) ** 2) / max(2 * len(dst) - 4, 1)
    stderr = float(math.sqrt(sigma2 / v2)) if v2 > 0 else math.inf
    return delta, stderr


def _frame_fit(align: str, tf: Transform2D, pairing: str, bodies: _Bodies, pairs: _Pairs, src: np.ndarray,
               dst: np.ndarray, inl: np.ndarray, ok: np.ndarray) -> FrameFit:
    """How well the final fit ``tf`` put the truth on the tracks: its inliers, outliers,
    rms and largest residual, and the pairs used per robot."""
    res = _residuals(src[inl], dst[inl], tf)
    per_robot = {}
    used_bodies = pairs.body[ok][inl]
    for b, name in enumerate(bodies.names):
        per_robot[name] = int(np.sum(used_bodies == b))
    fit = FrameFit(align, tf, pairing, int(inl.sum()), int((~inl).sum()),
                   float(np.sqrt(np.mean(res ** 2))) if len(res) else math.nan,
                   float(res.max()) if len(res) else math.nan, per_robot)
    return fit


def _truth_in_track_frame(truth: np.ndarray, tf: Transform2D, offset_us: float) -> np.ndarray:
    """``truth`` moved onto the tracks' clock (+ ``offset_us``, rounded) and frame (``tf``:
    positions, headings and velocities)."""
    out = np.empty(len(truth), dtype=TRUTH_DTYPE)
    out["t_us"] = truth["t_us"] + int(round(offset_us))
    out["robot"] = truth["robot"]
    out["x_m"], out["y_m"] = tf.apply(truth["x_m"], truth["y_m"])
    out["yaw_rad"] = tf.apply_yaw(truth["yaw_rad"])
    c, s = math.cos(tf.rotation_rad), math.sin(tf.rotation_rad)
    out["vx_mps"] = tf.scale * (c * truth["vx_mps"] - s * truth["vy_mps"])
    out["vy_mps"] = tf.scale * (s * truth["vx_mps"] + c * truth["vy_mps"])
    return out


# ----------------------------------------------------------------------------------------------
# readers (I/O)


def yaw_from_quaternion(qx, qy, qz, qw):
    """Rotation about +z (rad) of quaternions (arrays); NaN where any component is NaN."""
    qx, qy, qz, qw = (np.asarray(v, dtype=np.float64) for v in (qx, qy, qz, qw))
    return np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))


def topic_body_name(topic: str) -> str:
    """Default robot name of a pose topic: the element before a final ``/pose``, else the last one
    (``/vrpn_client_node/zumo1/pose`` -> ``zumo1``, ``/mocap/zumo2`` -> ``zumo2``)."""
    parts = [p for p in topic.split("/") if p]
    if not parts:
        return topic
    return parts[-2] if len(parts) > 1 and parts[-1] == "pose" else parts[-1]


def _select_topics(available: Sequence[str], patterns: Sequence[str], bodies: dict[str, str], where: str
                   ) -> dict[str, str]:
    """topic -> robot name of the topics to read."""
    listed = ", ".join(sorted(available)) or "none"
    if bodies:
        missing = [tp for tp in bodies.values() if tp not in available]
        if missing:
            raise MocapError(f"{where} has no PoseStamped topic {missing[0]} (it has: {listed})")
        return {tp: name for name, tp in bodies.items()}
    chosen = [tp for tp in available if not patterns or any(fnmatch.fnmatchcase(tp, p) for p in patterns)]
    if not chosen:
        raise MocapError(f"{where}: no PoseStamped topic matches {' '.join(patterns) or '*'} (it has: {listed})")
    out: dict[str, str] = {}
    for tp in sorted(chosen):
        name = topic_body_name(tp)
        clash = [k for k, v in out.items() if v == name]
        if clash:
            raise MocapError(f"{where}: topics {clash[0]} and {tp} both name the robot {name!r}: pick the "
                             "truth with --truth-topic PATTERN or map them with --body NAME=TOPIC")
        out[tp] = name
    return out


def _load_typestore():
    try:
        from rosbags.typesys import Stores, get_typestore
    except ImportError:       # the optional 'ros2' extra
        raise MissingRosbags(f"reading a rosbag2 or MCAP needs the Python package 'rosbags': {INSTALL_HINT}") from None
    return get_typestore(Stores.ROS2_HUMBLE)


def _truth_rows(samples: dict[str, list[tuple[int, float, float, float]]]) -> np.ndarray:
    n = sum(len(v) for v in samples.values())
    out = np.empty(n, dtype=TRUTH_DTYPE)
    i = 0
    for name, rows in samples.items():
        a = np.asarray(rows, dtype=np.float64).reshape(-1, 4)
        sl = slice(i, i + len(rows))
        out["t_us"][sl] = np.asarray([r[0] for r in rows], dtype=np.int64)
        out["robot"][sl] = name
        out["x_m"][sl], out["y_m"][sl], out["yaw_rad"][sl] = a[:, 1], a[:, 2], a[:, 3]
        i += len(rows)
    out["vx_mps"] = np.nan
    out["vy_mps"] = np.nan
    return out[np.argsort(out["t_us"], kind="stable")]


@dataclass
class BagTruth:
    """Truth read from a bag: rows in the bag's clock and frame, the topics used and the stamp source."""

    truth: np.ndarray
    topics: dict[str, str]          # topic -> robot name
    header_stamps: int              # messages stamped from header.stamp
    log_stamps: int                 # messages whose header stamp was 0: the bag's log time used


def read_pose_bag(path: str | Path, patterns: Sequence[str] = (), bodies: dict[str, str] | None = None) -> BagTruth:
    """``geometry_msgs/msg/PoseStamped`` topics of a rosbag2 folder (any storage rosbags reads) or
    an ``.mcap`` file, one topic per rigid body, as TRUTH_DTYPE rows in the bag's frame and clock
    (header stamp in µs; the log time where the header stamp is 0). ``patterns``: glob(s) of
    topics (default all PoseStamped topics); ``bodies``: robot name -> topic (overrides both)."""
    path = Path(path)
    typestore = _load_typestore()
    bodies = bodies or {}
    samples: dict[str, list] = {}
    counts = [0, 0]

    def add(name: str, log_ns: int, raw: bytes) -> None:
        msg = typestore.deserialize_cdr(raw, POSE_TYPE)
        stamp = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
        counts[stamp == 0] += 1
        p, q = msg.pose.position, msg.pose.orientation
        yaw = float(yaw_from_quaternion(q.x, q.y, q.z, q.w))
        samples.setdefault(name, []).append(((stamp or log_ns) // 1000, p.x, p.y, yaw))

    try:
        if path.is_dir():
            from rosbags.rosbag2 import Reader

            with Reader(path) as reader:
                conns = [c for c in reader.connections if c.msgtype == POSE_TYPE]
                chosen = _select_topics(sorted({c.topic for c in conns}), patterns, bodies, str(path))
                use = [c for c in conns if c.topic in chosen]
                for conn, log_ns, raw in reader.messages(connections=use):
                    add(chosen[conn.topic], log_ns, raw)
        else:
            from mcap.reader import make_reader

            with path.open("rb") as fh:
                reader = make_reader(fh)
                summary = reader.get_summary()
                chans = summary.channels.values() if summary else []
                schemas = summary.schemas if summary else {}
                pose = [c for c in chans if c.message_encoding == "cdr" and c.schema_id in schemas
                        and schemas[c.schema_id].name == POSE_TYPE]
                chosen = _select_topics(sorted({c.topic for c in pose}), patterns, bodies, str(path))
                for _, channel, message in reader.iter_messages(topics=list(chosen)):
                    if channel.topic in chosen:
                        add(chosen[channel.topic], message.log_time, message.data)
    except MocapError:
        raise
    except Exception as exc:  # noqa: BLE001 - rosbags and mcap raise their own errors for damaged files
        raise MocapError(f"cannot read {path} as a rosbag2 folder or MCAP file ({type(exc).__name__}: {exc})") from None
    if not samples:
        raise MocapError(f"{path}: the selected PoseStamped topics have no message")
    return BagTruth(_truth_rows(samples), {t: n for t, n in chosen.items()}, counts[0], counts[1])


#: accepted headers of a pose CSV (case-insensitive), first match wins
CSV_TIME = (("t_s", 1e6), ("time_s", 1e6), ("t_ms", 1e3), ("t_us", 1.0), ("t_ns", 1e-3))
CSV_NAME = ("name", "robot", "body", "rigid_body")
CSV_X, CSV_Y = ("x", "x_m"), ("y", "y_m")
CSV_QUAT = ("qx", "qy", "qz", "qw")
CSV_YAW = (("yaw", 1.0), ("yaw_rad", 1.0), ("yaw_deg", math.pi / 180))


def is_pose_csv_header(header: Sequence[str]) -> bool:
    """Whether a CSV header has what :func:`read_pose_csv` needs (a time, a name, x and y)."""
    h = {c.strip().lower() for c in header}
    return (any(n in h for n, _ in CSV_TIME) and any(n in h for n in CSV_NAME)
            and any(n in h for n in CSV_X) and any(n in h for n in CSV_Y))


def read_pose_csv(path: str | Path, bodies: dict[str, str] | None = None) -> np.ndarray:
    """A CSV of timestamped poses in another frame and clock as TRUTH_DTYPE rows (see
    :data:`CSV_TIME` etc.): a time column ``t_s``/``time_s`` (s), ``t_ms``, ``t_us`` or ``t_ns``;
    a body name ``name``/``robot``/``body``/``rigid_body``; ``x``/``x_m``, ``y``/``y_m`` (m; a
    ``z`` is ignored); optionally ``qx,qy,qz,qw`` or ``yaw``/``yaw_rad`` (rad) or ``yaw_deg``.
    Empty x/y: body not seen. ``bodies``: robot name -> name in the file (others are dropped)."""
    path = Path(path)
    try:
        with path.open(newline="", encoding="utf-8") as fh:
            reader = csv.reader(fh)
            header = [h.strip().lower() for h in next(reader, [])]
            rows = [r for r in reader if r and any(c.strip() for c in r)]
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise MocapError(f"cannot read the pose CSV {path}: {exc}") from None

    def col(names):
        return next((header.index(n) for n in names if n in header), None)

    tcol = next(((header.index(n), f) for n, f in CSV_TIME if n in header), None)
    ncol, xcol, ycol = col(CSV_NAME), col(CSV_X), col(CSV_Y)
    if tcol is None or ncol is None or xcol is None or ycol is None:
        raise MocapError(f"{path}: not a truth CSV (t_us,robot,x_m,y_m,...) nor a pose CSV: the header needs "
                         f"a time (t_s, t_ms, t_us or t_ns), a name (name, robot or body), x and y; "
                         f"found {','.join(header) or 'nothing'}")
    qcols = [col((q,)) for q in CSV_QUAT]
    ycolyaw = next(((header.index(n), f) for n, f in CSV_YAW if n in header), None)
    rename = {v: k for k, v in (bodies or {}).items()}
    out = np.empty(len(rows), dtype=TRUTH_DTYPE)
    keep = np.ones(len(rows), dtype=bool)

    def num(r, j, line, name, empty_ok=True):
        s = r[j].strip() if j < len(r) else ""
        if s == "":
            if empty_ok:
                return math.nan
            raise MocapError(f"{path}: line {line}, column {name} is empty")
        try:
            return float(s)
        except ValueError:
            raise MocapError(f"{path}: line {line}, column {name}: cannot read {s!r} as a number") from None

    for i, r in enumerate(rows):
        line = i + 2
        name = r[ncol].strip() if ncol < len(r) else ""
        if rename:
            if name not in rename:
                keep[i] = False
                continue
            name = rename[name]
        if not name:
            raise MocapError(f"{path}: line {line}: empty body name")
        j, factor = tcol
        out["t_us"][i] = int(round(num(r, j, line, header[j], empty_ok=False) * factor))
        out["robot"][i] = name
        out["x_m"][i], out["y_m"][i] = num(r, xcol, line, header[xcol]), num(r, ycol, line, header[ycol])
        if all(q is not None for q in qcols):
            q = [num(r, k, line, header[k]) for k in qcols]
            out["yaw_rad"][i] = float(yaw_from_quaternion(*q))
        elif ycolyaw is not None:
            out["yaw_rad"][i] = num(r, ycolyaw[0], line, header[ycolyaw[0]]) * ycolyaw[1]
        else:
            out["yaw_rad"][i] = math.nan
    out = out[keep]
    if rename and len(out) == 0:
        raise MocapError(f"{path}: no row of the bodies {', '.join(sorted(rename))} given with --body")
    out["vx_mps"] = np.nan
    out["vy_mps"] = np.nan
    return out[np.argsort(out["t_us"], kind="stable")]

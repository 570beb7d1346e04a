"""Robot identity from the robots' own telemetry: which track is which robot (pure).

A lab always has each robot's telemetry (``arena/telemetry/<robot>``: tread speeds from the
encoders, the gyro's yaw rate, the robot's clock), whether or not a webcam sees markers. The
tracker's tracks carry their own motion (velocity, heading) at a host capture time. So a track
is bound to a robot when the two move alike over a short window, time-aligned:

- Time. A telemetry sample is placed at its *robot* time mapped to host time with the offset
  ``min(host_time_ns - robot_time_us * 1000)`` over the recent samples (the sample that waited
  least on the serial link and in the bridge: the transport delay's floor), not at its arrival.
  Tracks are placed at their host capture time (``Track.host_ns``). A robot clock that jumps
  back (a reboot) starts that robot's history afresh.
- Signals. Both sides are reduced to the same two quantities, resampled on a common grid
  (:attr:`NamingParams.grid_s`) and averaged over the same baseline
  (:attr:`NamingParams.baseline_s`): speed ``|v|`` (the mean tread speed; the track's
  ``hypot(vx, vy)``) and yaw rate (the gyro; the track's heading, unwrapped modulo pi so a
  180 degree flip of an event-camera heading is no turn). Both are taken as differences of
  integrated quantities (distance, heading) over the baseline, so sample rates and noise of the
  two sides need not match.
- Score. The mean over the window of a clipped, normalised squared difference (noise scales
  :attr:`NamingParams.sigma_v_mps` + relative, :attr:`NamingParams.sigma_w_radps` + relative),
  over *evidence* samples only: a sample where robot and track both stand still says nothing
  (any still robot matches any still track) and is left out; a pair needs
  :attr:`NamingParams.min_evidence_s` of evidence to be scored at all. A small lag search
  (:attr:`NamingParams.max_lag_s`) absorbs the tracker's filter lag.
- Assignment. Every :attr:`NamingParams.eval_every_s` the scored pairs are assigned one to one
  (Hungarian method); an assigned pair counts only if its cost is at most
  :attr:`NamingParams.accept` and every alternative, for the robot and for the track, is
  clearly worse (:attr:`NamingParams.margin` and :attr:`NamingParams.ratio`): robots that
  drive alike (the same circle at the same speed) are never told apart by guessing. A pair
  that wins :attr:`NamingParams.confirmations` evaluations in a row is bound; a robot has one
  track at a time (binding it to a new one, e.g. after its old track was lost, unbinds the old).

No I/O, no clock, no Zenoh: times come with the data, ``now_ns`` with :meth:`TelemetryNamer.update`.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

__all__ = ["NamingParams", "TelemetryNamer", "pair_cost"]


@dataclass
class NamingParams:
    """Settings of :class:`TelemetryNamer` (physical defaults, not tuned to a simulator).

    Attributes:
        window_s: the sliding window scored, s.
        grid_s: step of the common resampling grid, s.
        baseline_s: speeds and yaw rates are averaged over this, s (both sides alike).
        min_evidence_s: a pair is scored only with this much evidence in its window, s.
        moving_mps, turning_radps: a grid sample is evidence when robot or track moves faster
            or turns faster than these.
        sigma_v_mps, sigma_v_rel: speed noise scale, m/s, + this fraction of the speed.
        sigma_w_radps, sigma_w_rel: yaw-rate noise scale, rad/s, + this fraction of the rate.
        clip: a sample's normalised cost is clipped here (one glitch cannot dominate).
        max_lag_s: the track may lag or lead the telemetry by up to this much, s.
        max_gap_s: a stretch longer than this without samples (a track not updated, telemetry
            lost) is unknown, not motion: no evidence either way, s.
        accept: an assigned pair counts when its cost is at most this.
        margin, ratio: ... and every alternative costs at least ``cost + margin`` and
            ``cost * ratio``.
        confirmations: evaluations in a row a pair must win to be bound.
        eval_every_s: evaluations at most this often (data time), s.
        stale_s: a robot or track with no sample this recent (before ``now``) takes no part, s.
        history_s: signal history kept, s.
        offset_history_s: the clock offset is the floor over this much telemetry, s.
    """

    window_s: float = 3.0
    grid_s: float = 0.05
    baseline_s: float = 0.4
    min_evidence_s: float = 1.0
    moving_mps: float = 0.03
    turning_radps: float = 0.3
    sigma_v_mps: float = 0.03
    sigma_v_rel: float = 0.10
    sigma_w_radps: float = 0.25
    sigma_w_rel: float = 0.10
    clip: float = 9.0
    max_lag_s: float = 0.1
    max_gap_s: float = 0.25
    accept: float = 1.5
    margin: float = 1.0
    ratio: float = 2.0
    confirmations: int = 3
    eval_every_s: float = 0.25
    stale_s: float = 1.0
    history_s: float = 6.0
    offset_history_s: float = 30.0


class _Robot:
    __slots__ = ("robot_us", "host_ns", "v", "w")

    def __init__(self) -> None:
        self.robot_us: deque[int] = deque()
        self.host_ns: deque[int] = deque()
        self.v: deque[float] = deque()
        self.w: deque[float] = deque()


class _Track:
    __slots__ = ("host_ns", "stamp_us", "x", "y", "yaw", "speed")

    def __init__(self) -> None:
        self.host_ns: deque[int] = deque()
        self.stamp_us: deque[int] = deque()
        self.x: deque[float] = deque()
        self.y: deque[float] = deque()
        self.yaw: deque[float] = deque()
        self.speed: deque[float] = deque()


def _cumtrapz(t: np.ndarray, y: np.ndarray) -> np.ndarray:
    out = np.zeros_like(t)
    if t.size > 1:
        out[1:] = np.cumsum(0.5 * (y[1:] + y[:-1]) * np.diff(t))
    return out


def _unwrap_half(a: np.ndarray) -> np.ndarray:
    """Unwrap angles modulo pi (a heading flipped by 180 degrees is the same axis)."""
    if a.size < 2:
        return a.copy()
    d = np.diff(a)
    d = (d + math.pi / 2) % math.pi - math.pi / 2
    return np.concatenate([[a[0]], a[0] + np.cumsum(d)])


@dataclass
class _Signals:
    """One side's integrated signals: times (s, relative), distance (m), heading (rad)."""

    t: np.ndarray
    dist: np.ndarray
    head_t: np.ndarray    # times of the valid heading samples
    head: np.ndarray
    max_gap: float = math.inf

    def rates(self, g: np.ndarray, baseline: float) -> tuple[np.ndarray, np.ndarray]:
        """Mean speed and yaw rate over ``[g - baseline, g]``; NaN where unknown (a gap of more
        than ``max_gap`` between samples overlaps it: nothing was measured there)."""
        d = (np.interp(g, self.t, self.dist) - np.interp(g - baseline, self.t, self.dist)) / baseline
        gaps = np.flatnonzero(np.diff(self.t) > self.max_gap)
        if gaps.size:
            bad = np.zeros(g.shape, bool)
            for k in gaps:
                bad |= (g > self.t[k]) & (g - baseline < self.t[k + 1])
            d = np.where(bad, np.nan, d)
        if self.head_t.size >= 2:
            w = (np.interp(g, self.head_t, self.head) - np.interp(g - baseline, self.head_t, self.head)) / baseline
            ok = (g - baseline >= self.head_t[0]) & (g <= self.head_t[-1])
            w = np.where(ok & np.isfinite(d), w, np.nan)
        else:
            w = np.full(g.shape, np.nan)
        return np.abs(d), w


def _coverage(sig: _Signals, g: np.ndarray, baseline: float) -> np.ndarray:
    return (g - baseline >= sig.t[0]) & (g <= sig.t[-1])


def side_rates(sig: _Signals, g: np.ndarray, p: NamingParams) -> tuple[np.ndarray, np.ndarray]:
    """Speed and yaw rate of one side on the grid ``g``; NaN where it has no data."""
    v, w = sig.rates(g, p.baseline_s)
    cov = _coverage(sig, g, p.baseline_s)
    return np.where(cov, v, np.nan), np.where(cov, w, np.nan)


def rates_cost(vr: np.ndarray, wr: np.ndarray, vt: np.ndarray, wt: np.ndarray,
               p: NamingParams) -> tuple[np.ndarray, np.ndarray]:
    """(cost, seconds of evidence) of a robot's rates (grid ``(G,)``) against track rates on the
    same grid (``(..., G)``, e.g. tracks x lags; NaN: unknown); cost is NaN with less than
    :attr:`NamingParams.min_evidence_s` of evidence."""
    vr, wr = np.broadcast_to(vr, vt.shape), np.broadcast_to(wr, wt.shape)
    known = np.isfinite(vr) & np.isfinite(vt)
    vr0, vt0 = np.where(known, vr, 0.0), np.where(known, vt, 0.0)
    w_known = known & np.isfinite(wt) & np.isfinite(wr)
    wr0, wt0 = np.where(w_known, wr, 0.0), np.where(w_known, wt, 0.0)
    ev = known & ((np.maximum(vr0, vt0) > p.moving_mps) | (np.maximum(np.abs(wr0), np.abs(wt0)) > p.turning_radps))
    n = np.count_nonzero(ev, axis=-1)
    sv = p.sigma_v_mps + p.sigma_v_rel * np.maximum(vr0, vt0)
    sw = p.sigma_w_radps + p.sigma_w_rel * np.maximum(np.abs(wr0), np.abs(wt0))
    c = ((vr0 - vt0) / sv) ** 2
    c = np.where(w_known, 0.5 * (c + ((wr0 - wt0) / sw) ** 2), c)
    total = np.where(ev, np.minimum(c, p.clip), 0.0).sum(axis=-1)
    seconds = n * p.grid_s
    with np.errstate(invalid="ignore", divide="ignore"):
        cost = np.where(seconds >= p.min_evidence_s, total / np.maximum(n, 1), np.nan)
    return cost, seconds


def _best_lag(cost: np.ndarray) -> np.ndarray:
    """The minimum over the last axis (lags), NaN where every lag is NaN."""
    filled = np.where(np.isfinite(cost), cost, np.inf)
    best = filled.min(axis=-1)
    return np.where(np.isfinite(best), best, np.nan)


def pair_cost(robot: _Signals, track: _Signals, p: NamingParams, end: float | None = None) -> tuple[float, float]:
    """(cost, seconds of evidence) of a robot's and a track's signals over the window ending at
    ``end`` (default: the later of their last samples), the best over the lags
    ``-max_lag_s .. max_lag_s`` of the track."""
    g = _grid(max(robot.t[-1], track.t[-1]) if end is None else end, p)
    vr, wr = side_rates(robot, g, p)
    vt, wt = _lagged(track, g, p)
    cost, seconds = rates_cost(vr, wr, vt, wt, p)
    if not np.isfinite(cost).any():
        return math.nan, float(seconds.max())
    k = int(np.nanargmin(cost))
    return float(cost[k]), float(seconds[k])


def _lagged(track: _Signals, g: np.ndarray, p: NamingParams) -> tuple[np.ndarray, np.ndarray]:
    """A track's rates at the lags ``-max_lag_s .. max_lag_s``: two ``(lags, G)`` arrays."""
    n_lag = int(round(p.max_lag_s / p.grid_s))
    rates = [side_rates(track, g + k * p.grid_s, p) for k in range(-n_lag, n_lag + 1)]
    return np.array([v for v, _ in rates]), np.array([w for _, w in rates])


def _grid(end: float, p: NamingParams) -> np.ndarray:
    """The common grid: ``window_s`` (plus the telemetry's allowed lateness, ``stale_s``) up to ``end``."""
    return np.arange(end, end - p.window_s - p.stale_s, -p.grid_s)[::-1]


class TelemetryNamer:
    """Binds tracks to robots by their motion (see the module docstring). Feed it with
    :meth:`add_telemetry` and :meth:`add_track` (any order, any thread if the caller locks),
    call :meth:`update` now and then: it returns the new bindings ``{track_id: robot}``."""

    def __init__(self, params: NamingParams | None = None) -> None:
        self.p = params or NamingParams()
        self._robots: dict[str, _Robot] = {}
        self._tracks: dict[int, _Track] = {}
        self._streak: dict[int, tuple[str, int]] = {}
        self.bound: dict[str, int] = {}          # robot -> track it is bound to
        self._last_eval_ns: int | None = None
        #: the last evaluation: {(robot, track_id): cost} of the pairs scored (for status / tests)
        self.last_costs: dict[tuple[str, int], float] = {}
        self.clock_resets = 0

    # ------------------------------------------------------------------ feeding
    def add_telemetry(self, robot: str, robot_time_us: int, host_time_ns: int, speed_left: float,
                      speed_right: float, gyro_z: float) -> None:
        """One telemetry sample: robot clock µs, host arrival ns, tread speeds m/s, yaw rate rad/s."""
        vals = (speed_left, speed_right, gyro_z)
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in vals):
            return
        r = self._robots.get(robot)
        if r is None:
            r = self._robots[robot] = _Robot()
        if r.robot_us and robot_time_us <= r.robot_us[-1]:
            if robot_time_us < r.robot_us[-1] - 1_000_000:   # the robot's clock restarted
                self.clock_resets += 1
                r = self._robots[robot] = _Robot()
            else:
                return                                       # a duplicate or reordered sample
        r.robot_us.append(int(robot_time_us))
        r.host_ns.append(int(host_time_ns))
        r.v.append(0.5 * (float(speed_left) + float(speed_right)))
        r.w.append(float(gyro_z))
        keep = robot_time_us - int(self.p.offset_history_s * 1e6)
        while r.robot_us and r.robot_us[0] < keep:
            for q in (r.robot_us, r.host_ns, r.v, r.w):
                q.popleft()

    def add_track(self, track_id: int, host_ns: int, x: float, y: float, yaw: float | None = None,
                  vx: float | None = None, vy: float | None = None, stamp_us: int | None = None) -> None:
        """One track update at host capture time ``host_ns`` (arena m, rad, m/s; None: unknown)."""
        tr = self._tracks.get(track_id)
        if tr is None:
            tr = self._tracks[track_id] = _Track()
        if tr.host_ns and host_ns <= tr.host_ns[-1]:
            return
        tr.host_ns.append(int(host_ns))
        tr.stamp_us.append(int(stamp_us) if stamp_us is not None else -1)
        tr.x.append(float(x))
        tr.y.append(float(y))
        tr.yaw.append(float(yaw) if yaw is not None and math.isfinite(yaw) else math.nan)
        sp = math.hypot(vx, vy) if vx is not None and vy is not None else math.nan
        tr.speed.append(sp if math.isfinite(sp) else math.nan)
        keep = host_ns - int(self.p.history_s * 1e9)
        while tr.host_ns and tr.host_ns[0] < keep:
            for q in (tr.host_ns, tr.stamp_us, tr.x, tr.y, tr.yaw, tr.speed):
                q.popleft()

    def forget_track(self, track_id: int) -> None:
        self._tracks.pop(track_id, None)
        self._streak.pop(track_id, None)
        for r, t in list(self.bound.items()):
            if t == track_id:
                del self.bound[r]

    # ------------------------------------------------------------------ queries
    def track_position_at(self, track_id: int, t: int, clock: str = "host",
                          tolerance: int | None = None) -> tuple[float, float] | None:
        """The track's position at time ``t`` (``clock="host"``: ns; ``"sensor"``: µs), linearly
        interpolated in its history; None outside it (beyond ``tolerance``: 50 ms)."""
        tr = self._tracks.get(track_id)
        if tr is None or not tr.host_ns:
            return None
        ts = np.asarray(tr.host_ns if clock == "host" else tr.stamp_us, dtype=np.int64)
        if clock != "host" and ts[0] < 0:
            return None
        tol = (50_000_000 if clock == "host" else 50_000) if tolerance is None else tolerance
        if t < ts[0] - tol or t > ts[-1] + tol:
            return None
        xs, ys = np.asarray(tr.x), np.asarray(tr.y)
        tf = (ts - ts[0]).astype(float)
        q = float(t - ts[0])
        return float(np.interp(q, tf, xs)), float(np.interp(q, tf, ys))

    def track_ids(self) -> list[int]:
        return list(self._tracks)

    def _robot_signals(self, r: _Robot, ref_ns: int) -> tuple[_Signals | None, int]:
        rus = np.asarray(r.robot_us, dtype=np.int64)
        if rus.size < 3:
            return None, 0
        offset = int((np.asarray(r.host_ns, dtype=np.int64) - rus * 1000).min())
        keep = rus * 1000 + offset >= ref_ns - int(self.p.history_s * 1e9)
        rus = rus[keep]
        if rus.size < 3:
            return None, 0
        t = (rus * 1000 + offset - ref_ns) / 1e9
        v = np.abs(np.asarray(r.v)[keep])
        w = np.asarray(r.w)[keep]
        head = _cumtrapz(t, w)
        return _Signals(t, _cumtrapz(t, v), t, head, self.p.max_gap_s), int(rus[-1] * 1000 + offset)

    def _track_signals(self, tr: _Track, ref_ns: int) -> _Signals | None:
        if len(tr.host_ns) < 3:
            return None
        t = (np.asarray(tr.host_ns, dtype=np.int64) - ref_ns) / 1e9
        x, y = np.asarray(tr.x), np.asarray(tr.y)
        sp = np.asarray(tr.speed)
        if not np.isfinite(sp).all():   # no velocity from the tracker: from the positions
            dt = np.maximum(np.diff(t), 1e-6)
            pos_sp = np.hypot(np.diff(x), np.diff(y)) / dt
            pos_sp = np.concatenate([pos_sp[:1], pos_sp])
            sp = np.where(np.isfinite(sp), sp, pos_sp)
        yaw = np.asarray(tr.yaw)
        ok = np.isfinite(yaw)
        return _Signals(t, _cumtrapz(t, sp), t[ok], _unwrap_half(yaw[ok]), self.p.max_gap_s)

    # ------------------------------------------------------------------ evaluation
    def update(self, now_ns: int) -> dict[int, str]:
        """Evaluate (at most every :attr:`NamingParams.eval_every_s`); returns the bindings made
        now, ``{track_id: robot}`` (each robot on one track, each track one robot)."""
        p = self.p
        if self._last_eval_ns is not None and now_ns - self._last_eval_ns < p.eval_every_s * 1e9:
            return {}
        self._last_eval_ns = now_ns
        stale = now_ns - int(p.stale_s * 1e9)
        for tid in [t for t, tr in self._tracks.items()
                    if not tr.host_ns or tr.host_ns[-1] < now_ns - int((p.history_s + p.stale_s) * 1e9)]:
            self.forget_track(tid)
        robots, rsig = [], []
        for name, r in self._robots.items():
            s, last = self._robot_signals(r, now_ns)
            if s is not None and last >= stale:
                robots.append(name)
                rsig.append(s)
        tracks, tsig = [], []
        for tid, tr in self._tracks.items():
            if tr.host_ns and tr.host_ns[-1] >= stale:
                s = self._track_signals(tr, now_ns)
                if s is not None:
                    tracks.append(tid)
                    tsig.append(s)
        self.last_costs = {}
        if not robots or not tracks:
            self._streak = {}
            return {}
        cost = np.full((len(robots), len(tracks)), np.nan)
        g = _grid(0.0, p)   # times are relative to now
        lagged = [_lagged(ts, g, p) for ts in tsig]
        vt = np.stack([v for v, _ in lagged])   # (tracks, lags, G)
        wt = np.stack([w for _, w in lagged])
        for i, rs in enumerate(rsig):
            vr, wr = side_rates(rs, g, p)
            cost[i] = _best_lag(rates_cost(vr, wr, vt, wt, p)[0])
            for j, c in enumerate(cost[i]):
                if math.isfinite(c):
                    self.last_costs[(robots[i], tracks[j])] = float(c)
        winners = self._assign(cost)
        out: dict[int, str] = {}
        streak: dict[int, tuple[str, int]] = {}
        for i, j in winners:
            tid, name = tracks[j], robots[i]
            prev = self._streak.get(tid)
            n = prev[1] + 1 if prev is not None and prev[0] == name else 1
            streak[tid] = (name, n)
            if n >= p.confirmations and self.bound.get(name) != tid:
                for other, t in list(self.bound.items()):
                    if t == tid:
                        del self.bound[other]
                self.bound[name] = tid
                out[tid] = name
        self._streak = streak
        return out

    def _assign(self, cost: np.ndarray) -> list[tuple[int, int]]:
        """Hungarian assignment of the finite costs; keep the pairs under ``accept`` whose
        alternatives (same row, same column) are all clearly worse."""
        from scipy.optimize import linear_sum_assignment

        p = self.p
        finite = np.isfinite(cost)
        if not finite.any():
            return []
        big = 1e6
        rows, cols = linear_sum_assignment(np.where(finite, cost, big))
        keep = []
        for i, j in zip(rows, cols):
            c = cost[i, j]
            if not (finite[i, j] and c <= p.accept):
                continue
            alts = np.concatenate([np.delete(cost[i, :], j), np.delete(cost[:, j], i)])
            alts = alts[np.isfinite(alts)]
            if alts.size and alts.min() < max(c + p.margin, c * p.ratio):
                continue
            keep.append((int(i), int(j)))
        return keep

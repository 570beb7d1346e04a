"""Missions: commanded paths as sequences of phases (pure).

A mission is a list of :class:`Segment` phases laid out in the arena frame from the
robot's start pose: ``line`` (drive straight), ``arc`` (drive on a circle of signed
curvature, + = left/counter-clockwise), ``turn`` (zero-point turn in place by a signed
angle) and ``pause`` (stand still). The controller (``robot_bridge.control``) runs the
phases one after another as a state machine; :meth:`Mission.path` is the commanded
shape used to score how well it was traced.

Patterns (``params`` keys in brackets, lengths in m, angles in degrees):

* ``circle``: [radius_m=0.3, direction=ccw|cw, laps=1]; the circle is tangent to the
  start heading, its centre to the left (ccw) or right (cw) of the robot.
* ``square``: [side_m=0.6, direction, laps] sides joined by 90 degree zero-point turns.
* ``figure8``: [radius_m=0.25, laps] a ccw circle then a cw circle, tangent at the start.
* ``back_and_forth``: [length_m=0.6, laps] straight out, turn 180, straight back, turn 180.
* ``waypoints``: [points=[[x, y], ...]] turn to face each point, drive to it (arena frame).

Any pattern takes ``pause_s`` and ``pause_every_m`` (stop-and-go: stand still
``pause_s`` seconds after every ``pause_every_m`` of driving; 0 = after each driving phase).

Every parameter is bounded physically (:class:`MissionLimits`, from the arena's size):
lengths and radii by the arena's diagonal, laps, pauses, the waypoint count, the number of
phases and the total path length by fixed caps. :func:`check_mission` applies them without
building anything (its cost does not depend on the values asked for), so a hostile request
such as ``pause_every_m=1e-6`` or ``laps=1e9`` is refused in microseconds, naming the
parameter and its allowed range, before a single phase is laid out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from .odometry import wrap_angle

PATTERNS = ("circle", "square", "figure8", "back_and_forth", "waypoints")
#: Tread speed at 100 % power on the Zumo 32U4 (150:1), m/s.
FULL_SPEED_MPS = 0.46

Pose = tuple[float, float, float]


class MissionError(ValueError):
    """A mission request with a bad or missing parameter; the text names it."""


@dataclass(frozen=True)
class Segment:
    """One phase of a mission, in the arena frame.

    Attributes:
        kind: ``line``, ``arc``, ``turn`` or ``pause``.
        start: commanded pose at the start of the phase (x m, y m, yaw rad).
        length_m: path length of a line or arc, m (0 for turn and pause).
        curvature: signed curvature of an arc, 1/m (+ = turning left); 0 for a line.
        turn_rad: signed angle of a zero-point turn, rad (+ = counter-clockwise).
        duration_s: length of a pause, s.
        label: phase name for logs and telemetry, e.g. ``side 2`` or ``turn 3``.
    """

    kind: str
    start: Pose
    length_m: float = 0.0
    curvature: float = 0.0
    turn_rad: float = 0.0
    duration_s: float = 0.0
    label: str = ""

    def pose_at(self, s: float) -> Pose:
        """Commanded pose after ``s`` metres along a line/arc (clipped to the segment)."""
        x0, y0, th0 = self.start
        if self.kind == "turn":
            return x0, y0, wrap_angle(th0 + self.turn_rad * min(max(s, 0.0), 1.0))
        if self.kind not in ("line", "arc"):
            return self.start
        s = min(max(s, 0.0), self.length_m)
        k = self.curvature
        if abs(k) < 1e-9:
            return x0 + s * math.cos(th0), y0 + s * math.sin(th0), th0
        th = th0 + k * s
        return x0 + (math.sin(th) - math.sin(th0)) / k, y0 - (math.cos(th) - math.cos(th0)) / k, wrap_angle(th)

    def positions_at(self, ss: np.ndarray) -> np.ndarray:
        """Commanded positions (n, 2), m, after each of ``ss`` metres along a line/arc (clipped
        to the segment): :meth:`pose_at` for many points at once (the start for a turn or pause)."""
        ss = np.asarray(ss, dtype=float)
        x0, y0, th0 = self.start
        if self.kind not in ("line", "arc"):
            return np.tile(np.array([x0, y0], dtype=float), (ss.size, 1))
        ss = np.clip(ss, 0.0, self.length_m)
        k = self.curvature
        if abs(k) < 1e-9:
            return np.column_stack([x0 + ss * math.cos(th0), y0 + ss * math.sin(th0)])
        th = th0 + k * ss
        return np.column_stack([x0 + (np.sin(th) - math.sin(th0)) / k, y0 - (np.cos(th) - math.cos(th0)) / k])

    @property
    def end(self) -> Pose:
        """Commanded pose at the end of the phase."""
        if self.kind == "turn":
            return self.pose_at(1.0)
        return self.pose_at(self.length_m)

    def points(self, step_m: float = 0.005) -> np.ndarray:
        """Samples of the commanded path of this phase, shape (n, 2), m (arena frame)."""
        if self.kind not in ("line", "arc") or self.length_m <= 0:
            return np.array([self.start[:2]])
        n = max(2, int(math.ceil(self.length_m / step_m)) + 1)
        return self.positions_at(np.linspace(0.0, self.length_m, n))


@dataclass
class Mission:
    """A named mission: its phases, its speed and where it started.

    Attributes:
        pattern: one of :data:`PATTERNS`.
        params: the validated parameters it was built from.
        segments: the phases in order.
        speed_mps: cruise tread speed, m/s.
    """

    pattern: str
    params: dict
    segments: list[Segment]
    speed_mps: float
    start: Pose = (0.0, 0.0, 0.0)

    def path(self, step_m: float = 0.005) -> np.ndarray:
        """The commanded shape: samples of every line/arc phase, shape (n, 2), m."""
        parts = [s.points(step_m) for s in self.segments if s.kind in ("line", "arc")]
        return np.concatenate(parts) if parts else np.array([self.start[:2]])

    @property
    def length_m(self) -> float:
        """Total driven path length, m."""
        return sum(s.length_m for s in self.segments)

    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) of the commanded path, m."""
        p = self.path(0.02)
        return float(p[:, 0].min()), float(p[:, 1].min()), float(p[:, 0].max()), float(p[:, 1].max())


# --------------------------------------------------------------------------- parameters


@dataclass(frozen=True)
class MissionLimits:
    """Physical bounds of mission parameters (see :meth:`for_arena`).

    Attributes:
        max_length_m: longest side_m / length_m, m (the arena's diagonal: nothing longer fits).
        max_radius_m: largest radius_m, m (half the diagonal).
        min_length_m: shortest side, length or radius, m (about the robot's own size).
        arena_m: (x, y) size of the arena, m; waypoints must lie inside it (origin at a
            corner). None: any waypoint with |x| and |y| up to ``max_length_m``.
        max_laps: most laps of a pattern.
        max_pause_s: longest stop-and-go pause, s.
        min_pause_every_m: shortest stop-and-go step, m (0 = a pause after each phase).
        max_waypoints: most waypoints of one mission.
        max_segments: most phases of one mission (each is a state of the controller).
        max_path_m: longest total path, m (about 18 min at full speed; the mission's scoring
            resamples the path every mm).
    """

    max_length_m: float = 5.0
    max_radius_m: float = 2.5
    min_length_m: float = 0.05
    arena_m: tuple[float, float] | None = None
    max_laps: int = 100
    max_pause_s: float = 60.0
    min_pause_every_m: float = 0.05
    max_waypoints: int = 256
    max_segments: int = 10_000
    max_path_m: float = 500.0

    @classmethod
    def for_arena(cls, size_m: tuple[float, float]) -> "MissionLimits":
        """Limits for an arena of ``size_m`` (x, y), m: lengths up to its diagonal, radii up to
        half of it, waypoints inside it."""
        sx, sy = (float(v) for v in size_m)
        diag = math.hypot(sx, sy)
        return cls(max_length_m=round(diag, 3), max_radius_m=round(diag / 2, 3), arena_m=(sx, sy))


DEFAULT_LIMITS = MissionLimits()


def _num(params: dict, key: str, default: float, lo: float, hi: float, unit: str = "") -> float:
    v = params.get(key, default)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise MissionError(f"parameter {key} must be a number, got {v!r}")
    if not lo <= v <= hi:
        raise MissionError(f"parameter {key}={v} out of range [{lo}, {hi}]{unit}")
    return float(v)


def _int(params: dict, key: str, default: int, lo: int, hi: int) -> int:
    v = params.get(key, default)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v != int(v):
        raise MissionError(f"parameter {key} must be an integer, got {v!r}")
    if not lo <= v <= hi:
        raise MissionError(f"parameter {key}={v} out of range [{lo}, {hi}]")
    return int(v)


def _direction(params: dict) -> float:
    d = params.get("direction", "ccw")
    if d not in ("ccw", "cw", "left", "right"):
        raise MissionError(f"parameter direction must be ccw or cw, got {d!r}")
    return 1.0 if d in ("ccw", "left") else -1.0


def mission_speed(power: float | None = None, speed_mps: float | None = None,
                  full_speed_mps: float = FULL_SPEED_MPS) -> float:
    """Cruise speed, m/s, from a power fraction (0.5 = 50 %) or an explicit speed (default 50 %)."""
    if power is not None and speed_mps is not None:
        raise MissionError("give either power or speed_mps, not both")
    if speed_mps is not None:
        if not 0.02 <= speed_mps <= full_speed_mps:
            raise MissionError(f"speed_mps={speed_mps} out of range [0.02, {full_speed_mps}]")
        return float(speed_mps)
    p = 0.5 if power is None else power
    if not 0.05 <= p <= 1.0:
        raise MissionError(f"power={p} out of range [0.05, 1.0] (fraction of full power)")
    return p * full_speed_mps


# --------------------------------------------------------------------------- builders

_KNOWN = {
    "circle": {"radius_m", "direction", "laps"},
    "square": {"side_m", "direction", "laps"},
    "figure8": {"radius_m", "laps"},
    "back_and_forth": {"length_m", "laps"},
    "waypoints": {"points"},
}
_COMMON = {"pause_s", "pause_every_m"}


@dataclass(frozen=True)
class MissionSize:
    """What :func:`check_mission` found: the phases and path length the mission will have."""

    segments: int
    length_m: float


def _waypoints(params: dict, limits: MissionLimits) -> list[tuple[float, float]]:
    pts = params.get("points")
    if not isinstance(pts, (list, tuple)) or not pts:
        raise MissionError("parameter points must be a non-empty list of [x, y] in metres")
    if len(pts) > limits.max_waypoints:
        raise MissionError(f"parameter points has {len(pts)} waypoints; at most {limits.max_waypoints}")
    if limits.arena_m is not None:
        (xlo, xhi), (ylo, yhi) = (0.0, limits.arena_m[0]), (0.0, limits.arena_m[1])
    else:
        xlo = ylo = -limits.max_length_m
        xhi = yhi = limits.max_length_m
    out = []
    for k, p in enumerate(pts):
        if (not isinstance(p, (list, tuple)) or len(p) != 2
                or not all(isinstance(c, (int, float)) and not isinstance(c, bool) and math.isfinite(c) for c in p)):
            raise MissionError(f"points[{k}] must be [x, y] in metres, got {p!r}")
        if not (xlo <= p[0] <= xhi and ylo <= p[1] <= yhi):
            raise MissionError(f"points[{k}]={list(p)} outside the arena: x in [{xlo}, {xhi}], "
                               f"y in [{ylo}, {yhi}] m")
        out.append((float(p[0]), float(p[1])))
    return out


def check_mission(pattern: str, params: dict[str, Any], limits: MissionLimits = DEFAULT_LIMITS,
                  start: Pose | None = None) -> MissionSize:
    """Validate ``params`` of ``pattern`` against ``limits`` without laying anything out (pure,
    cost independent of the values: O(number of waypoints)); raise :class:`MissionError` naming
    the parameter and its allowed range. Returns the number of phases and the path length the
    mission will have (``start`` is needed for an exact waypoint length; without it the path is
    measured from the first waypoint)."""
    if pattern not in _KNOWN:
        raise MissionError(f"unknown mission {pattern!r}; choose one of {', '.join(PATTERNS)}")
    if not isinstance(params, dict):
        raise MissionError("mission params must be a map")
    unknown = set(params) - _KNOWN[pattern] - _COMMON
    if unknown:
        raise MissionError(f"unknown parameter(s) for {pattern}: {', '.join(sorted(unknown))}; "
                           f"accepted: {', '.join(sorted(_KNOWN[pattern] | _COMMON))}")
    lim = limits
    pause_s = _num(params, "pause_s", 0.0, 0.0, lim.max_pause_s, " s")
    every = _num(params, "pause_every_m", 0.0, 0.0, lim.max_path_m, " m")
    if 0 < every < lim.min_pause_every_m:
        raise MissionError(f"parameter pause_every_m={every} out of range: 0 (a pause after each phase) or "
                           f"[{lim.min_pause_every_m}, {lim.max_path_m}] m")
    drives: list[tuple[float, int]] = []   # (length of a driving phase, how many such phases)
    turns = 0
    if pattern in ("circle", "figure8"):
        r = _num(params, "radius_m", 0.3 if pattern == "circle" else 0.25, lim.min_length_m, lim.max_radius_m, " m")
        if pattern == "circle":
            _direction(params)
        laps = _int(params, "laps", 1, 1, lim.max_laps)
        drives.append((2 * math.pi * r, laps * (1 if pattern == "circle" else 2)))
    elif pattern == "square":
        side = _num(params, "side_m", 0.6, lim.min_length_m, lim.max_length_m, " m")
        _direction(params)
        laps = _int(params, "laps", 1, 1, lim.max_laps)
        drives.append((side, 4 * laps))
        turns = 4 * laps
    elif pattern == "back_and_forth":
        length = _num(params, "length_m", 0.6, lim.min_length_m, lim.max_length_m, " m")
        laps = _int(params, "laps", 1, 1, lim.max_laps)
        drives.append((length, 2 * laps))
        turns = 2 * laps
    else:
        pts = _waypoints(params, lim)
        prev = tuple(start[:2]) if start is not None else pts[0]
        for p in pts:
            d = math.hypot(p[0] - prev[0], p[1] - prev[1])
            if d >= 1e-3:
                drives.append((d, 1))
                turns += 1
            prev = p
    length_m = sum(d * n for d, n in drives)
    if length_m > lim.max_path_m:
        raise MissionError(f"mission path of {length_m:.1f} m exceeds {lim.max_path_m:.0f} m: "
                           "fewer laps or shorter sides")
    segments = turns
    for d, n in drives:
        pieces = max(1, math.ceil(d / every - 1e-9)) if (pause_s > 0 and every > 0) else 1
        segments += n * pieces * (2 if pause_s > 0 else 1)
        if segments > lim.max_segments:
            break
    if segments > lim.max_segments:
        raise MissionError(f"mission would have {segments}{'+' if segments > lim.max_segments else ''} phases, "
                           f"at most {lim.max_segments}: fewer laps or a longer pause_every_m")
    return MissionSize(segments, length_m)


def build_mission(pattern: str, params: dict[str, Any], start: Pose, speed_mps: float,
                  limits: MissionLimits = DEFAULT_LIMITS) -> Mission:
    """Lay out ``pattern`` from the ``start`` pose (arena frame); raise :class:`MissionError`
    for an unknown pattern, an unknown parameter or a value out of ``limits`` (checked by
    :func:`check_mission` first, so the work done here is bounded)."""
    check_mission(pattern, params, limits, start)
    x, y, th = (float(v) for v in start)
    segs: list[Segment] = []

    def add(kind: str, label: str, **kw) -> None:
        p = segs[-1].end if segs else (x, y, th)
        segs.append(Segment(kind, p, label=label, **kw))

    laps = int(params.get("laps", 1))
    if pattern == "circle":
        r = float(params.get("radius_m", 0.3))
        sign = _direction(params)
        for lap in range(laps):
            add("arc", f"lap {lap + 1}", length_m=2 * math.pi * r, curvature=sign / r)
    elif pattern == "square":
        side = float(params.get("side_m", 0.6))
        sign = _direction(params)
        for lap in range(laps):
            for k in range(4):
                n = 4 * lap + k + 1
                add("line", f"side {n}", length_m=side)
                add("turn", f"turn {n}", turn_rad=sign * math.pi / 2)
    elif pattern == "figure8":
        r = float(params.get("radius_m", 0.25))
        for lap in range(laps):
            add("arc", f"lap {lap + 1} left", length_m=2 * math.pi * r, curvature=1.0 / r)
            add("arc", f"lap {lap + 1} right", length_m=2 * math.pi * r, curvature=-1.0 / r)
    elif pattern == "back_and_forth":
        length = float(params.get("length_m", 0.6))
        for lap in range(laps):
            add("line", f"out {lap + 1}", length_m=length)
            add("turn", f"turn {2 * lap + 1}", turn_rad=math.pi)
            add("line", f"back {lap + 1}", length_m=length)
            add("turn", f"turn {2 * lap + 2}", turn_rad=math.pi)
    elif pattern == "waypoints":
        for k, p in enumerate(_waypoints(params, limits)):
            cx, cy, cth = segs[-1].end if segs else (x, y, th)
            dx, dy = p[0] - cx, p[1] - cy
            dist = math.hypot(dx, dy)
            if dist < 1e-3:
                continue
            turn = wrap_angle(math.atan2(dy, dx) - cth)
            if abs(turn) > math.radians(1):
                add("turn", f"face {k + 1}", turn_rad=turn)
            add("line", f"to {k + 1}", length_m=dist)
        if not segs:
            raise MissionError("all waypoints coincide with the start position")

    segs = _with_pauses(segs, float(params.get("pause_s", 0.0)), float(params.get("pause_every_m", 0.0)))
    return Mission(pattern, dict(params), segs, float(speed_mps), (x, y, th))


def _with_pauses(segs: list[Segment], pause_s: float, every_m: float) -> list[Segment]:
    """Split driving phases every ``every_m`` metres and insert ``pause_s`` pauses (stop-and-go);
    with ``every_m`` = 0 a pause follows each driving phase."""
    if pause_s <= 0:
        return segs
    out: list[Segment] = []
    n = 0
    for seg in segs:
        if seg.kind not in ("line", "arc"):
            out.append(seg)
            continue
        pieces = max(1, int(math.ceil(seg.length_m / every_m - 1e-9))) if every_m > 0 else 1
        step = seg.length_m / pieces
        for k in range(pieces):
            start = seg.pose_at(k * step)
            label = seg.label if pieces == 1 else f"{seg.label} part {k + 1}"
            out.append(Segment(seg.kind, start, length_m=step, curvature=seg.curvature, label=label))
            n += 1
            out.append(Segment("pause", out[-1].end, duration_s=pause_s, label=f"pause {n}"))
    return out

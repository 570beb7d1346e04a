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
``pause_s`` seconds after every ``pause_every_m`` of driving; 0 = never).
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


def _num(params: dict, key: str, default: float, lo: float, hi: float) -> float:
    v = params.get(key, default)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise MissionError(f"parameter {key} must be a number, got {v!r}")
    if not lo <= v <= hi:
        raise MissionError(f"parameter {key}={v} out of range [{lo}, {hi}]")
    return float(v)


def _int(params: dict, key: str, default: int, lo: int, hi: int) -> int:
    v = params.get(key, default)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or v != int(v):
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


def build_mission(pattern: str, params: dict[str, Any], start: Pose, speed_mps: float) -> Mission:
    """Lay out ``pattern`` from the ``start`` pose (arena frame); raise :class:`MissionError`
    for an unknown pattern, an unknown parameter or a value out of range."""
    if pattern not in _KNOWN:
        raise MissionError(f"unknown mission {pattern!r}; choose one of {', '.join(PATTERNS)}")
    if not isinstance(params, dict):
        raise MissionError("mission params must be a map")
    unknown = set(params) - _KNOWN[pattern] - _COMMON
    if unknown:
        raise MissionError(f"unknown parameter(s) for {pattern}: {', '.join(sorted(unknown))}; "
                           f"accepted: {', '.join(sorted(_KNOWN[pattern] | _COMMON))}")
    x, y, th = (float(v) for v in start)
    segs: list[Segment] = []

    def add(kind: str, label: str, **kw) -> None:
        p = segs[-1].end if segs else (x, y, th)
        segs.append(Segment(kind, p, label=label, **kw))

    if pattern == "circle":
        r = _num(params, "radius_m", 0.3, 0.05, 5.0)
        sign = _direction(params)
        for lap in range(_int(params, "laps", 1, 1, 100)):
            add("arc", f"lap {lap + 1}", length_m=2 * math.pi * r, curvature=sign / r)
    elif pattern == "square":
        side = _num(params, "side_m", 0.6, 0.05, 5.0)
        sign = _direction(params)
        for lap in range(_int(params, "laps", 1, 1, 100)):
            for k in range(4):
                n = 4 * lap + k + 1
                add("line", f"side {n}", length_m=side)
                add("turn", f"turn {n}", turn_rad=sign * math.pi / 2)
    elif pattern == "figure8":
        r = _num(params, "radius_m", 0.25, 0.05, 5.0)
        for lap in range(_int(params, "laps", 1, 1, 100)):
            add("arc", f"lap {lap + 1} left", length_m=2 * math.pi * r, curvature=1.0 / r)
            add("arc", f"lap {lap + 1} right", length_m=2 * math.pi * r, curvature=-1.0 / r)
    elif pattern == "back_and_forth":
        length = _num(params, "length_m", 0.6, 0.05, 5.0)
        for lap in range(_int(params, "laps", 1, 1, 100)):
            add("line", f"out {lap + 1}", length_m=length)
            add("turn", f"turn {2 * lap + 1}", turn_rad=math.pi)
            add("line", f"back {lap + 1}", length_m=length)
            add("turn", f"turn {2 * lap + 2}", turn_rad=math.pi)
    elif pattern == "waypoints":
        pts = params.get("points")
        if not isinstance(pts, (list, tuple)) or not pts:
            raise MissionError("parameter points must be a non-empty list of [x, y] in metres")
        for k, p in enumerate(pts):
            if (not isinstance(p, (list, tuple)) or len(p) != 2
                    or not all(isinstance(c, (int, float)) and math.isfinite(c) for c in p)):
                raise MissionError(f"points[{k}] must be [x, y] in metres, got {p!r}")
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

    segs = _with_pauses(segs, _num(params, "pause_s", 0.0, 0.0, 60.0), _num(params, "pause_every_m", 0.0, 0.0, 100.0))
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

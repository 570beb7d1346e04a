"""The built-in "human driver": steers simulated robots along the paper's patterns.

It reads the true pose from the :class:`~simulator.world.World` (no encoders, no camera)
and sets motor powers, so scenarios run without the robot bridge. Paths are in the arena
frame (m); each robot gets its own cell of the arena so paths do not collide, except in
``"cross"`` where three robots drive straight lines through the arena centre.

Patterns: ``circle`` (radius ~0.3 m, counter-clockwise), ``square`` (side ~0.6 m, stop,
pause, zero-point turn, pause, go at each corner), ``stopgo`` (circles; robots 0 and 1 stop for 2 s in the
middle of the run), ``cross`` (3 robots back and forth on lines crossing at the centre,
zero-point turns at the ends; extra robots circle in the corners), ``figure8``
(a lemniscate ~0.6 x 0.3 m) and ``still`` (nobody moves).

Like a human operator (or a mission's phase sequencer), the driver stands still for a short,
seeded-random pause (:attr:`Autopilot.PAUSE_S`, 0.2-0.4 s) before and after every zero-point
turn (``pauses=False``: it turns as soon as it arrives and drives on as soon as it faces).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from simulator.world import MAX_POWER, World

PATTERNS = ("circle", "square", "stopgo", "cross", "figure8", "still")
#: How often the driver updates the motor powers, s.
CONTROL_PERIOD_S = 0.02


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


@dataclass
class Plan:
    """One robot's route: a polyline (m, arena frame), closed or back-and-forth, and whether
    corners are zero-point turns (stop, turn on the spot, go) or driven through smoothly."""

    points: np.ndarray
    closed: bool = True
    point_turns: bool = False
    start_s: float = 0.0
    stops: list[tuple[float, float]] = field(default_factory=list)   # (t_start s, duration s)
    _arc: np.ndarray | None = field(default=None, init=False, repr=False)

    def arc_length(self) -> np.ndarray:
        """Cumulative length (m) at each vertex of the closed route, plus the total at the end."""
        if self._arc is None:
            seg = np.hypot(*np.diff(np.vstack([self.points, self.points[:1]]), axis=0).T)
            self._arc = np.concatenate([[0.0], np.cumsum(seg)])
        return self._arc

    def start_pose(self) -> tuple[float, float, float]:
        """Pose (x m, y m, yaw rad) at the start of the route, facing along it."""
        p0, p1 = self.points[0], self.points[1]
        return float(p0[0]), float(p0[1]), math.atan2(p1[1] - p0[1], p1[0] - p0[0])


def _cells(n: int, arena_m: float) -> tuple[list[tuple[float, float]], float]:
    k = max(1, math.ceil(math.sqrt(n)))
    cell = arena_m / k
    centres = [((c + 0.5) * cell, (r + 0.5) * cell) for r in range(k) for c in range(k)]
    return centres[:n], cell


def _circle(c, radius, phase=-math.pi / 2, n=180) -> np.ndarray:
    a = phase + np.linspace(0, 2 * math.pi, n, endpoint=False)
    return np.column_stack([c[0] + radius * np.cos(a), c[1] + radius * np.sin(a)])


def _square(c, side) -> np.ndarray:
    h = side / 2
    return np.array([[c[0] - h, c[1] - h], [c[0] + h, c[1] - h], [c[0] + h, c[1] + h],
                     [c[0] - h, c[1] + h]])


def _figure8(c, a, n=240) -> np.ndarray:
    s = np.linspace(0, 2 * math.pi, n, endpoint=False)
    d = 1 + np.sin(s) ** 2
    return np.column_stack([c[0] + a * np.cos(s) / d, c[1] + a * np.sin(s) * np.cos(s) / d])


def make_plans(pattern: str, n: int, arena_m: float = 1.83, duration_s: float = 10.0,
               stagger_s: float = 0.3) -> list[Plan]:
    """Routes for ``n`` robots driving ``pattern``; robot i starts moving at
    ``0.2 + stagger_s * i`` s (so "a robot counts once it has moved" can be scored)."""
    if pattern not in PATTERNS:
        raise ValueError(f"pattern must be one of {PATTERNS}, got {pattern!r}")
    if n < 0:
        raise ValueError(f"number of robots must be >= 0, got {n}")
    centres, cell = _cells(n, arena_m)
    margin = 0.09
    plans: list[Plan] = []
    for i in range(n):
        start = 0.2 + stagger_s * i
        c = centres[i]
        radius = min(0.30, cell / 2 - margin)
        side = min(0.60, cell - 2 * margin)
        if pattern in ("circle", "stopgo", "still"):
            plan = Plan(_circle(c, radius), start_s=start)
            if pattern == "stopgo" and i < 2:
                plan.stops.append((max(start + 1.0, duration_s * 0.4), 2.0))
        elif pattern == "square":
            plan = Plan(_square(c, side), point_turns=True, start_s=start)
        elif pattern == "figure8":
            plan = Plan(_figure8(c, min(0.30, cell / 2 - margin)), start_s=start)
        else:   # cross
            if i < 3:
                mid = arena_m / 2
                half = 0.6
                ang = math.radians(90 + 60 * i)
                d = np.array([math.cos(ang), math.sin(ang)])
                a, b = np.array([mid, mid]) - half * d, np.array([mid, mid]) + half * d
                plan = Plan(np.array([a, b]), closed=False, point_turns=True,
                            start_s=0.2 + 1.1 * i)
            else:
                corners = [(0.25, 0.25), (arena_m - 0.25, 0.25), (arena_m - 0.25, arena_m - 0.25),
                           (0.25, arena_m - 0.25)]
                plan = Plan(_circle(corners[(i - 3) % 4], 0.12), start_s=start)
        plans.append(plan)
    return plans


class Autopilot:
    """Drives every robot of ``world`` along its :class:`Plan` at ``power`` (fraction of full
    motor power, e.g. 0.5 or 1.0) with pure pursuit on the true pose; corners of plans with
    ``point_turns`` are zero-point turns, with a pause (:attr:`PAUSE_S`, seeded jitter) before
    and after each unless ``pauses`` is False. Call :meth:`update` with the simulated time (s);
    it acts every :data:`CONTROL_PERIOD_S`.

    Args:
        world, plans, power: what to drive, where, how fast.
        pauses: stand still before and after every zero-point turn.
        seed: seed of the pause lengths (None: ``world.seed``).
    """

    LOOKAHEAD_M = 0.08
    ARRIVE_M = 0.012
    TURN_TOL_RAD = math.radians(3.0)
    #: Range of the pause before and after a zero-point turn, s (uniform, seeded).
    PAUSE_S = (0.2, 0.4)

    def __init__(self, world: World, plans: list[Plan], power: float = 1.0, pauses: bool = True,
                 seed: int | None = None):
        if not 0.05 <= power <= 1.0:
            raise ValueError(f"power must be a fraction in [0.05, 1], got {power}")
        if len(plans) != len(world.robots):
            raise ValueError(f"{len(plans)} plans for {len(world.robots)} robots")
        self.world = world
        self.plans = plans
        self.power = float(power)
        self.pauses = bool(pauses)
        self._rng = np.random.default_rng([int(world.seed if seed is None else seed), 2])
        self._next_t = 0.0
        # per robot: target vertex index, mode ("drive"|"turn"|"pause"), direction along open
        # routes; while pausing: until when (s) and the mode that follows
        self._target = [1 % max(len(p.points), 1) for p in plans]
        self._mode = ["drive"] * len(plans)
        self._pause_until = [0.0] * len(plans)
        self._after_pause = ["drive"] * len(plans)
        self._dir = [1] * len(plans)
        self._seg_i = [0] * len(plans)   # smooth paths: index of the nearest vertex
        # steering: effective track width (m) that maps a path curvature to a tread-speed
        # ratio, learnt from how the robot actually curves (as a driver gets the feel of a
        # robot whose treads scrub); and the last pose and command it is learnt from
        self._w_eff = [r.track_width_m * 1.25 for r in world.robots]
        self._last: list[tuple | None] = [None] * len(plans)

    def update(self, t: float) -> None:
        """Set motor powers for time ``t`` (s) if a control period has elapsed."""
        if t + 1e-9 < self._next_t:
            return
        self._next_t = t + CONTROL_PERIOD_S
        for i, plan in enumerate(self.plans):
            self._learn_width(i)
            left, right = self._command(i, plan, t)
            self.world.set_power(i, int(round(left)), int(round(right)))
            self._last[i] = (self.world.pose(i), self.world.power(i))

    def _learn_width(self, i: int) -> None:
        """Update the steering width of robot ``i`` from the curve it drove since the last
        command: on an arc (both treads forward, a clear speed ratio) the width that explains
        the observed curvature is ``2 * ratio * distance / yaw change``."""
        if self._last[i] is None:
            return
        (x0, y0, a0), (left, right) = self._last[i]
        x, y, a = self.world.pose(i)
        ds = math.hypot(x - x0, y - y0)
        dyaw = _wrap(a - a0)
        if left <= 0 or right <= 0 or ds < 1e-3:
            return
        ratio = (right - left) / (right + left)
        if abs(ratio) < 0.05 or ratio * dyaw <= 0 or abs(dyaw) < math.radians(0.2):
            return
        w_obs = 2.0 * ratio * ds / dyaw
        track = self.world.robots[i].track_width_m
        w = self._w_eff[i] + 0.1 * (w_obs - self._w_eff[i])
        self._w_eff[i] = min(max(w, track), 8.0 * track)

    # ------------------------------------------------------------------ internals
    def _command(self, i: int, plan: Plan, t: float) -> tuple[float, float]:
        if t < plan.start_s or any(s <= t < s + d for s, d in plan.stops):
            return 0.0, 0.0
        if len(plan.points) < 2:
            return 0.0, 0.0
        x, y, yaw = self.world.pose(i)
        p = self.power * MAX_POWER
        if plan.point_turns:
            return self._corner_route(i, plan, x, y, yaw, p, t)
        return self._pursuit(i, plan, x, y, yaw, p)

    def _steer(self, i: int, alpha: float, dist: float, p: float) -> tuple[float, float]:
        kappa = 2.0 * math.sin(alpha) / max(dist, 1e-3)
        w = self._w_eff[i]
        left, right = 1.0 - kappa * w / 2, 1.0 + kappa * w / 2
        scale = p / max(abs(left), abs(right), 1e-9)
        return left * scale, right * scale

    def _pursuit(self, i: int, plan: Plan, x: float, y: float, yaw: float, p: float):
        pts = plan.points
        n = len(pts)
        # nearest vertex, searched forward from the last one (figure 8 crosses itself)
        window = (self._seg_i[i] + np.arange(max(4, n // 8))) % n
        k = int(window[np.argmin(np.hypot(pts[window, 0] - x, pts[window, 1] - y))])
        self._seg_i[i] = k
        # look-ahead point: the first vertex LOOKAHEAD_M further along the path
        arc = plan.arc_length()
        ahead = (arc[k] + self.LOOKAHEAD_M) % arc[-1]
        j = int(np.searchsorted(arc, ahead)) % n
        tx, ty = pts[j]
        alpha = _wrap(math.atan2(ty - y, tx - x) - yaw)
        return self._steer(i, alpha, math.hypot(tx - x, ty - y), p)

    def _switch(self, i: int, mode: str, t: float) -> None:
        """Go to ``mode``, through a seeded pause when pausing is on (turns start and end so)."""
        if self.pauses:
            self._mode[i] = "pause"
            self._after_pause[i] = mode
            self._pause_until[i] = t + float(self._rng.uniform(*self.PAUSE_S))
        else:
            self._mode[i] = mode

    def _corner_route(self, i: int, plan: Plan, x: float, y: float, yaw: float, p: float,
                      t: float = 0.0):
        pts = plan.points
        tgt = pts[self._target[i]]
        dx, dy = tgt[0] - x, tgt[1] - y
        dist = math.hypot(dx, dy)
        if self._mode[i] == "pause":
            if t + 1e-9 < self._pause_until[i]:
                return 0.0, 0.0
            self._mode[i] = self._after_pause[i]
        if self._mode[i] == "drive":
            # arrived (or passed the corner along the segment direction)?
            if dist < self.ARRIVE_M or (dist < 0.05 and math.cos(math.atan2(dy, dx) - yaw) < 0):
                self._advance_target(i, plan)
                self._switch(i, "turn", t)
                return 0.0, 0.0
            if abs(_wrap(math.atan2(dy, dx) - yaw)) > math.radians(30):
                self._switch(i, "turn", t)
                return 0.0, 0.0
            # pure pursuit on the segment: look ahead of our projection onto it
            a = pts[self._previous(i, plan)]
            seg = tgt - a
            seg_len = float(np.hypot(*seg))
            s_proj = float(np.dot([x - a[0], y - a[1]], seg) / max(seg_len, 1e-9))
            s_look = min(seg_len, max(0.0, s_proj) + self.LOOKAHEAD_M)
            lx, ly = a + seg * (s_look / max(seg_len, 1e-9))
            alpha = _wrap(math.atan2(ly - y, lx - x) - yaw)
            slow = min(1.0, 0.3 + dist / 0.10)   # ease into the corner
            return self._steer(i, alpha, max(math.hypot(lx - x, ly - y), 0.02), p * slow)
        # zero-point turn towards the next target
        err = _wrap(math.atan2(dy, dx) - yaw)
        if abs(err) < self.TURN_TOL_RAD:
            self._switch(i, "drive", t)
            return 0.0, 0.0
        mag = p * min(1.0, 0.35 + abs(err) / math.radians(45))
        mag = max(mag, 90.0)
        return (-mag, mag) if err > 0 else (mag, -mag)

    def _previous(self, i: int, plan: Plan) -> int:
        if plan.closed:
            return (self._target[i] - 1) % len(plan.points)
        return self._target[i] - self._dir[i]

    def _advance_target(self, i: int, plan: Plan) -> None:
        n = len(plan.points)
        if plan.closed:
            self._target[i] = (self._target[i] + 1) % n
            return
        nxt = self._target[i] + self._dir[i]
        if not 0 <= nxt < n:
            self._dir[i] = -self._dir[i]
            nxt = self._target[i] + self._dir[i]
        self._target[i] = nxt

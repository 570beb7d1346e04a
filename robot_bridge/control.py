"""Mission control (pure): wheel-speed PID, pose fusion, the mission state machine, path error.

Two modes, chosen per mission:

* ``paper`` — the paper's method: each phase is driven open loop in the arena, closed loop
  on the encoders only. Lines and arcs set constant tread speeds (``v (1 -+ k W / 2)``) until
  the encoders report the phase length; zero-point turns spin until the encoders report the
  angle (with the nominal track width, so skid makes the turns short, as on the real robots).
* ``closed`` — follows the commanded path with the robot's own pose: pure pursuit on lines
  and arcs, heading control for zero-point turns. The pose comes from :class:`PoseEstimator`:
  camera tracks (``arena/robots/*``) delayed by the pipeline latency are propagated to *now*
  with odometry (latency compensation); when tracks are stale it runs on odometry alone.

Both modes end in the same per-side wheel-speed PID (encoders -> motor power -400..400).
Times are seconds (host clock unless stated), distances m, angles rad, arena frame.
"""

from __future__ import annotations

import math
from bisect import bisect_left
from collections import deque
from dataclasses import dataclass

import numpy as np

from .missions import Mission, Segment
from .odometry import Odometry, WheelGeometry, wrap_angle

MODES = ("paper", "closed")
MAX_POWER = 400


# --------------------------------------------------------------------------- SE(2) helpers


def compose(a, b):
    """Pose composition a ⊕ b (b expressed in a's frame)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], wrap_angle(a[2] + b[2])


def inverse(a):
    """Inverse pose ⊖ a."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return -c * a[0] - s * a[1], s * a[0] - c * a[1], wrap_angle(-a[2])


# --------------------------------------------------------------------------- wheel PID


@dataclass
class PIDGains:
    """Wheel-speed PID gains: power units per (m/s), per (m/s * s), per (m/s / s)."""

    kp: float = 500.0
    ki: float = 2500.0
    kd: float = 0.0
    i_limit: float = 120.0      # anti-windup clamp of the integral term, power units


class WheelPID:
    """Per-side tread-speed PID with feed-forward ``target / max_speed * 400``.

    ``update(targets m/s, measured m/s, dt s) -> (left, right)`` motor power, clipped to ±400.
    """

    def __init__(self, max_speed_mps: float, gains: PIDGains | None = None):
        self.max_speed = max_speed_mps
        self.g = gains or PIDGains()
        self._i = [0.0, 0.0]
        self._e = [0.0, 0.0]

    def reset(self) -> None:
        self._i = [0.0, 0.0]
        self._e = [0.0, 0.0]

    def update(self, target: tuple[float, float], measured: tuple[float, float], dt: float) -> tuple[int, int]:
        out = []
        for k in (0, 1):
            if target[k] == 0.0:
                self._i[k] = 0.0
                self._e[k] = 0.0
                out.append(0)
                continue
            e = target[k] - measured[k]
            if dt > 0:
                self._i[k] = max(-self.g.i_limit, min(self.g.i_limit, self._i[k] + self.g.ki * e * dt))
                d = (e - self._e[k]) / dt
            else:
                d = 0.0
            self._e[k] = e
            u = target[k] / self.max_speed * MAX_POWER + self.g.kp * e + self._i[k] + self.g.kd * d
            out.append(int(round(max(-MAX_POWER, min(MAX_POWER, u)))))
        return out[0], out[1]


# --------------------------------------------------------------------------- pose fusion


class PoseEstimator:
    """Fuse odometry (smooth, drifts) with delayed camera tracks (absolute, late, noisy).

    The fused pose is ``T ⊕ odometry`` with a correction ``T``. A track measured at host time
    ``t_pose`` is compared with the fused pose *at that time* (odometry history, so the
    pipeline latency is compensated), blended in, and ``T`` updated: the correction then
    carries forward to now through odometry. Tracks whose yaw disagrees by more than
    ``max_yaw_jump`` (a 180 degree heading flip) correct position only.

    Odometry takes its heading from the gyro, which is good for many seconds, so track
    headings only trim its slow drift: they are used while the robot drives (not while it
    stands or spins faster than ``max_spin_radps``: event-camera headings lag and flip
    there) and only within ``max_yaw_jump`` of the fused heading. A track further than
    ``max_jump_m`` from the fused position is an outlier, unless ``relock_after`` come in a
    row (then the estimate re-locks onto the tracks). Position innovations are split: across
    the heading they are blended at ``pos_gain``, along it at the much smaller ``along_gain``:
    encoders measure distance travelled well, while event-camera tracks lag along the motion
    (the centroid of a t_a window trails the robot).

    Args:
        stale_s: a track older than this no longer counts as fresh (source = ``odometry``).
        pos_gain, yaw_gain: blend factors in (0, 1] of a track into the fused pose.
        delay_s: extra age of every track pose beyond its stamp, s: the tracking pipeline's
            own lag (measure it once against ground truth).
    """

    def __init__(self, stale_s: float = 0.3, pos_gain: float = 0.3, yaw_gain: float = 0.02,
                 history_s: float = 3.0, max_yaw_jump: float = math.radians(30), delay_s: float = 0.0,
                 max_spin_radps: float = 1.0, max_jump_m: float = 0.15, relock_after: int = 25,
                 along_gain: float = 0.005):
        self.stale_s = stale_s
        self.delay_s = delay_s
        self.max_spin_radps = max_spin_radps
        self.pos_gain = pos_gain
        self.yaw_gain = yaw_gain
        self.history_s = history_s
        self.max_yaw_jump = max_yaw_jump
        self.max_jump_m = max_jump_m
        self.along_gain = along_gain
        self.relock_after = relock_after
        self._outliers = 0
        self._course_outliers = 0
        self._course: deque[tuple[float, float, float]] = deque()
        self.heading_relocks = 0
        self._yaw_known = False
        self._pos_known = False
        self._T = (0.0, 0.0, 0.0)
        self._times: deque[float] = deque()
        self._odo: deque[tuple[float, float, float]] = deque()
        self.last_track_t: float | None = None     # host time of the newest track pose
        self.tracks_used = 0
        self.tracks_rejected = 0

    def add_odometry(self, t: float, pose) -> None:
        """Record the odometry pose at host time ``t`` (increasing)."""
        self._times.append(t)
        self._odo.append(tuple(pose))
        while self._times and self._times[0] < t - self.history_s:
            self._times.popleft()
            self._odo.popleft()

    def _odo_at(self, t: float):
        times = self._times
        if not times:
            return None
        if t <= times[0]:
            return self._odo[0] if times[0] - t < 0.05 else None
        if t >= times[-1]:
            return self._odo[-1]
        i = bisect_left(times, t)
        t0, t1 = times[i - 1], times[i]
        a, b = self._odo[i - 1], self._odo[i]
        f = (t - t0) / (t1 - t0) if t1 > t0 else 0.0
        return (a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), wrap_angle(a[2] + f * wrap_angle(b[2] - a[2])))

    def set_pose(self, pose) -> None:
        """Declare the current fused pose (e.g. the known start pose, heading included)."""
        self._yaw_known = self._pos_known = True
        if self._odo:
            self._T = compose(tuple(pose), inverse(self._odo[-1]))
        else:
            self._T = tuple(pose)

    def add_track(self, t_pose: float, x: float, y: float, yaw: float | None) -> bool:
        """Blend a track pose measured at host time ``t_pose``; returns False if it was not used
        (older than the odometry history, or an outlier)."""
        t_pose -= self.delay_s
        odo = self._odo_at(t_pose)
        if odo is None:
            self.tracks_rejected += 1
            return False
        fused = compose(self._T, odo)
        jump = math.hypot(x - fused[0], y - fused[1])
        if self._pos_known and jump > self.max_jump_m and self._outliers < self.relock_after:
            self._outliers += 1          # an ID switch or a glitch; many in a row: re-lock on the tracks
            self.tracks_rejected += 1
            return False
        relock = not self._pos_known or self._outliers >= self.relock_after
        self._outliers = 0
        self._pos_known = True
        ex, ey = x - fused[0], y - fused[1]
        if relock:
            nx, ny = x, y
        else:  # cross-track at pos_gain; along the heading (where tracks lag) at along_gain
            c, s_ = math.cos(fused[2]), math.sin(fused[2])
            e_along = c * ex + s_ * ey
            e_cross = -s_ * ex + c * ey
            ga, gc = self.along_gain * e_along, self.pos_gain * e_cross
            nx = fused[0] + c * ga - s_ * gc
            ny = fused[1] + s_ * ga + c * gc
        nth = fused[2]
        before = self._odo_at(t_pose - 0.2)
        steady = before is not None and (
            abs(wrap_angle(odo[2] - before[2])) / 0.2 <= self.max_spin_radps
            and math.hypot(odo[0] - before[0], odo[1] - before[1]) >= 0.01)   # driving, not spinning
        if yaw is not None and math.isfinite(yaw):
            dyaw = wrap_angle(yaw - fused[2])
            if not self._yaw_known:
                nth = yaw
                self._yaw_known = True
            elif steady and abs(dyaw) <= self.max_yaw_jump:
                nth = wrap_angle(fused[2] + self.yaw_gain * dyaw)
        nth = self._check_course(t_pose, x, y, odo, nth)
        self._T = compose((nx, ny, nth), inverse(odo))
        self.last_track_t = t_pose if self.last_track_t is None else max(self.last_track_t, t_pose)
        self.tracks_used += 1
        return True

    def _check_course(self, t_pose: float, x: float, y: float, odo, nth: float) -> float:
        """Heading sanity check from positions only (no shape ambiguity): while odometry says the
        robot drove straight for 0.5 s, the tracks' displacement gives its course. If that
        disagrees with the fused heading by more than ``max_yaw_jump`` on ``relock_after``
        tracks in a row, the heading re-locks onto the course (a wrong initial heading)."""
        self._course.append((t_pose, x, y))
        while self._course and self._course[0][0] < t_pose - 0.6:
            self._course.popleft()
        t0, x0, y0 = self._course[0]
        o0 = self._odo_at(t0)
        if o0 is None or t_pose - t0 < 0.4:
            return nth
        moved = math.hypot(odo[0] - o0[0], odo[1] - o0[1])
        forward = math.cos(math.atan2(odo[1] - o0[1], odo[0] - o0[0]) - odo[2]) > 0.9
        if moved < 0.05 or not forward or abs(wrap_angle(odo[2] - o0[2])) > math.radians(5) \
                or math.hypot(x - x0, y - y0) < 0.6 * moved:
            return nth
        course = math.atan2(y - y0, x - x0)
        if abs(wrap_angle(course - nth)) <= self.max_yaw_jump:
            self._course_outliers = 0
            return nth
        self._course_outliers += 1
        if self._course_outliers < self.relock_after:
            return nth
        self._course_outliers = 0
        self.heading_relocks += 1
        return course

    def pose(self):
        """Current fused pose (x, y, yaw), arena frame."""
        return compose(self._T, self._odo[-1]) if self._odo else self._T

    def source(self, now: float) -> str:
        """``track`` while tracks are fresh, else ``odometry``."""
        if self.last_track_t is not None and now - self.last_track_t <= self.stale_s:
            return "track"
        return "odometry"


class TrackWatch:
    """Whether a closed loop still has its robot's track, or runs on odometry alone (pure).

    Call :meth:`update` on every control step with the host time, the host time of the newest
    track pose fused (``PoseEstimator.last_track_t``, None if none yet) and whether the robot is
    commanded to move. While it stands, no track is expected (a standing robot gives an event
    camera no events), so the clock starts when it moves: moving for more than ``lost_s`` with no
    track since is a *fallback* to odometry (counted in ``fallbacks``); a track coming back ends
    it. ``odometry_s`` times the driving without a track from its beginning (the last track, or
    the moment it started to move) to the measurement time of the track that ended it, not from
    when ``lost_s`` ran out, and without the time it stood meanwhile: how long the loop really
    drove on odometry alone. The part of it before the mission's first track (a track is named
    only once the robot moves) is ``before_first_track_s``. Tracks measured before ``start_t``
    (the mission's start: an earlier mission's) are not this mission's. :meth:`update` returns
    ``"lost"`` or ``"regained"`` when the state changes, else None.
    """

    def __init__(self, lost_s: float = 0.5, start_t: float | None = None):
        self.lost_s = lost_s
        self.start_t = start_t
        self.on_odometry = False
        self.fallbacks = 0
        self.odometry_s = 0.0
        self.before_first_track_s = 0.0
        self.had_track = False                # a fresh track came during this mission
        self._since: float | None = None      # when the current driving without a track began
        self._still_t: float | None = None    # last time the robot was commanded to stand

    def update(self, now: float, last_track_t: float | None, moving: bool) -> str | None:
        if last_track_t is not None and self.start_t is not None and last_track_t < self.start_t:
            last_track_t = None               # an earlier mission's track
        if not moving:
            self._still_t = now
        ref = max(t for t in (last_track_t, self._still_t) if t is not None) \
            if (last_track_t is not None or self._still_t is not None) else None
        if ref is None:
            self._still_t = ref = now
        fresh = last_track_t is not None and now - last_track_t <= self.lost_s
        if self.on_odometry:
            if fresh:                         # driven without a track until this one was measured
                self._close(min(now, last_track_t))
                self.on_odometry, self.had_track = False, True
                return "regained"
            if not moving:                    # standing is not driving on odometry
                self._close(now)
            elif self._since is None:
                self._since = now
            return None
        if moving and now - ref > self.lost_s:
            self.on_odometry, self._since = True, min(ref, now)
            self.fallbacks += 1
            return "lost"
        self.had_track = self.had_track or fresh
        return None

    def _close(self, end: float) -> None:
        """End the running stretch of driving without a track at ``end`` (never negative: a wall
        clock stepped back counts nothing)."""
        if self._since is not None:
            dt = max(0.0, end - self._since)
            self.odometry_s += dt
            if not self.had_track:
                self.before_first_track_s += dt
        self._since = None

    def _running(self, now: float) -> float:
        return max(0.0, now - self._since) if self._since is not None else 0.0

    def odometry_time(self, now: float) -> float:
        """Seconds driven on odometry alone so far (the running fallback included)."""
        return self.odometry_s + self._running(now)

    def as_dict(self, now: float) -> dict:
        first = self.before_first_track_s + (0.0 if self.had_track else self._running(now))
        return {"odometry_fallbacks": self.fallbacks, "odometry_only_s": round(self.odometry_time(now), 3),
                "odometry_before_first_track_s": round(first, 3), "on_odometry_at_end": self.on_odometry}


# --------------------------------------------------------------------------- mission runner


@dataclass
class ControlOutput:
    """What the runner wants now: motor power per side, the phase and whether it is done."""

    left: int
    right: int
    phase: str
    done: bool
    target_left_mps: float = 0.0
    target_right_mps: float = 0.0


@dataclass
class FollowerGains:
    """Closed-loop path following parameters."""

    lookahead_s: float = 0.25        # lookahead time: L = max(min_lookahead, v * lookahead_s), s
    min_lookahead_m: float = 0.05
    max_lookahead_m: float = 0.12
    decel_mps2: float = 0.8          # braking before a zero-point turn
    min_speed_mps: float = 0.04
    turn_kp: float = 4.0             # yaw rate per rad of heading error, 1/s
    turn_tol_rad: float = math.radians(1.5)


class MissionRunner:
    """Run a :class:`Mission` phase by phase; call :meth:`update` on every encoder sample.

    Args:
        mission: the mission (its segments are in the arena frame).
        geometry: the robot's calibrated geometry (closed mode uses it to turn yaw rates into
            tread speeds; paper mode uses ``paper_geometry``).
        mode: ``paper`` or ``closed``.
        paper_geometry: geometry the paper mode trusts for its encoder-only phases (default:
            nominal Zumo values, track width 0.09 m, as in the paper).
        estimator: pose source of closed mode (created if None).
        odometry: the robot's running odometry, shared with ``estimator`` (created at the
            mission start pose if None). The runner updates both on every sample.
    """

    def __init__(self, mission: Mission, geometry: WheelGeometry, mode: str = "paper",
                 paper_geometry: WheelGeometry | None = None, estimator: PoseEstimator | None = None,
                 pid: PIDGains | None = None, follower: FollowerGains | None = None,
                 odometry: Odometry | None = None):
        if mode not in MODES:
            raise ValueError(f"control mode must be one of {MODES}, got {mode!r}")
        self.mission = mission
        self.mode = mode
        self.geometry = geometry
        self.paper_geometry = paper_geometry or WheelGeometry(
            geometry.sprocket_diameter_m, 0.09, geometry.counts_per_rev, geometry.max_speed_mps)
        self.odometry = odometry or Odometry(geometry, mission.start)
        self.estimator = estimator or PoseEstimator()
        self.pid = WheelPID(geometry.max_speed_mps, pid)
        self.fg = follower or FollowerGains()
        self.index = 0
        self.done = False
        self._seg_t0: float | None = None
        self._seg_enc0: tuple[int, int] | None = None
        self._s = 0.0
        self._last: tuple[float, int, int] | None = None
        self.wheel_speeds = (0.0, 0.0)
        self._started = False

    @property
    def segment(self) -> Segment | None:
        return self.mission.segments[self.index] if self.index < len(self.mission.segments) else None

    @property
    def phase(self) -> str:
        seg = self.segment
        return seg.label if seg is not None else "done"

    def pose(self):
        """The pose the runner steers by: fused in closed mode, odometry in paper mode."""
        return self.estimator.pose() if self.mode == "closed" else self.odometry.pose

    def add_track(self, t_pose: float, x: float, y: float, yaw: float | None) -> bool:
        """Feed a camera track of this robot (host time of the pose, arena frame)."""
        return self.estimator.add_track(t_pose, x, y, yaw)

    def _next(self, t: float, enc: tuple[int, int]) -> None:
        self.index += 1
        self._seg_t0 = t
        self._seg_enc0 = enc
        self._s = 0.0
        if self.index >= len(self.mission.segments):
            self.done = True

    def update(self, t: float, enc_left: int, enc_right: int, t_robot: float | None = None,
               gyro_z: float | None = None) -> ControlOutput:
        """Advance with an encoder sample at host time ``t`` s (``t_robot``: robot clock, s,
        used for wheel speeds and gyro integration when given; ``gyro_z``: IMU yaw rate, rad/s).
        Returns the motor command."""
        tr = t if t_robot is None else t_robot
        pose_odo = self.odometry.update(enc_left, enc_right, gyro_z, tr)
        self.estimator.add_odometry(t, pose_odo)
        if not self._started:
            self._started = True
            if self.estimator.last_track_t is None:
                self.estimator.set_pose(self.mission.start)
        dt = 0.0
        if self._last is not None:
            dt = tr - self._last[0]
            if dt > 0:
                mpc = self.geometry.m_per_count
                vl = (enc_left - self._last[1]) * mpc / dt
                vr = (enc_right - self._last[2]) * mpc / dt
                a = 0.5  # light low-pass against count quantisation
                self.wheel_speeds = (a * vl + (1 - a) * self.wheel_speeds[0], a * vr + (1 - a) * self.wheel_speeds[1])
        self._last = (tr, enc_left, enc_right)
        enc = (enc_left, enc_right)
        if self._seg_t0 is None:
            self._seg_t0, self._seg_enc0 = t, enc
        target = (0.0, 0.0)
        for _ in range(len(self.mission.segments) + 1):  # advance over phases finished at once
            seg = self.segment
            if seg is None:
                break
            target, finished = (self._paper if self.mode == "paper" else self._closed)(seg, t, enc)
            if not finished:
                break
            self._next(t, enc)
            target = (0.0, 0.0)
        if self.done:
            self.pid.reset()
            return ControlOutput(0, 0, "done", True)
        target = self._limit(target)
        left, right = self.pid.update(target, self.wheel_speeds, dt)
        return ControlOutput(left, right, self.phase, False, target[0], target[1])

    def _limit(self, target: tuple[float, float]) -> tuple[float, float]:
        """Scale both tread speeds down together so the faster one stays within reach
        (keeps the commanded curvature when a circle at 100 % asks the outer tread for more)."""
        cap = 0.95 * self.geometry.max_speed_mps
        m = max(abs(target[0]), abs(target[1]))
        if m <= cap:
            return target
        return target[0] * cap / m, target[1] * cap / m

    # ---- paper mode: encoder-only phases
    def _paper(self, seg: Segment, t: float, enc: tuple[int, int]):
        v = self.mission.speed_mps
        mpc = self.paper_geometry.m_per_count
        dl = (enc[0] - self._seg_enc0[0]) * mpc
        dr = (enc[1] - self._seg_enc0[1]) * mpc
        if seg.kind == "pause":
            return (0.0, 0.0), t - self._seg_t0 >= seg.duration_s
        if seg.kind == "turn":
            angle = (dr - dl) / self.paper_geometry.track_width_m
            if abs(angle) >= abs(seg.turn_rad):
                return (0.0, 0.0), True
            sgn = 1.0 if seg.turn_rad > 0 else -1.0
            return (-sgn * v, sgn * v), False
        if 0.5 * (dl + dr) >= seg.length_m:
            return (0.0, 0.0), True
        half = 0.5 * seg.curvature * self.paper_geometry.track_width_m
        return (v * (1.0 - half), v * (1.0 + half)), False

    # ---- closed mode: path following on the fused pose
    def _closed(self, seg: Segment, t: float, enc: tuple[int, int]):
        x, y, th = self.estimator.pose()
        v_cruise = self.mission.speed_mps
        w_eff = self.geometry.track_width_m
        if seg.kind == "pause":
            return (0.0, 0.0), t - self._seg_t0 >= seg.duration_s
        if seg.kind == "turn":
            err = wrap_angle(seg.end[2] - th)
            w_max = 2.0 * v_cruise / w_eff
            if abs(err) < self.fg.turn_tol_rad:
                return (0.0, 0.0), True
            w = max(-w_max, min(w_max, self.fg.turn_kp * err))
            w_min = 2.0 * self.fg.min_speed_mps / w_eff
            if abs(w) < w_min:
                w = math.copysign(w_min, err)
            return (-0.5 * w * w_eff, 0.5 * w * w_eff), False
        # progress along the segment: project onto the path near the last progress
        s = self._project(seg, x, y)
        self._s = max(self._s, s)
        remaining = seg.length_m - self._s
        if remaining <= 0.003:
            return (0.0, 0.0), True
        v = v_cruise
        nxt = self.mission.segments[self.index + 1] if self.index + 1 < len(self.mission.segments) else None
        if nxt is None or nxt.kind != "arc" or seg.kind != "arc":
            v = min(v, max(self.fg.min_speed_mps, math.sqrt(2.0 * self.fg.decel_mps2 * remaining)))
        look = max(self.fg.min_lookahead_m, min(self.fg.max_lookahead_m, v * self.fg.lookahead_s))
        s_look = self._s + look
        if s_look <= seg.length_m:
            px, py, _ = seg.pose_at(s_look)
        else:  # beyond the end: extend straight along the end heading
            ex, ey, eth = seg.end
            extra = s_look - seg.length_m
            px, py = ex + extra * math.cos(eth), ey + extra * math.sin(eth)
        dx, dy = px - x, py - y
        c, s_ = math.cos(th), math.sin(th)
        lx, ly = c * dx + s_ * dy, -s_ * dx + c * dy
        d2 = lx * lx + ly * ly
        if lx <= 0.0:  # the lookahead point is behind: turn towards it on the spot
            w = math.copysign(2.0 * v / w_eff, ly if ly != 0 else 1.0)
            return (-0.5 * w * w_eff, 0.5 * w * w_eff), False
        kappa = 2.0 * ly / d2 if d2 > 1e-9 else 0.0
        kappa = max(-2.0 / w_eff, min(2.0 / w_eff, kappa))
        half = 0.5 * kappa * w_eff
        return (v * (1.0 - half), v * (1.0 + half)), False

    def _project(self, seg: Segment, x: float, y: float) -> float:
        """Arc length of the closest point of ``seg`` to (x, y), searched from the last progress."""
        lo = self._s
        hi = min(seg.length_m, lo + 0.15)
        ss = np.linspace(lo, hi, 31)
        pts = seg.positions_at(ss)
        d = np.hypot(pts[:, 0] - x, pts[:, 1] - y)
        return float(ss[int(np.argmin(d))])


# --------------------------------------------------------------------------- scoring


@dataclass(frozen=True)
class PathError:
    """How far a traced shape is from the commanded one, m.

    Attributes:
        mean_m: mean distance of traced points to the commanded path (the headline number).
        max_m: largest such distance.
        rms_m: root mean square of it.
        coverage_m: mean distance of commanded points to the trace (large when the robot
            cut a shape short or never reached part of it).
        n: number of traced points scored.
    """

    mean_m: float
    max_m: float
    rms_m: float
    coverage_m: float
    n: int

    def as_dict(self) -> dict:
        return {"mean_m": self.mean_m, "max_m": self.max_m, "rms_m": self.rms_m,
                "coverage_m": self.coverage_m, "n": self.n}


def path_error(traced: np.ndarray, commanded: np.ndarray, step_m: float = 0.001) -> PathError:
    """Compare a traced trajectory (n, 2) with a commanded path polyline (m, 2), both m.

    The commanded polyline is resampled every ``step_m`` so distances are exact to ``step_m/2``.
    """
    traced = np.asarray(traced, dtype=float).reshape(-1, 2)
    commanded = np.asarray(commanded, dtype=float).reshape(-1, 2)
    if len(traced) == 0 or len(commanded) == 0:
        raise ValueError("path_error needs at least one traced and one commanded point")
    dense = [commanded[:1]]
    for a, b in zip(commanded[:-1], commanded[1:]):
        n = max(1, int(math.ceil(float(np.hypot(*(b - a))) / step_m)))
        f = np.arange(1, n + 1)[:, None] / n
        dense.append(a + f * (b - a))
    dense = np.concatenate(dense)
    from scipy.spatial import cKDTree   # here, not at import: half a second off the bridge's start-up
    d, _ = cKDTree(dense).query(traced)
    cov, _ = cKDTree(traced).query(commanded)
    return PathError(float(d.mean()), float(d.max()), float(np.sqrt((d ** 2).mean())), float(cov.mean()), len(traced))

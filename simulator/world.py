"""Arena physics: tracked (skid-steer) robots driven by motor powers, with sensors.

Frames and units
----------------
Arena frame: origin at one mat corner, ``x`` and ``y`` in metres in ``[0, arena_m]``,
yaw counter-clockwise from +x in radians. Body frame: +x forward, +y left, +z up.
Time in seconds of simulated time.

Model (per robot, vectorised over robots)
-----------------------------------------
* Motor power ``-400..400`` per side (Zumo 32U4 ``setSpeeds`` units). The target tread
  speed is ``power / 400 * max_speed_mps * gain_side`` with a small static deadband and
  a per-side gain mismatch (seeded, a few %), so "drive straight" curves slightly.
* First-order motor lag (time constant 50-100 ms, seeded per robot and side; braking at
  power 0 is 2.5x faster, and a nearly still unpowered tread stops: static friction).
* Skid-steer kinematics: forward speed is the mean tread speed minus a small
  longitudinal slip; the yaw rate is ``(v_r - v_l) / (track_width * chi)`` with
  ``chi > 1`` growing with the turn rate (tracks skid sideways when turning), and a
  small lateral drift on curves. Encoders count tread (sprocket) rotation, so
  dead-reckoning from encoders over-estimates turns exactly like on the real robot.
* Tread scrubbing (``RobotSpec.spin_dps_full``, default 150 deg/s): turning drags the
  treads sideways over the mat; the resisting yaw torque, taken proportional to the yaw
  rate, loads the motors, so a powered tread runs slower by ``scrub * omega`` (the inner
  one of an arc faster: it is back-driven). ``scrub`` (m/s per rad/s) is set per robot so a
  zero-point turn at full power settles at ``spin_dps_full`` (and at about half of it at
  half power: the model is linear). Straight driving is unchanged (no yaw rate, no load);
  arcs lose yaw rate in proportion to their yaw rate. The sprockets (encoders) see the
  slowed treads plus the skid above; the gyro sees the true body rate. ``None``: no
  scrubbing (the kinematics above alone, ~350-380 deg/s at full power).
* Process noise (seeded) on tread speeds; walls keep the whole footprint inside the arena
  (the robot pushes against the wall, the treads keep turning).
* IMU: accelerometer (gravity + body acceleration), gyro and magnetometer in the body
  frame with white noise and a constant per-robot bias. Battery voltage drains with work.

Everything is reproducible: same ``seed`` and same sequence of calls give the same output.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numpy as np
from numba import njit

#: Full-scale motor power (Zumo 32U4 ``motors.setSpeeds`` range is -400..400).
MAX_POWER = 400
#: Gravity, m/s^2.
GRAVITY = 9.81
#: Earth magnetic field in the arena frame (x, y, z), µT: ~20 µT horizontal along +y
#: ("north"), ~-44 µT vertical (northern mid-latitudes).
EARTH_FIELD_UT = np.array([0.0, 20.0, -44.0])
LIGHTING_LEVELS = ("full", "dimmed", "dark")
#: Ids of the ArUco dictionary printed on the shells (DICT_4X4_50).
MARKER_IDS = 50


# -- checks of the simulator's parameter dataclasses (Scenario, DvsParams, RobotSpec) ----------
def _is_int(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def _is_real(value) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def _bounds(lo, hi, lo_open: bool, hi_open: bool, unit: str) -> str:
    u = f" {unit}" if unit else ""
    if lo is not None and hi is not None:
        return f" in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}{u}"
    if lo is not None:
        return f" {'>' if lo_open else '>='} {lo:g}{u}"
    if hi is not None:
        return f" {'<' if hi_open else '<='} {hi:g}{u}"
    return u


def check_number(owner: str, name: str, value, lo=None, hi=None, lo_open: bool = False, hi_open: bool = False,
                 unit: str = "", none: str | None = None, integer: bool = False) -> None:
    """Raise ValueError ``"<owner>.<name> must be ..., got <value>"`` unless ``value`` is a finite
    number (an integer if ``integer``; bools and strings are not numbers) within the bounds
    (``lo_open``/``hi_open``: the bound is excluded). ``none``: None is allowed and means this
    (e.g. ``"off"``)."""
    if value is None and none is not None:
        return
    ok = _is_int(value) if integer else _is_real(value)
    if ok:
        v = float(value)
        ok = (math.isfinite(v) and (lo is None or (v > lo if lo_open else v >= lo))
              and (hi is None or (v < hi if hi_open else v <= hi)))
    if not ok:
        what = ("an integer" if integer else "a finite number") + _bounds(lo, hi, lo_open, hi_open, unit)
        if none is not None:
            what += f", or None ({none})"
        raise ValueError(f"{owner}.{name} must be {what}, got {value!r}")


def check_bool(owner: str, name: str, value) -> None:
    """Raise ValueError unless ``value`` is True or False (not a string, a number or None)."""
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{owner}.{name} must be True or False, got {value!r}")


def check_choice(owner: str, name: str, value, choices) -> None:
    """Raise ValueError unless ``value`` is one of the strings ``choices``."""
    if not isinstance(value, str) or value not in choices:
        raise ValueError(f"{owner}.{name} must be one of {', '.join(choices)}, got {value!r}")


@njit(cache=True, nogil=True)
def _physics_step(h, pose, vtread, power, gain, tau, chi0, lat_slip, track, vmax, half, arena_m,
                  vel, acc_body, travel, energy, noise, deadband, noise_sigma, scrub):
    """Advance every robot by ``h`` s (see the module docstring for the model)."""
    for i in range(pose.shape[0]):
        v_body_old = 0.5 * (vtread[i, 0] + vtread[i, 1])
        work = 0.0
        for side in range(2):
            p = power[i, side]
            eff = 0.0 if abs(p) < deadband else p
            work += abs(eff) / MAX_POWER
            target = eff / MAX_POWER * vmax[i] * gain[i, side]
            if eff != 0.0:
                # scrubbing: the yaw-resisting torque loads the motors (torque-speed line);
                # it slows the tread that drives the turn and back-drives the other one.
                # An unpowered tread is held by the braked high-ratio gearbox.
                target += (1.0 if side == 0 else -1.0) * scrub[i] * vel[i, 2]
            # the motor driver brakes at power 0 (shorted windings): faster than it accelerates
            t_c = 0.4 * tau[i, side] if target == 0.0 else tau[i, side]
            v = vtread[i, side] + (target - vtread[i, side]) * (1.0 - math.exp(-h / t_c))
            if target == 0.0 and abs(v) < 0.01:
                v = 0.0             # static friction: an unpowered, nearly still tread stops
            if abs(v) > 1e-4:
                v += noise[i, side] * noise_sigma * abs(v)
            vtread[i, side] = v
        vl = vtread[i, 0]
        vr = vtread[i, 1]
        # skid-steer: turning skids the tracks, the effective track width grows with turn rate
        dv = vr - vl
        chi = chi0[i] * (1.0 + 0.3 * min(abs(dv) / (2.0 * vmax[i]), 1.0))
        omega = dv / (track[i] * chi)
        v = 0.5 * (vl + vr) * (1.0 - 0.02 * min(abs(omega) / 10.0, 1.0))
        v_lat = -lat_slip[i] * v * omega          # outward drift on curves
        yaw = pose[i, 2]
        c = math.cos(yaw)
        s = math.sin(yaw)
        vx = c * v - s * v_lat
        vy = s * v + c * v_lat
        lo = half[i]
        hi = arena_m - half[i]
        x_new = pose[i, 0] + vx * h
        y_new = pose[i, 1] + vy * h
        xc = min(max(x_new, lo), hi)
        yc = min(max(y_new, lo), hi)
        if xc != x_new:
            vx = 0.0                # against a wall: the treads slip, the body stays
        if yc != y_new:
            vy = 0.0
        pose[i, 0] = xc
        pose[i, 1] = yc
        pose[i, 2] = (yaw + omega * h + math.pi) % (2.0 * math.pi) - math.pi
        acc_body[i, 0] = (0.5 * (vl + vr) - v_body_old) / h
        acc_body[i, 1] = v * omega
        vel[i, 0] = vx
        vel[i, 1] = vy
        vel[i, 2] = omega
        travel[i, 0] += vl * h
        travel[i, 1] += vr * h
        energy[i] += work * h

@dataclass
class RobotSpec:
    """Static description of one robot (Zumo 32U4 class).

    Attributes:
        name: robot name (used in keys and truth files).
        color_rgb: shell colour, 0-255 per channel.
        marker_id: ArUco id (DICT_4X4_50) printed on the shell top, or None.
        length_m, width_m: shell footprint, m (length along the body x axis).
        track_width_m: distance between tread centres, m.
        sprocket_diameter_m: drive sprocket diameter, m.
        counts_per_rev: encoder counts per sprocket revolution (150:1 motors: 1807).
        max_speed_mps: tread speed at power 400, m/s (0.23 m/s at 200).
        start: initial pose (x m, y m, yaw rad) in the arena frame.
        spin_dps_full: zero-point turn rate at full power (left = -400, right = 400), deg/s,
            once the tread scrubbing has settled (real tracked robots: ~150 at full power,
            ~75 at half); ``None``: no scrubbing (the skid kinematics alone, ~350 deg/s).
    """

    name: str
    color_rgb: tuple[int, int, int]
    marker_id: int | None = None
    length_m: float = 0.10
    width_m: float = 0.10
    track_width_m: float = 0.09
    sprocket_diameter_m: float = 0.038
    counts_per_rev: int = 1807
    max_speed_mps: float = 0.46
    start: tuple[float, float, float] = (0.9, 0.9, 0.0)
    spin_dps_full: float | None = 150.0

    def __post_init__(self) -> None:
        check_number("RobotSpec", "marker_id", self.marker_id, 0, MARKER_IDS - 1, integer=True,
                     none="no marker (ArUco DICT_4X4_50 ids)")


def scrub_coefficient(spin_dps_full: float | None, chi0: float, track_width_m: float,
                      max_speed_mps: float) -> float:
    """Motor slow-down per yaw rate, (m/s) / (rad/s), that makes a zero-point turn at full
    power settle at ``spin_dps_full`` for a robot whose skid factor at rest is ``chi0``
    (0 when ``spin_dps_full`` is None or not below the skid kinematics' own rate).

    Steady spin at full power: each tread runs at ``v_s = max_speed - scrub * omega`` and
    ``omega = 2 v_s / (track * chi0 * (1 + 0.3 v_s / max_speed))`` (see :func:`_physics_step`).
    """
    if spin_dps_full is None:
        return 0.0
    if not spin_dps_full > 0:
        raise ValueError(f"spin_dps_full must be > 0 deg/s or None, got {spin_dps_full}")
    w = math.radians(spin_dps_full)
    b = track_width_m * chi0
    denom = 1.0 - 0.15 * b * w / max_speed_mps
    if denom <= 0:
        return 0.0
    v_s = 0.5 * b * w / denom
    return max(0.0, (max_speed_mps - v_s) / w)


class World:
    """The simulated arena with N robots. Thread-safe: every public method takes ``self.lock``.

    Args:
        robots: robot descriptions; robot ``i`` is ``robots[i]``.
        arena_m: side of the square arena, m (the paper's mats: 1.83 m).
        lighting: ceiling lighting level, one of ``"full"``, ``"dimmed"``, ``"dark"``.
        seed: seed of every random draw (mismatch, noise, biases).
    """

    #: Motor power below which the tread does not move (static friction), power units.
    DEADBAND = 12
    #: Tread-speed process noise, relative (1 sigma per sqrt(s)).
    SPEED_NOISE = 0.02

    def __init__(self, robots: list[RobotSpec], arena_m: float = 1.83, lighting: str = "full",
                 seed: int = 0):
        if lighting not in LIGHTING_LEVELS:
            raise ValueError(f"lighting must be one of {LIGHTING_LEVELS}, got {lighting!r}")
        if arena_m <= 0:
            raise ValueError(f"arena_m must be > 0, got {arena_m}")
        self.lock = threading.RLock()
        self.robots: list[RobotSpec] = list(robots)
        self.arena_m = float(arena_m)
        self.lighting = lighting
        self.seed = int(seed)
        self.t = 0.0
        n = len(self.robots)
        self._rng = np.random.default_rng(seed)
        rng = self._rng
        # geometry
        self._track = np.array([r.track_width_m for r in self.robots], dtype=float)
        self._vmax = np.array([r.max_speed_mps for r in self.robots], dtype=float)
        self._circ = np.array([math.pi * r.sprocket_diameter_m for r in self.robots], dtype=float)
        self._cpr = np.array([r.counts_per_rev for r in self.robots], dtype=float)
        # half-extent of the footprint for wall contact (half diagonal: any yaw stays inside)
        self._half = np.array([0.5 * math.hypot(r.length_m, r.width_m) for r in self.robots])
        # state: x, y, yaw, tread speeds (m/s), body velocity, tread travel (m)
        self._pose = np.array([r.start for r in self.robots], dtype=float).reshape(n, 3)
        for i in range(n):
            self._pose[i, :2] = np.clip(self._pose[i, :2], self._half[i],
                                        self.arena_m - self._half[i])
        self._power = np.zeros((n, 2))
        self._vtread = np.zeros((n, 2))
        self._vel = np.zeros((n, 3))        # vx, vy (arena, m/s), omega (rad/s)
        self._acc_body = np.zeros((n, 2))   # body-frame linear acceleration (x, y), m/s^2
        self._travel = np.zeros((n, 2))     # cumulative tread travel, m
        self._energy = np.zeros(n)          # work done by the motors, arbitrary units
        # per-robot imperfections (seeded)
        self._gain = 1.0 + rng.normal(0.0, 0.025, (n, 2))
        self._tau = rng.uniform(0.05, 0.10, (n, 2))
        self._chi0 = rng.uniform(1.15, 1.30, n)          # effective track-width factor
        # tread scrubbing: motor slow-down per yaw rate, (m/s)/(rad/s), 0 = off
        self._scrub = np.array([scrub_coefficient(r.spin_dps_full, self._chi0[i], r.track_width_m,
                                                  r.max_speed_mps)
                                for i, r in enumerate(self.robots)], dtype=float)
        self._lat_slip = rng.uniform(0.01, 0.03, n)      # lateral drift per (m/s * rad/s)
        self._gyro_bias = rng.normal(0.0, 0.01, (n, 3))   # rad/s
        self._accel_bias = rng.normal(0.0, 0.05, (n, 3))  # m/s^2
        self._mag_bias = rng.normal(0.0, 5.0, (n, 3))     # µT (hard iron)
        self._battery0 = rng.uniform(5000.0, 5400.0, n)   # mV, 4 x AA NiMH
        # physics noise is drawn in banks from self._rng; sensor noise from its own stream,
        # so reading the IMU (from other threads, at any time) never changes the motion
        self._noise_bank = np.zeros((0, n, 2))
        self._noise_i = 0
        self._imu_rng = np.random.default_rng([self.seed, 1])

    # ------------------------------------------------------------------ commands
    def set_power(self, i: int, left: int, right: int) -> None:
        """Set motor power of robot ``i`` per side, -400..400 (clipped)."""
        with self.lock:
            self._check(i)
            self._power[i, 0] = float(np.clip(left, -MAX_POWER, MAX_POWER))
            self._power[i, 1] = float(np.clip(right, -MAX_POWER, MAX_POWER))

    def power(self, i: int) -> tuple[int, int]:
        """Current commanded motor power (left, right) of robot ``i``."""
        with self.lock:
            self._check(i)
            return int(self._power[i, 0]), int(self._power[i, 1])

    # ------------------------------------------------------------------ physics
    def step(self, dt: float) -> None:
        """Advance the physics by ``dt`` seconds (internally in sub-steps of at most 5 ms)."""
        if dt < 0:
            raise ValueError(f"dt must be >= 0, got {dt}")
        with self.lock:
            n_sub = max(1, int(math.ceil(dt / 0.005 - 1e-9)))
            h = dt / n_sub
            for _ in range(n_sub):
                self._substep(h)
            self.t += dt

    def _substep(self, h: float) -> None:
        if h <= 0 or len(self.robots) == 0:
            return
        if self._noise_i >= len(self._noise_bank):
            self._noise_bank = self._rng.standard_normal((256,) + self._vtread.shape)
            self._noise_i = 0
        noise = self._noise_bank[self._noise_i]
        self._noise_i += 1
        _physics_step(h, self._pose, self._vtread, self._power, self._gain, self._tau, self._chi0,
                      self._lat_slip, self._track, self._vmax, self._half, self.arena_m, self._vel,
                      self._acc_body, self._travel, self._energy, noise,
                      float(self.DEADBAND), self.SPEED_NOISE * math.sqrt(h), self._scrub)

    # ------------------------------------------------------------------ state
    def pose(self, i: int) -> tuple[float, float, float]:
        """Pose of robot ``i``: (x m, y m, yaw rad in [-pi, pi)) in the arena frame."""
        with self.lock:
            self._check(i)
            x, y, yaw = self._pose[i]
            return float(x), float(y), float(yaw)

    def poses(self) -> np.ndarray:
        """Poses of all robots, shape (n, 3): x m, y m, yaw rad (arena frame). A copy."""
        with self.lock:
            return self._pose.copy()

    def velocity(self, i: int) -> tuple[float, float, float]:
        """Velocity of robot ``i``: vx, vy (m/s, arena frame) and yaw rate omega (rad/s)."""
        with self.lock:
            self._check(i)
            vx, vy, w = self._vel[i]
            return float(vx), float(vy), float(w)

    def velocities(self) -> np.ndarray:
        """Velocities of all robots, shape (n, 3): vx, vy (m/s, arena), omega (rad/s). A copy."""
        with self.lock:
            return self._vel.copy()

    def encoder_counts(self, i: int) -> tuple[int, int]:
        """Cumulative encoder counts (left, right) of robot ``i``: tread travel / sprocket
        circumference * counts_per_rev, unbounded Python ints (wrapping is the firmware's job)."""
        with self.lock:
            self._check(i)
            c = np.floor(self._travel[i] / self._circ[i] * self._cpr[i])
            return int(c[0]), int(c[1])

    def imu(self, i: int) -> dict:
        """One IMU sample of robot ``i`` in the body frame (x forward, y left, z up).

        Returns ``{"accel": (3,) m/s^2, "gyro": (3,) rad/s, "mag": (3,) µT}`` as numpy
        arrays, with white noise (accel 0.03 m/s^2, gyro 0.003 rad/s, mag 0.3 µT) and a
        constant per-robot bias. A resting robot reads accel ~ (0, 0, +9.81).
        """
        with self.lock:
            self._check(i)
            rng = self._imu_rng
            yaw = self._pose[i, 2]
            acc = np.array([self._acc_body[i, 0], self._acc_body[i, 1], GRAVITY])
            gyro = np.array([0.0, 0.0, self._vel[i, 2]])
            c, s = math.cos(yaw), math.sin(yaw)
            ex, ey, ez = EARTH_FIELD_UT
            mag = np.array([c * ex + s * ey, -s * ex + c * ey, ez])
            return {
                "accel": acc + self._accel_bias[i] + rng.normal(0.0, 0.03, 3),
                "gyro": gyro + self._gyro_bias[i] + rng.normal(0.0, 0.003, 3),
                "mag": mag + self._mag_bias[i] + rng.normal(0.0, 0.3, 3),
            }

    def battery_mv(self, i: int) -> int:
        """Battery voltage of robot ``i``, mV: drains with motor work, sags under load."""
        with self.lock:
            self._check(i)
            load = np.abs(self._power[i]).sum() / (2 * MAX_POWER)
            mv = self._battery0[i] - 0.5 * self._energy[i] - 250.0 * load
            return int(max(mv, 3500.0))

    def _check(self, i: int) -> None:
        if not 0 <= i < len(self.robots):
            raise IndexError(f"robot index {i} out of range (world has {len(self.robots)} robots)")

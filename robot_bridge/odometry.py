"""Wheel (tread) odometry from encoder counts, and its calibration (pure).

Frames: poses are (x m, y m, yaw rad) in the arena frame, yaw counter-clockwise from +x.
Encoder counts are cumulative per side; forward is positive.

Tracked robots skid when they turn, so the *effective* track width that maps the tread
speed difference to the yaw rate is larger than the distance between the treads (by
15-30 % on Zumo-class robots, more in fast turns). :func:`calibrate_track_width` measures
it from a spin; better, :class:`Odometry` takes the heading from the IMU gyro when given.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


def wrap_angle(a: float) -> float:
    """Wrap an angle to [-pi, pi), rad."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@dataclass(frozen=True)
class WheelGeometry:
    """Drive geometry of one robot.

    Attributes:
        sprocket_diameter_m: drive sprocket diameter, m (Zumo: ~0.038).
        track_width_m: effective track width used for turning, m (nominal 0.09 between tread
            centres; calibrated values are larger because tracks skid).
        counts_per_rev: encoder counts per sprocket revolution (150:1 motors: 1807).
        max_speed_mps: tread speed at power 400, m/s (feed-forward of the wheel PID).
    """

    sprocket_diameter_m: float = 0.038
    track_width_m: float = 0.09
    counts_per_rev: int = 1807
    max_speed_mps: float = 0.46

    def __post_init__(self):
        for name in ("sprocket_diameter_m", "track_width_m", "max_speed_mps"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.counts_per_rev <= 0:
            raise ValueError(f"counts_per_rev must be > 0, got {self.counts_per_rev}")

    @property
    def m_per_count(self) -> float:
        """Tread travel per encoder count, m."""
        return math.pi * self.sprocket_diameter_m / self.counts_per_rev


class Odometry:
    """Dead reckoning: integrate encoder count increments into an arena-frame pose.

    Example::

        odo = Odometry(WheelGeometry(), pose=(0.5, 0.5, 0.0))
        odo.update(100, 100)          # first call only latches the counts
        x, y, yaw = odo.update(300, 300)
    """

    #: the gyro bias is learned after the treads stood still this long, s ...
    BIAS_STILL_S = 0.3
    #: ... and only from rates below this (a real bias is small), rad/s
    BIAS_MAX_RADPS = 0.1

    def __init__(self, geometry: WheelGeometry, pose: tuple[float, float, float] = (0.0, 0.0, 0.0)):
        self.geometry = geometry
        self.x, self.y, self.yaw = (float(v) for v in pose)
        self.distance_m = 0.0   # total path length driven (mean of both treads), m
        self.gyro_bias = 0.0    # learned yaw-rate bias, rad/s
        self._last: tuple[int, int] | None = None
        self._still_since: float | None = None
        self._last_gyro: tuple[float | None, float | None] = (None, None)

    @property
    def pose(self) -> tuple[float, float, float]:
        """Current pose (x m, y m, yaw rad), arena frame."""
        return self.x, self.y, self.yaw

    def reset(self, pose: tuple[float, float, float]) -> None:
        """Set the pose (keeps the latched counts, so the next increment is still correct)."""
        self.x, self.y, self.yaw = (float(v) for v in pose)

    def update(self, enc_left: int, enc_right: int, gyro_z: float | None = None,
               t: float | None = None) -> tuple[float, float, float]:
        """Integrate from the previous sample to this one (midpoint rule); return the pose.

        Args:
            enc_left, enc_right: cumulative encoder counts.
            gyro_z: yaw rate from the IMU, rad/s (body z up). When given with ``t``, the heading
                is integrated from the gyro instead of the tread difference (tracked robots
                skid in turns, the gyro does not); its bias is learned while the treads stand still.
            t: sample time, s (the robot's clock).
        """
        if self._last is None:
            self._last = (enc_left, enc_right)
            self._last_gyro = (gyro_z, t)
            return self.pose
        mpc = self.geometry.m_per_count
        dl = (enc_left - self._last[0]) * mpc
        dr = (enc_right - self._last[1]) * mpc
        self._last = (enc_left, enc_right)
        ds = 0.5 * (dl + dr)
        dth = (dr - dl) / self.geometry.track_width_m
        g0, t0 = self._last_gyro
        self._last_gyro = (gyro_z, t)
        if dl != 0.0 or dr != 0.0 or t is None:
            self._still_since = t
        elif self._still_since is None:
            self._still_since = t
        if gyro_z is not None and t is not None and g0 is not None and t0 is not None and 0 < t - t0 < 0.5:
            # standing still for a while (not a stalled count) with a small rate: learn the bias
            if t - self._still_since >= self.BIAS_STILL_S and abs(gyro_z) < self.BIAS_MAX_RADPS:
                self.gyro_bias += 0.05 * (gyro_z - self.gyro_bias)
            dth = (0.5 * (g0 + gyro_z) - self.gyro_bias) * (t - t0)
        mid = self.yaw + 0.5 * dth
        self.x += ds * math.cos(mid)
        self.y += ds * math.sin(mid)
        self.yaw = wrap_angle(self.yaw + dth)
        self.distance_m += abs(ds)
        return self.pose


def calibrate_track_width(delta_left_counts: int, delta_right_counts: int, yaw_change_rad: float,
                          geometry: WheelGeometry) -> float:
    """Effective track width, m, from a zero-point turn.

    Args:
        delta_left_counts, delta_right_counts: encoder increments during the turn.
        yaw_change_rad: the true (unwrapped) yaw change during the turn, rad, measured by
            the camera tracks or by integrating the gyro.
        geometry: sprocket diameter and counts per revolution.
    """
    if abs(yaw_change_rad) < math.radians(30):
        raise ValueError("turn at least 30 degrees to calibrate the track width")
    mpc = geometry.m_per_count
    width = (delta_right_counts - delta_left_counts) * mpc / yaw_change_rad
    if width <= 0:
        raise ValueError("encoder increments and yaw change disagree in sign: are the motors swapped?")
    return width


def calibrate_sprocket_diameter(delta_left_counts: int, delta_right_counts: int, distance_m: float,
                                geometry: WheelGeometry) -> float:
    """Effective sprocket diameter, m, from a straight drive of known length ``distance_m``."""
    if distance_m < 0.2:
        raise ValueError("drive at least 0.2 m straight to calibrate the sprocket diameter")
    revs = 0.5 * (delta_left_counts + delta_right_counts) / geometry.counts_per_rev
    if revs <= 0:
        raise ValueError("encoders did not count forward during the straight drive")
    return distance_m / (math.pi * revs)

"""Small synthetic event windows for the tracker tests: square robots (outline events)
driving on a plane seen by an ideal camera, plus uniform noise. Sensor frame px, µs."""

from __future__ import annotations

import numpy as np

from arena.events import make_events

SCALE = 250.0      # px per metre of the test camera
SIZE = (640, 480)  # sensor, px


def calibration_dict(scale: float = SCALE, size=SIZE) -> dict:
    """A top-down camera: u = 20 + x*scale, v = (h - 20) - y*scale (y up in the arena)."""
    w, h = size
    pts = [(0.0, 0.0), (1.8, 0.0), (1.8, 1.8), (0.0, 1.8)]
    return {"image_size": [w, h],
            "points": [{"pixel": [20 + x * scale, h - 20 - y * scale], "arena_m": [x, y]} for x, y in pts]}


def robot_events(rng, pose_fn, t0: int, t1: int, rate_hz: float = 60_000.0, side_px: float = 25.0):
    """Outline events of a square robot whose pose (u, v, heading rad) at time t (µs) is
    pose_fn(t); the density follows the speed (no motion, no events)."""
    n = int(rate_hz * (t1 - t0) * 1e-6)
    t = np.sort(rng.integers(t0, t1, n))
    u, v, th = pose_fn(t)
    u2, v2, _ = pose_fn(t + 1000)
    moving = np.hypot(u2 - u, v2 - v) > 1e-6
    t, u, v, th = t[moving], u[moving], v[moving], th[moving]
    n = t.size
    s = rng.uniform(-side_px / 2, side_px / 2, n)
    e = rng.integers(0, 4, n)
    ox = np.where(e < 2, np.where(e == 0, -side_px / 2, side_px / 2), s)
    oy = np.where(e < 2, s, np.where(e == 2, -side_px / 2, side_px / 2))
    c, sn = np.cos(th), np.sin(th)
    x = u + c * ox - sn * oy
    y = v + sn * ox + c * oy
    p = (ox > 0).astype(np.uint8)
    return x, y, p, t


def window(rng, poses, t0: int, t1: int, noise_per_px_s: float = 0.05, size=SIZE):
    """Events of all robots (list of pose functions) plus noise in [t0, t1), sorted by t."""
    w, h = size
    xs, ys, ps, ts = [], [], [], []
    for f in poses:
        x, y, p, t = robot_events(rng, f, t0, t1)
        xs.append(x), ys.append(y), ps.append(p), ts.append(t)
    nn = rng.poisson(noise_per_px_s * w * h * (t1 - t0) * 1e-6)
    xs.append(rng.uniform(0, w, nn)), ys.append(rng.uniform(0, h, nn))
    ps.append(rng.integers(0, 2, nn)), ts.append(rng.integers(t0, t1, nn))
    x = np.clip(np.rint(np.concatenate(xs)), 0, w - 1)
    y = np.clip(np.rint(np.concatenate(ys)), 0, h - 1)
    t = np.concatenate(ts)
    o = np.argsort(t, kind="stable")
    return make_events(x[o], y[o], np.concatenate(ps)[o], t[o])


def line_pose(u0, v0, du_s, dv_s, t_start=0):
    """Straight motion at (du_s, dv_s) px/s from (u0, v0) at t_start µs (stationary before)."""
    def f(t):
        dt = np.maximum(np.asarray(t) - t_start, 0) * 1e-6
        th = np.full(dt.shape, np.arctan2(dv_s, du_s))
        return u0 + du_s * dt, v0 + dv_s * dt, th
    return f


class Counts:
    """The counting part of arena.service.Service (``count``, ``gauge``, ``error``), without
    Zenoh: what a LiveTracker counts lands in ``c``."""

    def __init__(self):
        self.c: dict[str, int] = {}

    def count(self, key, n=1):
        self.c[key] = self.c.get(key, 0) + n

    def gauge(self, key, value):
        pass

    def error(self, msg):
        pass

"""Homographies between a camera's pixels and arena metres, and the calibration JSON.

Frames: image ``u`` (column, right) and ``v`` (row, down) in px; arena ``x``/``y`` in metres
from one mat corner. A homography maps one *plane* of the world: points at another height
land elsewhere (parallax). For a camera at height ``H`` above the calibrated plane, a point
``h`` above that plane and a horizontal distance ``d`` from the camera's nadir is mapped
``h / (H - h) * d`` too far from the nadir. With the paper's set-up (mat corners clicked on
the floor, shells ~4.5 cm high, camera ~2.45 m up) that is ~1.9 cm at 1 m from the nadir,
more than the ground-truth error budget. So calibrate at the height of what you detect:
shell tops or markers (``height_m`` in the file) — e.g. place a robot at each mat corner
and click its shell-top centre — or use :func:`parallax_shift_m` to judge the error.

Calibration JSON (shared with the tracker)::

    {"image_size": [w, h],
     "height_m": 0.045,                # optional: plane height of "points" above the mats
     "points": [{"pixel": [u, v], "arena_m": [x, y]}, ...]}    # >= 4 points

Other keys (e.g. ``camera``, ``floor_points``) are kept but ignored here.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


class CalibrationError(ValueError):
    """A calibration file or point set that cannot give a homography."""


@dataclass
class Homography:
    """A plane homography pixel <-> arena metres.

    Attributes:
        H: 3x3 matrix mapping homogeneous pixels (u, v, 1) to arena (x, y, 1), m.
        height_m: height above the mats of the plane it maps, m.
        image_size: (width, height) of the image it applies to, px, if known.
    """

    H: np.ndarray
    height_m: float = 0.0
    image_size: tuple[int, int] | None = None
    Hinv: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        self.H = np.asarray(self.H, dtype=float).reshape(3, 3)
        if not np.all(np.isfinite(self.H)) or abs(np.linalg.det(self.H)) < 1e-15:
            raise CalibrationError("homography is singular or not finite")
        self.Hinv = np.linalg.inv(self.H)

    @classmethod
    def from_points(cls, pixels, arena_m, height_m: float = 0.0,
                    image_size: tuple[int, int] | None = None) -> "Homography":
        """Fit from >= 4 correspondences: ``pixels`` (n, 2) px and ``arena_m`` (n, 2) m.

        Exact for 4 points, least squares (normalised DLT) for more.
        Raises :class:`CalibrationError` for too few, non-finite or degenerate points
        (three of them on one line).
        """
        px = np.asarray(pixels, dtype=float).reshape(-1, 2)
        ar = np.asarray(arena_m, dtype=float).reshape(-1, 2)
        if len(px) != len(ar):
            raise CalibrationError(f"{len(px)} pixel points but {len(ar)} arena points")
        if len(px) < 4:
            raise CalibrationError(f"a homography needs at least 4 points, got {len(px)}")
        if not (np.all(np.isfinite(px)) and np.all(np.isfinite(ar))):
            raise CalibrationError("calibration points must be finite numbers")
        for pts, what in ((px, "pixel"), (ar, "arena")):
            # degenerate if the points do not span a plane (all within a line)
            centred = pts - pts.mean(0)
            sv = np.linalg.svd(centred, compute_uv=False)
            if sv[-1] < 1e-6 * max(sv[0], 1e-12):
                raise CalibrationError(f"the {what} points are collinear: need 4 spread-out points")
        return cls(_dlt(px, ar), float(height_m), image_size)

    def to_arena(self, uv) -> np.ndarray:
        """Map pixels ``(n, 2)`` (or one ``(2,)``) to arena metres, same shape."""
        return _apply(self.H, uv)

    def to_pixel(self, xy) -> np.ndarray:
        """Map arena metres ``(n, 2)`` (or one ``(2,)``) to pixels, same shape."""
        return _apply(self.Hinv, xy)

    def reprojection_error_m(self, pixels, arena_m) -> np.ndarray:
        """Distance (m) between ``arena_m`` and the mapped ``pixels``, per point."""
        return np.linalg.norm(self.to_arena(pixels) - np.asarray(arena_m, float).reshape(-1, 2), axis=1)

    def to_dict(self, points_px, points_m) -> dict:
        """Calibration-JSON dict of this homography's correspondences (px, m)."""
        d = {"points": [{"pixel": [float(u), float(v)], "arena_m": [float(x), float(y)]}
                        for (u, v), (x, y) in zip(np.asarray(points_px, float).reshape(-1, 2),
                                                  np.asarray(points_m, float).reshape(-1, 2))],
             "height_m": self.height_m}
        if self.image_size is not None:
            d["image_size"] = [int(self.image_size[0]), int(self.image_size[1])]
        return d


def _normaliser(pts: np.ndarray) -> np.ndarray:
    """Similarity moving the points' centroid to 0 and their mean distance to sqrt(2)."""
    c = pts.mean(0)
    d = np.linalg.norm(pts - c, axis=1).mean()
    s = math.sqrt(2) / d
    return np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1.0]])


def _dlt(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Normalised direct linear transform (Hartley & Zisserman, alg. 4.2), float64:
    exact for 4 points, algebraic least squares for more."""
    ts, td = _normaliser(src), _normaliser(dst)
    a = _apply(ts, src)
    b = _apply(td, dst)
    rows = []
    for (x, y), (u, v) in zip(a, b):
        rows.append([-x, -y, -1, 0, 0, 0, u * x, u * y, u])
        rows.append([0, 0, 0, -x, -y, -1, v * x, v * y, v])
    h = np.linalg.svd(np.array(rows))[2][-1].reshape(3, 3)
    h = np.linalg.inv(td) @ h @ ts
    return h / h[2, 2]


def _apply(m: np.ndarray, pts) -> np.ndarray:
    a = np.asarray(pts, dtype=float)
    flat = a.reshape(-1, 2)
    h = flat @ m[:, :2].T + m[:, 2]
    out = h[:, :2] / h[:, 2:3]
    return out.reshape(a.shape)


def homography_from_calibration(cal: dict, key: str = "points") -> Homography:
    """Build a :class:`Homography` from a calibration-JSON dict (``key`` selects the point
    list, e.g. ``"floor_points"``). Raises :class:`CalibrationError` with a clear message."""
    if not isinstance(cal, dict):
        raise CalibrationError("calibration must be a JSON object")
    pts = cal.get(key)
    if not isinstance(pts, list) or not pts:
        raise CalibrationError(f"calibration has no {key!r} list of {{'pixel', 'arena_m'}} points")
    try:
        px = [[float(v) for v in p["pixel"]] for p in pts]
        ar = [[float(v) for v in p["arena_m"]] for p in pts]
    except (KeyError, TypeError, ValueError) as e:
        raise CalibrationError(f"each of {key!r} needs 'pixel': [u, v] and 'arena_m': [x, y] ({e})") from None
    if any(len(p) != 2 for p in px + ar):
        raise CalibrationError(f"each 'pixel' and 'arena_m' in {key!r} must have 2 numbers")
    size = cal.get("image_size")
    image_size = (int(size[0]), int(size[1])) if isinstance(size, list) and len(size) == 2 else None
    height = 0.0 if key == "floor_points" else float(cal.get("height_m", 0.0) or 0.0)
    return Homography.from_points(px, ar, height, image_size)


def load_calibration(path: str | Path, key: str = "points") -> Homography:
    """Read a calibration JSON file and fit its homography (see the module docstring)."""
    path = Path(path)
    try:
        cal = json.loads(path.read_text())
    except FileNotFoundError:
        raise CalibrationError(f"calibration file not found: {path}") from None
    except (OSError, json.JSONDecodeError) as e:
        raise CalibrationError(f"cannot read calibration {path}: {e}") from None
    return homography_from_calibration(cal, key)


def save_calibration(path: str | Path, pixels, arena_m, image_size: tuple[int, int],
                     height_m: float = 0.0, **extra) -> Homography:
    """Write a calibration JSON from point pairs (px, m) after checking they give a
    homography; ``extra`` keys are stored too. Returns the homography."""
    h = Homography.from_points(pixels, arena_m, height_m, image_size)
    d = h.to_dict(pixels, arena_m)
    d.update(extra)
    Path(path).write_text(json.dumps(d, indent=2) + "\n")
    return h


def parallax_shift_m(height_m: float, camera_height_m: float, distance_m: float) -> float:
    """Horizontal error (m) of mapping a point ``height_m`` above the calibrated plane with
    that plane's homography, for a camera ``camera_height_m`` above the plane and the point
    ``distance_m`` (horizontally) from the camera's nadir: ``h / (H - h) * d``."""
    if camera_height_m <= height_m:
        raise ValueError("the camera must be above the point")
    return height_m / (camera_height_m - height_m) * distance_m


__all__ = ["CalibrationError", "Homography", "homography_from_calibration", "load_calibration",
           "save_calibration", "parallax_shift_m"]

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

Other keys (e.g. ``camera``, ``floor_points``) are kept but ignored here. The fit, the error
type and the reading of the file are :mod:`arena.homography`'s (shared with the tracker).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from arena.homography import (CalibrationError, apply_homography, calibration_points, fit_homography,
                              read_calibration_json)


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

        Exact for 4 points, least squares for more (:func:`arena.homography.fit_homography`).
        Raises :class:`CalibrationError` for too few, non-finite or degenerate points
        (all on one line).
        """
        return cls(fit_homography(pixels, arena_m), float(height_m), image_size)

    def to_arena(self, uv) -> np.ndarray:
        """Map pixels ``(n, 2)`` (or one ``(2,)``) to arena metres, same shape."""
        return apply_homography(self.H, uv)

    def to_pixel(self, xy) -> np.ndarray:
        """Map arena metres ``(n, 2)`` (or one ``(2,)``) to pixels, same shape."""
        return apply_homography(self.Hinv, xy)

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


def homography_from_calibration(cal: dict, key: str = "points") -> Homography:
    """Build a :class:`Homography` from a calibration-JSON dict (``key`` selects the point
    list, e.g. ``"floor_points"``). Raises :class:`CalibrationError` with a clear message."""
    px, ar = calibration_points(cal, key)
    size = cal.get("image_size")
    image_size = (int(size[0]), int(size[1])) if isinstance(size, list) and len(size) == 2 else None
    height = 0.0 if key == "floor_points" else float(cal.get("height_m", 0.0) or 0.0)
    return Homography.from_points(px, ar, height, image_size)


def load_calibration(path: str | Path, key: str = "points") -> Homography:
    """Read a calibration JSON file and fit its homography (see the module docstring)."""
    return homography_from_calibration(read_calibration_json(path), key)


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

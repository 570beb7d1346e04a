"""Calibration of the event camera: sensor pixels <-> arena metres by a homography.

Frames: sensor ``(u, v)`` px (u column right, v row down); arena ``(x, y)`` m (origin at
one mat corner, yaw counter-clockwise from +x). The calibration file is JSON::

    {"image_size": [w, h], "points": [{"pixel": [u, v], "arena_m": [x, y]}, ...]}

with at least 4 points (no 3 of the first 4 collinear). The same dict is accepted inside a
lab config's camera table (``arena.config.CameraConfig.calibration``). Optional keys:
``height_m`` (height above the mats of the plane the points were taken on, default 0) and
``camera_height_m`` (height of the lens above the mats), used for the parallax correction
of robots seen at their shell-top height (see :meth:`Calibration.parallax_factor`).

The fit, the error type and the file reader are :mod:`arena.homography`'s, shared with the
ground truth, the viewer and the recorder; this module adds what the tracker needs on top
(scale, Jacobian, parallax, finding the mat's corners).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from arena.homography import CalibrationError, apply_homography, calibration_points, fit_homography
from arena.homography import read_calibration_json as _read_json

__all__ = ["Calibration", "CalibrationError", "load_calibration"]


@dataclass
class Calibration:
    """A pixel <-> arena homography.

    Attributes:
        H: 3x3 homography, sensor px -> arena m.
        image_size: sensor (width, height), px.
        pixels, arena_m: the (n, 2) point pairs it was fitted to.
    """

    H: np.ndarray
    image_size: tuple[int, int]
    pixels: np.ndarray
    arena_m: np.ndarray
    height_m: float = 0.0
    camera_height_m: float | None = None

    def __post_init__(self) -> None:
        self._h = tuple(float(c) for c in np.asarray(self.H, dtype=np.float64).ravel())
        self._Hinv = np.linalg.inv(self.H)

    @classmethod
    def from_points(cls, pixels, arena_m, image_size: tuple[int, int]) -> "Calibration":
        """Fit the homography to >= 4 pairs of (u, v) px and (x, y) m (least squares)."""
        px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        am = np.asarray(arena_m, dtype=np.float64).reshape(-1, 2)
        w, h = (int(image_size[0]), int(image_size[1]))
        H = fit_homography(px, am)
        if w <= 0 or h <= 0:
            raise CalibrationError(f"image_size must be positive [w, h] px, got {list(image_size)}")
        return cls(H=H, image_size=(w, h), pixels=px, arena_m=am)

    @classmethod
    def from_dict(cls, d: dict, source: str = "calibration") -> "Calibration":
        """Build from the calibration JSON dict (see the module docstring)."""
        if not isinstance(d, dict):
            raise CalibrationError(f"{source}: expected a JSON object with image_size and points")
        try:
            size = d["image_size"]
            size = (int(size[0]), int(size[1]))
        except (KeyError, TypeError, IndexError, ValueError) as exc:
            raise CalibrationError(
                f"{source}: expected {{\"image_size\": [w, h], \"points\": [{{\"pixel\": [u, v], "
                f"\"arena_m\": [x, y]}}, ...]}} ({type(exc).__name__}: {exc})") from None
        try:
            px, am = calibration_points(d)
            cal = cls.from_points(px, am, size)
            cal.height_m = float(d.get("height_m", 0.0) or 0.0)
            cam_h = d.get("camera_height_m")
            cal.camera_height_m = None if cam_h is None else float(cam_h)
        except (ValueError, TypeError) as exc:
            raise CalibrationError(f"{source}: {exc}") from None
        if cal.camera_height_m is not None and not cal.camera_height_m > cal.height_m:
            raise CalibrationError(f"{source}: camera_height_m must be above height_m")
        return cal

    def to_dict(self) -> dict:
        d = {"image_size": [int(self.image_size[0]), int(self.image_size[1])],
             "points": [{"pixel": [float(u), float(v)], "arena_m": [float(x), float(y)]}
                        for (u, v), (x, y) in zip(self.pixels, self.arena_m)]}
        if self.height_m:
            d["height_m"] = self.height_m
        if self.camera_height_m is not None:
            d["camera_height_m"] = self.camera_height_m
        return d

    def nadir_m(self) -> tuple[float, float]:
        """Arena point under the camera, m: taken as the image centre's (a ceiling camera
        looking down with its principal point at the centre)."""
        return self.point_to_arena(self.image_size[0] / 2.0, self.image_size[1] / 2.0)

    def parallax_factor(self, object_height_m: float, camera_height_m: float) -> float:
        """Scale of distances from the nadir that brings a point seen at ``object_height_m``
        (e.g. a shell top), mapped with this calibration, to its true arena position.

        A ray from the lens (``camera_height_m`` above the mats) through a point at height
        hr meets the calibrated plane (``height_m``) at q = c + (P - c)(H - hc)/(H - hr):
        the factor is (H - hr)/(H - hc) (1 when the heights agree).
        """
        if not camera_height_m > max(object_height_m, self.height_m):
            raise CalibrationError(f"camera height {camera_height_m} m must be above the object "
                                   f"({object_height_m} m) and the calibration plane ({self.height_m} m)")
        return (camera_height_m - object_height_m) / (camera_height_m - self.height_m)

    def save(self, path: str | Path) -> None:
        """Write the calibration JSON file."""
        Path(path).write_text(json.dumps(self.to_dict(), indent=2) + "\n")

    # -- mapping ----------------------------------------------------------
    def to_arena(self, uv) -> np.ndarray:
        """Sensor (u, v) px -> arena (x, y) m; accepts (2,) or (n, 2)."""
        return apply_homography(self.H, uv)

    def to_pixel(self, xy) -> np.ndarray:
        """Arena (x, y) m -> sensor (u, v) px; accepts (2,) or (n, 2)."""
        return apply_homography(self._Hinv, xy)

    def point_to_arena(self, u: float, v: float) -> tuple[float, float]:
        """One sensor pixel (u, v) px -> arena (x, y) m, as Python floats (fast path)."""
        h = self._h
        w = h[6] * u + h[7] * v + h[8]
        return (h[0] * u + h[1] * v + h[2]) / w, (h[3] * u + h[4] * v + h[5]) / w

    def jacobian(self, u: float, v: float) -> tuple[tuple[float, float], tuple[float, float]]:
        """d(x, y)/d(u, v) at pixel (u, v): ((dx/du, dx/dv), (dy/du, dy/dv)), m per px."""
        h = self._h
        w = h[6] * u + h[7] * v + h[8]
        x = (h[0] * u + h[1] * v + h[2]) / w
        y = (h[3] * u + h[4] * v + h[5]) / w
        return (((h[0] - x * h[6]) / w, (h[1] - x * h[7]) / w),
                ((h[3] - y * h[6]) / w, (h[4] - y * h[7]) / w))

    def px_per_m(self, u: float | None = None, v: float | None = None) -> float:
        """Image scale at pixel (u, v) (default: the image centre), px per metre."""
        if u is None or v is None:
            u, v = self.image_size[0] / 2.0, self.image_size[1] / 2.0
        (a, b), (c, d) = self.jacobian(u, v)
        return 1.0 / math.sqrt(abs(a * d - b * c))

    def vector_to_arena(self, u: float, v: float, du: float, dv: float) -> tuple[float, float]:
        """A sensor-frame vector (px or px/s) at pixel (u, v) -> arena frame (m or m/s)."""
        (a, b), (c, d) = self.jacobian(u, v)
        return a * du + b * dv, c * du + d * dv

    def heading_to_arena(self, u: float, v: float, heading_px: float) -> float:
        """Heading in the sensor frame (rad from +u towards +v) -> arena yaw (rad, CCW from +x)."""
        ax, ay = self.vector_to_arena(u, v, math.cos(heading_px), math.sin(heading_px))
        return math.atan2(ay, ax)

    def reprojection_error_m(self) -> float:
        """RMS distance between the fitted and the given arena points, m."""
        d = self.to_arena(self.pixels) - self.arena_m
        return float(np.sqrt((d ** 2).sum(1).mean()))


def load_calibration(path: str | Path, camera: str | None = None) -> Calibration:
    """Load a calibration JSON file, or a lab config TOML (its camera ``camera`` or the first)."""
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"{path}: no such calibration file")
    if path.suffix.lower() == ".toml":
        from arena.config import ConfigError, load_lab_config

        try:
            cam = load_lab_config(path).camera(camera)
        except ConfigError as exc:
            raise CalibrationError(str(exc)) from None
        if cam.calibration is None:
            raise CalibrationError(f"{path}: camera {cam.name!r} has no calibration")
        return Calibration.from_dict(cam.calibration, f"{path} camera {cam.name}")
    return Calibration.from_dict(_read_json(path), str(path))


def mat_points(side_m: float) -> np.ndarray:
    """Arena coordinates (m) of the mat corners in the order :func:`find_mat_corners` returns
    them: bottom-left (origin), bottom-right, top-right, top-left of the image."""
    return np.array([[0.0, 0.0], [side_m, 0.0], [side_m, side_m], [0.0, side_m]])


def find_mat_corners(gray: np.ndarray) -> np.ndarray:
    """Corners of the mat (the largest bright quadrilateral) in a grayscale image, px.

    Works on a webcam frame (white mats on a darker floor) and on an accumulated event
    image (robots and noise light up the arena). Returns a (4, 2) array ordered
    bottom-left, bottom-right, top-right, top-left in the image. Raises
    :class:`CalibrationError` when no convincing quadrilateral is found.
    """
    if gray is None or gray.ndim != 2 or gray.size == 0:
        raise CalibrationError("expected a non-empty grayscale image")
    if float(gray.std()) < 2.0:
        raise CalibrationError("the image has no contrast: no mat found (give --points)")
    img = cv2.GaussianBlur(gray.astype(np.uint8), (5, 5), 0)
    _, mask = cv2.threshold(img, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    k = max(3, (min(gray.shape) // 60) | 1)
    mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_RECT, (k, k)))
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    if not contours:
        raise CalibrationError("no bright region found: is the mat in view? (or give --points)")
    c = max(contours, key=cv2.contourArea)
    area = cv2.contourArea(c)
    if area < 0.05 * gray.size:
        raise CalibrationError(f"the largest bright region covers only {100 * area / gray.size:.1f} % of the "
                               "image: no mat found (give --points)")
    if area > 0.97 * gray.size:
        raise CalibrationError("the bright region fills the whole image: the mat's edges are not in view "
                               "(give --points)")
    hull = cv2.convexHull(c)
    quad = None
    peri = cv2.arcLength(hull, True)
    for f in (0.01, 0.02, 0.03, 0.05, 0.08):
        approx = cv2.approxPolyDP(hull, f * peri, True)
        if len(approx) == 4:
            quad = approx.reshape(4, 2).astype(np.float64)
            break
    if quad is None:
        raise CalibrationError("the mat's outline is not a quadrilateral (occluded corner?): give --points")
    # a mat is one solid bright quadrilateral on a darker surround; speckle (e.g. an event image
    # of sensor noise only) can close into a large blob with four corners too: refuse it
    inside = np.zeros_like(mask)
    cv2.fillConvexPoly(inside, quad.astype(np.int32), 255)
    fill = float((mask[inside > 0] > 0).mean())
    spill = float((mask[inside == 0] > 0).mean()) if (inside == 0).any() else 0.0
    if fill < 0.85 or spill > 0.15:
        raise CalibrationError(f"no clear mat in the image (the bright quadrilateral found is {100 * fill:.0f} % "
                               f"filled, {100 * spill:.0f} % bright outside): give --points")
    # order: bottom-left, bottom-right, top-right, top-left (v grows downwards)
    s = quad.sum(1)
    d = quad[:, 0] - quad[:, 1]
    tl, br = quad[np.argmin(s)], quad[np.argmax(s)]
    tr, bl = quad[np.argmax(d)], quad[np.argmin(d)]
    return np.array([bl, br, tr, tl])

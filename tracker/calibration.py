"""Calibration of the event camera: sensor pixels <-> arena metres by a homography.

Frames: sensor ``(u, v)`` px (u column right, v row down); arena ``(x, y)`` m (origin at
one mat corner, yaw counter-clockwise from +x). The calibration file is JSON::

    {"image_size": [w, h], "points": [{"pixel": [u, v], "arena_m": [x, y]}, ...]}

with at least 4 points (no 3 of the first 4 collinear), each pixel on the sensor or off it by
less than the sensor's size (a point computed just out of view), and the arena points in metres (spanning under :data:`MAX_ARENA_SPAN_M`: more is cm or mm); a key not in
:data:`arena.homography.CALIBRATION_KEYS` is refused (a typo would fall back to a default).
The same dict is accepted inside a lab config's camera table
(``arena.config.CameraConfig.calibration``). Optional keys:
``height_m`` (height above the mats of the plane the points were taken on, default 0),
``camera_height_m`` (height of the lens above the mats, m) and ``nadir_m`` (``[x, y]``, the
arena point straight under the lens, m; or ``nadir_px``, its pixel), used for the parallax correction of robots seen
above the mats (see :meth:`Calibration.parallax_factor`). ``arena calibrate`` writes them when
it is told them (``--camera-height-m``, ``--nadir``) or can estimate them (the camera's pose
from the homography and the lens's focal length: :meth:`Calibration.estimate_pose`). Unknown
camera height: the tracker assumes :data:`FALLBACK_CAMERA_HEIGHT_M` and says so; unknown
nadir: the image centre's arena point (the nadir of a camera looking straight down).

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

from arena.config import CAMERA_HEIGHT_RANGE_M, NADIR_MAX_ARENAS, nadir_distance_m
from arena.homography import (CalibrationError, apply_homography, calibration_points, check_calibration_keys,
                              fit_homography)
from arena.homography import read_calibration_json as _read_json

__all__ = ["Calibration", "CalibrationError", "load_calibration", "camera_calibration", "CameraPose",
           "FALLBACK_CAMERA_HEIGHT_M", "DEFAULT_ROBOT_HEIGHT_M", "lens_focal_px", "CAMERA_HEIGHT_RANGE_M",
           "MAX_PLANE_HEIGHT_M", "MAX_PINHOLE_FOV_DEG", "PIXEL_PITCH_RANGE_UM", "MAX_ARENA_SPAN_M",
           "lens_height_disagreement", "LENS_HEIGHT_TOLERANCE", "check_extent"]

#: Lens height assumed when neither the command line, the lab file nor the calibration gives
#: one, m: a ceiling camera under a room's ~2.5 m ceiling. The tracker warns when it uses it.
FALLBACK_CAMERA_HEIGHT_M = 2.5
#: Effective visible height of a Zumo 32U4, m: the mean height of its event cloud, not its shell
#: top (4.5 cm). The events come from the treads (~3 cm), the shell's top edges (~4 cm), its side
#: walls and its shadow, so their centroid sits lower than the top: on independent recordings
#: (issue 19) a Zumo's cloud shifted outwards by ~1.3 % of its distance from the nadir (less for
#: bright shells), which under a 2.5 m camera is a point ~3.2 cm above the mats.
DEFAULT_ROBOT_HEIGHT_M = 0.032
#: Highest plane a calibration's points may be taken on (``height_m``), m: the mats (0) or a board
#: or the robots' shell tops on them; 2 m above the mats is already at a ceiling lens's height.
MAX_PLANE_HEIGHT_M = 2.0
#: Widest field of view, across the sensor's diagonal, of a lens the pinhole model of
#: :meth:`Calibration.estimate_pose` (no distortion) stands for, degrees: the widest rectilinear
#: lenses cover ~120-130 deg; a focal length giving more is a fisheye (not a pinhole) or a wrong
#: unit (e.g. 0.3 mm for 3 mm: 174 deg on a 640x480 sensor of 15 µm pixels).
MAX_PINHOLE_FOV_DEG = 150.0
#: Widest span of a calibration's arena points, m: a lab arena is a few metres (mats of 1.83 m),
#: a sports hall's floor under one camera a few tens; 50 m and more is a unit slip (cm or mm for m:
#: a 1.83 m mat typed in cm spans 183), which would put every position 100x off.
MAX_ARENA_SPAN_M = 50.0
#: Pixel pitch of real image and event sensors, µm (IMX636: 4.86, Prophesee Gen3 VGA: 15, DAVIS346:
#: 18.5; phone sensors ~1; none beyond ~40).
PIXEL_PITCH_RANGE_UM = (0.5, 50.0)


@dataclass(frozen=True)
class CameraPose:
    """The camera's pose recovered from a calibration and the focal length
    (:meth:`Calibration.estimate_pose`).

    Attributes:
        camera_height_m: lens height above the mats, m.
        nadir_m: arena point under the lens, m.
        tilt_deg: angle between the optical axis and the vertical, degrees.
        consistency: ratio of the two column norms of K^-1 H^-1 (1 for a pinhole with square
            pixels; far from 1: wrong lens values or a bad homography. For a camera looking
            nearly straight down it stays near 1 whatever the focal length, so it does not
            check the focal length: the height's relative error is the focal length's).
    """

    camera_height_m: float
    nadir_m: tuple[float, float]
    tilt_deg: float
    consistency: float


@dataclass
class Calibration:
    """A pixel <-> arena homography.

    Attributes:
        H: 3x3 homography, sensor px -> arena m.
        image_size: sensor (width, height), px.
        pixels, arena_m: the (n, 2) point pairs it was fitted to.
        height_m: height of the plane of the points above the mats, m.
        camera_height_m: lens height above the mats, m (None: unknown).
        nadir: arena point under the lens, (x, y) m (JSON key ``nadir_m``; None: unknown,
            :meth:`nadir_m` then gives the image centre's point).
    """

    H: np.ndarray
    image_size: tuple[int, int]
    pixels: np.ndarray
    arena_m: np.ndarray
    height_m: float = 0.0
    camera_height_m: float | None = None
    nadir: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        self._h = tuple(float(c) for c in np.asarray(self.H, dtype=np.float64).ravel())
        self._Hinv = np.linalg.inv(self.H)

    @classmethod
    def from_points(cls, pixels, arena_m, image_size: tuple[int, int]) -> "Calibration":
        """Fit the homography to >= 4 pairs of (u, v) px and (x, y) m (least squares).

        Points computed rather than seen (e.g. a model's projection of mat corners out of view)
        may lie off the sensor here; ``arena calibrate --points`` refuses them, and the calibration
        file (:meth:`from_dict`) refuses those off by more than the sensor's size (:func:`check_extent`)."""
        px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        am = np.asarray(arena_m, dtype=np.float64).reshape(-1, 2)
        w, h = (int(image_size[0]), int(image_size[1]))
        if w <= 0 or h <= 0:
            raise CalibrationError(f"image_size must be positive [w, h] px, got {list(image_size)}")
        H = fit_homography(px, am)
        return cls(H=H, image_size=(w, h), pixels=px, arena_m=am)

    @classmethod
    def from_dict(cls, d: dict, source: str = "calibration") -> "Calibration":
        """Build from the calibration JSON dict (see the module docstring)."""
        if not isinstance(d, dict):
            raise CalibrationError(f"{source}: expected a JSON object with image_size and points")
        size = d.get("image_size")
        if not (isinstance(size, (list, tuple)) and len(size) == 2
                and all(_real(v) and float(v) == int(v) and 0 < v <= 65535 for v in size)):
            raise CalibrationError(f"{source}: image_size: expected [w, h], the sensor size in px (integers "
                                   f"1..65535), got {_show(size) if 'image_size' in d else 'nothing (key missing)'}")
        check_calibration_keys(d, source)
        _check_points(d, source)
        try:
            px, am = calibration_points(d)
            # a file may hold points computed rather than seen (a model's projection of mat corners
            # just out of view): off the sensor by up to its own size is kept, farther is a typo
            check_extent(px, am, (int(size[0]), int(size[1])), lambda i: f"points[{i}]",
                         slack_px=float(max(int(size[0]), int(size[1]))))
            cal = cls.from_points(px, am, (int(size[0]), int(size[1])))
        except (ValueError, TypeError) as exc:
            raise CalibrationError(f"{source}: {exc}") from None
        h = d.get("height_m")
        if h is not None:
            if not (_real(h) and 0.0 <= h <= MAX_PLANE_HEIGHT_M):
                raise CalibrationError(f"{source}: height_m: expected the height above the mats of the plane the "
                                       f"points were taken on, in [0, {MAX_PLANE_HEIGHT_M:g}] m (0: the mats), got "
                                       f"{_show(h)}")
            cal.height_m = float(h)
        cam_h = d.get("camera_height_m")
        if cam_h is not None:
            if not _real(cam_h):
                raise CalibrationError(f"{source}: camera_height_m: expected the lens height above the mats in "
                                       f"{_height_range()} m, got {_show(cam_h)}")
            try:
                cal.with_geometry(camera_height_m=cam_h)
            except CalibrationError as exc:
                raise CalibrationError(f"{source}: camera_height_m: {exc}") from None
        nadir = d.get("nadir_m")
        if nadir is not None:
            cal.nadir = cal._nadir_in_range(_xy(nadir, f"{source}: nadir_m"), f"{source}: nadir_m")
        elif d.get("nadir_px") is not None:  # the nadir as a pixel (e.g. the principal point)
            uv = _xy(d["nadir_px"], f"{source}: nadir_px", "[u, v] in sensor pixels")
            cal.nadir = cal._nadir_in_range(cal.point_to_arena(*uv), f"{source}: nadir_px {list(uv)}")
        return cal

    def _nadir_in_range(self, xy: tuple[float, float], what: str) -> tuple[float, float]:
        """``xy`` if it lies within :data:`arena.config.NADIR_MAX_ARENAS` arena sides of the
        arena (the bounding box of the calibration's arena points), else CalibrationError."""
        lo, hi = self.arena_m.min(0), self.arena_m.max(0)
        side = float(max(hi - lo))
        d = nadir_distance_m((xy[0] - lo[0], xy[1] - lo[1]), tuple(hi - lo))
        if not (math.isfinite(xy[0]) and math.isfinite(xy[1])) or d > NADIR_MAX_ARENAS * side:
            raise CalibrationError(
                f"{what}: the arena point under the lens ({xy[0]:.3f}, {xy[1]:.3f}) m is {d:.2f} m from the arena "
                f"[{lo[0]:g}, {hi[0]:g}] x [{lo[1]:g}, {hi[1]:g}] m; expected within {NADIR_MAX_ARENAS:g} arena "
                f"sides ({NADIR_MAX_ARENAS * side:.2f} m) of it (a wrong sign, unit or frame?)")
        return xy

    def with_geometry(self, camera_height_m: float | None = None, nadir_m=None) -> "Calibration":
        """Set the lens height (m) and the nadir ((x, y) m) where given (None keeps the current)."""
        if camera_height_m is not None:
            lo, hi = CAMERA_HEIGHT_RANGE_M
            if not _real(camera_height_m):
                raise CalibrationError(f"camera height must be a number of metres, got {_show(camera_height_m)}")
            h = float(camera_height_m)
            if not (lo <= h <= hi):
                raise CalibrationError(f"camera height {h:g} m is outside {_height_range()} m, the physical range "
                                       "of a ceiling lens's height above the mats (measured, or estimated from the "
                                       "lens: check the unit and the lens values)")
            if not h > self.height_m:
                raise CalibrationError(f"camera height {camera_height_m} m must be above the calibration plane "
                                       f"({self.height_m} m)")
            self.camera_height_m = h
        if nadir_m is not None:
            self.nadir = self._nadir_in_range(_xy(nadir_m, "nadir_m"), "nadir_m")
        return self

    def to_dict(self) -> dict:
        d = {"image_size": [int(self.image_size[0]), int(self.image_size[1])],
             "points": [{"pixel": [float(u), float(v)], "arena_m": [float(x), float(y)]}
                        for (u, v), (x, y) in zip(self.pixels, self.arena_m)]}
        if self.height_m:
            d["height_m"] = self.height_m
        if self.camera_height_m is not None:
            d["camera_height_m"] = self.camera_height_m
        if self.nadir is not None:
            d["nadir_m"] = [float(self.nadir[0]), float(self.nadir[1])]
        return d

    def nadir_m(self) -> tuple[float, float]:
        """Arena point under the lens, m: the calibration's ``nadir_m`` when known, else the
        image centre's arena point (exact for a camera looking straight down with its principal
        point at the image centre; the arena centre when the camera is centred over it)."""
        if self.nadir is not None:
            return self.nadir
        return self.point_to_arena(self.image_size[0] / 2.0, self.image_size[1] / 2.0)

    def estimate_pose(self, focal_px: float, principal_px: tuple[float, float] | None = None) -> CameraPose:
        """The camera's height and nadir from this homography and the lens's focal length.

        The inverse homography (arena -> px) of a pinhole camera is K [r1 r2 t] up to scale
        (K: focal length ``focal_px`` in px, square pixels, principal point ``principal_px``,
        default the image centre; lens distortion ignored); its rotation and translation give
        the lens's position above the calibration plane. For a camera looking (nearly) straight
        down the height is ``focal_px / px_per_m``, so its relative error is the focal length's.
        """
        f = float(focal_px)
        if not (math.isfinite(f) and f > 0):
            raise CalibrationError(f"focal length must be > 0 px, got {focal_px}")
        cx, cy = principal_px if principal_px is not None else (self.image_size[0] / 2.0, self.image_size[1] / 2.0)
        K = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
        M = np.linalg.solve(K, self._Hinv)
        n1, n2 = float(np.linalg.norm(M[:, 0])), float(np.linalg.norm(M[:, 1]))
        lam = 2.0 / (n1 + n2)
        if M[2, 2] * lam < 0:  # the mats are in front of the lens
            lam = -lam
        r1, r2, t = lam * M[:, 0], lam * M[:, 1], lam * M[:, 2]
        R = np.column_stack([r1, r2, np.cross(r1, r2)])
        U, _, Vt = np.linalg.svd(R)
        R = U @ Vt
        C = -R.T @ t        # lens in the arena frame (z normal to the mats; sign: handedness)
        tilt = math.degrees(math.acos(min(1.0, abs(float(R[2, 2])))))
        return CameraPose(camera_height_m=self.height_m + abs(float(C[2])), nadir_m=(float(C[0]), float(C[1])),
                          tilt_deg=tilt, consistency=min(n1, n2) / max(n1, n2))

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


def _xy(value, what: str, expected: str = "[x, y] in arena metres") -> tuple[float, float]:
    if isinstance(value, (str, bytes, dict)) or not all(_real(c) for c in (value if hasattr(value, "__iter__") else [None])):
        raise CalibrationError(f"{what}: expected {expected}, got {_show(value)}")
    try:
        x, y = (float(c) for c in value)
    except (TypeError, ValueError):
        raise CalibrationError(f"{what}: expected {expected}, got {_show(value)}") from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise CalibrationError(f"{what}: expected finite {expected}, got {_show(value)}")
    return x, y


def _real(v) -> bool:
    """A finite real number (not a bool, not a string)."""
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
        return False
    try:
        return math.isfinite(v)
    except OverflowError:   # a JSON integer beyond a float
        return False


def _show(v) -> str:
    """``repr`` of a JSON value, cut to 60 characters."""
    r = repr(v)
    return r if len(r) <= 60 else r[:57] + "..."


def _height_range() -> str:
    return f"[{CAMERA_HEIGHT_RANGE_M[0]:g}, {CAMERA_HEIGHT_RANGE_M[1]:g}]"


def check_extent(px: np.ndarray, am: np.ndarray, size: tuple[int, int], name,
                 hint: str = "check the point and the sensor size", slack_px: float = 0.5) -> None:
    """Refuse, with a :class:`CalibrationError`, a pixel point off the sensor (``size`` (w, h)
    px, by more than ``slack_px``: half a pixel, either pixel convention, for points typed or
    found in an image) and arena points spanning more than
    :data:`MAX_ARENA_SPAN_M` (a unit slip); ``name(i)`` names point ``i``, ``hint`` says what
    to do. Non-finite values are left to the fitter."""
    w, h = size
    for i, (u, v) in enumerate(px):
        if (math.isfinite(u) and math.isfinite(v)
                and not (-slack_px <= u <= w + slack_px and -slack_px <= v <= h + slack_px)):
            far = f" by more than {slack_px:g} px" if slack_px > 1 else ""
            raise CalibrationError(f"{name(i)}: pixel ({u:g}, {v:g}) is outside the {w}x{h} px sensor{far} "
                                   f"(u 0-{w}, v 0-{h}); {hint}")
    fin = am[np.isfinite(am).all(1)]
    if len(fin):
        span = fin.max(0) - fin.min(0)
        if float(span.max()) > MAX_ARENA_SPAN_M:
            raise CalibrationError(f"the arena points span {span[0]:g} x {span[1]:g} m: are these in cm? arena "
                                   f"coordinates are metres (a lab arena spans under {MAX_ARENA_SPAN_M:g} m)")


def _check_points(d: dict, source: str) -> None:
    """The ``points`` list of a calibration dict, every error naming its key (``points[2].pixel``)."""
    pts = d.get("points")
    if not isinstance(pts, list):
        raise CalibrationError(f"{source}: points: expected a list of at least 4 {{\"pixel\": [u, v], \"arena_m\": "
                               f"[x, y]}}, got {_show(pts) if 'points' in d else 'nothing (key missing)'}")
    for i, p in enumerate(pts):
        if not isinstance(p, dict):
            raise CalibrationError(f"{source}: points[{i}]: expected {{\"pixel\": [u, v], \"arena_m\": [x, y]}}, "
                                   f"got {_show(p)}")
        for key, what in (("pixel", "[u, v] in sensor pixels"), ("arena_m", "[x, y] in arena metres")):
            v = p.get(key)
            if not (isinstance(v, list) and len(v) == 2 and all(_real(c) for c in v)):
                got = _show(v) if key in p else "nothing (key missing)"
                raise CalibrationError(f"{source}: points[{i}].{key}: expected {what} (2 finite numbers), got {got}")


def lens_focal_px(focal_length_mm: float, pixel_pitch_um: float, image_size: tuple[int, int]) -> float:
    """The focal length in pixels (for :meth:`Calibration.estimate_pose`) of a lens of
    ``focal_length_mm`` on a sensor of ``pixel_pitch_um`` pixels and ``image_size`` (w, h) px.

    Raises :class:`CalibrationError` for values no real camera has: a pitch outside
    :data:`PIXEL_PITCH_RANGE_UM`, or a focal length so short that the pinhole field of view
    across the sensor's diagonal exceeds :data:`MAX_PINHOLE_FOV_DEG` (e.g. 0.3 mm on a
    640x480 sensor of 15 µm pixels: 174 deg), the physical minimum for the pinhole model.
    """
    f_mm, pitch = focal_length_mm, pixel_pitch_um
    if not (_real(f_mm) and f_mm > 0):
        raise CalibrationError(f"focal length must be a number of mm > 0, got {_show(f_mm)}")
    lo, hi = PIXEL_PITCH_RANGE_UM
    if not (_real(pitch) and lo <= pitch <= hi):
        raise CalibrationError(f"pixel pitch {_show(pitch)} µm is outside [{lo:g}, {hi:g}] µm, the pitch of real "
                               "sensors (e.g. 15 for a Prophesee Gen3 VGA, 4.86 for an IMX636)")
    f_px = 1000.0 * float(f_mm) / float(pitch)
    half_diag = 0.5 * math.hypot(float(image_size[0]), float(image_size[1]))
    fov = 2.0 * math.degrees(math.atan2(half_diag, f_px))
    if fov > MAX_PINHOLE_FOV_DEG:
        f_min = 1e-3 * pitch * half_diag / math.tan(math.radians(0.5 * MAX_PINHOLE_FOV_DEG))
        raise CalibrationError(
            f"focal length {f_mm:g} mm with {pitch:g} µm pixels gives a {fov:.0f} deg field of view across the "
            f"{int(image_size[0])}x{int(image_size[1])} px sensor: no lens the pinhole model stands for (at most "
            f"{MAX_PINHOLE_FOV_DEG:g} deg, i.e. >= {f_min:.2f} mm here); check the unit (mm) and the lens's data sheet")
    return f_px


#: Relative difference between the lens's height estimate and a measured height beyond which
#: they disagree: a lens's nominal focal length is good to ~5 %, the pinhole model without
#: distortion and the homography's scale at the centre to a few % more; 20 % is a wrong lens
#: value (focal length, pixel pitch, sensor binning) or a wrong measurement.
LENS_HEIGHT_TOLERANCE = 0.2


def lens_height_disagreement(estimated_m: float, measured_m: float,
                             tolerance: float = LENS_HEIGHT_TOLERANCE) -> str | None:
    """A warning when the lens's height estimate and the measured height differ by more than
    ``tolerance`` of the measured one (None when they agree); the measured height is the one used."""
    diff = abs(estimated_m - measured_m) / measured_m
    if not diff > tolerance:
        return None
    return (f"warning: the lens gives the camera {estimated_m:.2f} m above the mats but --camera-height-m is "
            f"{measured_m:.2f} m ({100 * diff:.0f} % apart); using the measured {measured_m:.2f} m. Check the "
            "focal length, pixel pitch and the measurement (lens to mats)")


def camera_calibration(cam, source: str = "lab config") -> Calibration:
    """The calibration of a lab config's camera (``arena.config.CameraConfig``): its inline
    points or the file it names, with the camera table's ``camera_height_m`` and ``nadir_m``
    (when given) over the calibration's."""
    where = f"{source} camera {cam.name}"
    if cam.calibration is not None:
        cal = Calibration.from_dict(cam.calibration, where)
    elif cam.calibration_file is not None:
        path = Path(cam.calibration_file)
        if not path.is_file():
            raise CalibrationError(f"{path}: no such calibration file ({where})")
        cal = Calibration.from_dict(_read_json(path), str(path))
    else:
        raise CalibrationError(f"{source}: camera {cam.name!r} has no calibration")
    try:
        return cal.with_geometry(getattr(cam, "camera_height_m", None), getattr(cam, "nadir_m", None))
    except CalibrationError as exc:
        raise CalibrationError(f"{where}: {exc}") from None


def load_calibration(path: str | Path, camera: str | None = None) -> Calibration:
    """Load a calibration JSON file, or a lab config TOML (its camera ``camera`` or the first,
    see :func:`camera_calibration`)."""
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"{path}: no such calibration file")
    if path.suffix.lower() == ".toml":
        from arena.config import ConfigError, load_lab_config

        try:
            cam = load_lab_config(path).camera(camera)
        except ConfigError as exc:
            raise CalibrationError(str(exc)) from None
        return camera_calibration(cam, str(path))
    return Calibration.from_dict(_read_json(path), str(path))


def mat_points(side_m: float) -> np.ndarray:
    """Arena coordinates (m) of the mat corners in the order :func:`find_mat_corners` returns
    them: bottom-left (origin), bottom-right, top-right, top-left of the image."""
    return np.array([[0.0, 0.0], [side_m, 0.0], [side_m, side_m], [0.0, side_m]])


def find_mat_corners(gray: np.ndarray) -> np.ndarray:
    """Corners of the mat (the largest bright quadrilateral) in a grayscale image, px.

    Works on a webcam frame (white mats on a darker floor) and on any image where the mat is
    brighter than its surround. The bright region gives a coarse quadrilateral; each of its
    edges is then located to sub-pixel precision on profiles across it (see
    :func:`refine_quad`) and the corners are the intersections of the fitted edge lines.
    Returns a (4, 2) array ordered bottom-left, bottom-right, top-right, top-left in the
    image. Raises :class:`CalibrationError` when no convincing quadrilateral is found.
    """
    if gray is None or gray.ndim != 2 or gray.size == 0:
        raise CalibrationError("expected a non-empty grayscale image")
    if float(gray.std()) < 2.0:
        raise CalibrationError("the image has no contrast: no mat found (give --points)")
    img = cv2.GaussianBlur(gray.astype(np.uint8), (5, 5), 0)
    _, mask = cv2.threshold(img, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    quad = _quad_from_mask(mask)
    return _order_corners(refine_quad(cv2.GaussianBlur(gray.astype(np.float32), (0, 0), 1.0), quad))


def _quad_from_mask(mask: np.ndarray) -> np.ndarray:
    """The coarse quadrilateral (4, 2) of the largest region of a binary mask (255 = mat),
    with the checks that it is one solid region of plausible size."""
    k = max(3, (min(mask.shape) // 60) | 1)
    mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_RECT, (k, k)))
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    if not contours:
        raise CalibrationError("no bright region found: is the mat in view? (or give --points)")
    c = max(contours, key=cv2.contourArea)
    area = cv2.contourArea(c)
    if area < 0.05 * mask.size:
        raise CalibrationError(f"the largest bright region covers only {100 * area / mask.size:.1f} % of the "
                               "image: no mat found (give --points)")
    if area > 0.97 * mask.size:
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
    return quad


def _order_corners(quad: np.ndarray) -> np.ndarray:
    """Order 4 corners bottom-left, bottom-right, top-right, top-left (v grows downwards)."""
    s = quad.sum(1)
    d = quad[:, 0] - quad[:, 1]
    tl, br = quad[np.argmin(s)], quad[np.argmax(s)]
    tr, bl = quad[np.argmax(d)], quad[np.argmin(d)]
    return np.array([bl, br, tr, tl])


def refine_quad(level: np.ndarray, quad: np.ndarray, blur_px: float = 1.0, seg_px: float = 8.0,
                iterations: int = 3) -> np.ndarray:
    """Sub-pixel corners of a quadrilateral region brighter than its surround in ``level``.

    ``level`` is a float image whose value inside the region is higher than outside (a
    grayscale frame, or the flicker amplitude of :func:`flicker_maps`), blurred by about
    ``blur_px`` (Gaussian sigma, px); the inside level may vary slowly (vignetting, lamp
    fall-off). ``quad`` (4, 2) px is a coarse outline, in order around the region. The middle
    80 % of each edge is cut into segments; each segment's mean profile across the edge is
    normalised by its own inside and outside levels (so the local brightness does not matter)
    and the edge's position is the integral of that normalised profile (for a step blurred by
    any symmetric kernel, the integral is the step's position: no threshold, no bias from the
    blur). A robust line (Huber, then points beyond 3 px dropped) is fitted to each edge's
    positions and adjacent lines are intersected. The first pass uses long profiles (the
    coarse outline may be a few px off), the next ones profiles just longer than the blur
    (less noise). The coarse corners are returned when an edge has too few usable segments.
    Returns (4, 2) px in the input order.
    """
    lv = np.ascontiguousarray(level, dtype=np.float32)
    h, w = lv.shape
    q = np.asarray(quad, dtype=np.float64).reshape(4, 2).copy()
    half0 = max(6.0, 0.025 * min(w, h), 3.0 * blur_px + 3.0)       # half-length of a profile, px
    seg = max(4.0, seg_px)                                           # segment length along the edge, px
    for it in range(iterations):
        half = half0 if it == 0 else max(6.0, 3.0 * blur_px + 3.0)
        offs = np.arange(-half, half + 1e-9, 0.5)
        inner, outer = offs < -half / 2, offs > half / 2
        centre = q.mean(0)
        lines = []
        for i in range(4):
            a, b = q[i], q[(i + 1) % 4]
            length = float(np.hypot(*(b - a)))
            if length < 8 * half0:
                return q
            d = (b - a) / length
            n = np.array([d[1], -d[0]])
            if np.dot((a + b) / 2 - centre, n) < 0:
                n = -n                           # n points out of the region
            tau = np.arange(0.1 * length, 0.9 * length, 0.5)
            base = a + tau[:, None] * d
            pts = base[:, None, :] + offs[None, :, None] * n
            prof = cv2.remap(lv, pts[..., 0].astype(np.float32), pts[..., 1].astype(np.float32),
                             cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
            k = (tau - tau[0]) // seg
            nseg = int(k.max()) + 1
            good = np.isfinite(prof).all(1)
            cnt = np.bincount(k[good].astype(np.int64), minlength=nseg)
            mean = np.zeros((nseg, len(offs)))
            np.add.at(mean, k[good].astype(np.int64), prof[good])
            use = cnt >= 0.8 * cnt.max()
            mean = mean[use] / cnt[use, None]
            tc = np.bincount(k.astype(np.int64), weights=tau, minlength=nseg)[use] / \
                np.bincount(k.astype(np.int64), minlength=nseg)[use]
            inside = mean[:, inner].mean(1)
            outside = mean[:, outer].mean(1)
            contrast = inside - outside
            ok = contrast > 0.25 * np.median(contrast)
            if ok.sum() < 5:
                return q
            u = (mean[ok] - outside[ok, None]) / contrast[ok, None]
            e = np.clip(u.sum(1) * 0.5 - half, -half, half)   # integral of the normalised step - half
            p = a + tc[ok, None] * d + e[:, None] * n
            lines.append(_fit_line(p))
        q = np.array([_intersect(lines[i - 1], lines[i]) for i in range(4)])
    return q


def _fit_line(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A robust line (point, unit direction) through points (n, 2)."""
    keep = np.ones(len(p), bool)
    for _ in range(2):
        vx, vy, x0, y0 = cv2.fitLine(p[keep].astype(np.float32), cv2.DIST_HUBER, 0, 0.01, 0.01).ravel()
        d, c = np.array([vx, vy], np.float64), np.array([x0, y0], np.float64)
        r = np.abs((p - c) @ np.array([-d[1], d[0]]))
        new = r < 3.0
        if new.sum() < 4 or (new == keep).all():
            break
        keep = new
    return c, d


def _intersect(l1, l2) -> np.ndarray:
    (c1, d1), (c2, d2) = l1, l2
    A = np.column_stack([d1, -d2])
    s = np.linalg.solve(A, c2 - c1)
    return c1 + s[0] * d1


# -- the mat seen by an event camera under flickering light ---------------------------------
#: Width of the time bins of the whole sensor's signed event rate, s (Nyquist 2 kHz).
FLICKER_BIN_S = 2.5e-4
#: Band searched for the lamp's flicker, Hz (mains lamps: 100 or 120 Hz; some drivers higher).
FLICKER_BAND_HZ = (40.0, 1000.0)


def signed_rate(t_us: np.ndarray, p: np.ndarray, t0_us: int, out: np.ndarray) -> None:
    """Add events to ``out``, the sensor's ON minus OFF count per :data:`FLICKER_BIN_S` bin
    from ``t0_us`` (events outside ``out``'s span are ignored)."""
    k = ((np.asarray(t_us, np.int64) - t0_us) * (1e-6 / FLICKER_BIN_S)).astype(np.int64)
    m = (k >= 0) & (k < len(out))
    out += np.bincount(k[m], weights=2.0 * (p[m] > 0) - 1.0, minlength=len(out))


def flicker_frequency(rate: np.ndarray) -> float:
    """The lamp's flicker frequency, Hz, from the sensor's signed event rate
    (:func:`signed_rate`): the strongest line of its spectrum in :data:`FLICKER_BAND_HZ`.

    A lamp flickering at f makes every lit pixel fire ON events while it brightens and OFF
    while it dims, so ON minus OFF over the sensor oscillates at f; sensor noise has no line.
    Raises :class:`CalibrationError` when the strongest line is not far above the spectrum's
    median (no flickering light seen).
    """
    rate = np.asarray(rate, np.float64)
    if len(rate) < 8:
        raise CalibrationError("the recording is too short to see the light flicker")
    nfft = 1 << int(math.ceil(math.log2(len(rate) * 16)))
    spec = np.abs(np.fft.rfft(rate - rate.mean(), nfft)) ** 2
    fr = np.fft.rfftfreq(nfft, FLICKER_BIN_S)
    band = (fr >= FLICKER_BAND_HZ[0]) & (fr <= FLICKER_BAND_HZ[1])
    med = float(np.median(spec[band]))
    i = int(np.argmax(np.where(band, spec, -1.0)))
    # noise: the periodogram is exponential, its max over the band rarely exceeds ~15x its median
    if not (spec[i] > 40.0 * max(med, 1e-12)):
        raise CalibrationError("no flickering light found in the events (no line in their rate between "
                               f"{FLICKER_BAND_HZ[0]:g} and {FLICKER_BAND_HZ[1]:g} Hz)")
    if 0 < i < len(spec) - 1:                    # parabolic peak interpolation on the log spectrum
        y0, y1, y2 = np.log(spec[i - 1:i + 2] + 1e-300)
        den = y0 - 2 * y1 + y2
        i = i + (0.5 * (y0 - y2) / den if den < 0 else 0.0)
    return float(i * fr[1])


def add_phasors(A: np.ndarray, N: np.ndarray, x, y, p, t_us, t0_us: int, freq_hz: float) -> None:
    """Add events to the per-pixel lock-in sums at ``freq_hz``: ``A`` (h, w) complex,
    sum of polarity * exp(-2 pi i f t); ``N`` (h, w), event count."""
    h, w = A.shape
    idx = np.asarray(y, np.int64) * w + np.asarray(x, np.int64)
    ph = (2.0 * np.pi * freq_hz * 1e-6) * (np.asarray(t_us, np.int64) - t0_us).astype(np.float64)
    s = 2.0 * (np.asarray(p) > 0) - 1.0
    A += (np.bincount(idx, weights=s * np.cos(ph), minlength=h * w)
          - 1j * np.bincount(idx, weights=s * np.sin(ph), minlength=h * w)).reshape(h, w)
    N += np.bincount(idx, minlength=h * w).reshape(h, w)


def flicker_maps(A: np.ndarray, N: np.ndarray, sigma_px: float = 3.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Flicker amplitude and its significance per pixel from the lock-in sums (:func:`add_phasors`).

    The sums are smoothed coherently (Gaussian, ``sigma_px``) and projected on the local phase
    of the flicker (from a 5x wider smoothing: the response lags more where the light is dim),
    which gives ``amp``: events per pixel locked to the flicker, linear in the events (noise
    averages to zero, not to a positive bias). ``z`` is the Rayleigh statistic |sum|^2 / var:
    about 1 (exponential) where events have no phase relation to the light (sensor noise,
    leak events, a dark floor), large where they follow it. ``edge``: per pixel, its events'
    projection on the local phase clipped to +-2 events, smoothed by 1 px (for the edges: the
    pixels' response is very uneven, threshold mismatch), see :func:`find_mat_corners_flicker`.
    """
    def blur(a, s):
        return cv2.GaussianBlur(a, (0, 0), s, borderType=cv2.BORDER_REFLECT)

    re, im = A.real.astype(np.float32), A.imag.astype(np.float32)
    S = blur(re, sigma_px) + 1j * blur(im, sigma_px)
    R = blur(re, 5 * sigma_px) + 1j * blur(im, 5 * sigma_px)
    amp = (S * np.conj(R) / np.maximum(np.abs(R), 1e-12)).real.astype(np.float32)
    # var of a Gaussian-weighted sum of Poisson counts: sum g^2 N; g^2 is a Gaussian of
    # sigma/sqrt(2) scaled by 1 / (4 pi sigma^2)
    var = blur(N.astype(np.float32), sigma_px / math.sqrt(2.0)) / (4.0 * math.pi * sigma_px ** 2)
    z = (np.abs(S) ** 2 / np.maximum(var, 1e-12)).astype(np.float32)
    z[var <= 1e-9] = 0.0
    # per pixel: events locked to the local phase, clipped to +-2 (a few pixels with a low
    # contrast threshold fire on every cycle and would dominate any local mean), lightly smoothed
    R /= np.maximum(np.abs(R), 1e-12)
    locked = np.clip((A * np.conj(R)).real, -2.0, 2.0).astype(np.float32)
    edge = cv2.GaussianBlur(locked, (0, 0), 1.0, borderType=cv2.BORDER_REFLECT)
    return amp, z, edge


def find_mat_corners_flicker(amp: np.ndarray, z: np.ndarray, edge: np.ndarray | None = None,
                             z_min: float = 9.0) -> np.ndarray:
    """Corners of the mat from the flicker maps of an event recording (:func:`flicker_maps`), px.

    The mat is the region whose events follow the light's flicker significantly (``z`` above
    ``z_min``) and strongly: amplitude above the Otsu threshold of log amplitude (the mat is
    many times brighter than the floor; vignetting only scales it, which the log turns into a
    shift smaller than the gap). Its outline is refined on the amplitude map by
    :func:`refine_quad`. Ordered as :func:`find_mat_corners`; the same errors.
    """
    amp = np.asarray(amp, np.float32)
    sig = z > z_min
    if sig.mean() < 0.01:
        raise CalibrationError("no bright region found: is the mat in view? (or give --points)")
    la = np.log(np.maximum(amp, 1e-3 * float(np.percentile(amp[sig], 90))))
    lo, hi = float(la.min()), float(la.max())
    u8 = np.round(255.0 * (la - lo) / max(hi - lo, 1e-9)).astype(np.uint8)
    thr, _ = cv2.threshold(u8, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    mask = np.where(sig & (u8 > thr), 255, 0).astype(np.uint8)
    k = max(3, (min(mask.shape) // 100) | 1)
    mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    quad = _quad_from_mask(mask)
    return _order_corners(refine_quad(amp if edge is None else edge, quad, blur_px=1.0, seg_px=48.0))

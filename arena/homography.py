"""Plane homographies between a camera's pixels and arena metres, and the calibration JSON.

The one fitter (:func:`fit_homography`), the one error type (:class:`CalibrationError`) and the
one reader of the calibration file (:func:`read_calibration_json`, :func:`calibration_points`)
every service uses: the tracker's :class:`tracker.calibration.Calibration`, the ground truth's
:class:`groundtruth.homography.Homography`, the viewer and the Foxglove views are built on them.

Frames: image ``u`` (column, right) and ``v`` (row, down) in px; arena ``x``/``y`` in metres
from one mat corner. The calibration JSON::

    {"image_size": [w, h],
     "height_m": 0.045,                # optional: plane height of "points" above the mats, m
     "camera_height_m": 2.45,          # optional: lens height above the mats, m
     "points": [{"pixel": [u, v], "arena_m": [x, y]}, ...]}    # >= 4 points

Besides those, the keys the project's tools write (:data:`CALIBRATION_KEYS`: ``nadir_m``,
``nadir_px``, ``camera``, ``floor_points``, a second list of points on the floor) are allowed;
:func:`check_calibration_keys` refuses any other (a typo such as ``camera_heigth_m`` would
otherwise fall back to a default without a word), as the lab config refuses unknown keys.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

__all__ = ["CalibrationError", "fit_homography", "apply_homography", "calibration_points",
           "read_calibration_json", "check_calibration_keys", "CALIBRATION_KEYS"]

#: Every top-level key of the calibration JSON, as read or written by the project's tools.
CALIBRATION_KEYS = ("image_size", "points", "height_m", "camera_height_m", "nadir_m", "nadir_px", "camera",
                    "floor_points")


class CalibrationError(ValueError):
    """A calibration file or point set that cannot give a homography; the message says what is wrong."""


def fit_homography(src, dst) -> np.ndarray:
    """The 3x3 homography mapping the points ``src`` (n, 2) onto ``dst`` (n, 2), scaled so that
    ``H[2, 2] == 1``: exact for 4 points, least squares over all points for more (OpenCV's
    ``findHomography`` with method 0: no outlier rejection, every point counts), finished in
    float64 (see :func:`_polish`).

    Raises :class:`CalibrationError` for point sets of different lengths, fewer than 4 points,
    non-finite values or degenerate points (all on one line, or repeated).
    """
    a = np.asarray(src, dtype=np.float64).reshape(-1, 2)
    b = np.asarray(dst, dtype=np.float64).reshape(-1, 2)
    if len(a) != len(b):
        raise CalibrationError(f"{len(a)} pixel points but {len(b)} arena points")
    if len(a) < 4:
        raise CalibrationError(f"a homography needs at least 4 points, got {len(a)}")
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        raise CalibrationError("calibration points must be finite numbers")
    for pts in (a, b):
        # degenerate if the points do not span a plane (all within a line, or repeated)
        sv = np.linalg.svd(pts - pts.mean(0), compute_uv=False)
        if sv[-1] < 1e-6 * max(sv[0], 1e-12):
            raise _degenerate()
    if not _same_orientation(a, b):
        raise CalibrationError("the calibration points cross: some pixel points are not in the same order "
                               "(clockwise or counter-clockwise) as their arena points, which no camera "
                               "gives; check each PIXEL:ARENA pair (e.g. two corners swapped)")
    H, _ = cv2.findHomography(a, b, 0)
    if H is None or not np.isfinite(H).all() or abs(np.linalg.det(H)) < 1e-18 or H[2, 2] == 0:
        raise _degenerate()
    try:
        H = _polish(H / H[2, 2], a, b)
    except np.linalg.LinAlgError:   # crossed or mirrored correspondences: no homography fits them
        raise _degenerate() from None
    if not np.isfinite(H).all() or abs(np.linalg.det(H)) < 1e-18:
        raise _degenerate()
    return H


def _same_orientation(a: np.ndarray, b: np.ndarray, most: int = 30) -> bool:
    """Whether every triangle of points turns the same way in ``a`` and in ``b`` (all kept, or
    all mirrored): a camera's homography of the floor does, since every floor point it sees lies
    on one side of its horizon. Triangles too flat to tell are skipped; at most ``most`` points."""
    from itertools import combinations

    a, b = a[:most], b[:most]
    da, db = a - a.mean(0), b - b.mean(0)
    ea = 1e-9 * float((da ** 2).sum(1).max())
    eb = 1e-9 * float((db ** 2).sum(1).max())
    signs = set()
    for i, j, k in combinations(range(len(a)), 3):
        sa = (a[j, 0] - a[i, 0]) * (a[k, 1] - a[i, 1]) - (a[j, 1] - a[i, 1]) * (a[k, 0] - a[i, 0])
        sb = (b[j, 0] - b[i, 0]) * (b[k, 1] - b[i, 1]) - (b[j, 1] - b[i, 1]) * (b[k, 0] - b[i, 0])
        if abs(sa) > ea and abs(sb) > eb:
            signs.add(bool(sa > 0) == bool(sb > 0))
    return len(signs) <= 1


def _normaliser(pts: np.ndarray) -> np.ndarray:
    """Similarity moving the points' centroid to 0 and their mean distance to sqrt(2)."""
    c = pts.mean(0)
    s = np.sqrt(2) / np.linalg.norm(pts - c, axis=1).mean()
    return np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1.0]])


def _polish(H: np.ndarray, a: np.ndarray, b: np.ndarray, iterations: int = 5) -> np.ndarray:
    """Finish OpenCV's fit in float64: Gauss-Newton steps on the objective ``findHomography``
    minimises (squared distances in ``b``'s frame), on normalised points, each kept only if it
    lowers that error. OpenCV stops at float32 tolerances (its 4-point fit of a mat is 1.4e-7 m off
    its own points); polished, that fit is exact to ~1e-15 and a least-squares fit moves by ~1e-8
    relative."""
    ts, td = _normaliser(a), _normaliser(b)
    an, bn = apply_homography(ts, a), apply_homography(td, b)
    hn = td @ H @ np.linalg.inv(ts)
    hn = hn / hn[2, 2]
    x, y = an[:, 0], an[:, 1]
    one, zero = np.ones_like(x), np.zeros_like(x)
    r = (apply_homography(hn, an) - bn).ravel()
    for _ in range(iterations):
        w = hn[2, 0] * x + hn[2, 1] * y + 1.0
        u = (hn[0, 0] * x + hn[0, 1] * y + hn[0, 2]) / w
        v = (hn[1, 0] * x + hn[1, 1] * y + hn[1, 2]) / w
        jac = np.empty((2 * len(x), 8))
        jac[0::2] = np.column_stack([x, y, one, zero, zero, zero, -u * x, -u * y]) / w[:, None]
        jac[1::2] = np.column_stack([zero, zero, zero, x, y, one, -v * x, -v * y]) / w[:, None]
        step = np.linalg.lstsq(jac, -r, rcond=None)[0]
        cand = hn + np.append(step, 0.0).reshape(3, 3)
        rc = (apply_homography(cand, an) - bn).ravel()
        if not rc @ rc < r @ r:
            break
        hn, r = cand, rc
    H = np.linalg.inv(td) @ hn @ ts
    return H / H[2, 2]


def _degenerate() -> CalibrationError:
    return CalibrationError("the calibration points are degenerate (collinear or repeated): "
                            "give 4 or more points spread over the arena, e.g. the mat corners")


def apply_homography(H: np.ndarray, pts) -> np.ndarray:
    """Map points through ``H``: ``(n, 2)`` or one ``(2,)`` point in, the same shape out (float64)."""
    p = np.asarray(pts, dtype=np.float64)
    flat = p.reshape(-1, 2)
    q = flat @ H[:, :2].T + H[:, 2]
    return (q[:, :2] / q[:, 2:3]).reshape(p.shape)


def calibration_points(cal, key: str = "points") -> tuple[np.ndarray, np.ndarray]:
    """``(pixels (n, 2) px, arena (n, 2) m)`` of a calibration dict's point list ``key``
    (``"points"``, or e.g. ``"floor_points"``). Raises :class:`CalibrationError` naming what is
    missing or malformed; the number of points is checked by :func:`fit_homography`."""
    if not isinstance(cal, dict):
        raise CalibrationError("calibration must be a JSON object with image_size and points")
    pts = cal.get(key)
    if not isinstance(pts, list):
        raise CalibrationError(f"calibration has no {key!r} list of {{'pixel', 'arena_m'}} points")
    try:
        px = [[float(v) for v in p["pixel"]] for p in pts]
        am = [[float(v) for v in p["arena_m"]] for p in pts]
    except (KeyError, TypeError, ValueError) as exc:
        raise CalibrationError(f"each of {key!r} needs 'pixel': [u, v] and 'arena_m': [x, y] ({exc})") from None
    if any(len(p) != 2 for p in px + am):
        raise CalibrationError(f"each 'pixel' and 'arena_m' in {key!r} must have 2 numbers")
    return np.array(px, dtype=np.float64).reshape(-1, 2), np.array(am, dtype=np.float64).reshape(-1, 2)


def read_calibration_json(path: str | Path):
    """The parsed calibration JSON file at ``path`` (not yet checked). Raises
    :class:`CalibrationError` when it is missing or not readable JSON."""
    path = Path(path)
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise CalibrationError(f"{path}: calibration file not found") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CalibrationError(f"{path}: cannot read the calibration, not a readable JSON file ({exc})") from None


def check_calibration_keys(cal: dict, source: str = "calibration") -> None:
    """Refuse a key of the calibration dict ``cal`` not in :data:`CALIBRATION_KEYS` with a
    :class:`CalibrationError` naming it (and the known key it is closest to, if any)."""
    import difflib

    extra = sorted(str(k) for k in cal if k not in CALIBRATION_KEYS)
    if not extra:
        return
    close = difflib.get_close_matches(extra[0], CALIBRATION_KEYS, n=1, cutoff=0.7)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    raise CalibrationError(f"{source}: unknown key(s) {', '.join(repr(k)[:60] for k in extra[:5])}{hint}; "
                           f"known keys: {', '.join(CALIBRATION_KEYS)}")

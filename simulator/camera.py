"""The ceiling camera geometry and what it sees: the arena as a reflectance image, robot shells.

Frames: arena (x, y in m, origin at one mat corner, yaw CCW from +x) and sensor (u column
right, v row down, px; pixel ``(u, v)`` has its centre at ``(u, v)``). ``H`` maps arena
metres to sensor pixels in homogeneous coordinates: ``[u, v, 1]^T ~ H [x, y, 1]^T``.

The default homography is deliberately not a perfect square: the arena is rotated by a
few degrees and seen with a slight keystone, like a camera bolted to a ceiling by hand.

Reflectance model (0..1, linear light): foam mats 0.85 with ~2 % low-frequency texture and
faint darker seams between the 61 cm mats; the floor around the arena 0.3; shells
``0.04 + 0.75 * luminance(colour)`` (plastic is darker than foam: a yellow shell is only a
little darker than the mat, a black one ~20x darker); treads 0.06 (black rubber strips
along both sides); an optional ArUco marker (DICT_4X4_50, 6 x 6 cells including the
border) printed on the shell top.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from simulator.world import RobotSpec

MAT_REFLECTANCE = 0.85
FLOOR_REFLECTANCE = 0.30
TREAD_REFLECTANCE = 0.06
TREAD_WIDTH_M = 0.008
MARKER_SIDE_M = 0.075   # as simulator.webcam (marker_size_m): the same physical print
MAT_SIZE_M = 0.61
#: Illumination per lighting level (relative irradiance; "full" = 1).
ILLUMINATION = {"full": 1.0, "dimmed": 0.25, "dark": 0.06}


def shell_reflectance(color_rgb: tuple[int, int, int]) -> float:
    """Reflectance (0..1) a monochrome sensor sees for an sRGB shell colour (0-255 per channel)."""
    c = np.asarray(color_rgb, dtype=float) / 255.0
    if c.shape != (3,) or np.any(c < 0) or np.any(c > 1):
        raise ValueError(f"color_rgb must be three values in 0..255, got {color_rgb!r}")
    lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    lum = 0.2126 * lin[0] + 0.7152 * lin[1] + 0.0722 * lin[2]
    return float(0.04 + 0.75 * lum)


def marker_pattern(marker_id: int | None) -> np.ndarray:
    """6 x 6 reflectance grid of an ArUco DICT_4X4_50 marker (row 0 = marker top, towards
    the robot's front), black border included; all ones (no print) when ``marker_id`` is None."""
    if marker_id is None:
        return np.ones((6, 6), dtype=np.float32)
    if not 0 <= int(marker_id) < 50:
        raise ValueError(f"marker_id must be in 0..49 (DICT_4X4_50), got {marker_id}")
    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    img = cv2.aruco.generateImageMarker(d, int(marker_id), 6)
    return np.where(img > 127, 0.80, 0.05).astype(np.float32)


def default_homography(width: int, height: int, arena_m: float = 1.83,
                       fill: float = 0.90, rotation_deg: float = 2.5,
                       keystone: float = 0.03) -> np.ndarray:
    """Arena (m) -> sensor (px) homography for a ceiling camera centred over the arena.

    The arena fills ``fill`` of the shorter sensor side, is rotated by ``rotation_deg``
    and its far edge (arena y = arena_m) appears ``keystone`` narrower than the near edge.
    Arena +y points up in the image (towards smaller v), so the image is not mirrored.
    """
    s = fill * min(width, height) / 2.0
    k = keystone / 2.0
    # corners in normalised image coords (x right, y up), arena order (0,0),(L,0),(L,L),(0,L)
    quad = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0 - k, 1.0], [-1.0 + k, 1.0]])
    a = math.radians(rotation_deg)
    rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    quad = quad @ rot.T * s
    dst = np.column_stack([width / 2.0 + quad[:, 0], height / 2.0 - quad[:, 1]]).astype(np.float32)
    src = np.array([[0, 0], [arena_m, 0], [arena_m, arena_m], [0, arena_m]], dtype=np.float32)
    return cv2.getPerspectiveTransform(src, dst)


def apply_homography(h: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Map points (n, 2) through homography ``h`` (3 x 3); returns (n, 2) float64."""
    pts = np.asarray(pts, dtype=float).reshape(-1, 2)
    q = np.column_stack([pts, np.ones(len(pts))]) @ np.asarray(h, dtype=float).T
    return q[:, :2] / q[:, 2:3]


@dataclass
class CeilingCamera:
    """Geometry of the ceiling event camera and the static arena it looks at.

    Attributes:
        width, height: sensor size, px.
        arena_m: arena side, m.
        H: arena m -> sensor px homography (3 x 3). Built by :func:`default_homography`
           when not given.
        seed: seed of the mat texture.
        camera_height_m: height of the lens above the mats (camera over the arena centre), m.
        shell_height_m: height of the shell tops, m. The sensor sees the tops, which appear
            displaced outwards from the floor homography by the parallax factor
            ``camera_height_m / (camera_height_m - shell_height_m)`` (~1.8 %, up to ~2 cm at
            the arena corners), as a real ceiling camera calibrated on the mats does.
    """

    width: int = 640
    height: int = 480
    arena_m: float = 1.83
    H: np.ndarray | None = None
    seed: int = 0
    camera_height_m: float = 2.5
    shell_height_m: float = 0.045

    def __post_init__(self) -> None:
        if self.width < 16 or self.height < 16 or self.width > 4096 or self.height > 4096:
            raise ValueError(f"sensor size must be 16..4096 px per side, got {self.width}x{self.height}")
        if self.H is None:
            self.H = default_homography(self.width, self.height, self.arena_m)
        self.H = np.asarray(self.H, dtype=float)
        self.H_inv = np.linalg.inv(self.H)
        u, v = np.meshgrid(np.arange(self.width, dtype=float), np.arange(self.height, dtype=float))
        q = np.stack([u, v, np.ones_like(u)], axis=-1) @ self.H_inv.T
        #: arena coordinates (m) of each pixel centre, (height, width) float32
        self.ax = (q[..., 0] / q[..., 2]).astype(np.float32)
        self.ay = (q[..., 1] / q[..., 2]).astype(np.float32)
        if not 0 <= self.shell_height_m < self.camera_height_m:
            raise ValueError("shell_height_m must be >= 0 and below camera_height_m")
        #: floor distance from the nadir shrinks by this factor at shell-top height
        self.top_scale = (self.camera_height_m - self.shell_height_m) / self.camera_height_m
        self.nadir = np.array([self.arena_m / 2, self.arena_m / 2])
        #: arena coordinates (m) where each pixel's ray meets the shell-top plane
        self.ax_top = (self.nadir[0] + (self.ax - self.nadir[0]) * self.top_scale).astype(np.float32)
        self.ay_top = (self.nadir[1] + (self.ay - self.nadir[1]) * self.top_scale).astype(np.float32)
        c = apply_homography(self.H, [[self.arena_m / 2, self.arena_m / 2]])[0]
        d = apply_homography(self.H, [[self.arena_m / 2 + 0.01, self.arena_m / 2]])[0]
        #: mean pixel pitch on the arena, m/px
        self.pixel_m = 0.01 / float(np.hypot(*(d - c)))
        self.background = self._render_background()

    def to_pixels(self, xy_m: np.ndarray) -> np.ndarray:
        """Arena points (n, 2) in m on the mats -> sensor pixels (n, 2) (u, v)."""
        return apply_homography(self.H, xy_m)

    def top_to_pixels(self, xy_m: np.ndarray) -> np.ndarray:
        """Points (n, 2) in m at shell-top height (e.g. robot centres) -> sensor pixels (n, 2)."""
        xy = np.asarray(xy_m, dtype=float).reshape(-1, 2)
        return apply_homography(self.H, self.nadir + (xy - self.nadir) / self.top_scale)

    def to_arena(self, uv_px: np.ndarray) -> np.ndarray:
        """Sensor pixels (n, 2) (u, v) -> arena points (n, 2) in m."""
        return apply_homography(self.H_inv, uv_px)

    def calibration(self) -> dict:
        """Calibration in the project's JSON format: the four mat corners and the inner
        mat-seam crossings, ``{"image_size": [w, h], "points": [{"pixel": [u, v], "arena_m": [x, y]}]}``."""
        L = self.arena_m
        pts = [(0, 0), (L, 0), (L, L), (0, L)]
        pts += [(a, b) for a in (MAT_SIZE_M, 2 * MAT_SIZE_M) for b in (MAT_SIZE_M, 2 * MAT_SIZE_M)]
        pts.append((L / 2, L / 2))
        px = self.to_pixels(np.array(pts, dtype=float))
        return {"image_size": [self.width, self.height],
                "points": [{"pixel": [round(float(u), 3), round(float(v), 3)],
                            "arena_m": [round(float(x), 4), round(float(y), 4)]}
                           for (x, y), (u, v) in zip(pts, px)]}

    def _render_background(self) -> np.ndarray:
        """Static reflectance image (height, width) float32: mats, seams, texture, floor."""
        rng = np.random.default_rng(self.seed + 7919)
        coarse = rng.normal(0.0, 1.0, (self.height // 8 + 2, self.width // 8 + 2)).astype(np.float32)
        tex = cv2.resize(coarse, (self.width, self.height), interpolation=cv2.INTER_CUBIC)
        tex = tex / max(float(tex.std()), 1e-6)
        ax, ay, L = self.ax, self.ay, self.arena_m
        inside = (ax >= 0) & (ax <= L) & (ay >= 0) & (ay <= L)
        refl = np.where(inside, MAT_REFLECTANCE * (1.0 + 0.02 * tex),
                        FLOOR_REFLECTANCE * (1.0 + 0.05 * tex))
        # faint seams between mats: 2 mm wide, 10 % darker, area-weighted by pixel size
        seam_w = 0.002
        weight = min(1.0, seam_w / self.pixel_m)
        for k in range(1, int(round(L / MAT_SIZE_M))):
            s = k * MAT_SIZE_M
            near = inside & ((np.abs(ax - s) < self.pixel_m / 2) | (np.abs(ay - s) < self.pixel_m / 2))
            refl = np.where(near, refl * (1.0 - 0.10 * weight), refl)
        return refl.astype(np.float32)


def robot_appearance(robots: list[RobotSpec]) -> tuple[np.ndarray, np.ndarray]:
    """Per-robot rendering parameters for the sensor kernel.

    Returns ``(params, markers)``: ``params`` (n, 6) float64 = half length m, half width m,
    shell reflectance, tread reflectance, tread width m, marker half side m (0 = none);
    ``markers`` (n, 6, 6) float32 marker reflectance grids.
    """
    n = len(robots)
    params = np.zeros((n, 6))
    markers = np.ones((n, 6, 6), dtype=np.float32)
    for i, r in enumerate(robots):
        params[i] = (r.length_m / 2, r.width_m / 2, shell_reflectance(r.color_rgb),
                     TREAD_REFLECTANCE, TREAD_WIDTH_M,
                     MARKER_SIDE_M / 2 if r.marker_id is not None else 0.0)
        markers[i] = marker_pattern(r.marker_id)
    return params, markers

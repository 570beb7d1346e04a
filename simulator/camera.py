"""The ceiling camera geometry and what it sees: the arena as a reflectance image, robot bodies.

Frames: arena (x, y in m, origin at one mat corner, z up from the mats, yaw CCW from +x) and
sensor (u column right, v row down, px; pixel ``(u, v)`` has its centre at ``(u, v)``). ``H``
maps arena metres on the mats (z = 0) to sensor pixels in homogeneous coordinates:
``[u, v, 1]^T ~ H [x, y, 1]^T``; ``P`` (3 x 4) maps any arena point (x, y, z).

The camera is a pinhole ``camera_height_m`` above its nadir, which is ``nadir_offset_m`` away
from the arena centre (ceiling mounts are rarely centred), aimed at the arena centre (the tilt
gives a slight keystone) and rolled by a few degrees, like a camera bolted to a ceiling by hand.
A point at height z is seen where the ray from the lens through it meets the mats: its
distance from the nadir grows by ``camera_height_m / (camera_height_m - z)`` (parallax).

Reflectance model (0..1, linear light): white foam mats 0.80 with ~2 % low-frequency texture
and faint darker seams between the 61 cm mats; the floor around the arena 0.3; shells
``0.04 + 0.90 * luminance(colour)`` (black plastic ~0.05, near-white ~0.7, a little darker
than the foam); treads 0.06 (black silicone), blade 0.35 (brushed steel seen diffusely),
front sensor window 0.05, a darker rim where the shell top rounds off; vertical walls get
``WALL_LIGHT`` of the overhead light a horizontal surface gets; an optional ArUco marker
(DICT_4X4_50, 6 x 6 cells including the border) printed on the shell top. Robots are a
stack of boxes (:func:`robot_body`: shell 4 cm, treads 3 cm, blade 1 cm) ray-traced per
pixel by :mod:`simulator.dvs`, with a soft contact shadow on the mat around them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from simulator.world import RobotSpec

MAT_REFLECTANCE = 0.80
FLOOR_REFLECTANCE = 0.30
TREAD_REFLECTANCE = 0.06
BLADE_REFLECTANCE = 0.35
WINDOW_REFLECTANCE = 0.05
#: the rounded rim of the shell top faces partly away from the ceiling light: this fraction of the shell's
RIM_FACTOR = 0.55
#: irradiance of a vertical wall relative to a horizontal surface under overhead (diffuse) lighting
WALL_LIGHT = 0.5
TREAD_WIDTH_M = 0.008       # flat body: tread strips seen on the shell-top plane
MARKER_SIDE_M = 0.075   # as simulator.webcam (marker_size_m): the same physical print
MAT_SIZE_M = 0.61
#: default horizontal offset (dx, dy) of the camera's nadir from the arena centre, m
NADIR_OFFSET_M = (0.12, -0.07)
#: body models of :func:`robot_body`
BODIES = ("3d", "flat")
#: contact shadow: darkening of the mat at the robot's edge and its reach, m
SHADOW_DEPTH = 0.40
SHADOW_WIDTH_M = 0.010
#: Illumination per lighting level (relative irradiance; "full" = 1).
ILLUMINATION = {"full": 1.0, "dimmed": 0.25, "dark": 0.06}


def shell_reflectance(color_rgb: tuple[int, int, int]) -> float:
    """Reflectance (0..1) a monochrome sensor sees for an sRGB shell colour (0-255 per channel)."""
    c = np.asarray(color_rgb, dtype=float) / 255.0
    if c.shape != (3,) or np.any(c < 0) or np.any(c > 1):
        raise ValueError(f"color_rgb must be three values in 0..255, got {color_rgb!r}")
    lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    lum = 0.2126 * lin[0] + 0.7152 * lin[1] + 0.0722 * lin[2]
    return float(0.04 + 0.90 * lum)


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
                       camera_height_m: float = 2.5,
                       nadir_offset_m: tuple[float, float] = NADIR_OFFSET_M) -> np.ndarray:
    """Arena (m) -> sensor (px) floor homography of a pinhole ceiling camera.

    :func:`pinhole_camera` 's ``P`` restricted to the floor (z = 0); see there.
    """
    P = pinhole_camera(width, height, arena_m, fill, rotation_deg, camera_height_m, nadir_offset_m)
    return P[:, [0, 1, 3]] / P[2, 3]


def pinhole_camera(width: int, height: int, arena_m: float = 1.83, fill: float = 0.90,
                   rotation_deg: float = 2.5, camera_height_m: float = 2.5,
                   nadir_offset_m: tuple[float, float] = NADIR_OFFSET_M) -> np.ndarray:
    """3 x 4 projection matrix (arena x, y, z m -> sensor px) of a ceiling camera.

    The lens is ``camera_height_m`` above the point ``nadir_offset_m`` (dx, dy) away from the
    arena centre, tilted so that its optical axis meets the arena centre (a camera bolted off
    centre and aimed at the mats: the tilt gives the keystone), rolled by ``rotation_deg``
    about its axis; square pixels, principal point at the sensor centre, focal length such
    that the arena side spans ``fill`` of the shorter sensor side. Arena +y points up in the
    image (towards smaller v), so the image is not mirrored.
    """
    L = arena_m
    C = np.array([L / 2 + nadir_offset_m[0], L / 2 + nadir_offset_m[1], camera_height_m], float)
    T = np.array([L / 2, L / 2, 0.0])
    zc = (T - C) / np.linalg.norm(T - C)
    ex = np.array([1.0, 0.0, 0.0])
    xc = ex - ex.dot(zc) * zc
    xc /= np.linalg.norm(xc)
    yc = np.cross(zc, xc)
    R = np.stack([xc, yc, zc])                  # world -> camera rotation (rows: camera axes)
    f = fill * min(width, height) / 2.0 / (L / 2.0) * float(np.linalg.norm(T - C))
    a = math.radians(rotation_deg)
    roll = np.array([[math.cos(a), math.sin(a), 0.0], [-math.sin(a), math.cos(a), 0.0], [0, 0, 1]])
    K = np.array([[1.0, 0.0, width / 2.0], [0.0, 1.0, height / 2.0], [0.0, 0.0, 1.0]]) @ roll \
        @ np.diag([f, f, 1.0])
    return K @ np.column_stack([R, -R @ C])


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
        H: arena m -> sensor px floor homography (3 x 3). Built by :func:`default_homography`
           from the pinhole model (height, nadir offset) when not given.
        seed: seed of the mat texture.
        camera_height_m: height of the lens above the mats, m.
        nadir_offset_m: (dx, dy) of the point under the lens from the arena centre, m.
        shell_height_m: height of the shell tops, m (the ``flat`` body is drawn at it; the
            3-D body's shell has this height too).
        body: robot body model, ``"3d"`` (stacked boxes: blade, treads, shell, ray-traced:
            parallax and self-occlusion, walls facing the lens visible) or ``"flat"`` (the
            shell top as one plate at ``shell_height_m`` with tread strips, no walls).
        shadow: draw the soft contact shadow on the mat around each robot.
        rotation_deg: roll of the camera about its axis (the arena appears rotated), deg.
    """

    width: int = 640
    height: int = 480
    arena_m: float = 1.83
    H: np.ndarray | None = None
    seed: int = 0
    camera_height_m: float = 2.5
    nadir_offset_m: tuple[float, float] = NADIR_OFFSET_M
    shell_height_m: float = 0.04
    body: str = "3d"
    shadow: bool = True
    rotation_deg: float = 2.5

    def __post_init__(self) -> None:
        if self.width < 16 or self.height < 16 or self.width > 4096 or self.height > 4096:
            raise ValueError(f"sensor size must be 16..4096 px per side, got {self.width}x{self.height}")
        if not 0 <= self.shell_height_m < 0.5 * self.camera_height_m:
            raise ValueError("shell_height_m must be >= 0 and well below camera_height_m")
        if self.body not in BODIES:
            raise ValueError(f"body must be one of {BODIES}, got {self.body!r}")
        off = tuple(float(o) for o in self.nadir_offset_m)
        if len(off) != 2 or not all(math.isfinite(o) for o in off):
            raise ValueError(f"nadir_offset_m must be two finite numbers (dx, dy) m, got {self.nadir_offset_m!r}")
        self.nadir_offset_m = off
        if self.H is None:
            self.H = default_homography(self.width, self.height, self.arena_m,
                                        rotation_deg=self.rotation_deg,
                                        camera_height_m=self.camera_height_m, nadir_offset_m=off)
        self.H = np.asarray(self.H, dtype=float)
        self.H_inv = np.linalg.inv(self.H)
        #: arena point under the lens, m
        self.nadir = np.array([self.arena_m / 2 + off[0], self.arena_m / 2 + off[1]])
        h = self.camera_height_m
        #: 3 x 4 projection (arena x, y, z m -> px): the floor homography plus the lens centre
        #: (its null vector is (nadir, camera_height_m, 1))
        self.P = np.column_stack([self.H[:, 0], self.H[:, 1],
                                  -(self.H @ [self.nadir[0], self.nadir[1], 1.0]) / h, self.H[:, 2]])
        u, v = np.meshgrid(np.arange(self.width, dtype=float), np.arange(self.height, dtype=float))
        q = np.stack([u, v, np.ones_like(u)], axis=-1) @ self.H_inv.T
        #: arena coordinates (m) where each pixel centre's ray meets the mats, (height, width) float32
        self.ax = (q[..., 0] / q[..., 2]).astype(np.float32)
        self.ay = (q[..., 1] / q[..., 2]).astype(np.float32)
        #: floor distance from the nadir shrinks by this factor at shell-top height
        self.top_scale = (h - self.shell_height_m) / h
        c = apply_homography(self.H, [[self.arena_m / 2, self.arena_m / 2]])[0]
        d = apply_homography(self.H, [[self.arena_m / 2 + 0.01, self.arena_m / 2]])[0]
        #: mean pixel pitch on the arena, m/px
        self.pixel_m = 0.01 / float(np.hypot(*(d - c)))
        self.background = self._render_background()

    def to_pixels(self, xy_m: np.ndarray) -> np.ndarray:
        """Arena points (n, 2) in m on the mats -> sensor pixels (n, 2) (u, v)."""
        return apply_homography(self.H, xy_m)

    def project(self, xyz_m: np.ndarray) -> np.ndarray:
        """Arena points (n, 3) (x, y, z above the mats) in m -> sensor pixels (n, 2), by ``P``."""
        xyz = np.asarray(xyz_m, dtype=float).reshape(-1, 3)
        q = np.column_stack([xyz, np.ones(len(xyz))]) @ self.P.T
        return q[:, :2] / q[:, 2:3]

    def top_to_pixels(self, xy_m: np.ndarray, height_m: float | None = None) -> np.ndarray:
        """Points (n, 2) in m at ``height_m`` (default: shell-top height) -> sensor pixels (n, 2)."""
        xy = np.asarray(xy_m, dtype=float).reshape(-1, 2)
        z = self.shell_height_m if height_m is None else float(height_m)
        return self.project(np.column_stack([xy, np.full(len(xy), z)]))

    def to_arena(self, uv_px: np.ndarray) -> np.ndarray:
        """Sensor pixels (n, 2) (u, v) -> arena points (n, 2) in m on the mats."""
        return apply_homography(self.H_inv, uv_px)

    def relative_irradiance(self, vignetting: float, lamp_falloff: float) -> np.ndarray:
        """Per-pixel light gain (height, width) float32, 1 on the optical axis at the arena centre:
        the lens's relative illumination ``cos(theta) ** vignetting`` (theta: the pixel ray's
        angle to the optical axis; 4 = the ideal thin lens' cos^4 law) times the lamps' fall-off
        on the mats ``1 - lamp_falloff * (r / r_corner) ** 2`` (r from the arena centre)."""
        C = np.array([self.nadir[0], self.nadir[1], self.camera_height_m])
        g0 = self.to_arena([[self.width / 2.0, self.height / 2.0]])[0]
        axis = np.array([g0[0], g0[1], 0.0]) - C
        axis /= np.linalg.norm(axis)
        rx, ry, rz = self.ax - C[0], self.ay - C[1], -C[2]
        cos_t = (rx * axis[0] + ry * axis[1] + rz * axis[2]) / np.sqrt(rx * rx + ry * ry + rz * rz)
        gain = np.clip(cos_t, 1e-3, 1.0) ** float(vignetting)
        L = self.arena_m
        r2 = ((self.ax - L / 2) ** 2 + (self.ay - L / 2) ** 2) / (L * L / 2)
        gain = gain * np.clip(1.0 - float(lamp_falloff) * r2, 0.2, 1.0)
        return gain.astype(np.float32)

    def calibration(self) -> dict:
        """Calibration in the project's JSON format: the four mat corners and the inner
        mat-seam crossings, ``{"image_size": [w, h], "points": [{"pixel": [u, v], "arena_m": [x, y]}]}``,
        plus the lens: ``camera_height_m`` (above the mats), ``nadir_m`` (arena point under
        the lens, m) and ``nadir_px`` (its pixel)."""
        L = self.arena_m
        pts = [(0, 0), (L, 0), (L, L), (0, L)]
        pts += [(a, b) for a in (MAT_SIZE_M, 2 * MAT_SIZE_M) for b in (MAT_SIZE_M, 2 * MAT_SIZE_M)]
        pts.append((L / 2, L / 2))
        px = self.to_pixels(np.array(pts, dtype=float))
        nadir_px = self.to_pixels(self.nadir[None])[0]
        return {"image_size": [self.width, self.height],
                "points": [{"pixel": [round(float(u), 3), round(float(v), 3)],
                            "arena_m": [round(float(x), 4), round(float(y), 4)]}
                           for (x, y), (u, v) in zip(pts, px)],
                "camera_height_m": round(float(self.camera_height_m), 4),
                "nadir_m": [round(float(self.nadir[0]), 4), round(float(self.nadir[1]), 4)],
                "nadir_px": [round(float(nadir_px[0]), 3), round(float(nadir_px[1]), 3)]}

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


#: columns of a body box (robot frame: x forward, y left, m): x0, x1, y0, y1, top height,
#: top reflectance, wall reflectance, front-wall reflectance
BOX_COLS = 8
#: columns of the per-robot parameters: half length, half width (footprint), top height
#: (highest part), shell box index, window length, rim width, marker half side (0: none),
#: shadow depth, shadow reach m, rim reflectance, window reflectance, number of boxes
ROBOT_COLS = 12
MAX_BOXES = 4


def robot_body(r: RobotSpec, body: str = "3d", shell_height_m: float = 0.04) -> np.ndarray:
    """The boxes (k, :data:`BOX_COLS`) of one robot's body in its own frame, highest first.

    ``"3d"`` (Zumo 32U4 class; Pololu: ~10 x 10 cm, under 4 cm tall without the blade's mount):
    the shell (electronics and battery cover) between the treads, ``shell_height_m`` high,
    from 4.5 cm behind the centre to 4 cm ahead; two treads 1.3 cm wide, 3 cm high, along
    the sides; the blade across the front, 1 cm high, 1 cm deep. Neighbouring boxes overlap
    by 2 mm under the higher one so no mat shows through a seam. ``"flat"``: the old plate
    model, shell and tread strips at ``shell_height_m``, no blade (walls are not drawn).
    """
    hl, hw = r.length_m / 2, r.width_m / 2
    shell = shell_reflectance(r.color_rgb)
    wall = WALL_LIGHT
    if body == "flat":
        tw = TREAD_WIDTH_M
        return np.array([
            [-hl, hl, -hw + tw, hw - tw, shell_height_m, shell, shell * wall, shell * wall],
            [-hl, hl, hw - tw - 0.002, hw, shell_height_m, TREAD_REFLECTANCE, 0, 0],
            [-hl, hl, -hw, -hw + tw + 0.002, shell_height_m, TREAD_REFLECTANCE, 0, 0]])
    if body != "3d":
        raise ValueError(f"body must be one of {BODIES}, got {body!r}")
    tw = 0.13 * r.width_m
    blade = 0.10 * r.length_m
    front = hl - blade
    t_side = TREAD_REFLECTANCE
    return np.array([
        [-0.9 * hl, front, -hw + tw, hw - tw, shell_height_m, shell, shell * wall,
         WINDOW_REFLECTANCE * wall],
        [-0.96 * hl, front + 0.004, hw - tw - 0.002, hw, 0.75 * shell_height_m, t_side,
         t_side * wall, t_side * wall],
        [-0.96 * hl, front + 0.004, -hw, -hw + tw + 0.002, 0.75 * shell_height_m, t_side,
         t_side * wall, t_side * wall],
        [front - 0.002, hl, -hw, hw, 0.25 * shell_height_m, BLADE_REFLECTANCE,
         BLADE_REFLECTANCE * wall, BLADE_REFLECTANCE * wall]])


def robot_appearance(robots: list[RobotSpec], body: str = "3d", shadow: bool = True,
                     shell_height_m: float = 0.04) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-robot rendering parameters for the sensor kernel.

    Returns ``(params, boxes, markers)``: ``params`` (n, :data:`ROBOT_COLS`) float64,
    ``boxes`` (n, :data:`MAX_BOXES`, :data:`BOX_COLS`) (see :func:`robot_body`),
    ``markers`` (n, 6, 6) float32 marker reflectance grids.
    """
    n = len(robots)
    params = np.zeros((max(n, 1), ROBOT_COLS))
    boxes = np.zeros((max(n, 1), MAX_BOXES, BOX_COLS))
    markers = np.ones((max(n, 1), 6, 6), dtype=np.float32)
    for i, r in enumerate(robots):
        b = robot_body(r, body, shell_height_m)
        boxes[i, :len(b)] = b
        shell = shell_reflectance(r.color_rgb)
        solid = body == "3d"
        params[i] = (r.length_m / 2, r.width_m / 2, float(b[:, 4].max()), 0,
                     0.012 if solid else 0.0, 0.003 if solid else 0.0,
                     MARKER_SIDE_M / 2 if r.marker_id is not None else 0.0,
                     SHADOW_DEPTH if shadow else 0.0, SHADOW_WIDTH_M if shadow else 0.0,
                     shell * RIM_FACTOR, WINDOW_REFLECTANCE, len(b))
        markers[i] = marker_pattern(r.marker_id)
    return params, boxes, markers

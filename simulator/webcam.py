"""RGB webcam model: what a ceiling webcam beside the event camera sees, served as MJPEG.

Frames and units
----------------
Arena frame: origin at one mat corner, ``x``/``y`` in metres, ``z`` up from the mat surface.
Image frame: ``u`` (column, right), ``v`` (row, down), px. Times are world (simulated) seconds.

The camera is a pinhole camera (Logitech C920 class) mounted on the ceiling next to the
event camera, offset from the arena centre and slightly tilted, so the arena is a
non-square quadrilateral in the image. Because it is a real perspective camera, points
on the shell tops (``shell_height_m`` above the mats) appear displaced from where the
floor homography puts them (parallax); :attr:`WebcamModel.calibration` therefore gives
the image positions of the four mat corners both at floor height and at shell-top height.

Rendering is cheap by construction: the static background (white foam mats with seams
and grain, floor around them, vignetting, lighting level) is rendered once per lighting
level; each frame copies it and draws the robots (shell sides, top face in the shell
colour, a dark front mark or an ArUco marker) with anti-aliased sub-pixel polygons and a
small perspective warp for markers, into per-robot regions of interest. Motion blur
averages a few sub-poses across the exposure (centred on the world time, so the
exposure centre is the frame time); sensor noise is a shifted crop of a precomputed
noise bank; the optics blur is a 3x3 Gaussian.
"""

from __future__ import annotations

import http.server
import json
import logging
import math
import socketserver
import threading
import time
from pathlib import Path

import cv2
import numpy as np

log = logging.getLogger("simulator.webcam")

#: Lighting level -> (image gain, exposure time s, noise sigma DN). A webcam's auto
#: exposure lengthens the exposure and raises the gain (and the noise) as light drops.
LIGHTING = {
    "full": (1.0, 0.008, 2.0),
    "dimmed": (0.5, 0.020, 3.5),
    "dark": (0.18, 0.033, 6.0),
}
#: ArUco dictionary used for shell markers.
ARUCO_DICT = cv2.aruco.DICT_4X4_50
#: Foam mat tile side, m (the paper's 183 cm arena is 3 x 3 tiles of 61 cm).
MAT_TILE_M = 0.61


def _look_down_rotation(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """World->camera rotation of a camera looking straight down (image right = arena +x,
    image down = arena -y), then tilted by small roll/pitch/yaw angles (rad)."""
    r0 = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
    rvec = np.array([pitch, roll, yaw], dtype=float)
    rt, _ = cv2.Rodrigues(rvec)
    return rt @ r0


class WebcamModel:
    """Renders the arena as an RGB webcam sees it, at the world's current time.

    Args:
        world: a :class:`simulator.world.World` (uses ``lock``, ``t``, ``robots``,
            ``poses()``, ``velocities()``, ``lighting``, ``arena_m``).
        width, height: image size, px.
        fps: nominal frame rate, frames/s (used by :meth:`record` and the server).
        homography: ``None`` for the default perspective camera (2.45 m above the mats,
            12 cm beside the event camera, tilted a few degrees). A 3x4 projection matrix
            (arena metres x, y, z -> homogeneous pixels) places the camera explicitly. A 3x3
            floor homography (arena x, y -> pixels) is accepted too but then has no
            parallax (every height maps like the floor).
        blur: motion blur on (robots are averaged over sub-poses across the exposure).
        noise: sensor noise on (Gaussian, sigma from the lighting level).
        shell_height_m: height of the shell tops (and markers) above the mats, m.
        marker_size_m: side of the black ArUco square (6 x 6 cells with its border), m.
        flicker_hz, flicker_depth: ceiling light ripple (as in the event sensor model):
            intensity ``1 + depth * sin(2 pi f t)`` averaged over each exposure, so frames
            brighten and darken a few % from one to the next.
        seed: seed of the background grain and the sensor noise.
    """

    def __init__(self, world, width: int = 640, height: int = 480, fps: float = 24.0,
                 homography: np.ndarray | None = None, blur: bool = True, noise: bool = True,
                 shell_height_m: float = 0.045, marker_size_m: float = 0.075,
                 flicker_hz: float = 0.0, flicker_depth: float = 0.2, seed: int = 0):
        if width < 64 or height < 48:
            raise ValueError(f"image size must be at least 64x48 px, got {width}x{height}")
        if fps <= 0:
            raise ValueError(f"fps must be > 0, got {fps}")
        if flicker_hz < 0 or not 0 <= flicker_depth < 1:
            raise ValueError("flicker must be >= 0 Hz with a depth in [0, 1)")
        self.world = world
        self.flicker_hz, self.flicker_depth = float(flicker_hz), float(flicker_depth)
        self.width, self.height = int(width), int(height)
        self.fps = float(fps)
        self.blur, self.noise = bool(blur), bool(noise)
        self.shell_height_m = float(shell_height_m)
        self.marker_size_m = float(marker_size_m)
        self.arena_m = float(getattr(world, "arena_m", 1.83))
        self.P = self._projection(homography)
        self._rng = np.random.default_rng(seed)
        self._seed = seed
        self._backgrounds: dict[str, np.ndarray] = {}
        self._noise_bank: dict[str, np.ndarray] = {}
        self._markers: dict[tuple[int, float], np.ndarray] = {}
        #: World time (s) of the last rendered frame (the centre of its exposure).
        self.frame_time_s = 0.0

    # ------------------------------------------------------------------ geometry
    def _projection(self, homography) -> np.ndarray:
        if homography is not None:
            m = np.asarray(homography, dtype=float)
            if m.shape == (3, 3):
                return np.column_stack([m[:, 0], m[:, 1], np.zeros(3), m[:, 2]])
            if m.shape == (3, 4):
                return m
            raise ValueError(f"homography must be 3x3 (floor) or 3x4 (projection), got {m.shape}")
        a = self.arena_m
        centre = np.array([0.5 * a + 0.12, 0.5 * a - 0.05, 2.45])
        rot = _look_down_rotation(math.radians(2.5), math.radians(-3.5), math.radians(1.5))
        t = -rot @ centre
        rt = np.column_stack([rot, t])
        # fit focal length and principal point so the arena (with a margin) fills the image
        corners = np.array([[0, 0, 0, 1], [a, 0, 0, 1], [a, a, 0, 1], [0, a, 0, 1]], float)
        cam = corners @ rt.T
        xy = cam[:, :2] / cam[:, 2:3]
        span = xy.max(0) - xy.min(0)
        f = min(0.96 * self.width / span[0], 0.96 * self.height / span[1])
        mid = 0.5 * (xy.max(0) + xy.min(0))
        cx = 0.5 * self.width - f * mid[0]
        cy = 0.5 * self.height - f * mid[1]
        k = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])
        return k @ rt

    def project(self, xyz: np.ndarray) -> np.ndarray:
        """Project arena points ``(n, 3)`` (m) to image pixels ``(n, 2)`` (u, v)."""
        xyz = np.asarray(xyz, dtype=float).reshape(-1, 3)
        h = np.column_stack([xyz, np.ones(len(xyz))]) @ self.P.T
        return h[:, :2] / h[:, 2:3]

    def plane_homography(self, z_m: float) -> np.ndarray:
        """3x3 homography from arena (x, y) on the plane at height ``z_m`` (m) to pixels."""
        p = self.P
        return np.column_stack([p[:, 0], p[:, 1], p[:, 2] * z_m + p[:, 3]])

    @property
    def calibration(self) -> dict:
        """Calibration of this camera in the project's calibration-JSON format.

        ``points`` pairs the pixel position of each of the 4 mat corners with its arena
        position at shell-top height (``height_m``): the homography a detector of shell
        tops or markers should use. ``floor_points`` gives the same corners at floor height
        (``z = 0``, what one clicks on the mats). Using the floor homography for shell tops
        shifts positions by ``height_m / (camera_height - height_m) * distance_from_nadir``,
        about 1.9 cm for a 4.5 cm shell 1 m from the point under a 2.45 m-high camera.
        """
        a = self.arena_m
        xy = np.array([[0, 0], [a, 0], [a, a], [0, a]], float)

        def pts(z):
            uv = self.project(np.column_stack([xy, np.full(4, z)]))
            return [{"pixel": [round(float(u), 3), round(float(v), 3)],
                     "arena_m": [float(x), float(y)]} for (u, v), (x, y) in zip(uv, xy)]

        return {
            "camera": "webcam",
            "image_size": [self.width, self.height],
            "height_m": self.shell_height_m,
            "points": pts(self.shell_height_m),
            "floor_points": pts(0.0),
        }

    # ------------------------------------------------------------------ background
    def _background(self, lighting: str) -> np.ndarray:
        bg = self._backgrounds.get(lighting)
        if bg is None:
            bg = self._render_background(lighting)
            self._backgrounds[lighting] = bg
        return bg

    def _render_background(self, lighting: str) -> np.ndarray:
        gain = LIGHTING[lighting][0]
        a = self.arena_m
        res = 0.0025                      # texture resolution, m/px
        margin = 0.6                      # floor shown around the mats, m
        n = int(round((a + 2 * margin) / res))
        rng = np.random.default_rng(self._seed + 1)
        # floor (grey concrete), mats (off-white foam with grain)
        grain = cv2.GaussianBlur(rng.normal(0, 1, (n, n)).astype(np.float32), (0, 0), 1.5)
        tex = np.empty((n, n, 3), np.float32)
        tex[:] = (118, 124, 128)
        tex += 6.0 * grain[..., None]
        lo, hi = int(round(margin / res)), int(round((margin + a) / res))
        mats = np.empty((hi - lo, hi - lo, 3), np.float32)
        mats[:] = (226, 232, 234)
        tiles = max(1, int(round(a / MAT_TILE_M)))
        tile_rng = rng.uniform(-5, 5, (tiles, tiles))
        step = (hi - lo) / tiles
        for i in range(tiles):           # slight per-tile shade difference
            for j in range(tiles):
                mats[int(i * step):int((i + 1) * step), int(j * step):int((j + 1) * step)] += tile_rng[i, j]
        mats += 4.0 * grain[lo:hi, lo:hi, None]
        for k in range(1, tiles):        # faint seams between tiles (5 mm, a bit darker)
            s = int(round(k * step))
            mats[s - 1:s + 1, :] -= 28
            mats[:, s - 1:s + 1] -= 28
        tex[lo:hi, lo:hi] = mats
        # texture pixel (col, row) -> arena (x, y): x = -margin + col*res, y = a + margin - row*res
        t2a = np.array([[res, 0, -margin], [0, -res, a + margin], [0, 0, 1]])
        h = self.plane_homography(0.0) @ t2a
        img = cv2.warpPerspective(tex, h, (self.width, self.height), flags=cv2.INTER_LINEAR,
                                  borderValue=(60, 60, 60))
        # vignetting (cos^4 fall-off of a wide lens) and the lighting level
        yy, xx = np.mgrid[0:self.height, 0:self.width].astype(np.float32)
        r2 = ((xx - self.width / 2) ** 2 + (yy - self.height / 2) ** 2) / (1.4 * self.width) ** 2
        vig = (1.0 / (1.0 + r2)) ** 2
        img *= (vig * gain)[..., None]
        return np.clip(img, 0, 255).astype(np.uint8)

    def _noise(self, lighting: str) -> np.ndarray:
        bank = self._noise_bank.get(lighting)
        if bank is None:
            sigma = LIGHTING[lighting][2]
            rng = np.random.default_rng(self._seed + 2)
            bank = np.round(rng.normal(0, sigma, (self.height + 64, self.width + 64, 3))).astype(np.int16)
            self._noise_bank[lighting] = bank
        return bank

    def _marker_image(self, marker_id: int, gain: float) -> np.ndarray:
        """The marker (8 px per cell) with a one-cell white quiet zone, at this light level."""
        key = (marker_id, gain)
        img = self._markers.get(key)
        if img is None:
            d = cv2.aruco.getPredefinedDictionary(ARUCO_DICT)
            cell = 8
            m = cv2.aruco.generateImageMarker(d, int(marker_id), 6 * cell)
            m = cv2.copyMakeBorder(m, cell, cell, cell, cell, cv2.BORDER_CONSTANT, value=255)
            img = cv2.convertScaleAbs(cv2.cvtColor(m, cv2.COLOR_GRAY2BGR), alpha=0.92 * gain)
            self._markers[key] = img
        return img

    # ------------------------------------------------------------------ robots
    def _draw_robot(self, img: np.ndarray, origin: np.ndarray, spec, pose, gain: float) -> None:
        """Draw one robot at ``pose`` (x, y, yaw) into ``img`` whose pixel (0, 0) is image
        pixel ``origin``."""
        x, y, yaw = pose
        c, s = math.cos(yaw), math.sin(yaw)
        hl, hw = 0.5 * spec.length_m, 0.5 * spec.width_m
        hs = self.shell_height_m
        if spec.marker_id is not None:
            q = 0.5 * self.marker_size_m * 8 / 6      # marker plus a one-cell white quiet zone
            # image top edge = robot front (+x body), image left = robot left (+y body)
            inner = ((q, q), (q, -q), (-q, -q), (-q, q))
        else:                                         # front mark: a bar across the front
            inner = ((hl - 0.008, hw - 0.015), (hl - 0.030, hw - 0.015),
                     (hl - 0.030, -hw + 0.015), (hl - 0.008, -hw + 0.015))
        body = np.array(((hl, hw), (-hl, hw), (-hl, -hw), (hl, -hw)) * 2 + inner)
        pts = np.empty((12, 4))
        pts[:, 0] = x + c * body[:, 0] - s * body[:, 1]
        pts[:, 1] = y + s * body[:, 0] + c * body[:, 1]
        pts[:4, 2] = 0.0
        pts[4:, 2] = hs
        pts[:, 3] = 1.0
        hom = pts @ self.P.T
        uv = hom[:, :2] / hom[:, 2:3] - origin
        top, inner_px = uv[4:8], uv[8:]
        rgb = np.array(spec.color_rgb[::-1], float) * gain
        sc = 16.0                                     # 4 bits of sub-pixel precision
        hull = cv2.convexHull(np.round(uv[:8] * sc).astype(np.int32))
        cv2.fillConvexPoly(img, hull, tuple(float(v) for v in rgb * 0.55), cv2.LINE_AA, 4)
        cv2.fillConvexPoly(img, np.round(top * sc).astype(np.int32), tuple(float(v) for v in rgb),
                           cv2.LINE_AA, 4)
        if spec.marker_id is not None:
            canvas = self._marker_image(spec.marker_id, gain)
            side = canvas.shape[0]
            src = np.array([[0, 0], [side, 0], [side, side], [0, side]], np.float32)
            h = cv2.getPerspectiveTransform(src, inner_px.astype(np.float32))
            cv2.warpPerspective(canvas, h, (img.shape[1], img.shape[0]), dst=img,
                                flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_TRANSPARENT)
        else:
            # dark mark on bright shells, white mark on dark shells
            g = (25 if max(spec.color_rgb) > 90 else 235) * gain
            cv2.fillConvexPoly(img, np.round(inner_px * sc).astype(np.int32), (g, g, g),
                               cv2.LINE_AA, 4)

    def _robot_bbox(self, spec, poses: np.ndarray) -> tuple[int, int, int, int] | None:
        r = 0.5 * math.hypot(spec.length_m, spec.width_m)
        pts = []
        for x, y, _ in poses:
            for z in (0.0, self.shell_height_m):
                pts.append([(x - r, y - r, z), (x + r, y - r, z), (x + r, y + r, z), (x - r, y + r, z)])
        uv = self.project(np.array(pts).reshape(-1, 3))
        u0, v0 = np.floor(uv.min(0)).astype(int) - 3
        u1, v1 = np.ceil(uv.max(0)).astype(int) + 3
        u0, v0 = max(u0, 0), max(v0, 0)
        u1, v1 = min(u1, self.width), min(v1, self.height)
        if u1 <= u0 or v1 <= v0:
            return None
        return u0, v0, u1, v1

    # ------------------------------------------------------------------ render
    def render(self) -> np.ndarray:
        """Render the frame at the world's current time: BGR ``uint8`` (height, width, 3).

        The exposure is centred on the world time (robots are extrapolated with their
        current velocities), so detections from this frame compare with the world's pose
        at :attr:`frame_time_s`.
        """
        w = self.world
        with w.lock:
            t = float(w.t)
            poses = w.poses()
            vel = w.velocities()
            lighting = w.lighting
            specs = list(w.robots)
        gain, exposure, _ = LIGHTING[lighting]
        img = self._background(lighting).copy()
        for spec, pose, v in zip(specs, poses, vel):
            speed_px = 0.0
            if self.blur:
                speed_px = (math.hypot(v[0], v[1]) + abs(v[2]) * 0.07) * exposure * self.P[0, 0] / 2.4
            k = int(min(6, max(1, math.ceil(speed_px - 1e-9))))   # one sub-pose per px of travel
            offs = np.linspace(-0.5, 0.5, k) * exposure if k > 1 else np.zeros(1)
            sub = np.array([[pose[0] + v[0] * o, pose[1] + v[1] * o, pose[2] + v[2] * o] for o in offs])
            box = self._robot_bbox(spec, sub)
            if box is None:
                continue
            u0, v0, u1, v1 = box
            roi = img[v0:v1, u0:u1]
            origin = np.array([u0, v0], float)
            if k == 1:
                patch = roi.copy()
                self._draw_robot(patch, origin, spec, sub[0], gain)
            else:
                acc = np.zeros(roi.shape, np.float32)
                for p in sub:
                    patch = roi.copy()
                    self._draw_robot(patch, origin, spec, p, gain)
                    acc += patch
                patch = (acc * (1.0 / k) + 0.5).astype(np.uint8)
            img[v0:v1, u0:u1] = patch
        img = cv2.GaussianBlur(img, (3, 3), 0.6)
        if self.flicker_hz > 0:
            # mean of sin(2 pi f t') over the exposure centred on t: sin(2 pi f t) * sinc(f e)
            x = math.pi * self.flicker_hz * exposure
            ripple = math.sin(2 * math.pi * self.flicker_hz * t) * math.sin(x) / x
            img = cv2.convertScaleAbs(img, alpha=1.0 + self.flicker_depth * ripple)
        if self.noise:
            bank = self._noise(lighting)
            dy, dx = self._rng.integers(0, 64, 2)
            img = cv2.add(img, bank[dy:dy + self.height, dx:dx + self.width], dtype=cv2.CV_8U)
        self.frame_time_s = t
        return img

    def record(self, path: str | Path, seconds: float, step_world: bool = True) -> int:
        """Write ``seconds`` of video at :attr:`fps` to ``path`` (Motion-JPEG in AVI).

        With ``step_world`` the world is advanced by ``1 / fps`` between frames (offline,
        as fast as possible); otherwise frames sample a world that someone else steps.
        Returns the number of frames written.
        """
        path = Path(path)
        fourcc = cv2.VideoWriter_fourcc(*"MJPG")
        writer = cv2.VideoWriter(str(path), fourcc, self.fps, (self.width, self.height))
        if not writer.isOpened():
            raise OSError(f"cannot open {path} for writing (Motion-JPEG AVI)")
        n = int(round(seconds * self.fps))
        try:
            for i in range(n):
                if step_world and i:
                    self.world.step(1.0 / self.fps)
                writer.write(self.render())
        finally:
            writer.release()
        return n


class _Handler(http.server.BaseHTTPRequestHandler):
    server_version = "ArenaWebcam/1.0"
    protocol_version = "HTTP/1.0"

    def log_message(self, fmt, *args):  # route the access log to logging, quietly
        log.debug("%s - " + fmt, self.client_address[0], *args)

    def do_GET(self):  # noqa: N802 (http.server API)
        owner: WebcamServer = self.server.owner  # type: ignore[attr-defined]
        path = self.path.split("?", 1)[0]
        if path == "/stream.mjpg":
            self._stream(owner)
        elif path == "/snapshot.jpg":
            jpeg, t = owner.wait_frame(-1, timeout=5.0)[1:]
            self._send(200, "image/jpeg", jpeg, {"X-World-Time-us": str(int(t * 1e6))})
        elif path == "/calibration.json":
            body = json.dumps(owner.model.calibration, indent=1).encode()
            self._send(200, "application/json", body)
        else:
            self._send(404, "text/plain", b"not found: try /stream.mjpg, /snapshot.jpg, /calibration.json\n")

    def _send(self, code: int, ctype: str, body: bytes, extra: dict | None = None) -> None:
        self.send_response(code)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        for k, v in (extra or {}).items():
            self.send_header(k, v)
        self.end_headers()
        self.wfile.write(body)

    def _stream(self, owner: "WebcamServer") -> None:
        self.send_response(200)
        self.send_header("Content-Type", f"multipart/x-mixed-replace; boundary={owner.BOUNDARY}")
        self.send_header("Cache-Control", "no-cache")
        self.end_headers()
        seq = -1
        owner._clients_changed(+1)
        try:
            while not owner._stopping.is_set():
                got = owner.wait_frame(seq, timeout=1.0)
                if got is None:
                    continue
                seq, jpeg, t = got
                head = (f"--{owner.BOUNDARY}\r\nContent-Type: image/jpeg\r\n"
                        f"Content-Length: {len(jpeg)}\r\nX-World-Time-us: {int(t * 1e6)}\r\n\r\n")
                self.wfile.write(head.encode() + jpeg + b"\r\n")
        except (BrokenPipeError, ConnectionResetError, OSError):
            pass
        finally:
            owner._clients_changed(-1)


class _HTTPServer(socketserver.ThreadingMixIn, http.server.HTTPServer):
    daemon_threads = True
    allow_reuse_address = True


class WebcamServer:
    """Serve a :class:`WebcamModel` as an MJPEG stream over HTTP (like an IP webcam).

    Endpoints: ``/stream.mjpg`` (``multipart/x-mixed-replace`` JPEG parts, each with its
    ``Content-Length`` and an ``X-World-Time-us`` header), ``/snapshot.jpg`` and
    ``/calibration.json`` (:attr:`WebcamModel.calibration`). Frames are rendered and
    encoded once at ``fps`` by one thread, only while a client is connected, and shared by
    all clients. ``cv2.VideoCapture(server.url)`` opens the stream (FFmpeg ``mpjpeg``).

    Example::

        with WebcamServer(world, port=8090) as cam:
            cap = cv2.VideoCapture(cam.url)
            ok, frame = cap.read()

    Args:
        model_or_world: a :class:`WebcamModel`, or a world to wrap in a default model.
        host, port: where to listen (port 0 picks a free port, see :attr:`port`).
        fps: frames/s of the stream.
        quality: JPEG quality 1-100.
    """

    BOUNDARY = "arenaframe"

    def __init__(self, model_or_world, host: str = "127.0.0.1", port: int = 0, fps: float = 24.0,
                 quality: int = 90):
        if isinstance(model_or_world, WebcamModel):
            self.model = model_or_world
        else:
            self.model = WebcamModel(model_or_world, fps=fps)
        if fps <= 0:
            raise ValueError(f"fps must be > 0, got {fps}")
        self.fps = float(fps)
        self.quality = int(quality)
        self._host, self._port = host, int(port)
        self._httpd: _HTTPServer | None = None
        self._threads: list[threading.Thread] = []
        self._cond = threading.Condition()
        self._frame: tuple[int, bytes, float] | None = None
        self._clients = 0
        self._stopping = threading.Event()
        self._snapshot_wanted = threading.Event()
        #: Frames rendered and encoded so far.
        self.frames_served = 0

    @property
    def port(self) -> int:
        """The TCP port the server listens on (after :meth:`start`)."""
        if self._httpd is None:
            raise RuntimeError("WebcamServer not started")
        return self._httpd.server_address[1]

    @property
    def url(self) -> str:
        """``http://HOST:PORT/stream.mjpg``."""
        return f"http://{self._host}:{self.port}/stream.mjpg"

    def start(self) -> "WebcamServer":
        """Bind and start serving in background threads. Returns ``self``."""
        if self._httpd is not None:
            return self
        self._httpd = _HTTPServer((self._host, self._port), _Handler)
        self._httpd.owner = self  # type: ignore[attr-defined]
        self._stopping.clear()
        self._threads = [
            threading.Thread(target=self._httpd.serve_forever, kwargs={"poll_interval": 0.2},
                             name="webcam-http", daemon=True),
            threading.Thread(target=self._produce, name="webcam-render", daemon=True),
        ]
        for th in self._threads:
            th.start()
        log.info("webcam MJPEG stream at %s", self.url)
        return self

    def stop(self) -> None:
        """Stop serving and join the threads."""
        if self._httpd is None:
            return
        self._stopping.set()
        with self._cond:
            self._cond.notify_all()
        self._httpd.shutdown()
        self._httpd.server_close()
        for th in self._threads:
            th.join(timeout=3.0)
        self._httpd = None

    def __enter__(self) -> "WebcamServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # -- frame sharing
    def _clients_changed(self, d: int) -> None:
        with self._cond:
            self._clients += d
            self._cond.notify_all()

    def wait_frame(self, after_seq: int, timeout: float) -> tuple[int, bytes, float] | None:
        """Block until a frame newer than ``after_seq`` exists; return ``(seq, jpeg, t_s)``
        or ``None`` on timeout. ``after_seq=-1`` asks for a fresh frame."""
        deadline = time.monotonic() + timeout
        if after_seq < 0:
            self._snapshot_wanted.set()
            with self._cond:
                self._cond.notify_all()
        with self._cond:
            while not self._stopping.is_set():
                if self._frame is not None and self._frame[0] > after_seq:
                    return self._frame
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._cond.wait(left)
        return None

    def _produce(self) -> None:
        period = 1.0 / self.fps
        seq = 0
        next_t = time.monotonic()
        while not self._stopping.is_set():
            with self._cond:
                while self._clients == 0 and not self._snapshot_wanted.is_set() \
                        and not self._stopping.is_set():
                    self._cond.wait(0.5)
                    next_t = time.monotonic()
            if self._stopping.is_set():
                break
            self._snapshot_wanted.clear()
            frame = self.model.render()
            ok, jpeg = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, self.quality])
            if ok:
                seq += 1
                self.frames_served += 1
                with self._cond:
                    self._frame = (seq, jpeg.tobytes(), self.model.frame_time_s)
                    self._cond.notify_all()
            next_t += period
            delay = next_t - time.monotonic()
            if delay > 0:
                self._stopping.wait(delay)
            else:
                next_t = time.monotonic()

"""RGB ground truth: webcam frames, colour-blob and ArUco-marker robot detectors.

Frames and units: image ``u`` (column, right), ``v`` (row, down) in px; arena ``x``/``y`` in
metres, yaw in radians counter-clockwise from the arena +x axis, in ``[-pi, pi)``; times in
microseconds (``t_us``). Pixel -> arena goes through a :class:`~groundtruth.homography.Homography`
calibrated at shell-top / marker height (see that module for the parallax error otherwise).

Detectors are pure (frame in, :class:`Detection` list out) and keep only the small state a
tracker of headings needs (recent positions per robot). :class:`FrameSource` is the one
piece of I/O: it opens ``cv2.VideoCapture`` on a device index, a file or a URL and stamps
each frame when it is captured.

* :class:`HsvDetector` — the paper's method made robust: HSV thresholds per robot,
  morphology, external contours, area and shape (solidity, aspect) checks, the centroid by
  moments of the convex hull of the blob's lit top face (so neither the front mark nor the
  shaded shell sides bias it). Heading: the shell
  outline's orientation (``minAreaRect`` in arena metres, modulo 90° for a square shell)
  resolved by the dark front mark (a hole in the blob near its front edge) when present,
  else by the direction of motion (assuming forward driving); ``nan`` when neither is known.
* :class:`MarkerDetector` — ArUco markers (``cv2.aruco.ArucoDetector``, corners refined by
  fitting lines to the marker's edges):
  a unique id per robot, position = centre of the four corners and heading = the marker's
  "up" edge direction, both in arena metres, without ambiguity. The marker's top edge
  faces the robot's front.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from groundtruth.homography import Homography

@dataclass
class Detection:
    """One robot seen in one frame (a row of the ground-truth CSV:
    :class:`arena.formats.tables.GroundTruthCsvWriter` writes them).

    Attributes:
        t_us: capture time of the frame, µs (host clock for live sources, media time for files).
        robot: robot name.
        x_m, y_m: position in the arena frame, m.
        yaw_rad: heading, rad, counter-clockwise from arena +x; ``nan`` if unknown.
        u_px, v_px: image position of the detected centre, px.
        detector: ``"hsv"`` or ``"aruco"``.
    """

    t_us: int
    robot: str
    x_m: float
    y_m: float
    yaw_rad: float
    u_px: float
    v_px: float
    detector: str


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


# ---------------------------------------------------------------------------- frames
class FrameSource:
    """Frames from ``cv2.VideoCapture``, each stamped when it is captured.

    Args:
        source: a device index (``0`` or ``"0"``), a video file path, or a URL
            (``http://127.0.0.1:8090/stream.mjpg``, ``rtsp://...``).
        clock: for live sources, ``"host"`` stamps each frame with the host clock
            (``time.time_ns() // 1000``, µs) right after it is grabbed; ``"stream"`` reads an
            MJPEG-over-HTTP stream directly and uses the per-frame ``X-World-Time-us`` header
            that ``arena sim`` sends (the simulator's clock: the event camera's and the truth
            CSV's time base). Files are always stamped with their media time (µs from the start).
        timeout_s: network timeout of the ``"stream"`` reader, s.

    Raises ``OSError`` with a clear message if the source cannot be opened.
    """

    def __init__(self, source: str | int, clock: str = "host", timeout_s: float = 5.0):
        if clock not in ("host", "stream"):
            raise ValueError(f"clock must be 'host' or 'stream', got {clock!r}")
        self.source = source
        index = _as_index(source)
        self.live = index is not None or "://" in str(source)
        if clock == "stream" and not str(source).startswith(("http://", "https://")):
            raise OSError(f"clock 'stream' needs an MJPEG http:// URL, got {source!r}")
        if not self.live and not Path(str(source)).exists():
            raise OSError(f"video file not found: {source}")
        self.clock = clock
        self.timeout_s = float(timeout_s)
        self._cap = None
        self._http = None
        self._open()
        #: Frames read so far.
        self.frames = 0

    def _open(self) -> None:
        if self.clock == "stream":
            self._http = _MjpegReader(str(self.source), self.timeout_s)
            return
        index = _as_index(self.source)
        if index is not None:
            cap = cv2.VideoCapture(index)
        elif self.live:
            cap = cv2.VideoCapture(str(self.source), cv2.CAP_FFMPEG)
        else:
            cap = cv2.VideoCapture(str(self.source))
        if not cap.isOpened():
            cap.release()
            raise OSError(f"cannot open video source {self.source!r}")
        self._cap = cap

    def reopen(self) -> None:
        """Close and open the source again (a live stream that dropped). Raises ``OSError``."""
        self.close()
        self._open()

    @property
    def fps(self) -> float:
        """The source's nominal frame rate (0 if unknown), frames/s."""
        if self._cap is None:
            return 0.0
        return float(self._cap.get(cv2.CAP_PROP_FPS) or 0.0)

    def read(self) -> tuple[int, np.ndarray] | None:
        """Next ``(t_us, BGR frame)``, or ``None`` at the end of the stream."""
        if self._http is not None:
            got = self._http.read()
            if got is not None:
                self.frames += 1
            return got
        if not self._cap.grab():
            return None
        if self.live:
            t_us = time.time_ns() // 1000
        else:
            t_us = int(round(self._cap.get(cv2.CAP_PROP_POS_MSEC) * 1000.0))
        ok, frame = self._cap.retrieve()
        if not ok or frame is None:
            return None
        self.frames += 1
        return t_us, frame

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None
        if self._http is not None:
            self._http.close()
            self._http = None

    def __enter__(self) -> "FrameSource":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __iter__(self):
        while (got := self.read()) is not None:
            yield got


class _MjpegReader:
    """Minimal ``multipart/x-mixed-replace`` JPEG reader that keeps each part's headers."""

    TIME_HEADER = b"x-world-time-us"

    def __init__(self, url: str, timeout_s: float):
        import urllib.request

        try:
            self._resp = urllib.request.urlopen(url, timeout=timeout_s)
        except OSError as e:
            raise OSError(f"cannot open video source {url!r}: {e}") from None
        ctype = self._resp.headers.get("Content-Type", "")
        if "multipart/x-mixed-replace" not in ctype or "boundary=" not in ctype:
            self._resp.close()
            raise OSError(f"{url} is not an MJPEG stream (Content-Type {ctype!r})")
        self.url = url
        self._boundary = b"--" + ctype.split("boundary=", 1)[1].split(";")[0].strip().strip('"').encode()

    def read(self) -> tuple[int, np.ndarray] | None:
        """Next ``(t_us, frame)``; ``None`` when the stream ends or breaks."""
        try:
            part = self._part()
        except (OSError, ValueError):     # connection dropped, or a garbled part
            return None
        if part is None:
            return None
        headers, data = part
        if self.TIME_HEADER not in headers:
            raise OSError(f"{self.url} sends no X-World-Time-us per frame: use the host clock")
        frame = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        if frame is None:
            return None
        return int(headers[self.TIME_HEADER]), frame

    def _part(self) -> tuple[dict, bytes] | None:
        line = self._resp.readline()
        while line and line.strip() != self._boundary:
            line = self._resp.readline()
        if not line:
            return None
        headers = {}
        while (line := self._resp.readline().strip()):
            k, _, v = line.partition(b":")
            headers[k.strip().lower()] = v.strip()
        n = int(headers.get(b"content-length", b"-1"))
        if n < 0:
            raise ValueError("MJPEG part without Content-Length")
        return headers, self._resp.read(n)

    def close(self) -> None:
        self._resp.close()


def _as_index(source) -> int | None:
    if isinstance(source, int):
        return source
    s = str(source).strip()
    return int(s) if s.isdigit() else None


# ---------------------------------------------------------------------------- HSV
@dataclass(frozen=True)
class HsvRange:
    """An OpenCV HSV box: ``lo``/``hi`` as (H 0-179, S 0-255, V 0-255). If ``lo[0] > hi[0]``
    the hue range wraps around 180 (reds)."""

    lo: tuple[int, int, int]
    hi: tuple[int, int, int]

    def __post_init__(self):
        for t, name in ((self.lo, "lo"), (self.hi, "hi")):
            if len(t) != 3 or not (0 <= t[0] <= 179 and 0 <= t[1] <= 255 and 0 <= t[2] <= 255):
                raise ValueError(f"HSV {name} must be (H 0-179, S 0-255, V 0-255), got {t}")
        if self.lo[1] > self.hi[1] or self.lo[2] > self.hi[2]:
            raise ValueError(f"HSV range lo {self.lo} exceeds hi {self.hi} in S or V")

    def mask(self, hsv: np.ndarray) -> np.ndarray:
        """Binary mask (uint8 0/255) of the pixels of an HSV image inside the range."""
        lo, hi = self.lo, self.hi
        if lo[0] <= hi[0]:
            return cv2.inRange(hsv, lo, hi)
        a = cv2.inRange(hsv, lo, (179, hi[1], hi[2]))
        b = cv2.inRange(hsv, (0, lo[1], lo[2]), hi)
        return cv2.bitwise_or(a, b)

    @classmethod
    def parse(cls, value) -> "HsvRange":
        """From ``[[h, s, v], [h, s, v]]`` or ``{"lo": [...], "hi": [...]}`` (config files)."""
        if isinstance(value, HsvRange):
            return value
        if isinstance(value, dict):
            value = [value.get("lo"), value.get("hi")]
        try:
            lo, hi = value
            return cls(tuple(int(v) for v in lo), tuple(int(v) for v in hi))
        except (TypeError, ValueError) as e:
            raise ValueError(f"bad HSV range {value!r}: expected [[h,s,v],[h,s,v]] ({e})") from None


def sample_hsv_range(frame: np.ndarray, pixel: tuple[float, float], radius: int = 3,
                     margin: tuple[int, int, int] = (8, 50, 60), v_floor: float = 0.3) -> HsvRange:
    """Sample a robot's HSV range from a BGR frame around ``pixel`` (u, v), px.

    Takes the 5th-95th percentile of H, S and V in a ``(2 radius + 1)`` square (click on the
    middle of the shell top, away from the front mark) and widens it by ``margin`` (H, S, V).
    For coloured shells the value (brightness) range reaches down to ``v_floor`` times the
    sampled one, so the range still holds when the light is dimmed (hue and saturation do
    not change with the light level). The hue is handled circularly (a red shell gives a
    wrapping range).
    """
    h, w = frame.shape[:2]
    u, v = int(round(pixel[0])), int(round(pixel[1]))
    if not (0 <= u < w and 0 <= v < h):
        raise ValueError(f"pixel {pixel} outside the {w}x{h} frame")
    patch = frame[max(0, v - radius):v + radius + 1, max(0, u - radius):u + radius + 1]
    hsv = cv2.cvtColor(patch, cv2.COLOR_BGR2HSV).reshape(-1, 3).astype(float)
    s_lo, s_hi = np.percentile(hsv[:, 1], [5, 95])
    v_lo, v_hi = np.percentile(hsv[:, 2], [5, 95])
    if s_hi < 40 or np.median(hsv[:, 2]) < 70:   # black / grey shell: hue is meaningless
        return HsvRange((0, 0, int(max(0, v_lo - margin[2]))),
                        (179, int(min(255, s_hi + margin[1])), int(min(255, v_hi + margin[2]))))
    ang = hsv[:, 0] * (2 * math.pi / 180)
    mean = math.atan2(np.sin(ang).mean(), np.cos(ang).mean()) * 180 / (2 * math.pi)
    dev = (hsv[:, 0] - mean + 90) % 180 - 90
    d_lo, d_hi = np.percentile(dev, [5, 95])
    h_lo = int(math.floor(mean + d_lo - margin[0])) % 180
    h_hi = int(math.ceil(mean + d_hi + margin[0])) % 180
    return HsvRange((h_lo, int(max(0, s_lo - margin[1])), int(max(25, v_lo * v_floor))),
                    (h_hi, 255, int(min(255, v_hi + margin[2]))))


#: Value (V of HSV, 0-255) of the white mats in the light a nominal shell colour is given for:
#: a white surface a webcam's auto exposure puts at ~86 % of full scale. With
#: ``HsvDetector(white_v=WHITE_V)`` the V bounds of nominal-colour ranges follow the mats'
#: measured brightness (dimmed light, a darker exposure), as hue and saturation do not change.
WHITE_V = 220.0


def colour_detectable(rgb: tuple[int, int, int]) -> str | None:
    """Why a shell of nominal colour ``rgb`` (R, G, B 0-255) cannot be found by colour on the
    white mats (``None`` when it can): a pale, unsaturated shell (white, light grey) has neither
    a hue nor a brightness that sets it apart from them."""
    bgr = np.uint8([[list(rgb)[::-1]]])
    _, s, v = (int(c) for c in cv2.cvtColor(bgr, cv2.COLOR_BGR2HSV)[0, 0])
    if s < 60 and v > 110:
        return (f"shell colour {tuple(int(c) for c in rgb)} is too close to the white mats for colour detection "
                f"(saturation {s}/255, value {v}/255: only saturated colours or dark shells stand out)")
    return None


def hsv_range_from_rgb(rgb: tuple[int, int, int], hue_margin: int = 10) -> HsvRange:
    """A default HSV range for a nominal shell colour (R, G, B 0-255) from the lab config,
    tolerant to lighting (V down to 30 % of the nominal; with ``HsvDetector(white_v=...)`` the
    V bounds also follow the mats' brightness). Prefer :func:`sample_hsv_range` on a real
    frame. Raises ``ValueError`` for white/grey shells (indistinct from the mats, see
    :func:`colour_detectable`)."""
    why = colour_detectable(rgb)
    if why:
        raise ValueError(why)
    bgr = np.uint8([[list(rgb)[::-1]]])
    h, s, v = (int(c) for c in cv2.cvtColor(bgr, cv2.COLOR_BGR2HSV)[0, 0])
    if s < 60:
        return HsvRange((0, 0, 0), (179, 255, max(60, int(v * 2.5))))
    return HsvRange(((h - hue_margin) % 180, max(40, s // 2), max(25, int(v * 0.3))),
                    ((h + hue_margin) % 180, 255, 255))


class HsvDetector:
    """Colour-blob robot detector (one HSV range per robot; the largest valid blob wins).

    Args:
        ranges: robot name -> :class:`HsvRange` (or anything :meth:`HsvRange.parse` takes).
        homography: pixel -> arena at shell-top height.
        shell_size_m: (length, width) of the shell top, m; sets the area and shape checks.
        area_tolerance: accepted blob area (hull, in arena m^2) is within this factor of
            the nominal shell area (``nominal / tol .. nominal * tol``).
        min_solidity: blob area / convex hull area (a front mark removes ~15 %).
        front_mark: look for the dark front mark (a hole near the front edge).
        motion_min_m: displacement over ``motion_window_us`` above which the direction of
            motion resolves the heading when no front mark is seen, m.
        motion_window_us: how far back the motion heading looks, µs.
        top_ratio: blob pixels darker than this fraction of the blob's bright (90th
            percentile) value are the shaded shell sides the perspective shows; they are
            left out of the centroid and the outline.
        search_radius_px: a robot found in the previous frame is first searched within this
            many pixels of its last position (the whole frame if it is not found there).
        white_v: the mats' value (V, 0-255) the ranges were set for (:data:`WHITE_V` for
            ranges from nominal colours); each frame's V bounds are then scaled by the mats'
            measured value (the 75th percentile of V over the frame, which the mats fill) over
            ``white_v``, so a range holds when the light is dimmed. ``None``: fixed bounds.
        relative: the robots whose ranges follow the mats' value (default all, when
            ``white_v`` is given); ranges sampled on a frame are usually absolute.

    Headings: :attr:`heading_sources` counts, per detection, what resolved the shell's
    90-degree ambiguity: ``"front_mark"`` (the dark window strip / front mark seen as a hole
    in the blob), ``"motion"`` (the direction travelled over ``motion_window_us``, assuming
    forward driving) or ``"unknown"`` (neither: ``yaw_rad`` is ``nan``).
    """

    name = "hsv"

    def __init__(self, ranges: dict, homography: Homography, shell_size_m=(0.10, 0.10),
                 area_tolerance: float = 2.2, min_solidity: float = 0.55, front_mark: bool = True,
                 motion_min_m: float = 0.02, motion_window_us: int = 300_000, top_ratio: float = 0.75,
                 search_radius_px: int = 60, white_v: float | None = None, relative=None):
        self.ranges = {name: HsvRange.parse(r) for name, r in ranges.items()}
        if white_v is not None and not 0 < white_v <= 255:
            raise ValueError(f"white_v must be in (0, 255], got {white_v}")
        self.white_v = None if white_v is None else float(white_v)
        self.relative = set(self.ranges) if relative is None else set(relative)
        #: the last frame's V scale (mats' measured value / ``white_v``), 1.0 without ``white_v``
        self.v_scale = 1.0
        #: detections per heading source: front_mark, motion, unknown (see the class doc)
        self.heading_sources = {"front_mark": 0, "motion": 0, "unknown": 0}
        self.homography = homography
        self.shell_area_m2 = float(shell_size_m[0]) * float(shell_size_m[1])
        self.area_tolerance = float(area_tolerance)
        self.min_solidity = float(min_solidity)
        self.front_mark = bool(front_mark)
        self.motion_min_m = float(motion_min_m)
        self.motion_window_us = int(motion_window_us)
        self.top_ratio = float(top_ratio)
        self.search_radius_px = int(search_radius_px)
        self._last_px: dict[str, tuple[float, float]] = {}
        self._kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3))
        self.history_: dict[str, deque] = {}

    def detect(self, frame: np.ndarray, t_us: int) -> list[Detection]:
        """Detect every configured robot in a BGR frame captured at ``t_us`` (µs)."""
        _check_frame(frame)
        hsv = cv2.cvtColor(frame, cv2.COLOR_BGR2HSV)
        h, w = hsv.shape[:2]
        if self.white_v is not None:
            mats_v = float(np.percentile(hsv[::8, ::8, 2], 75))
            self.v_scale = min(1.3, max(0.05, mats_v / self.white_v))
        out = []
        for robot, rng in self.ranges.items():
            if self.white_v is not None and robot in self.relative:
                rng = _scaled_value(rng, self.v_scale)
            det = None
            last = self._last_px.get(robot)
            if last is not None:          # search near the last position first (cheap)
                r = self.search_radius_px
                x0, y0 = max(0, int(last[0]) - r), max(0, int(last[1]) - r)
                x1, y1 = min(w, int(last[0]) + r), min(h, int(last[1]) + r)
                if x1 - x0 > 8 and y1 - y0 > 8:
                    det = self._search(hsv, rng, robot, t_us, (x0, y0, x1, y1))
            if det is None:
                det = self._search(hsv, rng, robot, t_us, (0, 0, w, h))
            if det is None:
                self._last_px.pop(robot, None)
            else:
                self._last_px[robot] = (det.u_px, det.v_px)
                out.append(det)
        return out

    def _search(self, hsv, rng: HsvRange, robot: str, t_us: int, box) -> Detection | None:
        x0, y0, x1, y1 = box
        sub = hsv[y0:y1, x0:x1]
        mask = cv2.morphologyEx(rng.mask(sub), cv2.MORPH_OPEN, self._kernel)
        inner = (x0 > 0, y0 > 0, x1 < hsv.shape[1], y1 < hsv.shape[0])
        return self._best_blob(mask, sub[..., 2], robot, t_us, np.array([x0, y0], float), inner)

    def _best_blob(self, mask: np.ndarray, value: np.ndarray, robot: str, t_us: int,
                   off: np.ndarray, inner: tuple[bool, bool, bool, bool]) -> Detection | None:
        """Best blob of a (sub-)mask whose pixel (0, 0) is image pixel ``off``; ``inner``
        tells which sides (left, top, right, bottom) are cut from a larger image: a blob
        touching one of those may be clipped, so the caller searches the whole image."""
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        best = None
        lo = self.shell_area_m2 / self.area_tolerance
        hi = self.shell_area_m2 * self.area_tolerance
        for c in contours:
            if len(c) < 5:
                continue
            hull = cv2.convexHull(c)
            hull_area_px = cv2.contourArea(hull)
            if hull_area_px < 4:
                continue
            hull_m = self.homography.to_arena(hull.reshape(-1, 2) + off).astype(np.float32)
            area_m2 = cv2.contourArea(hull_m)
            if not lo <= area_m2 <= hi:
                continue
            solidity = cv2.contourArea(c) / hull_area_px
            if solidity < self.min_solidity:
                continue
            (_, _), (rw, rh), _ = cv2.minAreaRect(hull_m)
            if min(rw, rh) <= 0 or max(rw, rh) / min(rw, rh) > 2.0:
                continue
            if best is None or area_m2 > best[0]:
                best = (area_m2, c, hull, hull_m)
        if best is None:
            return None
        _, contour, hull, hull_m = best
        bx, by, bw, bh = cv2.boundingRect(contour)
        if (inner[0] and bx == 0) or (inner[1] and by == 0) or \
                (inner[2] and bx + bw >= mask.shape[1]) or (inner[3] and by + bh >= mask.shape[0]):
            return None
        refined = self._top_face(mask, value, contour)
        if refined is not None:
            mask, hull = refined
            hull_m = self.homography.to_arena(hull.reshape(-1, 2) + off).astype(np.float32)
        m = cv2.moments(hull)
        u, v = m["m10"] / m["m00"] + off[0], m["m01"] / m["m00"] + off[1]
        x, y = (float(a) for a in self.homography.to_arena(np.array([u, v])))
        yaw = self._heading(mask, hull, hull_m, (x, y), robot, t_us, off)
        return Detection(int(t_us), robot, x, y, yaw, float(u), float(v), self.name)

    def _top_face(self, mask, value, contour):
        """Keep the brightest part of the blob: the lit shell top, not the shaded sides the
        perspective shows (they would pull the centroid outwards). Returns (mask, hull) or
        None when the blob has no such split."""
        x0, y0, w, h = cv2.boundingRect(contour)
        blob = np.zeros((h, w), np.uint8)
        cv2.drawContours(blob, [contour - np.array([x0, y0], np.int32)], -1, 255, cv2.FILLED)
        blob &= mask[y0:y0 + h, x0:x0 + w]
        # the value averaged over each pixel's 3x3 blob neighbours (not the mats around): sensor
        # noise on a dark or dimly lit shell would otherwise speckle the split between top and sides
        inside = (blob > 0).astype(np.float32)
        raw = value[y0:y0 + h, x0:x0 + w].astype(np.float32) * inside
        vals = cv2.blur(raw, (3, 3), borderType=cv2.BORDER_CONSTANT) / \
            np.maximum(cv2.blur(inside, (3, 3), borderType=cv2.BORDER_CONSTANT), 1e-6)
        thr = self.top_ratio * float(np.percentile(vals[blob > 0], 75))
        top = np.where(vals >= thr, blob, 0).astype(np.uint8)
        top = cv2.morphologyEx(top, cv2.MORPH_OPEN, self._kernel)
        cs, _ = cv2.findContours(top, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        if not cs:
            return None
        c = max(cs, key=cv2.contourArea)
        if cv2.contourArea(c) < 0.4 * cv2.contourArea(contour):
            return None
        out = np.zeros_like(mask)
        out[y0:y0 + h, x0:x0 + w] = top
        return out, cv2.convexHull(c + np.array([x0, y0], np.int32))

    def _heading(self, mask, hull, hull_m, xy, robot, t_us, off) -> float:
        # outline orientation in arena metres, modulo 90 degrees (square) / 180 (oblong)
        (_, _), (rw, rh), ang = cv2.minAreaRect(hull_m * np.float32(1000.0))
        axis = math.radians(ang) if rw >= rh else math.radians(ang + 90.0)
        square = abs(rw - rh) < 0.2 * max(rw, rh)
        cands = [axis + k * math.pi / 2 for k in range(4)] if square else [axis, axis + math.pi]
        hint = self._mark_direction(mask, hull, xy, off) if self.front_mark else None
        hist = self.history_.setdefault(robot, deque())
        hist.append((t_us, xy[0], xy[1]))
        while hist and hist[0][0] < t_us - self.motion_window_us:
            hist.popleft()
        source = "front_mark"
        if hint is None and len(hist) >= 2:
            dx, dy = hist[-1][1] - hist[0][1], hist[-1][2] - hist[0][2]
            if math.hypot(dx, dy) >= self.motion_min_m:
                hint, source = math.atan2(dy, dx), "motion"
        if hint is None:
            self.heading_sources["unknown"] += 1
            return float("nan")
        self.heading_sources[source] += 1
        best = min(cands, key=lambda a: abs(_wrap(a - hint)))
        return _wrap(best)

    def _mark_direction(self, mask, hull, xy, off) -> float | None:
        """Direction (rad, arena) from the blob centre to the front mark, if one is seen."""
        x0, y0, w, h = cv2.boundingRect(hull)
        filled = np.zeros((h, w), np.uint8)
        cv2.fillConvexPoly(filled, hull.reshape(-1, 2) - (x0, y0), 255)
        hole = cv2.bitwise_and(filled, cv2.bitwise_not(mask[y0:y0 + h, x0:x0 + w]))
        hole = cv2.erode(hole, self._kernel)   # drop slivers along the outline
        n, _, stats, cents = cv2.connectedComponentsWithStats(hole)
        if n < 2:
            return None
        k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        if stats[k, cv2.CC_STAT_AREA] < max(3, 0.03 * w * h):
            return None
        mu, mv = cents[k] + (x0, y0) + off
        mx, my = self.homography.to_arena(np.array([mu, mv]))
        dx, dy = mx - xy[0], my - xy[1]
        if math.hypot(dx, dy) < 0.01:     # a hole in the middle is not a front mark
            return None
        return math.atan2(dy, dx)


def _scaled_value(rng: HsvRange, k: float) -> HsvRange:
    """``rng`` with its V bounds scaled by ``k`` (an open top, V >= 250, stays open)."""
    lo_v = int(round(rng.lo[2] * k))
    hi_v = rng.hi[2] if rng.hi[2] >= 250 else min(255, max(lo_v, int(round(rng.hi[2] * k))))
    return HsvRange((rng.lo[0], rng.lo[1], lo_v), (rng.hi[0], rng.hi[1], hi_v))


# ---------------------------------------------------------------------------- markers
class MarkerDetector:
    """ArUco marker detector: unique ids, position and heading without ambiguity.

    Args:
        ids: marker id -> robot name; ``None`` reports every id as ``"marker<id>"``.
        homography: pixel -> arena at marker height (the shell top); ``None`` for pixel
            measurements only (:meth:`centres_px`, e.g. to calibrate).
        dictionary: an OpenCV predefined dictionary id (default ``DICT_4X4_50``).
    """

    name = "aruco"

    def __init__(self, ids: dict[int, str] | None, homography: Homography | None,
                 dictionary: int = cv2.aruco.DICT_4X4_50):
        self.ids = None if ids is None else {int(k): str(v) for k, v in ids.items()}
        self.homography = homography
        params = cv2.aruco.DetectorParameters()
        # edge-line fits: on ~20 px markers they give ~4x better headings than SUBPIX corners
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_CONTOUR
        params.minMarkerPerimeterRate = 0.02
        self._det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(dictionary), params)

    def corners_px(self, frame: np.ndarray) -> list[tuple[int, np.ndarray]]:
        """Every marker in a BGR frame as ``(id, corners)``, corners (4, 2) px in the order
        top-left, top-right, bottom-right, bottom-left of the marker image."""
        _check_frame(frame)
        corners, ids, _ = self._det.detectMarkers(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY))
        if ids is None:
            return []
        return [(int(i), c.reshape(4, 2).astype(float)) for c, i in zip(corners, ids.ravel())]

    def centres_px(self, frame: np.ndarray) -> dict[int, tuple[float, float]]:
        """Image centre (u, v) px of each marker id: the intersection of the diagonals, which
        is the projection of the marker's centre under any perspective."""
        out = {}
        for i, c in self.corners_px(frame):
            h = np.column_stack([c, np.ones(4)])
            p = np.cross(np.cross(h[0], h[2]), np.cross(h[1], h[3]))
            if abs(p[2]) > 1e-12 and i not in out:
                out[i] = (float(p[0] / p[2]), float(p[1] / p[2]))
        return out

    def detect(self, frame: np.ndarray, t_us: int) -> list[Detection]:
        """Detect configured markers in a BGR frame captured at ``t_us`` (µs)."""
        if self.homography is None:
            raise ValueError("MarkerDetector.detect needs a homography (pixel -> arena)")
        out: dict[str, Detection] = {}
        for i, px in self.corners_px(frame):
            if self.ids is None:
                robot = f"marker{i}"
            elif i in self.ids:
                robot = self.ids[i]
            else:
                continue
            xy = self.homography.to_arena(px)
            x, y = xy.mean(0)
            front = 0.5 * (xy[0] + xy[1]) - 0.5 * (xy[2] + xy[3])
            yaw = math.atan2(front[1], front[0])
            u, v = self.homography.to_pixel(np.array([x, y]))
            det = Detection(int(t_us), robot, float(x), float(y), _wrap(yaw), float(u), float(v), self.name)
            if robot not in out:        # a duplicate id keeps its first (most confident) hit
                out[robot] = det
        return list(out.values())


def _check_frame(frame) -> None:
    if not isinstance(frame, np.ndarray) or frame.ndim != 3 or frame.shape[2] != 3 or frame.dtype != np.uint8:
        raise ValueError("frame must be a BGR uint8 image of shape (h, w, 3)")


def annotate(frame: np.ndarray, dets: list[Detection], homography: Homography | None = None) -> np.ndarray:
    """A copy of ``frame`` with each detection's centre, name and (given the homography)
    a 6 cm heading arrow drawn."""
    img = frame.copy()
    for d in dets:
        p = (int(round(d.u_px)), int(round(d.v_px)))
        cv2.circle(img, p, 3, (0, 0, 255), -1, cv2.LINE_AA)
        if homography is not None and not math.isnan(d.yaw_rad):
            tip = homography.to_pixel(np.array([d.x_m + 0.06 * math.cos(d.yaw_rad),
                                                d.y_m + 0.06 * math.sin(d.yaw_rad)]))
            cv2.arrowedLine(img, p, (int(round(tip[0])), int(round(tip[1]))), (0, 0, 255), 1,
                            cv2.LINE_AA, tipLength=0.3)
        cv2.putText(img, d.robot, (p[0] + 6, p[1] - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                    (0, 0, 255), 1, cv2.LINE_AA)
    return img

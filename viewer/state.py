"""The viewer's model: everything the page shows, updated from decoded arena messages.

Thread-safe (one lock): Zenoh callbacks call the ``on_*`` methods, the HTTP server calls
:meth:`ViewerState.snapshot` and :meth:`ViewerState.render_frame`. Frames: arena ``(x, y)`` m,
yaw counter-clockwise from +x; sensor ``(u, v)`` px (u column right, v row down).
"""

from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from arena import codec
from arena.homography import CalibrationError, calibration_points, fit_homography
from arena.messages import EventWindow, GroundTruthPose, Status, Telemetry, Track
from arena.timematch import NO_OVERLAP, PoseHistory, timed_error

#: Display colours (RGB) as in the paper: ON (positive) black, OFF (negative) blue, no event white.
ON_RGB = (0, 0, 0)
OFF_RGB = (0, 0, 255)
BACKGROUND_RGB = (255, 255, 255)
#: Colours of the index image of :meth:`ViewerState.render_index`: 0 no event, 1 ON, 2 OFF.
PALETTE = np.array([BACKGROUND_RGB, ON_RGB, OFF_RGB], np.uint8)


class ViewerConfigError(ValueError):
    """A calibration the viewer cannot use (the message says what is wrong)."""


def arena_to_pixel_homography(calibration: dict) -> np.ndarray:
    """3x3 homography arena m -> sensor px fitted to a calibration dict
    (``{"image_size": [w, h], "points": [{"pixel": [u, v], "arena_m": [x, y]}, ...]}``, >= 4 points)."""
    try:
        px, am = calibration_points(calibration)
        return fit_homography(am, px)
    except CalibrationError as exc:
        raise ViewerConfigError(str(exc)) from None


def project(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Apply homography ``H`` to (n, 2) points."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    h = np.c_[xy, np.ones(len(xy))] @ H.T
    return h[:, :2] / h[:, 2:3]


@dataclass
class _TrackView:
    msg: Track
    seen: float  # monotonic s
    latency_ms: float | None = None  # edge publish of the slice -> received here (wall clocks)
    trail_m: deque = field(default_factory=lambda: deque(maxlen=300))
    trail_px: deque = field(default_factory=lambda: deque(maxlen=300))
    hist_sensor: PoseHistory = field(default_factory=PoseHistory)  # by stamp_us
    hist_host: PoseHistory = field(default_factory=PoseHistory)  # by host_ns // 1000, when known

    def add(self, msg: Track) -> None:
        self.hist_sensor.add(msg.stamp_us, msg.x, msg.y)
        if msg.host_ns is not None:
            self.hist_host.add(msg.host_ns // 1000, msg.x, msg.y)


@dataclass
class _GtView:
    msg: GroundTruthPose
    seen: float  # monotonic s
    hist: PoseHistory = field(default_factory=PoseHistory)  # by the poses' own stamps


@dataclass
class _Window:
    t_end_us: int
    msg: EventWindow
    events: tuple[np.ndarray, np.ndarray] | None = None  # (flat pixel index, palette index), once decoded


def _r(v: float | None, nd: int = 4) -> float | None:
    return None if v is None else round(float(v), nd)


class ViewerState:
    """What the page shows.

    ``camera``: the camera whose events are drawn (None: the first one seen). ``accumulate_us``:
    the event image shows the windows whose end lies in the last ``accumulate_us`` µs of sensor
    time. ``H_arena_to_px``: homography used to draw tracks that carry no ``u_px``/``v_px``.
    ``robot_size_m``: (length, width) of the boxes drawn around tracks. Tracks and ground-truth
    poses not updated for ``track_timeout_s`` are dropped. One entry per track: when a track
    (camera, track id) shows up on another key (``arena/robots/3`` becomes ``arena/robots/zumo1``
    once it is named), its entry moves to that key. Each named track's ``error_m`` compares the
    robot's ground-truth pose with the track interpolated at that pose's stamp, on the clock
    ``gt_clock`` (see :func:`timed_error`). ``clock``: monotonic seconds (tests pass their own).

    Bounds whatever the publishers send: at most ``max_tracks`` tracks, and as many ground-truth
    robots, telemetry robots and service statuses, are kept (beyond that the least recently
    updated goes, counted in ``counts["evicted"]``); each update costs the same however many are
    kept. The event image is at most ``max_image_side`` px wide and high: a larger sensor is
    shown downsampled by the smallest integer factor that fits (``image.scale`` in the
    snapshot; the overlay stays in sensor px), so a window declaring a 65535 x 65535 px sensor
    costs no more memory than a real one. The image draws at most ``max_window_events`` events
    of a window (a window of more, such as a valid 9 KB window of 10 M events, is subsampled
    deterministically: one event of each run of k in its order, the smallest k that fits;
    counted in ``counts["subsampled"]``) and at most ``max_events`` in all (the oldest windows go first, by
    the events they declare, so the decoding a render needs is bounded too); ``image.drawn`` in
    the snapshot is the number of events the latest render drew.
    """

    def __init__(self, camera: str | None = None, accumulate_us: int = 100_000,
                 H_arena_to_px: np.ndarray | None = None, arena_size_m: tuple[float, float] = (1.83, 1.83),
                 robot_size_m: tuple[float, float] = (0.10, 0.10), telemetry_len: int = 200,
                 track_timeout_s: float = 3.0, status_timeout_s: float = 5.0,
                 max_windows: int = 1000, max_events: int = 4_000_000, gt_clock: str = "auto",
                 max_tracks: int = 200, max_image_side: int = 2048, max_window_events: int = 1_000_000,
                 clock: Callable[[], float] = time.monotonic):
        self.camera = camera
        self.accumulate_us = int(accumulate_us)
        self.H = H_arena_to_px
        self.arena_size_m = tuple(arena_size_m)
        self.robot_size_m = tuple(robot_size_m)
        self.telemetry_len = telemetry_len
        self.track_timeout_s = track_timeout_s
        self.status_timeout_s = status_timeout_s
        if gt_clock not in ("auto", "sensor", "host"):
            raise ViewerConfigError(f"gt_clock must be 'auto', 'sensor' or 'host', got {gt_clock!r}")
        self.gt_clock = gt_clock
        if max_tracks < 1 or max_image_side < 1 or max_window_events < 1 or max_events < 1:
            raise ViewerConfigError("max_tracks, max_image_side, max_window_events and max_events must be >= 1")
        self.max_tracks, self.max_image_side = int(max_tracks), int(max_image_side)
        self._now = clock
        self._lock = threading.Lock()
        self._windows: deque[_Window] = deque()
        #: bounds of the accumulated image whatever the windows' times say (a flood of windows
        #: with one end time, or a camera stamping 1 µs windows): the oldest go first
        self.max_windows, self.max_events = int(max_windows), int(max_events)
        self._n_events = 0
        #: events drawn of one window: a window declaring more is subsampled (never more than the total)
        self.max_window_events = min(int(max_window_events), self.max_events)
        self._drawn = 0                     # events the latest render drew (a gauge)
        self._render_lock = threading.Lock()  # one render at a time: a window is decoded once
        self._size: tuple[int, int] | None = None
        self._cam_info: dict = {}
        # least recently updated first (updates move an entry to the end): expiry and eviction
        # take from the front, O(1) per update
        self._tracks: OrderedDict[str, _TrackView] = OrderedDict()
        self._track_key: dict[tuple[str, int], str] = {}  # (camera, track id) -> its key in _tracks
        self._gt: OrderedDict[str, _GtView] = OrderedDict()
        self._telemetry: OrderedDict[str, dict[str, deque]] = OrderedDict()
        self._status: OrderedDict[tuple[str, str], tuple[Status, float]] = OrderedDict()
        self._alive: OrderedDict[tuple[str, str], None] = OrderedDict()
        self.counts = {"windows": 0, "tracks": 0, "groundtruth": 0, "telemetry": 0, "status": 0, "bad": 0,
                       "bad_keys": 0, "evicted": 0, "subsampled": 0}
        self.frame_no = 0

    # -- inputs -------------------------------------------------------------------------------
    def on_window(self, msg: EventWindow) -> None:
        """Add an event window (ignored unless it is from the viewed camera)."""
        with self._lock:
            if self.camera is None:
                self.camera = msg.camera
            if msg.camera != self.camera:
                return
            self.counts["windows"] += 1
            if self._windows and (msg.t_end_us < self._windows[-1].t_end_us - self.accumulate_us
                                  or (msg.width, msg.height) != self._size):
                # sensor time went back (a restarted camera or a looping replay) or the sensor size
                # changed: the windows kept belong to another image
                self._windows.clear()
                self._n_events = 0
            self._windows.append(_Window(msg.t_end_us, msg))
            self._n_events += msg.count
            self._size = (msg.width, msg.height)
            self._cam_info = {"camera": msg.camera, "seq": msg.seq, "t_end_us": msg.t_end_us,
                              "dropped": msg.dropped, "codec": msg.codec}
            oldest = msg.t_end_us - self.accumulate_us
            while self._windows and (self._windows[0].t_end_us <= oldest or len(self._windows) > self.max_windows
                                     or (self._n_events > self.max_events and len(self._windows) > 1)):
                self._n_events -= self._windows.popleft().msg.count

    def on_track(self, key: str, msg: Track) -> None:
        """Add a track update received on ``key``."""
        now = self._now()
        with self._lock:
            self.counts["tracks"] += 1
            self._expire(now)
            ident = (msg.camera, msg.track_id)
            tv = self._tracks.get(key)
            # the same track under another key (numbered before it was named, or the other way
            # round): one entry per track, the newest key's, which keeps the trail and history
            other = self._track_key.get(ident)
            if other is not None and other != key:
                moved = self._tracks.pop(other, None)
                if tv is None and moved is not None:
                    tv = self._tracks[key] = moved
            if tv is None:
                tv = self._tracks[key] = _TrackView(msg, now)
            else:
                old = (tv.msg.camera, tv.msg.track_id)
                if old != ident and self._track_key.get(old) == key:
                    del self._track_key[old]  # this key now shows another track
            self._track_key[ident] = key
            self._tracks.move_to_end(key)
            while len(self._tracks) > self.max_tracks:
                self._drop_track(next(iter(self._tracks)))
                self.counts["evicted"] += 1
            tv.msg, tv.seen = msg, now
            edge_ns = msg.edge_publish_ns or msg.tracker_publish_ns
            tv.latency_ms = (time.time_ns() - edge_ns) / 1e6 if edge_ns else None
            tv.trail_m.append((round(msg.x, 4), round(msg.y, 4)))
            tv.add(msg)
            uv = self._track_pixel(msg)
            if uv is not None:
                tv.trail_px.append(uv)

    def on_groundtruth(self, msg: GroundTruthPose) -> None:
        """Add a ground-truth pose."""
        now = self._now()
        with self._lock:
            self.counts["groundtruth"] += 1
            self._expire(now)
            gv = self._gt.get(msg.robot)
            if gv is None:
                gv = self._gt[msg.robot] = _GtView(msg, now)
                self._bound(self._gt)
            self._gt.move_to_end(msg.robot)
            gv.msg, gv.seen = msg, now
            gv.hist.add(msg.stamp_us, msg.x, msg.y)

    def _expire(self, now: float) -> None:
        """Drop the tracks and ground-truth poses not updated for ``track_timeout_s`` (lock held;
        both are ordered by update, so this looks only at the expired ones and the next)."""
        while self._tracks:
            key, tv = next(iter(self._tracks.items()))
            if now - tv.seen <= self.track_timeout_s:
                break
            self._drop_track(key)
        while self._gt:
            robot, gv = next(iter(self._gt.items()))
            if now - gv.seen <= self.track_timeout_s:
                break
            del self._gt[robot]

    def _drop_track(self, key: str) -> None:
        tv = self._tracks.pop(key)
        ident = (tv.msg.camera, tv.msg.track_id)
        if self._track_key.get(ident) == key:
            del self._track_key[ident]

    def _bound(self, table: OrderedDict) -> None:
        """Evict the least recently updated entries of ``table`` beyond ``max_tracks`` (lock held)."""
        while len(table) > self.max_tracks:
            table.popitem(last=False)
            self.counts["evicted"] += 1

    def on_telemetry(self, msg: Telemetry) -> None:
        """Add a telemetry sample (kept: wheel speeds m/s, gyro z rad/s, battery mV)."""
        with self._lock:
            self.counts["telemetry"] += 1
            h = self._telemetry.get(msg.robot)
            if h is None:
                h = self._telemetry[msg.robot] = {k: deque(maxlen=self.telemetry_len) for k in
                                                  ("speed_left", "speed_right", "gyro_z", "battery_mv")}
                self._bound(self._telemetry)
            self._telemetry.move_to_end(msg.robot)
            h["speed_left"].append(round(msg.speed_left, 4))
            h["speed_right"].append(round(msg.speed_right, 4))
            h["gyro_z"].append(round(msg.gyro[2], 4))
            h["battery_mv"].append(msg.battery_mv)

    def on_status(self, msg: Status) -> None:
        """Add a service status."""
        with self._lock:
            self.counts["status"] += 1
            self._status[(msg.role, msg.name)] = (msg, self._now())
            self._status.move_to_end((msg.role, msg.name))
            self._bound(self._status)

    def on_alive(self, role: str, name: str, alive: bool) -> None:
        """A liveliness token appeared (``alive``) or disappeared."""
        with self._lock:
            if alive:
                self._alive[(role, name)] = None
                self._alive.move_to_end((role, name))
                self._bound(self._alive)
            else:
                self._alive.pop((role, name), None)

    def on_bad(self) -> int:
        """Count a payload that was not a valid arena message (or not the one its key carries);
        returns the count so far."""
        with self._lock:
            self.counts["bad"] += 1
            return self.counts["bad"]

    def on_bad_key(self) -> int:
        """Count a sample or liveliness token on a key that is not a valid arena key; returns the
        count so far."""
        with self._lock:
            self.counts["bad_keys"] += 1
            return self.counts["bad_keys"]

    # -- outputs ------------------------------------------------------------------------------
    def track_count(self) -> int:
        """Number of tracks currently shown (updated within the last ``track_timeout_s``)."""
        now = self._now()
        with self._lock:
            return sum(1 for t in self._tracks.values() if now - t.seen <= self.track_timeout_s)

    def _pixel(self, x: float, y: float, u: float | None, v: float | None) -> tuple[float, float] | None:
        if u is not None and v is not None:
            return (round(u, 1), round(v, 1))
        if self.H is not None:
            uv = project(self.H, [(x, y)])[0]
            return (round(float(uv[0]), 1), round(float(uv[1]), 1))
        return None

    def _track_pixel(self, m: Track) -> tuple[float, float] | None:
        """Pixel of a track in the viewed camera: its own ``u_px``/``v_px`` when it comes from that
        camera, else projected from arena metres."""
        own = not m.camera or self.camera is None or m.camera == self.camera
        return self._pixel(m.x, m.y, m.u_px if own else None, m.v_px if own else None)

    def _box_px(self, x: float, y: float, yaw: float | None, uv: tuple[float, float]) -> list | None:
        """Corners (px) of the robot's footprint; with no calibration, None."""
        if self.H is None:
            return None
        L, W = self.robot_size_m
        c, s = math.cos(yaw or 0.0), math.sin(yaw or 0.0)
        corners = [(x + c * dx - s * dy, y + s * dx + c * dy)
                   for dx, dy in ((L / 2, W / 2), (-L / 2, W / 2), (-L / 2, -W / 2), (L / 2, -W / 2))]
        pc = project(self.H, corners)
        centre = project(self.H, [(x, y)])[0]
        pc += np.asarray(uv) - centre  # centre the box on the tracked pixel
        return [[round(float(a), 1), round(float(b), 1)] for a, b in pc]

    def _heading_px(self, x: float, y: float, yaw: float | None, uv: tuple[float, float]) -> list | None:
        """End point (px) of a 0.1 m heading arrow from the track's pixel."""
        if yaw is None or self.H is None:
            return None
        a, b = project(self.H, [(x, y), (x + 0.1 * math.cos(yaw), y + 0.1 * math.sin(yaw))])
        d = b - a
        return [round(uv[0] + float(d[0]), 1), round(uv[1] + float(d[1]), 1)]

    def snapshot(self) -> dict:
        """Everything the page shows, as a JSON-able dict (sent by Server-Sent Events)."""
        now = self._now()
        with self._lock:
            self._expire(now)
            tracks = []
            for key, tv in sorted(self._tracks.items()):
                m = tv.msg
                uv = self._track_pixel(m)
                speed = math.hypot(m.vx, m.vy) if m.vx is not None and m.vy is not None else None
                gv = self._gt.get(m.robot) if m.robot else None
                te = timed_error(tv.hist_sensor, tv.hist_host, gv.hist, self.gt_clock) if gv else None
                tracks.append({
                    "key": key, "id": m.track_id, "robot": m.robot, "label": m.robot or f"#{m.track_id}",
                    "x": _r(m.x), "y": _r(m.y), "yaw": _r(m.yaw), "speed": _r(speed), "state": m.state,
                    "n_events": m.n_events, "stamp_us": m.stamp_us, "uv": list(uv) if uv else None,
                    "box_px": self._box_px(m.x, m.y, m.yaw, uv) if uv else None,
                    "heading_px": self._heading_px(m.x, m.y, m.yaw, uv) if uv else None,
                    "trail_m": list(tv.trail_m), "trail_px": list(tv.trail_px), "age_s": round(now - tv.seen, 2),
                    "latency_ms": _r(tv.latency_ms, 1),
                    # ground truth of the track's robot vs the track at that pose's stamp (None: no
                    # ground truth of that robot; error_note says why there is no figure)
                    "error_m": _r(te.err_m) if te else None,
                    "error_note": None if te or gv is None else NO_OVERLAP,
                    "error_clock": te.clock if te else None,
                    "error_behind_ms": _r(te.behind_us / 1000, 1) if te else None,
                })
            gts = []
            for robot, gv in sorted(self._gt.items()):
                g = gv.msg
                gts.append({"robot": robot, "x": _r(g.x), "y": _r(g.y), "yaw": _r(g.yaw), "detector": g.detector,
                            # the pose's own u_px/v_px are the webcam's: project the metres instead
                            "uv": list(self._pixel(g.x, g.y, None, None) or []) or None})
            telemetry = {r: {k: list(v) for k, v in h.items()} for r, h in sorted(self._telemetry.items())}
            services = []
            for role, name in sorted(set(self._status) | set(self._alive)):
                st, seen = self._status.get((role, name), (None, None))
                services.append({
                    "role": role, "name": name, "alive": (role, name) in self._alive,
                    "state": st.state if st else None, "host": st.host if st else None,
                    "rates": {k: round(v, 1) for k, v in (st.rates if st else {}).items()
                              if isinstance(v, (int, float))},
                    "gauges": {k: (round(v, 3) if isinstance(v, float) else v)
                               for k, v in (st.gauges if st else {}).items()},
                    "errors": st.errors if st else None, "last_error": st.last_error if st else None,
                    "stale": seen is None or now - seen > self.status_timeout_s,
                })
            w, h = self._size or (0, 0)
            n_events = self._n_events
            return {
                "time_ns": time.time_ns(), "frame_no": self.frame_no,
                "image": {"width": w, "height": h, "scale": self._scale(w, h), "events": n_events,
                          "windows": len(self._windows), "drawn": self._drawn,
                          "accumulate_ms": self.accumulate_us / 1000, **self._cam_info},
                "calibrated": self.H is not None, "arena_size_m": list(self.arena_size_m),
                "tracks": tracks, "groundtruth": gts, "telemetry": telemetry, "services": services,
                "counts": dict(self.counts),
            }

    def _scale(self, w: int, h: int) -> int:
        """Downsampling factor of the event image of a ``w`` x ``h`` px sensor (1: full size)."""
        return max(1, -(-max(w, h) // self.max_image_side))

    def render_index(self) -> np.ndarray | None:
        """The accumulated event image as palette indices (H x W uint8, see :data:`PALETTE`: 0 no
        event, 1 ON, 2 OFF; the latest event of a pixel wins); None before the first window.
        A sensor wider or higher than ``max_image_side`` px is downsampled by the integer factor
        ``s`` of :meth:`_scale` (image ceil(H/s) x ceil(W/s), the latest event of each s x s block
        wins). Windows are decoded once, on first render."""
        with self._lock:
            if self._size is None:
                return None
            w, h = self._size
            wins = list(self._windows)
            self.frame_no += 1
        f = self._scale(w, h)
        wi, hi = -(-w // f), -(-h // f)
        flat = np.zeros(hi * wi, np.uint8)
        drawn = 0
        with self._render_lock:   # (concurrent renders would each decode the same new windows)
            for win in wins:
                if win.events is None:
                    win.events = self._decode(win.msg, w, h, f, wi)
                pos, colour = win.events
                flat[pos] = colour  # in time order: the latest event of a pixel wins
                drawn += pos.size
        with self._lock:
            self._drawn = drawn
        return flat.reshape(hi, wi)

    def _decode(self, msg: EventWindow, w: int, h: int, f: int, wi: int) -> tuple[np.ndarray, np.ndarray]:
        """A window's events as (flat pixel index, palette index), at most ``max_window_events``
        of them (one of each run of k in the window's order beyond that); none if it cannot be decoded."""
        try:
            ev = codec.decode(msg.codec, msg.data, msg.count)
        except codec.CodecError:
            self.on_bad()
            return np.empty(0, np.int32), np.empty(0, np.uint8)
        if ev.size > self.max_window_events:
            # one event of each run of k in the window's order (k the smallest that fits), at a
            # place in its run drawn from a generator seeded by the window's seq: deterministic,
            # in time order, and unlike every k-th event not in step with a regular pattern
            # (every other event of a scan would be every other column)
            k = -(-ev.size // self.max_window_events)
            starts = np.arange(0, ev.size, k)
            pick = starts + np.random.default_rng(abs(msg.seq)).integers(0, k, starts.size)
            ev = ev[np.minimum(pick, ev.size - 1)]
            with self._lock:
                self.counts["subsampled"] += 1
        xs, ys = ev["x"], ev["y"]
        inside = (xs < w) & (ys < h)
        xs, ys = xs[inside].astype(np.int32), ys[inside].astype(np.int32)  # 2048 x 2048 at most: int32 fits
        if f > 1:
            xs //= f
            ys //= f
        return ys * wi + xs, (2 - (ev["p"][inside] & 1)).astype(np.uint8)

    def render_frame(self) -> np.ndarray | None:
        """The accumulated event image (H x W x 3, RGB uint8): ON black, OFF blue, no event white;
        None before the first window."""
        index = self.render_index()
        return None if index is None else PALETTE[index]

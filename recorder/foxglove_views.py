"""Arena messages -> Foxglove well-known messages (pure: no Zenoh, files or clocks).

:class:`FoxgloveConverter` turns the samples ``arena record`` receives (a Zenoh key, the payload
bytes, the receive time) into messages of Foxglove's published schemas, protobuf-encoded with the
official generated classes (PyPI ``foxglove-schemas-protobuf``), so Foxglove's 3D panel shows the
robots moving over the event image. The same bytes go into the MCAP file (``arena record``) and
out of the live WebSocket server (``arena foxglove``).

Topics (none under ``arena/``, so ``arena replay`` never publishes them):

================================  ============================  ==========================================
topic                             schema                        content
================================  ============================  ==========================================
``foxglove/robots/<slot>/pose``   ``foxglove.PoseInFrame``      the track's pose in frame ``arena``
``foxglove/tf``                   ``foxglove.FrameTransforms``  ``arena`` -> ``robot/<slot>`` per update
``foxglove/robots/<slot>/scene``  ``foxglove.SceneUpdate``      box, heading arrow and label of the robot
``foxglove/arena``                ``foxglove.SceneUpdate``      the arena outline (once a second)
``foxglove/events/<cam>/image``   ``foxglove.CompressedImage``  accumulated event image (PNG), frame ``<cam>``
``foxglove/events/<cam>/points``  ``foxglove.PointCloud``       the same event pixels placed in the arena
                                                                (frame ``arena``; only with a calibration)
================================  ============================  ==========================================

**Slots** (the ``<slot>`` of a robot's topics and frame): a track keeps the slot of the first
identity it was seen with, so its topics never change when the tracker names it: a track first
seen unnamed is ``track-<id>``; one first seen named is its name. A name that arrives later
relabels the box (the ``TextPrimitive``) but not the topic, and is remembered: a later track first
seen with that name (the robot re-acquired under a new track id) reuses the slot the name first
appeared on. So within one recording each robot has one set of topics unless it was lost and
found again unnamed.

Frames: ``arena`` (the arena floor, x/y in metres from the mat corner, z up), ``robot/<slot>``
(x forward along the heading), ``<camera>`` (the event image, pixels; not placed in 3D). Message
timestamps are the sender's wall-clock publish time (``tracker_publish_ns``, ``publish_ns``),
else the receive time: the same clock as the MCAP log times, so transforms and entities line up.
"""

from __future__ import annotations

import functools
import math
from collections import deque
from dataclasses import dataclass, field

import cv2
import numpy as np
from foxglove_schemas_protobuf.ArrowPrimitive_pb2 import ArrowPrimitive
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.CubePrimitive_pb2 import CubePrimitive
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.Point3_pb2 import Point3
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.TextPrimitive_pb2 import TextPrimitive
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.descriptor_pb2 import FileDescriptorSet
from google.protobuf.duration_pb2 import Duration
from google.protobuf.timestamp_pb2 import Timestamp

from arena import codec
from arena.homography import calibration_points, fit_homography
from arena.keys import InvalidKey, parse_key
from arena.messages import CONFIRMED, EventWindow, MessageError, Track

__all__ = ["ARENA_FRAME", "MAX_IMAGE_PIXELS", "FoxgloveMessage", "FoxgloveConverter", "RobotShape",
           "calibration_sizes", "pixel_to_arena_homography", "quaternion_from_yaw", "robot_frame", "schema_data", "SCHEMAS", "TOPIC_PREFIX"]

ARENA_FRAME = "arena"
TOPIC_PREFIX = "foxglove/"
TF_TOPIC = "foxglove/tf"
ARENA_TOPIC = "foxglove/arena"

#: the message classes used, by schema name
SCHEMAS = {cls.DESCRIPTOR.full_name: cls
           for cls in (PoseInFrame, FrameTransforms, SceneUpdate, CompressedImage, PointCloud)}

_ON_RGB = (0, 0, 0)         # event image palette, as `arena view`: ON black, OFF blue, none white
_OFF_RGB = (30, 60, 200)
_NONE_RGB = (255, 255, 255)
#: largest event image (px) a view is made of (2048 x 2048; see FoxgloveConverter)
MAX_IMAGE_PIXELS = 1 << 22
#: most compressed event bytes kept per camera for its image (the newest windows are kept)
MAX_KEPT_BYTES = 64 << 20
# PNG of a mostly white image: no row filter and run-length matching are 3-4x faster than
# OpenCV's defaults (6 vs 22 ms for 640 x 480) and smaller (10 vs 21 kB)
_PNG_PARAMS = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE]
if hasattr(cv2, "IMWRITE_PNG_FILTER"):  # OpenCV >= 4.10
    _PNG_PARAMS += [cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_NONE]


@functools.cache
def schema_data(name: str) -> bytes:
    """The serialized ``FileDescriptorSet`` of schema ``name`` (e.g. ``foxglove.PoseInFrame``) and
    every file it imports, dependencies first: the MCAP/WebSocket schema data of a protobuf channel."""
    fds = FileDescriptorSet()
    seen: set[str] = set()

    def add(fd) -> None:
        for dep in fd.dependencies:
            if dep.name not in seen:
                seen.add(dep.name)
                add(dep)
        fd.CopyToProto(fds.file.add())

    add(SCHEMAS[name].DESCRIPTOR.file)
    return fds.SerializeToString()


def quaternion_from_yaw(yaw: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of the rotation by ``yaw`` rad about +z (counter-clockwise seen from above)."""
    return 0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0)


def robot_frame(slot: str) -> str:
    """Frame id of the robot on ``slot``."""
    return f"robot/{slot}"


def pixel_to_arena_homography(calibration: dict) -> np.ndarray:
    """3x3 homography sensor px -> arena m fitted to a calibration dict
    (``{"image_size": [w, h], "points": [{"pixel": [u, v], "arena_m": [x, y]}, ...]}``, >= 4 points).
    Raises :class:`arena.homography.CalibrationError` (a ValueError) with what is wrong."""
    px, am = calibration_points(calibration)
    return fit_homography(px, am)


@dataclass(frozen=True)
class RobotShape:
    """A robot's box: ``length_m`` along its heading, ``width_m`` across, ``height_m``; RGB 0-255."""

    length_m: float = 0.10
    width_m: float = 0.10
    height_m: float = 0.05
    color_rgb: tuple[int, int, int] = (110, 110, 110)


@dataclass(frozen=True)
class FoxgloveMessage:
    """One Foxglove message: topic, schema name (``foxglove.X``), protobuf bytes, times (ns)."""

    topic: str
    schema: str
    data: bytes
    log_time_ns: int
    publish_time_ns: int


@dataclass
class _Camera:
    width: int = 0
    height: int = 0
    windows: deque = field(default_factory=lambda: deque(maxlen=1000))   # recent EventWindows, oldest first
    next_frame_us: int | None = None
    blank: np.ndarray | None = None          # an image without events (BGR), copied for each image


def _ts(ns: int) -> Timestamp:
    return Timestamp(seconds=ns // 1_000_000_000, nanos=ns % 1_000_000_000)


def _color(rgb, a: float = 1.0) -> Color:
    return Color(r=rgb[0] / 255.0, g=rgb[1] / 255.0, b=rgb[2] / 255.0, a=a)


class FoxgloveConverter:
    """Convert arena samples into :class:`FoxgloveMessage` lists (see the module doc for topics).

    ``arena_size_m``: (x, y) of the arena outline; ``robots``: box shape per robot name (others get
    ``default_robot``); ``image_period_us``: sensor time between two event images (250 000: 4 Hz);
    ``accumulate_us``: sensor time one image shows; ``pixel_to_arena``: camera name -> 3x3
    homography px -> arena m (``"*"`` for any camera), which adds the placed point cloud;
    ``lifetime_s``: how long a robot's box stays after its last update; ``max_rate_hz``: at most
    this many updates a second per robot (receive time; the tracker publishes ~100: Foxglove needs
    fewer, and the full-rate poses stay on ``arena/robots/*``); an update that changes the robot's
    name or state is always converted.

    **Bounded cost of the event image.** What a window makes the view allocate depends only on the
    size it declares, so the view is made only for a window of a plausible sensor: ``sensor_sizes``
    (camera name -> (width, height), ``"*"`` for any camera; :func:`calibration_sizes` of the
    calibrations) renders a camera only at its calibrated size, and no view is larger than
    ``max_image_pixels`` (default 4 Mpx, 2048 x 2048: every event camera sold today is at most
    1280 x 960). Another window gets no view: counted in ``skipped``, its reason added to
    ``notes`` once per camera and size (the caller logs them). The placed points are computed for the
    event pixels only, never for every pixel of the sensor.

    Bad samples are counted in ``rejected`` (and the last reason kept in ``last_error``), never raised.
    """

    def __init__(self, arena_size_m: tuple[float, float] = (1.83, 1.83), robots: dict[str, RobotShape] | None = None,
                 default_robot: RobotShape = RobotShape(), image_period_us: int = 250_000,
                 accumulate_us: int = 100_000, pixel_to_arena: dict[str, np.ndarray] | None = None,
                 lifetime_s: float = 1.0, outline_period_ns: int = 1_000_000_000, max_rate_hz: float = 30.0,
                 sensor_sizes: dict[str, tuple[int, int]] | None = None,
                 max_image_pixels: int = MAX_IMAGE_PIXELS):
        if image_period_us <= 0 or accumulate_us <= 0:
            raise ValueError("image_period_us and accumulate_us must be > 0")
        if max_image_pixels < 1:
            raise ValueError("max_image_pixels must be >= 1")
        self.sensor_sizes = {k: (int(v[0]), int(v[1])) for k, v in (sensor_sizes or {}).items()}
        self.max_image_pixels = int(max_image_pixels)
        self.skipped = 0                    # windows recorded but given no view (size; see the class doc)
        self.notes: list[str] = []          # why, once per camera and size; the caller empties it
        self._skip_seen: set[tuple[str, int, int]] = set()
        self.arena_size_m = (float(arena_size_m[0]), float(arena_size_m[1]))
        self.robots = dict(robots or {})
        self.default_robot = default_robot
        self.image_period_us = int(image_period_us)
        self.accumulate_us = int(accumulate_us)
        self.pixel_to_arena = dict(pixel_to_arena or {})
        self.lifetime_ns = int(lifetime_s * 1e9)
        self.outline_period_ns = int(outline_period_ns)
        self.min_interval_ns = int(1e9 / max_rate_hz) if max_rate_hz > 0 else 0
        self._last_update: dict[str, tuple[int, str | None, str]] = {}   # slot -> (log ns, name, state)
        self.rejected = 0
        self.last_error = ""
        self._slot_of_track: dict[int, str] = {}
        self._slot_of_name: dict[str, str] = {}
        self._cameras: dict[str, _Camera] = {}
        self._last_outline_ns: int | None = None

    # ------------------------------------------------------------------ entry point

    def convert(self, key: str, payload: bytes, log_time_ns: int) -> list[FoxgloveMessage]:
        """The Foxglove messages derived from one sample received on ``key`` at ``log_time_ns``
        (host wall clock, ns): three per track update, an image (and point cloud) when the
        camera's sensor time passed the next frame, the arena outline once a second."""
        out: list[FoxgloveMessage] = []
        if self._last_outline_ns is None or log_time_ns - self._last_outline_ns >= self.outline_period_ns:
            self._last_outline_ns = log_time_ns
            out.append(self.outline(log_time_ns))
        try:
            kind = parse_key(key).kind
        except InvalidKey:
            return out      # not an arena key with a Foxglove view (status, cmd...): nothing to add
        try:
            if kind == "robots":
                out += self.track(Track.decode(payload), log_time_ns)
            elif kind == "events":
                out += self.window(EventWindow.decode(payload), log_time_ns)
        except (MessageError, codec.CodecError) as exc:
            self.rejected += 1
            self.last_error = f"{key}: {exc}"
        return out

    # ------------------------------------------------------------------ robots

    def slot(self, track: Track) -> str:
        """The topic slot of ``track`` (see the module doc: first identity seen, then kept)."""
        slot = self._slot_of_track.get(track.track_id)
        if slot is None:
            slot = self._slot_of_name.get(track.robot, track.robot) if track.robot else f"track-{track.track_id}"
            self._slot_of_track[track.track_id] = slot
        if track.robot and track.robot not in self._slot_of_name:
            self._slot_of_name[track.robot] = slot
        return slot

    def track(self, t: Track, log_time_ns: int) -> list[FoxgloveMessage]:
        """PoseInFrame, FrameTransforms and SceneUpdate of one track update (none when the robot's
        last one is less than 1 / ``max_rate_hz`` ago with the same name and state)."""
        slot = self.slot(t)
        last = self._last_update.get(slot)
        if (last is not None and last[1:] == (t.robot, t.state)
                and 0 <= log_time_ns - last[0] < self.min_interval_ns):
            return []
        self._last_update[slot] = (log_time_ns, t.robot, t.state)
        stamp_ns = t.tracker_publish_ns or log_time_ns
        ts = _ts(stamp_ns)
        yaw = t.yaw if t.yaw is not None else 0.0
        qx, qy, qz, qw = quaternion_from_yaw(yaw)
        q = Quaternion(x=qx, y=qy, z=qz, w=qw)
        pose = Pose(position=Vector3(x=t.x, y=t.y, z=0.0), orientation=q)
        shape = self.robots.get(t.robot, self.default_robot) if t.robot else self.default_robot
        frame = robot_frame(slot)
        msgs = []

        pif = PoseInFrame(timestamp=ts, frame_id=ARENA_FRAME, pose=pose)
        msgs.append(FoxgloveMessage(f"foxglove/robots/{slot}/pose", "foxglove.PoseInFrame",
                                    pif.SerializeToString(), log_time_ns, stamp_ns))
        tf = FrameTransforms(transforms=[FrameTransform(
            timestamp=ts, parent_frame_id=ARENA_FRAME, child_frame_id=frame,
            translation=Vector3(x=t.x, y=t.y, z=0.0), rotation=q)])
        msgs.append(FoxgloveMessage(TF_TOPIC, "foxglove.FrameTransforms", tf.SerializeToString(),
                                    log_time_ns, stamp_ns))

        alpha = 0.85 if t.state == CONFIRMED else 0.4
        h = shape.height_m
        entity = SceneEntity(
            timestamp=ts, frame_id=ARENA_FRAME, id=frame, frame_locked=False,
            lifetime=Duration(seconds=self.lifetime_ns // 1_000_000_000, nanos=self.lifetime_ns % 1_000_000_000),
            cubes=[CubePrimitive(pose=Pose(position=Vector3(x=t.x, y=t.y, z=h / 2), orientation=q),
                                 size=Vector3(x=shape.length_m, y=shape.width_m, z=h),
                                 color=_color(shape.color_rgb, alpha))],
            texts=[TextPrimitive(pose=Pose(position=Vector3(x=t.x, y=t.y, z=h + 0.04),
                                           orientation=Quaternion(w=1.0)),
                                 billboard=True, font_size=14.0, scale_invariant=True,
                                 color=_color((255, 255, 255)), text=t.robot or f"track {t.track_id}")])
        if t.yaw is not None:  # no heading known yet: no arrow
            entity.arrows.append(ArrowPrimitive(
                pose=Pose(position=Vector3(x=t.x, y=t.y, z=h + 0.005), orientation=q),
                shaft_length=0.6 * shape.length_m, shaft_diameter=0.012, head_length=0.35 * shape.length_m,
                head_diameter=0.03, color=_color((230, 40, 40))))
        msgs.append(FoxgloveMessage(f"foxglove/robots/{slot}/scene", "foxglove.SceneUpdate",
                                    SceneUpdate(entities=[entity]).SerializeToString(), log_time_ns, stamp_ns))
        return msgs

    def outline(self, log_time_ns: int) -> FoxgloveMessage:
        """The arena outline: a closed line around the floor, in frame ``arena``."""
        w, h = self.arena_size_m
        line = LinePrimitive(type=LinePrimitive.LINE_LOOP, pose=Pose(orientation=Quaternion(w=1.0)),
                             thickness=0.01, scale_invariant=False,
                             points=[Point3(x=0.0, y=0.0), Point3(x=w, y=0.0), Point3(x=w, y=h), Point3(x=0.0, y=h)],
                             color=_color((40, 160, 60)))
        label = TextPrimitive(pose=Pose(position=Vector3(x=0.0, y=-0.05), orientation=Quaternion(w=1.0)),
                              billboard=True, font_size=12.0, scale_invariant=True, color=_color((40, 160, 60)),
                              text=f"arena {w:g} x {h:g} m")
        entity = SceneEntity(timestamp=_ts(log_time_ns), frame_id=ARENA_FRAME, id="arena", lines=[line],
                             texts=[label])
        return FoxgloveMessage(ARENA_TOPIC, "foxglove.SceneUpdate", SceneUpdate(entities=[entity]).SerializeToString(),
                               log_time_ns, log_time_ns)

    # ------------------------------------------------------------------ event images

    def window(self, w: EventWindow, log_time_ns: int) -> list[FoxgloveMessage]:
        """Keep the window; once the camera's sensor time reaches the next frame, the accumulated
        image of the last ``accumulate_us`` (and its placed point cloud, with a calibration).
        A window whose size is not its camera's calibrated size, or above ``max_image_pixels``,
        gets no view (counted in ``skipped``; see the class doc)."""
        why = self._no_view_reason(w)
        if why is not None:
            self.skipped += 1
            if (w.camera, w.width, w.height) not in self._skip_seen and len(self._skip_seen) < 1000:
                self._skip_seen.add((w.camera, w.width, w.height))
                self.notes.append(f"no Foxglove view of {w.camera}'s {w.width} x {w.height} px windows: {why} "
                                  f"(the windows are recorded; said once per camera and size)")
            return []
        cam = self._cameras.get(w.camera)
        if cam is None or (cam.width, cam.height) != (w.width, w.height):
            cam = self._cameras[w.camera] = _Camera(w.width, w.height)
        cam.windows.append(w)
        while cam.windows and cam.windows[0].t_end_us <= w.t_end_us - self.accumulate_us:
            cam.windows.popleft()
        kept = sum(len(x.data) for x in cam.windows)
        while len(cam.windows) > 1 and kept > MAX_KEPT_BYTES:   # the image shows the newest only
            kept -= len(cam.windows.popleft().data)
        if cam.next_frame_us is None:
            cam.next_frame_us = w.t_end_us
        if w.t_end_us < cam.next_frame_us:
            if cam.next_frame_us - w.t_end_us > 10 * self.image_period_us:  # the sensor clock restarted
                cam.windows.clear()
                cam.windows.append(w)
                cam.next_frame_us = w.t_end_us
            else:
                return []
        cam.next_frame_us = w.t_end_us + self.image_period_us
        on, off = self._accumulate(cam, w.t_end_us)
        stamp_ns = w.publish_ns or log_time_ns
        out = [self._image(w.camera, cam, on, off, stamp_ns, log_time_ns)]
        H = self.pixel_to_arena.get(w.camera, self.pixel_to_arena.get("*"))
        if H is not None:
            out.append(self._points(w.camera, cam, H, on, off, stamp_ns, log_time_ns))
        return out

    def _no_view_reason(self, w: EventWindow) -> str | None:
        size = self.sensor_sizes.get(w.camera, self.sensor_sizes.get("*"))
        if size is not None and (w.width, w.height) != size:
            return f"its calibration is for {size[0]} x {size[1]} px"
        if w.width * w.height > self.max_image_pixels:
            return f"larger than {self.max_image_pixels} px"
        return None

    def _accumulate(self, cam: _Camera, t_end_us: int) -> tuple[np.ndarray, np.ndarray]:
        """Flat indices (row * width + column) of the ON pixels and of the OFF pixels with events in
        ``[t_end_us - accumulate_us, t_end_us)``; a pixel with both shows its latest polarity."""
        last = np.full(cam.width * cam.height, -1, np.int8)
        t0 = t_end_us - self.accumulate_us
        for w in cam.windows:
            ev = codec.decode(w.codec, w.data, w.count)
            ev = ev[(ev["t"] >= t0) & (ev["x"] < cam.width) & (ev["y"] < cam.height)]
            if ev.size:
                flat = ev["y"].astype(np.int64) * cam.width + ev["x"]
                last[flat] = (ev["p"] > 0).astype(np.int8)   # later events overwrite earlier ones
        return np.flatnonzero(last == 1), np.flatnonzero(last == 0)

    def _image(self, camera: str, cam: _Camera, on, off, stamp_ns: int, log_time_ns: int) -> FoxgloveMessage:
        if cam.blank is None:
            cam.blank = np.empty((cam.height * cam.width, 3), np.uint8)
            cam.blank[:] = _NONE_RGB[::-1]   # OpenCV writes BGR
        img = cam.blank.copy()
        img[off] = _OFF_RGB[::-1]
        img[on] = _ON_RGB[::-1]
        ok, png = cv2.imencode(".png", img.reshape(cam.height, cam.width, 3), _PNG_PARAMS)
        if not ok:  # pragma: no cover - OpenCV always encodes a uint8 image
            raise RuntimeError("PNG encoding failed")
        msg = CompressedImage(timestamp=_ts(stamp_ns), frame_id=camera, data=png.tobytes(), format="png")
        return FoxgloveMessage(f"foxglove/events/{camera}/image", "foxglove.CompressedImage",
                               msg.SerializeToString(), log_time_ns, stamp_ns)

    def _points(self, camera: str, cam: _Camera, H: np.ndarray, on, off, stamp_ns: int,
                log_time_ns: int) -> FoxgloveMessage:
        rec = np.zeros((on.size + off.size, 4), np.float32)   # x, y, z (float32), r, g, b, a (4 x uint8)
        rec[:on.size, :2] = _place(on, cam.width, H)        # only the event pixels: cost by events, not sensor
        rec[on.size:, :2] = _place(off, cam.width, H)
        rgba = rec[:, 3].view(np.uint32)
        rgba[:on.size] = _pack_rgba(_ON_RGB)
        rgba[on.size:] = _pack_rgba(_OFF_RGB)
        F = PackedElementField
        fields = [F(name="x", offset=0, type=F.FLOAT32), F(name="y", offset=4, type=F.FLOAT32),
                  F(name="z", offset=8, type=F.FLOAT32), F(name="red", offset=12, type=F.UINT8),
                  F(name="green", offset=13, type=F.UINT8), F(name="blue", offset=14, type=F.UINT8),
                  F(name="alpha", offset=15, type=F.UINT8)]
        msg = PointCloud(timestamp=_ts(stamp_ns), frame_id=ARENA_FRAME, pose=Pose(orientation=Quaternion(w=1.0)),
                         point_stride=16, fields=fields, data=rec.tobytes())
        return FoxgloveMessage(f"foxglove/events/{camera}/points", "foxglove.PointCloud",
                               msg.SerializeToString(), log_time_ns, stamp_ns)


def _place(flat: np.ndarray, width: int, H: np.ndarray) -> np.ndarray:
    """(n, 2) float32 arena m of the pixels at flat indices ``flat`` (row * ``width`` + column)."""
    v, u = np.divmod(flat.astype(np.int64), width)
    hom = np.stack([u, v, np.ones(u.size, np.int64)], axis=1).astype(np.float64) @ H.T
    return (hom[:, :2] / hom[:, 2:3]).astype(np.float32)


def calibration_sizes(calibrations: dict[str, dict]) -> dict[str, tuple[int, int]]:
    """camera name -> (width, height) of each calibration dict's ``image_size`` (when it has a valid one)."""
    out = {}
    for name, calib in calibrations.items():
        size = calib.get("image_size") if isinstance(calib, dict) else None
        if (isinstance(size, (list, tuple)) and len(size) == 2
                and all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in size)):
            out[name] = (int(size[0]), int(size[1]))
    return out


def _pack_rgba(rgb) -> np.uint32:
    """Bytes r, g, b, 255 in memory order, as one native uint32."""
    return np.frombuffer(bytes([rgb[0], rgb[1], rgb[2], 255]), np.uint32)[0]

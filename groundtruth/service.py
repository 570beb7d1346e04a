"""The ground-truth service: webcam frames -> robot poses on Zenoh, CSV and annotated frames.

One thin I/O layer around :mod:`groundtruth.rgb` (detectors) and :mod:`groundtruth.homography`:

* reads frames from a :class:`~groundtruth.rgb.FrameSource` (device index, file or URL),
  stamped at capture (µs, host clock for live sources);
* publishes each detection as a :class:`arena.messages.GroundTruthPose` on
  ``arena/groundtruth/<robot>`` (x, y in arena metres, yaw in rad or ``None`` when unknown,
  the pixel position, the detector name);
* writes the CSV ``t_us,robot,x_m,y_m,yaw_rad,u_px,v_px,detector`` and, on request, an
  annotated video (``.avi``/``.mp4``) or a PNG sequence (a directory);
* reports presence (``arena/alive/groundtruth/<name>``) and a status once a second with the
  counters ``frames``, ``detections``, ``published`` and the gauges ``fps``, ``detect_ms``,
  ``robots_seen``.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
import urllib.request
from pathlib import Path

import cv2
import numpy as np

from arena.formats.tables import GroundTruthCsvWriter
from arena.keys import groundtruth_key
from arena.messages import GroundTruthPose
from groundtruth.homography import CalibrationError, Homography, homography_from_calibration
from groundtruth.rgb import (WHITE_V, Detection, FrameSource, HsvDetector, HsvRange,
                             MarkerDetector, annotate, hsv_range_from_rgb)

log = logging.getLogger("groundtruth.service")


class SetupError(ValueError):
    """Bad user input for the service (calibration, robots, detector); the message says why."""


def load_calibration_any(source: str | dict) -> Homography:
    """A homography from a calibration dict, a JSON file path or an ``http(s)://`` URL
    (the simulator's webcam serves ``/calibration.json``)."""
    if isinstance(source, dict):
        cal = source
    elif str(source).startswith(("http://", "https://")):
        try:
            with urllib.request.urlopen(str(source), timeout=10) as r:
                cal = json.loads(r.read())
        except (OSError, ValueError) as e:
            raise CalibrationError(f"cannot fetch calibration from {source}: {e}") from None
    else:
        path = Path(source)
        try:
            cal = json.loads(path.read_text())
        except FileNotFoundError:
            raise CalibrationError(f"calibration file not found: {path}") from None
        except (OSError, ValueError) as e:
            raise CalibrationError(f"cannot read calibration {path}: {e}") from None
    return homography_from_calibration(cal)


def build_detector(kind: str, homography: Homography, robots=(), markers: dict[int, str] | None = None,
                   colours: dict[str, object] | None = None, front_mark: bool = True):
    """Make the detector ``kind`` (``"aruco"`` or ``"hsv"``).

    Args:
        robots: robot configs (objects with ``name``, ``marker_id``, ``color_rgb``,
            ``hsv_range``, ``length_m``, ``width_m``), e.g. ``LabConfig.robots``.
        markers: extra marker id -> robot name (overrides the configs).
        colours: extra robot name -> HSV range (``[[h,s,v],[h,s,v]]``) or RGB colour tuple.
        front_mark: the HSV detector looks for the shells' front marks.

    With no marker ids known the ArUco detector reports every marker as ``marker<id>``.
    Ranges made from a nominal colour (RGB) follow the mats' brightness (``white_v``, see
    :class:`~groundtruth.rgb.HsvDetector`); explicit HSV ranges are used as given.
    Raises :class:`SetupError` when the HSV detector has no robot colour to look for, or a
    colour given in ``colours`` cannot be told from the white mats (a config robot with such
    a colour is skipped with a warning).
    """
    robots = list(robots)
    if kind == "aruco":
        ids = {int(r.marker_id): r.name for r in robots if getattr(r, "marker_id", None) is not None}
        ids.update(markers or {})
        return MarkerDetector(ids or None, homography)
    if kind != "hsv":
        raise SetupError(f"unknown detector {kind!r}: use aruco or hsv")
    ranges: dict[str, HsvRange] = {}
    nominal: set[str] = set()
    for r in robots:
        try:
            if getattr(r, "hsv_range", None):
                ranges[r.name] = HsvRange.parse(r.hsv_range)
            else:
                ranges[r.name] = hsv_range_from_rgb(tuple(r.color_rgb))
                nominal.add(r.name)
        except ValueError as e:
            log.warning("robot %s skipped by the colour detector: %s", r.name, e)
    for name, c in (colours or {}).items():
        try:
            if isinstance(c, (list, tuple)) and len(c) == 3 and all(isinstance(v, int) for v in c):
                ranges[name] = hsv_range_from_rgb(tuple(c))
                nominal.add(name)
            else:
                ranges[name] = HsvRange.parse(c)
                nominal.discard(name)
        except ValueError as e:
            raise SetupError(f"robot {name}: {e}") from None
    if not ranges:
        raise SetupError("the hsv detector needs robot colours: give --lab with robots or --robot NAME=COLOUR")
    size = (0.10, 0.10)
    if robots:
        size = (float(robots[0].length_m), float(robots[0].width_m))
    return HsvDetector(ranges, homography, shell_size_m=size, front_mark=front_mark,
                       white_v=WHITE_V if nominal else None, relative=nominal)


def heading_note(detector) -> str:
    """How ``detector`` resolves headings, for the service's start line and docs."""
    if isinstance(detector, HsvDetector):
        how = "the dark front mark (window strip) on the shell, else the direction of motion" \
            if detector.front_mark else "the direction of motion (no front mark)"
        return f"colour blobs; heading modulo 90 deg from the shell outline, resolved by {how}"
    return "ArUco markers; heading from each marker's orientation"


def heading_counts(detector) -> str | None:
    """``headings: N from the front mark, M from motion, K unknown`` of an HSV detector so far."""
    c = getattr(detector, "heading_sources", None)
    if not c:
        return None
    return (f"headings: {c['front_mark']} from the front mark, {c['motion']} from motion, "
            f"{c['unknown']} unknown")


def marker_calibration(frames, at: dict[int, tuple[float, float]], height_m: float,
                       min_seen: float = 0.5) -> tuple[Homography, np.ndarray, np.ndarray]:
    """Calibrate at marker height from ArUco markers placed at known arena positions.

    Put >= 4 markers (e.g. robots with their marker, or printed markers raised to shell
    height) at known spots spread over the arena, ``at`` = {marker id: (x, y) m}. The median
    image centre of each marker over ``frames`` (BGR images) pairs with its position.
    Returns ``(homography, pixels (n, 2), arena_m (n, 2))``. Raises :class:`SetupError`
    naming the markers seen in fewer than ``min_seen`` of the frames.
    """
    if len(at) < 4:
        raise SetupError(f"need at least 4 markers at known positions, got {len(at)}")
    det = MarkerDetector(None, None)
    seen: dict[int, list] = {i: [] for i in at}
    n = 0
    size = None
    for frame in frames:
        n += 1
        size = (frame.shape[1], frame.shape[0])
        for i, uv in det.centres_px(frame).items():
            if i in seen:
                seen[i].append(uv)
    missing = sorted(i for i, v in seen.items() if n == 0 or len(v) < min_seen * n)
    if missing:
        raise SetupError(f"marker(s) {missing} not seen in enough of the {n} frames: "
                         "check they are in view, lit, and of dictionary DICT_4X4_50")
    ids = sorted(at)
    px = np.array([np.median(np.array(seen[i]), axis=0) for i in ids])
    xy = np.array([at[i] for i in ids], dtype=float)
    try:
        h = Homography.from_points(px, xy, height_m, size)
    except CalibrationError as e:
        raise SetupError(str(e)) from None
    return h, px, xy


class AnnotatedOutput:
    """Annotated frames to a video file (``.avi`` Motion-JPEG, ``.mp4`` mp4v) or, for any other
    path, a directory of ``frame_000000.png`` files."""

    def __init__(self, path: str | Path, fps: float, homography: Homography | None):
        self.path = Path(path)
        self.fps = fps if fps and fps > 0 else 24.0
        self.homography = homography
        self._writer = None
        self._n = 0
        self._video = self.path.suffix.lower() in (".avi", ".mp4")
        if not self._video:
            self.path.mkdir(parents=True, exist_ok=True)

    def write(self, frame: np.ndarray, dets: list[Detection]) -> None:
        img = annotate(frame, dets, self.homography)
        if self._video:
            if self._writer is None:
                fourcc = cv2.VideoWriter_fourcc(*("MJPG" if self.path.suffix.lower() == ".avi" else "mp4v"))
                self._writer = cv2.VideoWriter(str(self.path), fourcc, self.fps, (img.shape[1], img.shape[0]))
                if not self._writer.isOpened():
                    raise OSError(f"cannot write video {self.path}")
            self._writer.write(img)
        else:
            cv2.imwrite(str(self.path / f"frame_{self._n:06d}.png"), img)
        self._n += 1

    def close(self) -> None:
        if self._writer is not None:
            self._writer.release()


def detection_to_message(d: Detection) -> GroundTruthPose:
    """The Zenoh message of one detection (``yaw=None`` when the heading is unknown)."""
    return GroundTruthPose(robot=d.robot, stamp_us=int(d.t_us), x=float(d.x_m), y=float(d.y_m),
                           yaw=None if math.isnan(d.yaw_rad) else float(d.yaw_rad),
                           u_px=float(d.u_px), v_px=float(d.v_px), detector=d.detector)


class GroundTruthRunner:
    """Runs the loop frame -> detections -> Zenoh/CSV/annotation for one webcam.

    Args:
        session: an open ``zenoh.Session`` (or ``None`` to only write files).
        source: where frames come from.
        detector: a detector from :func:`build_detector`.
        svc: the :class:`arena.service.Service` whose counters to update, or ``None``.
        csv_path, annotate_path: optional outputs.
    """

    def __init__(self, session, source: FrameSource, detector, svc=None, csv_path=None,
                 annotate_path=None):
        self.session, self.source, self.detector, self.svc = session, source, detector, svc
        self._csv = GroundTruthCsvWriter(csv_path) if csv_path else None
        self._ann = (AnnotatedOutput(annotate_path, source.fps, getattr(detector, "homography", None))
                     if annotate_path else None)
        self._pubs: dict[str, object] = {}
        self.frames = 0
        self.detections = 0
        self.seen: set[str] = set()

    def _publish(self, d: Detection) -> None:
        if self.session is None:
            return
        pub = self._pubs.get(d.robot)
        if pub is None:
            pub = self._pubs[d.robot] = self.session.declare_publisher(groundtruth_key(d.robot))
        pub.put(detection_to_message(d).encode())
        if self.svc is not None:
            self.svc.count("published")

    def step(self) -> bool:
        """Process one frame; ``False`` at the end of the source."""
        got = self.source.read()
        if got is None:
            return False
        t_us, frame = got
        t0 = time.perf_counter()
        dets = self.detector.detect(frame, t_us)
        detect_ms = (time.perf_counter() - t0) * 1e3
        self.frames += 1
        self.detections += len(dets)
        for d in dets:
            self.seen.add(d.robot)
            try:
                self._publish(d)
            except ValueError as e:          # e.g. a robot name that is not a valid key
                if self.svc is not None:
                    self.svc.error(f"cannot publish {d.robot}: {e}")
        if self._csv is not None:
            self._csv.write(dets)
        if self._ann is not None:
            self._ann.write(frame, dets)
        if self.svc is not None:
            self.svc.count("frames")
            self.svc.count("detections", len(dets))
            self.svc.gauge("detect_ms", round(detect_ms, 2))
            self.svc.gauge("robots_seen", len(self.seen))
        return True

    def run(self, stop: threading.Event | None = None, max_frames: int | None = None,
            duration_s: float | None = None) -> int:
        """Loop until a file ends, ``stop`` is set, ``max_frames`` or ``duration_s``; a live
        source that drops is reopened. Returns the number of frames processed."""
        t_end = None if duration_s is None else time.monotonic() + duration_s
        t_rate, n_rate = time.monotonic(), 0
        stop = stop or threading.Event()

        def running() -> bool:
            return not stop.is_set() and (max_frames is None or self.frames < max_frames) \
                and (t_end is None or time.monotonic() < t_end)

        while running():
            if not self.step():
                if not self.source.live or not self._reconnect(stop, running):
                    break
                continue
            n_rate += 1
            now = time.monotonic()
            if self.svc is not None and now - t_rate >= 1.0:
                self.svc.gauge("fps", round(n_rate / (now - t_rate), 2))
                t_rate, n_rate = now, 0
        return self.frames

    def _reconnect(self, stop: threading.Event, running) -> bool:
        """A live source stopped delivering: reopen it with backoff (0.2 s doubling to 5 s)
        while the run goes on. Returns False if the run ended first."""
        delay = 0.2
        while running():
            msg = f"video source {self.source.source} stopped delivering frames; reconnecting"
            if self.svc is not None:
                self.svc.error(msg)
                self.svc.set_state("waiting")
            else:
                log.warning(msg)
            if stop.wait(delay):
                return False
            try:
                self.source.reopen()
            except OSError:
                delay = min(2 * delay, 5.0)
                continue
            if self.svc is not None:
                self.svc.count("reconnects")
                self.svc.set_state("running")
            return True
        return False

    def close(self) -> None:
        if self._csv is not None:
            self._csv.close()
        if self._ann is not None:
            self._ann.close()
        for p in self._pubs.values():
            try:
                p.undeclare()
            except Exception:  # noqa: BLE001 - the session may be closing
                pass

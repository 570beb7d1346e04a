"""From event slices to arena tracks: accumulation, detection, tracking, calibration.

:class:`Pipeline` keeps the last ``accumulation_us`` (t_a, default 100 ms) of slices and, on
every slice (default 10 ms, so 100 Hz), detects robots in that window (sensor px), maps the
detections to the arena (m) with the calibration, and updates the tracker. It is pure: no
clocks, files or sockets; the offline CLI and the live service feed it.

>>> pipe = Pipeline(calibration)                                   # doctest: +SKIP
>>> for t_end, events in iter_slices(chunks, 10_000):              # doctest: +SKIP
...     for tr in pipe.push(events, t_end): print(tr.track_id, tr.x, tr.y)
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator

import numpy as np

from arena.slicing import Slicer
from tracker.accumulate import PixelWindow
from tracker.calibration import DEFAULT_ROBOT_HEIGHT_M, FALLBACK_CAMERA_HEIGHT_M, Calibration
from tracker.detect import Detection, Detector, DetectorConfig, PaperConfig, PaperDetector
from tracker.fleet import FleetConfig, FleetTracker
from tracker.idtrack import IDTrack
from tracker.objects import Observation, TrackedRobot

__all__ = ["Pipeline", "warm_up", "iter_slices", "TRACKERS", "DETECTORS",
           "PAPER_SIGMA_PX"]

TRACKERS = ("fleet", "idtrack")
DETECTORS = ("default", "paper")
#: The paper's new-robot distance (authors' code), px.
PAPER_SIGMA_PX = 100.0


class Pipeline:
    """Accumulate slices, detect, track, calibrate.

    Args:
        calibration: pixel <-> arena homography (gives the sensor size and the px/m scale).
        tracker: ``fleet`` (default) or ``idtrack`` (the paper's Algorithm 1).
        detector: ``default`` or ``paper``.
        accumulation_us: t_a, µs.
        chassis_m: robot footprint side, m (physical parameter of detector and tracker).
        fleet_size: number of robots in the lab, caps confirmed tracks (None: unknown).
        backend: DBSCAN backend ``grid`` (exact, fast) or ``sklearn`` (reference).
        robot_height_m: effective height of what the camera sees of the robots, m (default
            :data:`~tracker.calibration.DEFAULT_ROBOT_HEIGHT_M`, a Zumo's event cloud: 3.2 cm).
        camera_height_m: lens height above the mats, m (default: the calibration's
            ``camera_height_m``, else :data:`~tracker.calibration.FALLBACK_CAMERA_HEIGHT_M` =
            2.5 m assumed, and :attr:`parallax_warning` says so). With the robot height it
            corrects the parallax of the default detector's positions: distances from the
            calibration's nadir (:meth:`Calibration.nadir_m`) shrink by the factor
            :attr:`parallax` (1.3 % for 3.2 cm under 2.5 m: ~1.7 cm at a 1.83 m arena's corners
            seen from its centre). Paper mode keeps the paper's plain homography.
    """

    def __init__(self, calibration: Calibration, tracker: str = "fleet", detector: str = "default",
                 accumulation_us: int = 100_000, chassis_m: float = 0.10, fleet_size: int | None = None,
                 backend: str = "grid", robot_height_m: float = DEFAULT_ROBOT_HEIGHT_M,
                 camera_height_m: float | None = None
                 ) -> None:
        if tracker not in TRACKERS:
            raise ValueError(f"unknown tracker {tracker!r}; choose from {', '.join(TRACKERS)}")
        if detector not in DETECTORS:
            raise ValueError(f"unknown detector {detector!r}; choose from {', '.join(DETECTORS)}")
        if not accumulation_us > 0:
            raise ValueError(f"accumulation time must be > 0 µs, got {accumulation_us!r}")
        self.calibration = calibration
        self.accumulation_us = int(accumulation_us)
        w, h = calibration.image_size
        ppm = calibration.px_per_m()
        if camera_height_m is not None:
            cam_h, cam_src = float(camera_height_m), "given"
        elif calibration.camera_height_m is not None:
            cam_h, cam_src = calibration.camera_height_m, "calibration"
        else:
            cam_h, cam_src = FALLBACK_CAMERA_HEIGHT_M, "assumed"
        #: lens height used for the parallax correction, m, and where it came from
        #: (``given``, ``calibration`` or ``assumed``: :data:`FALLBACK_CAMERA_HEIGHT_M`)
        self.camera_height_m, self.camera_height_source = cam_h, cam_src
        #: parallax: arena positions are scaled by this about the nadir (1 in paper mode)
        self.parallax = 1.0 if detector == "paper" else calibration.parallax_factor(robot_height_m, cam_h)
        self._nadir = calibration.nadir_m()
        #: one line for the log when the correction rests on the assumed height (else None)
        self.parallax_warning: str | None = None
        if cam_src == "assumed" and detector != "paper":
            self.parallax_warning = (
                f"camera height unknown: parallax correction assumes the lens {cam_h:g} m above the mats "
                f"(robots seen {100 * robot_height_m:g} cm up: positions pulled {100 * (1 - self.parallax):.2f} % "
                f"towards the nadir at ({self._nadir[0]:.2f}, {self._nadir[1]:.2f}) m"
                f"{'' if calibration.nadir is not None else ', the image centre'}); set --camera-height-m, "
                "[services.tracker] camera_height_m, the lab camera's camera_height_m or the calibration's "
                "(arena calibrate --camera-height-m)")
        if detector == "paper":
            self.detector = PaperDetector(PaperConfig(backend=backend), w, h)
        else:
            self.detector = Detector(ppm, w, h, DetectorConfig(chassis_m=chassis_m, backend=backend))
        if tracker == "idtrack":
            self.tracker = IDTrack(sigma=PAPER_SIGMA_PX / ppm)
        else:
            self.tracker = FleetTracker(FleetConfig(chassis_m=chassis_m, fleet_size=fleet_size))
        self.pixels = PixelWindow(w, h, self.accumulation_us)
        self.last_t_us: int | None = None
        #: detections of the last window (sensor frame)
        self.detections_: list[Detection] = []

    def window(self) -> np.ndarray:
        """Events of the current window ``[t_end - t_a, t_end)``."""
        return self.pixels.events()

    def push(self, events: np.ndarray, t_end_us: int) -> list[TrackedRobot]:
        """Add one slice (events sorted by t, all ``< t_end_us``) and update the tracks.

        Returns the tracks at ``t_end_us`` (arena frame). Raises ValueError for a slice
        that does not end after the previous one or holds pixels outside the sensor (the
        caller counts and skips it; the pipeline's state is unchanged).
        """
        t_end_us = int(t_end_us)
        if self.last_t_us is not None and t_end_us <= self.last_t_us:
            raise ValueError(f"slice ending at {t_end_us} µs is not after the previous one ({self.last_t_us} µs)")
        self.pixels.push(events, t_end_us)
        self.last_t_us = t_end_us
        hints = None
        if isinstance(self.tracker, FleetTracker):
            pred = self.tracker.predictions(t_end_us)
            if len(pred):   # >= 2 split a shared cluster; one groups a robot's edge clusters
                hints = self.calibration.to_pixel(pred)
        if isinstance(self.detector, Detector):
            dets = self.detector.detect_window(self.pixels, t_end_us, hints=hints)
        else:
            dets = self.detector.detect(self.pixels.events(), t_end_us)
        self.detections_ = dets
        obs = [self._observation(d) for d in dets]
        return self.tracker.update(obs, t_end_us)

    #: correct an outline-placed detection's parallax for half the robot's visible height (its
    #: silhouette reaches from the ground on the side facing the nadir to the top edge on the far
    #: side, so its middle is seen half as high); False: the full height for every detection
    outline_parallax: bool = True

    def _observation(self, d: Detection) -> Observation:
        cal = self.calibration
        k = self.parallax
        if d.outline and self.outline_parallax and k != 1.0:
            # the height k corrects for, halved: k = (H - h)/(H - h_cal) -> (H - h/2)/(H - h_cal)
            span = self.camera_height_m - cal.height_m
            h = self.camera_height_m - k * span
            k = (self.camera_height_m - 0.5 * h) / span
        x, y = cal.point_to_arena(d.u, d.v)
        x = self._nadir[0] + (x - self._nadir[0]) * k
        y = self._nadir[1] + (y - self._nadir[1]) * k
        vx = vy = sig = yaw = math.nan
        if math.isfinite(d.du):
            vx, vy = cal.vector_to_arena(d.u, d.v, d.du, d.dv)
            vx, vy = vx * k, vy * k
            if math.isfinite(d.speed_sigma):
                sig = d.speed_sigma * k / cal.px_per_m(d.u, d.v)
        if math.isfinite(d.heading):
            yaw = cal.heading_to_arena(d.u, d.v, d.heading)
        shape = math.nan
        if math.isfinite(d.shape_axis):
            shape = cal.heading_to_arena(d.u, d.v, d.shape_axis)
        return Observation(x=float(x), y=float(y), t_us=d.t_us, vx=vx, vy=vy, speed_sigma=sig, yaw=yaw,
                           yaw_source=d.heading_source, u=d.u, v=d.v, n_events=d.n_events,
                           t_vel_us=d.t_vel_us, shape_yaw=shape, shape_order=d.shape_order,
                           t_act_us=d.t_act_us, whole=d.whole)


def warm_up(make_pipeline, n_slices: int = 12) -> None:
    """Run a throw-away pipeline from ``make_pipeline()`` over a few synthetic slices (a
    robot-sized blob drifting across the sensor's middle), so every numba kernel of the
    window codecs and the detection path is compiled (or loaded from numba's on-disk cache) before the first real
    slice: on a fresh install that takes ~10-15 s of CPU, which a live tracker would otherwise
    spend while its queue overflows."""
    from arena.codec import CODECS, decode, encode
    from arena.events import make_events

    pipe = make_pipeline()
    w, h = pipe.calibration.image_size
    rng = np.random.default_rng(0)
    side = max(4, min(w, h) // 16)
    for k in range(n_slices):
        n = 3000
        u = w // 2 - side + k + rng.integers(0, side, n)
        v = h // 2 - side // 2 + rng.integers(0, side, n)
        t = np.sort(rng.integers(k * 10_000, (k + 1) * 10_000, n))
        ev = make_events(np.clip(u, 0, w - 1), np.clip(v, 0, h - 1), rng.integers(0, 2, n), t)
        if k == 0:   # the live tracker decodes every window first
            for codec in CODECS:
                decode(codec, encode(ev, codec), ev.size)
        pipe.push(ev, (k + 1) * 10_000)
    # windows of zero and one event: numba types an array of at most one element as contiguous,
    # a separate specialisation a live tracker would otherwise compile on its first empty window
    for k, ev in enumerate((ev[:0], ev[:1])):
        for codec in CODECS:
            decode(codec, encode(ev, codec), ev.size)
        make_pipeline().push(ev, (n_slices + k + 1) * 10_000)


def iter_slices(chunks: Iterable[np.ndarray], slice_us: int, start_us: int | None = None, *,
                slicer: Slicer | None = None) -> Iterator[tuple[int, np.ndarray]]:
    """Cut a stream of event chunks into the windows the edge publishes: :class:`arena.slicing.Slicer`.

    Yields ``(t_end_us, events)`` for every window ``[t_end_us - slice_us, t_end_us)``, empty
    ones included; boundaries are multiples of ``slice_us`` of the sensor clock, from the first
    event's window (or ``start_us``'s) to the last event's, which ends the stream partly filled
    (the edge flushes it at the end of a file). Late (out-of-order) events go into the window
    open when they arrive, as at the edge; a jump in time longer than the Slicer's
    ``max_gap_slices`` windows restarts the windows instead of emitting them all empty.
    ``slicer``: a Slicer of ``slice_us`` to use (read its ``late`` and ``skipped_gaps`` after).
    """
    if slicer is None:
        slicer = Slicer(slice_us, start_us=start_us)
    elif slicer.slice_us != slice_us or start_us is not None:
        raise ValueError(f"iter_slices: give either a Slicer of {slice_us} µs or start_us, "
                         f"got a Slicer of {slicer.slice_us} µs and start_us={start_us!r}")
    for chunk in chunks:
        for s in slicer.push(chunk):
            yield s.t_end_us, s.events
    for s in slicer.flush():
        yield s.t_end_us, s.events

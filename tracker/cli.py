"""``arena track`` (offline on a file, or live on Zenoh) and ``arena calibrate``."""

from __future__ import annotations

import argparse
import math
import re
import sys
import time
from pathlib import Path

from arena.clitools import fail, formatter

TRACK_EXAMPLES = """\
Examples:
  # offline: any recording the edge reads (.raw EVT 2/2.1/3, .dat, .aedat4, the paper's .csv, .npy/.npz)
  arena track --input rec.raw --calibration calib.json --tracks-out tracks.csv
  arena track --input rec.aedat4 --calibration lab.toml --tracker idtrack --detector paper \\
              --tracks-out paper_tracks.csv                 # the paper's method, for comparison
  arena track --input rec.npz --calibration calib.json --tracks-out t.csv --slice-ms 5 --accumulation-ms 60
  arena track --input rec.raw --lab lab.toml --tracks-out t.csv   # calibration, robots, [services.tracker]
  # live: subscribe arena/events/cam0, publish arena/robots/<id>, answer get('arena/robots/*')
  arena track --camera cam0 --calibration calib.json
  arena track --camera cam0 --lab lab.toml --tracks-out live.csv -e tcp/10.0.0.1:7447 -m client
Options not given as flags come from the lab config's [services.tracker] table (tracker, detector,
backend, slice_ms, accumulation_ms, chassis_cm, robot_height_cm, camera_height_m, fleet_size, queue,
names_from_groundtruth, state_max_age_s), else the defaults. The method in use is printed at the end
offline and shown live by `arena status` (gauges tracker, detector).
CSV columns: t_us,track_id,robot,x_m,y_m,yaw_rad,vx_mps,vy_mps,u_px,v_px,state,n_events,host_ns
(t_us: time of the pose in the input's clock; arena metres; yaw CCW from +x; host_ns: host
capture time of t_us, live only; empty = unknown)."""

CALIBRATE_EXAMPLES = """\
Examples:
  # four (or more) correspondences pixel u,v : arena x,y (m); the sensor size is needed
  arena calibrate --size 640x480 --points 112,431:0,0 528,431:1.83,0 528,15:1.83,1.83 112,15:0,1.83 -o calib.json
  # find the mat corners in a webcam frame (bright mat on a darker floor)
  arena calibrate --image frame.png --arena-size 1.83 -o calib.json
  # or in the event image accumulated over the first seconds of a recording
  arena calibrate --events rec.raw --seconds 5 -o calib.json
  # where the lens is, for the tracker's parallax correction: measured ...
  arena calibrate --image frame.png --camera-height-m 2.45 --nadir 0.92,0.90 -o calib.json
  # ... or estimated from the homography and the lens (focal length, sensor pixel pitch)
  arena calibrate --image frame.png --focal-length-mm 4.5 --pixel-pitch-um 15 -o calib.json
Without --camera-height-m or the lens, the file has no camera_height_m: the tracker then
assumes 2.5 m and warns. Without --nadir (or the lens) the nadir is the image centre's point.
The corners found are mapped to the arena with (0,0) at the image's bottom-left mat corner,
x along the image's bottom edge and y up the image. A preview PNG (grid every 0.25 m) is
written beside the JSON (--preview to choose its path)."""


def _positive_ms(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a duration in ms, got {text!r}") from None
    if not (v > 0 and math.isfinite(v)):
        raise argparse.ArgumentTypeError(f"duration must be > 0 ms, got {text!r}")
    return v


def register_track(sub) -> None:
    """Add ``arena track``."""
    from arena.session import add_zenoh_arguments

    p = sub.add_parser("track", help="detect and track the robots (offline file or live)", formatter_class=formatter,
                       description="Detect robots in event windows (DBSCAN), estimate their heading, keep their\n"
                                   "IDs and map them to arena metres. Offline with --input, live with --camera.",
                       epilog=TRACK_EXAMPLES)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--input", metavar="FILE", help="event recording to track offline")
    src.add_argument("--camera", metavar="NAME", help="live: track arena/events/NAME")
    p.add_argument("--calibration", metavar="FILE",
                   help="calibration JSON, or a lab config TOML (its camera's calibration); "
                        "default: the --lab config's camera")
    p.add_argument("--tracks-out", metavar="CSV", help="write the tracks here (required offline)")
    p.add_argument("--tracker", choices=("fleet", "idtrack"), default=None,
                   help="fleet: Kalman + assignment + life cycle (default); idtrack: the paper's Algorithm 1")
    p.add_argument("--detector", choices=("default", "paper"), default=None,
                   help="default: physical, adaptive; paper: DBSCAN x3 with the paper's pixel parameters")
    p.add_argument("--backend", choices=("grid", "sklearn"), default=None,
                   help="DBSCAN backend: grid (exact, fast; default) or sklearn (reference)")
    p.add_argument("--slice-ms", type=_positive_ms, default=None, help="offline slice length, ms (default 10)")
    p.add_argument("--accumulation-ms", type=_positive_ms, default=None,
                   help="accumulation time t_a, ms (default 100, the paper's best)")
    p.add_argument("--chassis-cm", type=float, default=None, help="robot footprint side, cm (default 10)")
    p.add_argument("--robot-height-cm", type=float, default=None,
                   help="effective height of what the camera sees of the robots, cm, for the parallax "
                        "correction (default: the lab's [[robots]] robot_height_cm, else 3.2: a Zumo's event "
                        "cloud, lower than its 4.5 cm shell top)")
    p.add_argument("--camera-height-m", type=float, default=None,
                   help="lens height above the mats, m, for the parallax correction (default: the lab "
                        "camera's or the calibration's camera_height_m; without one 2.5 m is ASSUMED and a "
                        "warning says so)")
    p.add_argument("--fleet-size", type=int, default=None,
                   help="number of robots (caps confirmed tracks; default: the lab config's robots)")
    p.add_argument("--name", default=None, help="live: service name in arena status (default: tracker-CAMERA)")
    p.add_argument("--queue", type=int, default=None,
                   help="live: newest slices kept when lagging or when a burst arrives late "
                        "(default 100: 1 s of 10 ms slices; a lagging tracker catches up at ~1 ms per slice)")
    p.add_argument("--no-names", dest="names_from_groundtruth", action="store_false", default=None,
                   help="live: do not name tracks after the robots of arena/groundtruth/* poses")
    p.add_argument("--state", metavar="FILE", default=None,
                   help="live: fleet state file, written every second and read at start so that track IDs "
                        "survive a restart (default: tracker-NAME.json in $ARENA_STATE_DIR, systemd's "
                        "$STATE_DIRECTORY or ~/.local/state/arena)")
    p.add_argument("--no-state", dest="use_state", action="store_false",
                   help="live: neither read nor write the state file (every start is afresh)")
    p.add_argument("--state-max-age", type=float, default=None, metavar="S",
                   help="live: a state file older than this is not restored, s (default 600)")
    p.add_argument("--duration", type=float, default=None, help=argparse.SUPPRESS)
    add_zenoh_arguments(p)
    p.set_defaults(func=run_track)


def _load_calibration(path: str | None, camera: str | None = None):
    from tracker.calibration import CalibrationError, load_calibration

    if not path:
        raise fail("arena track: --calibration FILE is required (calibration JSON or lab TOML); "
                         "make one with `arena calibrate`")
    try:
        return load_calibration(path, camera)
    except CalibrationError as exc:
        raise fail(f"arena track: {exc}") from None


def _lab(args):
    """The lab config of this run: ``--lab`` (or ``ARENA_LAB``), else offline a lab TOML given as
    ``--calibration``; None without one."""
    from arena.config import ConfigError, load_lab_config
    from arena.session import load_lab_from_args

    try:
        lab = load_lab_from_args(args)
        if lab is None and not args.camera and args.calibration and Path(args.calibration).suffix.lower() == ".toml":
            lab = load_lab_config(args.calibration)
    except ConfigError as exc:  # a lab file that does not say what it means: exit 2, like a bad flag
        print(f"arena track: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    return lab


def run_track(args) -> int:
    from arena.config import apply_service_options

    lab = _lab(args)
    # flags win, then the lab file's [services.tracker], then the defaults
    apply_service_options(args, lab, "tracker")
    if args.robot_height_cm is None:  # then the lab's robots, then a Zumo's event cloud
        from tracker.calibration import DEFAULT_ROBOT_HEIGHT_M

        lab_h = lab.robot_height_cm() if lab is not None else None
        args.robot_height_cm = lab_h if lab_h is not None else 100.0 * DEFAULT_ROBOT_HEIGHT_M
    if args.camera:
        return run_live(args)
    return run_offline(args, lab)


def _check_geometry(args) -> None:
    if args.robot_height_cm is None:  # not resolved by run_track: a Zumo's event cloud
        from tracker.calibration import DEFAULT_ROBOT_HEIGHT_M

        args.robot_height_cm = 100.0 * DEFAULT_ROBOT_HEIGHT_M
    if not (args.chassis_cm > 0 and math.isfinite(args.chassis_cm)):
        raise fail(f"arena track: --chassis-cm must be > 0, got {args.chassis_cm}")
    if not (0 <= args.robot_height_cm < 100):
        raise fail(f"arena track: --robot-height-cm must be in [0, 100), got {args.robot_height_cm}")
    if args.camera_height_m is not None:
        from arena.config import CAMERA_HEIGHT_RANGE_M

        lo, hi = CAMERA_HEIGHT_RANGE_M
        if not (lo <= args.camera_height_m <= hi):   # as arena calibrate, the lab file and the calibration
            raise fail(f"arena track: --camera-height-m must be {lo:g}-{hi:g} m (the lens above the mats), "
                       f"got {args.camera_height_m}")
        if not args.camera_height_m > args.robot_height_cm / 100:
            raise fail(f"arena track: --camera-height-m must be above the robots, got {args.camera_height_m}")


def pipeline_options(args) -> dict:
    """Pipeline keyword arguments from the command line (both modes)."""
    return dict(tracker=args.tracker, detector=args.detector, accumulation_us=int(round(args.accumulation_ms * 1000)),
                chassis_m=args.chassis_cm / 100.0, backend=args.backend, robot_height_m=args.robot_height_cm / 100.0,
                camera_height_m=args.camera_height_m)


def run_live(args) -> int:
    """``arena track --camera NAME``: build the pipeline, state file and CSV log from the flags and
    the lab file, then :func:`tracker.service.run` until interrupted (or ``--duration`` s)."""
    import logging

    from arena.clitools import session_or_exit
    from arena.config import ConfigError
    from arena.keys import events_key
    from arena.service import stop_on_signals
    from arena.session import load_lab_from_args
    from tracker.calibration import CalibrationError, camera_calibration
    from arena.formats.tables import TrackCsvWriter
    from tracker.pipeline import Pipeline, warm_up
    from tracker.service import default_state_path, run

    log = logging.getLogger("tracker")
    try:
        lab = load_lab_from_args(args)
    except ConfigError as exc:
        raise fail(f"arena track: {exc}") from None
    try:
        events_key(args.camera)
    except ValueError as exc:
        raise fail(f"arena track: {exc}") from None
    if args.calibration:
        cal = _load_calibration(args.calibration, args.camera)
    elif lab is not None:
        try:
            cam = lab.camera(args.camera)
            if cam.calibration is None and cam.calibration_file is None:
                raise fail(f"arena track: camera {args.camera!r} of {lab.path} has no calibration; "
                           "give --calibration FILE")
            # its points or file, with the camera table's camera_height_m / nadir_m
            cal = camera_calibration(cam, lab.path or "lab config")
        except (ConfigError, CalibrationError) as exc:
            raise fail(f"arena track: {exc}") from None
    else:
        raise fail("arena track: --calibration FILE (or --lab with the camera's calibration) is required")
    fleet_size = args.fleet_size if args.fleet_size is not None else ((len(lab.robots) or None) if lab is not None else None)
    _check_geometry(args)

    def make_pipeline() -> Pipeline:
        return Pipeline(cal, fleet_size=fleet_size, **pipeline_options(args))

    try:
        pipe = make_pipeline()
    except CalibrationError as exc:
        raise fail(f"arena track: {exc}") from None
    if pipe.parallax_warning:
        log.warning("%s", pipe.parallax_warning)
    # compile the kernels before declaring liveliness: "alive" then means "tracks at full rate"
    t0 = time.monotonic()
    warm_up(make_pipeline)
    if time.monotonic() - t0 > 2.0:
        log.info("tracker kernels compiled in %.1f s (cached for the next start)", time.monotonic() - t0)
    name = args.name or f"tracker-{args.camera}"
    state_path = None
    if getattr(args, "use_state", True) and args.tracker == "fleet":
        state_path = Path(args.state) if args.state else default_state_path(name)
    stop = stop_on_signals()
    csv_file = open(args.tracks_out, "w", newline="") if args.tracks_out else None
    try:
        with session_or_exit(args, "arena track", lab=lab, wait_s=None) as session:
            run(session, make_pipeline, args.camera, stop, name=name, pipeline=pipe, tracker=args.tracker,
                detector=args.detector, queue=args.queue, names_from_groundtruth=args.names_from_groundtruth,
                state_path=state_path, state_max_age_s=args.state_max_age,
                writer=TrackCsvWriter(csv_file) if csv_file else None, duration_s=args.duration)
    finally:
        if csv_file is not None:
            csv_file.close()
    return 0


def run_offline(args, lab=None) -> int:
    """``arena track --input FILE``; ``lab``: the lab config (gives the calibration when there
    is no ``--calibration``, and the number of robots)."""
    from arena.formats import FormatError, iter_events
    from arena.slicing import Slicer
    from tracker.calibration import CalibrationError
    from arena.formats.tables import TrackCsvWriter
    from tracker.pipeline import Pipeline, iter_slices

    if not args.tracks_out:
        raise fail("arena track: --tracks-out CSV is required with --input")
    if args.fleet_size is not None and args.fleet_size < 1:
        raise fail(f"arena track: --fleet-size must be >= 1, got {args.fleet_size}")
    _check_geometry(args)
    if args.calibration is None and lab is not None and lab.cameras:  # the lab's camera: a file it names, or inline
        from tracker.calibration import camera_calibration

        try:
            cal = camera_calibration(lab.camera(), lab.path or "lab config")
        except CalibrationError as exc:
            raise fail(f"arena track: {exc}") from None
    else:
        cal = _load_calibration(args.calibration)
    fleet_size = args.fleet_size
    if fleet_size is None and lab is not None:  # a lab config also tells how many robots there are
        fleet_size = len(lab.robots) or None
    w, h = cal.image_size
    opts = {"width": w, "height": h} if Path(args.input).suffix.lower() in (".csv", ".npy", ".npz") else {}
    try:   # a 0-byte file has no events in any format (a RAW reader would complain of its header)
        zero_bytes = Path(args.input).is_file() and Path(args.input).stat().st_size == 0
    except OSError:
        zero_bytes = False
    try:
        reader = _NoEvents() if zero_bytes else iter_events(args.input, **opts)
    except TypeError:  # this format takes no size option
        reader = iter_events(args.input)
    except (FormatError, OSError) as exc:
        raise fail(f"arena track: {exc}") from None
    try:
        pipe = Pipeline(cal, fleet_size=fleet_size, **pipeline_options(args))
    except CalibrationError as exc:
        raise fail(f"arena track: {exc}") from None
    if pipe.parallax_warning:
        print(f"arena track: warning: {pipe.parallax_warning}", file=sys.stderr)
    slice_us = int(round(args.slice_ms * 1000))
    try:   # the edge's windows (arena.slicing): multiples of slice_us, late events kept and counted
        slicer = Slicer(slice_us)
    except ValueError as exc:
        raise fail(f"arena track: --slice-ms: {exc}") from None
    n_rows = n_slices = n_events = 0
    t0 = time.perf_counter()
    try:
        with reader, open(args.tracks_out, "w", newline="") as fh:
            if reader.width and reader.height and (reader.width, reader.height) != (w, h):
                raise fail(f"arena track: {args.input} is {reader.width}x{reader.height} px but the "
                                 f"calibration is for {w}x{h} px")
            writer = TrackCsvWriter(fh)
            for t_end, ev in iter_slices(reader, slice_us, slicer=slicer):
                n_rows += writer.write(pipe.push(ev, t_end))
                n_slices += 1
                n_events += len(ev)
    except (FormatError, OSError) as exc:
        raise fail(f"arena track: {exc}") from None
    except ValueError as exc:  # events outside the calibrated sensor
        raise fail(f"arena track: {args.input}: {exc}") from None
    dt = time.perf_counter() - t0
    if n_events == 0:   # an input error, as `arena convert` and `arena edge` say of the same file
        raise fail(f"arena track: no events in {args.input}{' (0-byte file)' if zero_bytes else ''}: no tracks, "
                   f"{args.tracks_out} has only its header; check the file (a recording of a still scene under "
                   "steady light has none)")
    print(f"{args.tracker} tracker, {args.detector} detector: {n_slices} slices, {n_rows} track rows -> "
          f"{args.tracks_out} ({dt:.1f} s, {1e3 * dt / max(1, n_slices):.2f} ms per slice); "
          f"{slicer.late} late event(s) kept in the slice open when they came (as the edge does)"
          + (f", {slicer.skipped_gaps} gap(s) over {slicer.max_gap_slices} slices skipped" if slicer.skipped_gaps
             else ""), file=sys.stderr)
    return 0


class _NoEvents:
    """The event reader of a 0-byte file: no chunks, no sensor size."""

    width = height = None

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        return None

    def __iter__(self):
        return iter(())


# ----------------------------------------------------------------------------- calibrate


def _point(text: str) -> tuple[tuple[float, float], tuple[float, float]]:
    try:
        px, am = text.split(":")
        u, v = (float(s) for s in px.split(","))
        x, y = (float(s) for s in am.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"a point is u,v:x,y (pixel px : arena m), got {text!r}") from None
    return (u, v), (x, y)


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(s) for s in text.lower().split("x"))
        if not (0 < w <= 65535 and 0 < h <= 65535):
            raise ValueError
    except ValueError:
        raise argparse.ArgumentTypeError(f"size is WIDTHxHEIGHT in px (1-65535 each), e.g. 640x480; "
                                         f"got {text!r}") from None
    return w, h


def register_calibrate(sub) -> None:
    """Add ``arena calibrate``."""
    p = sub.add_parser("calibrate", help="make the camera calibration (pixel -> arena metres)",
                       formatter_class=formatter,
                       description="Fit the homography between sensor pixels and arena metres and write the\n"
                                   "calibration JSON {\"image_size\": [w, h], \"points\": [...]} and a preview PNG.",
                       epilog=CALIBRATE_EXAMPLES)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--points", nargs="+", type=_point, metavar="U,V:X,Y", help=">= 4 correspondences")
    src.add_argument("--image", metavar="PNG", help="a webcam/camera frame showing the whole mat")
    src.add_argument("--events", metavar="FILE", help="an event recording; its accumulated image is used")
    p.add_argument("--size", type=_size, metavar="WxH", help="sensor size, px (needed with --points)")
    p.add_argument("--arena-size", type=float, default=1.83, help="mat side, m (default 1.83)")
    p.add_argument("--seconds", type=float, default=5.0, help="events accumulated from the start, s (default 5)")
    p.add_argument("--camera-height-m", type=float, default=None, metavar="M",
                   help="lens height above the mats, m (measured; stored as camera_height_m for the "
                        "tracker's parallax correction; wins over the estimate from the lens)")
    p.add_argument("--nadir", type=_xy_arg, default=None, metavar="X,Y",
                   help="arena point under the lens, m (e.g. a plumb line; stored as nadir_m; default: "
                        "the estimate from the lens, else none: the tracker uses the image centre's point); "
                        "outside the mat it may be negative: --nadir -0.2,0.9")
    p.add_argument("--focal-length-mm", type=float, default=None, metavar="MM",
                   help="lens focal length, mm: with --pixel-pitch-um, estimate the camera's height and nadir "
                        "from the homography (pinhole model, principal point at the image centre)")
    p.add_argument("--pixel-pitch-um", type=float, default=None, metavar="UM",
                   help="sensor pixel pitch, µm (e.g. 15 for a Prophesee Gen3 VGA, 4.86 for an IMX636)")
    p.add_argument("-o", "--output", required=True, metavar="JSON", help="calibration file to write")
    p.add_argument("--preview", metavar="PNG", help="preview image (default: OUTPUT with .png)")
    p.set_defaults(func=run_calibrate)
    # argparse reads an argument starting with '-' as an option unless it is a plain negative
    # number, so `--nadir -0.2,0.9` failed ("expected one argument"). No option of this parser
    # looks like a number: a negative X,Y pair is a value too (`--nadir=-0.2,0.9` always was)
    p._negative_number_matcher = _NEGATIVE_VALUE


#: what arena calibrate takes as a value although it starts with '-': -5, -0.5, -.5, -0.2,0.9, -1,-2
_NEGATIVE_VALUE = re.compile(r"^-(\d+\.?\d*|\.\d+)(,-?(\d+\.?\d*|\.\d+))?$")


def _xy_arg(text: str) -> tuple[float, float]:
    try:
        x, y = (float(s) for s in text.split(","))
        if not (math.isfinite(x) and math.isfinite(y)):
            raise ValueError
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y in arena metres, got {text!r}") from None
    return x, y


def _camera_geometry(args, cal) -> list[str]:
    """Put the lens height and nadir (given, or estimated from the lens) into ``cal``; returns
    the lines to print."""
    from tracker.calibration import (FALLBACK_CAMERA_HEIGHT_M, CalibrationError, lens_focal_px,
                                     lens_height_disagreement)

    notes = []
    lens = (args.focal_length_mm, args.pixel_pitch_um)
    if (lens[0] is None) != (lens[1] is None):
        raise fail("arena calibrate: --focal-length-mm and --pixel-pitch-um go together")
    if args.camera_height_m is not None and not (math.isfinite(args.camera_height_m) and args.camera_height_m > 0):
        raise fail(f"arena calibrate: --camera-height-m must be > 0 m, got {args.camera_height_m}")
    height, nadir = args.camera_height_m, args.nadir
    if lens[0] is not None:
        if not all(math.isfinite(v) and v > 0 for v in lens):
            raise fail(f"arena calibrate: --focal-length-mm and --pixel-pitch-um must be > 0, got {lens}")
        try:
            pose = cal.estimate_pose(lens_focal_px(lens[0], lens[1], cal.image_size))
        except CalibrationError as exc:
            raise fail(f"arena calibrate: {exc}") from None
        notes.append(f"estimated from the lens: camera {pose.camera_height_m:.3f} m above the mats, nadir "
                     f"({pose.nadir_m[0]:.3f}, {pose.nadir_m[1]:.3f}) m, tilt {pose.tilt_deg:.1f} deg"
                     + (f" (warning: the homography fits this focal length poorly, column ratio "
                        f"{pose.consistency:.3f}; check the lens values)" if pose.consistency < 0.95 else ""))
        if height is not None:
            disagreement = lens_height_disagreement(pose.camera_height_m, height)
            if disagreement:
                notes.append(disagreement)
        height = pose.camera_height_m if height is None else height
        nadir = pose.nadir_m if nadir is None else nadir
    try:
        cal.with_geometry(height, nadir)
    except CalibrationError as exc:
        raise fail(f"arena calibrate: {exc}") from None
    if cal.camera_height_m is None:
        notes.append(f"warning: camera height unknown, none stored: the tracker will assume "
                     f"{FALLBACK_CAMERA_HEIGHT_M:g} m for its parallax correction; measure the lens height and "
                     "give --camera-height-m (or --focal-length-mm with --pixel-pitch-um to estimate it)")
    if cal.nadir is None:
        x, y = cal.nadir_m()
        notes.append(f"nadir unknown, none stored: the tracker will use the image centre's point ({x:.3f}, "
                     f"{y:.3f}) m (the nadir of a camera looking straight down; give --nadir X,Y if it is not)")
    return notes


def run_calibrate(args) -> int:
    import cv2
    import numpy as np

    from tracker.calibration import (MAX_ARENA_SPAN_M, Calibration, CalibrationError, check_extent, find_mat_corners,
                                     mat_points)

    L = args.arena_size
    if not (L > 0 and math.isfinite(L)):
        raise fail(f"arena calibrate: --arena-size must be > 0 m, got {L}")
    if L > MAX_ARENA_SPAN_M:
        raise fail(f"arena calibrate: --arena-size {L:g}: is it in cm? the mat side is in metres (e.g. 1.83)")
    image = None
    try:
        if args.points:
            if not args.size:
                raise fail("arena calibrate: --size WxH is required with --points")
            px, am = np.array([p for p, _ in args.points]), np.array([a for _, a in args.points])
            check_extent(px.reshape(-1, 2), am.reshape(-1, 2), args.size,
                         lambda i: f"--points {i + 1} ({_show_pair(args.points[i])})")
            cal = Calibration.from_points(px, am, args.size)
        else:
            if args.image:
                image = cv2.imread(args.image, cv2.IMREAD_GRAYSCALE)
                if image is None:
                    raise fail(f"arena calibrate: cannot read the image {args.image!r}")
            try:
                if args.events:
                    image, corners = _event_corners(args.events, args.seconds)
                else:
                    corners = find_mat_corners(image)
            except CalibrationError as exc:
                if args.events:   # a still, steadily lit mat makes no events
                    raise CalibrationError(
                        f"{exc}. An event camera sees the mat only where its light changes: record it "
                        "under flickering mains light (most lamps flicker at 100/120 Hz) or while "
                        "sweeping a light over it, or calibrate from a webcam frame (--image)") from None
                raise

            size = (image.shape[1], image.shape[0])
            # as the calibration file's loader, so that `arena track` reads what this writes
            check_extent(np.asarray(corners, np.float64), mat_points(L), size,
                         lambda i: f"mat corner {i + 1} found", "the mat's corners must all be in view (or give "
                                                                 "--points)")
            cal = Calibration.from_points(corners, mat_points(L), size)
    except CalibrationError as exc:
        raise fail(f"arena calibrate: {exc}") from None
    notes = _camera_geometry(args, cal)
    try:
        cal.save(args.output)
    except OSError as exc:
        raise fail(f"arena calibrate: cannot write {args.output}: {exc.strerror or exc} (check the folder exists "
                   "and is writable)") from None
    preview = args.preview or str(Path(args.output).with_suffix(".png"))
    if image is None:
        image = np.full((cal.image_size[1], cal.image_size[0]), 255, np.uint8)
    if Path(preview).resolve() == Path(args.output).resolve():
        raise fail(f"arena calibrate: --preview {preview} is the calibration's own path (-o): give a .png")
    try:
        written = cv2.imwrite(preview, _preview(cal, image, L))
    except cv2.error as exc:      # e.g. a folder, or no image format for its extension
        raise fail(f"arena calibrate: cannot write the preview {preview}: {str(exc).strip().splitlines()[-1]}") from None
    if not written:
        raise fail(f"arena calibrate: cannot write the preview {preview} (does its folder exist? is it a .png?); "
                   f"the calibration {args.output} is written")
    print(f"wrote {args.output} ({len(cal.pixels)} points, reprojection {1000 * cal.reprojection_error_m():.1f} mm, "
          f"{cal.px_per_m():.1f} px/m at the centre) and {preview}", file=sys.stderr)
    for line in notes:
        print(f"arena calibrate: {line}", file=sys.stderr)
    return 0


def _show_pair(pair) -> str:
    (u, v), (x, y) = pair
    return f"{u:g},{v:g}:{x:g},{y:g}"


def _event_corners(path: str, seconds: float):
    """The mat's corners from the first ``seconds`` of an event recording under flickering
    light, and a preview image of the flicker amplitude. Two passes over the file (its
    flicker frequency, then per-pixel lock-in sums at it), so memory does not grow with the
    recording."""
    import numpy as np

    from arena.formats import FormatError, iter_events
    from tracker.calibration import (FLICKER_BIN_S, CalibrationError, add_phasors, find_mat_corners_flicker,
                                     flicker_frequency,
                                     flicker_maps, signed_rate)

    if not (seconds > 0 and math.isfinite(seconds)):
        raise fail(f"arena calibrate: --seconds must be > 0, got {seconds}")
    span_us = int(round(seconds * 1e6))

    def chunks():
        with iter_events(path) as reader:
            w, h = reader.width, reader.height
            if not (w and h):
                raise fail(f"arena calibrate: {path} does not carry its sensor size; convert it with "
                           "`arena convert --size WxH` first")
            t0 = None
            for chunk in reader:
                if chunk.size == 0:
                    continue
                t0 = int(chunk["t"][0]) if t0 is None else t0
                chunk = chunk[chunk["t"] < t0 + span_us]
                if chunk.size == 0:
                    break
                yield w, h, t0, chunk

    try:
        rate = np.zeros(int(math.ceil(seconds / FLICKER_BIN_S)), np.float64)
        size, t0, t_end = None, None, None
        for w, h, t0, c in chunks():
            size = (w, h)
            signed_rate(c["t"], c["p"], t0, rate)
            t_end = int(c["t"][-1])
        if size is None:
            raise CalibrationError("the recording has no events")
        rate = rate[:max(1, int((t_end - t0) * 1e-6 / FLICKER_BIN_S) + 1)]
        freq = flicker_frequency(rate)
        w, h = size
        A, N = np.zeros((h, w), np.complex128), np.zeros((h, w), np.float64)
        for _, _, t0, c in chunks():
            add_phasors(A, N, c["x"], c["y"], c["p"], c["t"], t0, freq)
    except (FormatError, OSError) as exc:
        raise fail(f"arena calibrate: {exc}") from None
    amp, z, edge = flicker_maps(A, N)
    hi = float(np.percentile(amp, 99.5))
    image = (255.0 * np.clip(amp / max(hi, 1e-9), 0.0, 1.0)).astype(np.uint8)
    return image, find_mat_corners_flicker(amp, z, edge)


def _preview(cal, gray, L: float):
    import cv2
    import numpy as np

    img = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    ticks = np.arange(0.0, L + 1e-9, 0.25)
    for t in ticks:
        for a, b in (((t, 0.0), (t, L)), ((0.0, t), (L, t))):
            pa, pb = cal.to_pixel(np.array([a, b]))
            cv2.line(img, tuple(int(round(c)) for c in pa), tuple(int(round(c)) for c in pb), (0, 160, 0), 1)
    for (u, v), (x, y) in zip(cal.pixels, cal.arena_m):
        cv2.circle(img, (int(round(u)), int(round(v))), 5, (0, 0, 255), 2)
        cv2.putText(img, f"({x:g},{y:g})", (int(round(u)) + 6, int(round(v)) - 6), cv2.FONT_HERSHEY_SIMPLEX,
                    0.4, (0, 0, 255), 1)
    return img

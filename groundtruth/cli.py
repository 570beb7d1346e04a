"""Command-line entry points of the groundtruth package, one ``register_*`` function per command.

Each ``register_*(subparsers)`` adds one ``arena`` subcommand (see ``[project.entry-points.
"arena.commands"]`` in pyproject.toml) and sets ``func`` to a ``run(args) -> exit code``.
Heavy imports (matplotlib, the simulator) happen inside the run functions so ``arena --help`` stays fast.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from arena.clitools import formatter


# --------------------------------------------------------------------------------------------
# arena eval
# --------------------------------------------------------------------------------------------
def register_eval(sub) -> None:
    """Add ``arena eval``: score a tracks CSV against truth (our CSV, a mocap bag or a pose CSV)."""
    p = sub.add_parser(
        "eval", help="score tracks against ground truth (MOTA, IDF1, HOTA, MAE, ...)",
        formatter_class=formatter,
        description="Score a tracker's CSV against truth: per-frame optimal matching with a distance\n"
                    "gate, precision, recall, position MAE (cm), heading MAE (deg, circular), CLEAR MOT\n"
                    "(MOTA, MOTP, ID switches, fragmentations), IDF1 and HOTA. A robot counts once it\n"
                    "has moved. Frames are the tracks' update times; truth is interpolated there.\n\n"
                    "tracks CSV: t_us,track_id,robot,x_m,y_m,yaw_rad,vx_mps,vy_mps,u_px,v_px,state,n_events\n"
                    "            [,host_ns: host capture time of t_us, ns since the epoch, live tracks]\n"
                    "truth:      a truth CSV t_us,robot,x_m,y_m[,yaw_rad,...] (simulator truth or\n"
                    "            `arena groundtruth`: arena frame, the tracks' clock), or motion capture:\n"
                    "            a rosbag2 folder / .mcap file of geometry_msgs/msg/PoseStamped (one topic\n"
                    "            per rigid body, z up), or a pose CSV with a time (t_s, t_ms, t_us or t_ns),\n"
                    "            a name (name, robot or body), x, y [, z] and qx,qy,qz,qw or yaw / yaw_deg.\n"
                    "Mocap truth is put on the tracks' clock (--time-offset) and frame (--align) first;\n"
                    "the offset and the fit (rotation, translation, scale, residuals) are printed and\n"
                    "written to the JSON. See docs/mocap.md.",
        epilog="Examples:\n"
               "  arena eval --tracks tracks.csv --truth truth.csv\n"
               "  arena eval --tracks tracks.csv --truth truth.csv --gate-cm 5 --json scores.json\n"
               "  arena eval --tracks tracks.csv --truth webcam_gt.csv --report eval_report/\n"
               "  arena eval --tracks tracks.csv --truth mocap_bag/ --time-offset auto --align rigid\n"
               "  arena eval --tracks tracks.csv --truth run.mcap --truth-topic '/vrpn*/pose' \\\n"
               "      --body zumo1=/vrpn_client_node/Zumo_01/pose --time-offset -1700000000.1234\n"
               "  arena eval --tracks tracks.csv --truth mocap_bag/ --track-clock host --time-offset 0\n"
               "Exit code 0 when scored; 1 when there was no ground truth to score against (no frame\n"
               "inside the truth's time span, or no robot that moved: MOTA, IDF1, HOTA are n/a; or\n"
               "mocap truth that could not be aligned); 2 for unreadable input (including a truth\n"
               "file without rows).")
    p.add_argument("--tracks", required=True, metavar="CSV", help="tracker output (arena track --tracks-out)")
    p.add_argument("--truth", required=True, metavar="CSV|BAG",
                   help="truth CSV, pose CSV, rosbag2 folder or .mcap file")
    p.add_argument("--gate-cm", type=float, default=10.0, help="match distance gate in cm (default 10)")
    p.add_argument("--all-frames", action="store_true",
                   help="count robots from the start, not only once they have moved")
    p.add_argument("--include-tentative", action="store_true",
                   help="also score rows whose state is 'tentative' (excluded by default)")
    p.add_argument("--json", metavar="OUT", help="write the scores as JSON to OUT")
    p.add_argument("--report", metavar="DIR", help="write report.md with plots into DIR")
    m = p.add_argument_group("truth on another clock or in another frame (motion capture)")
    m.add_argument("--time-offset", metavar="S|auto", default="0",
                   help="truth time + S seconds = track time (default 0); 'auto' estimates it by\n"
                        "cross-correlating the robots' speeds, refined on the positions")
    m.add_argument("--track-clock", choices=("sensor", "host"), default="sensor",
                   help="score the tracks at their sensor time t_us (default) or at their host capture\n"
                        "time host_ns (live tracks: the edge's estimate of the camera's clock on its\n"
                        "host), which lines up with truth stamped by a host's clock (ROS, mocap)")
    m.add_argument("--align", choices=("none", "rigid", "similarity"), default=None,
                   help="fit the truth's frame to the tracks' (2-D): none (default for a truth CSV),\n"
                        "rigid (default for a bag or pose CSV) or similarity (also a scale)")
    m.add_argument("--truth-topic", metavar="PATTERN", action="append", default=[],
                   help="bag: read the PoseStamped topics matching this glob (repeatable; default all)")
    m.add_argument("--body", metavar="NAME=TOPIC", action="append", default=[],
                   help="robot NAME is the bag topic TOPIC (or the pose CSV's body TOPIC); repeatable.\n"
                        "Default name: the topic's element before /pose, else its last element")
    p.set_defaults(func=run_eval)


def _load_truth(args):
    """(truth array, truth kind, description lines) of ``--truth``; raises CsvFormatError/MocapError."""
    from arena.formats.tables import TRUTH_REQUIRED, read_truth_csv
    from groundtruth.mocap import MocapError, is_pose_csv_header, read_pose_bag, read_pose_csv

    path = Path(args.truth)
    bodies = {}
    for b in args.body:
        name, sep, source = b.partition("=")
        if not sep or not name.strip() or not source.strip():
            raise MocapError(f"--body {b!r}: expected NAME=TOPIC (e.g. zumo1=/vrpn_client_node/zumo1/pose)")
        bodies[name.strip()] = source.strip()
    if path.is_dir() or path.suffix.lower() == ".mcap":
        if not path.exists():
            raise MocapError(f"truth bag not found: {path}")
        bag = read_pose_bag(path, args.truth_topic, bodies)
        stamps = "header stamps" if not bag.log_stamps else f"{bag.log_stamps} message(s) without a header stamp: log time"
        lines = [f"truth: {len(bag.topics)} rigid bod{'y' if len(bag.topics) == 1 else 'ies'} from {path} ({stamps}): "
                 + ", ".join(f"{t} -> {n}" for t, n in bag.topics.items())]
        return bag.truth, "bag", lines
    if path.is_file():
        with path.open(encoding="utf-8", errors="replace") as fh:
            header = [h.strip() for h in fh.readline().split(",")]
        if not all(c in header for c in TRUTH_REQUIRED) and is_pose_csv_header(header):
            if args.truth_topic:
                raise MocapError("--truth-topic is for a bag; a pose CSV names its bodies in a column (use --body)")
            truth = read_pose_csv(path, bodies)
            names = ", ".join(sorted(set(truth["robot"])))
            return truth, "pose-csv", [f"truth: pose CSV {path}, bodies {names or 'none'}"]
    if args.body or args.truth_topic:
        raise MocapError("--body and --truth-topic are for a bag or a pose CSV, not a truth CSV "
                         "(t_us,robot,x_m,y_m: its robot column names the robots)")
    return read_truth_csv(args.truth), "csv", []


def _alignment_lines(al) -> list[str]:
    lines = []
    if al.offset_source == "auto":
        e = al.estimate
        err = f"+-{e.stderr_us / 1000:.3f} ms" if e.stderr_us != float("inf") else "no timing in the positions"
        lines.append(f"time offset: {al.offset_us * 1e-6:+.6f} s (auto: speed cross-correlation peak "
                     f"r={e.correlation:.3f}, next peak r={e.next_best:.3f}, at {e.coarse_us * 1e-6:+.4f} s; "
                     f"refined on the positions, {err})")
        if not e.correlation >= 0.5 or e.next_best > 0.95 * e.correlation:
            lines.append("note: the speed correlation is weak or ambiguous: check the offset, or give --time-offset S")
    elif al.offset_us:
        lines.append(f"time offset: {al.offset_us * 1e-6:+.6f} s (given)")
    f = al.fit
    if f is not None and f.mode != "none":
        tf = f.transform
        lines.append(f"frame ({f.mode} fit, pairs by {f.pairing}, {f.n_pairs} pairs, {f.n_rejected} beyond the gate): "
                     f"rotation {tf.to_dict()['rotation_deg']:.4f} deg, translation ({tf.tx_m:.5f}, {tf.ty_m:.5f}) m, "
                     f"scale {tf.scale:.6f}; residual RMS {f.rms_m * 1e3:.2f} mm, max {f.max_m * 1e3:.2f} mm")
    elif f is not None:
        lines.append(f"frame: none (truth taken in the arena frame); residual RMS {f.rms_m * 1e3:.2f} mm over "
                     f"{f.n_pairs} pairs by {f.pairing}")
    return lines


def run_eval(args: argparse.Namespace) -> int:
    """Run ``arena eval``; returns the exit code."""
    from arena.formats.tables import CsvFormatError, read_tracks_csv
    from groundtruth.metrics import evaluate
    from groundtruth.mocap import MocapError, align_truth
    from groundtruth.report import format_scores, no_ground_truth, write_eval_report, write_json

    def fail(msg: str, code: int = 2) -> int:
        print(f"arena eval: {msg}", file=sys.stderr)
        return code

    if not args.gate_cm > 0:
        return fail(f"--gate-cm must be positive, got {args.gate_cm}")
    auto = str(args.time_offset).strip().lower() == "auto"
    try:
        offset_s = None if auto else float(args.time_offset)
        if offset_s is not None and not abs(offset_s) < 1e12:
            raise ValueError
    except ValueError:
        return fail(f"--time-offset expects seconds (e.g. -0.1234) or auto, got {args.time_offset!r}")
    try:
        tracks = read_tracks_csv(args.tracks, clock=args.track_clock)
        truth, kind, lines = _load_truth(args)
    except (CsvFormatError, MocapError) as exc:
        return fail(str(exc))
    if args.track_clock == "host":
        n_all = len(read_tracks_csv(args.tracks))
        lines.append(f"tracks on the host clock (host_ns): {len(tracks)} of {n_all} rows"
                     + (f"; {n_all - len(tracks)} without a host_ns (empty) left out" if n_all > len(tracks) else ""))
    if len(truth) == 0:
        return fail(f"truth file {args.truth} has a header but no rows")
    exclude = () if args.include_tentative else ("tentative",)
    mode = args.align or ("none" if kind == "csv" else "rigid")
    alignment = None
    if auto or mode != "none" or offset_s:
        try:
            alignment = align_truth(tracks, truth, time_offset_us=None if auto else offset_s * 1e6, align=mode,
                                    gate_m=args.gate_cm / 100.0, exclude_states=exclude)
        except MocapError as exc:
            return fail(f"cannot align the truth with the tracks: {exc}", 1)
        truth = alignment.truth
        lines += _alignment_lines(alignment)
    for line in lines:
        print(line)
    scores = evaluate(tracks, truth, gate_m=args.gate_cm / 100.0, moved_only=not args.all_frames,
                      exclude_states=exclude)
    print(format_scores(scores))
    meta = {"tracks": str(args.tracks), "truth": str(args.truth)}
    if alignment is not None:
        meta["alignment"] = alignment.to_dict()
    try:
        if args.json:
            write_json(args.json, scores, **meta)
            print(f"scores written to {args.json}")
        if args.report:
            path = write_eval_report(args.report, scores, tracks, truth, str(args.tracks), str(args.truth),
                                     alignment=lines, meta={k: v for k, v in meta.items() if k == "alignment"})
            print(f"report written to {path}")
    except OSError as exc:
        return fail(f"cannot write output: {exc}")
    why = no_ground_truth(scores)
    if why:
        hint = ("give --time-offset S or auto" if kind != "csv" else
                "check that --truth covers the tracks' times; --all-frames counts robots that never moved")
        return fail(f"nothing measured: {why} ({hint})", 1)
    return 0


# --------------------------------------------------------------------------------------------
# arena groundtruth
# --------------------------------------------------------------------------------------------
def register_groundtruth(sub) -> None:
    """Add ``arena groundtruth``: robot poses from an RGB webcam (ArUco markers or shell colours)."""
    from arena.session import add_zenoh_arguments

    p = sub.add_parser(
        "groundtruth", help="ground-truth robot poses from an RGB webcam (ArUco or colour)",
        formatter_class=formatter,
        description="Read a webcam (device index, video file or URL such as the simulator's MJPEG\n"
                    "stream), detect the robots with ArUco markers (unique ids and heading) or shell\n"
                    "colours (HSV + contours; the square shell's heading, known modulo 90 deg, resolved\n"
                    "by the dark front mark / window strip, else by the direction of motion), map them to\n"
                    "arena metres with a homography calibrated at shell-top height, and publish\n"
                    "arena/groundtruth/<robot>. Optionally write the CSV\n"
                    "t_us,robot,x_m,y_m,yaw_rad,u_px,v_px,detector and annotated frames.\n"
                    "Defaults for --video, --calibration, --detector and the robots come from the\n"
                    "lab config ([webcam] and [[robots]]) when --lab or ARENA_LAB is given.",
        epilog="Examples:\n"
               "  arena groundtruth --video http://127.0.0.1:8090/stream.mjpg \\\n"
               "      --calibration http://127.0.0.1:8090/calibration.json --clock stream --csv gt.csv\n"
               "  arena groundtruth --video 0 --calibration webcam_calib.json --detector aruco \\\n"
               "      --marker 0=zumo1 --marker 1=zumo2 --csv gt.csv\n"
               "  arena groundtruth --video run.avi --calibration webcam_calib.json --detector hsv \\\n"
               "      --robot zumo1=red --robot zumo2=#2850dc --no-zenoh --csv gt.csv --annotate ann.avi\n"
               "  arena groundtruth --video run.avi --sample-hsv 320,240   # print the HSV range there\n"
               "  arena groundtruth --video 0 --calibrate-out webcam_calib.json \\\n"
               "      --at 0=0.10,0.10 --at 1=1.73,0.10 --at 2=1.73,1.73 --at 3=0.10,1.73\n"
               "  arena groundtruth --lab deploy/lab.toml --csv gt.csv\n"
               "--clock and --name not given come from the lab config's [services.groundtruth] table.\n"
               "Exit code 0 when the source ends or on Ctrl-C, 2 for bad input.")
    p.add_argument("--video", metavar="SRC", help="device index, video file or URL (default: lab [webcam] source)")
    p.add_argument("--calibration", metavar="JSON|URL",
                   help="calibration JSON (file or http URL) at shell-top height (default: lab [webcam])")
    p.add_argument("--detector", choices=("aruco", "hsv"), help="detector (default: lab [webcam] or aruco)")
    p.add_argument("--robot", metavar="NAME=COLOUR", action="append", default=[],
                   help="colour detector robot: NAME=#rrggbb, NAME=red|green|..., or NAME=h,s,v:h,s,v "
                        "(an HSV range); repeatable")
    p.add_argument("--marker", metavar="ID=NAME", action="append", default=[],
                   help="ArUco id of a robot, repeatable (unknown ids are ignored when any is given)")
    p.add_argument("--no-front-mark", action="store_true",
                   help="colour detector: shells have no front mark (heading from motion only)")
    p.add_argument("--clock", choices=("host", "stream"), default=None,
                   help="frame times of a live source: host clock at capture (default), or the\n"
                        "X-World-Time-us of each MJPEG part (arena sim: the simulator's clock, the\n"
                        "time base of its event camera and truth CSV)")
    p.add_argument("--csv", metavar="OUT", help="write detections to this CSV")
    p.add_argument("--annotate", metavar="OUT", help="annotated frames: a .avi/.mp4 video or a directory of PNGs")
    p.add_argument("--name", default=None, help="service name in arena status (default webcam)")
    p.add_argument("--no-zenoh", action="store_true", help="do not publish (files only)")
    p.add_argument("--max-frames", type=int, default=None, help="stop after N frames")
    p.add_argument("--duration", type=float, default=None, help="stop after S seconds")
    p.add_argument("--sample-hsv", metavar="U,V",
                   help="print the HSV range around pixel U,V of the first frame (for the lab config) and exit")
    c = p.add_argument_group("calibrate at shell height from markers at known spots (then exit)")
    c.add_argument("--calibrate-out", metavar="JSON", help="write the calibration JSON here")
    c.add_argument("--at", metavar="ID=X,Y", action="append", default=[],
                   help="marker ID lies at arena X,Y metres (its centre), repeatable, >= 4 spread out")
    c.add_argument("--height-m", type=float, default=0.045,
                   help="height of the markers above the mats, m (default 0.045, the shell tops)")
    c.add_argument("--calib-frames", type=int, default=24, help="frames to average (default 24)")
    add_zenoh_arguments(p)
    p.set_defaults(func=run_groundtruth)


def _parse_robot_colour(text: str):
    from arena.config import NAMED_COLOURS

    name, sep, value = text.partition("=")
    if not sep or not name or not value:
        raise ValueError(f"--robot {text!r}: expected NAME=COLOUR")
    v = value.strip().lower()
    if v in NAMED_COLOURS:
        return name, tuple(NAMED_COLOURS[v])
    if v.startswith("#") and len(v) == 7:
        return name, tuple(int(v[i:i + 2], 16) for i in (1, 3, 5))
    if ":" in v:
        lo, hi = v.split(":", 1)
        return name, [[int(x) for x in lo.split(",")], [int(x) for x in hi.split(",")]]
    raise ValueError(f"--robot {text!r}: colour must be a name, #rrggbb or h,s,v:h,s,v")


def run_groundtruth(args: argparse.Namespace) -> int:
    """Run ``arena groundtruth``; returns the exit code."""
    from arena.config import ConfigError, apply_service_options
    from arena.session import load_lab_from_args
    from groundtruth.homography import CalibrationError
    from groundtruth.rgb import FrameSource, sample_hsv_range
    from groundtruth.service import SetupError, build_detector, load_calibration_any

    def fail(msg: str) -> int:
        print(f"arena groundtruth: {msg}", file=sys.stderr)
        return 2

    try:
        lab = load_lab_from_args(args)
    except ConfigError as exc:
        return fail(str(exc))
    apply_service_options(args, lab, "groundtruth")  # flags win, then [services.groundtruth], then the defaults
    cam = lab.webcam if lab is not None else None
    video = args.video if args.video is not None else (cam.source if cam else None)
    if video is None:
        return fail("no video source: give --video INDEX|FILE|URL or a lab config with [webcam] source")
    try:
        colours = dict(_parse_robot_colour(r) for r in args.robot)
        markers = {}
        for m in args.marker:
            i, sep, name = m.partition("=")
            if not sep or not name or not i.strip().isdigit():
                raise ValueError(f"--marker {m!r}: expected ID=NAME with an integer ID")
            markers[int(i)] = name
    except ValueError as exc:
        return fail(str(exc))
    try:
        source = FrameSource(video, clock=args.clock)
    except OSError as exc:
        return fail(str(exc))
    with source:
        if args.sample_hsv:
            try:
                u, v = (float(c) for c in args.sample_hsv.split(","))
                got = source.read()
                if got is None:
                    return fail(f"no frame from {video}")
                rng = sample_hsv_range(got[1], (u, v))
            except ValueError as exc:
                return fail(f"--sample-hsv: {exc}")
            print(f"hsv_range = [[{', '.join(map(str, rng.lo))}], [{', '.join(map(str, rng.hi))}]]")
            return 0
        if args.calibrate_out:
            return _calibrate(args, source)
        calib = args.calibration or (cam.calibration_file or cam.calibration if cam else None)
        if calib is None:
            return fail("no calibration: give --calibration FILE|URL or a lab [webcam] calibration")
        try:
            homography = load_calibration_any(calib)
            kind = args.detector or (cam.detector if cam else "aruco")
            detector = build_detector(kind, homography, lab.robots if lab else (), markers, colours,
                                      front_mark=not args.no_front_mark)
        except (CalibrationError, SetupError) as exc:
            return fail(str(exc))
        if kind == "hsv" and lab is not None:
            from groundtruth.rgb import colour_detectable

            for r in lab.robots:
                why = None if getattr(r, "hsv_range", None) or r.name in colours else colour_detectable(r.color_rgb)
                if why:
                    print(f"arena groundtruth: warning: robot {r.name} is not detected by colour: {why}; "
                          "give it an ArUco marker (--detector aruco) or a saturated or dark shell",
                          file=sys.stderr, flush=True)
        return _run_loop(args, lab, source, detector)


def _calibrate(args, source) -> int:
    import itertools

    from groundtruth.service import SetupError, marker_calibration

    try:
        at = {}
        for a in args.at:
            i, sep, xy = a.partition("=")
            x, y = (float(v) for v in xy.split(","))
            if not sep or not i.strip().isdigit():
                raise ValueError
            at[int(i)] = (x, y)
    except ValueError:
        print(f"arena groundtruth: --at expects ID=X,Y (e.g. 0=0.10,0.10), got {args.at}", file=sys.stderr)
        return 2
    frames = (f for _, f in itertools.islice(iter(source.read, None), max(1, args.calib_frames)))
    try:
        h, px, xy = marker_calibration(frames, at, args.height_m)
    except SetupError as exc:
        print(f"arena groundtruth: {exc}", file=sys.stderr)
        return 2
    from groundtruth.homography import save_calibration

    save_calibration(args.calibrate_out, px, xy, h.image_size, args.height_m, camera="webcam")
    err = h.reprojection_error_m(px, xy) * 100
    print(f"calibration written to {args.calibrate_out} ({len(px)} markers at {args.height_m} m, "
          f"residual max {err.max():.2f} cm)")
    return 0


def _run_loop(args, lab, source, detector) -> int:
    import contextlib

    import cv2

    from arena.clitools import session_or_exit
    from arena.service import Service, stop_on_signals
    from groundtruth.service import GroundTruthRunner, heading_counts, heading_note

    # One OpenCV thread: on 640x480 frames at 24 fps its worker pool mostly busy-waits between
    # calls, 15 -> 12 % of a core for decode + detection, with the same results.
    cv2.setNumThreads(1)
    stop = stop_on_signals()
    with contextlib.ExitStack() as stack:
        session = svc = None
        if not args.no_zenoh:
            session = stack.enter_context(session_or_exit(args, "arena groundtruth", lab=lab, wait_s=None))
            svc = stack.enter_context(Service(session, "groundtruth", args.name))
        try:
            runner = GroundTruthRunner(session, source, detector, svc, args.csv, args.annotate)
        except OSError as exc:
            print(f"arena groundtruth: cannot write output: {exc}", file=sys.stderr)
            return 2
        stack.callback(runner.close)
        print(f"arena groundtruth: {detector.name} detector on {source.source}"
              + ("" if session is None else f", publishing arena/groundtruth/* as groundtruth/{args.name}")
              + f" ({heading_note(detector)})", flush=True)
        try:
            runner.run(stop, max_frames=args.max_frames, duration_s=args.duration)
        except KeyboardInterrupt:
            pass
        except OSError as exc:
            print(f"arena groundtruth: {exc}", file=sys.stderr)
            return 2
        counts = heading_counts(detector)
        print(f"arena groundtruth: {runner.frames} frames, {runner.detections} detections, "
              f"robots seen: {', '.join(sorted(runner.seen)) or 'none'}" + (f"; {counts}" if counts else ""),
              flush=True)
    return 0

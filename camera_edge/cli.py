"""``arena edge`` and ``arena convert`` command lines."""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys

from arena.clitools import fail, formatter, number, seconds
from arena.codec_names import CODECS, DEFAULT_CODEC
from arena.config import SERVICE_OPTIONS

log = logging.getLogger("camera_edge")

EDGE_EXAMPLES = """\
Examples:
  arena edge 'tcp://127.0.0.1:9000?width=640&height=480' --camera cam0   # simulator's camera
  arena edge rec.raw --camera cam0 --speed 1 --loop          # replay a recording in real time
  arena edge prophesee: --camera cam0 --denoise --hot-pixels learn --hot-save hot.txt
  arena edge inivation: --camera cam0 --roi calib.json --roi-margin 10
  arena edge --lab lab.toml --camera cam0                    # source, size, [services.edge] options
  arena edge --list-devices                                  # attached event cameras (USB)
Options not given as flags come from the lab config's [services.edge] table (slice_ms, codec,
speed, hot_pixels, hot_learn_s, hot_save, roi, roi_margin, denoise, queue), else the defaults.
Status: arena status (events/s in, filtered, bytes/s out, encode time, drops)."""

CONVERT_EXAMPLES = """\
Examples:
  arena convert rec.raw rec.aedat4                 # EVT 3.0 RAW -> AEDAT4 (LZ4)
  arena convert rec.aedat4 rec.raw --evt 2         # -> Prophesee RAW, EVT 2.0
  arena convert paper.csv rec.raw --size 1280x720  # CSV carries no sensor size
  arena convert rec.dat rec.npz
Formats by extension: read .raw (EVT 2.0/2.1/3.0) .dat .aedat4 .csv .npy .npz;
write .raw (EVT 3.0 or 2.0) .dat .aedat4 .csv .npz .npy."""


#: Largest sensor side, px (= arena.formats.base.MAX_SENSOR_PX; not imported: the parser stays light).
MAX_SENSOR_PX = 65535


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
        if not (1 <= w <= MAX_SENSOR_PX and 1 <= h <= MAX_SENSOR_PX):
            raise ValueError
        return w, h
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must be WIDTHxHEIGHT in px, each 1-{MAX_SENSOR_PX}, e.g. 1280x720; "
                                         f"got {text!r}") from None


#: The physical range of each numeric option of ``arena edge`` (flag and ``[services.edge]`` key alike).
EDGE_RANGES = {
    "slice_ms": number(0.001, 1000.0, "ms of sensor time"),
    "speed": number(0.0, 1000.0, "x real time", note=" (0 = as fast as possible)"),
    "hot_learn_s": number(0.0, 600.0, "s", lo_open=True),
    "roi_margin": number(0, 4096, "px", integer=True),
    "denoise": number(1, 1_000_000, "µs", integer=True),
    "queue": number(1, 10_000, "windows", integer=True),
}
#: USB entries passed over that ``arena edge --list-devices`` names, at most (then how many more)
MAX_DEVICE_NOTES = 20
#: Longest --duration of ``arena edge``, s (a week; leave it out to run until stopped).
EDGE_DURATION_MAX_S = 7 * 86_400.0


def _no_events(path: str) -> str | None:
    """Why the event file ``path`` gives no event (``"no events in PATH (...)"``), or None when it
    has one, or cannot be read (its reader then says why). Reads up to the first event only."""
    import warnings

    from arena.formats import FormatError, iter_events

    try:
        if os.path.getsize(path) == 0:
            return f"no events in {path} (the file is empty, 0 bytes)"
    except OSError:
        return None
    from arena.formats import SkippedData

    skipped: dict[str, int] = {}   # what it skipped is why it has none: counted by unit, not kept
    show = warnings.showwarning

    def tally(message, category, *args, **kw) -> None:
        if isinstance(message, SkippedData):
            skipped[message.unit] = skipped.get(message.unit, 0) + message.count
        else:
            show(message, category, *args, **kw)

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always", SkippedData)
            warnings.showwarning = tally
            with iter_events(path) as reader:
                if any(chunk.size for chunk in reader):
                    return None
                invalid = reader.invalid
    except (FormatError, OSError, ValueError):
        return None
    if skipped:
        why = skip_summary(skipped).removeprefix(", ")
    else:
        why = f"{invalid} invalid events only" if invalid else "a header without events"
    return f"no events in {path} ({why})"


def skip_summary(skipped: dict[str, int]) -> str:
    """``", N UNIT skipped"`` for each unit of ``skipped`` (by name), for a summary line; a unit
    saying what happened to them instead (``"... (kept)"``) is not a skip, and has no "skipped"."""
    return "".join(f", {n} {unit}" + ("" if unit.endswith(")") else " skipped") for unit, n in sorted(skipped.items()))


def register_convert(sub) -> None:
    """Add ``arena convert``."""
    p = sub.add_parser("convert", help="convert event recordings between formats", formatter_class=formatter,
                       description="Convert an event recording to another format, chosen by extension,\n"
                                   "keeping the sensor size and absolute timestamps.", epilog=CONVERT_EXAMPLES)
    p.add_argument("input", help="input file (.raw .dat .aedat4 .csv .npy .npz)")
    p.add_argument("output", help="output file (.raw .dat .aedat4 .csv .npz .npy)")
    p.add_argument("--evt", type=int, choices=(3, 2), default=3, help="EVT version of a .raw output (default 3)")
    p.add_argument("--compression", default="lz4", choices=("lz4", "lz4high", "zstd", "zstdhigh", "none"),
                   help="packet compression of an .aedat4 output (default lz4)")
    p.add_argument("--size", type=_size, default=None, metavar="WxH",
                   help="sensor size in px (for CSV/npy inputs, which do not carry it)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (shown for inputs > 64 MB)")
    p.add_argument("--strict", action="store_true",
                   help="fail (exit 2, no output) at the first skipped part of the input: corrupt packets, "
                        "invalid events, a cut-off word (default: skip them, warn, count them in the summary)")
    p.set_defaults(func=run_convert)


def run_convert(args) -> int:
    import warnings

    from arena.formats import FormatError
    from arena.formats.base import SkippedData
    from camera_edge.convert import convert

    w, h = args.size or (None, None)
    from pathlib import Path

    from arena.formats import WRITE_EXTENSIONS
    # the converter's own checks (same file, output format) come first; then: is there anything to convert?
    src, dst = Path(args.input), Path(args.output)
    empty = (_no_events(args.input) if src.is_file() and src.resolve() != dst.resolve()
             and dst.suffix.lower() in WRITE_EXTENSIONS else None)
    if empty:   # nothing to convert: an input error, and no empty output file
        print(f"arena convert: {empty}; nothing written", file=sys.stderr)
        return 2
    big = os.path.isfile(args.input) and os.path.getsize(args.input) > 64 << 20
    skipped: dict[str, int] = {}   # what the reader skipped, by unit (its SkippedData warnings)

    def tally(message, category, *_args, **_kw) -> None:
        if not issubclass(category, SkippedData):
            print(f"arena convert: warning: {message}", file=sys.stderr)
            return
        if not skipped:   # the first one says what; the summary says how many
            print(f"arena convert: warning: {message} (see the summary; --strict makes this an error)",
                  file=sys.stderr)
        skipped[message.unit] = skipped.get(message.unit, 0) + message.count

    with warnings.catch_warnings():
        warnings.simplefilter("error" if args.strict else "always", SkippedData)
        warnings.showwarning = tally
        try:
            res = convert(args.input, args.output, evt=args.evt, compression=args.compression, width=w, height=h,
                          progress=big and not args.no_progress)
        except SkippedData as exc:
            print(f"arena convert: {exc} (--strict: stopped, no output written)", file=sys.stderr)
            return 2
        except FormatError as exc:
            print(f"arena convert: {exc}", file=sys.stderr)
            return 2
        except OSError as exc:   # a write that failed part way (EFBIG, ENOSPC) names no file: say which
            what = exc if exc.filename else f"converting {args.input} to {args.output}: {exc.strerror or exc}"
            print(f"arena convert: {what}", file=sys.stderr)
            return 2
    skipped.pop("invalid events", None)
    extra = f", {res['invalid']} invalid events skipped" if res["invalid"] else ""
    extra += skip_summary(skipped)
    print(f"{args.output}: {res['events']} events, {res['width']} x {res['height']} px{extra}")
    return 0


def register_edge(sub) -> None:
    """Add ``arena edge``."""
    from arena.session import add_zenoh_arguments

    p = sub.add_parser("edge", help="read an event camera, filter, slice, compress and publish",
                       formatter_class=formatter, epilog=EDGE_EXAMPLES,
                       description="Read events from a camera, a TCP stream or a file, filter them, cut\n"
                                   "fixed slices of sensor time and publish them compressed on\n"
                                   "arena/events/<camera> (congestion control DROP).")
    p.add_argument("source", nargs="?", help="tcp://HOST:PORT, prophesee:[SERIAL], inivation:[NAME] or a file "
                   "(.raw .dat .aedat4 .csv .npy .npz); default: the camera's source in the lab config")
    p.add_argument("--camera", default=None, help="camera name (key arena/events/<camera>; default cam0 or the "
                   "lab config's first camera)")
    p.add_argument("--list-devices", action="store_true", help="list attached event cameras and exit")
    p.add_argument("--slice-ms", type=EDGE_RANGES["slice_ms"], default=None,
                   help="slice duration in ms of sensor time, 0.001-1000 (default 10)")
    p.add_argument("--codec", choices=CODECS, default=None,
                   help=f"window codec (default {DEFAULT_CODEC}, lossless; planes-zstd-ms/1 floors times to 1 ms)")
    p.add_argument("--speed", type=EDGE_RANGES["speed"], default=None,
                   help="file replay speed, 0-1000: 1 real time, 0 as fast as possible")
    p.add_argument("--loop", action="store_true", help="replay a file forever (times keep increasing)")
    f = p.add_argument_group("filters (each optional, in this order)")
    f.add_argument("--hot-pixels", metavar="learn|FILE", default=None,
                   help="drop hot pixels: learned over --hot-learn-s, or listed in FILE (x,y lines or .npy)")
    f.add_argument("--hot-learn-s", type=EDGE_RANGES["hot_learn_s"], default=None,
                   help="learning time of hot pixels, s, up to 600 (default 2)")
    f.add_argument("--hot-save", metavar="FILE", default=None,
                   help="with --hot-pixels learn: write the learnt hot pixels to FILE (x,y lines, or .npy), "
                        "to pass as --hot-pixels FILE next time")
    f.add_argument("--roi", metavar="lab|CALIB_JSON", default=None,
                   help="keep events inside the arena: the hull of the calibration points (lab: the lab camera's)")
    f.add_argument("--roi-margin", type=EDGE_RANGES["roi_margin"], default=None,
                   help="grow the region of interest by PX, 0-4096 (default 10)")
    f.add_argument("--denoise", nargs="?", const=10_000, type=EDGE_RANGES["denoise"], default=None, metavar="DT_US",
                   help="background-activity filter: keep events with a neighbour within DT_US µs, "
                        "1-1000000 (default 10000)")
    p.add_argument("--queue", type=EDGE_RANGES["queue"], default=None,
                   help="windows queued before the oldest is dropped, 1-10000 (default 32)")
    p.add_argument("--duration", type=seconds(0.0, EDGE_DURATION_MAX_S), default=None,
                   help=f"stop after this many seconds, up to {EDGE_DURATION_MAX_S:g} (default: until stopped)")
    add_zenoh_arguments(p)
    p.set_defaults(func=run_edge_cli)


#: options of ``[services.edge]`` in the lab config (flags win) and their built-in defaults; the
#: definition (types, ranges) is :data:`arena.config.SERVICE_OPTIONS` ``["edge"]``
LAB_OPTIONS = {k: o.default for k, o in SERVICE_OPTIONS["edge"].items()}


def _apply_lab_options(args, options: dict) -> str | None:
    """Fill flags left unset from ``[services.edge]`` ``options`` then the defaults (see
    :func:`arena.config.apply_service_options`); returns an error or None."""
    from arena.config import ConfigError, fill_service_options, parse_service_options

    try:
        fill_service_options(args, "edge", parse_service_options("edge", options))
    except ConfigError as exc:
        return str(exc)
    return _check_options(args)


def _check_options(args) -> str | None:
    """Checks across options (after the flags and the lab file are merged); returns an error or None."""
    if isinstance(args.denoise, bool):  # `denoise = true` in the lab config: the default window
        args.denoise = 10_000 if args.denoise else None
    if args.denoise is not None and (not isinstance(args.denoise, int) or args.denoise <= 0):
        return f"denoise must be a time window in µs > 0 (or true), got {args.denoise!r}"
    for key, check in EDGE_RANGES.items():   # the flags were parsed by these; the lab file's values too
        v = getattr(args, key, None)
        if v is None:
            continue
        lo, hi, lo_open, hi_open, integer, what = check.range
        ok = not isinstance(v, bool) and isinstance(v, (int, float)) and (not integer or isinstance(v, int))
        if not (ok and math.isfinite(v) and (v > lo if lo_open else v >= lo) and (v < hi if hi_open else v <= hi)):
            return f"--{key.replace('_', '-')} ({key}) must be {what}, got {v!r}"
    if args.codec not in CODECS:
        return f"codec must be one of {', '.join(CODECS)}, got {args.codec!r}"
    if args.hot_save is not None and (not isinstance(args.hot_save, str) or args.hot_pixels != "learn"):
        return f"--hot-save (hot_save) takes a file name and needs --hot-pixels learn; got {args.hot_save!r}"
    return None


def _build_filters(args, width: int, height: int, lab_camera) -> list:
    from camera_edge.filters import BackgroundActivityFilter, HotPixelFilter, RoiFilter

    filters = []
    if args.hot_pixels:
        if args.hot_pixels == "learn":
            filters.append(HotPixelFilter(width, height, learn_us=int(args.hot_learn_s * 1e6)))
        else:
            try:
                filters.append(HotPixelFilter(width, height, path=args.hot_pixels))
            except ValueError as exc:
                raise fail(f"arena edge: {exc}") from None
    if args.roi:
        if args.roi == "lab":
            if lab_camera is None or not lab_camera.calibration:
                raise fail("arena edge: --roi lab needs --lab with a calibration for this camera")
            calib = lab_camera.calibration
        else:
            try:
                with open(args.roi) as fh:
                    calib = json.load(fh)
            except (OSError, ValueError) as exc:
                raise fail(f"arena edge: cannot read calibration {args.roi}: {exc}") from None
        try:
            filters.append(RoiFilter.from_calibration(calib, margin_px=args.roi_margin))
        except (KeyError, ValueError, TypeError) as exc:
            raise fail(f"arena edge: {args.roi} is not a usable calibration: {exc}") from None
        if filters[-1].mask_.shape != (height, width):
            raise fail(f"arena edge: calibration image size {filters[-1].mask_.shape[::-1]} differs "
                             f"from the sensor's {width} x {height}")
    if args.denoise is not None:
        filters.append(BackgroundActivityFilter(width, height, dt_us=args.denoise))
    return filters


def _list_devices() -> int:
    """`arena edge --list-devices`: the event cameras on USB, and the entries that could not be read."""
    from camera_edge.devices import list_devices

    notes: list[str] = []
    try:
        devices = list_devices(notes=notes)
    except RuntimeError as exc:
        print(f"arena edge: {exc}", file=sys.stderr)
        return 2
    for d in devices:
        print(d.describe())
    for line in notes[:MAX_DEVICE_NOTES]:   # a camera may hide behind an entry that cannot be read
        print(f"arena edge: {line}", file=sys.stderr)
    if len(notes) > MAX_DEVICE_NOTES:
        print(f"arena edge: and {len(notes) - MAX_DEVICE_NOTES} more USB entries skipped", file=sys.stderr)
    if not devices:
        print("no event camera found on USB (Prophesee 31f7/04b4, iniVation 152a)")
    return 0


def run_edge_cli(args) -> int:
    from arena.config import ConfigError, apply_service_options
    from arena.keys import InvalidKey, validate_name
    from arena.service import stop_on_signals
    from arena.session import load_lab_from_args, open_session
    from camera_edge.pipeline import EdgePipeline, warm_up
    from camera_edge.service import run_edge
    from camera_edge.sources import SourceError, open_source

    if args.list_devices:
        return _list_devices()
    try:
        lab = load_lab_from_args(args)
    except ConfigError as exc:
        print(f"arena edge: {exc}", file=sys.stderr)
        return 2
    cam = None
    if lab is not None and lab.cameras:
        try:
            cam = lab.camera(args.camera)
        except ConfigError as exc:
            print(f"arena edge: {exc}", file=sys.stderr)
            return 2
    apply_service_options(args, lab, "edge")  # [services.edge] was checked when the lab file was loaded
    err = _check_options(args)
    if err:
        print(f"arena edge: {err}", file=sys.stderr)
        return 2
    name = args.camera or (cam.name if cam else "cam0")
    try:
        validate_name(name, "camera name")
    except InvalidKey as exc:
        print(f"arena edge: {exc}", file=sys.stderr)
        return 2
    source_url = args.source or (cam.source if cam else None)
    if not source_url:
        print("arena edge: give a SOURCE (or --lab with a camera source); see --help", file=sys.stderr)
        return 2
    opts: dict = {}
    if args.loop:
        if ":" in source_url.split("/")[0]:
            print("arena edge: --loop applies to file sources only", file=sys.stderr)
            return 2
        opts["loop"] = True
    if source_url.lower().startswith("tcp://") and cam is not None:
        opts.update(width=cam.width, height=cam.height)
    empty = _no_events(source_url) if os.path.isfile(source_url) else None
    if empty:   # a file with nothing to publish: say so before compiling and waiting for Zenoh
        print(f"arena edge: {empty}", file=sys.stderr)
        return 2
    try:
        source = open_source(source_url, speed=args.speed, **opts)
    except SourceError as exc:
        print(f"arena edge: {exc}", file=sys.stderr)
        return 2
    stop = stop_on_signals()
    with source:
        filters = _build_filters(args, source.width, source.height, cam)
        pipeline = EdgePipeline(filters, slice_us=int(round(args.slice_ms * 1000)))
        # compile the kernels before declaring liveliness (seconds on the first run after install)
        warm_up(lambda: _build_filters(args, source.width, source.height, cam), source.width, source.height,
                args.codec, slice_us=pipeline.slicer.slice_us)
        with open_session(args, lab=lab, wait_s=None) as session:
            res = run_edge(session, source, pipeline, name, args.codec, queue_size=args.queue,
                           duration_s=args.duration, stop=stop, hot_save=args.hot_save)
    log.info("edge %s done: %s", name, res)
    # what the source skipped, as `arena convert` says it (its status: source_invalid, source_skipped)
    skips = (f", {res['invalid']} invalid events skipped" if res["invalid"] else "") + skip_summary(res["skipped"])
    print(f"arena edge {name}: {res['events_in']} events in, {res['events_kept']} kept, "
          f"{res['windows']} windows, {res['windows_dropped']} dropped in {res['wall_s']:.2f} s "
          f"(CPU {res['cpu_s']:.2f} s){skips}", file=sys.stderr)
    return 0

"""A run folder as a rosbag2 (MCAP storage): the file side of ``arena export RUN --rosbag OUT``.

Reads the run folder that ``arena demo`` writes (or any folder with the same files):

- ``tracks.csv`` (required; the tracker's ``t_us,track_id,robot,x_m,y_m,yaw_rad,...``) ->
  ``/arena/robots/<name>/pose`` (``geometry_msgs/msg/PoseStamped``) and ``/tf``
  (``tf2_msgs/msg/TFMessage``, one per tracker update, ``arena`` -> ``<name>``);
- ``groundtruth.csv`` (webcam ground truth, when present) -> ``/arena/groundtruth/<name>/pose``;
- ``truth.csv`` (the simulator's exact poses, when present) -> ``/arena/sim/truth/<name>/pose``;

``<name>`` is :func:`ros2.convert.entity_name`: the robot's name, else ``track_<id>``. The CSV
columns are read here by name (the formats of ``tracker/pipeline.py`` and
``groundtruth/metrics.py``; services share only ``arena/``, so this reader is this package's own).

Stamps: header stamp = bag receive time = the row's ``t_us`` x 1000 ns (the sensor clock of the
run: in ``arena demo`` every file shares the simulator's clock), plus ``offset_ns``; with
``stamps="wall"`` the offset is estimated from the tracks in ``arena.mcap`` (the tracker's
publish time against the sensor time it carries: :func:`ros2.convert.clock_offset_ns`).
"""

from __future__ import annotations

import csv
import json
import math
import shutil
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path

from ros2.cdr import INSTALL_HINT, MissingRosbags, Serializer
from ros2.convert import (POSE_TYPE, TF_TOPIC, TF_TYPE, Pose, RosNameError, clock_offset_ns, entity_name,
                          groundtruth_topic, pose_topic, ros_token, sim_truth_topic, stamp_ns, tf_groups)

#: rosbag2 metadata version written (rosbags writes 8 or 9; 8 is the older, read by more distros)
BAG_VERSION = 8


class ExportError(ValueError):
    """The run folder or the output cannot be used; the text says what to do (exit 2)."""


@dataclass
class RunPoses:
    """What a run folder holds, as poses per topic (stamps not yet shifted)."""

    tracks: dict[str, list[Pose]] = field(default_factory=dict)       # topic -> poses
    groundtruth: dict[str, list[Pose]] = field(default_factory=dict)
    truth: dict[str, list[Pose]] = field(default_factory=dict)
    track_rows: int = 0
    unknown_yaw: int = 0        # track rows without a heading: NaN orientation, no transform
    skipped_truth_rows: int = 0  # truth/ground-truth rows without x/y (robot not seen)


@dataclass
class ExportResult:
    """What :func:`export_run` wrote: messages per topic, the stamp offset used, and counts."""

    path: Path
    messages: dict[str, int]
    offset_ns: int
    stamps: str
    track_rows: int
    unknown_yaw: int
    skipped_truth_rows: int

    @property
    def total(self) -> int:
        return sum(self.messages.values())


# ----------------------------------------------------------------------------------------------
# reading


def _rows(path: Path, required: tuple[str, ...], what: str) -> Iterable[tuple[int, dict[str, str]]]:
    try:
        fh = path.open(newline="", encoding="utf-8")
    except OSError as exc:
        raise ExportError(f"cannot read {path}: {exc.strerror or exc}") from None
    with fh:
        try:
            reader = csv.reader(fh)
            header = [h.strip() for h in next(reader, [])]
            missing = [c for c in required if c not in header]
            if missing:
                raise ExportError(f"{path}: the {what} header lacks {', '.join(missing)} (found "
                                  f"{','.join(header) or 'nothing'}): is this the run folder's {path.name}?")
            for line, r in enumerate(reader, start=2):
                if r and any(c.strip() for c in r):
                    yield line, {h: (r[i].strip() if i < len(r) else "") for i, h in enumerate(header)}
        except UnicodeDecodeError:
            raise ExportError(f"{path} is not a text CSV: give the {what} CSV of a run folder") from None
        except csv.Error as exc:
            raise ExportError(f"{path} is not a readable CSV ({exc})") from None


def _num(path: Path, line: int, row: dict, col: str, kind=float, optional: bool = False):
    s = row.get(col, "")
    if s == "":
        if optional:
            return math.nan
        raise ExportError(f"{path}: line {line}, column {col} is empty")
    try:
        return int(s) if kind is int else float(s)
    except ValueError:
        raise ExportError(f"{path}: line {line}, column {col}: cannot read {s!r} as a number") from None


def read_tracks(path: Path) -> tuple[dict[str, list[Pose]], int, int]:
    """Poses per topic of a tracks CSV, rows counted and rows without a yaw."""
    out: dict[str, list[Pose]] = {}
    origin: dict[str, str] = {}      # ROS name -> the robot name (or track id) it was made from
    rows = unknown = 0
    for line, r in _rows(path, ("t_us", "track_id", "x_m", "y_m"), "tracks"):
        robot = r.get("robot", "")
        try:
            name = entity_name(robot, r["track_id"])
        except RosNameError as exc:
            raise ExportError(f"{path}: line {line}: {exc}") from None
        source = robot or f"track {r['track_id']}"
        if origin.setdefault(name, source) != source:
            raise ExportError(f"{path}: line {line}: {source!r} and {origin[name]!r} both become the ROS 2 name "
                              f"{name!r}: rename one of the robots (ROS 2 names hold letters, digits and '_')")
        yaw = _num(path, line, r, "yaw_rad", optional=True)
        pose = Pose(name, stamp_ns(_num(path, line, r, "t_us", int)),
                    _num(path, line, r, "x_m"), _num(path, line, r, "y_m"), yaw)
        out.setdefault(pose_topic(name), []).append(pose)
        rows += 1
        unknown += not math.isfinite(yaw)
    return out, rows, unknown


def read_truth(path: Path, topic_of) -> tuple[dict[str, list[Pose]], int]:
    """Poses per topic of a truth or ground-truth CSV (rows without x/y skipped and counted)."""
    out: dict[str, list[Pose]] = {}
    skipped = 0
    for line, r in _rows(path, ("t_us", "robot", "x_m", "y_m"), "truth"):
        x, y = _num(path, line, r, "x_m", optional=True), _num(path, line, r, "y_m", optional=True)
        if not (math.isfinite(x) and math.isfinite(y)):
            skipped += 1
            continue
        try:
            name = ros_token(r["robot"])
        except RosNameError as exc:
            raise ExportError(f"{path}: line {line}: {exc}") from None
        pose = Pose(name, stamp_ns(_num(path, line, r, "t_us", int)), x, y,
                    _num(path, line, r, "yaw_rad", optional=True))
        out.setdefault(topic_of(name), []).append(pose)
    return out, skipped


def wall_offset_ns(mcap_path: Path) -> int:
    """Offset from the run's sensor clock to the host wall clock (ns), from the tracks recorded in
    ``arena.mcap``: :func:`ros2.convert.clock_offset_ns` over (publish time, ``stamp_us``)."""
    from mcap.reader import make_reader

    if not mcap_path.is_file():
        raise ExportError(f"--stamps wall needs the run's recording {mcap_path}, which is missing: "
                          "use --stamps sensor (the default)")

    def pairs():
        with mcap_path.open("rb") as fh:
            for _, channel, message in make_reader(fh).iter_messages():
                if not channel.topic.startswith("arena/robots/") or channel.message_encoding != "json":
                    continue
                try:
                    d = json.loads(message.data)
                except ValueError:
                    continue
                t_us, pub = d.get("stamp_us"), d.get("tracker_publish_ns")
                if isinstance(t_us, int) and isinstance(pub, int) and pub > 0:
                    yield pub, t_us
    try:
        offset = clock_offset_ns(pairs())
    except Exception as exc:  # noqa: BLE001 - mcap raises its own errors for a damaged file
        raise ExportError(f"cannot read {mcap_path} for --stamps wall ({exc}): use --stamps sensor") from None
    if offset is None:
        raise ExportError(f"{mcap_path} has no recorded track with a publish time: use --stamps sensor")
    return offset


def read_run(run_dir: Path) -> RunPoses:
    """The poses of a run folder; raises :class:`ExportError` for a folder that is not a run or
    has no track."""
    run_dir = Path(run_dir)
    tracks_csv = run_dir / "tracks.csv"
    if not run_dir.is_dir():
        raise ExportError(f"{run_dir} is not a folder: give a run folder of `arena demo` (it holds tracks.csv)")
    if not tracks_csv.is_file():
        raise ExportError(f"{run_dir} is not a run folder (no tracks.csv): give the folder `arena demo` "
                          "printed as 'run folder: ...'")
    run = RunPoses()
    run.tracks, run.track_rows, run.unknown_yaw = read_tracks(tracks_csv)
    if run.track_rows == 0:
        raise ExportError(f"{tracks_csv} has no track (only its header): nothing to export; "
                          "was the tracker running during the run?")
    for fname, topic_of, attr in (("groundtruth.csv", groundtruth_topic, "groundtruth"),
                                  ("truth.csv", sim_truth_topic, "truth")):
        if (run_dir / fname).is_file():
            poses, skipped = read_truth(run_dir / fname, topic_of)
            setattr(run, attr, poses)
            run.skipped_truth_rows += skipped
    return run


# ----------------------------------------------------------------------------------------------
# writing


def _prepare_out(out: Path, run_dir: Path, force: bool) -> None:
    if not out.exists():
        if not out.parent.is_dir():
            raise ExportError(f"folder {out.parent} does not exist: create it or give another OUT")
        return
    if not force:
        raise ExportError(f"{out} exists: give another OUT, or --force to replace it")
    if out.is_dir():
        inside = out.resolve()
        if inside == run_dir.resolve() or inside in run_dir.resolve().parents:
            raise ExportError(f"{out} holds the run folder itself: give another OUT")
        if not (out / "metadata.yaml").is_file():
            raise ExportError(f"{out} is a folder but not a rosbag2 (no metadata.yaml): --force only replaces "
                              "a bag; remove it yourself or give another OUT")
        shutil.rmtree(out)
    else:
        raise ExportError(f"{out} is a file, not a rosbag2 folder: --force only replaces a bag; give another OUT")


def write_bag(out: Path, run: RunPoses, serializer: Serializer, metadata: dict[str, str] | None = None) -> dict[str, int]:
    """Write ``run`` as a rosbag2 with MCAP storage at ``out`` (a new folder); messages in stamp
    order; returns messages per topic."""
    try:
        from rosbags.rosbag2 import StoragePlugin, Writer
    except ImportError:   # the optional 'ros2' extra
        raise MissingRosbags(f"writing a rosbag2 needs the Python package 'rosbags': {INSTALL_HINT}") from None

    typestore = serializer.typestore
    items: list[tuple[int, str, bytes]] = []
    for group in (run.tracks, run.groundtruth, run.truth):
        for topic, poses in group.items():
            items += [(p.stamp_ns, topic, serializer.pose_cdr(p)) for p in poses]
    all_tracks = [p for poses in run.tracks.values() for p in poses]
    items += [(g[0].stamp_ns, TF_TOPIC, serializer.tf_cdr(g)) for g in tf_groups(all_tracks)]
    items.sort(key=lambda it: it[0])          # stable: same-stamp messages keep their file order
    counts: dict[str, int] = {}
    writer = Writer(out, version=BAG_VERSION, storage_plugin=StoragePlugin.MCAP)
    with writer:
        for key, value in (metadata or {}).items():
            writer.set_custom_data(key, value)
        conns = {}
        for topic in [*run.tracks, *run.groundtruth, *run.truth]:
            conns[topic] = writer.add_connection(topic, POSE_TYPE, typestore=typestore)
        if TF_TOPIC in {t for _, t, _ in items}:
            conns[TF_TOPIC] = writer.add_connection(TF_TOPIC, TF_TYPE, typestore=typestore)
        for stamp, topic, data in items:
            writer.write(conns[topic], stamp, data)
            counts[topic] = counts.get(topic, 0) + 1
    return counts


def export_run(run_dir: str | Path, out: str | Path, serializer: Serializer, *, force: bool = False,
               stamps: str = "sensor", metadata: dict[str, str] | None = None) -> ExportResult:
    """Export the run folder ``run_dir`` as the rosbag2 ``out`` (see the module docstring).
    Raises :class:`ExportError` for a bad run folder or output; a partly written bag is removed."""
    run_dir, out = Path(run_dir), Path(out)
    if stamps not in ("sensor", "wall"):
        raise ExportError(f"--stamps {stamps!r}: expected sensor or wall")
    run = read_run(run_dir)   # the run is checked before the recording is read or OUT touched
    offset = wall_offset_ns(run_dir / "arena.mcap") if stamps == "wall" else 0
    if offset:
        for group in (run.tracks, run.groundtruth, run.truth):
            for topic, poses in group.items():
                group[topic] = [replace(p, stamp_ns=p.stamp_ns + offset) for p in poses]
    _prepare_out(out, run_dir, force)
    meta = {"arena.run": str(run_dir.resolve()), "arena.stamps": stamps, "arena.offset_ns": str(offset),
            **(metadata or {})}
    try:
        counts = write_bag(out, run, serializer, meta)
    except ValueError as exc:          # a stamp before 0 (split_stamp)
        shutil.rmtree(out, ignore_errors=True)
        raise ExportError(f"cannot export {run_dir}: {exc}") from None
    except BaseException:
        shutil.rmtree(out, ignore_errors=True)
        raise
    return ExportResult(out, counts, offset, stamps, run.track_rows, run.unknown_yaw, run.skipped_truth_rows)

"""The tracks CSV and the truth CSVs: the one definition of each header, dtype, writer and reader.

Three files, two kinds (one module, because the two readers share their CSV parsing and their
error type; in metres, radians counter-clockwise from the arena +x axis, m/s, px, times in µs):

* **tracks** (``tracks.csv``, the tracker's output): :data:`TRACK_CSV_HEADER`
  ``t_us,track_id,robot,x_m,y_m,yaw_rad,vx_mps,vy_mps,u_px,v_px,state,n_events,host_ns``, an empty
  cell where unknown; ``host_ns`` is the host capture time of ``t_us`` (ns since the Unix epoch)
  when the tracker knew it. Written by :class:`TrackCsvWriter` (track objects as the trackers
  report them, or :data:`TRACK_DTYPE` arrays), read by :func:`read_tracks_csv`.
* **truth**, two formats with one reader (:func:`read_truth_csv`, which needs
  :data:`TRUTH_REQUIRED` and ignores the other columns):

  - the simulator's exact poses (``truth.csv``, >= 200 Hz): :data:`TRUTH_CSV_HEADER`
    ``t_us,robot,x_m,y_m,yaw_rad,vx_mps,vy_mps``, written by :class:`TruthCsvWriter`;
  - the webcam ground truth (``groundtruth.csv``, ~24 fps): :data:`GROUNDTRUTH_CSV_HEADER`
    ``t_us,robot,x_m,y_m,yaw_rad,u_px,v_px,detector`` (no velocity; the detection's image
    position and detector), written by :class:`GroundTruthCsvWriter`.

Readers raise :class:`CsvFormatError` (a ``ValueError``) naming the file, line and column.
Pure: numpy and the ``csv`` module, no clocks, no sockets.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import IO

import numpy as np

__all__ = ["CsvFormatError", "TRACK_CSV_HEADER", "TRACK_REQUIRED", "TRACK_DTYPE", "TrackCsvWriter", "tracks_array",
           "write_tracks_csv", "read_tracks_csv", "TRUTH_CSV_HEADER", "GROUNDTRUTH_CSV_HEADER", "TRUTH_REQUIRED",
           "TRUTH_DTYPE", "TruthCsvWriter", "write_truth_csv", "GroundTruthCsvWriter", "read_truth_csv"]

#: Columns of the tracks CSV.
TRACK_CSV_HEADER = ("t_us", "track_id", "robot", "x_m", "y_m", "yaw_rad", "vx_mps", "vy_mps",
                    "u_px", "v_px", "state", "n_events", "host_ns")
#: What :func:`read_tracks_csv` needs of a tracks CSV's header (the others are optional).
TRACK_REQUIRED = ("t_us", "track_id", "x_m", "y_m")
#: Structured dtype of tracks: NaN for unknown floats, "" for unknown strings, -1 for unknown n_events.
TRACK_DTYPE = np.dtype([
    ("t_us", "<i8"), ("track_id", "U64"), ("robot", "U64"), ("x_m", "<f8"), ("y_m", "<f8"),
    ("yaw_rad", "<f8"), ("vx_mps", "<f8"), ("vy_mps", "<f8"), ("u_px", "<f8"), ("v_px", "<f8"),
    ("state", "U16"), ("n_events", "<i8"),
])

#: Columns of the simulator's truth CSV (exact poses and velocities).
TRUTH_CSV_HEADER = ("t_us", "robot", "x_m", "y_m", "yaw_rad", "vx_mps", "vy_mps")
#: Columns of the webcam ground-truth CSV (``yaw_rad`` ``nan`` when unknown).
GROUNDTRUTH_CSV_HEADER = ("t_us", "robot", "x_m", "y_m", "yaw_rad", "u_px", "v_px", "detector")
#: What :func:`read_truth_csv` needs of a truth CSV's header (both formats have it).
TRUTH_REQUIRED = ("t_us", "robot", "x_m", "y_m")
#: Structured dtype of truth / ground truth: NaN where unknown.
TRUTH_DTYPE = np.dtype([
    ("t_us", "<i8"), ("robot", "U64"), ("x_m", "<f8"), ("y_m", "<f8"), ("yaw_rad", "<f8"),
    ("vx_mps", "<f8"), ("vy_mps", "<f8"),
])


class CsvFormatError(ValueError):
    """A tracks or truth CSV that cannot be read: the message names the file, line and column."""


# ----------------------------------------------------------------------------------------------
# tracks


def _fmt(x: float | None, digits: int) -> str:
    return "" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


class TrackCsvWriter:
    """Writes tracks as CSV rows with :data:`TRACK_CSV_HEADER` on ``stream`` (opened with
    ``newline=""``): m and rad to 5 decimals, m/s to 4, px to 2; empty = unknown.

    :meth:`write` takes track objects as the trackers report them (attributes ``t_us``,
    ``track_id``, ``robot`` (None: unknown), ``x``, ``y``, ``yaw``, ``vx``, ``vy``, ``u``, ``v``,
    ``state``, ``n_events``); :meth:`write_array` a :data:`TRACK_DTYPE` array (n_events -1:
    empty). ``host_ns``: the host capture time of ``t_us`` (ns since the epoch), written when the
    caller knows the sensor-to-host offset of the window (``write(..., sensor_to_host_ns=...)``)."""

    def __init__(self, stream: IO[str]) -> None:
        self._w = csv.writer(stream, lineterminator="\n")
        self._w.writerow(TRACK_CSV_HEADER)

    def _row(self, t_us, track_id, robot, x, y, yaw, vx, vy, u, v, state, n_events, host) -> None:
        self._w.writerow([t_us, track_id, robot, _fmt(x, 5), _fmt(y, 5), _fmt(yaw, 5), _fmt(vx, 4), _fmt(vy, 4),
                          _fmt(u, 2), _fmt(v, 2), state, n_events, host])

    def write(self, tracks: Iterable, sensor_to_host_ns: int | None = None) -> int:
        """Write track objects; returns the number of rows written."""
        n = 0
        for tr in tracks:
            host = "" if sensor_to_host_ns is None else int(tr.t_us) * 1000 + int(sensor_to_host_ns)
            self._row(tr.t_us, tr.track_id, tr.robot or "", tr.x, tr.y, tr.yaw, tr.vx, tr.vy, tr.u, tr.v,
                      tr.state, tr.n_events, host)
            n += 1
        return n

    def write_array(self, tracks: np.ndarray) -> int:
        """Write a :data:`TRACK_DTYPE` array (no host times); returns the number of rows written."""
        for r in tracks.tolist():
            t_us, track_id, robot, x, y, yaw, vx, vy, u, v, state, n_events = r
            self._row(t_us, track_id, robot, x, y, yaw, vx, vy, u, v, state, "" if n_events < 0 else n_events, "")
        return len(tracks)


def tracks_array(tracks: Iterable) -> np.ndarray:
    """Track objects (as :meth:`TrackCsvWriter.write` takes them) as a :data:`TRACK_DTYPE` array,
    at full precision (what reading their CSV back gives, without its rounding)."""
    rows = [(tr.t_us, str(tr.track_id), tr.robot or "", tr.x, tr.y, tr.yaw, tr.vx, tr.vy, tr.u, tr.v,
             tr.state, tr.n_events) for tr in tracks]
    return np.array(rows, dtype=TRACK_DTYPE) if rows else np.zeros(0, TRACK_DTYPE)


def write_tracks_csv(path: str | Path, tracks: np.ndarray) -> None:
    """Write a :data:`TRACK_DTYPE` array to ``path`` with :class:`TrackCsvWriter`."""
    with Path(path).open("w", newline="") as fh:
        TrackCsvWriter(fh).write_array(tracks)


# ----------------------------------------------------------------------------------------------
# truth


class TruthCsvWriter:
    """Incremental truth CSV writer: :data:`TRUTH_CSV_HEADER` (robot = name; metres, radians CCW
    from arena +x to 5 decimals, m/s to 4; arena frame).

    :meth:`write` takes rows of 7 fields in the header's order: with ``robot_names``, the robot
    field is an index into them (the simulator's truth arrays); without, it is the name
    (a :data:`TRUTH_DTYPE` array)."""

    def __init__(self, path: str | Path, robot_names: Sequence[str] | None = None):
        self.path = Path(path)
        self.names = None if robot_names is None else list(robot_names)
        self._f = open(self.path, "w")
        self._f.write(",".join(TRUTH_CSV_HEADER) + "\n")

    def write(self, truth: np.ndarray) -> None:
        """Append truth rows (see the class)."""
        names = self.names
        # plain tuples: reading numpy record fields one by one cost 5x more (the simulator
        # writes 4 robots x 1 kHz rows)
        if names is None:
            self._f.writelines(f"{t},{r},{x:.5f},{y:.5f},{a:.5f},{vx:.4f},{vy:.4f}\n"
                               for t, r, x, y, a, vx, vy in truth.tolist())
        else:
            self._f.writelines(f"{t},{names[r]},{x:.5f},{y:.5f},{a:.5f},{vx:.4f},{vy:.4f}\n"
                               for t, r, x, y, a, vx, vy in truth.tolist())

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> "TruthCsvWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def write_truth_csv(path: str | Path, truth: np.ndarray, robot_names: Sequence[str] | None = None) -> Path:
    """Write truth rows to ``path`` with :class:`TruthCsvWriter` (``robot_names``: see there)."""
    with TruthCsvWriter(path, robot_names) as w:
        w.write(truth)
    return Path(path)


class GroundTruthCsvWriter:
    """Writes webcam detections to a CSV with the :data:`GROUNDTRUTH_CSV_HEADER` header: objects
    with ``t_us``, ``robot``, ``x_m``, ``y_m``, ``yaw_rad`` (NaN: unknown, written ``nan``),
    ``u_px``, ``v_px``, ``detector``; m and rad to 5 decimals (0.1 mm, 1e-5 rad), px to 2."""

    def __init__(self, path: str | Path):
        self._f = open(path, "w", newline="")
        self._w = csv.writer(self._f)
        self._w.writerow(GROUNDTRUTH_CSV_HEADER)

    def write(self, detections: Iterable) -> None:
        for d in detections:
            self._w.writerow([d.t_us, d.robot, f"{d.x_m:.5f}", f"{d.y_m:.5f}",
                              "nan" if math.isnan(d.yaw_rad) else f"{d.yaw_rad:.5f}",
                              f"{d.u_px:.2f}", f"{d.v_px:.2f}", d.detector])

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> "GroundTruthCsvWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# ----------------------------------------------------------------------------------------------
# readers


def _read_csv(path: str | Path, required: Sequence[str], what: str) -> tuple[list[str], list[list[str]]]:
    path = Path(path)
    if not path.is_file():
        raise CsvFormatError(f"{what} file not found: {path}")
    try:
        with path.open(newline="", encoding="utf-8") as fh:
            reader = csv.reader(fh)
            header = next(reader, None)
            if header is None:
                raise CsvFormatError(f"{what} file {path} is empty (expected a header with {','.join(required)})")
            header = [h.strip() for h in header]
            missing = [c for c in required if c not in header]
            if missing:
                raise CsvFormatError(
                    f"{what} file {path}: header lacks column(s) {', '.join(missing)}; "
                    f"found {','.join(header)}")
            rows = [r for r in reader if r and any(c.strip() for c in r)]
    except UnicodeDecodeError as exc:
        bad = exc.object[exc.start:exc.start + 1].hex()
        raise CsvFormatError(f"{what} file {path} is not a text CSV (byte 0x{bad} is not UTF-8): give the "
                             f"CSV with the header {','.join(required)},...") from None
    except csv.Error as exc:
        raise CsvFormatError(f"{what} file {path} is not a readable CSV ({exc})") from None
    return header, rows


def _column(header: list[str], rows: list[list[str]], name: str, kind: str, path, default=None):
    """Parse one column: kind 'i' (int), 'f' (float, '' -> NaN) or 's' (str)."""
    if name not in header:
        n = len(rows)
        if kind == "f":
            return np.full(n, np.nan)
        if kind == "i":
            return np.full(n, -1 if default is None else default, dtype=np.int64)
        return np.full(n, "", dtype=object)
    j = header.index(name)
    out = []
    for i, r in enumerate(rows):
        s = r[j].strip() if j < len(r) else ""
        try:
            if kind == "s":
                out.append(s)
            elif kind == "f":
                out.append(float(s) if s else math.nan)
            elif s == "":
                if default is None:
                    raise ValueError("empty")
                out.append(default)
            else:
                out.append(int(float(s)) if ("." in s or "e" in s.lower()) else int(s))
        except (ValueError, OverflowError):
            raise CsvFormatError(f"{path}: line {i + 2}, column {name}: cannot read {s[:40]!r} as "
                                 f"{ {'i': 'an integer', 'f': 'a number'}[kind] }") from None
    try:
        return np.asarray(out, dtype=object if kind == "s" else (np.float64 if kind == "f" else np.int64))
    except OverflowError:   # an integer beyond 64 bits
        raise CsvFormatError(f"{path}: column {name}: a value is out of range for a 64-bit integer") from None


def read_tracks_csv(path: str | Path, clock: str = "sensor") -> np.ndarray:
    """Read a tracks CSV into a :data:`TRACK_DTYPE` array (times µs, metres, rad, m/s, px).

    Required columns: :data:`TRACK_REQUIRED`; the others of :data:`TRACK_CSV_HEADER` are optional.
    ``clock="host"``: ``t_us`` becomes the rows' host capture time (the ``host_ns`` column of live
    tracks, µs since the epoch); rows without one (an empty cell) are left out, a file with none
    is an error, and so is a negative one (a broken value, not an absent one).
    Raises :class:`CsvFormatError` for a missing or empty file, a wrong header or a bad value.
    """
    if clock not in ("sensor", "host"):
        raise ValueError(f"clock must be 'sensor' or 'host', got {clock!r}")
    header, rows = _read_csv(path, TRACK_REQUIRED, "tracks")
    if clock == "host":
        host = _column(header, rows, "host_ns", "i", path, default=-1)   # an empty cell: -1, absent
        if "host_ns" in header:   # a host time before the epoch is a broken value, not an absent one
            j = header.index("host_ns")
            bad = [i for i, r in enumerate(rows) if host[i] < 0 and j < len(r) and r[j].strip()]
            if bad:
                raise CsvFormatError(f"{path}: line {bad[0] + 2}, column host_ns: {rows[bad[0]][j].strip()[:40]} "
                                     "is negative (ns since the Unix epoch, >= 0; leave the cell empty when "
                                     "the host time is unknown)")
        if not (host >= 0).any():
            raise CsvFormatError(f"{path}: no row has a host_ns (tracks of a file replayed faster than real "
                                 "time, or of an older tracker): score on the sensor clock")
        rows = [r for r, h in zip(rows, host) if h >= 0]
        host = host[host >= 0]
    out = np.empty(len(rows), dtype=TRACK_DTYPE)
    out["t_us"] = host // 1000 if clock == "host" else _column(header, rows, "t_us", "i", path)
    for name in ("track_id", "robot", "state"):
        out[name] = _column(header, rows, name, "s", path)
    for name in ("x_m", "y_m", "yaw_rad", "vx_mps", "vy_mps", "u_px", "v_px"):
        out[name] = _column(header, rows, name, "f", path)
    out["n_events"] = _column(header, rows, "n_events", "i", path, default=-1)
    if np.any(out["track_id"] == ""):
        line = int(np.flatnonzero(out["track_id"] == "")[0]) + 2
        raise CsvFormatError(f"{path}: line {line}: empty track_id")
    return out


def read_truth_csv(path: str | Path) -> np.ndarray:
    """Read a truth or ground-truth CSV (either format) into a :data:`TRUTH_DTYPE` array.

    Required columns: :data:`TRUTH_REQUIRED`; ``yaw_rad``, ``vx_mps``, ``vy_mps`` are used when
    present; other columns (``u_px``, ``detector``, ...) are ignored. Rows with empty x/y (robot
    not seen) are kept with NaN (the scorer skips them).
    """
    header, rows = _read_csv(path, TRUTH_REQUIRED, "truth")
    out = np.empty(len(rows), dtype=TRUTH_DTYPE)
    out["t_us"] = _column(header, rows, "t_us", "i", path)
    out["robot"] = _column(header, rows, "robot", "s", path)
    for name in ("x_m", "y_m", "yaw_rad", "vx_mps", "vy_mps"):
        out[name] = _column(header, rows, name, "f", path)
    if np.any(out["robot"] == ""):
        line = int(np.flatnonzero(out["robot"] == "")[0]) + 2
        raise CsvFormatError(f"{path}: line {line}: empty robot name")
    return out

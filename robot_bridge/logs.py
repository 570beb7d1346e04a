"""Telemetry logs: one CSV per robot per mission plus a JSON manifest.

Nothing may be lost quietly:

* every row is written and flushed to the OS at once (a killed process loses nothing
  that was logged; ``fsync`` every ``fsync_interval_s`` bounds the loss on power failure);
* a file that reaches ``max_bytes`` is closed and continued in ``<stem>.partNNN.csv``;
* sequence gaps of the link become explicit ``gap`` rows (``missing`` = packets lost),
  so a reader can prove that every sample the robot sent is either a row or counted.

File names: ``<dir>/<robot>_<mission_id>.csv`` (then ``.part002.csv`` ...) and
``<dir>/<robot>_<mission_id>.json``. Units in the CSV: host time ns (``time.time_ns``),
robot time µs (unwrapped), encoder counts, wheel speeds m/s, accel m/s², gyro rad/s,
mag µT (body frame), battery mV, motor power -400..400.
"""

from __future__ import annotations

import csv
import io
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

COLUMNS = (
    "host_time_ns", "robot_time_us", "seq", "event", "missing",
    "enc_left", "enc_right", "speed_left", "speed_right",
    "accel_x", "accel_y", "accel_z", "gyro_x", "gyro_y", "gyro_z", "mag_x", "mag_y", "mag_z",
    "battery_mv", "power_left", "power_right", "phase",
)


@dataclass
class Sample:
    """One telemetry row (see module docstring for units)."""

    host_time_ns: int
    robot_time_us: int
    seq: int
    enc_left: int
    enc_right: int
    speed_left: float
    speed_right: float
    accel: tuple[float, float, float]
    gyro: tuple[float, float, float]
    mag: tuple[float, float, float]
    battery_mv: int
    power_left: int
    power_right: int
    phase: str = ""


def _atomic_json(path: Path, data: dict) -> None:
    tmp = path.with_suffix(".json.tmp")
    with open(tmp, "w", encoding="utf-8") as f:
        json.dump(data, f, indent=2, sort_keys=True, default=str)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


class MissionLog:
    """Writer of one robot's mission log. Use as a context manager.

    Args:
        directory: where to write (created if missing).
        robot: robot name.
        mission_id: unique id of the mission (e.g. ``20261123T101500Z-circle``).
        manifest: what to record about the mission (pattern, params, mode, start pose...).
        max_bytes: rotate the CSV when it reaches this size.
        fsync_interval_s: fsync the CSV at most this often.
    """

    def __init__(self, directory: str | os.PathLike, robot: str, mission_id: str, manifest: dict | None = None,
                 max_bytes: int = 50 * 1024 * 1024, fsync_interval_s: float = 1.0):
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.robot = robot
        self.mission_id = mission_id
        self.stem = f"{robot}_{mission_id}"
        self.max_bytes = max_bytes
        self.fsync_interval_s = fsync_interval_s
        self.rows = 0
        self.gap_rows = 0
        self.missing = 0
        self.files: list[str] = []
        self.manifest_path = self.dir / f"{self.stem}.json"
        self._manifest = {"robot": robot, "mission_id": mission_id, "status": "running",
                          "started_ns": time.time_ns(), "columns": list(COLUMNS), **(manifest or {})}
        self._f: io.TextIOWrapper | None = None
        self._w = None
        self._last_sync = time.monotonic()
        self._open_part()
        self._write_manifest()

    def _open_part(self) -> None:
        if self._f is not None:
            self._f.flush()
            os.fsync(self._f.fileno())
            self._f.close()
        n = len(self.files) + 1
        name = f"{self.stem}.csv" if n == 1 else f"{self.stem}.part{n:03d}.csv"
        self._f = open(self.dir / name, "w", newline="", encoding="utf-8")
        self._w = csv.writer(self._f)
        self._w.writerow(COLUMNS)
        self._f.flush()
        self.files.append(name)

    def _write_manifest(self) -> None:
        self._manifest.update(files=self.files, rows=self.rows, gap_rows=self.gap_rows, missing=self.missing)
        _atomic_json(self.manifest_path, self._manifest)

    def _emit(self, row: list) -> None:
        self._w.writerow(row)
        self._f.flush()
        now = time.monotonic()
        if now - self._last_sync >= self.fsync_interval_s:
            os.fsync(self._f.fileno())
            self._last_sync = now
        if self._f.tell() >= self.max_bytes:
            self._open_part()
            self._write_manifest()

    def sample(self, s: Sample) -> None:
        """Append one telemetry row (flushed at once)."""
        self._emit([s.host_time_ns, s.robot_time_us, s.seq, "sample", 0, s.enc_left, s.enc_right,
                    f"{s.speed_left:.5f}", f"{s.speed_right:.5f}",
                    *(f"{v:.5f}" for v in s.accel), *(f"{v:.5f}" for v in s.gyro), *(f"{v:.4f}" for v in s.mag),
                    s.battery_mv, s.power_left, s.power_right, s.phase])
        self.rows += 1

    def gap(self, host_time_ns: int, first_missing_seq: int, missing: int, phase: str = "") -> None:
        """Record that ``missing`` robot packets starting at ``first_missing_seq`` never arrived."""
        self._emit([host_time_ns, "", first_missing_seq, "gap", missing] + [""] * (len(COLUMNS) - 6) + [phase])
        self.gap_rows += 1
        self.missing += missing

    #: events a mission goes on after (the others end it: ``link_down``, ``estop``, its status)
    PROGRESS_EVENTS = ("gap", "odometry_fallback", "track_regained")

    def event(self, host_time_ns: int, what: str, phase: str = "") -> None:
        """Record a non-sample event (``link_down``, ``estop``, ``phase`` change...) as a row."""
        self._emit([host_time_ns, "", "", what, 0] + [""] * (len(COLUMNS) - 6) + [phase])

    def close(self, status: str = "finished", **results) -> None:
        """fsync, close and write the final manifest (``status`` and any results, e.g. path error)."""
        if self._f is None:
            return
        self._f.flush()
        os.fsync(self._f.fileno())
        self._f.close()
        self._f = None
        self._manifest.update(status=status, finished_ns=time.time_ns(), **results)
        self._write_manifest()

    def __enter__(self) -> "MissionLog":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close("failed" if exc_type else "finished")


def read_log(directory: str | os.PathLike, robot: str, mission_id: str) -> tuple[dict, list[dict]]:
    """Read a mission's manifest and all its CSV rows (every part, in order)."""
    d = Path(directory)
    manifest = json.loads((d / f"{robot}_{mission_id}.json").read_text())
    rows: list[dict] = []
    for name in manifest["files"]:
        with open(d / name, newline="", encoding="utf-8") as f:
            rows += list(csv.DictReader(f))
    return manifest, rows

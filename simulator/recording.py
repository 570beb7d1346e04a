"""Writing simulated recordings: Prophesee RAW (EVT 3.0), the paper's CSV, ``.npz``.

* ``.raw``: Prophesee header lines (``% evt 3.0``, ``% format EVT3;height=H;width=W``,
  ``% geometry WxH``, ..., ``% end``) followed by EVT 3.0 words (:mod:`simulator.evt3`).
* ``.csv``: the paper's event CSV, header ``x,y,p,t`` (px, px, 1 = ON / 0 = OFF, µs).
* ``.npz``: ``events`` (EVENT_DTYPE), ``is_signal``, ``truth``, ``robot_names``,
  ``calibration`` (JSON string), ``width``, ``height``, ``homography``.

The truth CSV (``t_us,robot,x_m,y_m,yaw_rad,vx_mps,vy_mps`` with ``robot`` the robot name) is
:class:`arena.formats.tables.TruthCsvWriter` (``arena sim --truth-csv``).
"""

from __future__ import annotations

import datetime as _dt
import json
from pathlib import Path

import numpy as np

from arena.events import as_events
from simulator.evt3 import Evt3Encoder

EVENT_FORMATS = (".raw", ".csv", ".npz")


def raw_header(width: int, height: int, serial: str = "SIM00001") -> bytes:
    """The ``%`` header of a Prophesee EVT 3.0 RAW file for a ``width`` x ``height`` sensor."""
    now = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M:%S")
    lines = [f"% Date {now}", "% evt 3.0", f"% format EVT3;height={height};width={width}",
             f"% geometry {width}x{height}", "% integrator_name arena-fleet simulator",
             "% plugin_name simulator", f"% serial_number {serial}", "% end"]
    return ("\n".join(lines) + "\n").encode("ascii")


class RawWriter:
    """Incremental Prophesee RAW (EVT 3.0) writer: ``write(events)`` slices in time order."""

    def __init__(self, path: str | Path, width: int, height: int):
        self.path = Path(path)
        self._f = open(self.path, "wb")
        self._f.write(raw_header(width, height))
        self._enc = Evt3Encoder()

    def write(self, events: np.ndarray, until_us: int | None = None, ordered: bool = False) -> None:
        """Append time-sorted events (µs); ``until_us`` marks time passing without events;
        ``ordered``: already in :func:`simulator.evt3.canonical_order`."""
        self._f.write(self._enc.encode(as_events(events), until_us, ordered=ordered))

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> "RawWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def write_events(path: str | Path, events: np.ndarray, width: int, height: int) -> Path:
    """Write events to ``path``; the format follows the extension (.raw, .csv, .npz)."""
    path = Path(path)
    ext = path.suffix.lower()
    events = as_events(events)
    if ext == ".raw":
        with RawWriter(path, width, height) as w:
            w.write(events)
    elif ext == ".csv":
        write_events_csv(path, events)
    elif ext == ".npz":
        np.savez_compressed(path, events=events, width=width, height=height)
    else:
        raise ValueError(f"unknown event file extension {ext!r} (use one of {EVENT_FORMATS})")
    return path


def write_events_csv(path: str | Path, events: np.ndarray) -> None:
    """The paper's CSV: header ``x,y,p,t``, one event per line."""
    ev = as_events(events)
    table = np.column_stack([ev["x"].astype(np.int64), ev["y"].astype(np.int64),
                             ev["p"].astype(np.int64), ev["t"]])
    with open(path, "w") as f:
        f.write("x,y,p,t\n")
        np.savetxt(f, table, fmt="%d", delimiter=",")


def save_recording(rec, path: str | Path) -> Path:
    """Save a :class:`simulator.scenarios.Recording`: ``.npz`` keeps everything (events,
    labels, truth, names, calibration); ``.raw``/``.csv`` keep only the events."""
    path = Path(path)
    if path.suffix.lower() != ".npz":
        return write_events(path, rec.events, rec.width, rec.height)
    np.savez_compressed(path, events=rec.events, is_signal=rec.is_signal, truth=rec.truth,
                        robot_names=np.array(rec.robot_names),
                        calibration=json.dumps(rec.calibration), width=rec.width,
                        height=rec.height, homography=rec.homography)
    return path


def load_recording(path: str | Path):
    """Read a ``.npz`` written by :func:`save_recording` back into a
    :class:`simulator.scenarios.Recording` (without robot specs and scenario)."""
    from simulator.scenarios import Recording
    try:
        z = np.load(path, allow_pickle=False)
        return Recording(events=z["events"], is_signal=z["is_signal"], truth=z["truth"],
                         robot_names=[str(n) for n in z["robot_names"]],
                         calibration=json.loads(str(z["calibration"])), width=int(z["width"]),
                         height=int(z["height"]), homography=z["homography"])
    except (KeyError, ValueError, OSError) as e:
        raise ValueError(f"{path}: not a simulator recording (.npz from save_recording): {e}") from None

"""Event file formats, chosen by file extension.

Read: Prophesee RAW (EVT 2.0 / 2.1 / 3.0, version from the header), Prophesee DAT,
AEDAT 4.0 (iniVation, LZ4/ZSTD packets), the paper's CSV (``x,y,p,t_us``), ``.npy``
and ``.npz`` (arrays x, y, p, t). Write: RAW EVT 3.0 or 2.0 (``evt=3|2``), DAT,
AEDAT4, CSV, npz/npy. Events are :data:`arena.events.EVENT_DTYPE` (px, px, 1=ON, µs),
timestamps are the sensor's absolute ones.

The tracks CSV and the truth CSVs (the tracker's output, the simulator's exact poses, the webcam
ground truth) are :mod:`arena.formats.tables`: their headers, dtypes, writers and readers.

>>> ev, width, height = read_events("rec.raw")            # doctest: +SKIP
>>> for chunk in iter_events("rec.aedat4"): ...           # doctest: +SKIP
>>> write_events("rec.dat", ev, width, height)            # doctest: +SKIP
"""

from __future__ import annotations

from pathlib import Path

import importlib

import numpy as np

from arena.formats.base import DEFAULT_CHUNK_EVENTS, EventReader, EventWriter, FormatError, SkippedData
from arena.formats.tables import (GROUNDTRUTH_CSV_HEADER, TRACK_CSV_HEADER, TRACK_DTYPE, TRACK_REQUIRED,
                                  TRUTH_CSV_HEADER, TRUTH_DTYPE, TRUTH_REQUIRED, CsvFormatError, GroundTruthCsvWriter,
                                  TrackCsvWriter, TruthCsvWriter, read_tracks_csv, read_truth_csv, tracks_array,
                                  write_tracks_csv, write_truth_csv)

__all__ = ["FormatError", "SkippedData", "EventReader", "EventWriter", "READ_EXTENSIONS", "WRITE_EXTENSIONS",
           "iter_events", "read_events", "write_events", "open_writer",
           # the tracks and truth CSVs (arena.formats.tables)
           "CsvFormatError", "TRACK_CSV_HEADER", "TRACK_REQUIRED", "TRACK_DTYPE", "TrackCsvWriter", "tracks_array",
           "write_tracks_csv", "read_tracks_csv", "TRUTH_CSV_HEADER", "GROUNDTRUTH_CSV_HEADER", "TRUTH_REQUIRED",
           "TRUTH_DTYPE", "TruthCsvWriter", "write_truth_csv", "GroundTruthCsvWriter", "read_truth_csv"]

#: the event format classes and their modules, imported when first used: their numba kernels load
#: numba (~0.5 s), which a command that only reads a tracks or truth CSV (arena.formats.tables) does
#: not need; ``from arena.formats import RawReader`` still works (module ``__getattr__``)
_CLASSES = {"Aedat4Reader": "aedat4", "Aedat4Writer": "aedat4", "CsvReader": "csvfile", "CsvWriter": "csvfile",
            "DatReader": "dat", "DatWriter": "dat", "NumpyReader": "numpy_files", "NumpyWriter": "numpy_files",
            "RawReader": "raw", "RawWriter": "raw"}
_READERS = {".raw": "RawReader", ".dat": "DatReader", ".aedat4": "Aedat4Reader", ".csv": "CsvReader",
            ".npy": "NumpyReader", ".npz": "NumpyReader"}
_WRITERS = {".raw": "RawWriter", ".dat": "DatWriter", ".aedat4": "Aedat4Writer", ".csv": "CsvWriter",
            ".npy": "NumpyWriter", ".npz": "NumpyWriter"}
READ_EXTENSIONS = tuple(_READERS)
WRITE_EXTENSIONS = tuple(_WRITERS)


def _ext(path: str | Path, table: dict, verb: str) -> type:
    ext = Path(path).suffix.lower()
    if ext not in table:
        raise FormatError(f"cannot {verb} {str(path)!r}: unknown extension {ext or '(none)'!r}; "
                          f"known: {', '.join(table)}")
    return __getattr__(table[ext])


def __getattr__(name: str):
    """The event format classes (``RawReader``, ``CsvWriter``, ...), imported on first use."""
    if name not in _CLASSES:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"arena.formats.{_CLASSES[name]}"), name)


def iter_events(path: str | Path, chunk_events: int = DEFAULT_CHUNK_EVENTS, **opts) -> EventReader:
    """Open an event file for streaming: iterate the returned reader for event chunks.

    The reader exposes ``width`` and ``height`` (px) and is a context manager.
    ``opts`` go to the format's reader (e.g. ``width``/``height`` for CSV and npy).
    Raises :class:`FormatError` for unknown or corrupt files, ``OSError`` if unreadable; what a
    reader skips (corrupt packets, invalid events) it counts and issues as :class:`SkippedData`
    warnings (``warnings.simplefilter("error", SkippedData)`` makes them errors).
    """
    cls = _ext(path, _READERS, "read")
    if not Path(path).is_file():
        raise FormatError(f"no such file: {str(path)!r}")
    try:
        return cls(path, chunk_events=chunk_events, **opts)
    except (UnicodeDecodeError, ValueError) as exc:
        if isinstance(exc, FormatError):
            raise
        raise FormatError(f"{path}: corrupt {Path(path).suffix} file ({exc})") from None


def read_events(path: str | Path, **opts) -> tuple[np.ndarray, int, int]:
    """Read a whole event file: returns ``(events, width, height)``."""
    with iter_events(path, **opts) as reader:
        return reader.read_all(), reader.width, reader.height


def open_writer(path: str | Path, width: int, height: int, **opts) -> EventWriter:
    """Open a streaming writer chosen by extension; ``opts``: ``evt=3|2`` for RAW,
    ``compression=`` for AEDAT4."""
    cls = _ext(path, _WRITERS, "write")
    return cls(path, width, height, **opts)


def write_events(path: str | Path, events: np.ndarray, width: int, height: int, **opts) -> None:
    """Write ``events`` (sensor ``width`` x ``height`` px) to ``path``, format by extension."""
    with open_writer(path, width, height, **opts) as writer:
        writer.write(events)

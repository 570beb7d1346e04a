"""Common reader/writer interfaces and errors of the event file formats.

Hostile or damaged files: every reader raises :class:`FormatError` (one error type; ``OSError``
only when the file cannot be read at all), allocates no more than the file can hold (sizes in a
file are checked against the file's length before anything is read or allocated), range-checks
the values it returns (0 <= x < width, 0 <= y < height, p 0 or 1, a sensor of 1..65535 px a
side) and reports what it skips: events with invalid values in ``reader.invalid``, undecodable
parts (packets, words, bytes) in ``reader.skipped``, each also issued once per chunk as a
:class:`SkippedData` warning, which ``warnings.simplefilter("error", SkippedData)`` turns into
the error (``arena convert --strict``).
"""

from __future__ import annotations

import os
import warnings

import numpy as np

from arena.events import EVENT_DTYPE

#: Default number of events per chunk yielded by the streaming readers.
DEFAULT_CHUNK_EVENTS = 1 << 18
#: Largest sensor side, px (an :class:`arena.messages.EventWindow`'s limit); coordinates are < this.
MAX_SENSOR_PX = 65535
_INT64_MAX = (1 << 63) - 1


class FormatError(ValueError):
    """An event file is unknown, corrupt or truncated; the message says which and where."""


class SkippedData(FormatError, UserWarning):
    """Part of an event file was skipped: issued as a warning (the reader goes on), or raised as
    the :class:`FormatError` it also is under ``warnings.simplefilter("error", SkippedData)``.
    ``count`` of ``unit`` (e.g. ``"invalid events"``, ``"corrupt packets"``) were skipped."""

    def __init__(self, message: str, count: int = 1, unit: str = "events") -> None:
        super().__init__(message)
        self.count = int(count)
        self.unit = unit


def check_size(width, height, where: str) -> tuple[int, int]:
    """``(width, height)`` as ints if both are 1..:data:`MAX_SENSOR_PX` px, else :class:`FormatError`."""
    try:
        w, h = int(width), int(height)
    except (TypeError, ValueError, OverflowError):
        raise FormatError(f"{where}: sensor size {width!r} x {height!r} is not a pair of integers") from None
    if not (1 <= w <= MAX_SENSOR_PX and 1 <= h <= MAX_SENSOR_PX):
        raise FormatError(f"{where}: sensor size {w} x {h} px is outside 1..{MAX_SENSOR_PX} px a side")
    return w, h


def file_size(f) -> int:
    """Length in bytes of the open file ``f``."""
    return os.fstat(f.fileno()).st_size


def read_exactly(f, n: int, total: int, what: str, where: str) -> bytes:
    """Read ``n`` bytes of ``f`` (of ``total`` bytes), refusing a size beyond the file's end
    before allocating it (``read(n)`` allocates n bytes first)."""
    if n < 0 or n > total - f.tell():
        raise FormatError(f"{where}: {what} of {n} bytes runs past the end of the file "
                          f"({max(0, total - f.tell())} bytes left): truncated or corrupt")
    data = f.read(n)
    if len(data) < n:
        raise FormatError(f"{where}: {what} is truncated ({len(data)} of {n} bytes)")
    return data


class EventReader:
    """A streaming reader of one event file.

    Iterating yields event chunks (:data:`arena.events.EVENT_DTYPE`, sensor frame, µs)
    in file order. ``width`` and ``height`` (px) are known after opening.
    ``invalid`` counts events dropped because they lay outside the sensor or had invalid values
    (a polarity other than 0/1, a coordinate beyond 16 bits); ``skipped`` counts undecodable
    parts (packets, words, bytes: see each reader) skipped; both are also issued as
    :class:`SkippedData` warnings.
    """

    width: int
    height: int
    path: str = ""

    def __init__(self) -> None:
        self.invalid = 0
        self.skipped = 0

    def chunks(self):  # pragma: no cover - abstract
        raise NotImplementedError

    def __iter__(self):
        return self.chunks()

    def read_all(self) -> np.ndarray:
        """Read the remaining events into one array."""
        parts = list(self.chunks())
        return np.concatenate(parts) if parts else np.empty(0, EVENT_DTYPE)

    def _valid(self, ev: np.ndarray) -> np.ndarray:
        bad = (ev["x"] >= self.width) | (ev["y"] >= self.height)
        nbad = int(np.count_nonzero(bad))
        if nbad:
            self._invalid(nbad)
            ev = ev[~bad]
        return ev

    def _invalid(self, n: int) -> None:
        self.invalid += n
        warnings.warn(SkippedData(f"{self.path}: events outside the sensor or with invalid values (polarity "
                                  "not 0/1, a coordinate beyond 16 bits) skipped", n, "invalid events"), stacklevel=3)

    def _skip(self, n: int, unit: str, why: str) -> None:
        """Count and report ``n`` undecodable ``unit`` skipped (``why``: what and where)."""
        self.skipped += n
        warnings.warn(SkippedData(f"{self.path}: {why}", n, unit), stacklevel=3)

    def _columns(self, x, y, p, t) -> np.ndarray:
        """Events from four equal-length numeric columns of any dtype, range-checked without
        wrapping (0 <= x, y < 65535; p -1 (OFF), 0 or 1; t integral within int64): rows that fail
        are dropped and counted as invalid. Raises :class:`FormatError` for non-numeric or
        mismatched columns."""
        cols = []
        for name, a in zip("xypt", (x, y, p, t)):
            a = np.asarray(a)
            if a.dtype.kind not in "biuf":
                raise FormatError(f"{self.path}: column {name} holds {a.dtype} values, expected integers")
            if a.ndim != 1:
                raise FormatError(f"{self.path}: column {name} has shape {a.shape}, expected one dimension")
            cols.append(a)
        x, y, p, t = cols
        if not (x.size == y.size == p.size == t.size):
            raise FormatError(f"{self.path}: columns x, y, p, t have different lengths "
                              f"({x.size}, {y.size}, {p.size}, {t.size})")
        ok = (x >= 0) & (x < MAX_SENSOR_PX) & (y >= 0) & (y < MAX_SENSOR_PX) & ((p == 0) | (p == 1) | (p == -1))
        for a in (x, y):
            if a.dtype.kind == "f":
                ok &= a == np.floor(a)
        if t.dtype.kind == "f":
            ok &= np.isfinite(t) & (t == np.floor(t)) & (np.abs(t) < 2.0**63)
        elif t.dtype.kind == "u" and t.dtype.itemsize == 8:
            ok &= t <= _INT64_MAX
        nbad = x.size - int(np.count_nonzero(ok))
        if nbad:
            x, y, p, t = x[ok], y[ok], p[ok], t[ok]
            self._invalid(nbad)
        ev = np.empty(x.size, EVENT_DTYPE)
        ev["x"] = x
        ev["y"] = y
        ev["p"] = p > 0
        ev["t"] = t
        return ev

    def close(self) -> None:
        """Release the file."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class EventWriter:
    """A streaming writer of one event file: ``write(events)`` any number of times, then ``close()``."""

    def write(self, events: np.ndarray) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def close(self) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def check_events(events: np.ndarray) -> np.ndarray:
    """Return ``events`` as :data:`EVENT_DTYPE` or raise ``FormatError``."""
    if not isinstance(events, np.ndarray) or events.dtype.names is None:
        raise FormatError("events must be a structured numpy array with fields x, y, p, t")
    from arena.events import as_events

    try:
        return as_events(events)
    except ValueError as exc:
        raise FormatError(str(exc)) from None

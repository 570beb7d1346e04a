"""The paper's CSV: one event per line ``x,y,p,t_us`` (px, px, 1/0, µs), with or without
a header line. A header may name the columns in another order (``t,x,y,p``,
``timestamp``, ``polarity``); polarity -1 is read as 0 (OFF). Lines with a polarity other than
-1/0/1 or a coordinate outside 0..65534 are counted in ``invalid`` and skipped (never wrapped into
16 bits); a value beyond 64 bits is an error.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from arena.formats.base import (
    DEFAULT_CHUNK_EVENTS,
    EventReader,
    EventWriter,
    FormatError,
    check_events,
    check_size,
)

#: longest first line read (a header, or the first event): a file without newlines is not read whole
_MAX_HEADER = 4096

_ALIASES = {"x": "x", "y": "y", "p": "p", "pol": "p", "polarity": "p", "t": "t", "t_us": "t",
            "ts": "t", "timestamp": "t", "time": "t", "time_us": "t"}


class CsvReader(EventReader):
    """Streaming reader of an event CSV file. Size: ``width``/``height`` arguments, else 1 + the
    largest x / y of the first chunk (so give them when you know the sensor)."""

    def __init__(self, path: str | Path, chunk_events: int = DEFAULT_CHUNK_EVENTS,
                 width: int | None = None, height: int | None = None) -> None:
        super().__init__()
        self.path = str(path)
        self._f = open(path, "rb")
        first = self._f.readline(_MAX_HEADER)   # bounded: a binary file may have no newline at all
        self._order = [0, 1, 2, 3]
        self._line = 1
        if len(first) >= _MAX_HEADER and not first.endswith(b"\n"):
            self._f.close()
            raise FormatError(f"{path}: the first line is longer than {_MAX_HEADER} bytes: not an event CSV "
                              "(one event per line: x,y,p,t)")
        if first and any(b < 9 or 13 < b < 32 or b == 127 for b in first.rstrip(b"\r\n")):
            self._f.close()
            raise FormatError(f"{path}: binary data, not a text CSV (one event per line: x,y,p,t); "
                              "for a camera recording use its own extension (.raw, .dat, .aedat4, .npz)")
        if first and any(c.isalpha() for c in first.decode("latin-1")):
            names = [_ALIASES.get(n.strip().lower()) for n in first.decode("latin-1").split(",")]
            if sorted(n for n in names if n) != ["p", "t", "x", "y"] or len(names) != 4:
                self._f.close()
                shown = first.strip().decode("latin-1")
                shown = shown if len(shown) <= 80 else shown[:77] + "..."
                raise FormatError(f"{path}: CSV header {shown!r} must name columns x, y, p, t")
            self._order = [names.index(k) for k in ("x", "y", "p", "t")]
            self._pending = b""
        else:
            self._pending = first
            self._line = 0
        self._chunk_bytes = max(256, chunk_events * 24)
        self._first = None
        if width is None or height is None:
            self._first = self._next()
            mx = int(self._first["x"].max()) + 1 if self._first is not None and self._first.size else 1
            my = int(self._first["y"].max()) + 1 if self._first is not None and self._first.size else 1
            width, height = width or mx, height or my
        try:
            self.width, self.height = check_size(width, height, self.path)
        except FormatError:
            self._f.close()
            raise

    def _parse(self, block: bytes) -> np.ndarray:
        try:
            vals = np.array(block.replace(b",", b" ").split(), dtype=np.int64)
        except ValueError:
            raise FormatError(f"{self.path}: non-numeric value in the CSV near line {self._line + 1}") from None
        except OverflowError:
            raise FormatError(f"{self.path}: a value beyond 64 bits in the CSV near line {self._line + 1}") from None
        if vals.size % 4:
            raise FormatError(f"{self.path}: a CSV line near line {self._line + 1} does not have 4 columns")
        vals = vals.reshape(-1, 4)
        self._line += vals.shape[0]
        o = self._order
        return self._columns(vals[:, o[0]], vals[:, o[1]], vals[:, o[2]], vals[:, o[3]])

    def _next(self):
        data = self._pending + self._f.read(self._chunk_bytes)
        if not data.strip():
            self._pending = b""
            return None
        cut = data.rfind(b"\n")
        if cut < 0 or len(data) < self._chunk_bytes:
            block, self._pending = data, b""
        else:
            block, self._pending = data[:cut + 1], data[cut + 1:]
        return self._parse(block)

    def chunks(self):
        if self._first is not None:
            first, self._first = self._first, None
            yield self._valid(first)
        while (ev := self._next()) is not None:
            yield self._valid(ev)

    def close(self) -> None:
        self._f.close()


class CsvWriter(EventWriter):
    """Writer of the paper's CSV with a ``x,y,p,t_us`` header line."""

    def __init__(self, path: str | Path, width: int = 0, height: int = 0, header: bool = True) -> None:
        self._f = open(path, "w", newline="\n")
        if header:
            self._f.write("x,y,p,t_us\n")

    def write(self, events: np.ndarray) -> None:
        events = check_events(events)
        cols = np.column_stack([events["x"], events["y"], events["p"], events["t"]]).astype(np.int64)
        np.savetxt(self._f, cols, fmt="%d", delimiter=",")

    def close(self) -> None:
        self._f.close()

"""The paper's CSV: one event per line ``x,y,p,t_us`` (px, px, 1/0, µs), with or without
a header line. A header may name the columns in another order (``t,x,y,p``,
``timestamp``, ``polarity``); polarity -1 is read as 0 (OFF). Lines with a polarity other than
-1/0/1 or a coordinate outside 0..65534 are counted in ``invalid`` and skipped (never wrapped into
16 bits); a value beyond 64 bits is an error. Fields are decimal integers with an optional sign,
spaces or tabs around them and CRLF or LF line ends; blank lines are skipped.

The reader streams the file in blocks of about ``24 * chunk_events`` bytes (whole lines; the cut
line waits for the next block), parsed by one numba kernel straight from the bytes: ~23 M events/s
(~400 MB/s) a core on the paper's lines (``bench/bench_decoders.py``; the numpy text split it
replaces read 1.2-1.8, ``pandas.read_csv`` reads 10). Errors name their line. The writer
formats with a second kernel (~24 M events/s, the same text as ``numpy.savetxt``'s ``%d``).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
from numba import njit

from arena.events import EVENT_DTYPE
from arena.formats.base import (
    DEFAULT_CHUNK_EVENTS,
    MAX_SENSOR_PX,
    EventReader,
    EventWriter,
    FormatError,
    SkippedData,
    check_events,
    check_size,
)

#: longest first line read (a header, or the first event): a file without newlines is not read whole
_MAX_HEADER = 4096

_ALIASES = {"x": "x", "y": "y", "p": "p", "pol": "p", "polarity": "p", "t": "t", "t_us": "t",
            "ts": "t", "timestamp": "t", "time": "t", "time_us": "t"}

#: kernel status codes
_OK, _NON_NUMERIC, _COLUMNS, _OVERFLOW = 0, 1, 2, 3


@njit(cache=True, nogil=True)
def _line_end(buf, n, final, pos):
    """At a CR or LF at ``pos``: ``(status, ended)``; a CR must be followed by LF (status 1 when
    not), and a CR last in a block that is not ``final`` waits for the next block."""
    if buf[pos] == 13:
        if pos + 1 < n:
            return (0, True) if buf[pos + 1] == 10 else (1, False)
        return 0, final
    return 0, True


@njit(cache=True, nogil=True)
def _careful_line(buf, i, n, final):
    """Parse the one line at ``buf[i]`` in full generality (spaces/tabs around fields, signs,
    CRLF, leading zeros, values up to 64 bits, a blank line). Returns ``(status, ended, end,
    columns, v0, v1, v2, v3)``: ``ended`` False when the line runs past ``n`` and the block is
    not ``final``; ``end`` the index after the line's LF."""
    col = 0
    v0 = v1 = v2 = v3 = 0
    while True:
        while i < n and (buf[i] == 32 or buf[i] == 9):
            i += 1
        if i >= n:
            return 0, final, n, col, v0, v1, v2, v3
        c = buf[i]
        if c == 10 or c == 13:
            if col > 0:                      # "1,2," ends with an empty field
                return 2, True, i, col, v0, v1, v2, v3
            status, ended = _line_end(buf, n, final, i)
            return status, ended, i + 1 + (c == 13), col, v0, v1, v2, v3
        neg = False
        if c == 45 or c == 43:               # '-' '+'
            neg = c == 45
            i += 1
        d0 = i
        while i < n and buf[i] == 48:
            i += 1
        z = i
        v = 0
        while i < n and i - z < 18 and 48 <= buf[i] <= 57:
            v = v * 10 + (buf[i] - 48)
            i += 1
        if i < n and 48 <= buf[i] <= 57:     # a 19th significant digit: check against 2**63
            d = np.int64(buf[i] - 48)
            i += 1
            if (i < n and 48 <= buf[i] <= 57) or v > 922337203685477580 or (
                    v == 922337203685477580 and d > (8 if neg else 7)):
                return 3, True, i, col, v0, v1, v2, v3
            v = -(v * 10) - d if neg else v * 10 + d
        elif neg:
            v = -v
        if i == d0:
            return (1 if i < n or final else 0), i < n or final, i, col, v0, v1, v2, v3
        if col >= 4:
            return 2, True, i, col, v0, v1, v2, v3
        if col == 0:
            v0 = v
        elif col == 1:
            v1 = v
        elif col == 2:
            v2 = v
        else:
            v3 = v
        col += 1
        while i < n and (buf[i] == 32 or buf[i] == 9):
            i += 1
        if i >= n:
            return 0, final, n, col, v0, v1, v2, v3
        c = buf[i]
        if c == 44:                          # ','
            i += 1
            if col >= 4:
                return 2, True, i, col, v0, v1, v2, v3
            continue
        if c == 10 or c == 13:
            status, ended = _line_end(buf, n, final, i)
            return status, ended, i + 1 + (c == 13), col, v0, v1, v2, v3
        return 1, True, i, col, v0, v1, v2, v3


@njit(cache=True, nogil=True)
def _parse_lines(buf, n, final, order, xlim, ylim, out):
    """Parse the whole lines of ``buf[:n]`` (uint8) into ``out`` (EVENT_DTYPE), and the last
    line too when ``final``.

    Each line is 4 comma-separated decimal integers, field ``order[j]`` of a line holding column
    j of x, y, p, t. Lines of plain digits and commas (and a '-') take a one-pass fast path;
    any other line is parsed by :func:`_careful_line`. Rows with x or y outside
    0..xlim-1 / 0..ylim-1 (at most MAX_SENSOR_PX) or a polarity other than -1/0/1 are dropped
    and counted. Returns
    ``(status, bytes consumed, events written, invalid rows, lines read, line of the error)``
    (the error's line counted from this block's first line, 1-based): status 0 ok,
    1 non-numeric, 2 not 4 columns, 3 beyond 64 bits."""
    o0, o1, o2, o3 = order[0], order[1], order[2], order[3]
    i = 0
    k = 0
    bad = 0
    lines = 0
    while i < n:
        # fast path: [-]digits x 4 with 3 commas, LF; at most 18 digits a field
        ls = i
        col = 0
        nd = 0
        v = 0
        neg = False
        v0 = v1 = v2 = v3 = 0
        careful = False
        while True:
            if i >= n:
                careful = True
                break
            c = buf[i]
            d = np.uint8(c - 48)
            if d < 10:
                v = v * 10 + d
                nd += 1
            elif c == 44 or c == 10:
                if nd == 0 or nd > 18:
                    careful = True
                    break
                if neg:
                    v = -v
                if col == 0:
                    v0 = v
                elif col == 1:
                    v1 = v
                elif col == 2:
                    v2 = v
                else:
                    v3 = v
                col += 1
                if c == 10:
                    i += 1
                    if col != 4:
                        careful = True
                    break
                if col > 3:
                    careful = True
                    break
                v = 0
                nd = 0
                neg = False
            elif c == 45 and nd == 0 and not neg:
                neg = True
            else:
                careful = True
                break
            i += 1
        if careful:
            status, ended, end, col, v0, v1, v2, v3 = _careful_line(buf, ls, n, final)
            if status:
                return status, ls, k, bad, lines, lines + 1
            if not ended:
                return 0, ls, k, bad, lines, 0      # an incomplete last line: the next block's
            i = end
            lines += 1
            if col == 0:
                continue                              # a blank line
            if col != 4:
                return 2, ls, k, bad, lines - 1, lines
        else:
            lines += 1
        x = v0 if o0 == 0 else v1 if o0 == 1 else v2 if o0 == 2 else v3
        y = v0 if o1 == 0 else v1 if o1 == 1 else v2 if o1 == 2 else v3
        p = v0 if o2 == 0 else v1 if o2 == 1 else v2 if o2 == 2 else v3
        t = v0 if o3 == 0 else v1 if o3 == 1 else v2 if o3 == 2 else v3
        if 0 <= x < xlim and 0 <= y < ylim and -1 <= p <= 1:
            out[k].x = x
            out[k].y = y
            out[k].p = 1 if p > 0 else 0
            out[k].t = t
            k += 1
        else:
            bad += 1
    return 0, min(i, n), k, bad, lines, 0


class CsvReader(EventReader):
    """Streaming reader of an event CSV file. Size: ``width``/``height`` arguments, else 1 + the
    largest x / y of the first chunk (so give them when you know the sensor). Memory: one block
    of ``24 * chunk_events`` bytes (at least 8 KiB) and the events parsed from it."""

    def __init__(self, path: str | Path, chunk_events: int = DEFAULT_CHUNK_EVENTS,
                 width: int | None = None, height: int | None = None) -> None:
        super().__init__()
        self.path = str(path)
        self._f = open(path, "rb")
        first = self._f.readline(_MAX_HEADER)   # bounded: a binary file may have no newline at all
        self._order = np.arange(4, dtype=np.int64)
        self._line = 1
        if len(first) >= _MAX_HEADER and not first.endswith(b"\n"):
            self._f.close()
            raise FormatError(f"{path}: the first line is longer than {_MAX_HEADER} bytes: not an event CSV "
                              "(one event per line: x,y,p,t)")
        if first and any(b < 9 or 13 < b < 32 or b == 127 for b in first.rstrip(b"\r\n")):
            self._f.close()
            raise FormatError(f"{path}: binary data, not a text CSV (one event per line: x,y,p,t); "
                              "for a camera recording use its own extension (.raw, .dat, .aedat4, .npz)")
        self._buf = bytearray(max(2 * _MAX_HEADER, int(chunk_events) * 24))
        self._view = np.frombuffer(self._buf, np.uint8)
        self._lim = (MAX_SENSOR_PX, MAX_SENSOR_PX)   # the sensor's size once known
        self._have = 0                          # bytes of _buf not parsed yet (the cut line)
        self._eof = False
        if first and any(c.isalpha() for c in first.decode("latin-1")):
            names = [_ALIASES.get(n.strip().lower()) for n in first.decode("latin-1").split(",")]
            if sorted(n for n in names if n) != ["p", "t", "x", "y"] or len(names) != 4:
                self._f.close()
                shown = first.strip().decode("latin-1")
                shown = shown if len(shown) <= 80 else shown[:77] + "..."
                raise FormatError(f"{path}: CSV header {shown!r} must name columns x, y, p, t")
            self._order = np.array([names.index(k) for k in ("x", "y", "p", "t")], np.int64)
        else:
            self._buf[:len(first)] = first
            self._have = len(first)
            self._line = 0
        self._first = None
        self._last_t: int | None = None
        self.unordered = 0                      # events earlier than the one before them
        if width is None or height is None:
            try:
                self._first = self._next()
            except FormatError:
                self._f.close()
                raise
            mx = int(self._first["x"].max()) + 1 if self._first is not None and self._first.size else 1
            my = int(self._first["y"].max()) + 1 if self._first is not None and self._first.size else 1
            width, height = width or mx, height or my
        try:
            self.width, self.height = check_size(width, height, self.path)
        except FormatError:
            self._f.close()
            raise
        self._lim = (self.width, self.height)

    def _next(self) -> np.ndarray | None:
        """The events of the next block's whole lines; None at the end of the file."""
        while True:
            if not self._eof and self._have < len(self._buf):
                got = self._f.readinto(memoryview(self._buf)[self._have:])
                self._eof = not got
                self._have += got
            if self._have == 0 and self._eof:
                return None
            # room for the most events the block can hold (the shortest line, "0,0,0,0\n", has 8
            # bytes); pages past the events written are never touched, so never resident
            out = np.empty(self._have // 8 + 1, EVENT_DTYPE)
            status, used, k, bad, lines, err = _parse_lines(self._view, self._have, self._eof, self._order,
                                                            *self._lim, out)
            if status:
                where = f"{self.path}: line {self._line + err}"
                self._line += lines
                if status == _OVERFLOW:
                    raise FormatError(f"{where} of the CSV has a value beyond 64 bits")
                if status == _COLUMNS:
                    raise FormatError(f"{where} of the CSV does not have 4 columns (x,y,p,t)")
                raise FormatError(f"{where} of the CSV has a non-numeric or empty value (one event per "
                                  "line: integers x,y,p,t)")
            self._line += lines
            rest = self._have - used
            self._buf[:rest] = self._buf[used:self._have]
            self._have = rest
            if bad:
                self._invalid(bad)
            if used == 0 and not self._eof and rest == len(self._buf):
                raise FormatError(f"{self.path}: line {self._line + 1} of the CSV is longer than "
                                  f"{len(self._buf)} bytes: not an event CSV (one event per line: x,y,p,t)")
            if k or (self._eof and not self._have):
                ev = out[:k]
                self._time_order(ev)
                return ev

    def _time_order(self, ev: np.ndarray) -> None:
        """Count (``unordered``) and report the events earlier than the event before them: kept
        as read, but a recording's times do not go back (``--strict`` makes it an error)."""
        if not ev.size:
            return
        t = ev["t"]
        n = int(np.count_nonzero(t[1:] < t[:-1])) + int(self._last_t is not None and int(t[0]) < self._last_t)
        self._last_t = int(t[-1])
        if n:
            self.unordered += n
            warnings.warn(SkippedData(f"{self.path}: times go backwards (events earlier than the one before "
                                      "them, kept as read)", n, "events out of time order (kept)"), stacklevel=4)

    def chunks(self):
        if self._first is not None:
            first, self._first = self._first, None
            yield self._valid(first)
        while (ev := self._next()) is not None:
            yield ev            # checked against the sensor's size by the kernel

    def close(self) -> None:
        self._f.close()


@njit(cache=True, nogil=True)
def _format_lines(x, y, p, t, buf) -> int:
    """Write events as ``x,y,p,t\\n`` lines into ``buf`` (uint8, at least 35 bytes an event);
    returns the bytes written."""
    digits = np.empty(20, np.uint8)
    j = 0
    for i in range(x.size):
        for f in range(4):
            if f == 0:
                v = np.uint64(x[i])
            elif f == 1:
                v = np.uint64(y[i])
            elif f == 2:
                v = np.uint64(p[i])
            else:
                tv = t[i]
                if tv < 0:
                    buf[j] = 45                      # '-'; |-2**63| fits in uint64
                    j += 1
                    v = np.uint64(-(tv + 1)) + np.uint64(1)
                else:
                    v = np.uint64(tv)
            nd = 0
            while True:
                digits[nd] = np.uint8(v % np.uint64(10)) + 48
                nd += 1
                v //= np.uint64(10)
                if v == 0:
                    break
            for d in range(nd - 1, -1, -1):
                buf[j] = digits[d]
                j += 1
            buf[j] = 44 if f < 3 else 10
            j += 1
    return j


class CsvWriter(EventWriter):
    """Writer of the paper's CSV with a ``x,y,p,t_us`` header line."""

    #: events formatted at a time (a 9 MB text buffer)
    BLOCK_EVENTS = 1 << 18

    def __init__(self, path: str | Path, width: int = 0, height: int = 0, header: bool = True) -> None:
        self._f = open(path, "wb")
        self._buf = np.empty(self.BLOCK_EVENTS * 35, np.uint8)   # 5+5+1+20 digits, '-', 4 separators
        if header:
            self._f.write(b"x,y,p,t_us\n")

    def write(self, events: np.ndarray) -> None:
        events = check_events(events)
        for i in range(0, events.size, self.BLOCK_EVENTS):
            ev = events[i:i + self.BLOCK_EVENTS]
            n = _format_lines(ev["x"], ev["y"], ev["p"], ev["t"], self._buf)
            self._f.write(memoryview(self._buf)[:n])

    def close(self) -> None:
        self._f.close()

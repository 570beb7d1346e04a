"""Prophesee DAT files: ``% key value`` header lines, a 2-byte (event type, event size)
preamble, then 8-byte events: uint32 t (µs), uint32 with x in bits 13..0, y in 27..14
and polarity in 31..28.

The 32-bit time wraps after 71.6 min; the reader extends wraps. The writer stores
``t mod 2**32``, so absolute times beyond 2**32 µs are kept only relative to the wrap.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from arena.events import EVENT_DTYPE
from arena.formats.base import DEFAULT_CHUNK_EVENTS, EventReader, EventWriter, FormatError, check_events, check_size

log = logging.getLogger(__name__)

_CD_TYPE = 0x0C
_DECIMAL = re.compile(r"-?[0-9]+")   # a negative one: check_size says why
_WORD = np.dtype([("t", "<u4"), ("d", "<u4")])
#: longest header line read (real ones are < 100 bytes): a file of one endless line is not read whole
_MAX_LINE = 4096


class DatReader(EventReader):
    """Streaming reader of a Prophesee DAT (CD events) file."""

    def __init__(self, path: str | Path, chunk_events: int = DEFAULT_CHUNK_EVENTS) -> None:
        super().__init__()
        self.path = str(path)
        self._f = open(path, "rb")
        try:
            self._header(path)
        except FormatError:
            self._f.close()
            raise
        self._chunk = chunk_events
        self._offset = 0
        self._last = -1
        self.truncated_bytes = 0

    def _header(self, path) -> None:
        fields: dict[str, str] = {}
        while True:
            pos = self._f.tell()
            if self._f.read(1) != b"%":
                self._f.seek(pos)
                break
            line = self._f.readline(_MAX_LINE)
            if not line.endswith(b"\n"):
                raise FormatError(f"{path}: DAT header is truncated (or a line is longer than {_MAX_LINE} bytes)")
            key, _, value = line.decode("latin-1").strip().partition(" ")
            fields[key.lower()] = value.strip()
        pre = self._f.read(2)
        if len(pre) < 2:
            raise FormatError(f"{path}: DAT file ends before its event type/size bytes")
        self.event_type, self.event_size = pre[0], pre[1]
        if self.event_size != 8:
            raise FormatError(f"{path}: DAT event size {self.event_size} not supported (expected 8)")
        self.fields = fields
        if "width" in fields or "height" in fields:
            # given, they are the size: plain decimals (int() also takes "4_80", "+640", "٤٨٠"),
            # both of them, and 0 is refused like any size outside 1..65535, not replaced
            w, h = fields.get("width"), fields.get("height")
            if w is None or h is None:
                raise FormatError(f"{path}: DAT header gives {'Width' if h is None else 'Height'} "
                                  f"without {'Height' if h is None else 'Width'}")
            if not (_DECIMAL.fullmatch(w) and _DECIMAL.fullmatch(h)):
                raise FormatError(f"{path}: DAT header's Width/Height are not integers ({w!r}, {h!r})")
            width, height = int(w), int(h)
        elif "geometry" in fields:
            m = re.fullmatch(r"([0-9]+)\s*x\s*([0-9]+)", fields["geometry"])
            if not m:
                raise FormatError(f"{path}: DAT header's geometry {fields['geometry']!r} is not WIDTHxHEIGHT")
            width, height = int(m.group(1)), int(m.group(2))
        else:
            width, height = 1280, 720
            log.warning("%s: DAT header gives no sensor size; assuming 1280 x 720", path)
        self.width, self.height = check_size(width, height, str(path))

    def chunks(self):
        """Event chunks; bytes of an event cut off by the end of the file are counted in
        ``skipped`` (and ``truncated_bytes``) and reported."""
        while True:
            data = self._f.read(self._chunk * 8)
            if not data:
                return
            n = len(data) // 8
            if len(data) % 8:
                self.truncated_bytes = len(data) % 8
                self._skip(self.truncated_bytes, "bytes of a cut-off event",
                           "the file ends inside an event (truncated?): its bytes are ignored")
            w = np.frombuffer(data[:n * 8], dtype=_WORD)
            t = w["t"].astype(np.int64)
            prev = np.empty(n, np.int64)
            if n:
                prev[0] = self._last if self._last >= 0 else t[0]
                prev[1:] = t[:-1]
            wrap = (t - prev) < -(1 << 31)
            t += self._offset + (np.cumsum(wrap, dtype=np.int64) << 32)
            self._offset += int(np.count_nonzero(wrap)) << 32
            self._last = int(w["t"][-1]) if n else self._last
            ev = np.empty(n, EVENT_DTYPE)
            d = w["d"]
            ev["x"] = d & 0x3FFF
            ev["y"] = (d >> 14) & 0x3FFF
            ev["p"] = (d >> 28) & 1
            ev["t"] = t
            bad = d >= (2 << 28)             # a polarity nibble other than 0 or 1: corrupt
            if bad.any():
                self._invalid(int(np.count_nonzero(bad)))
                ev = ev[~bad]
            yield self._valid(ev)

    def close(self) -> None:
        self._f.close()


class DatWriter(EventWriter):
    """Writer of a Prophesee DAT file (CD events, version 2 header)."""

    def __init__(self, path: str | Path, width: int, height: int) -> None:
        self._f = open(path, "wb")
        self._f.write(f"% Data file containing CD events.\n% Version 2\n% Width {width}\n"
                      f"% Height {height}\n% end\n".encode())
        self._f.write(bytes([_CD_TYPE, 8]))

    def write(self, events: np.ndarray) -> None:
        events = check_events(events)
        w = np.empty(events.size, _WORD)
        w["t"] = (events["t"] & 0xFFFFFFFF).astype(np.uint32)
        w["d"] = (events["x"].astype(np.uint32) & 0x3FFF) | ((events["y"].astype(np.uint32) & 0x3FFF) << 14) \
            | ((events["p"].astype(np.uint32) & 1) << 28)
        self._f.write(w.tobytes())

    def close(self) -> None:
        self._f.close()

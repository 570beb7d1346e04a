"""Prophesee RAW files: ``% key value`` text header, then EVT 2.0, 2.1 or 3.0 words.

The header is the run of lines starting with ``%`` at the file start (an
optional ``% end`` line closes it). The EVT version comes from ``% evt 3.0``
or ``% format EVT3;height=720;width=1280``; the sensor size from ``format``,
``% geometry 1280x720``, ``% width``/``% height`` or, for old files without
any of these, from the sensor generation in ``plugin_name``/``sensor_generation``.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from arena.formats.base import DEFAULT_CHUNK_EVENTS, EventReader, EventWriter, FormatError, check_events, check_size
from arena.formats.evt2 import Evt2Decoder, Evt2Encoder, Evt21Decoder
from arena.formats.evt3 import Evt3Decoder, Evt3Encoder

log = logging.getLogger(__name__)

#: Sensor size (width, height) px by sensor generation found in old headers.
_SENSOR_SIZES = [
    ("imx636", (1280, 720)), ("imx646", (1280, 720)), ("gen41", (1280, 720)), ("gen4", (1280, 720)),
    ("genx320", (320, 320)), ("gen31", (640, 480)), ("gen3", (640, 480)), ("imx8", (320, 320)),
]


def _types(known: set[int], continued: set[int]) -> tuple[np.ndarray, np.ndarray]:
    return np.isin(np.arange(16), sorted(known)), np.isin(np.arange(16), sorted(continued))


#: word types each EVT version defines, and its CONTINUED types (extra data of an OTHERS word):
#: EVT 3.0 adds 0x7 CONTINUED_4 to 0xF CONTINUED_12
_WORD_TYPES = {"3.0": _types({0x0, 0x2, 0x3, 0x4, 0x5, 0x6, 0x7, 0x8, 0xA, 0xE, 0xF}, {0x7, 0xF}),
               "2.0": _types({0x0, 0x1, 0x8, 0xA, 0xE, 0xF}, {0xF}),
               "2.1": _types({0x0, 0x1, 0x8, 0xA, 0xE, 0xF}, {0xF})}
_DECODERS = {"3.0": Evt3Decoder, "2.0": Evt2Decoder, "2.1": Evt21Decoder}
_FORMAT_NAMES = {"EVT3": "3.0", "EVT2": "2.0", "EVT21": "2.1"}


@dataclass
class RawHeader:
    """Parsed RAW header: ``fields`` (key -> value text), EVT ``version``, sensor size px, byte length."""

    fields: dict = field(default_factory=dict)
    version: str = ""
    width: int = 0
    height: int = 0
    size: int = 0


def parse_raw_header(data: bytes) -> RawHeader:
    """Parse the header at the start of ``data`` (the first few KB of a RAW file); raises
    :class:`FormatError` if it names no known EVT version or a sensor size that is not 1..65535 px."""
    try:
        hdr = _parse_raw_header(data)
    except ValueError as exc:   # int() of a size that is not a number
        if isinstance(exc, FormatError):
            raise
        raise FormatError(f"RAW header gives a sensor size that is not a number ({exc})") from None
    hdr.width, hdr.height = check_size(hdr.width, hdr.height, "RAW header")
    return hdr


def _parse_raw_header(data: bytes) -> RawHeader:
    fields: dict[str, str] = {}
    pos = 0
    while pos < len(data) and data[pos:pos + 1] == b"%":
        end = data.find(b"\n", pos)
        if end < 0:
            raise FormatError("RAW header line is not terminated (truncated file?)")
        line = data[pos + 1:end].decode("latin-1").strip()
        pos = end + 1
        if line == "end":
            break
        key, _, value = line.partition(" ")
        fields[key.lower()] = value.strip()
    hdr = RawHeader(fields=fields, size=pos)
    sized = False                 # a size given is the size (0 is refused, not replaced)
    fmt = fields.get("format", "")
    if fmt:
        name, *opts = fmt.split(";")
        hdr.version = _FORMAT_NAMES.get(name.strip().upper(), "")
        kv = dict(o.split("=", 1) for o in opts if "=" in o)
        if "width" in kv and "height" in kv:
            hdr.width, hdr.height = _decimal(kv["width"]), _decimal(kv["height"])
            sized = True
    if not hdr.version and "evt" in fields:
        hdr.version = fields["evt"].strip()
    if hdr.version not in _DECODERS:
        raise FormatError(f"RAW header does not name a known EVT version (evt={fields.get('evt')!r}, "
                          f"format={fmt!r}); supported: EVT 2.0, 2.1, 3.0")
    if not sized:
        m = re.fullmatch(r"([0-9]+)\s*x\s*([0-9]+)", fields.get("geometry", ""))
        if "geometry" in fields and not m:
            raise FormatError(f"RAW header's geometry {fields['geometry']!r} is not WIDTHxHEIGHT")
        if m:
            hdr.width, hdr.height = int(m.group(1)), int(m.group(2))
        elif "width" in fields and "height" in fields:
            hdr.width, hdr.height = _decimal(fields["width"]), _decimal(fields["height"])
        else:
            hint = (fields.get("sensor_generation", "") + " " + fields.get("plugin_name", "")).lower()
            for key, size in _SENSOR_SIZES:
                if key in hint.replace(".", ""):
                    hdr.width, hdr.height = size
                    break
            else:
                hdr.width, hdr.height = 1280, 720
                log.warning("RAW header gives no sensor size; assuming 1280 x 720")
    return hdr


def _decimal(text: str) -> int:
    """A size in a header: plain decimal digits (``int()`` also takes "4_80", "+640", "٤٨٠")."""
    if not re.fullmatch(r"-?[0-9]+", text.strip()):   # a negative one: check_size says why
        raise FormatError(f"RAW header gives a sensor size that is not a number ({text!r})")
    return int(text)


def make_decoder(version: str):
    """A new streaming decoder for EVT ``version`` ("3.0", "2.0" or "2.1")."""
    try:
        return _DECODERS[version]()
    except KeyError:
        raise FormatError(f"unknown EVT version {version!r}; supported: {sorted(_DECODERS)}") from None


class RawReader(EventReader):
    """Streaming reader of a Prophesee RAW file (EVT 2.0 / 2.1 / 3.0)."""

    def __init__(self, path: str | Path, chunk_events: int = DEFAULT_CHUNK_EVENTS) -> None:
        super().__init__()
        self.path = str(path)
        self._f = open(path, "rb")
        head = self._f.read(1 << 16)
        try:
            self.header = parse_raw_header(head)
        except FormatError as exc:
            self._f.close()
            raise FormatError(f"{path}: {exc}") from None
        self.width, self.height = self.header.width, self.header.height
        self.decoder = make_decoder(self.header.version)
        self._f.seek(self.header.size)
        self._chunk_bytes = max(64, chunk_events * self.decoder.word_bytes)
        wb = self.decoder.word_bytes
        self._word = np.dtype(f"<u{wb}")
        self._type_shift = 8 * wb - 4
        self._known, self._continued = _WORD_TYPES[self.header.version]
        self._tail = b""                # bytes of a word cut by the chunk's end
        self._last_type = -1            # type of the last word not a CONTINUED one

    def _unknown_words(self, data: bytes) -> int:
        """Words of ``data`` (after the previous chunk's cut word) that no decoder reads: of a type
        the EVT version does not define, or CONTINUED words not after an OTHERS word."""
        data = self._tail + data
        usable = len(data) - len(data) % self._word.itemsize
        self._tail = data[usable:]
        if not usable:
            return 0
        typ = (np.frombuffer(data, self._word, usable // self._word.itemsize) >> self._type_shift).astype(np.intp)
        n = int(np.count_nonzero(~self._known[typ]))
        cont = self._continued[typ]
        if cont.any():
            idx = np.where(cont, -1, np.arange(typ.size))
            np.maximum.accumulate(idx, out=idx)
            before = np.where(idx >= 0, typ[np.maximum(idx, 0)], self._last_type)
            n += int(np.count_nonzero(cont & (before != 0xE)))
        last = np.flatnonzero(~cont)
        if last.size:
            self._last_type = int(typ[last[-1]])
        return n

    def chunks(self):
        """Event chunks; event words before the first TIME_HIGH (no time known) and the bytes of
        a word cut off by the end of the file are counted in ``skipped`` and reported."""
        words = 0
        while True:
            data = self._f.read(self._chunk_bytes)
            if not data:
                break
            unknown = self._unknown_words(data)
            if unknown:
                self._skip(unknown, "words of no known type",
                           "words of a type the EVT version does not define, or CONTINUED words not after an "
                           "OTHERS word, skipped (not EVT data?)")
            ev = self.decoder.feed(data)
            if self.decoder.skipped_words > words:
                self._skip(self.decoder.skipped_words - words, "event words without a time",
                           "event words before the first TIME_HIGH (no time known) skipped")
                words = self.decoder.skipped_words
            if ev.size:
                yield self._valid(ev)
        if self.decoder.pending_bytes:
            self._skip(self.decoder.pending_bytes, "bytes of a cut-off word",
                       "the file ends inside a word (truncated?): its bytes are ignored")

    def close(self) -> None:
        self._f.close()


class RawWriter(EventWriter):
    """Writer of a Prophesee RAW file in EVT 3.0 (``evt=3``) or EVT 2.0 (``evt=2``)."""

    def __init__(self, path: str | Path, width: int, height: int, evt: int | str = 3) -> None:
        evt = str(evt)
        if evt not in ("3", "3.0", "2", "2.0"):
            raise FormatError(f"can write RAW as EVT 3 or 2, not {evt!r}")
        three = evt.startswith("3")
        self._enc = Evt3Encoder() if three else Evt2Encoder()
        self._f = open(path, "wb")
        name = "EVT3" if three else "EVT2"
        self._f.write((f"% evt {'3.0' if three else '2.0'}\n% format {name};height={height};width={width}\n"
                       f"% geometry {width}x{height}\n% integrator_name arena\n% end\n").encode())

    def write(self, events: np.ndarray) -> None:
        events = check_events(events)
        try:
            self._f.write(self._enc.encode(events))
        except ValueError as exc:
            raise FormatError(str(exc)) from None

    def close(self) -> None:
        self._f.close()

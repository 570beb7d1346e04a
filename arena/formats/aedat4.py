"""iniVation AEDAT 4.0 files (DV software): a minimal reader and writer of event streams.

Layout: ``#!AER-DAT4.0\\r\\n``, then a size-prefixed FlatBuffer ``IOHeader`` (identifier
``IOHE``; compression: 0 none, 1 LZ4, 2 LZ4 high, 3 ZSTD, 4 ZSTD high; dataTablePosition;
infoNode: an XML description of the streams), then packets: int32 stream id,
int32 byte size and the compressed body, a size-prefixed FlatBuffer
``EventPacket`` (identifier ``EVTS``) whose ``elements`` vector holds 16-byte
structs (int64 t µs, int16 x, int16 y, bool on, 3 pad bytes).

Only polarity-event streams (``EVTS``) are read; frames, IMU and trigger packets are
skipped. The writer writes one event stream and no file data table
(``dataTablePosition = -1``), which iniVation's dv-processing (tested, every compression) and the
``aedat`` package accept.
"""

from __future__ import annotations

import struct
import xml.etree.ElementTree as ET
from pathlib import Path

import lz4.frame
import numpy as np
import zstandard

from arena.events import EVENT_DTYPE
from arena.formats.base import DEFAULT_CHUNK_EVENTS, EventReader, EventWriter, FormatError, check_events

MAGIC = b"#!AER-DAT4.0\r\n"
COMPRESSIONS = {"none": 0, "lz4": 1, "lz4high": 2, "zstd": 3, "zstdhigh": 4}
_AEDAT_EVENT = np.dtype([("t", "<i8"), ("x", "<i2"), ("y", "<i2"), ("on", "u1"), ("pad", "V3")])


def _field(buf: bytes, table: int, index: int) -> int | None:
    """Absolute position of field ``index`` of the FlatBuffer table at ``table``, or None if absent."""
    vt = table - struct.unpack_from("<i", buf, table)[0]
    vt_size = struct.unpack_from("<H", buf, vt)[0]
    if 4 + 2 * index + 2 > vt_size:
        return None
    off = struct.unpack_from("<H", buf, vt + 4 + 2 * index)[0]
    return table + off if off else None


def _parse_info(xml_text: str) -> dict[int, dict]:
    """Streams described by the infoNode XML: id -> {type, width, height}."""
    streams: dict[int, dict] = {}
    root = ET.fromstring(xml_text)
    for node in root.iter("node"):
        name = node.get("name", "")
        if not name.isdigit():
            continue
        attrs = {a.get("key"): (a.text or "") for a in node.findall("attr")}
        info = node.find("node[@name='info']")
        iattrs = {a.get("key"): (a.text or "") for a in info.findall("attr")} if info is not None else {}
        streams[int(name)] = {"type": attrs.get("typeIdentifier", ""),
                              "width": int(iattrs.get("sizeX", 0) or 0),
                              "height": int(iattrs.get("sizeY", 0) or 0)}
    return streams


def _decompress(body: bytes, compression: int) -> bytes:
    if compression == 0:
        return body
    if compression in (1, 2):
        return lz4.frame.decompress(body)
    if compression in (3, 4):
        return zstandard.ZstdDecompressor().decompressobj().decompress(body)
    raise FormatError(f"unknown AEDAT4 compression {compression}")


def _packet_events(buf: bytes) -> np.ndarray:
    """Events of one decompressed, size-prefixed ``EventPacket`` FlatBuffer."""
    if len(buf) < 12 or buf[8:12] != b"EVTS":
        raise FormatError("AEDAT4 event packet lacks the EVTS identifier")
    table = 4 + struct.unpack_from("<I", buf, 4)[0]
    pos = _field(buf, table, 0)
    if pos is None:
        return np.empty(0, EVENT_DTYPE)
    vec = pos + struct.unpack_from("<I", buf, pos)[0]
    n = struct.unpack_from("<I", buf, vec)[0]
    if vec + 4 + 16 * n > len(buf):
        raise FormatError("AEDAT4 event packet is shorter than its element count says")
    raw = np.frombuffer(buf, _AEDAT_EVENT, count=n, offset=vec + 4)
    ev = np.empty(n, EVENT_DTYPE)
    ev["x"] = raw["x"]
    ev["y"] = raw["y"]
    ev["p"] = raw["on"] != 0
    ev["t"] = raw["t"]
    return ev


class Aedat4Reader(EventReader):
    """Streaming reader of the first polarity-event stream of an AEDAT 4.0 file (one chunk per packet)."""

    def __init__(self, path: str | Path, chunk_events: int = DEFAULT_CHUNK_EVENTS) -> None:
        super().__init__()
        self.path = str(path)
        self._f = open(path, "rb")
        try:
            if self._f.read(len(MAGIC)) != MAGIC:
                raise FormatError(f"{path}: not an AEDAT 4.0 file (bad magic)")
            size_b = self._f.read(4)
            if len(size_b) < 4:
                raise FormatError(f"{path}: AEDAT4 header is truncated")
            size = struct.unpack("<I", size_b)[0]
            hdr = size_b + self._f.read(size)
            if len(hdr) < size + 4:
                raise FormatError(f"{path}: AEDAT4 header is truncated")
            table = 4 + struct.unpack_from("<I", hdr, 4)[0]
            p = _field(hdr, table, 0)
            self.compression = struct.unpack_from("<i", hdr, p)[0] if p else 0
            p = _field(hdr, table, 1)
            self.data_table_position = struct.unpack_from("<q", hdr, p)[0] if p else -1
            p = _field(hdr, table, 2)
            if p is None:
                raise FormatError(f"{path}: AEDAT4 header has no stream description")
            s = p + struct.unpack_from("<I", hdr, p)[0]
            n = struct.unpack_from("<I", hdr, s)[0]
            self.streams = _parse_info(hdr[s + 4:s + 4 + n].decode("utf-8", "replace"))
        except (struct.error, ET.ParseError) as exc:
            self._f.close()
            raise FormatError(f"{path}: corrupt AEDAT4 header ({exc})") from None
        except FormatError:
            self._f.close()
            raise
        ids = [i for i, s in sorted(self.streams.items()) if s["type"] == "EVTS"]
        if not ids:
            self._f.close()
            raise FormatError(f"{path}: AEDAT4 file has no polarity event (EVTS) stream")
        self.stream_id = ids[0]
        self.width = self.streams[self.stream_id]["width"] or 1
        self.height = self.streams[self.stream_id]["height"] or 1
        self.skipped_packets = 0

    def chunks(self):
        while True:
            if 0 <= self.data_table_position <= self._f.tell():
                return
            head = self._f.read(8)
            if len(head) < 8:
                if head:
                    raise FormatError(f"{self.path}: truncated AEDAT4 packet header")
                return
            sid, size = struct.unpack("<ii", head)
            body = self._f.read(size)
            if size < 0 or len(body) < size:
                raise FormatError(f"{self.path}: truncated AEDAT4 packet ({len(body)} of {size} bytes)")
            if sid != self.stream_id:
                continue
            try:
                ev = _packet_events(_decompress(body, self.compression))
            except (RuntimeError, zstandard.ZstdError, struct.error, FormatError):
                self.skipped_packets += 1
                continue
            if ev.size:
                yield self._valid(ev)

    def close(self) -> None:
        self._f.close()


def _header_buffer(compression: int, info: str) -> bytes:
    """The size-prefixed ``IOHeader`` FlatBuffer, file identifier ``IOHE`` (which iniVation's
    readers verify: without it dv-processing refused our files)."""
    s = info.encode()
    body = bytearray(48 + len(s) + 1)
    # [0] size prefix, [4] root offset, [8] "IOHE", [12] vtable (3 fields), [24] table:
    # [24] vtable offset, [28] compression, [32] dataTablePosition, [40] infoNode offset;
    # [44] the string (length, bytes, NUL)
    struct.pack_into("<I", body, 4, 24 - 4)
    body[8:12] = b"IOHE"
    struct.pack_into("<HHHHH", body, 12, 10, 20, 4, 8, 16)
    struct.pack_into("<iiqI", body, 24, 24 - 12, compression, -1, 44 - 40)
    struct.pack_into("<I", body, 44, len(s))
    body[48:48 + len(s)] = s
    body += b"\0" * (-len(body) % 8)
    struct.pack_into("<I", body, 0, len(body) - 4)
    return bytes(body)


def _packet_buffer(events: np.ndarray) -> bytes:
    n = events.size
    out = bytearray(32)
    # [0] size prefix, [4] root offset, [8] "EVTS", [12] vtable, [20] table, [28] vector
    struct.pack_into("<I", out, 4, 20 - 4)
    out[8:12] = b"EVTS"
    struct.pack_into("<HHH", out, 12, 6, 8, 4)
    struct.pack_into("<iII", out, 20, 20 - 12, 28 - 24, n)
    raw = np.zeros(n, _AEDAT_EVENT)
    raw["t"] = events["t"]
    raw["x"] = events["x"]
    raw["y"] = events["y"]
    raw["on"] = events["p"] != 0
    struct.pack_into("<I", out, 0, 32 + 16 * n - 4)
    return bytes(out) + raw.tobytes()


class Aedat4Writer(EventWriter):
    """Writer of an AEDAT 4.0 file with one polarity-event stream (id 0).

    ``compression``: "lz4" (default, as DV), "lz4high", "zstd", "zstdhigh" or "none".
    Each :meth:`write` call becomes packets of at most ``packet_events`` events.
    """

    def __init__(self, path: str | Path, width: int, height: int, compression: str = "lz4",
                 packet_events: int = 1 << 16) -> None:
        key = compression.lower().replace("_", "").replace("-", "")
        if key not in COMPRESSIONS:
            raise FormatError(f"unknown AEDAT4 compression {compression!r}; choose from {sorted(COMPRESSIONS)}")
        self._comp = COMPRESSIONS[key]
        self._packet = packet_events
        info = ('<dv version="2.0"><node name="outInfo" path="/mainloop/Recorder/outInfo/">'
                '<node name="0" path="/mainloop/Recorder/outInfo/0/">'
                f'<attr key="compression" type="string">{key.upper()}</attr>'
                '<attr key="originalModuleName" type="string">arena</attr>'
                '<attr key="originalOutputName" type="string">events</attr>'
                '<attr key="typeDescription" type="string">Array of events (polarity ON/OFF).</attr>'
                '<attr key="typeIdentifier" type="string">EVTS</attr>'
                '<node name="info" path="/mainloop/Recorder/outInfo/0/info/">'
                f'<attr key="sizeX" type="int">{int(width)}</attr>'
                f'<attr key="sizeY" type="int">{int(height)}</attr>'
                '<attr key="source" type="string">arena</attr></node></node></node></dv>')
        self._f = open(path, "wb")
        self._f.write(MAGIC + _header_buffer(self._comp, info))
        self._zstd = zstandard.ZstdCompressor(level=3 if self._comp == 3 else 19)

    def _compress(self, buf: bytes) -> bytes:
        if self._comp == 0:
            return buf
        if self._comp in (1, 2):
            return lz4.frame.compress(buf, compression_level=0 if self._comp == 1 else 9)
        return self._zstd.compress(buf)

    def write(self, events: np.ndarray) -> None:
        events = check_events(events)
        for i in range(0, events.size, self._packet):
            body = self._compress(_packet_buffer(events[i:i + self._packet]))
            self._f.write(struct.pack("<ii", 0, len(body)) + body)

    def close(self) -> None:
        self._f.close()

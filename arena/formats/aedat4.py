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
from arena.formats.base import (
    DEFAULT_CHUNK_EVENTS,
    EventReader,
    EventWriter,
    FormatError,
    check_events,
    check_size,
    file_size,
    read_exactly,
)

MAGIC = b"#!AER-DAT4.0\r\n"
COMPRESSIONS = {"none": 0, "lz4": 1, "lz4high": 2, "zstd": 3, "zstdhigh": 4}
_AEDAT_EVENT = np.dtype([("t", "<i8"), ("x", "<i2"), ("y", "<i2"), ("on", "u1"), ("pad", "V3")])
#: a packet decompresses to at most this many times its size (LZ4 reaches 255, real event packets
#: under 20) and 1 MiB more, so a small hostile packet cannot claim gigabytes
_MAX_RATIO = 1024
#: most bytes one event packet may hold decompressed: 4 Mi events. DV writes one packet per batch
#: the camera delivers, 10 ms of events by libcaer's default; even at a DVXplorer's peak 165 Mev/s
#: that is 1.65 M events (26 MB), and our writer's packets are 65 536 events (never over this). A
#: packet claiming more is damage or a bomb: it is skipped before it is held in memory
_MAX_PACKET = 64 << 20
#: most events of one packet (the elements after the 32 bytes of FlatBuffer around them)
_MAX_PACKET_EVENTS = (_MAX_PACKET - 32) // 16


def _at(buf: bytes, fmt: str, pos: int):
    """``struct.unpack_from`` that refuses positions outside ``buf`` (a negative one would count
    from the end)."""
    if pos < 0 or pos + struct.calcsize(fmt) > len(buf):
        raise FormatError(f"AEDAT4 FlatBuffer offset {pos} outside its {len(buf)} bytes")
    return struct.unpack_from(fmt, buf, pos)[0]


def _field(buf: bytes, table: int, index: int) -> int | None:
    """Absolute position of field ``index`` of the FlatBuffer table at ``table``, or None if absent."""
    vt = table - _at(buf, "<i", table)
    vt_size = _at(buf, "<H", vt)
    if 4 + 2 * index + 2 > vt_size:
        return None
    off = _at(buf, "<H", vt + 4 + 2 * index)
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
        try:
            size = (int(iattrs.get("sizeX", 0) or 0), int(iattrs.get("sizeY", 0) or 0))
        except ValueError:
            raise FormatError(f"stream {name}'s sizeX/sizeY are not integers") from None
        streams[int(name)] = {"type": attrs.get("typeIdentifier", ""), "width": size[0], "height": size[1]}
    return streams


def _decompress(body: bytes, compression: int) -> bytes | bytearray:
    """The packet ``body`` decompressed, at most ``_MAX_RATIO`` times its size (plus 1 MiB) and
    at most :data:`_MAX_PACKET` bytes: what a frame header declares is not allocated beyond that,
    and the data is held once (not in pieces and joined)."""
    if compression == 0:
        return body
    cap = min(_MAX_PACKET, _MAX_RATIO * len(body) + (1 << 20))
    if compression in (1, 2):
        # in pieces into one buffer: decompress(body, max_length=cap) holds its output twice (a
        # buffer of cap bytes, then copied into the bytes returned)
        d, out, data = lz4.frame.LZ4FrameDecompressor(), bytearray(), body
        while not d.eof:
            piece = d.decompress(data, max_length=1 << 20)
            data = b""
            if len(out) + len(piece) > cap:
                raise FormatError(f"AEDAT4 packet of {len(body)} bytes expands beyond {cap} bytes")
            out += piece
            if not piece and not d.eof:    # input used up, the frame unfinished
                raise FormatError("AEDAT4 LZ4 packet is truncated")
        return out
    if compression in (3, 4):
        declared = zstandard.frame_content_size(body)   # zstd allocates it whatever the caller's cap
        if declared > cap:
            raise FormatError(f"AEDAT4 packet of {len(body)} bytes declares {declared} bytes decompressed")
        # a known size: into a buffer of that size, then one byte more must not come; unknown
        # (-1, a streamed frame): grown a piece at a time (read(cap) would allocate cap bytes)
        out = bytearray(declared if declared >= 0 else 0)
        with zstandard.ZstdDecompressor(max_window_size=1 << 27).stream_reader(body) as r:
            if declared >= 0:
                got = 0
                with memoryview(out) as view:
                    while got < declared and (k := r.readinto(view[got:])):
                        got += k
                if got < declared:
                    raise FormatError(f"AEDAT4 packet is truncated ({got} of the {declared} bytes it declares)")
                if r.read(1):
                    raise FormatError(f"AEDAT4 packet expands beyond the {declared} bytes it declares")
            else:
                while piece := r.read(1 << 20):
                    if len(out) + len(piece) > cap:
                        raise FormatError(f"AEDAT4 packet of {len(body)} bytes expands beyond {cap} bytes")
                    out += piece
        return out
    raise FormatError(f"unknown AEDAT4 compression {compression}")


def _packet_events(buf: bytes | bytearray) -> np.ndarray:
    """Events of one decompressed, size-prefixed ``EventPacket`` FlatBuffer (their x, y still
    the file's int16: see :meth:`Aedat4Reader.chunks`)."""
    if len(buf) < 12 or buf[8:12] != b"EVTS":
        raise FormatError("AEDAT4 event packet lacks the EVTS identifier")
    if _at(buf, "<I", 0) != len(buf) - 4:
        raise FormatError(f"AEDAT4 event packet's size prefix {_at(buf, '<I', 0)} is not its "
                          f"{len(buf) - 4} bytes")
    table = 4 + _at(buf, "<I", 4)
    pos = _field(buf, table, 0)
    if pos is None:
        if len(buf) - table >= 32:     # an element's worth beyond an empty table: a damaged table
            raise FormatError(f"AEDAT4 event packet of {len(buf)} bytes has no elements field: its table "
                              "is damaged")
        return np.empty(0, _AEDAT_EVENT)
    vec = pos + _at(buf, "<I", pos)
    n = _at(buf, "<I", vec)
    if vec + 4 + 16 * n > len(buf):
        raise FormatError("AEDAT4 event packet is shorter than its element count says")
    if len(buf) - (vec + 4 + 16 * n) >= 16:
        # FlatBuffers are built back to front: the elements vector, written first, ends the buffer
        # (dv-processing's packets and ours, every compression); whole unread elements after it
        # mean a damaged count
        raise FormatError(f"AEDAT4 event packet holds {len(buf) - (vec + 4 + 16 * n)} bytes after its "
                          f"{n} elements: its element count is damaged")
    return np.frombuffer(buf, _AEDAT_EVENT, count=n, offset=vec + 4)


class Aedat4Reader(EventReader):
    """Streaming reader of the first polarity-event stream of an AEDAT 4.0 file (chunks of at most
    ``chunk_events`` events, none spanning two packets).

    A packet of that stream that does not decompress or parse is skipped and counted in
    ``skipped`` (also ``skipped_packets``), with a :class:`~arena.formats.base.SkippedData` warning;
    so is a packet of a stream id the header does not describe (a damaged id would otherwise drop
    events without a word). Packets of other described streams (frames, IMU) are skipped silently.
    A packet over :data:`_MAX_PACKET` bytes (stored or decompressed) counts as corrupt. Events whose
    ``on`` byte is neither 0 nor 1 (dv-processing writes a bool) count in ``invalid``.
    """

    def __init__(self, path: str | Path, chunk_events: int = DEFAULT_CHUNK_EVENTS) -> None:
        super().__init__()
        self.path = str(path)
        self._chunk = max(1, int(chunk_events))
        self._f = open(path, "rb")
        try:
            self._size = file_size(self._f)
            if self._f.read(len(MAGIC)) != MAGIC:
                raise FormatError(f"{path}: not an AEDAT 4.0 file (bad magic)")
            size_b = self._f.read(4)
            if len(size_b) < 4:
                raise FormatError(f"{path}: AEDAT4 header is truncated")
            size = struct.unpack("<I", size_b)[0]
            if size > self._size - self._f.tell():
                raise FormatError(f"{path}: AEDAT4 header is truncated (it says {size} bytes)")
            hdr = size_b + self._f.read(size)
            table = 4 + _at(hdr, "<I", 4)
            p = _field(hdr, table, 0)
            self.compression = _at(hdr, "<i", p) if p else 0
            if self.compression not in COMPRESSIONS.values():
                raise FormatError(f"{path}: unknown AEDAT4 compression {self.compression}")
            p = _field(hdr, table, 1)
            self.data_table_position = _at(hdr, "<q", p) if p else -1
            p = _field(hdr, table, 2)
            if p is None:
                raise FormatError(f"{path}: AEDAT4 header has no stream description")
            s = p + _at(hdr, "<I", p)
            n = _at(hdr, "<I", s)
            self.streams = _parse_info(hdr[s + 4:s + 4 + n].decode("utf-8", "replace"))
        except (struct.error, ET.ParseError, FormatError, ValueError) as exc:
            self._f.close()
            if isinstance(exc, FormatError) and str(exc).startswith(f"{path}:"):
                raise
            raise FormatError(f"{path}: corrupt AEDAT4 header ({exc})") from None
        first_packet = self._f.tell()
        if self.data_table_position > self._size:
            self._f.close()
            raise FormatError(f"{path}: truncated: the header says the packets end at byte "
                              f"{self.data_table_position}, the file has {self._size} bytes")
        if 0 <= self.data_table_position < first_packet:
            self._f.close()
            raise FormatError(f"{path}: the header's dataTablePosition {self.data_table_position} lies before "
                              f"the first packet (byte {first_packet}): the header is damaged")
        ids = [i for i, s in sorted(self.streams.items()) if s["type"] == "EVTS"]
        if not ids:
            self._f.close()
            raise FormatError(f"{path}: AEDAT4 file has no polarity event (EVTS) stream")
        self.stream_id = ids[0]
        info = self.streams[self.stream_id]
        try:
            self.width, self.height = check_size(info["width"] or 1, info["height"] or 1, self.path)
        except FormatError:
            self._f.close()
            raise
        self.skipped_packets = 0

    def chunks(self):
        end = self.data_table_position if self.data_table_position >= 0 else self._size
        while True:
            pos = self._f.tell()
            if pos >= end:
                if pos > end:
                    raise FormatError(f"{self.path}: a packet runs over the header's dataTablePosition {end}: "
                                      "the header or the packet is damaged")
                return
            head = self._f.read(8)
            if len(head) < 8:
                raise FormatError(f"{self.path}: truncated AEDAT4 packet header at byte {pos}")
            sid, size = struct.unpack("<ii", head)
            if 0 <= size <= self._size - pos - 8 and size > end - pos - 8:
                raise FormatError(f"{self.path}: the packet at byte {pos} runs over the header's dataTablePosition "
                                  f"{end}: the header or the packet is damaged")
            if size < 0 or size > end - pos - 8:
                raise FormatError(f"{self.path}: truncated AEDAT4 packet at byte {pos} (it says {size} bytes, "
                                  f"{end - pos - 8} left)")
            if sid != self.stream_id:
                self._f.seek(size, 1)
                if sid not in self.streams:
                    self._skip(1, "packets of undescribed streams",
                               f"AEDAT4 packet at byte {pos} of stream {sid}, which the header does not "
                               f"describe, skipped (the events are stream {self.stream_id})")
                continue
            if size > _MAX_PACKET:     # not read: it would be held whole
                self._f.seek(size, 1)
                self.skipped_packets += 1
                self._skip(1, "corrupt packets", f"AEDAT4 event packet at byte {pos} skipped ({size} bytes, "
                           f"over the {_MAX_PACKET} bytes of a real packet)")
                continue
            body = read_exactly(self._f, size, end, "AEDAT4 packet", self.path)
            try:
                raw = _packet_events(_decompress(body, self.compression))
            except (RuntimeError, zstandard.ZstdError, FormatError) as exc:
                self.skipped_packets += 1
                self._skip(1, "corrupt packets", f"AEDAT4 event packet at byte {pos} skipped ({exc})")
                continue
            for i in range(0, raw.size, self._chunk):
                part = raw[i:i + self._chunk]
                # the on byte as stored: _columns drops (and counts) any but 0 and 1
                yield self._valid(self._columns(part["x"], part["y"], part["on"], part["t"]))

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
        self._packet = max(1, min(int(packet_events), _MAX_PACKET_EVENTS))   # what the reader accepts
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

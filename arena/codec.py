"""Event-window codecs: compact, lossless by default, carried by name in ``EventWindow.codec``.

``planes-zstd/1`` (default, lossless): each event becomes one control byte and one
low-bits byte, plus rare escape varints, each stream zstd-compressed separately:

* a *run* event continues the previous one (same t, y and p, larger x): the control
  byte holds ``gap >> 7`` (``gap = x - x_prev - 1``) and the low byte ``gap & 127``;
* any other event: control = 16 + ((p * 2 + dt_code) * 3 + dy_code) * 16 + (x >> 7),
  low byte = ``x & 127``; ``dt_code`` 0 means same time, 1 means the zigzag time step is
  in the dt escape stream; ``dy_code`` 0/1 mean dy = 0/-1, 2 means the zigzag dy is in
  the dy escape stream.

Layout: ``<4sIqIIIIII`` header (magic ``EVW1``, count, base time µs, raw lengths of the
dt and dy escape streams, compressed lengths of the four streams) then the streams.
Coordinates must be < 2048 (as in EVT 3.0); times are any int64, in any order.

``planes-zstd-ms/1`` (lossy, for thin links): times are floored to 1 ms (relative to
``t_ref_us``) and the events of each millisecond put in (y, p, x) order, then coded as above:
the same set of (x, y, p) events, each with its millisecond. ``raw/1``: the :data:`EVENT_DTYPE` bytes.
"""

from __future__ import annotations

import struct
import threading

import numpy as np
import zstandard
from numba import njit

from arena.codec_names import (  # noqa: F401 (re-exported)
    CODECS,
    DEFAULT_CODEC,
    LOSSY_CODEC,
    MAX_EVENTS_PER_BYTE,
    MAX_WINDOW_EVENTS,
    RAW_CODEC,
)
from arena.events import EVENT_DTYPE

_HEADER = struct.Struct("<4sIqIIIIII")
_MAGIC = b"EVW1"
_MAX_X = 2048
_LEVEL = 1
#: an empty plane, read-only like the decompressed ones: numba compiles one specialisation per
#: combination of writable and read-only arguments, so a writable empty escape stream cost a
#: compile in the middle of a live stream the first time one turned up
_EMPTY = np.empty(0, np.uint8)
_EMPTY.setflags(write=False)


class CodecError(ValueError):
    """Encoded event data is corrupt, truncated, of an unknown codec or exceeds a limit."""


@njit(cache=True, nogil=True)
def _put_varint(buf, n, v):
    if v < 0x4000:      # one or two bytes (nearly every time or row step): no loop to mispredict;
        big = v >= 0x80  # the second byte is written regardless and overwritten when unused
        buf[n] = (v & 0x7F) | (0x80 if big else 0)
        buf[n + 1] = v >> 7
        return n + 1 + big
    while v >= 0x80:
        buf[n] = (v & 0x7F) | 0x80
        v >>= 7
        n += 1
    buf[n] = v
    return n + 1


@njit(cache=True, nogil=True)
def _encode_planes(xs, ys, ps, ts, t_base, ctrl, low, dt_esc, dy_esc):
    """Fill the streams; returns the escape stream lengths, or (-1, x) for an x >= 2048."""
    px = np.int64(0)
    py = np.int64(0)
    pp = np.int64(0)
    pt = t_base
    ndt = 0
    ndy = 0
    for i in range(xs.size):
        x = np.int64(xs[i])
        y = np.int64(ys[i])
        p = np.int64(ps[i]) & 1
        t = ts[i]
        if x >= 2048:
            return -1, x
        if t == pt and y == py and p == pp and x > px and i > 0:
            gap = x - px - 1
            ctrl[i] = gap >> 7
            low[i] = gap & 0x7F
        else:
            dtc = 0
            if t != pt:
                d = t - pt
                ndt = _put_varint(dt_esc, ndt, np.uint64((d << 1) ^ (d >> 63)))
                dtc = 1
            dy = y - py
            if dy == 0:
                dyc = 0
            elif dy == -1:
                dyc = 1
            else:
                dyc = 2
                ndy = _put_varint(dy_esc, ndy, np.uint64((dy << 1) ^ (dy >> 63)))
            ctrl[i] = 16 + ((p * 2 + dtc) * 3 + dyc) * 16 + (x >> 7)
            low[i] = x & 0x7F
        px = x
        py = y
        pp = p
        pt = t
    return ndt, ndy


@njit(cache=True, nogil=True)
def _get_varint(buf, n):
    if n + 1 < buf.size:                    # one or two bytes: no loop
        b0 = np.uint64(buf[n])
        if b0 < 0x80:
            return b0, n + 1
        b1 = np.uint64(buf[n + 1])
        if b1 < 0x80:
            return (b0 & np.uint64(0x7F)) | (b1 << np.uint64(7)), n + 2
    v = np.uint64(0)
    shift = np.uint64(0)
    while True:
        if n >= buf.size or shift > 63:
            return v, -1
        b = np.uint64(buf[n])
        v |= (b & np.uint64(0x7F)) << shift
        n += 1
        if b < 0x80:
            return v, n
        shift += np.uint64(7)


@njit(cache=True, nogil=True)
def _decode_planes(ctrl, low, dt_esc, dy_esc, t_base, xs, ys, ps, ts):
    """Returns 0 on success, or a negative error code."""
    px = np.int64(0)
    py = np.int64(0)
    pp = np.int64(0)
    pt = t_base
    kdt = 0
    kdy = 0
    for i in range(ctrl.size):
        c = np.int64(ctrl[i])
        lo = np.int64(low[i])
        if c < 16:
            x = px + 1 + ((c << 7) | lo)
            if i == 0 or lo > 0x7F:
                return -1
        else:
            c -= 16
            if c >= 192 or lo > 0x7F:
                return -1
            x = ((c & 15) << 7) | lo
            k = c >> 4
            dyc = k % 3
            k //= 3
            dtc = k & 1
            pp = k >> 1
            if dtc:
                u, kdt = _get_varint(dt_esc, kdt)
                if kdt < 0:
                    return -2
                pt += np.int64(u >> np.uint64(1)) ^ -np.int64(u & np.uint64(1))
            if dyc == 1:
                py -= 1
            elif dyc == 2:
                u, kdy = _get_varint(dy_esc, kdy)
                if kdy < 0:
                    return -3
                py += np.int64(u >> np.uint64(1)) ^ -np.int64(u & np.uint64(1))
        if x >= 65536 or py < 0 or py >= 65536:
            return -4
        xs[i] = x
        ys[i] = py
        ps[i] = pp
        ts[i] = pt
        px = x
    if kdt != dt_esc.size or kdy != dy_esc.size:
        return -5
    return 0


@njit(cache=True, nogil=True)
def _decode_step(ctrl, low, dt_esc, kdt, dt_more, dy_esc, kdy, dy_more, st, xs, ys, ps, ts, i0):
    """:func:`_decode_planes` resumable, for a window decoded in chunks: decodes events ``i0 + j``
    from ``ctrl[j]``, ``low[j]`` with the escape bytes at hand (``dt_more``/``dy_more``: more of
    that stream is still to come), the state ``st = [px, py, pp, pt]`` carried between calls.
    Returns ``(j, kdt, kdy, code)``: ``j`` events done; ``code`` 0 when the chunk is done, 1 or 2
    when the next event needs more bytes of the dt or dy stream (no partial event is consumed), a
    negative error code as :func:`_decode_planes`."""
    px = st[0]
    py = st[1]
    pp = st[2]
    pt = st[3]
    for j in range(ctrl.size):
        i = i0 + j
        c = np.int64(ctrl[j])
        lo = np.int64(low[j])
        if c < 16:
            x = px + 1 + ((c << 7) | lo)
            if i == 0 or lo > 0x7F:
                return j, kdt, kdy, -1
        else:
            c -= 16
            if c >= 192 or lo > 0x7F:
                return j, kdt, kdy, -1
            x = ((c & 15) << 7) | lo
            k = c >> 4
            dyc = k % 3
            k //= 3
            dtc = k & 1
            if dtc and dt_more and dt_esc.size - kdt < 10:
                st[0] = px
                st[1] = py
                st[2] = pp
                st[3] = pt
                return j, kdt, kdy, 1
            if dyc == 2 and dy_more and dy_esc.size - kdy < 10:
                st[0] = px
                st[1] = py
                st[2] = pp
                st[3] = pt
                return j, kdt, kdy, 2
            pp = k >> 1
            if dtc:
                u, kdt = _get_varint(dt_esc, kdt)
                if kdt < 0:
                    return j, kdt, kdy, -2
                pt += np.int64(u >> np.uint64(1)) ^ -np.int64(u & np.uint64(1))
            if dyc == 1:
                py -= 1
            elif dyc == 2:
                u, kdy = _get_varint(dy_esc, kdy)
                if kdy < 0:
                    return j, kdt, kdy, -3
                py += np.int64(u >> np.uint64(1)) ^ -np.int64(u & np.uint64(1))
        if x >= 65536 or py < 0 or py >= 65536:
            return j, kdt, kdy, -4
        xs[i] = x
        ys[i] = py
        ps[i] = pp
        ts[i] = pt
        px = x
    st[0] = px
    st[1] = py
    st[2] = pp
    st[3] = pt
    return ctrl.size, kdt, kdy, 0


_local = threading.local()


#: zstd's level-1 strategy with the shortest matches it allows (7 bytes) and a 4096-entry hash
#: table. The streams are mostly entropy-coded (short matches rarely pay), and the table is reset
#: for every frame of a 10 ms window, so on the simulator's windows this is 15-20 % faster than
#: level 1 and 1.5 % smaller (bench/bench_codec.py); on the real sample the same size, faster.
_FAST = zstandard.ZstdCompressionParameters(window_log=17, hash_log=12, chain_log=12, search_log=1, min_match=7,
                                            target_length=0, strategy=zstandard.STRATEGY_FAST)


@njit(cache=True, nogil=True)
def _first_ms(ts, base):
    """The first whole millisecond of ``base``'s grid at or before the earliest of ``ts``, µs."""
    t_lo = ts[0]
    for i in range(ts.size):
        if ts[i] < t_lo:
            t_lo = ts[i]
    return base + (t_lo - base) // 1000 * 1000


@njit(cache=True, nogil=True)
def _key_pass(xs, ys, ps, ts, base, key):
    """The lossy codec's sort keys ``ms << 28 | y << 12 | p << 11 | x`` (ms counted from the
    first whole millisecond of ``base``'s grid at or before the earliest event); returns that
    millisecond's time, or (0, False) when a key would not fit (x >= 2048, y >= 65536 or a
    span over 2^35 ms): the caller then sorts without packing."""
    t_min = _first_ms(ts, base)
    for i in range(xs.size):
        ms = (ts[i] - t_min) // 1000
        x = np.int64(xs[i])
        if x >= 2048 or ms >= (1 << 35):
            return t_min, False
        key[i] = (ms << 28) | (np.int64(ys[i]) << 12) | ((np.int64(ps[i]) & 1) << 11) | x
    return t_min, True


@njit(cache=True, nogil=True)
def _key_pass32(xs, ys, ps, ts, base, key):
    """As :func:`_key_pass` in 32 bits, ``ms << 23 | y << 12 | p << 11 | x``, for a window of
    under 512 ms with x, y < 2048 (a 10 ms window always is): numpy sorts 32-bit keys about twice
    as fast. Returns (t_min, False) when a key would not fit."""
    t_min = _first_ms(ts, base)
    for i in range(xs.size):
        ms = (ts[i] - t_min) // 1000
        x = np.int64(xs[i])
        y = np.int64(ys[i])
        if x >= 2048 or y >= 2048 or ms >= 512:
            return t_min, False
        key[i] = np.uint32((ms << 23) | (y << 12) | ((np.int64(ps[i]) & 1) << 11) | x)
    return t_min, True


@njit(cache=True, nogil=True)
def _unpack_keys32(key, t_min, xs, ys, ps, ts):
    for i in range(key.size):
        k = np.int64(key[i])
        xs[i] = k & 0x7FF
        ps[i] = (k >> 11) & 1
        ys[i] = (k >> 12) & 0x7FF
        ts[i] = t_min + (k >> 23) * 1000


def _lossy_keys(xs, ys, ps, ts, base: int, key: np.ndarray) -> int | None:
    t_min, ok = _key_pass(xs, ys, ps, ts, base, key)
    return int(t_min) if ok else None


@njit(cache=True, nogil=True)
def _unpack_keys(key, t_min, xs, ys, ps, ts):
    for i in range(key.size):
        k = key[i]
        xs[i] = k & 0x7FF
        ps[i] = (k >> 11) & 1
        ys[i] = (k >> 12) & 0xFFFF
        ts[i] = t_min + (k >> 28) * 1000


def _compressor(level: int) -> zstandard.ZstdCompressor:
    """A zstd compressor of ``level`` (1: the tuned :data:`_FAST` parameters) reused within the
    calling thread (they are not thread-safe)."""
    cache = _local.__dict__.setdefault("compressors", {})
    if level not in cache:
        cache[level] = (zstandard.ZstdCompressor(compression_params=_FAST) if level == _LEVEL
                        else zstandard.ZstdCompressor(level=level))
    return cache[level]


def _decompressor() -> zstandard.ZstdDecompressor:
    """A zstd decompressor reused within the calling thread."""
    if not hasattr(_local, "decompressor"):
        _local.decompressor = zstandard.ZstdDecompressor()
    return _local.decompressor


def _stream_decompressors() -> list[zstandard.ZstdDecompressor]:
    """Four zstd decompressors (one per stream: their readers run interleaved, and one
    decompressor serves one operation at a time) reused within the calling thread, each refusing
    a frame whose window is over :data:`_MAX_STREAM_WINDOW`."""
    if not hasattr(_local, "stream_decompressors"):
        _local.stream_decompressors = [zstandard.ZstdDecompressor(max_window_size=_MAX_STREAM_WINDOW)
                                       for _ in range(4)]
    return _local.stream_decompressors


def _check(events: np.ndarray) -> np.ndarray:
    if not isinstance(events, np.ndarray) or events.dtype != EVENT_DTYPE:
        from arena.events import as_events

        events = as_events(np.asarray(events))
    return events


def encode(events: np.ndarray, codec: str = DEFAULT_CODEC, t_ref_us: int | None = None,
           level: int = _LEVEL) -> bytes:
    """Encode an event array (:data:`EVENT_DTYPE`, px, µs) with ``codec``.

    ``t_ref_us``: base of the time deltas and origin of the 1 ms grid of the lossy codec
    (default: the first event's time). ``level``: zstd level (1, the default, is fastest and
    uses parameters tuned for these streams).
    Raises :class:`CodecError` for an unknown codec or x >= 2048.
    """
    events = _check(events)
    if codec == RAW_CODEC:
        return events.tobytes()
    if codec not in (DEFAULT_CODEC, LOSSY_CODEC):
        raise CodecError(f"unknown codec {codec!r}; known: {', '.join(CODECS)}")
    n = events.size
    base = int(t_ref_us) if t_ref_us is not None else (int(events["t"][0]) if n else 0)
    xs, ys, ps, ts = events["x"], events["y"], events["p"], events["t"]
    if codec == LOSSY_CODEC and n:
        # floor to 1 ms; within one millisecond the order carries no information any more, so
        # sort by (ms, y, p, x), which turns the events into cheap runs
        key32 = np.empty(n, np.uint32)
        t_min, ok = _key_pass32(xs, ys, ps, ts, base, key32)
        key = None
        if not ok:
            key = np.empty(n, np.int64)
            t_min = _lossy_keys(xs, ys, ps, ts, base, key)
        if ok or t_min is not None:   # one packed key per event, sorted, unpacked
            out = (np.empty(n, np.uint16), np.empty(n, np.uint16), np.empty(n, np.uint8), np.empty(n, np.int64))
            if ok:
                key32.sort()
                _unpack_keys32(key32, int(t_min), *out)
            else:
                key.sort()
                _unpack_keys(key, t_min, *out)
            xs, ys, ps, ts = out
        else:
            t_min = base + (int(ts.min()) - base) // 1000 * 1000
            ms = (ts - t_min) // 1000
            order = np.lexsort((xs, ps, ys, ms))
            xs, ys, ps, ts = xs[order], ys[order], ps[order], t_min + ms[order] * 1000
    ctrl = np.empty(n, np.uint8)
    low = np.empty(n, np.uint8)
    dt_esc = np.empty(n * 10, np.uint8)
    dy_esc = np.empty(n * 3, np.uint8)
    ndt, ndy = _encode_planes(xs, ys, ps, ts, base, ctrl, low, dt_esc, dy_esc)
    if ndt < 0:
        raise CodecError(f"{codec} codes x < {_MAX_X}; got x = {ndy}")
    z = _compressor(level)
    parts = [z.compress(a.data) if a.size else b"" for a in (ctrl, low, dt_esc[:ndt], dy_esc[:ndy])]
    head = _HEADER.pack(_MAGIC, n, base, ndt, ndy, *(len(p) for p in parts))
    return b"".join([head, *parts])


#: Most bytes of decompressed streams a window is decoded from in one piece (each stream to its
#: full length, zstd allocating that length up front); a window whose header declares more (a
#: 10 ms window of over ~3 M events) is decoded in chunks of :data:`_CHUNK` bytes, so what its
#: streams decompress to is never held at once: decode holds the events (13 B each) and a few MB.
_ONE_SHOT_BYTES = 16 << 20
_CHUNK = 1 << 20
#: Largest zstd window a chunked stream may need (each of the four keeps one): 8 MiB is what level
#: 19 uses; :func:`encode` at level 1 uses 128 KiB.
_MAX_STREAM_WINDOW = 1 << 23


def decode(codec: str, data: bytes, count: int, max_events: int = MAX_WINDOW_EVENTS) -> np.ndarray:
    """Decode ``count`` events coded with ``codec``; raises :class:`CodecError` on any mismatch.

    ``max_events`` (default :data:`arena.codec_names.MAX_WINDOW_EVENTS`, the limit
    :class:`arena.messages.DecodeLimits` applies too) bounds the memory a corrupt or hostile
    message can claim, as do :data:`~arena.codec_names.MAX_EVENTS_PER_BYTE` (a window of repeated
    bytes that zstd packs 16 000 to one is refused) and each zstd frame's declared content size,
    checked against the header's stream lengths before anything is allocated. What the streams
    decompress to is bounded too: a window's streams are decompressed whole only up to
    :data:`_ONE_SHOT_BYTES` together, beyond that in chunks with a hard cap at the header's
    lengths, so decode holds at most the ``count`` events (13 B each, 130 MB at the limit) and a
    few MB, whatever the header claims. A MemoryError while decoding is a :class:`CodecError`.
    """
    try:
        return _decode(codec, data, count, max_events)
    except MemoryError:
        raise CodecError(f"{codec} payload of {len(data)} bytes ({count} events) does not fit in memory") from None


def _read_exact(reader, k: int) -> bytes:
    """Up to ``k`` bytes of a zstd stream reader (fewer only at the end of its frame)."""
    got = reader.read(k)
    if len(got) == k or not got:
        return got
    parts, total = [got], len(got)
    while total < k:
        more = reader.read(k - total)
        if not more:
            break
        parts.append(more)
        total += len(more)
    return b"".join(parts)


def _ro(buf: bytes) -> np.ndarray:
    if not buf:
        return _EMPTY
    a = np.frombuffer(buf, np.uint8)
    a.setflags(write=False)
    return a


def _decode_chunked(codec: str, frames: list, n: int, ndt: int, ndy: int, base: int) -> np.ndarray:
    """Decode the four streams ``frames`` in chunks of :data:`_CHUNK` (see :func:`decode`)."""
    lengths = (n, n, ndt, ndy)
    readers = [d.stream_reader(f) if length else None
               for d, f, length in zip(_stream_decompressors(), frames, lengths)]
    ev = np.empty(n, EVENT_DTYPE)
    xs, ys, ps, ts = ev["x"], ev["y"], ev["p"], ev["t"]
    st = np.array([0, 0, 0, base], np.int64)
    esc = [_EMPTY, _EMPTY]             # the dt and dy bytes at hand
    pos = [0, 0]                       # next byte of each
    read = [0, 0]                      # bytes read of each stream so far
    more = [ndt > 0, ndy > 0]

    def refill(s: int) -> None:
        got = _read_exact(readers[2 + s], min(_CHUNK, lengths[2 + s] - read[s]))
        read[s] += len(got)
        if read[s] >= lengths[2 + s] or not got:
            more[s] = False
        rest = esc[s][pos[s]:]
        esc[s] = _ro(bytes(rest) + got) if rest.size else _ro(got)
        pos[s] = 0

    i = 0
    while i < n:
        for s, per_event in ((0, 10), (1, 3)):
            # an escape is at most 10 (dt) or 3 (dy) bytes: more left than the events left can
            # take is refused now, not after decoding them all
            if lengths[2 + s] - (read[s] - (esc[s].size - pos[s])) > per_event * (n - i):
                raise CodecError(f"{codec} payload is inconsistent (code -5)")
        k = min(_CHUNK, n - i)
        ctrl, low = _read_exact(readers[0], k), _read_exact(readers[1], k)
        if len(ctrl) != k or len(low) != k:
            raise CodecError(f"{codec} stream has fewer bytes than the header's {n}")
        ctrl, low = _ro(ctrl), _ro(low)
        j = 0
        while j < k:
            done, pos[0], pos[1], code = _decode_step(ctrl[j:], low[j:], esc[0], pos[0], more[0], esc[1], pos[1],
                                                      more[1], st, xs, ys, ps, ts, i + j)
            if code < 0:
                raise CodecError(f"{codec} payload is inconsistent (code {code})")
            j += done
            if code:
                refill(code - 1)
        i += k
    for s, reader in enumerate(readers):
        if reader is None:
            continue
        if s < 2:
            if reader.read(1):
                raise CodecError(f"{codec} stream has more bytes than the header's {n}")
        elif pos[s - 2] != esc[s - 2].size or more[s - 2] or read[s - 2] != lengths[s] or reader.read(1):
            raise CodecError(f"{codec} payload is inconsistent (code -5)")
    return ev


def _decode(codec: str, data: bytes, count: int, max_events: int) -> np.ndarray:
    if count < 0 or count > max_events:
        raise CodecError(f"event count {count} outside [0, {max_events}]")
    if codec == RAW_CODEC:
        if len(data) != count * EVENT_DTYPE.itemsize:
            raise CodecError(f"raw/1 payload has {len(data)} bytes, expected {count * EVENT_DTYPE.itemsize}")
        return np.frombuffer(data, EVENT_DTYPE).copy()
    if codec not in (DEFAULT_CODEC, LOSSY_CODEC):
        raise CodecError(f"unknown codec {codec!r}; known: {', '.join(CODECS)}")
    if len(data) < _HEADER.size:
        raise CodecError(f"{codec} payload of {len(data)} bytes is shorter than its header")
    magic, n, base, ndt, ndy, *sizes = _HEADER.unpack_from(data)
    if magic != _MAGIC:
        raise CodecError(f"{codec} payload has a bad magic {magic!r}")
    if n != count:
        raise CodecError(f"{codec} payload holds {n} events but the message says {count}")
    if _HEADER.size + sum(sizes) != len(data):
        raise CodecError(f"{codec} payload is {len(data)} bytes, its header says {_HEADER.size + sum(sizes)}")
    if ndt > 10 * n or ndy > 3 * n:
        raise CodecError(f"{codec} escape streams larger than possible for {n} events")
    if n > MAX_EVENTS_PER_BYTE * len(data):
        raise CodecError(f"{codec} payload of {len(data)} bytes claims {n} events, more than "
                         f"{MAX_EVENTS_PER_BYTE} per byte: a decompression bomb or corrupt")
    frames, pos = [], _HEADER.size
    for size, raw_len in zip(sizes, (n, n, ndt, ndy)):
        frame = data[pos:pos + size]
        pos += size
        if not raw_len:
            if size:
                raise CodecError(f"{codec} stream of {size} bytes where the header says it is empty")
        else:
            try:
                # zstd allocates a frame's declared content size whatever max_output_size says
                declared = zstandard.frame_content_size(frame)
            except zstandard.ZstdError as exc:
                raise CodecError(f"{codec} payload is corrupt ({exc})") from None
            if declared != raw_len and declared != -1:
                raise CodecError(f"{codec} stream declares {declared} bytes, the header {raw_len}")
        frames.append(frame)
    if 2 * n + ndt + ndy > _ONE_SHOT_BYTES:
        try:
            return _decode_chunked(codec, frames, n, ndt, ndy, base)
        except zstandard.ZstdError as exc:
            raise CodecError(f"{codec} payload is corrupt ({exc})") from None
    d = _decompressor()
    out = []
    for frame, raw_len in zip(frames, (n, n, ndt, ndy)):
        if not raw_len:
            out.append(_EMPTY)
            continue
        try:
            # bytes after the frame are refused, as the chunked path's stream readers do
            plane = d.decompress(frame, max_output_size=raw_len, allow_extra_data=False)
        except zstandard.ZstdError as exc:
            raise CodecError(f"{codec} payload is corrupt ({exc})") from None
        if len(plane) != raw_len:
            raise CodecError(f"{codec} stream has {len(plane)} bytes, expected {raw_len}")
        out.append(np.frombuffer(plane, np.uint8))
    ev = np.empty(n, EVENT_DTYPE)
    err = _decode_planes(out[0], out[1], out[2], out[3], base, ev["x"], ev["y"], ev["p"], ev["t"])
    if err:
        raise CodecError(f"{codec} payload is inconsistent (code {err})")
    return ev

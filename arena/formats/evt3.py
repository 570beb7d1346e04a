"""Prophesee EVT 3.0 (16-bit words): streaming decoder and encoder.

Word layout (little endian, type in bits 15..12):

====  ===============  ==========================================================
0x0   EVT_ADDR_Y       y in bits 10..0 (bit 11 = system type / master-slave, ignored)
0x2   EVT_ADDR_X       one event at x = bits 10..0, polarity bit 11
0x3   VECT_BASE_X      base x = bits 10..0, polarity bit 11 for the next vectors
0x4   VECT_12          12-bit valid mask: events at base_x + i; base_x += 12
0x5   VECT_8           8-bit valid mask: events at base_x + i; base_x += 8
0x6   EVT_TIME_LOW     time bits 11..0 (µs)
0x8   EVT_TIME_HIGH    time bits 23..12; a repeat does not reset TIME_LOW
0xA   EXT_TRIGGER      ignored
0xE   OTHERS           ignored
0xF   CONTINUED        ignored
====  ===============  ==========================================================

The 24-bit time wraps every 16.78 s; the decoder extends it to 64 bits (a
TIME_HIGH that goes back by more than half its range is a wrap).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from arena.events import EVENT_DTYPE

_WRAP = 1 << 24

# state slots
_Y, _TH, _TL, _BX, _POL, _OFF, _HAVE_T, _SKIPPED, _TL_FRESH = range(9)


def _events_per_word() -> np.ndarray:
    """How many events each of the 65536 words encodes (EVT_ADDR_X 1, VECT_12/VECT_8 their set
    bits, others 0): counting a chunk is then one table load per word, ~10x faster than a branch
    on the type and a popcount."""
    w = np.arange(1 << 16)
    typ = w >> 12
    bits = np.array([bin(i).count("1") for i in range(4096)], dtype=np.uint8)
    return np.where(typ == 0x2, 1, np.where(typ == 0x4, bits[w & 0xFFF],
                                            np.where(typ == 0x5, bits[w & 0xFF], 0))).astype(np.uint8)


_EVENTS_PER_WORD = _events_per_word()


@njit(cache=True, nogil=True)
def _count_events(words, per_word):
    """Number of events the words encode (events before the first TIME_HIGH included)."""
    n = 0
    for i in range(words.size):
        n += per_word[words[i]]
    return n


@njit(cache=True, nogil=True)
def _decode(words, state, xs, ys, ps, ts):
    y = state[_Y]
    th = state[_TH]
    tl = state[_TL]
    bx = state[_BX]
    pol = state[_POL]
    off = state[_OFF]
    have_t = state[_HAVE_T]
    skipped = state[_SKIPPED]
    fresh = state[_TL_FRESH]
    t = off + ((th << 12) | tl)
    n = 0
    for i in range(words.size):
        w = np.int64(words[i])
        typ = w >> 12
        if typ == 0x2:                      # the commonest word first
            if have_t:
                xs[n] = w & 0x7FF
                ys[n] = y
                ps[n] = (w >> 11) & 1
                ts[n] = t
                n += 1
            else:
                skipped += 1
        elif typ == 0x0:
            y = w & 0x7FF
        elif typ == 0x3:
            bx = w & 0x7FF
            pol = (w >> 11) & 1
        elif typ == 0x4 or typ == 0x5:
            nb = 12 if typ == 0x4 else 8
            m = w & (0xFFF if typ == 0x4 else 0xFF)
            if have_t:
                b = 0
                while m:                        # stops after the highest set bit
                    if m & 1:
                        xs[n] = bx + b
                        ys[n] = y
                        ps[n] = pol
                        ts[n] = t
                        n += 1
                    m >>= 1
                    b += 1
            else:
                skipped += 1
            if bx < 4096:                   # a run of vectors past x 2047 is garbage: never wrap x
                bx += nb
        elif typ == 0x6:
            tl = w & 0xFFF
            t = off + ((th << 12) | tl)
            fresh = 1
        elif typ == 0x8:
            nth = w & 0xFFF
            if have_t and nth < th and th - nth > 2048:
                off += _WRAP
            if nth != th:
                fresh = 0
            th = nth
            have_t = 1
            t = off + ((th << 12) | tl)
    state[_TL_FRESH] = fresh
    state[_Y] = y
    state[_TH] = th
    state[_TL] = tl
    state[_BX] = bx
    state[_POL] = pol
    state[_OFF] = off
    state[_HAVE_T] = have_t
    state[_SKIPPED] = skipped
    return n


class Evt3Decoder:
    """Streaming EVT 3.0 decoder: ``feed(bytes) -> events`` (:data:`EVENT_DTYPE`).

    Chunks may split words anywhere; the decoder keeps the odd byte and the
    state (y, time, vector base) between calls. Events that arrive before the
    first TIME_HIGH have no time and are counted in :attr:`skipped_words`.
    """

    word_bytes = 2

    def __init__(self) -> None:
        self._state = np.zeros(9, dtype=np.int64)
        self._rest = b""

    @property
    def skipped_words(self) -> int:
        """Event words dropped because no TIME_HIGH had been seen yet."""
        return int(self._state[_SKIPPED])

    @property
    def time_us(self) -> int | None:
        """Sensor time the stream has surely reached (µs), also from time words without events:
        a new TIME_HIGH period counts from its start until a TIME_LOW refines it."""
        st = self._state
        if not st[_HAVE_T]:
            return None
        return int(st[_OFF] + ((st[_TH] << 12) | (st[_TL] if st[_TL_FRESH] else 0)))

    @property
    def pending_bytes(self) -> int:
        """Bytes of an incomplete word kept for the next :meth:`feed`."""
        return len(self._rest)

    def feed(self, data: bytes | bytearray | memoryview) -> np.ndarray:
        """Decode the next chunk of the byte stream; returns the complete events in it."""
        if self._rest:
            data = self._rest + bytes(data)
        mv = memoryview(data)
        usable = len(mv) - (len(mv) % 2)
        self._rest = bytes(mv[usable:])
        words = np.frombuffer(mv[:usable], dtype="<u2")
        return decode_words(words, self._state)


def decode_words(words: np.ndarray, state: np.ndarray) -> np.ndarray:
    """Decode a uint16 word array with a decoder ``state`` (updated in place)."""
    ev = np.empty(_count_events(words, _EVENTS_PER_WORD), dtype=EVENT_DTYPE)
    n = _decode(words, state, ev["x"], ev["y"], ev["p"], ev["t"])  # writes straight into the fields
    return ev if n == ev.size else ev[:n].copy()


def decode_evt3(data: bytes) -> np.ndarray:
    """Decode a complete EVT 3.0 byte string (no header) into events."""
    return Evt3Decoder().feed(data)


@njit(cache=True, nogil=True)
def _encode(xs, ys, ps, ts, state, out):
    # state: [last_y, last_th, last_tl, started]
    last_y = state[0]
    last_th = state[1]
    last_tl = state[2]
    started = state[3]
    n = 0
    i = 0
    ne = xs.size
    while i < ne:
        t = ts[i]
        th = (t >> 12) & 0xFFF
        tl = t & 0xFFF
        epoch = t >> 24
        if not started or th != last_th or epoch != state[4]:
            # walk the decoder through the 24-bit wraps since the last word (or since 0):
            # each TIME_HIGH 0xFFF then 0x000 pair makes it add one wrap
            for _ in range(epoch - state[4]):
                if not started:
                    out[n] = 0x8000
                    n += 1
                    started = 1
                out[n] = 0x8FFF
                out[n + 1] = 0x8000
                n += 2
            out[n] = 0x8000 | th
            n += 1
            last_th = th
            state[4] = epoch
            last_tl = -1
        if tl != last_tl:
            out[n] = 0x6000 | tl
            n += 1
            last_tl = tl
        y = ys[i]
        if not started or y != last_y:
            out[n] = y & 0x7FF
            n += 1
            last_y = y
        started = 1
        # a run of one t, y and p with increasing x: code each stretch whose events fill adjacent
        # 12-px words as VECT_BASE_X + VECT_12 words when that takes fewer words than one
        # EVT_ADDR_X per event (never an empty VECT_12 word to skip a gap)
        p = ps[i]
        j = i + 1
        while j < ne and ts[j] == t and ys[j] == y and ps[j] == p and xs[j] > xs[j - 1]:
            j += 1
        k = i
        while k < j:
            bx = np.int64(xs[k])
            last_w = 0
            kk = k + 1
            while kk < j:
                w = (np.int64(xs[kk]) - bx) // 12
                if w > last_w + 1:
                    break
                last_w = w
                kk += 1
            if 2 + last_w < kk - k:
                out[n] = 0x3000 | (p << 11) | bx
                n += 1
                for w in range(last_w + 1):
                    m = 0
                    while k < kk and xs[k] < bx + 12 * (w + 1):
                        m |= 1 << (xs[k] - bx - 12 * w)
                        k += 1
                    out[n] = 0x4000 | m
                    n += 1
            else:
                out[n] = 0x2000 | (p << 11) | xs[k]
                n += 1
                k += 1
        i = j
    state[0] = last_y
    state[1] = last_th
    state[2] = last_tl
    state[3] = started
    return n


class Evt3Encoder:
    """Streaming EVT 3.0 encoder: ``encode(events) -> bytes``.

    Emits TIME_HIGH on every change of time bits 23..12; absolute times beyond
    24 bits are kept by emitting one TIME_HIGH 0xFFF, 0x000 pair per wrap (at the
    start and across gaps), which every wrap-extending decoder replays; TIME_LOW on change, EVT_ADDR_Y on change of row, and VECT_BASE_X +
    VECT_12 for stretches of one row, time and polarity whose events fill adjacent 12-px words,
    where that takes fewer words than one EVT_ADDR_X per event. Times must be non-decreasing and >= 0; x, y < 2048.
    """

    def __init__(self) -> None:
        self._state = np.zeros(5, dtype=np.int64)

    def encode(self, events: np.ndarray) -> bytes:
        if events.size == 0:
            return b""
        _check_encodable(events, 2048, 2048)
        wraps = (int(events["t"][-1]) >> 24) - int(self._state[4])
        out = np.empty(events.size * 4 + 2 * wraps + 8, dtype=np.uint16)
        n = _encode(events["x"].astype(np.int64), events["y"].astype(np.int64),
                    events["p"].astype(np.int64), events["t"].astype(np.int64), self._state, out)
        return out[:n].tobytes()


def _check_encodable(events: np.ndarray, max_x: int, max_y: int) -> None:
    if int(events["x"].max()) >= max_x or int(events["y"].max()) >= max_y:
        raise ValueError(f"event coordinates exceed the format's range ({max_x} x {max_y})")
    if int(events["t"][0]) < 0 or np.any(np.diff(events["t"]) < 0):
        raise ValueError("event times must be >= 0 and non-decreasing to be written as RAW")


def encode_evt3(events: np.ndarray) -> bytes:
    """Encode events (non-decreasing t, µs) as EVT 3.0 words (no header)."""
    return Evt3Encoder().encode(events)

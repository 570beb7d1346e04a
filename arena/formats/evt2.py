"""Prophesee EVT 2.0 (32-bit words) and EVT 2.1 (64-bit vectorised words).

EVT 2.0 word (little endian, type in bits 31..28):

====  ===============  ===================================================
0x0   CD_OFF           t bits 5..0 in 27..22, x in 21..11, y in 10..0
0x1   CD_ON            same as CD_OFF with polarity 1
0x8   EVT_TIME_HIGH    t bits 33..6 in 27..0
0xA   EXT_TRIGGER      ignored
0xE   OTHERS           ignored
0xF   CONTINUED        ignored
====  ===============  ===================================================

EVT 2.1 word (64 bits little endian, type in bits 63..60): EVT_NEG (0x0) /
EVT_POS (0x1) carry t bits 5..0 in 59..54, x (a multiple of 32) in 53..43,
y in 42..32 and a 32-bit valid mask in 31..0 (event at x + i for bit i);
EVT_TIME_HIGH (0x8) carries t bits 33..6 in 59..32.

The 34-bit time wraps after 4.8 h; a TIME_HIGH going back by more than half
its range is extended as a wrap.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from arena.events import EVENT_DTYPE
from arena.formats.evt3 import _check_encodable

_TH_HALF = 1 << 27
_WRAP = 1 << 34


@njit(cache=True, nogil=True)
def _decode2(words, state, xs, ys, ps, ts):
    # state: [th, offset, have_t, skipped]
    th = state[0]
    off = state[1]
    have_t = state[2]
    skipped = state[3]
    n = 0
    for i in range(words.size):
        w = np.int64(words[i])
        typ = w >> 28
        if typ <= 1:
            if have_t:
                xs[n] = (w >> 11) & 0x7FF
                ys[n] = w & 0x7FF
                ps[n] = typ
                ts[n] = off + ((th << 6) | ((w >> 22) & 0x3F))
                n += 1
            else:
                skipped += 1
        elif typ == 0x8:
            nth = w & 0xFFFFFFF
            if have_t and nth < th and th - nth > _TH_HALF:
                off += _WRAP
            th = nth
            have_t = 1
    state[0] = th
    state[1] = off
    state[2] = have_t
    state[3] = skipped
    return n


@njit(cache=True, nogil=True)
def _count21(words):
    n = 0
    for i in range(words.size):
        w = words[i]
        if (w >> np.uint64(60)) <= np.uint64(1):
            m = w & np.uint64(0xFFFFFFFF)
            while m:
                m &= m - np.uint64(1)
                n += 1
    return n


@njit(cache=True, nogil=True)
def _decode21(words, state, xs, ys, ps, ts):
    th = state[0]
    off = state[1]
    have_t = state[2]
    skipped = state[3]
    n = 0
    for i in range(words.size):
        w = words[i]
        hi = np.int64(w >> np.uint64(32))
        typ = hi >> 28
        if typ <= 1:
            if have_t:
                x0 = (hi >> 11) & 0x7FF
                y = hi & 0x7FF
                t = off + ((th << 6) | ((hi >> 22) & 0x3F))
                m = np.int64(w & np.uint64(0xFFFFFFFF))
                for b in range(32):
                    if (m >> b) & 1:
                        xs[n] = x0 + b
                        ys[n] = y
                        ps[n] = typ
                        ts[n] = t
                        n += 1
            else:
                skipped += 1
        elif typ == 0x8:
            nth = hi & 0xFFFFFFF
            if have_t and nth < th and th - nth > _TH_HALF:
                off += _WRAP
            th = nth
            have_t = 1
    state[0] = th
    state[1] = off
    state[2] = have_t
    state[3] = skipped
    return n


class _WordDecoder:
    word_bytes = 4

    def __init__(self) -> None:
        self._state = np.zeros(4, dtype=np.int64)
        self._rest = b""

    @property
    def skipped_words(self) -> int:
        """Event words dropped because no TIME_HIGH had been seen yet."""
        return int(self._state[3])

    @property
    def time_us(self) -> int | None:
        """Latest sensor time known from TIME_HIGH words (µs, 64 µs resolution)."""
        return int(self._state[1] + (self._state[0] << 6)) if self._state[2] else None

    @property
    def pending_bytes(self) -> int:
        """Bytes of an incomplete word kept for the next :meth:`feed`."""
        return len(self._rest)

    def _words(self, data, dtype):
        if self._rest:
            data = self._rest + bytes(data)
        mv = memoryview(data)
        usable = len(mv) - (len(mv) % self.word_bytes)
        self._rest = bytes(mv[usable:])
        return np.frombuffer(mv[:usable], dtype=dtype)


class Evt2Decoder(_WordDecoder):
    """Streaming EVT 2.0 decoder: ``feed(bytes) -> events``; chunks may split words."""

    word_bytes = 4

    def feed(self, data: bytes | bytearray | memoryview) -> np.ndarray:
        words = self._words(data, "<u4")
        ev = np.empty(words.size, EVENT_DTYPE)
        n = _decode2(words, self._state, ev["x"], ev["y"], ev["p"], ev["t"])
        return ev[:n].copy() if n < 0.9 * ev.size else ev[:n]


class Evt21Decoder(_WordDecoder):
    """Streaming EVT 2.1 decoder: ``feed(bytes) -> events``; chunks may split words."""

    word_bytes = 8

    def feed(self, data: bytes | bytearray | memoryview) -> np.ndarray:
        words = self._words(data, "<u8")
        ev = np.empty(_count21(words), EVENT_DTYPE)
        n = _decode21(words, self._state, ev["x"], ev["y"], ev["p"], ev["t"])
        return ev if n == ev.size else ev[:n].copy()


def _wrap_prefix(epochs: int) -> bytes:
    """TIME_HIGH words that make a decoder start ``epochs`` 34-bit wraps in (absolute time kept)."""
    if epochs <= 0:
        return b""
    pairs = np.tile(np.array([0x8FFFFFFF, 0x80000000], "<u4"), epochs)
    return np.concatenate([np.array([0x80000000], "<u4"), pairs]).tobytes()


class Evt2Encoder:
    """Streaming EVT 2.0 encoder: ``encode(events) -> bytes`` (t non-decreasing, µs).

    Times beyond 34 bits at the first event are kept by a prefix of TIME_HIGH words
    (one max/zero pair per wrap); later wraps are the decoder's usual wrap extension."""

    def __init__(self) -> None:
        self._last_th = -1

    def encode(self, events: np.ndarray) -> bytes:
        if events.size == 0:
            return b""
        _check_encodable(events, 2048, 2048)
        t = events["t"].astype(np.int64)
        th = (t >> 6) & 0xFFFFFFF
        cd = ((events["p"].astype(np.uint32) & 1) << 28) | ((t.astype(np.uint32) & 0x3F) << 22) \
            | (events["x"].astype(np.uint32) << 11) | events["y"].astype(np.uint32)
        prev = np.empty_like(th)
        prev[0] = self._last_th
        prev[1:] = th[:-1]
        new_th = th != prev
        n_th = int(new_th.sum())
        out = np.empty(events.size + n_th, dtype=np.uint32)
        # position of each event word: its index plus the TIME_HIGH words before and at it
        pos = np.arange(events.size) + np.cumsum(new_th)
        out[pos] = cd
        out[pos[new_th] - 1] = (0x8 << 28) | th[new_th].astype(np.uint32)
        prefix = b"" if self._last_th >= 0 else _wrap_prefix(int(t[0]) >> 34)
        self._last_th = int(th[-1])
        return prefix + out.astype("<u4").tobytes()


def encode_evt2(events: np.ndarray) -> bytes:
    """Encode events as EVT 2.0 words (no header)."""
    return Evt2Encoder().encode(events)


def encode_evt21(events: np.ndarray) -> bytes:
    """Encode events as EVT 2.1 words (one event per word; no header). For tests and tools."""
    if events.size == 0:
        return b""
    _check_encodable(events, 2048, 2048)
    t = events["t"].astype(np.int64)
    th = (t >> 6) & 0xFFFFFFF
    prev = np.concatenate([[-1], th[:-1]])
    new_th = th != prev
    x = events["x"].astype(np.uint64)
    hi = ((events["p"].astype(np.uint64) & 1) << 28) | ((t.astype(np.uint64) & 0x3F) << 22) \
        | ((x & ~np.uint64(31)) << 11) | events["y"].astype(np.uint64)
    words = (hi << 32) | (np.uint64(1) << (x & np.uint64(31)))
    out = np.empty(events.size + int(new_th.sum()), dtype=np.uint64)
    pos = np.arange(events.size) + np.cumsum(new_th)
    out[pos] = words
    out[pos[new_th] - 1] = (np.uint64(0x8) << 60) | (th[new_th].astype(np.uint64) << 32)
    return out.astype("<u8").tobytes()

"""Fixed-duration slicing of an event stream in sensor time.

A :class:`Slicer` cuts the stream into back-to-back windows ``[t_start, t_start + slice_us)``
(sensor µs), aligned to multiples of ``slice_us``, across chunk boundaries. Every window
is emitted, empty ones included, so a consumer knows time advanced. Events older than the
current window (out of order) go into the current window and are counted in ``late``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from arena.events import concat_events, empty_events


@dataclass
class Slice:
    """One window: ``events`` with ``t_start_us <= t < t_end_us`` (sensor µs)."""

    t_start_us: int
    t_end_us: int
    events: np.ndarray


class Slicer:
    """Cut event chunks into fixed windows of ``slice_us`` µs (default 10 ms).

    ``push(events)`` returns the windows completed by these events; ``advance(t_us)`` closes
    the windows that end at or before ``t_us`` (sensor time known without events);
    ``flush()`` returns the last, partial window. ``max_gap_slices`` bounds how many empty
    windows one jump in time may emit (a longer gap restarts the windows at the new time).
    """

    def __init__(self, slice_us: int = 10_000, max_gap_slices: int = 1000) -> None:
        if slice_us <= 0:
            raise ValueError(f"slice_us must be > 0, got {slice_us}")
        self.slice_us = int(slice_us)
        self.max_gap_slices = max_gap_slices
        self._start: int | None = None
        self._parts: list[np.ndarray] = []
        self.late = 0
        self.skipped_gaps = 0

    def _close_until(self, t_us: int, out: list[Slice]) -> None:
        """Close windows ending at or before ``t_us``."""
        assert self._start is not None
        n_close = (t_us - self._start) // self.slice_us
        if n_close <= 0:
            return
        if n_close > self.max_gap_slices:
            out.append(self._take())
            self.skipped_gaps += 1
            self._start = t_us - t_us % self.slice_us
            return
        out.append(self._take())
        for _ in range(int(n_close) - 1):
            out.append(Slice(self._start, self._start + self.slice_us, empty_events(0)))
            self._start += self.slice_us

    def _take(self) -> Slice:
        ev = concat_events(self._parts)
        self._parts = []
        s = Slice(self._start, self._start + self.slice_us, ev)
        self._start += self.slice_us
        return s

    def push(self, events: np.ndarray) -> list[Slice]:
        """Add a chunk (time-ordered :data:`EVENT_DTYPE`); return the completed windows."""
        out: list[Slice] = []
        if events.size == 0:
            return out
        # one contiguous copy per chunk: numpy's searchsorted copies a strided array (the packed
        # event's field) in full on every call, which made slicing O(windows x chunk)
        t = np.ascontiguousarray(events["t"])
        if self._start is None:
            t0 = int(t[0])
            self._start = t0 - t0 % self.slice_us
        i = 0
        n = events.size
        while i < n:
            end = self._start + self.slice_us
            j = i + int(np.searchsorted(t[i:], end, side="left"))
            if j > i:
                late = int(np.count_nonzero(t[i:j] < self._start))
                self.late += late
                self._parts.append(events[i:j])
            if j >= n:
                break
            self._close_until(int(t[j]), out)
            i = j
        return out

    def advance(self, t_us: int | None) -> list[Slice]:
        """Close the windows that end at or before sensor time ``t_us`` (no effect if None)."""
        out: list[Slice] = []
        if t_us is not None and self._start is not None:
            self._close_until(int(t_us), out)
        return out

    def flush(self) -> list[Slice]:
        """Return the current partial window (if any events or time were seen)."""
        if self._start is None:
            return []
        return [self._take()]

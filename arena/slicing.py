"""Fixed-duration slicing of an event stream in sensor time: the windows of the contract.

The edge publishes these windows on ``arena/events/<camera>`` and the offline tracker
(``arena track --input``, :func:`tracker.pipeline.iter_slices`) cuts a recording into the same
ones, so offline results measure the system that runs live.

A :class:`Slicer` cuts the stream into back-to-back windows ``[t_start, t_start + slice_us)``
(sensor µs) whose boundaries are multiples of ``slice_us`` of the sensor clock, across chunk
boundaries. Every window is emitted, empty ones included, so a consumer knows time advanced.

Events are taken in stream order: a window closes when the first event at or after its end
arrives (or when :meth:`Slicer.advance` says sensor time passed it). An event older than the
window then open ("late", out of order) is not dropped: it goes into that open window, after
the events that came before it, and is counted in :attr:`Slicer.late`. So a window's events
are ``< t_end_us``, and all ``>= t_start_us`` unless some were late.

>>> from arena.events import make_events
>>> s = Slicer(10_000)
>>> [(w.t_start_us, w.t_end_us, w.events.size) for w in s.push(make_events([1, 1], [1, 1], [0, 0], [12_345, 31_000]))]
[(10000, 20000, 1), (20000, 30000, 0)]
>>> [(w.t_start_us, w.t_end_us, w.events.size) for w in s.flush()]
[(30000, 40000, 1)]
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from arena.events import concat_events, empty_events

__all__ = ["Slice", "Slicer"]


@dataclass
class Slice:
    """One window: ``events`` of ``[t_start_us, t_end_us)`` (sensor µs), late events included
    (those may be older than ``t_start_us``; see :class:`Slicer`)."""

    t_start_us: int
    t_end_us: int
    events: np.ndarray


class Slicer:
    """Cut event chunks into fixed windows of ``slice_us`` µs (default 10 ms) on multiples of ``slice_us``.

    ``push(events)`` returns the windows completed by these events; ``advance(t_us)`` closes
    the windows that end at or before ``t_us`` (sensor time known without events);
    ``flush()`` returns the last, partial window (the end of a file). ``max_gap_slices`` bounds
    how many empty windows one jump in time may emit (a longer gap restarts the windows at the
    new time, counted in ``skipped_gaps``). ``start_us``: the first window starts at this time
    (floored to a multiple of ``slice_us``) instead of at the first event's; empty windows fill
    the time up to the first event. ``late`` counts the events older than their window's start.
    """

    def __init__(self, slice_us: int = 10_000, max_gap_slices: int = 1000, start_us: int | None = None) -> None:
        if slice_us <= 0:
            raise ValueError(f"slice duration must be > 0 µs, got {slice_us!r}")
        self.slice_us = int(slice_us)
        self.max_gap_slices = max_gap_slices
        self._start: int | None = None if start_us is None else int(start_us) - int(start_us) % self.slice_us
        self._parts: list[np.ndarray] = []
        #: events older than the start of the window they went into (out of order)
        self.late = 0
        #: jumps in time longer than ``max_gap_slices`` windows (the windows restarted)
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
        """Add a chunk (:data:`~arena.events.EVENT_DTYPE`, in stream order, normally sorted by
        time); return the completed windows."""
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
            # the binary search is exact for sorted times; out of order, the window ends at the
            # first event >= end in stream order (checked with one max: cheaper than a sort test)
            j = i + int(np.searchsorted(t[i:], end, side="left"))
            if j > i:
                seg = t[i:j]
                if int(seg.max()) >= end:
                    j = i + int(np.argmax(seg >= end))
                    seg = t[i:j]
            if j > i:
                if int(seg.min()) < self._start:
                    self.late += int(np.count_nonzero(seg < self._start))
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
        """Return the current partial window (if any events or time were seen); it ends at
        the next multiple of ``slice_us``, like every window."""
        if self._start is None:
            return []
        return [self._take()]

"""The pure part of the edge: filter, then slice an event stream (no I/O, no clocks)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from camera_edge.filters import EventFilter
from camera_edge.slicing import Slicer


@dataclass
class Window:
    """A slice ready to publish: events of ``[t_start_us, t_end_us)`` (sensor µs) after the
    filters, and how many events the filters removed since the previous window."""

    t_start_us: int
    t_end_us: int
    events: np.ndarray
    filtered: int


class EdgePipeline:
    """``push(chunk, time_us) -> windows``: run the filters in order, then cut fixed slices.

    ``time_us`` is the source's latest sensor time (µs) so windows close in silent periods.
    """

    def __init__(self, filters: list[EventFilter] | None = None, slice_us: int = 10_000) -> None:
        self.filters = list(filters or [])
        self.slicer = Slicer(slice_us)
        self.n_in = 0
        self.n_out = 0
        self._filtered = 0

    def _windows(self, slices) -> list[Window]:
        out = []
        for s in slices:
            out.append(Window(s.t_start_us, s.t_end_us, s.events, self._filtered))
            self._filtered = 0
        return out

    def push(self, events: np.ndarray, time_us: int | None = None) -> list[Window]:
        """Filter and slice one chunk (time-ordered :data:`EVENT_DTYPE`)."""
        self.n_in += events.size
        kept = events
        for f in self.filters:
            if kept.size == 0:
                break
            kept = f(kept)
        self.n_out += kept.size
        self._filtered += events.size - kept.size
        slices = self.slicer.push(kept)
        slices += self.slicer.advance(time_us)
        return self._windows(slices)

    def flush(self) -> list[Window]:
        """The last, partial window (end of a file)."""
        return self._windows(self.slicer.flush())

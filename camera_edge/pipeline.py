"""The pure part of the edge: slice an event stream, then filter each slice (no I/O, no clocks)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from camera_edge.filters import EventFilter
from camera_edge.slicing import Slicer


@dataclass
class Window:
    """A slice ready to publish: events of ``[t_start_us, t_end_us)`` (sensor µs) after the
    filters, and how many events of this slice the filters removed."""

    t_start_us: int
    t_end_us: int
    events: np.ndarray
    filtered: int


class EdgePipeline:
    """``push(chunk, time_us) -> windows``: cut fixed slices, then run the filters in order on each.

    ``time_us`` is the source's latest sensor time (µs) so windows close in silent periods.
    """

    def __init__(self, filters: list[EventFilter] | None = None, slice_us: int = 10_000) -> None:
        self.filters = list(filters or [])
        self.slicer = Slicer(slice_us)
        self.n_in = 0
        self.n_out = 0

    def _windows(self, slices) -> list[Window]:
        out = []
        for s in slices:
            kept = s.events
            for f in self.filters:
                kept = f(kept)
            self.n_out += kept.size
            out.append(Window(s.t_start_us, s.t_end_us, kept, s.events.size - kept.size))
        return out

    def push(self, events: np.ndarray, time_us: int | None = None) -> list[Window]:
        """Slice and filter one chunk (time-ordered :data:`EVENT_DTYPE`); returns closed windows."""
        self.n_in += events.size
        slices = self.slicer.push(events)
        slices += self.slicer.advance(time_us)
        return self._windows(slices)

    def flush(self) -> list[Window]:
        """The last, partial window (end of a file)."""
        return self._windows(self.slicer.flush())

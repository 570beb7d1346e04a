"""The pure part of the edge: slice an event stream, then filter each slice (no I/O, no clocks)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from camera_edge.filters import EventFilter
from arena.slicing import Slicer


@dataclass
class Window:
    """A slice ready to publish: events of ``[t_start_us, t_end_us)`` (sensor µs) after the
    filters, and how many events of this slice the filters removed."""

    t_start_us: int
    t_end_us: int
    events: np.ndarray
    filtered: int
    #: host capture time - sensor time, ns (None: unknown, e.g. a file replayed faster than real time)
    sensor_to_host_ns: int | None = None


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


def warm_up(make_filters, width: int, height: int, codec: str, slice_us: int = 10_000) -> None:
    """Run throw-away filters (``make_filters()``: fresh instances, so no learnt state is
    touched), the EVT 3.0 decoder and the window codec over a few synthetic slices, so their
    numba kernels are compiled (or loaded from numba's cache) before the first real events: on
    a fresh install that takes seconds, during which a live edge would drop windows.

    Chunks and windows of zero and one event are run too: numba types an array of at most one
    element as contiguous, a separate specialisation that a live edge would otherwise compile
    the first time a chunk holds only time words or a window is empty."""
    from arena.codec import encode
    from arena.events import make_events
    from arena.formats.evt3 import Evt3Decoder, decode_evt3, encode_evt3

    rng = np.random.default_rng(0)
    n = 2000
    t = np.sort(rng.integers(0, 3 * slice_us, n))
    ev = make_events(rng.integers(0, width, n), rng.integers(0, height, n), rng.integers(0, 2, n), t)
    time_words = np.array([0x8000, 0x6000 | 5], "<u2").tobytes()   # a chunk of time words only
    for chunk in (decode_evt3(encode_evt3(ev)), decode_evt3(encode_evt3(ev[:1])), Evt3Decoder().feed(time_words)):
        pipe = EdgePipeline(make_filters(), slice_us=slice_us)
        for w in pipe.push(chunk, 3 * slice_us) + pipe.flush():
            encode(w.events, codec, t_ref_us=w.t_start_us)

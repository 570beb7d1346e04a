"""Per-pixel statistics of a sliding event window, updated slice by slice.

The window ``[t_end - t_a, t_end)`` changes by one slice at a time: :class:`PixelWindow`
adds the new slice's events and removes the expired slice's, so each update costs
O(events of two slices), not O(events of the window). For every active pixel (sensor
frame, px) it keeps the event count, the ON-event count and the sums of event times
(s, relative to an internal origin) and of their squares: enough for the detector's
centroids and straight-motion fits, which are sums over pixels.
"""

from __future__ import annotations

from collections import deque

import numpy as np
from numba import njit

__all__ = ["PixelWindow"]

#: Re-base the time origin after this long, s (keeps t^2 sums precise).
_REBASE_S = 20.0


#: one slot's statistics, side by side: an event touches one record, not four arrays (issue 22:
#: the events of a slice hit pixels at random, so each array was one more cache miss per event)
STATS_DTYPE = np.dtype([("count", np.int64), ("on", np.int64), ("st", np.float64), ("st2", np.float64)])


@njit(cache=True, nogil=True)
def _apply(x, y, p, t, sign, t_ref, width, slot, active, stats, n_active, trans, n_trans):
    """Add (sign=+1) or remove (sign=-1) events. Statistics live in slots 0..n_active-1
    (contiguous records of :data:`STATS_DTYPE`); ``slot[pixel]`` is the pixel's slot or -1,
    ``active[slot]`` its pixel.
    When ``trans`` is not empty, each pixel turning active is appended to it as
    ``pixel + 1`` and each turning inactive as ``-(pixel + 1)`` (from ``n_trans`` on).
    Returns ``(n_active, n_trans)``."""
    record = trans.shape[0] > 0
    for i in range(x.shape[0]):
        k = np.int64(y[i]) * width + np.int64(x[i])
        ti = (t[i] - t_ref) * 1e-6
        j = slot[k]
        if sign > 0:
            if j < 0:
                j = n_active
                slot[k] = j
                active[j] = k
                r = stats[j]
                r.count = 0
                r.on = 0
                r.st = 0.0
                r.st2 = 0.0
                n_active += 1
                if record:
                    trans[n_trans] = k + 1
                    n_trans += 1
            r = stats[j]
            r.count += 1
            if p[i]:
                r.on += 1
            r.st += ti
            r.st2 += ti * ti
        else:
            r = stats[j]
            r.count -= 1
            if p[i]:
                r.on -= 1
            r.st -= ti
            r.st2 -= ti * ti
            if r.count == 0:
                last = n_active - 1
                kl = active[last]
                active[j] = kl
                slot[kl] = j
                rl = stats[last]
                r.count = rl.count
                r.on = rl.on
                r.st = rl.st
                r.st2 = rl.st2
                slot[k] = -1
                n_active -= 1
                if record:
                    trans[n_trans] = -(k + 1)
                    n_trans += 1
    return n_active, n_trans


@njit(cache=True, nogil=True)
def _coords(active, n_active, width):
    u = np.empty(n_active, dtype=np.int64)
    v = np.empty(n_active, dtype=np.int64)
    for j in range(n_active):
        y = active[j] // width     # one division (pixels are >= 0)
        v[j] = y
        u[j] = active[j] - y * width
    return u, v


@njit(cache=True, nogil=True)
def _gather(stats, slots):
    """(count, on, sum_t, sum_t2) of the slots ``slots``, in one pass over their records."""
    n = slots.shape[0]
    count = np.empty(n, dtype=np.int64)
    on = np.empty(n, dtype=np.int64)
    st = np.empty(n, dtype=np.float64)
    st2 = np.empty(n, dtype=np.float64)
    for i in range(n):
        r = stats[slots[i]]
        count[i] = r.count
        on[i] = r.on
        st[i] = r.st
        st2[i] = r.st2
    return count, on, st, st2


class PixelWindow:
    """Sliding window of event slices with per-pixel statistics.

    Args:
        width, height: sensor size, px.
        accumulation_us: t_a, µs.
    """

    _no_trans = np.zeros(0, dtype=np.int64)

    def __init__(self, width: int, height: int, accumulation_us: int) -> None:
        if width <= 0 or height <= 0:
            raise ValueError(f"sensor size must be positive, got {width}x{height}")
        self.width, self.height = int(width), int(height)
        self.accumulation_us = int(accumulation_us)
        # pixel -> slot map (int32: the only sensor-sized array, touched at random); the
        # statistics live in slots, sized to the active pixels and grown on demand, so
        # they stay in cache
        self._slot = np.full(self.width * self.height, -1, dtype=np.int32)
        self._alloc(1 << 14)
        self._n_active = 0
        self._slices: deque[tuple[int, np.ndarray]] = deque()
        self.t_ref_us: int | None = None
        self.n_events = 0
        # pixels that turned active / inactive during one push, for an attached index
        self._index = None
        self._trans = np.zeros(0, dtype=np.int64)
        self._n_trans = 0
        self._recording = False

    def _alloc(self, cap: int) -> None:
        old = getattr(self, "_active", None)
        active, stats = np.zeros(cap, dtype=np.int64), np.zeros(cap, dtype=STATS_DTYPE)
        if old is not None:
            m = self._n_active
            active[:m] = self._active[:m]
            stats[:m] = self._stats[:m]
        self._active, self._stats = active, stats

    def _check(self, ev: np.ndarray) -> None:
        if ev.size and (int(ev["x"].max()) >= self.width or int(ev["y"].max()) >= self.height):
            raise ValueError(f"event at ({int(ev['x'].max())}, {int(ev['y'].max())}) px lies outside "
                             f"the {self.width}x{self.height} sensor")

    def _run(self, ev: np.ndarray, sign: int) -> None:
        if ev.size == 0:
            return
        need = self._n_active + (ev.size if sign > 0 else 0)
        if need > self._active.size:
            self._alloc(max(need, 2 * self._active.size))
        trans = self._no_trans
        if self._recording:
            if self._n_trans + ev.size > self._trans.size:
                grown = np.zeros(max(self._n_trans + ev.size, 2 * self._trans.size, 4096), dtype=np.int64)
                grown[:self._n_trans] = self._trans[:self._n_trans]
                self._trans = grown
            trans = self._trans
        self._n_active, n_trans = _apply(ev["x"], ev["y"], ev["p"], ev["t"], sign, self.t_ref_us, self.width,
                                         self._slot, self._active, self._stats, self._n_active, trans,
                                         self._n_trans)
        if self._recording:
            self._n_trans = n_trans
        self.n_events += sign * ev.size

    @property
    def n_active(self) -> int:
        """Number of active pixels (at least one event in the window)."""
        return self._n_active

    @property
    def index(self):
        """The attached index (see :meth:`attach`), or None."""
        return self._index

    def attach(self, index) -> None:
        """Keep ``index`` up to date with the set of active pixels (None detaches).

        ``index.rebuild(pixels)`` is called now with the active pixels (``y * width + x``),
        then ``index.update(changes)`` after every :meth:`push` with the pixels that turned
        active (``pixel + 1``) or inactive (``-(pixel + 1)``) in it, in order.
        """
        self._index = index
        if index is not None:
            index.rebuild(self._active[:self._n_active].copy())

    def push(self, events: np.ndarray, t_end_us: int) -> None:
        """Add one slice (events with t < t_end_us) and expire what is older than t_end - t_a."""
        self._check(events)
        if self.t_ref_us is None:
            self.t_ref_us = int(events["t"][0]) if events.size else int(t_end_us)
        elif (t_end_us - self.t_ref_us) * 1e-6 > _REBASE_S:
            self._rebase(int(t_end_us) - self.accumulation_us)
        lo = int(t_end_us) - self.accumulation_us
        keep = events[events["t"] >= lo] if events.size and events["t"][0] < lo else events
        self._recording = self._index is not None
        self._n_trans = 0
        try:
            # expire whole slices, then the old part of the oldest one
            while self._slices and self._slices[0][0] <= lo:
                _, old = self._slices.popleft()
                self._run(old, -1)
            if self._slices:
                t0, first = self._slices[0]
                if first.size and first["t"][0] < lo:
                    cut = int(np.searchsorted(first["t"], lo, side="left"))
                    self._run(first[:cut], -1)
                    self._slices[0] = (t0, first[cut:])
            self._run(keep, +1)
        except BaseException:
            self._recording = False
            if self._index is not None:   # never leave an index out of step with the pixels
                self._index.rebuild(self._active[:self._n_active].copy())
            raise
        self._recording = False
        self._slices.append((int(t_end_us), keep))
        if self._index is not None:
            self._index.update(self._trans[:self._n_trans])

    def _rebase(self, t_new: int) -> None:
        # the same events leave and come back: the set of active pixels does not change
        # (their slots do), so nothing is recorded for an attached index
        slices = list(self._slices)
        for _, ev in slices:
            self._run(ev, -1)
        self.t_ref_us = t_new
        for _, ev in slices:
            self._run(ev, +1)

    @property
    def slot_map(self) -> np.ndarray:
        """Pixel (``y * width + x``) -> its slot in :meth:`pixels`' arrays, -1 when inactive
        (read only: a view of the window's own map)."""
        view = self._slot.view()
        view.flags.writeable = False
        return view

    def slot_stats(self, slots: np.ndarray):
        """(count, sum_t, sum_t2) of the active pixels in slots ``slots`` (times in s from ``t_ref_us``)."""
        st = self._stats
        return st["count"][slots], st["st"][slots], st["st2"][slots]

    def slot_on(self, slots: np.ndarray) -> np.ndarray:
        """ON-event counts of the active pixels in slots ``slots``."""
        return self._stats["on"][slots]

    def slot_records(self, slots: np.ndarray):
        """(count, on_count, sum_t, sum_t2) of the active pixels in slots ``slots`` (int64 slots, each
        < :attr:`n_active`; times in s from ``t_ref_us``), gathered in one pass."""
        slots = np.asarray(slots, dtype=np.int64)
        if slots.size and (int(slots.min()) < 0 or int(slots.max()) >= self._n_active):
            raise IndexError(f"slots must lie in [0, {self._n_active}), got {int(slots.min())}..{int(slots.max())}")
        return _gather(self._stats, slots)

    def coords(self, pixels: np.ndarray):
        """(u, v) of pixels given as ``y * width + x`` (non-negative int64)."""
        pixels = np.asarray(pixels, dtype=np.int64)
        return _coords(pixels, pixels.size, self.width)

    def events(self) -> np.ndarray:
        """The window's events, concatenated (sorted by t when the slices were)."""
        from arena.events import concat_events
        return concat_events([ev for _, ev in self._slices])

    def pixels(self):
        """Active pixels: (u, v, count, on_count, sum_t, sum_t2) arrays; times in s from ``t_ref_us``."""
        m = self._n_active
        u, v = _coords(self._active, m, self.width)
        st = self._stats[:m]
        return u, v, st["count"].copy(), st["on"].copy(), st["st"].copy(), st["st2"].copy()

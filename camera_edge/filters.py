"""Edge event filters: pure, stateful where they must be, each counting events in and out.

* :class:`HotPixelFilter` removes pixels that fire far more than their neighbours (learned from
  the first ``learn_us`` of the stream, or loaded from a file of hot pixel coordinates).
* :class:`BackgroundActivityFilter` keeps an event only if a neighbouring pixel fired within
  ``dt_us`` before it (the classic nearest-neighbour timestamp filter, Delbruck 2008).
* :class:`RoiFilter` keeps events inside a polygon of the sensor (e.g. the arena outline from
  the calibration), rasterised once into a mask.

All take and return :data:`arena.events.EVENT_DTYPE` arrays (sensor px, µs) in time order.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from numba import njit

from arena.events import select_events


class EventFilter:
    """Base: ``__call__(events) -> kept events``; ``n_in``/``n_out`` count events."""

    name = "filter"

    def __init__(self) -> None:
        self.n_in = 0
        self.n_out = 0

    def __call__(self, events: np.ndarray) -> np.ndarray:
        self.n_in += events.size
        out = self._apply(events)
        self.n_out += out.size
        return out

    def _apply(self, events: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError


@njit(cache=True, nogil=True)
def _lookup(xs, ys, mask, keep, want):
    """keep[i] = (mask[y, x] == want) for each event."""
    for i in range(xs.size):
        keep[i] = mask[ys[i], xs[i]] == want


def _select(events: np.ndarray, mask: np.ndarray, want: bool) -> np.ndarray:
    keep = np.empty(events.size, np.bool_)
    _lookup(events["x"], events["y"], mask, keep, want)
    return select_events(events, keep)


@njit(cache=True, nogil=True)
def _count_pixels(xs, ys, width, counts):
    for i in range(xs.size):
        counts[np.int64(ys[i]) * width + xs[i]] += 1


class HotPixelFilter(EventFilter):
    """Remove hot pixels.

    Learning: during the first ``learn_us`` µs of sensor time events pass unchanged while
    per-pixel counts accumulate; then a pixel is hot if its rate exceeds ``min_rate_hz`` and its
    count exceeds ``factor`` times (the mean count of its 8 neighbours + 1). A moving edge makes
    neighbouring pixels fire together (ratio ~1-3 on the simulator's scenes), a hot pixel fires
    alone (ratio 29-99 at 50 Hz, even in the dark with 1 Hz background noise); so the robots'
    busiest pixels are not taken for hot ones, however much the scene moves. (Comparing with the
    mean rate of all active pixels, as before, missed every 50 Hz hot pixel of a scene with
    robots: their paths raise that mean.) Or give ``hot_pixels`` (k, 2) (x, y) or a ``path``
    saved by :meth:`save` (``.npy`` or text ``x,y`` lines).
    """

    name = "hot_pixel"

    def __init__(self, width: int, height: int, learn_us: int = 2_000_000, factor: float = 10.0,
                 min_rate_hz: float = 20.0, hot_pixels: np.ndarray | None = None,
                 path: str | Path | None = None) -> None:
        super().__init__()
        self.width, self.height = width, height
        self.learn_us, self.factor, self.min_rate_hz = learn_us, factor, min_rate_hz
        self.mask_ = np.zeros((height, width), bool)
        self._counts: np.ndarray | None = np.zeros(height * width, np.int64)
        self._t0: int | None = None
        if path is not None:
            hot_pixels = self.load(path)
        if hot_pixels is not None:
            self._set(np.asarray(hot_pixels, np.int64).reshape(-1, 2))

    @staticmethod
    def load(path: str | Path) -> np.ndarray:
        """Hot pixel coordinates (k, 2) (x, y) from ``.npy`` or a text file of ``x,y`` lines."""
        path = Path(path)
        try:
            if path.suffix == ".npy":
                return np.load(path).astype(np.int64).reshape(-1, 2)
            return np.loadtxt(path, delimiter=",", dtype=np.int64, ndmin=2).reshape(-1, 2)
        except (OSError, ValueError) as exc:
            raise ValueError(f"{path}: not a hot pixel list (x,y per line, or .npy (k, 2)): {exc}") from None

    def save(self, path: str | Path) -> None:
        """Save the hot pixels as ``x,y`` text lines (or ``.npy``)."""
        pts = self.hot_pixels_
        if Path(path).suffix == ".npy":
            np.save(path, pts)
        else:
            np.savetxt(path, pts, fmt="%d", delimiter=",")

    @property
    def hot_pixels_(self) -> np.ndarray:
        """Hot pixels (k, 2) as (x, y) px."""
        ys, xs = np.nonzero(self.mask_)
        return np.column_stack([xs, ys]).astype(np.int64)

    @property
    def learning(self) -> bool:
        """Whether the filter is still learning (passes everything)."""
        return self._counts is not None

    def _set(self, pts: np.ndarray) -> None:
        ok = (pts[:, 0] >= 0) & (pts[:, 0] < self.width) & (pts[:, 1] >= 0) & (pts[:, 1] < self.height)
        self.mask_[:] = False
        self.mask_[pts[ok, 1], pts[ok, 0]] = True
        self._counts = None

    def _apply(self, events: np.ndarray) -> np.ndarray:
        if self._counts is not None:
            if events.size == 0:
                return events
            if self._t0 is None:
                self._t0 = int(events["t"][0])
            end = self._t0 + self.learn_us
            k = int(np.searchsorted(events["t"], end))
            _count_pixels(events["x"][:k], events["y"][:k], self.width, self._counts)
            if k == events.size:
                return events
            counts = self._counts.reshape(self.height, self.width).astype(np.float32)
            around = cv2.boxFilter(counts, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT) - counts
            hot = np.flatnonzero((counts.ravel() / (self.learn_us / 1e6) > self.min_rate_hz)
                                 & (counts.ravel() > self.factor * (around.ravel() / 8 + 1)))
            self._set(np.column_stack([hot % self.width, hot // self.width]))
            return np.concatenate([events[:k], _select(events[k:], self.mask_, False)])
        return _select(events, self.mask_, False)


@njit(cache=True, nogil=True)
def _ba_filter(xs, ys, ts, last, dt_us, keep):
    """``last`` holds each pixel's latest time, padded by one pixel on every side."""
    n = 0
    for i in range(xs.size):
        x = np.int64(xs[i]) + 1
        y = np.int64(ys[i]) + 1
        t = ts[i]
        lim = t - dt_us
        k = (last[y - 1, x - 1] >= lim) | (last[y - 1, x] >= lim) | (last[y - 1, x + 1] >= lim) \
            | (last[y, x - 1] >= lim) | (last[y, x + 1] >= lim) \
            | (last[y + 1, x - 1] >= lim) | (last[y + 1, x] >= lim) | (last[y + 1, x + 1] >= lim)
        keep[i] = k
        n += k
        last[y, x] = t
    return n


class BackgroundActivityFilter(EventFilter):
    """Nearest-neighbour timestamp filter: keep an event if one of its 8 neighbours fired
    within ``dt_us`` µs before it. Removes isolated background activity; moving edges,
    whose neighbours fire together, pass. Memory: one int64 per pixel."""

    name = "background"

    def __init__(self, width: int, height: int, dt_us: int = 5000) -> None:
        super().__init__()
        if dt_us <= 0:
            raise ValueError(f"dt_us must be > 0, got {dt_us}")
        self.dt_us = int(dt_us)
        self._last = np.full((height + 2, width + 2), -(1 << 62), np.int64)  # padded: no edge tests

    def _apply(self, events: np.ndarray) -> np.ndarray:
        keep = np.empty(events.size, np.bool_)
        _ba_filter(events["x"], events["y"], events["t"], self._last, self.dt_us, keep)
        return select_events(events, keep)


class RoiFilter(EventFilter):
    """Keep events inside ``polygon`` ((k, 2) sensor px, u right, v down), optionally grown by
    ``margin_px``. The polygon is rasterised once with OpenCV."""

    name = "roi"

    def __init__(self, width: int, height: int, polygon, margin_px: int = 0) -> None:
        super().__init__()
        pts = np.asarray(polygon, dtype=np.float64).reshape(-1, 2)
        if pts.shape[0] < 3:
            raise ValueError(f"a region of interest needs at least 3 corners, got {pts.shape[0]}")
        mask = np.zeros((height, width), np.uint8)
        cv2.fillPoly(mask, [np.round(pts).astype(np.int32)], 1)
        if margin_px > 0:
            k = 2 * int(margin_px) + 1
            mask = cv2.dilate(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
        self.mask_ = mask.astype(bool)

    @classmethod
    def from_calibration(cls, calibration: dict, margin_px: int = 0) -> "RoiFilter":
        """ROI = convex hull of the calibration points' pixels (``{"image_size": [w, h],
        "points": [{"pixel": [u, v], "arena_m": [x, y]}, ...]}``)."""
        w, h = calibration["image_size"]
        px = np.array([p["pixel"] for p in calibration["points"]], np.float32)
        if px.shape[0] < 3:
            raise ValueError("the calibration needs at least 3 points to make a region of interest")
        hull = cv2.convexHull(px).reshape(-1, 2)
        return cls(int(w), int(h), hull, margin_px)

    def _apply(self, events: np.ndarray) -> np.ndarray:
        return _select(events, self.mask_, True)

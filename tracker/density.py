"""Incremental neighbour counts of a sliding window's active pixels, for exact DBSCAN.

Exact grid DBSCAN (:func:`tracker.dbscan.dbscan_grid`) over the active pixels of the
window needs, for each active pixel, the number of active pixels in its eps-disk (itself
included): the pixel is a core pixel when that count reaches ``min_samples``. Each 10 ms
slice turns only ~10 % of a 100 ms window's pixels on or off, so :class:`NeighbourIndex`
keeps that count for every pixel of the sensor (sensor frame, px) and adds or removes one
disk per pixel that changes: O(changed pixels x disk rows) per slice, each disk row one
fixed-width vector add, instead of a re-count of the whole window.

To find the core pixels without looking at every pixel, the sensor is cut into tiles of
8 x 8 px, each with an upper bound of the counts inside it: the exact maximum when the tile
was last scanned, plus one for every pixel turned on since within eps of the tile (turning
pixels off only lowers counts). A query for ``min_samples`` scans only the tiles whose
bound reaches it (and resets their bounds to the exact maximum): the robots' tiles, and a
background tile once every few slices, when enough noise has landed near it. Then it scans
the grid cells within DBSCAN's reach of the cores for the active pixels that may be border
pixels, and returns those pixels in the window's slot order, the order
:meth:`tracker.accumulate.PixelWindow.pixels` lists them in. Clustering them with their
core flags (:func:`tracker.dbscan.dbscan_from_cores`) gives exactly the labels the full
grid DBSCAN gives those pixels; every other active pixel is noise.

The per-cell pixel counts the detector's noise estimate needs (cells of ``noise_cell`` px)
are kept the same way, O(1) per changed pixel.
"""

from __future__ import annotations

import numpy as np
from numba import njit, uint64

from tracker.dbscan import disk_half_widths, grid_geometry

__all__ = ["NeighbourIndex", "TILE"]

#: side of the tiles whose count bounds are kept, px
TILE = 8


@njit(cache=True, nogil=True)
def _update(changes, nb, mask, rad, width, height, stride, bound, tgw, ncount, ncell, ngw):
    """Apply pixel changes (``pixel + 1`` on, ``-(pixel + 1)`` off; pixels as ``y * width + x``)
    to the neighbour counts ``nb``, the tile bounds and the noise-cell counts.

    ``nb`` is a padded image (row ``stride``, ``rad`` rows and columns of margin, more on the
    right) so that each row of a disk is one run of ``mask.shape[1]`` lanes (a multiple of 16)
    starting ``rad`` px left of the pixel: one vector add per row, with no edge cases.
    (Indices are unsigned in the row loops: a signed index is checked for wrap-around at
    every lane, which kept LLVM from vectorising them; issue 22: the row adds ran ~2x faster in a
    micro-benchmark, the same integer sums.)"""
    nrow = mask.shape[0]
    span = uint64(mask.shape[1])
    flat = mask.reshape(mask.size)
    for i in range(changes.shape[0]):
        c = changes[i]
        k = c - 1 if c > 0 else -c - 1
        y = k // width
        x = k - y * width
        base = y * stride + x   # padded index of (x - rad, y - rad)
        if c > 0:
            ncount[(y // ncell) * ngw + x // ncell] += 1
            for r in range(nrow):
                o = uint64(base + r * stride)
                mo = uint64(r) * span
                for q in range(span):
                    nb[o + q] += flat[mo + q]
            # every count within eps of (x, y) went up by at most one
            for ty in range(max(y - rad, 0) // 8, min(y + rad, height - 1) // 8 + 1):
                for tx in range(max(x - rad, 0) // 8, min(x + rad, width - 1) // 8 + 1):
                    bound[ty * tgw + tx] += 1
        else:
            ncount[(y // ncell) * ngw + x // ncell] -= 1
            for r in range(nrow):
                o = uint64(base + r * stride)
                mo = uint64(r) * span
                for q in range(span):
                    nb[o + q] -= flat[mo + q]


@njit(cache=True, nogil=True)
def _select(nb, bound, tgw, tgh, slot, n_slots, order, min_samples, width, height, stride, rad, cell, reach,
            cmark, cgw, cgh):
    """The active pixels in the grid cells within ``reach`` of a cell holding a core pixel
    (active, ``nb >= min_samples``), sorted by their slot in the window (``order``: at least
    n_slots entries of -1, left so), as ``(pixels, slots, core flags)``; pixels as
    ``y * width + x``. Tiles whose bound reaches min_samples are scanned and their bound reset."""
    # 1. cores, from the tiles that may hold one; the cells holding cores (cmark bit 1)
    cells = np.empty(cgw * cgh, dtype=np.int64)
    xcell = np.empty(width, dtype=np.int64)   # x // cell, looked up (a division per core costs more)
    for x in range(width):
        xcell[x] = x // cell
    nc = 0
    for t in range(tgw * tgh):
        if bound[t] < min_samples:
            continue
        x0 = (t % tgw) * 8
        y0 = (t // tgw) * 8
        mx = 0
        for y in range(y0, min(y0 + 8, height)):
            row = uint64((y + rad) * stride + rad)
            srow = uint64(y * width)
            ycell = (y // cell) * cgw
            for x in range(uint64(x0), uint64(min(x0 + 8, width))):
                val = nb[row + x]
                if val > mx:
                    mx = val
                if val >= min_samples and slot[srow + x] >= 0:
                    cc = ycell + xcell[x]
                    if cmark[cc] == 0:
                        cmark[cc] = 1
                        cells[nc] = cc
                        nc += 1
        bound[t] = mx
    # 2. the cells to scan (bit 2): within reach of a core cell
    side = 2 * reach + 1
    scan = np.empty(nc * side * side, dtype=np.int64)
    ns = 0
    for i in range(nc):
        gx = cells[i] % cgw
        gy = cells[i] // cgw
        for yy in range(max(gy - reach, 0), min(gy + reach + 1, cgh)):
            for xx in range(max(gx - reach, 0), min(gx + reach + 1, cgw)):
                c2 = yy * cgw + xx
                if cmark[c2] & 2 == 0:
                    cmark[c2] |= 2
                    scan[ns] = c2
                    ns += 1
    # 3. their active pixels, put in slot order by a scatter (slots are < n_slots), each as
    # 2 * pixel + its core flag (read here, where the rows of nb come in order, not per slot below)
    n = 0
    for i in range(ns):
        c2 = scan[i]
        gy = c2 // cgw
        x0 = (c2 - gy * cgw) * cell
        y0 = gy * cell
        for y in range(y0, min(y0 + cell, height)):
            srow = uint64(y * width)
            nrow = uint64((y + rad) * stride + rad)
            for x in range(uint64(x0), uint64(min(x0 + cell, width))):
                j = slot[srow + x]
                if j >= 0:
                    order[j] = np.int64(srow + x) * 2 + (1 if nb[nrow + x] >= min_samples else 0)
                    n += 1
        cmark[c2] = 0
    pix = np.empty(n, dtype=np.int64)
    sl = np.empty(n, dtype=np.int64)
    core = np.empty(n, dtype=np.bool_)
    i = 0
    for j in range(n_slots):
        if i == n:
            break
        k = order[j]
        if k >= 0:
            order[j] = -1
            pix[i] = k >> 1
            sl[i] = j
            core[i] = (k & 1) == 1
            i += 1
    return pix, sl, core


@njit(cache=True, nogil=True)
def _rebuild(pixels, nb, mask, rad, width, height, stride, bound, tgw, ncount, ncell, ngw):
    nb[:] = 0
    bound[:] = 0
    ncount[:] = 0
    changes = np.empty(pixels.shape[0], dtype=np.int64)
    for i in range(pixels.shape[0]):
        changes[i] = pixels[i] + 1
    _update(changes, nb, mask, rad, width, height, stride, bound, tgw, ncount, ncell, ngw)


class NeighbourIndex:
    """Neighbour counts and noise-cell counts of a window's active pixels.

    Attach it to a :class:`tracker.accumulate.PixelWindow` (``window.attach(index)``), which
    then feeds it the pixels that turn on or off at every push.

    Args:
        width, height: sensor size, px.
        eps: DBSCAN radius, px (distance ``<= eps``, as in :func:`tracker.dbscan.dbscan_grid`).
        noise_cell: side of the cells whose active pixels are counted (:attr:`noise_counts`), px.
    """

    def __init__(self, width: int, height: int, eps: float, noise_cell: int) -> None:
        if width <= 0 or height <= 0:
            raise ValueError(f"sensor size must be positive, got {width}x{height}")
        if int(noise_cell) < 1:
            raise ValueError(f"noise_cell must be >= 1 px, got {noise_cell!r}")
        self.width, self.height = int(width), int(height)
        self.eps = float(eps)
        self.half = disk_half_widths(self.eps)
        self.rad = (self.half.size - 1) // 2
        if int((2 * self.half + 1).sum()) > 32767:
            raise ValueError(f"eps {eps!r} px is too large for 16-bit neighbour counts (at most ~100 px)")
        self.cell, self.reach = grid_geometry(self.eps)
        # each row of the disk as a run of `span` lanes (a multiple of 16) from x - rad
        span = -(-(2 * self.rad + 1) // 16) * 16
        # 8-bit counts when the disk holds at most 127 pixels (eps up to ~6.3 px, the default
        # detector's 5.9 px): half the memory, so more of it stays in cache between slices
        dtype = np.int8 if int((2 * self.half + 1).sum()) <= 127 else np.int16
        self._mask = np.zeros((2 * self.rad + 1, span), dtype=dtype)
        for r, w in enumerate(self.half):
            self._mask[r, self.rad - w:self.rad + w + 1] = 1
        # the padded count image: rad rows above and below, rad columns left, span - rad right
        self._stride = self.width + span
        self._nb = np.zeros(self._stride * (self.height + 2 * self.rad + 1), dtype=dtype)
        self._tgw = (self.width + TILE - 1) // TILE
        self._tgh = (self.height + TILE - 1) // TILE
        self._bound = np.zeros(self._tgw * self._tgh, dtype=np.int64)
        self.noise_cell = int(noise_cell)
        self._ngw = self.width // self.noise_cell + 1
        self._ngh = self.height // self.noise_cell + 1
        #: active pixels per noise cell, row-major: ``(v // c) * (width // c + 1) + u // c``, c = noise_cell
        self.noise_counts = np.zeros(self._ngw * self._ngh, dtype=np.int64)
        self._cgw = (self.width + self.cell - 1) // self.cell
        self._cgh = (self.height + self.cell - 1) // self.cell
        self._cmark = np.zeros(self._cgw * self._cgh, dtype=np.uint8)
        self._order = np.full(0, -1, dtype=np.int64)

    def matches(self, width: int, height: int, eps: float, noise_cell: int) -> bool:
        """True when this index was built for these parameters."""
        return (self.width, self.height, self.eps, self.noise_cell) == (
            int(width), int(height), float(eps), int(noise_cell))

    def _args(self):
        return (self._nb, self._mask, self.rad, self.width, self.height, self._stride, self._bound, self._tgw,
                self.noise_counts, self.noise_cell, self._ngw)

    def rebuild(self, pixels: np.ndarray) -> None:
        """Start over from the active pixels ``pixels`` (``y * width + x``)."""
        _rebuild(np.asarray(pixels, dtype=np.int64), *self._args())

    def update(self, changes: np.ndarray) -> None:
        """Apply pixels turned on (``pixel + 1``) and off (``-(pixel + 1)``)."""
        if changes.size:
            _update(changes, *self._args())

    def neighbours(self, pixels: np.ndarray) -> np.ndarray:
        """Active pixels within eps of each pixel in ``pixels`` (``y * width + x``), itself
        included when active."""
        k = np.asarray(pixels, dtype=np.int64)
        return self._nb[(k // self.width + self.rad) * self._stride + k % self.width + self.rad].astype(np.int64)

    def select(self, slot: np.ndarray, n_slots: int, min_samples: int):
        """The pixels DBSCAN with ``min_samples`` may label, for a window whose pixel -> slot
        map is ``slot`` (slots < ``n_slots``): ``(pixels, slots, core)`` sorted by slot, with
        the pixels as ``y * width + x`` and their core flags."""
        if int(min_samples) < 1:
            raise ValueError(f"min_samples must be >= 1, got {min_samples!r}")
        if self._order.size < n_slots:
            self._order = np.full(max(int(n_slots), 2 * self._order.size), -1, dtype=np.int64)
        return _select(self._nb, self._bound, self._tgw, self._tgh, slot, int(n_slots), self._order,
                       int(min_samples), self.width, self.height, self._stride, self.rad, self.cell, self.reach,
                       self._cmark, self._cgw, self._cgh)

    def tiles_due(self, min_samples: int) -> int:
        """How many tiles a query for ``min_samples`` would scan now."""
        return int(np.count_nonzero(self._bound >= int(min_samples)))

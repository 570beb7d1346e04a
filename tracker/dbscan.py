"""DBSCAN over the active pixels of an event window.

Two backends compute the same clustering of a set of *unique* integer pixel
coordinates ``(u, v)`` (sensor frame, px):

- :func:`dbscan_sklearn` — the reference: :class:`sklearn.cluster.DBSCAN`.
- :func:`dbscan_grid` — the default: an exact grid algorithm compiled with numba.

Semantics (identical to scikit-learn): a pixel is a *core* pixel when at least
``min_samples`` pixels (itself included) lie at a Euclidean distance ``<= eps``.
Two core pixels within ``eps`` of each other belong to the same cluster; a
non-core pixel within ``eps`` of a core pixel is a *border* pixel of one of
those cores' clusters; every other pixel is noise (label ``-1``).

:func:`dbscan_grid` numbers clusters in the order scikit-learn does (by the
smallest index of a core pixel in the cluster), so the labels of core and noise
pixels are identical to scikit-learn's. A border pixel within ``eps`` of cores
of two different clusters goes to the cluster of its nearest core, whereas
scikit-learn gives it to whichever cluster its visiting order reaches first:
that is the only possible difference.

The grid backend bins pixels into square cells of side ``c`` (any two pixels in
one cell are within ``eps``), counts neighbours by visiting nearby cells, unites
all cores of a cell at once, and tests pairs of cells only while they are not
yet united. Its cost grows with the number of active pixels, not with the
sensor size.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["dbscan_sklearn", "dbscan_grid", "core_mask", "dbscan_from_cores", "grid_geometry", "disk_half_widths"]


def _check(u: np.ndarray, v: np.ndarray, eps: float, min_samples: int) -> tuple[np.ndarray, np.ndarray]:
    u = np.asarray(u)
    v = np.asarray(v)
    if u.shape != v.shape or u.ndim != 1:
        raise ValueError(f"u and v must be 1-D arrays of equal length, got shapes {u.shape} and {v.shape}")
    if not (eps > 0 and math.isfinite(eps)):
        raise ValueError(f"eps must be a positive finite distance in px, got {eps!r}")
    if int(min_samples) < 1:
        raise ValueError(f"min_samples must be >= 1, got {min_samples!r}")
    return u.astype(np.int64, copy=False), v.astype(np.int64, copy=False)


def dbscan_sklearn(u: np.ndarray, v: np.ndarray, eps: float, min_samples: int) -> np.ndarray:
    """Reference DBSCAN (scikit-learn) over pixels ``(u, v)``; returns labels, -1 = noise."""
    u, v = _check(u, v, eps, min_samples)
    if u.size == 0:
        return np.empty(0, dtype=np.int64)
    from sklearn.cluster import DBSCAN

    pts = np.column_stack([u, v]).astype(np.float64)
    return DBSCAN(eps=float(eps), min_samples=int(min_samples)).fit(pts).labels_.astype(np.int64)


def dbscan_grid(u: np.ndarray, v: np.ndarray, eps: float, min_samples: int) -> np.ndarray:
    """Exact DBSCAN over unique integer pixels ``(u, v)`` (px); returns labels, -1 = noise.

    ``eps`` is the neighbourhood radius in px (distance ``<= eps``), ``min_samples``
    counts the pixel itself, as in scikit-learn. Pixels must be unique (duplicates
    would be counted twice, as scikit-learn would).
    """
    labels, _ = _grid(u, v, eps, min_samples)
    return labels


def core_mask(u: np.ndarray, v: np.ndarray, eps: float, min_samples: int) -> np.ndarray:
    """Boolean mask of the core pixels of :func:`dbscan_grid`."""
    _, core = _grid(u, v, eps, min_samples)
    return core


def grid_geometry(eps: float) -> tuple[int, int]:
    """The grid of :func:`dbscan_grid` for radius ``eps`` (px): ``(cell, reach)``.

    ``cell`` is the largest cell side (px) such that any two integer pixels of one cell are
    within eps; cells more than ``reach`` cells apart on an axis hold no pixels within eps.
    """
    eps = float(eps)
    # Largest cell side c (px) such that two integer pixels of one cell, at most
    # (c-1)*sqrt(2) apart, are always within eps.
    cell = max(1, int(math.floor(eps / math.sqrt(2.0))) + 1)
    while (cell - 1) * math.sqrt(2.0) > eps:
        cell -= 1
    # Cells up to `reach` away can hold pixels within eps: the closest pixels of
    # two cells k apart on one axis are (k-1)*c+1 px apart.
    reach = int(math.floor((eps - 1.0) / cell)) + 1 if eps >= 1.0 else 0
    return cell, reach


def disk_half_widths(eps: float) -> np.ndarray:
    """The integer eps-disk as row runs: ``half[dy + rad]`` is the largest ``w`` with
    ``w^2 + dy^2 <= eps^2`` for ``dy`` in ``[-rad, rad]`` (px); the same disk the grid
    backend counts neighbours in."""
    eps2 = float(eps) * float(eps)
    rad = 0
    while (rad + 1) * (rad + 1) <= eps2:
        rad += 1
    half = np.empty(2 * rad + 1, dtype=np.int64)
    for dy in range(-rad, rad + 1):
        w = 0
        while (w + 1) * (w + 1) + dy * dy <= eps2:
            w += 1
        half[dy + rad] = w
    return half


def dbscan_from_cores(u: np.ndarray, v: np.ndarray, core: np.ndarray, eps: float) -> np.ndarray:
    """DBSCAN labels of unique pixels ``(u, v)`` (px) whose core flags are already known.

    Gives exactly :func:`dbscan_grid`'s labels when ``core`` is its core mask: clusters are
    the eps-connected components of the cores, numbered by their smallest index; a non-core
    pixel joins the cluster of its nearest core within ``eps`` (ties: the core of smallest
    index), else it is noise (-1). Pixels far from every core may be left out of the input
    without changing the others' labels, which is what the incremental detector relies on.
    """
    u, v = _check(u, v, eps, 1)
    core = np.asarray(core, dtype=np.bool_)
    if core.shape != u.shape:
        raise ValueError(f"core must have one flag per pixel, got shape {core.shape} for {u.size} pixels")
    if u.size == 0:
        return np.empty(0, dtype=np.int64)
    cell, reach = grid_geometry(eps)
    return _cores_kernel(u, v, core, float(eps) * float(eps), cell, reach)


def _grid(u, v, eps, min_samples):
    u, v = _check(u, v, eps, min_samples)
    n = u.size
    if n == 0:
        return np.empty(0, dtype=np.int64), np.zeros(0, dtype=bool)
    cell, reach = grid_geometry(eps)
    return _grid_kernel(u, v, float(eps) * float(eps), int(min_samples), cell, reach)


@njit(cache=True, nogil=True)
def _find(parent, i):
    root = i
    while parent[root] != root:
        root = parent[root]
    while parent[i] != root:
        nxt = parent[i]
        parent[i] = root
        i = nxt
    return root


@njit(cache=True, nogil=True)
def _union(parent, a, b):
    ra = _find(parent, a)
    rb = _find(parent, b)
    if ra == rb:
        return
    if ra < rb:
        parent[rb] = ra
    else:
        parent[ra] = rb


@njit(cache=True, nogil=True)
def _cells_touch(pu, pv, core, s0, s1, t0, t1, eps2):
    """True when a core pixel of cell [s0, s1) is within eps of one of [t0, t1)."""
    for a in range(s0, s1):
        if not core[a]:
            continue
        for b in range(t0, t1):
            if not core[b]:
                continue
            du = pu[a] - pu[b]
            dv = pv[a] - pv[b]
            if du * du + dv * dv <= eps2:
                return True
    return False


@njit(cache=True, nogil=True)
def _grid_kernel(u, v, eps2, min_samples, cell, reach):
    # plain loops instead of array expressions, fancy indexing and .min(): each of those
    # compiles its own numba template, seconds in all on a cold cache (same code speed)
    n = u.shape[0]
    umin = u[0]
    umax = u[0]
    vmin = v[0]
    vmax = v[0]
    for i in range(1, n):
        umin = min(umin, u[i])
        umax = max(umax, u[i])
        vmin = min(vmin, v[i])
        vmax = max(vmax, v[i])
    gw = (umax - umin) // cell + 1
    gh = (vmax - vmin) // cell + 1
    cid = np.empty(n, dtype=np.int64)
    for i in range(n):
        cid[i] = ((v[i] - vmin) // cell) * gw + (u[i] - umin) // cell
    ncell = gw * gh
    start = np.zeros(ncell + 1, dtype=np.int64)
    for i in range(n):
        start[cid[i] + 1] += 1
    for c in range(ncell):
        start[c + 1] += start[c]
    # counting sort by cell (stable)
    order = np.empty(n, dtype=np.int64)
    fill = np.empty(ncell, dtype=np.int64)
    for c in range(ncell):
        fill[c] = start[c]
    for i in range(n):
        order[fill[cid[i]]] = i
        fill[cid[i]] += 1
    pu = np.empty(n, dtype=np.int64)
    pv = np.empty(n, dtype=np.int64)
    for a in range(n):
        pu[a] = u[order[a]]
        pv[a] = v[order[a]]

    # 1. pre-screen on the cell grid: a pixel can only be core if the (2 reach + 1)^2
    # block of cells around its cell holds >= min_samples pixels ("dense" cells), and only
    # be a border pixel if its cell is within reach of a dense cell; other pixels are
    # noise whatever the details, and are never looked at again.
    cnt_pre = np.zeros((gh + 1, gw + 1), dtype=np.int64)
    for c in range(ncell):
        cnt_pre[c // gw + 1, c % gw + 1] = start[c + 1] - start[c]
    for r in range(1, gh + 1):
        for x in range(1, gw + 1):
            cnt_pre[r, x] += cnt_pre[r - 1, x] + cnt_pre[r, x - 1] - cnt_pre[r - 1, x - 1]
    dense_pre = np.zeros((gh + 1, gw + 1), dtype=np.int64)
    dense = np.zeros(ncell, dtype=np.bool_)
    for c in range(ncell):
        if start[c + 1] == start[c]:
            continue
        gx = c % gw
        gy = c // gw
        x0 = max(gx - reach, 0)
        x1 = min(gx + reach + 1, gw)
        y0 = max(gy - reach, 0)
        y1 = min(gy + reach + 1, gh)
        tot = cnt_pre[y1, x1] - cnt_pre[y0, x1] - cnt_pre[y1, x0] + cnt_pre[y0, x0]
        if tot >= min_samples:
            dense[c] = True
            dense_pre[gy + 1, gx + 1] = 1
    for r in range(1, gh + 1):
        for x in range(1, gw + 1):
            dense_pre[r, x] += dense_pre[r - 1, x] + dense_pre[r, x - 1] - dense_pre[r - 1, x - 1]

    # neighbour counts (itself included) of the pixels of dense cells, from an occupancy
    # image (column x stored at x + 1): the eps-disk is a stack of row runs of half-width half[dy]
    rad = 0
    while (rad + 1) * (rad + 1) <= eps2:
        rad += 1
    half = np.empty(2 * rad + 1, dtype=np.int64)
    for dy in range(-rad, rad + 1):
        w = 0
        while (w + 1) * (w + 1) + dy * dy <= eps2:
            w += 1
        half[dy + rad] = w
    bw = umax - umin + 1
    bh = vmax - vmin + 1
    # row prefix sums of the occupancy, only on the rows a dense cell's disk can reach
    # (2 reads per run)
    occ = np.zeros((bh, bw + 1), dtype=np.int16)
    for i in range(n):
        occ[v[i] - vmin, u[i] - umin + 1] = 1
    need = np.zeros(bh, dtype=np.bool_)
    for c in range(ncell):
        if dense[c]:
            r0 = max((c // gw) * cell - rad, 0)
            r1 = min((c // gw + 1) * cell + rad, bh)
            for r in range(r0, r1):
                need[r] = True
    for r in range(bh):
        if need[r]:
            for x in range(bw):
                occ[r, x + 1] += occ[r, x]
    core = np.zeros(n, dtype=np.bool_)
    for c in range(ncell):
        if not dense[c]:
            continue
        for a in range(start[c], start[c + 1]):
            x = pu[a] - umin
            y = pv[a] - vmin
            k = 0
            for dy in range(-rad, rad + 1):
                r = y + dy
                if r < 0 or r >= bh:
                    continue
                w = half[dy + rad]
                lo = max(x - w, 0)
                hi = min(x + w + 1, bw)
                k += occ[r, hi] - occ[r, lo]
            core[a] = k >= min_samples

    # 2. union of cores: all cores of a cell at once, then pairs of cells
    parent = np.arange(n)
    first_core = np.full(ncell, -1, dtype=np.int64)
    for c in range(ncell):
        for a in range(start[c], start[c + 1]):
            if core[a]:
                if first_core[c] < 0:
                    first_core[c] = a
                else:
                    _union(parent, first_core[c], a)
    # cells are tested ring by ring (nearest cells first), so that most far
    # pairs are already united through nearer ones and are skipped
    for ring in range(1, reach + 1):
        for c in range(ncell):
            fa = first_core[c]
            if fa < 0:
                continue
            gx = c % gw
            gy = c // gw
            for dy in range(0, ring + 1):
                yy = gy + dy
                if yy >= gh:
                    continue
                for dx in range(-ring, ring + 1):
                    if max(abs(dx), dy) != ring or (dy == 0 and dx <= 0):
                        continue
                    xx = gx + dx
                    if xx < 0 or xx >= gw:
                        continue
                    c2 = yy * gw + xx
                    fb = first_core[c2]
                    if fb < 0 or _find(parent, fa) == _find(parent, fb):
                        continue
                    if _cells_touch(pu, pv, core, start[c], start[c + 1], start[c2], start[c2 + 1], eps2):
                        _union(parent, fa, fb)

    # 3. border pixels: cluster of the nearest core within eps (cells scanned
    # ring by ring, stopping once no farther ring can hold a nearer core)
    attach = np.full(n, -1, dtype=np.int64)
    for c in range(ncell):
        gx = c % gw
        gy = c // gw
        x0 = max(gx - reach, 0)
        x1 = min(gx + reach + 1, gw)
        y0 = max(gy - reach, 0)
        y1 = min(gy + reach + 1, gh)
        if dense_pre[y1, x1] - dense_pre[y0, x1] - dense_pre[y1, x0] + dense_pre[y0, x0] == 0:
            continue
        for a in range(start[c], start[c + 1]):
            if core[a]:
                continue
            best = eps2 + 1.0
            for ring in range(0, reach + 1):
                if ring > 0 and attach[a] >= 0:
                    dmin = (ring - 1) * cell + 1
                    if dmin * dmin > best:
                        break
                for dy in range(-ring, ring + 1):
                    yy = gy + dy
                    if yy < 0 or yy >= gh:
                        continue
                    for dx in range(-ring, ring + 1):
                        if max(abs(dx), abs(dy)) != ring:
                            continue
                        xx = gx + dx
                        if xx < 0 or xx >= gw:
                            continue
                        c2 = yy * gw + xx
                        if first_core[c2] < 0:
                            continue
                        for b in range(start[c2], start[c2 + 1]):
                            if not core[b]:
                                continue
                            du = pu[a] - pu[b]
                            dv = pv[a] - pv[b]
                            d2 = du * du + dv * dv
                            if d2 <= eps2 and (d2 < best or (d2 == best and order[b] < order[attach[a]])):
                                best = d2
                                attach[a] = b

    # 4. labels in scikit-learn's order: clusters numbered by their smallest
    # original index among core pixels
    root_min = np.full(n, n, dtype=np.int64)
    for a in range(n):
        if core[a]:
            r = _find(parent, a)
            if order[a] < root_min[r]:
                root_min[r] = order[a]
    # rank roots by root_min
    roots = np.empty(n, dtype=np.int64)
    keys = np.empty(n, dtype=np.int64)
    nr = 0
    for a in range(n):
        if core[a] and _find(parent, a) == a:
            roots[nr] = a
            keys[nr] = root_min[a]
            nr += 1
    # label clusters in the order of their first pixel: the keys are distinct indices in
    # [0, n) (clusters are disjoint), so a scatter ranks them without a sort (which would
    # also cost seconds of numba compilation on a fresh install)
    slot = np.full(n, -1, dtype=np.int64)
    for k in range(nr):
        slot[keys[k]] = k
    root_label = np.full(n, -1, dtype=np.int64)
    label = 0
    for i in range(n):
        if slot[i] >= 0:
            root_label[roots[slot[i]]] = label
            label += 1
    labels = np.full(n, -1, dtype=np.int64)
    core_out = np.zeros(n, dtype=np.bool_)
    for a in range(n):
        if core[a]:
            labels[order[a]] = root_label[_find(parent, a)]
            core_out[order[a]] = True
        elif attach[a] >= 0:
            labels[order[a]] = root_label[_find(parent, attach[a])]
    return labels, core_out


@njit(cache=True, nogil=True)
def _core_lists_touch(pu, pv, cidx, s0, s1, t0, t1, eps2):
    """True when a core of the list ``cidx[s0:s1]`` is within eps of one of ``cidx[t0:t1]``."""
    for i in range(s0, s1):
        a = cidx[i]
        for j in range(t0, t1):
            b = cidx[j]
            du = pu[a] - pu[b]
            dv = pv[a] - pv[b]
            if du * du + dv * dv <= eps2:
                return True
    return False


@njit(cache=True, nogil=True)
def _box_gap2(x, y, x0, x1, y0, y1):
    """Squared distance from pixel (x, y) to the box [x0, x1] x [y0, y1] (0 inside)."""
    dx = x0 - x if x < x0 else (x - x1 if x > x1 else 0)
    dy = y0 - y if y < y0 else (y - y1 if y > y1 else 0)
    return dx * dx + dy * dy


@njit(cache=True, nogil=True)
def _cores_kernel(u, v, core_in, eps2, cell, reach):
    """Steps 2-4 of :func:`_grid_kernel` (union of cores, border pixels, labels) for pixels
    whose core flags are given (input order).

    Each cell keeps the list of its cores and their bounding box, so the pair tests and the
    border search visit cores only, and skip a cell whose cores' box is farther than eps (or
    than the best core found so far) from the pixel: the same tests on fewer pairs, hence the
    same labels (issue 22: the incremental detector's selection holds many noise pixels around
    the robots, each of which looked at every pixel of the 3 x 3 cells around it)."""
    n = u.shape[0]
    umin = u[0]
    umax = u[0]
    vmin = v[0]
    vmax = v[0]
    for i in range(1, n):
        umin = min(umin, u[i])
        umax = max(umax, u[i])
        vmin = min(vmin, v[i])
        vmax = max(vmax, v[i])
    gw = (umax - umin) // cell + 1
    gh = (vmax - vmin) // cell + 1
    # cell of each pixel, with the column's and row's cell looked up (two divisions per pixel
    # cost more than the tables)
    xcell = np.empty(umax - umin + 1, dtype=np.int64)
    for x in range(xcell.shape[0]):
        xcell[x] = x // cell
    ycell = np.empty(vmax - vmin + 1, dtype=np.int64)
    for y in range(ycell.shape[0]):
        ycell[y] = (y // cell) * gw
    cid = np.empty(n, dtype=np.int64)
    for i in range(n):
        cid[i] = ycell[v[i] - vmin] + xcell[u[i] - umin]
    ncell = gw * gh
    start = np.zeros(ncell + 1, dtype=np.int64)
    for i in range(n):
        start[cid[i] + 1] += 1
    for c in range(ncell):
        start[c + 1] += start[c]
    order = np.empty(n, dtype=np.int64)
    fill = np.empty(ncell, dtype=np.int64)
    for c in range(ncell):
        fill[c] = start[c]
    for i in range(n):
        order[fill[cid[i]]] = i
        fill[cid[i]] += 1
    pu = np.empty(n, dtype=np.int64)
    pv = np.empty(n, dtype=np.int64)
    core = np.zeros(n, dtype=np.bool_)
    for a in range(n):
        pu[a] = u[order[a]]
        pv[a] = v[order[a]]
        core[a] = core_in[order[a]]
    # per cell: its cores (cidx[cstart[c]:cstart[c + 1]], in cell order) and their box
    cstart = np.zeros(ncell + 1, dtype=np.int64)
    cidx = np.empty(n, dtype=np.int64)
    bx0 = np.empty(ncell, dtype=np.int64)
    bx1 = np.empty(ncell, dtype=np.int64)
    by0 = np.empty(ncell, dtype=np.int64)
    by1 = np.empty(ncell, dtype=np.int64)
    m = 0
    for c in range(ncell):
        cstart[c] = m
        for a in range(start[c], start[c + 1]):
            if core[a]:
                if m == cstart[c]:
                    bx0[c] = pu[a]
                    bx1[c] = pu[a]
                    by0[c] = pv[a]
                    by1[c] = pv[a]
                else:
                    bx0[c] = min(bx0[c], pu[a])
                    bx1[c] = max(bx1[c], pu[a])
                    by0[c] = min(by0[c], pv[a])
                    by1[c] = max(by1[c], pv[a])
                cidx[m] = a
                m += 1
    cstart[ncell] = m
    parent = np.arange(n)
    first_core = np.full(ncell, -1, dtype=np.int64)
    for c in range(ncell):
        if cstart[c + 1] > cstart[c]:
            fa = cidx[cstart[c]]
            first_core[c] = fa
            for i in range(cstart[c] + 1, cstart[c + 1]):
                _union(parent, fa, cidx[i])
    for ring in range(1, reach + 1):
        for c in range(ncell):
            fa = first_core[c]
            if fa < 0:
                continue
            gx = c % gw
            gy = c // gw
            for dy in range(0, ring + 1):
                yy = gy + dy
                if yy >= gh:
                    continue
                for dx in range(-ring, ring + 1):
                    if max(abs(dx), dy) != ring or (dy == 0 and dx <= 0):
                        continue
                    xx = gx + dx
                    if xx < 0 or xx >= gw:
                        continue
                    c2 = yy * gw + xx
                    fb = first_core[c2]
                    if fb < 0 or _find(parent, fa) == _find(parent, fb):
                        continue
                    # boxes farther apart than eps hold no pair within eps
                    gx_ = max(bx0[c2] - bx1[c], bx0[c] - bx1[c2], 0)
                    gy_ = max(by0[c2] - by1[c], by0[c] - by1[c2], 0)
                    if gx_ * gx_ + gy_ * gy_ > eps2:
                        continue
                    if _core_lists_touch(pu, pv, cidx, cstart[c], cstart[c + 1], cstart[c2], cstart[c2 + 1],
                                         eps2):
                        _union(parent, fa, fb)
    # border pixels: the nearest core within eps (ties: smallest input index). The cells within
    # reach are visited nearest box first, and the visit stops at the first box farther than the
    # best core so far: the nearest core (smallest index among equals) does not depend on the
    # order cells are visited in, and a box farther than the best holds no core as near
    attach = np.full(n, -1, dtype=np.int64)
    side = 2 * reach + 1
    cand = np.empty(side * side, dtype=np.int64)
    cand_lb = np.empty(side * side, dtype=np.int64)
    for c in range(ncell):
        if start[c + 1] - start[c] == cstart[c + 1] - cstart[c]:
            continue   # all cores
        gy = c // gw
        gx = c - gy * gw
        for a in range(start[c], start[c + 1]):
            if core[a]:
                continue
            x = pu[a]
            y = pv[a]
            # the cells within reach holding a core whose box is within eps, by box distance
            nc = 0
            for yy in range(max(gy - reach, 0), min(gy + reach + 1, gh)):
                for xx in range(max(gx - reach, 0), min(gx + reach + 1, gw)):
                    c2 = yy * gw + xx
                    if first_core[c2] < 0:
                        continue
                    lb = _box_gap2(x, y, bx0[c2], bx1[c2], by0[c2], by1[c2])
                    if lb > eps2:
                        continue
                    q = nc
                    while q > 0 and cand_lb[q - 1] > lb:
                        cand_lb[q] = cand_lb[q - 1]
                        cand[q] = cand[q - 1]
                        q -= 1
                    cand_lb[q] = lb
                    cand[q] = c2
                    nc += 1
            best = eps2 + 1.0
            for q in range(nc):
                if cand_lb[q] > best:
                    break
                c2 = cand[q]
                for i in range(cstart[c2], cstart[c2 + 1]):
                    b = cidx[i]
                    du = x - pu[b]
                    dv = y - pv[b]
                    d2 = du * du + dv * dv
                    if d2 <= eps2 and (d2 < best or (d2 == best and order[b] < order[attach[a]])):
                        best = d2
                        attach[a] = b
    # labels: clusters numbered by the smallest input index of their cores
    root_label = np.full(n, -1, dtype=np.int64)
    labels = np.full(n, -1, dtype=np.int64)
    # input order = index order: the first core met of a cluster gives its number
    inv = np.empty(n, dtype=np.int64)
    for a in range(n):
        inv[order[a]] = a
    label = 0
    for i in range(n):
        a = inv[i]
        if core[a]:
            r = _find(parent, a)
            if root_label[r] < 0:
                root_label[r] = label
                label += 1
            labels[i] = root_label[r]
    for i in range(n):
        a = inv[i]
        if not core[a] and attach[a] >= 0:
            labels[i] = root_label[_find(parent, attach[a])]
    return labels

"""Robot detection in one accumulated event window.

Input: the events of the last accumulation time ``t_a`` (``arena.events.EVENT_DTYPE``,
sensor frame: ``x`` column right, ``y`` row down, px; ``t`` in µs) and the end time of
the window. Output: a list of :class:`Detection` in the sensor frame (px, px/s, rad
measured from the sensor's +u axis towards +v). Conversion to arena metres is the
pipeline's job (:mod:`tracker.calibration`).

Two detectors:

- :class:`PaperDetector` — the paper's method: DBSCAN three times over the unique active
  pixels (all events: eps 15 px, minPts 170; ON and OFF events: eps 6 px, minPts 50),
  cluster centroids, and the heading ``atan2(C-y - C+y, C-x - C+x)`` from the nearest ON
  and OFF cluster centroids. Its pose refers to the window's end, as in the paper.
- :class:`Detector` (default) — physical parameters (chassis size in m, speeds in m/s)
  converted to px with the calibration's scale, a density threshold adapted to the
  measured noise level, rejection of clusters too small to be a robot, the split of a
  cluster that holds several predicted robots, and a pose at the window's end: the
  cluster's events are fitted by a straight motion ``p(t) = p0 + w (t - t0)`` (least
  squares), evaluated at the end of the cluster's activity, which also gives the
  velocity and the motion heading. The cluster's shape gives the chassis orientation
  modulo its symmetry (the 4th angular harmonic of a square footprint's outline points
  at its corners): the fleet tracker resolves it with its heading prediction, which keeps
  the heading right through zero-point turns, when there is no motion direction.

All per-window work is O(active pixels): the statistics come per pixel (count, sum of
times, sum of squared times), from :class:`tracker.accumulate.PixelWindow` or from the
window's events. On a :class:`~tracker.accumulate.PixelWindow` (:meth:`Detector.detect_window`)
the default detector does less: a :class:`tracker.density.NeighbourIndex` attached to the
window keeps every pixel's neighbour count up to date slice by slice, and only the pixels
near dense ones are clustered, with exactly the labels of the full-window grid DBSCAN
(``DetectorConfig.incremental``; off, every slice re-clusters the whole window).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from tracker.dbscan import dbscan_from_cores, dbscan_grid, dbscan_sklearn
from tracker.density import NeighbourIndex

__all__ = ["Detection", "Detector", "DetectorConfig", "PaperDetector", "PaperConfig", "BACKENDS"]

#: DBSCAN backends by name: ``grid`` (exact, default) and ``sklearn`` (reference).
BACKENDS = {"grid": dbscan_grid, "sklearn": dbscan_sklearn}


@dataclass
class Detection:
    """One robot seen in a window (sensor frame).

    Attributes:
        u, v: position, px (column right, row down), at time ``t_us``.
        t_us: time the position refers to, µs (sensor clock).
        n_events: events in the cluster.
        n_pixels: unique active pixels in the cluster.
        du, dv: velocity, px/s (NaN when not estimated).
        speed_sigma: 1-sigma uncertainty of the speed, px/s (NaN when unknown).
        heading: heading in the sensor frame, rad from +u towards +v (NaN when unknown).
        heading_source: ``"motion"``, ``"polarity"`` or ``""``.
        radius: rms distance of the cluster's pixels to its centroid, px.
        t_vel_us: time the velocity and the motion heading refer to (mean event time), µs.
        shape_axis: orientation of the cluster's shape, rad in the sensor frame, known only
            modulo 2*pi/``shape_order`` (NaN when the shape is too round to tell).
        shape_order: the chassis' rotational symmetry (4 for a square footprint, 2 for a rectangle).
        t_act_us: end of the cluster's activity (µs), where the position is evaluated: before
            ``t_us`` when the robot stopped inside the window (None: not estimated).
        whole: True when the detection covers the whole robot (its leading and trailing edges
            grouped, or a filled cluster as long and wide as the chassis); False for a lone
            edge bar or a sparse part, whose position is less certain (``shape_axis`` NaN).
        n_parts: DBSCAN clusters grouped into this detection (1: a single cluster).
        outline: True when ``u, v`` is the middle of the outline (the silhouette's extent, each
            pixel once), False when it is an event centroid (or its motion fit). A silhouette
            reaches from the ground (the foot of the walls facing the lens) to the top edge on
            the far side, so its middle is seen at half the robot's height (the pipeline
            corrects its parallax for that height).
    """

    u: float
    v: float
    t_us: int
    n_events: int
    n_pixels: int
    du: float = math.nan
    dv: float = math.nan
    speed_sigma: float = math.nan
    heading: float = math.nan
    heading_source: str = ""
    radius: float = math.nan
    t_vel_us: int | None = None
    shape_axis: float = math.nan
    shape_order: int = 4
    t_act_us: int | None = None
    whole: bool = True
    n_parts: int = 1
    outline: bool = False


# --------------------------------------------------------------------------- pixels


@njit(cache=True, nogil=True)
def _pixelize(x, y, scratch, width):
    """Unique pixels of events: returns (u, v, count, ev_pix). ``scratch`` (int32,
    width*height, all -1) is restored to -1 before returning."""
    n = x.shape[0]
    ev_pix = np.empty(n, dtype=np.int64)
    lin = np.empty(n, dtype=np.int64)
    m = 0
    for i in range(n):
        k = np.int64(y[i]) * width + np.int64(x[i])
        j = scratch[k]
        if j < 0:
            scratch[k] = m
            lin[m] = k
            j = m
            m += 1
        ev_pix[i] = j
    count = np.zeros(m, dtype=np.int64)
    for i in range(n):
        count[ev_pix[i]] += 1
    pu = np.empty(m, dtype=np.int64)
    pv = np.empty(m, dtype=np.int64)
    for j in range(m):
        pu[j] = lin[j] % width
        pv[j] = lin[j] // width
        scratch[lin[j]] = -1
    return pu, pv, count, ev_pix


class _Pixels:
    """Scratch image reused between windows to find unique pixels in O(n)."""

    def __init__(self) -> None:
        self._scratch = np.full(0, -1, dtype=np.int32)
        self._shape = (0, 0)

    def __call__(self, x: np.ndarray, y: np.ndarray, width: int, height: int):
        if x.size and (int(x.max()) >= width or int(y.max()) >= height):
            raise ValueError(
                f"event at ({int(x.max())}, {int(y.max())}) px lies outside the {width}x{height} sensor")
        if self._shape != (width, height):
            self._scratch = np.full(width * height, -1, dtype=np.int32)
            self._shape = (width, height)
        return _pixelize(x, y, self._scratch, width)


# --------------------------------------------------------------------------- paper


@dataclass
class PaperConfig:
    """The paper's pixel parameters (authors' code). eps in px, min_samples counts the point."""

    eps_all: float = 15.0
    min_samples_all: int = 170
    eps_polarity: float = 6.0
    min_samples_polarity: int = 50
    backend: str = "grid"


class PaperDetector:
    """The paper's detection: three DBSCANs (all, ON, OFF), centroids, ON/OFF heading."""

    def __init__(self, config: PaperConfig | None = None, width: int = 640, height: int = 480) -> None:
        self.config = config or PaperConfig()
        if self.config.backend not in BACKENDS:
            raise ValueError(f"unknown DBSCAN backend {self.config.backend!r}; choose from {sorted(BACKENDS)}")
        self.width, self.height = int(width), int(height)
        self._pix = _Pixels()

    def _clusters(self, ev: np.ndarray, eps: float, min_samples: int):
        dbscan = BACKENDS[self.config.backend]
        pu, pv, count, _ = self._pix(ev["x"], ev["y"], self.width, self.height)
        labels = dbscan(pu, pv, eps, min_samples)
        k = int(labels.max()) + 1 if labels.size else 0
        out = []
        for c in range(k):
            sel = labels == c
            out.append((float(pu[sel].mean()), float(pv[sel].mean()), int(count[sel].sum()), int(sel.sum())))
        return out

    def detect(self, events: np.ndarray, t_end_us: int, hints: np.ndarray | None = None) -> list[Detection]:
        """Detections in the window ``events`` ending at ``t_end_us`` (µs). ``hints`` is ignored."""
        cfg = self.config
        full = self._clusters(events, cfg.eps_all, cfg.min_samples_all)
        if not full:
            return []
        on = self._clusters(events[events["p"] == 1], cfg.eps_polarity, cfg.min_samples_polarity)
        off = self._clusters(events[events["p"] == 0], cfg.eps_polarity, cfg.min_samples_polarity)
        centres = np.array([[c[0], c[1]] for c in full])
        on_idx = off_idx = None
        from scipy.spatial import cKDTree  # only the paper's detector needs it: not at import (start-up)

        if on:
            _, on_idx = cKDTree(np.array([[c[0], c[1]] for c in on])).query(centres)
        if off:
            _, off_idx = cKDTree(np.array([[c[0], c[1]] for c in off])).query(centres)
        dets = []
        for i, (u, v, n_ev, n_px) in enumerate(full):
            heading, src = math.nan, ""
            if on_idx is not None and off_idx is not None:
                cp, cm = on[on_idx[i]], off[off_idx[i]]
                heading, src = math.atan2(cm[1] - cp[1], cm[0] - cp[0]), "polarity"
            dets.append(Detection(u=u, v=v, t_us=int(t_end_us), n_events=n_ev, n_pixels=n_px,
                                  heading=heading, heading_source=src))
        return dets


# --------------------------------------------------------------------------- default


@dataclass
class DetectorConfig:
    """Physical parameters of the default detector (converted to px with ``px_per_m``).

    Attributes:
        chassis_m: robot footprint side, m (Zumo 32U4: 0.10).
        eps_chassis: DBSCAN radius as a fraction of the chassis side.
        min_fill: least fraction of the eps-disk a robot's pixels fill (density floor).
        noise_false_rate: tolerated probability that pure noise reaches minPts at a pixel.
        noise_quantile: the noise density minPts is set for: this quantile of the active pixels
            per noise cell, over the cells without robots (the densest 10 % left out); 0.5
            would be a typical cell, but noise is densest over dark floor and in dim corners.
        min_area_chassis: least cluster area (active pixels) as a fraction of the chassis area.
        min_speed_mps: speed above which the motion direction gives the heading, m/s.
        chassis_aspect: footprint length / width; near 1 the shape gives the heading modulo
            90 degrees (4-fold), otherwise modulo 180 degrees.
        min_anisotropy: least normalised harmonic amplitude for a shape orientation.
        backend: DBSCAN backend, ``grid`` (exact, fast) or ``sklearn``.
        incremental: with the ``grid`` backend, on a pixel window, keep the neighbour counts
            between slices and cluster only near dense pixels (same labels as re-clustering
            the whole window, which ``False`` does every slice).
        group_edges: group the clusters of one robot (a plain shell is seen only through its
            leading and trailing edges: two bars of opposite polarity one chassis length apart
            along the motion) and place the robot by fitting its footprint (a box of the chassis
            size) to the outline, instead of one detection per cluster at its event centroid.
            ``False``: the detector before issue 19 (one detection per cluster).
        outline_filled: with ``group_edges``, a single filled cluster is placed by its outline
            too (the middle of its trimmed extent along and across the motion, or along the sensor
            axes when it does not move, e.g. a zero-point turn; each pixel once), not by its event
            centroid: a shell's events are not spread evenly over its footprint (a bright shell
            barely contrasts with the mats, and its dark front window's inner edge gives most of
            its events), so the centroid sits where the contrast is (1.4 cm ahead of the centre on
            a near-white shell at full speed). ``False``: the event centroid's motion fit.
        edge_flanks: the outline's ends are its edge bars' outer flanks (where a bar falls to half
            its peak), the leading end placed by each pixel's first event time and the trailing
            end by its last (see :func:`_outline_extent`); ``False``: the trimmed extremes of the
            pixels moved by their mean event times, which stray pixels (a noise event moves a
            pixel by the wrong time, anywhere along the path) and inner edges pulled off: the
            outline then sat 0.2-0.5 cm behind a moving robot's centre, depending on its shell.
    """

    chassis_m: float = 0.10
    eps_chassis: float = 0.25
    min_fill: float = 0.12
    noise_false_rate: float = 1e-7
    noise_quantile: float = 0.95
    min_area_chassis: float = 0.12
    min_speed_mps: float = 0.05
    chassis_aspect: float = 1.0
    min_anisotropy: float = 0.08
    backend: str = "grid"
    incremental: bool = True
    group_edges: bool = True
    outline_filled: bool = True
    edge_flanks: bool = True

    def validate(self) -> None:
        for name in ("chassis_m", "eps_chassis", "min_fill", "noise_false_rate", "min_area_chassis",
                     "chassis_aspect"):
            val = getattr(self, name)
            if not (isinstance(val, (int, float)) and val > 0 and math.isfinite(val)):
                raise ValueError(f"detector {name} must be a positive number, got {val!r}")
        if not (isinstance(self.noise_quantile, (int, float)) and 0 <= self.noise_quantile <= 1):
            raise ValueError(f"detector noise_quantile must be in [0, 1], got {self.noise_quantile!r}")
        if self.backend not in BACKENDS:
            raise ValueError(f"unknown DBSCAN backend {self.backend!r}; choose from {sorted(BACKENDS)}")
        for name in ("incremental", "group_edges", "outline_filled", "edge_flanks"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"detector {name} must be true or false, got {getattr(self, name)!r}")


def _lowest_quantile(counts: np.ndarray, m: int, q: float) -> float:
    """``np.quantile`` (method ``linear``) at ``q`` of the ``m`` smallest of ``counts`` (an integer
    array), bit for bit: the same virtual index ``(m - 1) q``, the same two order statistics and
    numpy's own interpolation (``_lerp``), for one ``np.partition`` of ``counts`` instead of a
    partition plus ``np.quantile``'s general machinery (~0.1-0.2 ms per slice, issue 22)."""
    h = (m - 1) * float(q)
    if h >= m - 1:          # numpy takes the largest value
        return float(np.partition(counts, m - 1)[m - 1])
    lo = math.floor(h)
    part = np.partition(counts, (lo, lo + 1))
    a, b = int(part[lo]), int(part[lo + 1])
    g = h - lo
    d = b - a
    # numpy's _lerp: a + d g, or b - d (1 - g) from g >= 0.5 on
    return float(b - d * (1.0 - g)) if g >= 0.5 else float(a + d * g)


@functools.lru_cache(maxsize=4096)
def _poisson_quantile(lam: float, tail: float) -> int:
    """Smallest k with P(X >= k) <= tail for X ~ Poisson(lam) (memoised: the noise density
    takes few distinct values, active pixels per cell over the cell's area)."""
    if lam <= 0:
        return 1
    term = math.exp(-lam)
    cdf = term
    k = 0
    while 1.0 - cdf > tail and k < 100000:
        k += 1
        term *= lam / k
        cdf += term
    return k + 1


@njit(cache=True, nogil=True)
def _cluster_moments(labels, pu, pv, cnt, st, st2, k):
    """Per cluster sums over its pixels' events: n, t, t2, x, y, xt, yt, x2, y2 and the
    bounding box umin, umax, vmin, vmax, and xy (px; t in s from the window's origin)."""
    s = np.zeros((k, 14))
    for c in range(k):
        s[c, 9] = 1e18
        s[c, 11] = 1e18
        s[c, 10] = -1e18
        s[c, 12] = -1e18
    for j in range(labels.shape[0]):
        c = labels[j]
        if c < 0:
            continue
        n = float(cnt[j])
        x = float(pu[j])
        y = float(pv[j])
        s[c, 0] += n
        s[c, 1] += st[j]
        s[c, 2] += st2[j]
        s[c, 3] += x * n
        s[c, 4] += y * n
        s[c, 5] += x * st[j]
        s[c, 6] += y * st[j]
        s[c, 7] += x * x * n
        s[c, 8] += y * y * n
        s[c, 9] = min(s[c, 9], x)
        s[c, 10] = max(s[c, 10], x)
        s[c, 11] = min(s[c, 11], y)
        s[c, 12] = max(s[c, 12], y)
        s[c, 13] += x * y * n
    return s


@njit(cache=True, nogil=True)
def _cluster_on(labels, on, k):
    """ON events per cluster: ``np.bincount(labels[labels >= 0], weights=on[labels >= 0], minlength=k)``,
    summed in the same order (so the same floats), without the two masked copies."""
    out = np.zeros(k)
    for j in range(labels.shape[0]):
        c = labels[j]
        if c >= 0:
            out[c] += float(on[j])
    return out


@njit(cache=True, nogil=True)
def _cluster_harmonic(labels, pu, pv, cnt, cx, cy, order, k):
    """Per cluster, sum of count * z^order / |z|^(order-2) with z = (u - cx) + i (v - cy)
    (order 2 or 4), and the sum of count * |z|^2 (the normaliser): the shape's order-fold
    orientation."""
    re = np.zeros(k)
    im = np.zeros(k)
    nz = np.zeros(k)
    for j in range(labels.shape[0]):
        c = labels[j]
        if c < 0:
            continue
        dx = pu[j] - cx[c]
        dy = pv[j] - cy[c]
        r2 = dx * dx + dy * dy
        if r2 <= 0.0:
            continue
        # z^2 / |z|^0 or z^4 / |z|^2
        zr = dx * dx - dy * dy
        zi = 2.0 * dx * dy
        if order == 4:
            zr, zi = (zr * zr - zi * zi) / r2, 2.0 * zr * zi / r2
        w = float(cnt[j])
        re[c] += w * zr
        im[c] += w * zi
        nz[c] += w * r2
    return re, im, nz


@njit(cache=True, nogil=True)
def _outline_extent(glab, pu, pv, cnt, st, st2, ng, ax, ay, vu, vv, t_ev, cap, binw, tail, edge_times):
    """Extent of each group's outline along its axis (ax, ay) and across it, px, at the group's
    time ``t_ev`` (s): every pixel is moved by the group's velocity (vu, vv px/s) from its event
    time to ``t_ev``, so a moving edge's pixels gather where the edge is then. Pixels count once,
    not by their events (the extent does not depend on the shell's contrast); the ``tail``
    fraction of a group's pixels is left out at either end (stray pixels), in bins of ``binw`` px
    over at most ``cap`` px. The event time is the pixel's mean. With ``edge_times`` (the
    detector's ``edge_flanks``): along the axis the leading end takes each pixel's first event
    time and the trailing end its last (mean -/+ sqrt(3) sd, the ends of a uniform spread; the
    silhouette's boundary is where a pixel's changes begin, ahead, and end, behind, while inner
    edges such as a dark front window add events later or earlier and pull the mean inwards),
    and each end, on both axes, is the outer flank of its half's profile: the outermost bin where
    it reaches half its peak (3-bin sums), so stray pixels (a noise event moves a pixel by the
    wrong time, anywhere along the path: ~10 % of a group's pixels) do not set it. Returns (ng,
    4): a_lo, a_hi, l_lo, l_hi (px, in the rotated frame a = x ax + y ay, l = y ax - x ay)."""
    out = np.zeros((ng, 4))
    amin = np.full(ng, 1e18)
    amax = np.full(ng, -1e18)
    lmin = np.full(ng, 1e18)
    lmax = np.full(ng, -1e18)
    npix = np.zeros(ng, dtype=np.int64)
    m = glab.shape[0]
    pa = np.empty(m)      # along the axis, at the first event time (leading end)
    pz = np.empty(m)      # along the axis, at the last event time (trailing end)
    pl = np.empty(m)
    for j in range(m):
        g = glab[j]
        if g < 0:
            continue
        tm = st[j] / cnt[j]
        half = 0.0
        if edge_times and cnt[j] > 1:
            var = st2[j] / cnt[j] - tm * tm
            if var > 0.0:
                half = math.sqrt(3.0 * var)
        va = vu[g] * ax[g] + vv[g] * ay[g]
        dt = t_ev[g] - tm
        x = pu[j] + vu[g] * dt
        y = pv[j] + vv[g] * dt
        a = x * ax[g] + y * ay[g]
        lat = y * ax[g] - x * ay[g]
        pa[j] = a + va * half
        pz[j] = a - va * half
        pl[j] = lat
        amin[g] = min(amin[g], min(pa[j], pz[j]))
        amax[g] = max(amax[g], max(pa[j], pz[j]))
        lmin[g] = min(lmin[g], lat)
        lmax[g] = max(lmax[g], lat)
        npix[g] += 1
    nmax = int(cap / binw) + 1
    na = np.zeros(ng, dtype=np.int64)
    nl = np.zeros(ng, dtype=np.int64)
    oa = np.zeros(ng + 1, dtype=np.int64)
    ol = np.zeros(ng + 1, dtype=np.int64)
    for g in range(ng):
        if npix[g] > 0:
            na[g] = min(nmax, int((amax[g] - amin[g]) / binw) + 1)
            nl[g] = min(nmax, int((lmax[g] - lmin[g]) / binw) + 1)
        oa[g + 1] = oa[g] + na[g]
        ol[g + 1] = ol[g] + nl[g]
    ha = np.zeros(oa[ng], dtype=np.int64)
    hz = np.zeros(oa[ng], dtype=np.int64)
    hl = np.zeros(ol[ng], dtype=np.int64)
    for j in range(m):
        g = glab[j]
        if g < 0:
            continue
        ha[oa[g] + min(int((pa[j] - amin[g]) / binw), na[g] - 1)] += 1
        hz[oa[g] + min(int((pz[j] - amin[g]) / binw), na[g] - 1)] += 1
        hl[ol[g] + min(int((pl[j] - lmin[g]) / binw), nl[g] - 1)] += 1
    for g in range(ng):
        if npix[g] == 0:
            continue
        tol = int(tail * npix[g])
        for axis in range(2):
            if axis == 0:
                lo_hist = hz[oa[g]:oa[g + 1]]
                hi_hist = ha[oa[g]:oa[g + 1]]
                lo0 = amin[g]
            else:
                lo_hist = hl[ol[g]:ol[g + 1]]
                hi_hist = lo_hist
                lo0 = lmin[g]
            nb = lo_hist.shape[0]
            q0 = 0
            acc = lo_hist[0]
            while q0 < nb - 1 and acc <= tol:
                q0 += 1
                acc += lo_hist[q0]
            q1 = nb - 1
            acc = hi_hist[nb - 1]
            while q1 > 0 and acc <= tol:
                q1 -= 1
                acc += hi_hist[q1]
            q1 = max(q1, q0)
            if edge_times and q1 - q0 >= 4:
                # each end at the outer flank of its half's profile (an edge bar along the
                # motion, the side across it): the outermost place where it is at least half its
                # peak (3-bin sums), not the last stray pixel
                mid = (q0 + q1) // 2
                pk = 0
                for b in range(q0, mid + 1):
                    sm = lo_hist[max(b - 1, 0)] + lo_hist[b] + lo_hist[min(b + 1, nb - 1)]
                    pk = max(pk, sm)
                b0 = q0
                while b0 < mid:
                    sm = lo_hist[max(b0 - 1, 0)] + lo_hist[b0] + lo_hist[min(b0 + 1, nb - 1)]
                    if 2 * sm >= pk:
                        break
                    b0 += 1
                pk = 0
                for b in range(mid, q1 + 1):
                    sm = hi_hist[max(b - 1, 0)] + hi_hist[b] + hi_hist[min(b + 1, nb - 1)]
                    pk = max(pk, sm)
                b1 = q1
                while b1 > mid:
                    sm = hi_hist[max(b1 - 1, 0)] + hi_hist[b1] + hi_hist[min(b1 + 1, nb - 1)]
                    if 2 * sm >= pk:
                        break
                    b1 -= 1
                q0, q1 = b0, b1
            out[g, 2 * axis] = lo0 + q0 * binw
            out[g, 2 * axis + 1] = lo0 + (q1 + 1) * binw
    return out


@njit(cache=True, nogil=True)
def _group_sums(grp, s, cxt, cyt, ctt, cxx, cyy, cxy, labels, on, has_on, pu, pv, ng):
    """Per group (``grp``: group of each cluster) of :meth:`Detector._grouped`: the sums of its
    clusters' moments (``s[:, :9]``) and centred sums, its number of clusters, each pixel's group
    (-1: none), its pixels, and the ON events' count and coordinate sums (zeros without ``on``).
    Summed in the order of numpy's ``bincount``/``add.at``: the same values."""
    k = grp.shape[0]
    gs = np.zeros((ng, 9))
    gxt = np.zeros(ng)
    gyt = np.zeros(ng)
    gtt = np.zeros(ng)
    gxx = np.zeros(ng)
    gyy = np.zeros(ng)
    gxy = np.zeros(ng)
    parts = np.zeros(ng, dtype=np.int64)
    for c in range(k):
        g = grp[c]
        for q in range(9):
            gs[g, q] += s[c, q]
        gxt[g] += cxt[c]
        gyt[g] += cyt[c]
        gtt[g] += ctt[c]
        gxx[g] += cxx[c]
        gyy[g] += cyy[c]
        gxy[g] += cxy[c]
        parts[g] += 1
    m = labels.shape[0]
    glab = np.full(m, -1, dtype=np.int64)
    npx = np.zeros(ng, dtype=np.int64)
    on_n = np.zeros(ng)
    on_x = np.zeros(ng)
    on_y = np.zeros(ng)
    for j in range(m):
        c = labels[j]
        if c < 0:
            continue
        g = grp[c]
        glab[j] = g
        npx[g] += 1
        if has_on:
            w = float(on[j])
            on_n[g] += w
            on_x[g] += w * pu[j]
            on_y[g] += w * pv[j]
    return gs, gxt, gyt, gtt, gxx, gyy, gxy, parts, glab, npx, on_n, on_x, on_y


@njit(cache=True, nogil=True)
def _group_axes(gs, gn, gtm, gvt, gxt, gyt, gtt, gxx, gyy, gxy, on_n, on_x, on_y, has_on, t_end_rel,
                length, min_speed):
    """Per group of :meth:`Detector._grouped`: the straight-motion fit (bx, by px/s, its sigma),
    the activity end ``t_eval`` (s), the motion axis (ax, ay), whether the axis comes from the
    outline (``along``) and whether the group moves, and its velocity along the axis (px/s).

    The motion axis: the line from the ON to the OFF centroid when they are apart (two edges),
    else the short axis of an elongated part (an edge lies across the motion), else the
    velocity; the velocity only orients it (timestamps can skew)."""
    ng = gs.shape[0]
    bx = np.zeros(ng)
    by = np.zeros(ng)
    sig = np.full(ng, np.nan)
    t_eval = np.full(ng, t_end_rel)
    ax = np.ones(ng)
    ay = np.zeros(ng)
    along = np.zeros(ng, dtype=np.bool_)   # axis from the outline, not the velocity
    moving = np.zeros(ng, dtype=np.bool_)
    vel = np.zeros((ng, 2))
    for g in range(ng):
        if gtt[g] > 1e-12:
            bx[g] = gxt[g] / gtt[g]
            by[g] = gyt[g] / gtt[g]
            res = max((gxx[g] + gyy[g] - bx[g] * gxt[g] - by[g] * gyt[g]) / gn[g], 1e-9)
            sig[g] = math.sqrt(res / gtt[g])
            # activity end: mean + sqrt(3) sd is the end of a uniform interval;
            # a robot that stopped inside the window stays where it stopped
            t_eval[g] = min(t_end_rel, gtm[g] + math.sqrt(3.0 * gvt[g]))
        got = False
        if has_on and 0 < on_n[g] < gs[g, 0]:
            n_off = gs[g, 0] - on_n[g]
            dx = (gs[g, 3] - on_x[g]) / n_off - on_x[g] / on_n[g]
            dy = (gs[g, 4] - on_y[g]) / n_off - on_y[g] / on_n[g]
            dd = math.hypot(dx, dy)
            if dd >= 0.5 * length:
                ax[g] = dx / dd
                ay[g] = dy / dd
                got = True
        if not got:
            # eigenvectors of the pooled within-part covariance
            a_ = gxx[g]
            b_ = gxy[g]
            c_ = gyy[g]
            tr = a_ + c_
            disc = math.sqrt(max(0.25 * (a_ - c_) ** 2 + b_ * b_, 0.0))
            lmin = 0.5 * tr - disc
            lmax = 0.5 * tr + disc
            if lmax > 0 and lmax >= 3.0 * max(lmin, 0.0):
                # minor axis: eigenvector of lmin
                if abs(b_) > 1e-12:
                    ex, ey = b_, lmin - a_
                elif a_ <= c_:
                    ex, ey = 1.0, 0.0
                else:
                    ex, ey = 0.0, 1.0
                en = math.hypot(ex, ey)
                ax[g] = ex / en
                ay[g] = ey / en
                got = True
        if got:
            along[g] = True
            va = bx[g] * ax[g] + by[g] * ay[g]
            if va < 0:
                ax[g] = -ax[g]
                ay[g] = -ay[g]
                va = -va
            moving[g] = not math.isnan(sig[g]) and va > min_speed and va > 3.0 * sig[g]
            if moving[g]:
                vel[g, 0] = va * ax[g]
                vel[g, 1] = va * ay[g]
        else:
            sp = math.hypot(bx[g], by[g])
            moving[g] = not math.isnan(sig[g]) and sp > min_speed and sp > 3.0 * sig[g]
            if moving[g]:
                ax[g] = bx[g] / sp
                ay[g] = by[g] / sp
                vel[g, 0] = bx[g]
                vel[g, 1] = by[g]
    return bx, by, sig, t_eval, ax, ay, along, moving, vel


@njit(cache=True, nogil=True)
def _group_poses(gs, gn, gtm, gtt, npx, parts, group_hint, hints, fit, bx, by, t_eval, ax, ay, along, moving,
                 h_re, h_im, h_n, min_area, length, width, outline_filled, sensor_w, sensor_h, order,
                 min_anisotropy):
    """Per group of :meth:`Detector._grouped`: kept (a robot's size), whole, placed by its outline,
    position (u, v px), velocity (px/s, NaN when unknown), motion heading (rad, NaN), shape axis
    (rad, NaN) and rms radius (px)."""
    ng = gs.shape[0]
    keep = np.zeros(ng, dtype=np.bool_)
    whole_ = np.zeros(ng, dtype=np.bool_)
    outl = np.zeros(ng, dtype=np.bool_)
    uv = np.zeros((ng, 2))
    vel = np.full((ng, 2), np.nan)
    heading = np.full(ng, np.nan)
    axis = np.full(ng, np.nan)
    radius = np.zeros(ng)
    for g in range(ng):
        nev = gs[g, 0]
        if npx[g] < min_area or nev < 3:
            continue
        keep[g] = True
        a_lo = fit[g, 0]
        a_hi = fit[g, 1]
        l_lo = fit[g, 2]
        l_hi = fit[g, 3]
        # both edges (or a filled footprint): as long as most of a chassis, and wide
        whole = a_hi - a_lo >= 0.6 * length and l_hi - l_lo >= 0.5 * width
        whole_[g] = whole
        xg = gs[g, 3] / gn[g]
        yg = gs[g, 4] / gn[g]
        if parts[g] == 1 and whole and not along[g] and not outline_filled:
            # one filled cluster (a marked or textured robot): the event fit at activity end
            if gtt[g] > 1e-12:
                u = xg + bx[g] * (t_eval[g] - gtm[g])
                v = yg + by[g] * (t_eval[g] - gtm[g])
            else:
                u = xg
                v = yg
        else:
            outl[g] = True
            # the outline's middle: between the leading and the trailing edge
            a_c = 0.5 * (a_lo + a_hi)
            hi = group_hint[g]
            if not whole and hi >= 0 and along[g]:
                # a lone edge: the robot lies half a chassis behind it (a leading edge)
                # or ahead of it (a trailing one), whichever is nearer the prediction
                a_h = hints[hi, 0] * ax[g] + hints[hi, 1] * ay[g]
                back = a_hi - 0.5 * length
                ahead = a_lo + 0.5 * length
                a_c = back if abs(a_h - back) <= abs(a_h - ahead) else ahead
            l_c = 0.5 * (l_lo + l_hi)
            u = a_c * ax[g] - l_c * ay[g]
            v = a_c * ay[g] + l_c * ax[g]
        uv[g, 0] = min(max(u, 0.0), sensor_w - 1.0)
        uv[g, 1] = min(max(v, 0.0), sensor_h - 1.0)
        if gtt[g] > 1e-12:
            # along the outline's axis when it gives one (the fit across it is timing skew)
            if along[g]:
                va = bx[g] * ax[g] + by[g] * ay[g]
                vel[g, 0] = va * ax[g]
                vel[g, 1] = va * ay[g]
            else:
                vel[g, 0] = bx[g]
                vel[g, 1] = by[g]
        if moving[g]:
            heading[g] = math.atan2(ay[g], ax[g])
        if whole and h_n[g] > 0 and math.hypot(h_re[g], h_im[g]) >= min_anisotropy * h_n[g]:
            axis[g] = math.atan2(h_im[g], h_re[g]) / order
            if order == 4:
                axis[g] -= math.pi / 4   # the 4th harmonic points at the corners
        radius[g] = math.sqrt(max(gs[g, 7] / gn[g] - xg * xg + gs[g, 8] / gn[g] - yg * yg, 0.0))
    return keep, whole_, outl, uv, vel, heading, axis, radius


@njit(cache=True, nogil=True)
def _pixel_stats(ev_pix, m, t, p, t_ref):
    """Per-pixel count, ON count, sum of t and of t^2 (t in s from t_ref)."""
    cnt = np.zeros(m, dtype=np.int64)
    on = np.zeros(m, dtype=np.int64)
    st = np.zeros(m)
    st2 = np.zeros(m)
    for i in range(ev_pix.shape[0]):
        j = ev_pix[i]
        ti = (t[i] - t_ref) * 1e-6
        cnt[j] += 1
        on[j] += p[i]
        st[j] += ti
        st2[j] += ti * ti
    return cnt, on, st, st2


class Detector:
    """Default detector: adaptive exact DBSCAN, split by predictions, pose at window end.

    Args:
        px_per_m: image scale on the arena, px per metre (from the calibration).
        width, height: sensor size, px.
        config: :class:`DetectorConfig`.
    """

    def __init__(self, px_per_m: float, width: int, height: int, config: DetectorConfig | None = None) -> None:
        if not (px_per_m > 0 and math.isfinite(px_per_m)):
            raise ValueError(f"px_per_m must be a positive scale in px/m, got {px_per_m!r}")
        self.config = config or DetectorConfig()
        self.config.validate()
        self.px_per_m = float(px_per_m)
        self.width, self.height = int(width), int(height)
        self.chassis_px = self.config.chassis_m * self.px_per_m
        self.eps_px = max(1.5, self.config.eps_chassis * self.chassis_px)
        self._disk = float(_disk_size(self.eps_px))
        self._pix = _Pixels()
        # side of the cells the noise level is measured in, px; least minPts
        self._noise_cell = max(4, int(round(self.chassis_px)))
        self._floor = max(3, int(math.ceil(self.config.min_fill * self._disk)))
        #: last noise density used, active pixels per px^2 (outside robots)
        self.noise_density_: float = 0.0
        #: last minPts used
        self.min_samples_: int = 0

    # -- density threshold ------------------------------------------------
    def _min_samples(self, pu: np.ndarray, pv: np.ndarray) -> int:
        """minPts from the measured noise: trimmed mean of active pixels per cell."""
        cell = self._noise_cell
        gw = self.width // cell + 1
        gh = self.height // cell + 1
        return self._min_samples_from_counts(np.bincount((pv // cell) * gw + pu // cell, minlength=gw * gh))

    def _min_samples_from_counts(self, counts: np.ndarray) -> int:
        """minPts from the active pixels per noise cell (``_noise_cell`` px, row-major)."""
        cell = self._noise_cell
        # cells holding robots are the dense tail: drop the top 10 % (the smallest 90 % kept);
        # background activity is not uniform (shot noise is densest over dark floor and in
        # vignetted corners): minPts from the noisiest background cells, not from their mean,
        # else noise there clusters into robots (2 Hz/px: ~1 000 false positives per 4 s)
        rho = _lowest_quantile(counts, max(1, int(0.9 * counts.size)), self.config.noise_quantile) / (cell * cell)
        self.noise_density_ = rho
        noise = _poisson_quantile(rho * self._disk, self.config.noise_false_rate)
        return max(self._floor, noise)

    def detect(self, events: np.ndarray, t_end_us: int, hints: np.ndarray | None = None) -> list[Detection]:
        """Detections in the window ``events`` (sorted by t) ending at ``t_end_us`` (µs).

        ``hints``: optional (k, 2) array of predicted robot positions, px; a cluster that
        holds two or more of them is split between them.
        """
        if events.size == 0:
            return []
        pu, pv, _, ev_pix = self._pix(events["x"], events["y"], self.width, self.height)
        t_ref = int(events["t"][0])
        cnt, on, st, st2 = _pixel_stats(ev_pix, pu.size, events["t"], events["p"], t_ref)
        return self.detect_pixels(pu, pv, cnt, st, st2, t_ref, t_end_us, hints, on=on)

    def detect_window(self, window, t_end_us: int, hints: np.ndarray | None = None) -> list[Detection]:
        """Detections from a :class:`tracker.accumulate.PixelWindow` ending at ``t_end_us`` (µs).

        With ``config.incremental`` (and the grid backend) the first call attaches a
        :class:`tracker.density.NeighbourIndex` to the window, which the window then keeps
        up to date at every push; the result equals that of re-clustering the whole window.
        """
        if (self.config.incremental and self.config.backend == "grid" and hasattr(window, "attach")
                and (window.width, window.height) == (self.width, self.height)):
            return self._detect_incremental(window, t_end_us, hints)
        pu, pv, cnt, on, st, st2 = window.pixels()
        if pu.size == 0:
            return []
        return self.detect_pixels(pu, pv, cnt, st, st2, window.t_ref_us, t_end_us, hints, on=on)

    def _detect_incremental(self, window, t_end_us: int, hints: np.ndarray | None) -> list[Detection]:
        idx = window.index
        if not (isinstance(idx, NeighbourIndex)
                and idx.matches(self.width, self.height, self.eps_px, self._noise_cell)):
            idx = NeighbourIndex(self.width, self.height, self.eps_px, self._noise_cell)
            window.attach(idx)
        if window.n_active == 0:
            return []
        ms = self._min_samples_from_counts(idx.noise_counts)
        self.min_samples_ = ms
        pix, slots, core = idx.select(window.slot_map, window.n_active, ms)
        if not core.any():
            return []
        pu, pv = window.coords(pix)
        labels = dbscan_from_cores(pu, pv, core, self.eps_px)
        # the slots' count, ON count, sum_t and sum_t2, in one pass over the window's records
        cnt, on, st, st2 = window.slot_records(slots)
        if not self.config.group_edges:
            on = None
        return self._detections(labels, pu, pv, cnt, st, st2, window.t_ref_us, t_end_us, hints, on=on)

    def detect_pixels(self, pu, pv, cnt, st, st2, t_ref_us: int, t_end_us: int,
                      hints: np.ndarray | None = None, on=None) -> list[Detection]:
        """Detections from per-pixel statistics: pixel (u, v) px, event count, and sums of
        event times and squared times (s from ``t_ref_us``); ``on``: ON events per pixel
        (None: unknown, the edge grouping then ignores polarity)."""
        ms = self._min_samples(pu, pv)
        self.min_samples_ = ms
        labels = BACKENDS[self.config.backend](pu, pv, self.eps_px, ms)
        return self._detections(labels, pu, pv, cnt, st, st2, t_ref_us, t_end_us, hints, on=on)

    def _detections(self, labels, pu, pv, cnt, st, st2, t_ref_us: int, t_end_us: int,
                    hints: np.ndarray | None, on=None) -> list[Detection]:
        """Detections from DBSCAN labels of pixels (any subset holding every labelled pixel,
        in the window's order: the sums, hence the results, are the same)."""
        cfg = self.config
        k = int(labels.max()) + 1 if labels.size else 0
        if k == 0:
            return []
        s = _cluster_moments(labels, pu, pv, cnt, st, st2, k)
        if hints is not None and len(hints) >= 2:
            labels, k2 = self._split(labels, k, s, pu, pv, np.asarray(hints, dtype=float))
            if k2 != k:
                k = k2
                s = _cluster_moments(labels, pu, pv, cnt, st, st2, k)
        if cfg.group_edges:
            return self._grouped(labels, k, s, pu, pv, cnt, on, st, st2, t_ref_us, t_end_us, hints)
        npx = np.bincount(labels[labels >= 0], minlength=k)
        order = 4 if 0.8 <= cfg.chassis_aspect <= 1.25 else 2
        n_safe = np.maximum(s[:, 0], 1.0)
        h_re, h_im, h_n = _cluster_harmonic(labels, pu, pv, cnt, s[:, 3] / n_safe, s[:, 4] / n_safe,
                                            order, k)
        min_area = cfg.min_area_chassis * self.chassis_px ** 2
        t_end_rel = (int(t_end_us) - int(t_ref_us)) * 1e-6
        ppm = self.px_per_m
        dets = []
        for c in range(k):
            n = s[c, 0]
            if npx[c] < min_area or n < 3:
                continue
            tm = s[c, 1] / n
            xm = s[c, 3] / n
            ym = s[c, 4] / n
            stt = s[c, 2] - n * tm * tm
            sxx = s[c, 7] / n - xm * xm
            syy = s[c, 8] / n - ym * ym
            radius = math.sqrt(max(sxx + syy, 0.0))
            t_eval = t_end_rel
            if stt <= 1e-12:
                u, v = xm, ym
                du = dv = sig = math.nan
            else:
                bx = (s[c, 5] - n * xm * tm) / stt
                by = (s[c, 6] - n * ym * tm) / stt
                # activity end: mean + sqrt(3) sd is the end of a uniform interval;
                # a robot that stopped inside the window stays where it stopped
                t_eval = min(t_end_rel, tm + math.sqrt(3.0 * stt / n))
                u = xm + bx * (t_eval - tm)
                v = ym + by * (t_eval - tm)
                # residual spread of positions about the line -> velocity sigma
                res = max(sxx + syy - (bx * bx + by * by) * stt / n, 1e-9)
                sig = math.sqrt(res / stt)
                du, dv = bx, by
            u = min(max(u, 0.0), self.width - 1.0)
            v = min(max(v, 0.0), self.height - 1.0)
            heading, src = math.nan, ""
            if not math.isnan(du):
                speed = math.hypot(du, dv)
                if speed > cfg.min_speed_mps * ppm and speed > 3.0 * sig:
                    heading, src = math.atan2(dv, du), "motion"
            axis = math.nan
            if h_n[c] > 0 and math.hypot(h_re[c], h_im[c]) >= cfg.min_anisotropy * h_n[c]:
                axis = math.atan2(h_im[c], h_re[c]) / order
                if order == 4:
                    axis -= math.pi / 4   # the 4th harmonic points at the corners
            dets.append(Detection(u=u, v=v, t_us=int(t_end_us), n_events=int(n), n_pixels=int(npx[c]),
                                  du=du, dv=dv, speed_sigma=sig, heading=heading, heading_source=src,
                                  radius=radius, t_vel_us=int(t_ref_us) + int(round(tm * 1e6)),
                                  shape_axis=axis, shape_order=order,
                                  t_act_us=int(t_ref_us) + int(round(t_eval * 1e6))))
        return dets

    # -- one robot, several clusters (issue 19) --------------------------------
    def _group_clusters(self, k, tm, xm, ym, mom, onf, hints):
        """Group id per cluster and, per group, the index of its hint (-1: none).

        With predictions (``hints``, px): every cluster whose event centroid lies within one
        chassis side of a prediction (a robot's parts lie within half its diagonal of its centre,
        plus the prediction's error) joins its nearest prediction's group; two predictions are
        never one group. The rest (a new robot's first windows, an edge just out of reach) pair
        up as a leading and a trailing edge (:meth:`_edge_pair`), best pairs first: two free
        clusters make a new group; a free cluster joins a prediction's group that holds one
        cluster only."""
        length = self.chassis_px
        grp = np.full(k, -1, dtype=np.int64)
        group_hint: list[int] = []
        if hints is not None and len(hints):
            d = np.hypot(xm[:, None] - hints[None, :, 0], ym[:, None] - hints[None, :, 1])
            near = np.argmin(d, axis=1)
            ok = d[np.arange(k), near] <= length
            hint_group: dict[int, int] = {}
            for c in np.nonzero(ok)[0].tolist():
                h = int(near[c])
                g = hint_group.get(h)
                if g is None:
                    g = hint_group[h] = len(group_hint)
                    group_hint.append(h)
                grp[c] = g
        size = np.bincount(grp[grp >= 0], minlength=max(1, len(group_hint)))
        # candidates: free clusters and the lone clusters of predictions' groups
        pool = np.nonzero((grp < 0) | ((grp >= 0) & (size[np.maximum(grp, 0)] == 1)))[0]
        if pool.size >= 2 and (grp[pool] < 0).any():
            px, py = xm[pool], ym[pool]
            d = np.hypot(px[:, None] - px[None, :], py[:, None] - py[None, :])
            ia, ib = np.nonzero(np.triu(d <= 1.5 * length, 1))
            cand = []
            for a, b in zip(pool[ia].tolist(), pool[ib].tolist()):
                if grp[a] >= 0 and grp[b] >= 0:
                    continue   # two predictions are two robots
                score = self._edge_pair(a, b, tm, xm, ym, mom, onf)
                if score is not None:
                    cand.append((score, a, b))
            cand.sort()
            used = set()
            for _, a, b in cand:
                if a in used or b in used:
                    continue
                used.update((a, b))
                if grp[a] < 0 and grp[b] < 0:
                    grp[a] = grp[b] = len(group_hint)
                    group_hint.append(-1)
                elif grp[a] < 0:
                    grp[a] = grp[b]
                else:
                    grp[b] = grp[a]
        for c in np.nonzero(grp < 0)[0].tolist():
            grp[c] = len(group_hint)
            group_hint.append(-1)
        return grp, group_hint

    def _edge_pair(self, a, b, tm, xm, ym, mom, onf):
        """How well clusters ``a`` and ``b`` make the leading and trailing edges of one plain
        shell (smaller is better; None: they do not). The edges of a chassis of length L are
        two bars about L apart (their event centroids are the edges at the mean time), each
        elongated across the line between them (an edge, not a blob), of opposite polarities
        (the shell darker or brighter than the mat at both) unless one is mixed. Event times
        are not used: a sensor's timestamps can skew along a row or column, and a robot that
        starts gives only a short, poorly fitted motion."""
        n, cxt, cyt, ctt, cxx, cyy, cxy = mom
        length = self.chassis_px
        fa, fb = onf[a], onf[b]
        if abs(fa - 0.5) > 0.25 and abs(fb - 0.5) > 0.25 and (fa > 0.5) == (fb > 0.5):
            return None
        dx = xm[a] - xm[b]
        dy = ym[a] - ym[b]
        dd = math.hypot(dx, dy)
        if abs(dd - length) > 0.35 * length:
            return None
        ux, uy = dx / dd, dy / dd
        worst = 0.0
        for c in (a, b):
            v_along = ux * ux * cxx[c] + uy * uy * cyy[c] + 2 * ux * uy * cxy[c]
            v_across = uy * uy * cxx[c] + ux * ux * cyy[c] - 2 * ux * uy * cxy[c]
            if not v_across >= 2.0 * v_along:
                return None
            worst = max(worst, v_along / v_across)
        return abs(dd - length) / length + worst

    def _grouped(self, labels, k, s, pu, pv, cnt, on, st, st2, t_ref_us: int, t_end_us: int,
                 hints) -> list[Detection]:
        """Detections of grouped clusters (``group_edges``), placed by a footprint fit."""
        cfg = self.config
        length = self.chassis_px
        width = self.chassis_px / cfg.chassis_aspect
        n = np.maximum(s[:, 0], 1.0)
        tm = s[:, 1] / n
        xm = s[:, 3] / n
        ym = s[:, 4] / n
        # per cluster centred sums (event-weighted): the within-cluster motion fit
        cxt = s[:, 5] - n * xm * tm
        cyt = s[:, 6] - n * ym * tm
        ctt = np.maximum(s[:, 2] - n * tm * tm, 0.0)
        cxx = np.maximum(s[:, 7] - n * xm * xm, 0.0)
        cyy = np.maximum(s[:, 8] - n * ym * ym, 0.0)
        cxy = s[:, 13] - n * xm * ym
        if on is not None:
            onf = _cluster_on(labels, on, k) / n
        else:
            onf = np.full(k, 0.5)
        h = None if hints is None or not len(hints) else np.asarray(hints, dtype=float).reshape(-1, 2)
        grp, group_hint = self._group_clusters(k, tm, xm, ym, (n, cxt, cyt, ctt, cxx, cyy, cxy), onf, h)
        ng = len(group_hint)
        has_on = on is not None
        # per group sums of its clusters' moments, its pixels and (polarity centroids: a plain
        # shell's OFF and ON edges lie along the motion) their ON events
        gs, gxt, gyt, gtt, gxx, gyy, gxy, parts, glab, npx, on_n, on_x, on_y = _group_sums(
            grp, s, cxt, cyt, ctt, cxx, cyy, cxy, labels, on if has_on else np.zeros(0, np.int64), has_on, pu, pv, ng)
        t_end_rel = (int(t_end_us) - int(t_ref_us)) * 1e-6
        min_speed = cfg.min_speed_mps * self.px_per_m
        gn = np.maximum(gs[:, 0], 1.0)
        gtm = gs[:, 1] / gn
        gvt = np.maximum(gs[:, 2] / gn - gtm * gtm, 0.0)
        bx, by, sig, t_eval, ax, ay, along_axis, moving, vel = _group_axes(
            gs, gn, gtm, gvt, gxt, gyt, gtt, gxx, gyy, gxy, on_n, on_x, on_y, has_on,
            t_end_rel, length, min_speed)
        fit = _outline_extent(glab, pu, pv, cnt, st, st2, ng, ax, ay, vel[:, 0].copy(), vel[:, 1].copy(),
                              t_eval, 4.0 * (length + width), 0.5, 0.02, cfg.edge_flanks)
        order = 4 if 0.8 <= cfg.chassis_aspect <= 1.25 else 2
        h_re, h_im, h_n = _cluster_harmonic(glab, pu, pv, cnt, gs[:, 3] / gn, gs[:, 4] / gn, order, ng)
        min_area = cfg.min_area_chassis * self.chassis_px ** 2
        hint_xy = h if h is not None else np.zeros((0, 2))
        keep, whole, outl, uv, vel_px, heading, axis, radius = _group_poses(
            gs, gn, gtm, gtt, npx, parts, np.asarray(group_hint, dtype=np.int64), hint_xy, fit, bx, by, t_eval,
            ax, ay, along_axis, moving, h_re, h_im, h_n, min_area, length, width, cfg.outline_filled,
            float(self.width), float(self.height), order, cfg.min_anisotropy)
        t_end_us, t_ref_us = int(t_end_us), int(t_ref_us)
        dets = []
        kept = np.nonzero(keep)[0]
        if kept.size == 0:
            return dets
        # the kept groups' values as Python numbers at once (``tolist`` gives what ``float()`` and
        # ``bool()`` of each element give), not ~20 numpy scalar reads per detection
        uv_, vel_, nev_ = uv[kept].tolist(), vel_px[kept].tolist(), gs[kept, 0].tolist()
        npx_, sig_, hd_, rad_ = npx[kept].tolist(), sig[kept].tolist(), heading[kept].tolist(), radius[kept].tolist()
        gtm_, axis_, tev_ = gtm[kept].tolist(), axis[kept].tolist(), t_eval[kept].tolist()
        whole_, parts_, outl_ = whole[kept].tolist(), parts[kept].tolist(), outl[kept].tolist()
        for i in range(kept.size):
            hd = hd_[i]
            dets.append(Detection(u=uv_[i][0], v=uv_[i][1], t_us=t_end_us, n_events=int(nev_[i]),
                                  n_pixels=npx_[i], du=vel_[i][0], dv=vel_[i][1],
                                  speed_sigma=sig_[i], heading=hd,
                                  heading_source="" if math.isnan(hd) else "motion", radius=rad_[i],
                                  t_vel_us=t_ref_us + int(round(gtm_[i] * 1e6)), shape_axis=axis_[i],
                                  shape_order=order, t_act_us=t_ref_us + int(round(tev_[i] * 1e6)),
                                  whole=whole_[i], n_parts=parts_[i], outline=outl_[i]))
        return dets

    def _split(self, labels, k, s, pu, pv, hints):
        """Give each cluster holding >= 2 hints (px) one part per hint (nearest-seed
        assignment refined by two centroid updates). Returns (labels, k)."""
        near = 0.5 * self.chassis_px
        # how far a prediction may lie from a cluster of its robot: half a chassis when the
        # cluster fills the robot; with edge grouping, a cluster may be one edge bar, half a
        # chassis from the centre, plus the prediction's error (a quarter chassis)
        reach = 0.75 * self.chassis_px if self.config.group_edges else near
        hu, hv = hints[:, :1], hints[:, 1:2]
        # hint h near cluster c's box, in the order of h then c (which numbers the new parts)
        box = (s[:, 9] - reach <= hu) & (hu <= s[:, 10] + reach) & (s[:, 11] - reach <= hv) & (hv <= s[:, 12] + reach)
        inside: dict[int, list[int]] = {}
        for h, c in zip(*(a.tolist() for a in np.nonzero(box))):
            inside.setdefault(c, []).append(h)
        if not any(len(hs) >= 2 for hs in inside.values()):
            return labels, k
        # each cluster's pixels in index order, without a pass over all labels per cluster
        by_label = np.argsort(labels, kind="stable")
        first = np.searchsorted(labels[by_label], np.arange(k + 1))
        out = None
        for c, hs in inside.items():
            if len(hs) < 2:
                continue
            sel = by_label[first[c]:first[c + 1]]
            part, n_parts = _split_cluster(pu[sel].astype(float), pv[sel].astype(float), hints[hs], near, reach)
            if n_parts < 2:
                continue
            if out is None:
                out = labels.copy()
            for q in range(1, n_parts):
                out[sel[part == q]] = k
                k += 1
        return (labels if out is None else out), k


@njit(cache=True, nogil=True)
def _split_cluster(x, y, hints, near, reach):
    """One cluster's pixels (x, y px) split between the hints (k, 2) px: the hints with a pixel
    within ``reach`` px are the seeds; unless there are fewer than two, or all lie within
    ``near`` of each other (one robot), each pixel goes to its nearest seed, seeds moved to
    their parts' centroids three times. Returns the part of each pixel and the number of
    parts (seeds), 0 when the cluster is not split. (Sums of integer pixel coordinates are exact, so this equals
    the same steps in numpy, bit for bit.)"""
    n = x.shape[0]
    m = hints.shape[0]
    reach2 = reach * reach
    seeds = np.empty((m, 2))
    ns = 0
    for q in range(m):
        best = np.inf
        for i in range(n):
            dx = x[i] - hints[q, 0]
            dy = y[i] - hints[q, 1]
            d = dx * dx + dy * dy
            if d < best:
                best = d
        if best <= reach2:
            seeds[ns, 0] = hints[q, 0]
            seeds[ns, 1] = hints[q, 1]
            ns += 1
    empty = np.empty(0, dtype=np.int64)
    if ns < 2:
        return empty, 0
    # two robots cannot overlap: seeds closer than half a chassis are one robot
    apart = False
    for a in range(ns):
        for b in range(a + 1, ns):
            dx = seeds[a, 0] - seeds[b, 0]
            dy = seeds[a, 1] - seeds[b, 1]
            if not math.sqrt(dx * dx + dy * dy) < near:
                apart = True
    if not apart:
        return empty, 0
    part = np.zeros(n, dtype=np.int64)
    sx = np.zeros(ns)
    sy = np.zeros(ns)
    cnt = np.zeros(ns, dtype=np.int64)
    for _ in range(3):
        for q in range(ns):
            sx[q] = 0.0
            sy[q] = 0.0
            cnt[q] = 0
        for i in range(n):
            best = np.inf
            bq = 0
            for q in range(ns):
                dx = x[i] - seeds[q, 0]
                dy = y[i] - seeds[q, 1]
                d = dx * dx + dy * dy
                if d < best:
                    best = d
                    bq = q
            part[i] = bq
            sx[bq] += x[i]
            sy[bq] += y[i]
            cnt[bq] += 1
        for q in range(ns):
            if cnt[q] > 0:
                seeds[q, 0] = sx[q] / cnt[q]
                seeds[q, 1] = sy[q] / cnt[q]
    return part, ns


@njit(cache=True, nogil=True)
def _disk_size(eps):
    """Number of integer pixels within eps of a pixel (itself included)."""
    r = int(eps)
    n = 0
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            if dx * dx + dy * dy <= eps * eps:
                n += 1
    return n

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
  velocity and the motion heading.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy.spatial import cKDTree

from tracker.dbscan import dbscan_grid, dbscan_sklearn

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


# --------------------------------------------------------------------------- pixels


@njit(cache=True)
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
        min_area_chassis: least cluster area (active pixels) as a fraction of the chassis area.
        min_speed_mps: speed above which the motion direction gives the heading, m/s.
        backend: DBSCAN backend, ``grid`` (exact, fast) or ``sklearn``.
    """

    chassis_m: float = 0.10
    eps_chassis: float = 0.25
    min_fill: float = 0.12
    noise_false_rate: float = 1e-7
    min_area_chassis: float = 0.12
    min_speed_mps: float = 0.04
    backend: str = "grid"

    def validate(self) -> None:
        for name in ("chassis_m", "eps_chassis", "min_fill", "noise_false_rate", "min_area_chassis"):
            val = getattr(self, name)
            if not (isinstance(val, (int, float)) and val > 0 and math.isfinite(val)):
                raise ValueError(f"detector {name} must be a positive number, got {val!r}")
        if self.backend not in BACKENDS:
            raise ValueError(f"unknown DBSCAN backend {self.backend!r}; choose from {sorted(BACKENDS)}")


def _poisson_quantile(lam: float, tail: float) -> int:
    """Smallest k with P(X >= k) <= tail for X ~ Poisson(lam)."""
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


@njit(cache=True)
def _cluster_moments(ev_label, t, x, y, k):
    """Per cluster sums over events: n, t, t2, x, y, xt, yt, x2, y2, tmax (t relative to t[0])."""
    s = np.zeros((k, 10))
    t0 = t[0] if t.shape[0] else 0
    for i in range(ev_label.shape[0]):
        c = ev_label[i]
        if c < 0:
            continue
        ti = (t[i] - t0) * 1e-6
        xi = float(x[i])
        yi = float(y[i])
        s[c, 0] += 1.0
        s[c, 1] += ti
        s[c, 2] += ti * ti
        s[c, 3] += xi
        s[c, 4] += yi
        s[c, 5] += xi * ti
        s[c, 6] += yi * ti
        s[c, 7] += xi * xi
        s[c, 8] += yi * yi
        if s[c, 0] == 1.0 or ti > s[c, 9]:
            s[c, 9] = ti
    return s


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
        #: last noise density used, active pixels per px^2 (outside robots)
        self.noise_density_: float = 0.0
        #: last minPts used
        self.min_samples_: int = 0

    # -- density threshold ------------------------------------------------
    def _min_samples(self, pu: np.ndarray, pv: np.ndarray) -> int:
        """minPts from the measured noise: trimmed mean of active pixels per cell."""
        cell = max(4, int(round(self.chassis_px)))
        gw = self.width // cell + 1
        gh = self.height // cell + 1
        counts = np.bincount((pv // cell) * gw + pu // cell, minlength=gw * gh).astype(float)
        # cells holding robots are the dense tail: drop the top 10 %
        keep = np.sort(counts)[: max(1, int(0.9 * counts.size))]
        rho = float(keep.mean()) / (cell * cell)
        self.noise_density_ = rho
        floor = int(math.ceil(self.config.min_fill * self._disk))
        noise = _poisson_quantile(rho * self._disk, self.config.noise_false_rate)
        return max(3, floor, noise)

    def detect(self, events: np.ndarray, t_end_us: int, hints: np.ndarray | None = None) -> list[Detection]:
        """Detections in the window ``events`` (sorted by t) ending at ``t_end_us`` (µs).

        ``hints``: optional (k, 2) array of predicted robot positions, px; a cluster that
        holds two or more of them is split between them.
        """
        if events.size == 0:
            return []
        cfg = self.config
        x, y, t = events["x"], events["y"], events["t"]
        pu, pv, count, ev_pix = self._pix(x, y, self.width, self.height)
        ms = self._min_samples(pu, pv)
        self.min_samples_ = ms
        labels = BACKENDS[cfg.backend](pu, pv, self.eps_px, ms)
        k = int(labels.max()) + 1 if labels.size else 0
        if k == 0:
            return []
        min_area = cfg.min_area_chassis * self.chassis_px ** 2
        npx = np.bincount(labels[labels >= 0], minlength=k)
        if hints is not None and len(hints) >= 2:
            labels, k = self._split(labels, k, pu, pv, np.asarray(hints, dtype=float))
            npx = np.bincount(labels[labels >= 0], minlength=k)
        ev_label = labels[ev_pix]
        s = _cluster_moments(ev_label, t, x, y, k)
        t0 = int(t[0])
        t_end_rel = (int(t_end_us) - t0) * 1e-6
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
            if stt <= 1e-12:
                u, v = xm, ym
                du = dv = sig = math.nan
                t_eval = t_end_rel
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
            dets.append(Detection(u=u, v=v, t_us=int(t_end_us), n_events=int(n), n_pixels=int(npx[c]),
                                  du=du, dv=dv, speed_sigma=sig, heading=heading,
                                  heading_source=src, radius=radius, t_vel_us=t0 + int(round(tm * 1e6))))
        return dets

    def _split(self, labels, k, pu, pv, hints):
        """Give each cluster holding >= 2 hints (px) one part per hint (nearest-seed
        assignment refined by two centroid updates)."""
        inside = [[] for _ in range(k)]
        near = 0.5 * self.chassis_px
        clustered = labels >= 0
        if not clustered.any():
            return labels, k
        tree = cKDTree(np.column_stack([pu[clustered], pv[clustered]]))
        d, j = tree.query(hints, distance_upper_bound=near)
        lab_c = labels[clustered]
        for h in range(len(hints)):
            if math.isfinite(d[h]):
                inside[lab_c[j[h]]].append(h)
        labels = labels.copy()
        for c in range(k):
            hs = inside[c]
            if len(hs) < 2:
                continue
            seeds = hints[hs].copy()
            # two robots cannot overlap: seeds closer than half a chassis are one robot
            dd = np.hypot(*(seeds[:, None, :] - seeds[None, :, :]).transpose(2, 0, 1))
            if np.all(dd[np.triu_indices(len(hs), 1)] < 0.5 * self.chassis_px):
                continue
            sel = np.flatnonzero(labels == c)
            pts = np.column_stack([pu[sel], pv[sel]]).astype(float)
            for _ in range(3):
                part = np.argmin(((pts[:, None, :] - seeds[None, :, :]) ** 2).sum(-1), axis=1)
                for q in range(len(seeds)):
                    if np.any(part == q):
                        seeds[q] = pts[part == q].mean(0)
            for q in range(1, len(seeds)):
                labels[sel[part == q]] = k
                k += 1
        return labels, k


@njit(cache=True)
def _disk_size(eps):
    """Number of integer pixels within eps of a pixel (itself included)."""
    r = int(eps)
    n = 0
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            if dx * dx + dy * dy <= eps * eps:
                n += 1
    return n

"""DVS (event camera) pixel model of the ceiling camera looking at the arena.

Per pixel (after v2e, Hu et al. 2021, and ESIM, Rebecq et al. 2018):

* the scene is rendered as irradiance ``I = illumination * reflectance`` (see
  :mod:`simulator.camera`) and converted to log intensity ``L = ln(I + dark_current)``;
* a photoreceptor first-order low-pass on ``L`` whose cutoff scales with the irradiance
  (``cutoff_hz * (I + dark_current)``, at least ``min_cutoff_hz``): dark shells and dim
  light respond slower, smearing the trailing edge;
* a memorised level per pixel; when the low-passed level departs from it by the pixel's
  ON or OFF threshold (``threshold_on/off`` with per-pixel Gaussian mismatch
  ``threshold_sigma``) the pixel fires one event per threshold crossed, with timestamps
  interpolated linearly inside the internal time step (µs); the memory advances by one
  threshold per crossing, and crossings within the refractory period after the pixel's
  last event are lost (the pixel is held in reset, as in v2e);
* the light reaching a pixel falls off towards the sensor's corners: lens vignetting
  (``cos^n`` off the optical axis) times the ceiling lamps' fall-off over the mats;
* background activity: Poisson events at ``noise_rate_hz`` per pixel on average with uniform
  times over the whole sensor, more in dark pixels (shot noise), leak events (ON, at a rate
  proportional to the pixel's light), plus a few hot pixels firing at ``hot_rate_hz``;
  labelled noise. These are drawn statistically, not through the pixel memories.

Performance: only pixels near robots change, so the model runs only inside regions of
interest (the dilated union of each robot's footprint over the last few photoreceptor time
constants); the memory of every other pixel stays as it is. Inside them a pixel at rest
(low-pass settled, no event owed) is skipped unless a robot that moved this step covers
it. The ROI model gives the events of the full-frame model (tested). With ``flicker_hz > 0`` the
whole sensor changes and the whole frame is simulated (slow; not real time).

Robots are ray-traced per pixel as stacked boxes (blade, treads, shell; see
:func:`simulator.camera.robot_body`) through the pinhole camera: parallax and self-occlusion
come out of the geometry (see :func:`_reflectance`).
Sensor frame: x = column u, y = row v, px; timestamps in µs of the sensor clock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from arena.events import EVENT_DTYPE
from simulator.camera import ILLUMINATION, CeilingCamera, robot_appearance
from simulator.world import RobotSpec, check_bool, check_number

#: Default background-activity rate per pixel by lighting level, Hz (more in the dark).
NOISE_RATE_HZ = {"full": 0.5, "dimmed": 1.0, "dark": 2.0}


@dataclass
class DvsParams:
    """Parameters of the pixel model (defaults are typical of a Prophesee Gen4 / v2e).

    Attributes:
        threshold_on, threshold_off: nominal contrast thresholds, ln units.
        threshold_sigma: per-pixel threshold mismatch (Gaussian sigma), ln units.
        refractory_us: minimum time between two events of one pixel, µs.
        cutoff_hz: photoreceptor 3 dB cutoff at irradiance 1 (white under full light), Hz.
        min_cutoff_hz: floor of the photoreceptor cutoff, Hz.
        dark_current: irradiance-equivalent dark current (relative), limits dark contrast.
        noise_rate_hz: background activity (shot noise and junction leakage) per pixel
            averaged over the sensor, Hz; None = by lighting (full 0.5, dimmed 1.0, dark 2.0).
        noise_on_fraction: fraction of background events that are ON.
        shot_noise: spread the background activity by brightness: a pixel's rate scales as
            ``(I_mat / I_pixel) ** 0.5`` (clipped to 0.25..4x; darker pixels, e.g. the floor
            around the mats or the vignetted corners, fire more), keeping the mean; False =
            the same rate everywhere.
        leak_rate_hz: leak events (ON, from the reset switch's parasitic photocurrent) per
            pixel at full light on the optical axis, Hz; scales with the pixel's light
            (lighting level x vignetting and lamp fall-off); 0 = off.
        vignetting: exponent n of the lens's relative illumination ``cos(theta) ** n`` (theta
            off the optical axis; 4 = ideal lens, real lenses 2-4); 0 = off.
        lamp_falloff: fraction by which the ceiling lights are dimmer at the mat corners than
            at the arena centre (quadratic in the distance); 0 = off.
        hot_pixels: number of hot pixels; hot_rate_hz: their event rate, Hz.
        step_us: internal time step, µs (<= 1000, i.e. >= 1 kHz).
        trace_every: the scene (each pixel's reflectance through the robots' 3-D bodies and
            shadows) is ray-traced every ``trace_every`` steps and held in between, as an
            emulator fed by a 500 Hz render would be (2: a robot at full speed moves 0.9 mm,
            0.2 px, in 2 ms); the photoreceptor, thresholds and event times run every step.
            1 = traced every step. The trace is the simulator's largest cost.
        flicker_hz: ceiling light flicker (0 = off, 100 or 120 typical), Hz; at most half
            the internal rate (``0.5e6 / step_us``: 500 Hz at the default step).
        flicker_depth: relative modulation depth of the flicker.
    """

    threshold_on: float = 0.25
    threshold_off: float = 0.25
    threshold_sigma: float = 0.03
    refractory_us: int = 500
    cutoff_hz: float = 400.0
    min_cutoff_hz: float = 5.0
    dark_current: float = 0.003
    noise_rate_hz: float | None = None
    noise_on_fraction: float = 0.5
    shot_noise: bool = True
    leak_rate_hz: float = 0.15
    vignetting: float = 2.0
    lamp_falloff: float = 0.10
    hot_pixels: int = 5
    hot_rate_hz: float = 50.0
    step_us: int = 1000
    trace_every: int = 2
    flicker_hz: float = 0.0
    flicker_depth: float = 0.2

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Raise ValueError naming the parameter and its allowed values when one has the wrong
        type (a string, NaN, an infinity, ...) or is out of range. Run on construction (and by
        the sensor, for fields changed since)."""
        own = "DvsParams"
        for name in ("threshold_on", "threshold_off"):
            check_number(own, name, getattr(self, name), 0, lo_open=True, unit="(ln units)")
        check_number(own, "threshold_sigma", self.threshold_sigma, 0, unit="(ln units)")
        check_number(own, "refractory_us", self.refractory_us, 0, integer=True, unit="µs")
        check_number(own, "cutoff_hz", self.cutoff_hz, 0, lo_open=True, unit="Hz")
        check_number(own, "min_cutoff_hz", self.min_cutoff_hz, 0, lo_open=True, unit="Hz")
        check_number(own, "dark_current", self.dark_current, 0, unit="(relative irradiance)")
        check_number(own, "noise_rate_hz", self.noise_rate_hz, 0, unit="Hz",
                     none="by lighting: full 0.5, dimmed 1.0, dark 2.0")
        check_number(own, "noise_on_fraction", self.noise_on_fraction, 0.0, 1.0)
        check_bool(own, "shot_noise", self.shot_noise)
        check_number(own, "leak_rate_hz", self.leak_rate_hz, 0, unit="Hz")
        check_number(own, "vignetting", self.vignetting, 0, 8, unit="(cos exponent)")
        check_number(own, "lamp_falloff", self.lamp_falloff, 0, 0.8, hi_open=True)
        check_number(own, "hot_pixels", self.hot_pixels, 0, integer=True)
        check_number(own, "hot_rate_hz", self.hot_rate_hz, 0, unit="Hz")
        check_number(own, "step_us", self.step_us, 1, 1000, integer=True, unit="µs (internal rate >= 1 kHz)")
        check_number(own, "trace_every", self.trace_every, 1, 10, integer=True, unit="steps")
        # sampled once a step: a flicker beyond half the internal rate would alias to a false one
        check_number(own, "flicker_hz", self.flicker_hz, 0, 0.5e6 / self.step_us,
                     unit=f"Hz (at most half the internal rate, 1e6/step_us = {1e6 / self.step_us:g} Hz)")
        check_number(own, "flicker_depth", self.flicker_depth, 0, 1, hi_open=True)


@njit(cache=True, inline="always")
def _clamp01(x):
    return min(max(x, 0.0), 1.0)


@njit(cache=True, inline="always", error_model="numpy")
def _cover(x, y, x0, x1, y0, y1, ipix):
    """Area fraction of a pixel (side ``1 / ipix``, centred at x, y) inside the rectangle."""
    return (_clamp01(min(x - x0, x1 - x) * ipix + 0.5)
            * _clamp01(min(y - y0, y1 - y) * ipix + 0.5))


@njit(cache=True, inline="always", error_model="numpy")
def _reflectance(u, v, ax, ay, bg, state, rp, bodies, markers, members, n_members, pix_m,
                 inv_h, flat, scr):
    """Reflectance seen by pixel (u, v): background with the robots of ``members`` on top.

    Per robot, the pixel's ray (from the lens through the point ``(ax, ay)`` where it meets
    the mats; in the robot frame it moves by ``(nadir - point) / camera_height`` per metre
    of height) is intersected with the body's boxes: each box covers the pixel where the
    ray passes through it, seen on its top face or (3-D body) on a wall; boxes are composited
    front to back by the height where the ray enters them (the highest surface hit is seen),
    with area-weighted coverage at their silhouettes (no aliasing). What lies below is
    darkened by the contact shadow.
    """
    x = ax[v, u]
    y = ay[v, u]
    refl = bg[v, u]
    for j in range(n_members):
        i = members[j]
        dx = x - state[i, 0]
        dy = y - state[i, 1]
        c = state[i, 2]
        s = state[i, 3]
        bx = c * dx + s * dy
        by = -s * dx + c * dy
        if bx < state[i, 7] or bx > state[i, 8] or by < state[i, 9] or by > state[i, 10]:
            continue        # outside what the robot (its parallax hull, shadow) can touch
        rx = (state[i, 4] - bx) * inv_h
        ry = (state[i, 5] - by) * inv_h
        hp = 0.5 * pix_m
        if rp[i, 6] <= 0.0:
            # the ray meets the shell top's interior (past its rim, the front window and the
            # area-weighted edge): the full trace below gives exactly the shell's top there
            zt = bodies[i, 0, 4]
            tx = bx + rx * zt
            ty = by + ry * zt
            mr = hp + rp[i, 5]
            if (tx >= bodies[i, 0, 0] + mr and tx <= bodies[i, 0, 1] - (hp + rp[i, 4])
                    and ty >= bodies[i, 0, 2] + mr and ty <= bodies[i, 0, 3] - mr):
                refl = bodies[i, 0, 5]
                continue
        # does the ray pass beside every box (on one side of their union from the mats up to
        # the top of the highest)? Then the boxes below leave it as it is (no box is hit)
        zt = state[i, 15]
        tx = bx + rx * zt
        ty = by + ry * zt
        beside = (max(bx, tx) < state[i, 11] - hp or min(bx, tx) > state[i, 12] + hp
                  or max(by, ty) < state[i, 13] - hp or min(by, ty) > state[i, 14] + hp)
        hl = rp[i, 0]
        hw = rp[i, 1]
        sw = rp[i, 8]
        if sw > 0.0:        # contact shadow on the mat (and whatever else lies below)
            ox = max(abs(bx) - hl, 0.0)
            oy = max(abs(by) - hw, 0.0)
            if ox < sw and oy < sw:
                d = math.sqrt(ox * ox + oy * oy)
                if d < sw:
                    q = 1.0 - d / sw
                    refl *= 1.0 - rp[i, 7] * q * q
        if beside:
            continue
        nb = int(rp[i, 11])
        ipix = 1.0 / pix_m
        irx = 1.0 / rx if rx != 0.0 else 0.0
        iry = 1.0 / ry if ry != 0.0 else 0.0
        k = 0
        for q in range(nb):
            x0 = bodies[i, q, 0]
            x1 = bodies[i, q, 1]
            y0 = bodies[i, q, 2]
            y1 = bodies[i, q, 3]
            zt = bodies[i, q, 4]
            tx = bx + rx * zt       # the ray at the box's top
            ty = by + ry * zt
            if ((tx < x0 - hp and bx < x0 - hp) or (tx > x1 + hp and bx > x1 + hp)
                    or (ty < y0 - hp and by < y0 - hp) or (ty > y1 + hp and by > y1 + hp)):
                continue        # the ray passes beside the box from its top to the mats
            ct = _cover(tx, ty, x0, x1, y0, y1, ipix)
            if flat or ct >= 1.0:
                # (3-D: the ray is inside the box at its top, so it enters there)
                alpha = ct
                ze = zt
            else:
                cf = _cover(bx, by, x0, x1, y0, y1, ipix)      # at the foot
                alpha = max(ct, cf)
                ze = zt if ct >= cf else 0.0
                if alpha < 1.0:
                    # between top and foot (a wall's corner): where the x and y margins meet
                    zm = 0.5 * zt
                    xm = bx + rx * zm
                    ym = by + ry * zm
                    if xm - x0 < x1 - xm:
                        mx0, mx1 = bx - x0, rx
                    else:
                        mx0, mx1 = x1 - bx, -rx
                    if ym - y0 < y1 - ym:
                        my0, my1 = by - y0, ry
                    else:
                        my0, my1 = y1 - by, -ry
                    den = mx1 - my1
                    if den != 0.0:
                        zc = min(max((my0 - mx0) / den, 0.0), zt)
                        cc = _cover(bx + rx * zc, by + ry * zc, x0, x1, y0, y1, ipix)
                        if cc > alpha:
                            alpha = cc
                            ze = zc
                # where the centre ray enters the box (slabs): its height orders the boxes
                lo = 0.0
                hi = zt
                if rx != 0.0:
                    za = (x0 - bx) * irx
                    zb = (x1 - bx) * irx
                    lo = max(lo, min(za, zb))
                    hi = min(hi, max(za, zb))
                elif bx < x0 or bx > x1:
                    hi = -1.0
                if ry != 0.0:
                    za = (y0 - by) * iry
                    zb = (y1 - by) * iry
                    lo = max(lo, min(za, zb))
                    hi = min(hi, max(za, zb))
                elif by < y0 or by > y1:
                    hi = -1.0
                if lo <= hi:
                    ze = hi
            if alpha <= 0.0:
                continue
            top = bodies[i, q, 5]
            if q == 0 and ct > 0.0:     # the shell top: rim, front sensor window, marker
                mh = rp[i, 6]
                if mh > 0.0 and abs(tx) < mh and abs(ty) < mh:
                    row = min(int((mh - tx) / (2.0 * mh) * 6.0), 5)
                    col = min(int((mh - ty) / (2.0 * mh) * 6.0), 5)
                    top = markers[i, row, col]
                else:
                    rim = rp[i, 5]
                    if rim > 0.0:
                        e = min(tx - x0, min(y1 - ty, ty - y0))
                        top += (rp[i, 9] - top) * _clamp01((rim - e) * ipix + 0.5)
                    win = rp[i, 4]
                    if win > 0.0:
                        top += (rp[i, 10] - top) * _clamp01((tx - (x1 - win)) * ipix + 0.5)
            wall = bodies[i, q, 6]
            if alpha > ct and bodies[i, q, 7] != wall and bx + rx * ze > x1 - 5e-4:
                wall = bodies[i, q, 7]      # the front wall
            # insert by entry height, highest first
            p = k
            while p > 0 and scr[p - 1, 0] < ze:
                scr[p, 0] = scr[p - 1, 0]
                scr[p, 1] = scr[p - 1, 1]
                scr[p, 2] = scr[p - 1, 2]
                p -= 1
            scr[p, 0] = ze
            scr[p, 1] = alpha
            scr[p, 2] = ct * top + (alpha - ct) * wall
            k += 1
            if ct >= 1.0:
                break       # its top covers the pixel, and the boxes below are no higher
        acc = 0.0
        trans = 1.0
        for p in range(k):
            acc += trans * scr[p, 2]
            trans *= 1.0 - scr[p, 1]
        refl = acc + trans * refl
    return refl


@njit(cache=True, nogil=True, error_model="numpy")
def _robot_hull(state, r, rp, inv_h, pix_m, hom, quad):
    """The robot-frame rectangle (``state[r, 7:11]``: x0, x1, y0, y1) of mat points whose
    pixel ray can meet robot r or its contact shadow, and its corners in pixels (``quad[r]``).

    A ray through mat point ``b`` is at ``b + (nadir - b) * z / h`` at height z: it meets the
    body (inside the footprint, below its top ``zt``) only if ``b`` lies in the hull of the
    footprint and the footprint scaled about the nadir by ``h / (h - zt)``; the contact shadow
    reaches ``rp[r, 8]`` beyond the footprint; one pixel more for the area-weighted edges.
    """
    hl = rp[r, 0]
    hw = rp[r, 1]
    k = rp[r, 2] * inv_h
    sw = rp[r, 8]
    nx = state[r, 4]
    ny = state[r, 5]
    state[r, 7] = min(-hl - sw, (-hl - nx * k) / (1.0 - k)) - pix_m
    state[r, 8] = max(hl + sw, (hl - nx * k) / (1.0 - k)) + pix_m
    state[r, 9] = min(-hw - sw, (-hw - ny * k) / (1.0 - k)) - pix_m
    state[r, 10] = max(hw + sw, (hw - ny * k) / (1.0 - k)) + pix_m
    c = state[r, 2]
    s = state[r, 3]
    for q in range(4):
        bx = state[r, 7] if q == 0 or q == 3 else state[r, 8]
        by = state[r, 9] if q < 2 else state[r, 10]
        xa = state[r, 0] + c * bx - s * by
        ya = state[r, 1] + s * bx + c * by
        w_ = hom[2, 0] * xa + hom[2, 1] * ya + hom[2, 2]
        quad[r, q, 0] = (hom[0, 0] * xa + hom[0, 1] * ya + hom[0, 2]) / w_
        quad[r, q, 1] = (hom[1, 0] * xa + hom[1, 1] * ya + hom[1, 2]) / w_


@njit(cache=True, inline="always", error_model="numpy")
def _row_span(quad, r, v):
    """Columns (lo, hi) of row ``v`` inside the convex quadrilateral ``quad[r]`` (corners in
    order) widened by a pixel; lo > hi when the row misses it."""
    y0 = v - 1.0
    y1 = v + 1.0
    umin = 1e18
    umax = -1e18
    for e in range(4):
        pu = quad[r, e, 0]
        pv = quad[r, e, 1]
        qu = quad[r, (e + 1) % 4, 0]
        qv = quad[r, (e + 1) % 4, 1]
        # clip the edge to the band y0 <= v <= y1
        t0 = 0.0
        t1 = 1.0
        dv = qv - pv
        if dv != 0.0:
            ta = (y0 - pv) / dv
            tb = (y1 - pv) / dv
            t0 = max(t0, min(ta, tb))
            t1 = min(t1, max(ta, tb))
        elif pv < y0 or pv > y1:
            continue
        if t0 <= t1:
            ua = pu + (qu - pu) * t0
            ub = pu + (qu - pu) * t1
            umin = min(umin, min(ua, ub))
            umax = max(umax, max(ua, ub))
    if umin > umax:
        return 1, 0
    return int(math.floor(umin)) - 1, int(math.ceil(umax)) + 1


@njit(cache=True, nogil=True)
def _alias_table(w):
    """Vose's alias table of the weights ``w`` (n,): draw ``i`` uniform in 0..n-1, keep it
    with probability ``prob[i]``, else take ``alias[i]``; gives i with probability w_i / sum."""
    n = w.shape[0]
    prob = np.ones(n, dtype=np.float32)
    alias = np.arange(n).astype(np.int64)
    total = 0.0
    for i in range(n):
        total += w[i]
    if total <= 0.0:
        return prob, alias
    q = np.empty(n)
    small = np.empty(n, dtype=np.int64)
    large = np.empty(n, dtype=np.int64)
    ns = 0
    nl = 0
    for i in range(n):
        q[i] = w[i] * n / total
        if q[i] < 1.0:
            small[ns] = i
            ns += 1
        else:
            large[nl] = i
            nl += 1
    while ns > 0 and nl > 0:
        ns -= 1
        a = small[ns]
        g = large[nl - 1]
        prob[a] = q[a]
        alias[a] = g
        q[g] = (q[g] + q[a]) - 1.0
        if q[g] < 1.0:
            nl -= 1
            small[ns] = g
            ns += 1
    return prob, alias


@njit(cache=True, nogil=True)
def _merge_boxes(boxes, owner):
    """Merge overlapping boxes in place; ``owner[i]`` = index of the box robot i ends in.
    Returns the number of boxes left (compacted to the front)."""
    n = boxes.shape[0]
    alive = np.ones(n, dtype=np.bool_)
    for i in range(n):
        owner[i] = i
    changed = True
    while changed:
        changed = False
        for i in range(n):
            if not alive[i]:
                continue
            for j in range(i + 1, n):
                if not alive[j]:
                    continue
                if (boxes[i, 0] < boxes[j, 2] and boxes[j, 0] < boxes[i, 2]
                        and boxes[i, 1] < boxes[j, 3] and boxes[j, 1] < boxes[i, 3]):
                    boxes[i, 0] = min(boxes[i, 0], boxes[j, 0])
                    boxes[i, 1] = min(boxes[i, 1], boxes[j, 1])
                    boxes[i, 2] = max(boxes[i, 2], boxes[j, 2])
                    boxes[i, 3] = max(boxes[i, 3], boxes[j, 3])
                    alive[j] = False
                    for r in range(n):
                        if owner[r] == j:
                            owner[r] = i
                    changed = True
    m = 0
    remap = np.empty(n, dtype=np.int64)     # every owner is alive: all read entries get set
    for i in range(n):
        if alive[i]:
            for c in range(4):      # element-wise: a row assignment compiles numpy's
                boxes[m, c] = boxes[i, c]   # broadcasting and its error text (~3 s)
            remap[i] = m
            m += 1
    for r in range(n):
        owner[r] = remap[owner[r]]
    return m


# fast-math without nnan/ninf (NaN checks stay valid): reciprocal and contracted arithmetic
@njit(cache=True, nogil=True, error_model="numpy", fastmath={"nsz", "arcp", "contract", "afn", "reassoc"})
def _dvs_block(poses, t_seq, t_start, cur_boxes, hist, hist_i, full_frame, width, height,
               hom, nadir_x, nadir_y, cam_h, flat, gain, ax, ay, bg, bg_log, rp, bodies, markers,
               pix_m, illum_seq, dark, cutoff_hz,
               min_cutoff_hz, lmem, llp, thr_on, thr_off, t_last, refr_us, max_refr_count,
               init, ox, oy, op, ot, last_refl, last_target, last_alpha, bg_alpha, std_dt_us,
               settled, prev_pose, quad, trace_every):
    """Run the pixel model over the steps ``t_seq`` (µs, increasing, after ``t_start``).

    ``poses`` (k, n, 3) are the robot poses at each step, ``cur_boxes`` (k, n, 4) their
    footprint boxes (px); ``hist`` (n, K, 4) is the ring buffer of recent footprint boxes
    whose union per robot is simulated. Stops early when the output buffers could overflow.
    Returns (steps done, events written, new hist_i).
    """
    k_steps = poses.shape[0]
    n_rob = poses.shape[1]
    K = hist.shape[1]
    cap = ox.shape[0]
    n = np.int64(0)     # not a literal 0: numba would compile _sort_segment once per literal
    state = np.zeros((max(n_rob, 1), 16))
    for r in range(n_rob):      # union of the robot's boxes (robot frame) and their top
        state[r, 11] = 1e9
        state[r, 12] = -1e9
        state[r, 13] = 1e9
        state[r, 14] = -1e9
        for q in range(int(rp[r, 11])):
            state[r, 11] = min(state[r, 11], bodies[r, q, 0])
            state[r, 12] = max(state[r, 12], bodies[r, q, 1])
            state[r, 13] = min(state[r, 13], bodies[r, q, 2])
            state[r, 14] = max(state[r, 14], bodies[r, q, 3])
            state[r, 15] = max(state[r, 15], bodies[r, q, 4])
    near_list = np.zeros(max(n_rob, 1), dtype=np.int64)
    scr = np.zeros((8, 3))
    inv_h = 1.0 / cam_h
    pquad = np.zeros((max(n_rob, 1), 4, 2))
    rspan = np.zeros((max(n_rob, 1), 4), dtype=np.int64)    # this row: near lo, hi, moving lo, hi
    moved = np.zeros(max(n_rob, 1), dtype=np.bool_)
    boxes = np.zeros((max(n_rob, 1), 4), dtype=np.int64)
    owner = np.zeros(max(n_rob, 1), dtype=np.int64)
    members = np.zeros((max(n_rob, 1), max(n_rob, 1)), dtype=np.int64)
    n_members = np.zeros(max(n_rob, 1), dtype=np.int64)
    t_prev = t_start
    done = 0
    static_light = not full_frame
    for s in range(k_steps):
        dt_us = t_seq[s] - t_prev
        for r in range(n_rob):
            moved[r] = (poses[s, r, 0] != prev_pose[r, 0] or poses[s, r, 1] != prev_pose[r, 1]
                        or poses[s, r, 2] != prev_pose[r, 2])
            prev_pose[r, 0] = poses[s, r, 0]
            prev_pose[r, 1] = poses[s, r, 1]
            prev_pose[r, 2] = poses[s, r, 2]
            state[r, 0] = poses[s, r, 0]
            state[r, 1] = poses[s, r, 1]
            state[r, 2] = math.cos(poses[s, r, 2])
            state[r, 3] = math.sin(poses[s, r, 2])
            # the lens's nadir in the robot frame, and how far beyond its footprint a robot
            # can change a pixel: contact shadow, parallax of its top, a pixel
            ex = nadir_x - state[r, 0]
            ey = nadir_y - state[r, 1]
            state[r, 4] = state[r, 2] * ex + state[r, 3] * ey
            state[r, 5] = -state[r, 3] * ex + state[r, 2] * ey
            for c in range(4):      # the previous step's hull (pixels it leaves change too)
                pquad[r, c, 0] = quad[r, c, 0]
                pquad[r, c, 1] = quad[r, c, 1]
            _robot_hull(state, r, rp, inv_h, pix_m, hom, quad)
            if math.isnan(pquad[r, 0, 0]):
                for c in range(4):
                    pquad[r, c, 0] = quad[r, c, 0]
                    pquad[r, c, 1] = quad[r, c, 1]
        if full_frame or init:
            m = 1
            boxes[0, 0] = 0
            boxes[0, 1] = 0
            boxes[0, 2] = width
            boxes[0, 3] = height
            n_members[0] = n_rob
            for r in range(n_rob):
                members[0, r] = r
        else:
            for r in range(n_rob):
                for c in range(4):
                    hist[r, hist_i % K, c] = cur_boxes[s, r, c]
            hist_i += 1
            for r in range(n_rob):
                b0 = hist[r, 0, 0]
                b1 = hist[r, 0, 1]
                b2 = hist[r, 0, 2]
                b3 = hist[r, 0, 3]
                for q in range(1, K):
                    b0 = min(b0, hist[r, q, 0])
                    b1 = min(b1, hist[r, q, 1])
                    b2 = max(b2, hist[r, q, 2])
                    b3 = max(b3, hist[r, q, 3])
                boxes[r, 0] = min(max(b0, 0), width)
                boxes[r, 1] = min(max(b1, 0), height)
                boxes[r, 2] = min(max(b2, 0), width)
                boxes[r, 3] = min(max(b3, 0), height)
            m = _merge_boxes(boxes[:n_rob], owner[:n_rob]) if n_rob > 0 else 0
            n_members[:] = 0
            for r in range(n_rob):
                b = owner[r]
                members[b, n_members[b]] = r
                n_members[b] += 1
        max_per_px = max_refr_count
        if refr_us > 0:
            max_per_px = min(max_refr_count, dt_us // refr_us + 1)
        area = 0
        for b in range(m):
            area += max(boxes[b, 2] - boxes[b, 0], 0) * max(boxes[b, 3] - boxes[b, 1], 0)
        if not init and n + area * max_per_px > cap:
            return done, n, hist_i
        n_step0 = n
        dt_s = dt_us * 1e-6
        std_dt = dt_us == std_dt_us     # the cached low-pass factors are for this step
        illum = illum_seq[s]
        # the scene is ray-traced every trace_every-th step and held in between (static light)
        trace_now = init or trace_every <= 1 or (t_seq[s] // std_dt_us) % trace_every == 0
        for b in range(m):
            mem = members[b]
            nm = n_members[b]
            for v in range(boxes[b, 1], boxes[b, 3]):
                # per robot, the pixels of this row inside its hull (near) and, if it moved,
                # inside its hull now or at the last step (near_moving)
                for j in range(nm):
                    r = mem[j]
                    lo, hi = _row_span(quad, r, v)
                    rspan[r, 0] = lo
                    rspan[r, 1] = hi
                    if moved[r]:
                        lo2, hi2 = _row_span(pquad, r, v)
                        if lo2 <= hi2:
                            lo = min(lo, lo2)
                            hi = max(hi, hi2)
                        rspan[r, 2] = lo
                        rspan[r, 3] = hi
                    else:
                        rspan[r, 2] = 1
                        rspan[r, 3] = 0
                for u in range(boxes[b, 0], boxes[b, 2]):
                    kn = 0              # the robots whose hull holds the pixel
                    near_moving = False  # ... or whose last one does, of a robot that moved
                    for j in range(nm):
                        r = mem[j]
                        if rspan[r, 0] <= u <= rspan[r, 1]:
                            near_list[kn] = r
                            kn += 1
                        if rspan[r, 2] <= u <= rspan[r, 3]:
                            near_moving = True
                    if static_light and not near_moving and settled[v, u] and not init:
                        continue            # nothing changes here: skip the pixel
                    if kn > 0 and static_light and not trace_now and last_refl[v, u] >= 0.0:
                        refl = last_refl[v, u]
                    elif kn > 0:
                        refl = _reflectance(u, v, ax, ay, bg, state, rp, bodies, markers,
                                            near_list, kn, pix_m, inv_h, flat, scr)
                    else:
                        refl = bg[v, u]
                    irr = -1.0      # computed when needed
                    if static_light:
                        # per pixel, the reflectance it saw when last simulated, its log
                        # intensity and low-pass factor (for std_dt; -1 = not yet computed)
                        if refl == last_refl[v, u]:
                            if settled[v, u] and not init:
                                continue    # the same light, settled: nothing can happen
                            target = last_target[v, u]      # e.g. inside a uniform shell
                            a = last_alpha[v, u] if std_dt else -1.0
                        else:
                            if refl == bg[v, u]:
                                target = float(bg_log[v, u])
                                a = bg_alpha[v, u]
                            else:
                                irr = illum * gain[v, u] * refl
                                target = math.log(irr + dark)
                                a = -1.0
                            last_refl[v, u] = refl
                            last_target[v, u] = target
                            last_alpha[v, u] = a
                            if not std_dt:
                                a = -1.0
                    else:
                        irr = illum * gain[v, u] * refl
                        target = math.log(irr + dark)
                        a = -1.0
                    if init:
                        llp[v, u] = target
                        lmem[v, u] = target
                        settled[v, u] = 1
                        continue
                    old = llp[v, u]
                    new = old
                    settled[v, u] = 1
                    if abs(target - old) > 1e-6:    # settled (float32 memory)
                        settled[v, u] = 0
                        if a < 0.0:
                            if irr < 0.0:
                                irr = illum * gain[v, u] * refl
                            f = max(cutoff_hz * (irr + dark), min_cutoff_hz)
                            a = 1.0 - math.exp(-2.0 * math.pi * f * dt_s)
                            if static_light and std_dt:
                                last_alpha[v, u] = a
                        new = old + (target - old) * a
                        llp[v, u] = new
                    ref = lmem[v, u]
                    d_new = new - ref
                    if d_new >= thr_on[v, u]:
                        thr = thr_on[v, u]
                        sign = 1.0
                    elif d_new <= -thr_off[v, u]:
                        thr = thr_off[v, u]
                        sign = -1.0
                    else:
                        continue
                    settled[v, u] = 0       # may still owe events (refractory, per-step cap)
                    d_old = old - ref
                    span = d_new - d_old
                    tl = t_last[v, u]
                    k = 0           # threshold crossings
                    e = 0           # events emitted (crossings inside the refractory period are lost)
                    while e < max_per_px:
                        level = sign * (k + 1) * thr
                        if abs(level) > abs(d_new):
                            break
                        frac = (level - d_old) / span if span != 0.0 else 1.0
                        frac = min(max(frac, 0.0), 1.0)
                        te = t_prev + max(1, int(frac * dt_us + 0.5))
                        k += 1
                        if te - tl >= refr_us:
                            ox[n] = u
                            oy[n] = v
                            op[n] = 1 if sign > 0 else 0
                            ot[n] = te
                            n += 1
                            tl = te
                            e += 1
                    if k > 0:
                        lmem[v, u] = ref + sign * k * thr
                        t_last[v, u] = tl
        if n - n_step0 > 1:
            _sort_segment(ox, oy, op, ot, n_step0, n, t_prev, dt_us)
        t_prev = t_seq[s]
        done += 1
    return done, n, hist_i


@njit(cache=True, nogil=True)
def _sort_segment(ox, oy, op, ot, a, b, t0, span):
    """Sort events a..b-1 of the column buffers by time, stably. Their times lie in
    (t0, t0 + span], so a counting sort over the offsets does it in one pass (no comparison
    sort: numba's argsort would add seconds of compile time)."""
    start = np.zeros(span + 2, dtype=np.int64)
    for i in range(a, b):
        start[ot[i] - t0 + 1] += 1
    for k in range(span + 1):
        start[k + 1] += start[k]
    m = b - a
    tx = np.empty(m, dtype=ox.dtype)
    ty = np.empty(m, dtype=oy.dtype)
    tp = np.empty(m, dtype=op.dtype)
    tt = np.empty(m, dtype=ot.dtype)
    for i in range(a, b):
        k = start[ot[i] - t0]
        start[ot[i] - t0] = k + 1
        tx[k] = ox[i]
        ty[k] = oy[i]
        tp[k] = op[i]
        tt[k] = ot[i]
    for i in range(m):
        ox[a + i] = tx[i]
        oy[a + i] = ty[i]
        op[a + i] = tp[i]
        ot[a + i] = tt[i]


@njit(cache=True, nogil=True)
def _merge(sx, sy, sp, st, nx, ny, np_, nt, out, is_sig):
    """Merge time-sorted signal and noise columns into ``out`` (EVENT_DTYPE) and labels."""
    i = 0
    j = 0
    for k in range(out.shape[0]):
        if j >= nt.shape[0] or (i < st.shape[0] and st[i] <= nt[j]):
            out[k].x = sx[i]
            out[k].y = sy[i]
            out[k].p = sp[i]
            out[k].t = st[i]
            is_sig[k] = True
            i += 1
        else:
            out[k].x = nx[j]
            out[k].y = ny[j]
            out[k].p = np_[j]
            out[k].t = nt[j]
            is_sig[k] = False
            j += 1


class DvsSensor:
    """The event camera: renders the arena and runs the pixel model.

    Args:
        camera: geometry and static scene (:class:`simulator.camera.CeilingCamera`).
        robots: the robots to draw (their footprint, colour and marker).
        lighting: ``"full"``, ``"dimmed"`` or ``"dark"``.
        params: pixel-model parameters (:class:`DvsParams`).
        seed: seed of threshold mismatch, hot pixels and noise.

    Use: ``reset(poses, t_us)`` once, then ``advance(poses_seq, t_seq)`` with the robot
    poses (k, n, 3) (x m, y m, yaw rad, arena frame) at k increasing times ``t_seq`` (µs,
    consecutive ones at most ``params.step_us`` apart); it returns the events of
    ``(t_prev, t_seq[-1]]`` sorted by time and a signal/noise label per event.
    """

    def __init__(self, camera: CeilingCamera, robots: list[RobotSpec], lighting: str = "full",
                 params: DvsParams | None = None, seed: int = 0):
        if lighting not in ILLUMINATION:
            raise ValueError(f"lighting must be one of {tuple(ILLUMINATION)}, got {lighting!r}")
        self.params = params or DvsParams()
        self.params.validate()
        self.camera = camera
        self.lighting = lighting
        self.width, self.height = camera.width, camera.height
        p = self.params
        self.noise_rate_hz = NOISE_RATE_HZ[lighting] if p.noise_rate_hz is None else p.noise_rate_hz
        self._rng = np.random.default_rng(seed)
        rng = self._rng
        h, w = self.height, self.width
        self._thr_on = np.maximum(rng.normal(p.threshold_on, p.threshold_sigma, (h, w)),
                                  0.25 * p.threshold_on).astype(np.float32)
        self._thr_off = np.maximum(rng.normal(p.threshold_off, p.threshold_sigma, (h, w)),
                                   0.25 * p.threshold_off).astype(np.float32)
        self._lmem = np.zeros((h, w), dtype=np.float32)
        self._llp = np.zeros((h, w), dtype=np.float32)
        self._t_last = np.full((h, w), -(10 ** 12), dtype=np.int64)
        # cache of the last non-background reflectance and its log intensity per pixel
        self._last_refl = np.full((h, w), -1.0)
        self._last_target = np.zeros((h, w))
        self._last_alpha = np.zeros((h, w))
        # 1 = pixel at rest (low-pass settled, no event owed): skipped unless a robot moves near
        self._settled = np.ones((h, w), dtype=np.uint8)
        self._prev_pose = np.full((max(len(robots), 1), 3), np.nan)
        # each robot's hull (what it can change: parallax hull of its body, contact shadow)
        # in pixels at the last step: 4 corners (u, v); NaN = none yet
        self._quad = np.full((max(len(robots), 1), 4, 2), np.nan)
        hot = rng.choice(h * w, size=min(p.hot_pixels, h * w), replace=False)
        #: hot pixel addresses (k, 2): u, v
        self.hot_pixels = np.column_stack([hot % w, hot // w]).astype(np.int64)
        self._n = len(robots)
        rp, bodies, markers = robot_appearance(robots, camera.body, camera.shadow,
                                               camera.shell_height_m)
        self._rp, self._bodies, self._markers = rp, bodies, markers
        self._illum0 = ILLUMINATION[lighting]
        #: per-pixel light gain: lens vignetting x lamp fall-off (1 on the axis at the centre)
        self.gain = camera.relative_irradiance(p.vignetting, p.lamp_falloff)
        irr_bg = self._illum0 * self.gain * camera.background
        self._bg_log = np.log(irr_bg + p.dark_current).astype(np.float32)
        # photoreceptor low-pass factor of background pixels for one step of step_us
        f_bg = np.maximum(p.cutoff_hz * (irr_bg + p.dark_current), p.min_cutoff_hz)
        self._bg_alpha = 1.0 - np.exp(-2.0 * np.pi * f_bg * p.step_us * 1e-6)
        self._init_reach(camera, rp, bodies)
        self._init_background(camera)
        self._hist = np.zeros((self._n, self._keep_steps, 4), dtype=np.int64)
        self._hist_i = 0
        self._buf = self._alloc(1 << 16)
        self._ready = False
        #: time of the last update, µs
        self.t_us = 0

    def _init_reach(self, camera: CeilingCamera, rp: np.ndarray, bodies: np.ndarray) -> None:
        """Set how far (px) from its floor centre each robot can change a pixel and how long
        (``keep_s``) a pixel stays simulated after a robot left (part of ``__init__``)."""
        p = self.params
        # ROI: how far (px) from its floor centre a robot can change a pixel (footprint,
        # contact shadow, parallax of its top anywhere on the sensor), and how long a pixel
        # stays simulated after a robot left (4 photoreceptor time constants of the darkest
        # part of a robot, at most 150 ms)
        self._reach_const = rp[:, 8] + camera.pixel_m       # shadow reach + a pixel, m
        self._parallax = rp[:, 2] / (camera.camera_height_m - rp[:, 2])   # top shift / distance
        self._diag = np.hypot(rp[:, 0], rp[:, 1])
        L = camera.arena_m
        on_mats = (camera.ax >= 0) & (camera.ax <= L) & (camera.ay >= 0) & (camera.ay <= L)
        gain_min = float(self.gain[on_mats].min()) if on_mats.any() else float(self.gain.min())
        darkest = float(bodies[:, :, 5][bodies[:, :, 4] > 0].min()) if self._n else 0.04
        tau_max = 1.0 / (2 * math.pi * max(p.min_cutoff_hz, p.cutoff_hz * (
            self._illum0 * gain_min * darkest + p.dark_current)))
        self.keep_s = min(0.15, max(0.02, 4.0 * tau_max))
        self._keep_steps = max(1, int(math.ceil(self.keep_s * 1e6 / p.step_us)))

    def _init_background(self, camera: CeilingCamera) -> None:
        """Set the per-pixel rates of background activity and leak events, and the alias
        table to draw their pixels from (part of ``__init__``)."""
        p = self.params
        h, w = self.height, self.width
        # statistical background: per-pixel rates of background activity (spread by
        # brightness when shot_noise) and of leak events (ON, proportional to the light)
        from simulator.camera import MAT_REFLECTANCE
        if p.shot_noise:
            w_ba = np.clip(np.sqrt(MAT_REFLECTANCE / np.maximum(self.gain * camera.background, 1e-6)),
                           0.25, 4.0)
            w_ba = w_ba / w_ba.mean()
        else:
            w_ba = np.ones((h, w))
        ba = self.noise_rate_hz * w_ba
        leak = p.leak_rate_hz * self._illum0 * self.gain.astype(np.float64)
        total = ba + leak
        #: mean background + leak event rate of the whole sensor, Hz
        self.background_rate_hz = float(total.sum())
        self._noise_cdf = np.cumsum(total.ravel())
        self._noise_p_on = ((p.noise_on_fraction * ba + leak).ravel()
                            / np.maximum(total.ravel(), 1e-300)).astype(np.float32)
        # Walker/Vose alias table of the per-pixel rates: a pixel in O(1) per event (two
        # gathers) instead of a binary search of the cumulative rates (cache misses)
        self._alias_prob, self._alias_idx = _alias_table(total.ravel())

    # ------------------------------------------------------------------ public
    def reset(self, poses: np.ndarray, t_us: int = 0) -> None:
        """Set every pixel's memory to the scene at ``poses`` (n, 3) at ``t_us`` (no events)."""
        poses = self._check_poses(poses)[None]
        self._llp[:] = self._bg_log
        self._lmem[:] = self._bg_log
        self._t_last[:] = -(10 ** 12)
        self._quad[:] = np.nan
        self._hist[:] = self._robot_boxes(poses)[0][:, None, :]
        self._hist_i = 0
        self._kernel(poses, np.array([int(t_us)], np.int64), int(t_us), init=True)
        self.t_us = int(t_us)
        self._ready = True

    def advance(self, poses_seq: np.ndarray, t_seq) -> tuple[np.ndarray, np.ndarray]:
        """Advance through times ``t_seq`` (µs) with robots at ``poses_seq`` (k, n, 3) (or
        one time and (n, 3) poses). Returns ``(events, is_signal)``: an
        :data:`arena.events.EVENT_DTYPE` array of ``(t_prev, t_seq[-1]]`` sorted by ``t``,
        and True for events caused by scene change (False: background activity, hot pixels).
        """
        if not self._ready:
            raise RuntimeError("DvsSensor.reset(poses) must be called before advance()")
        t_seq = np.atleast_1d(np.asarray(t_seq, dtype=np.int64))
        poses_seq = np.asarray(poses_seq, dtype=float).reshape(len(t_seq), self._n, 3)
        steps = np.diff(np.concatenate([[self.t_us], t_seq]))
        if len(t_seq) == 0 or np.any(steps <= 0) or np.any(steps > self.params.step_us):
            raise ValueError(f"times must increase from {self.t_us} µs in steps of 1.."
                             f"{self.params.step_us} µs")
        t0 = self.t_us
        sx, sy, sp, st = self._kernel(poses_seq, t_seq, t0, init=False)
        nx, ny, np_, nt = self._noise(t0, int(t_seq[-1]) - t0)
        self.t_us = int(t_seq[-1])
        ev = np.empty(len(st) + len(nt), dtype=EVENT_DTYPE)
        is_sig = np.empty(len(ev), dtype=bool)
        _merge(sx, sy, sp, st, nx, ny, np_, nt, ev, is_sig)
        return ev, is_sig

    # ------------------------------------------------------------------ internals
    @staticmethod
    def _alloc(cap: int):
        return (np.empty(cap, np.uint16), np.empty(cap, np.uint16),
                np.empty(cap, np.uint8), np.empty(cap, np.int64))

    def _check_poses(self, poses) -> np.ndarray:
        poses = np.asarray(poses, dtype=float)
        if poses.size != 3 * self._n:
            raise ValueError(f"expected poses for {self._n} robots, got shape {poses.shape}")
        return poses.reshape(self._n, 3)

    def _illum(self, t_us: np.ndarray) -> np.ndarray:
        p = self.params
        t = np.asarray(t_us, dtype=float)
        if p.flicker_hz > 0:
            # rectified mains: intensity ripple at flicker_hz
            return self._illum0 * (1.0 + p.flicker_depth * np.sin(2 * math.pi * p.flicker_hz * t * 1e-6))
        return np.full(t.shape, self._illum0)

    def _robot_boxes(self, poses_seq: np.ndarray) -> np.ndarray:
        """Footprint boxes (k, n, 4) (u0, v0, u1, v1; px, end exclusive) of poses (k, n, 3)."""
        k = poses_seq.shape[0]
        if self._n == 0:
            return np.zeros((k, 0, 4), dtype=np.int64)
        uv = self.camera.to_pixels(poses_seq[:, :, :2].reshape(-1, 2)).reshape(k, self._n, 2)
        # how far (px) from its floor centre a robot can change a pixel: its footprint, the
        # contact shadow, the parallax of its top (at its distance from the nadir), a pixel
        d = np.hypot(poses_seq[:, :, 0] - self.camera.nadir[0], poses_seq[:, :, 1] - self.camera.nadir[1])
        reach = self._reach_const + self._parallax * (d + self._diag)
        r = (self._diag + reach) / self.camera.pixel_m * 1.05 + 3.0
        return np.stack([np.floor(uv[..., 0] - r), np.floor(uv[..., 1] - r),
                         np.ceil(uv[..., 0] + r) + 1, np.ceil(uv[..., 1] + r) + 1],
                        axis=-1).astype(np.int64)

    def _kernel(self, poses_seq, t_seq, t0, init) -> tuple[np.ndarray, ...]:
        """Run the pixel kernel; return time-sorted signal event columns (x, y, p, t)."""
        p = self.params
        cur = self._robot_boxes(poses_seq)
        illum = self._illum(t_seq)
        max_count = 16 if p.refractory_us == 0 else p.step_us // p.refractory_us + 1
        full = p.flicker_hz > 0
        out = []
        while True:
            ox, oy, op, ot = self._buf
            done, n, self._hist_i = _dvs_block(
                poses_seq, t_seq, t0, cur, self._hist, self._hist_i, full, self.width,
                self.height, self.camera.H, float(self.camera.nadir[0]), float(self.camera.nadir[1]),
                float(self.camera.camera_height_m), self.camera.body == "flat", self.gain,
                self.camera.ax, self.camera.ay, self.camera.background,
                self._bg_log, self._rp, self._bodies, self._markers, self.camera.pixel_m, illum,
                p.dark_current, p.cutoff_hz, p.min_cutoff_hz, self._lmem, self._llp,
                self._thr_on, self._thr_off, self._t_last, int(p.refractory_us), int(max_count),
                init, ox, oy, op, ot, self._last_refl, self._last_target, self._last_alpha,
                self._bg_alpha, int(p.step_us), self._settled, self._prev_pose, self._quad,
                int(p.trace_every))
            out.append((ox[:n].copy(), oy[:n].copy(), op[:n].copy(), ot[:n].copy()))
            if done == len(t_seq):
                break
            if done == 0:   # one step needs more room than we have: grow
                self._buf = self._alloc(2 * len(ox) if n else max(2 * len(ox), 1 << 20))
                if len(self._buf[0]) > (1 << 27):
                    raise MemoryError("DVS step needs more than 2^27 events of buffer")
            t0 = int(t_seq[done - 1]) if done else t0
            poses_seq, t_seq, cur, illum = poses_seq[done:], t_seq[done:], cur[done:], illum[done:]
        if len(out) == 1:
            return out[0]
        return tuple(np.concatenate([o[c] for o in out]) for c in range(4))

    def _noise(self, t0: int, dt: int) -> tuple[np.ndarray, ...]:
        """Background activity, leak and hot-pixel events in (t0, t0 + dt] µs: time-sorted
        columns (x, y, p, t)."""
        rng = self._rng
        k = int(rng.poisson(self.background_rate_hz * dt * 1e-6))
        npx = len(self._alias_idx)
        if k:
            pix = rng.integers(0, npx, k)
            pix = np.where(rng.random(k, dtype=np.float32) < self._alias_prob[pix], pix,
                           self._alias_idx[pix])
            pol_bg = rng.random(k, dtype=np.float32) < self._noise_p_on[pix]
        else:
            pix, pol_bg = np.zeros(0, np.int64), np.zeros(0, bool)
        hot = self.hot_pixels
        kh = rng.poisson(self.params.hot_rate_hz * dt * 1e-6, len(hot))
        which = np.repeat(np.arange(len(hot)), kh)
        idx = np.concatenate([pix, hot[which, 1] * self.width + hot[which, 0]])
        pol = np.concatenate([pol_bg, rng.integers(0, 2, len(which)).astype(bool)])
        # sort by time with one int64 key (time offset, pixel, polarity): no argsort gathers
        key = rng.integers(0, dt, len(idx)) * (2 * npx) + idx * 2 + pol
        key.sort()
        t = t0 + 1 + key // (2 * npx)
        rem = key % (2 * npx)
        idx = rem >> 1
        pol = (rem & 1).astype(np.uint8)
        return ((idx % self.width).astype(np.uint16), (idx // self.width).astype(np.uint16), pol,
                t.astype(np.int64))

"""The default fleet tracker: Kalman prediction, gating, optimal assignment, life cycle.

Arena frame throughout: metres, m/s, yaw in rad counter-clockwise from +x, times in µs.

- Each track runs a constant-velocity Kalman filter on ``(x, y, vx, vy)``, updated with the
  detection's position (and its velocity when the detector measured one), and a heading
  filter on ``(yaw, yaw_rate)`` fed with the motion heading, which refers to the middle of
  the detection window: the filter predicts it forward to the pose time (no heading lag).
- Detections are assigned to predicted tracks by the Hungarian algorithm
  (``scipy.optimize.linear_sum_assignment``) on Euclidean distance, gated.
- Life cycle: a new track is *tentative* until ``confirm_hits`` detections; a confirmed
  track that misses a detection is *coasting*. An event camera sees only motion, so a
  robot without events has stopped: a coasting track brakes to rest (``stop_tau_s``) and
  stays where it stopped, with its ID, for as long as needed (robots do not vanish). A
  detection closer than one chassis to an existing track never starts a new track (two
  robots cannot overlap), and ``fleet_size`` caps the confirmed tracks.
- Restart: :meth:`FleetTracker.snapshot` gives the fleet as a small JSON-able dict and
  :meth:`FleetTracker.restore` brings it back in a new tracker (the live service writes it to
  a state file every second). Restored tracks keep their IDs and robot names and wait, at
  rest, where they were last seen: a robot that stood still is matched there when it moves;
  one that drove on during the restart is found again when a new track confirms within
  ``reclaim_m`` of it, or within the distance it can have driven since (``max_speed_mps``
  times the time since it was last seen; optimal assignment, nearest first), and takes that
  track over. A restored track that no detection matches within ``lost_s`` (2 s) of the restore
  is lost: no longer predicted, reported or saved (a state file's claim nobody confirmed must not
  be published for the whole run), but kept aside (:attr:`FleetTracker.dormant`) so a robot that
  stood still through the restart and moves off later still gets its ID and name back.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tracker.objects import COASTING, CONFIRMED, TENTATIVE, Observation, TrackedRobot

__all__ = ["FleetTracker", "FleetConfig"]


def linear_sum_assignment(cost: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``scipy.optimize.linear_sum_assignment(cost)``, the solver loaded on the first assignment
    (:func:`_load_lsap`; issue 22: start-up of ``arena track``)."""
    global _lsap
    if _lsap is None:
        _lsap = _load_lsap()
    return _lsap(cost)


_lsap = None


def _load_lsap():
    """scipy's compiled solver, the very function ``scipy.optimize.linear_sum_assignment`` is
    (``scipy/optimize/_lsap*.so``; it needs only numpy), loaded without the ``scipy.optimize``
    package: its ``__init__`` imports all of scipy.optimize (linprog, minimize, scipy.sparse,
    scipy.spatial), ~0.25 s of CPU on the 2-core VM (measured at load ~5), for this one
    function. The module is not left in ``sys.modules``, so a later ``import scipy.optimize``
    loads it its usual way.
    Falls back to the public import when scipy.optimize is already imported, or the file is
    not where scipy keeps it."""
    import sys

    if "scipy.optimize" not in sys.modules:
        try:
            import importlib.machinery
            import importlib.util
            import os

            import scipy

            folder = os.path.join(os.path.dirname(scipy.__file__), "optimize")
            for suffix in importlib.machinery.EXTENSION_SUFFIXES:
                path = os.path.join(folder, "_lsap" + suffix)
                if os.path.isfile(path):
                    spec = importlib.util.spec_from_file_location("scipy.optimize._lsap", path)
                    module = importlib.util.module_from_spec(spec)
                    spec.loader.exec_module(module)
                    if sys.modules.get(spec.name) is module:
                        del sys.modules[spec.name]
                    return module.linear_sum_assignment
        except Exception:  # noqa: BLE001 - any surprise: the public import below
            pass
    from scipy.optimize import linear_sum_assignment as lsa

    return lsa


@dataclass
class FleetConfig:
    """Physical parameters of the fleet tracker.

    Attributes:
        chassis_m: robot footprint side, m: no new track within it of another track.
        gate_m: largest distance between a prediction and its detection, m.
        accel_mps2: process noise, white acceleration 1-sigma, m/s^2.
        pos_sigma_m: detection position noise, m.
        vel_sigma_mps: floor of the detection velocity noise, m/s.
        yaw_accel_radps2: heading process noise, rad/s^2.
        min_speed_mps: speed above which the motion heading is trusted, m/s.
        spin_radius_m: the motion heading is not trusted either while the robot turns faster
            than its speed over this radius (a zero-point turn: the centroid of a spinning
            robot drifts sideways by a few cm/s, in no relation to where it points), m.
        shape_sigma_deg: noise of the shape orientation, degrees (each track also learns how
            far its robot's shape disagrees with the motion heading while it drives, and
            ignores the shape when that disagreement is large: a round shell).
        yaw_reset_updates: consecutive motion headings more than 45 degrees off the filter
            that restart it on the motion heading; after as many windows hidden in another
            robot's cluster (it may have turned there) the first such heading does at once. A
            window without its cluster otherwise means no motion (an event camera sees every
            turn), so it does not: a robot creeping out of a corner or starting from rest, with
            few events and a jumping centroid, flipped by up to 180 degrees when it did.
        yaw_settle_updates: a fresh heading (a new track's first, or one just restarted) is
            restarted after 2 disagreeing motion headings, not ``yaw_reset_updates``, until
            this many have agreed with it: a starting robot's cluster grows unevenly, so its
            first apparent motion can point anywhere (it did 90-180 degrees off for 90 ms).
        confirm_hits: detections needed to confirm a track.
        tentative_max_misses: consecutive misses that delete a tentative track.
        stop_tau_s: time constant with which a coasting track brakes to rest, s.
        fleet_size: most confirmed tracks (None: unlimited).
        lost_s: a coasting track unseen this long may be re-acquired anywhere when the fleet
            is full and a new robot-sized object keeps being detected elsewhere, s.
        reclaim_m: a restored track not seen since the restore is taken over by a new track
            that confirms within this distance of it, m (the robot drove on meanwhile), or
            within how far a robot at ``max_speed_mps`` can have driven since it was last seen.
        max_speed_mps: the fleet's top speed, m/s (Zumo-class robots: 0.46), with a margin.
        sparse_fraction: a detection with fewer events than this fraction of its robot's
            usual count while moving comes from part of the outline only: a robot creeping out
            of a turn on the spot, whose event centroid sits up to 5 cm off the chassis centre.
            Its position then counts less (variance times (fraction * usual / events)^2), its
            velocity is taken as zero (few events, little motion) and its apparent motion gives
            no heading. The usual count follows the
            detections of the moving robot with a ~1 s memory, so a robot that keeps driving
            slowly is soon tracked normally again. 0 turns this off.
        robust_heading: the heading and pose filter for partial clusters, slow spins, lagged
            velocities and stops (see :meth:`_Track._update_yaw`); False restores the previous
            filter (kept for A/B comparisons).
        activity_prior: with ``robust_heading``, a detection whose activity ended before the
            window's end (``Observation.t_act_us``: a robot slowing down or stopped) widens the
            filter's position variance by its velocity times that time, squared: the filter
            drove on since then unseen (an event camera sees every motion), so the detection
            counts more. False: the position prior is trusted as it is (the track overshot a
            stop by ~1 cm and stood there).
    """

    chassis_m: float = 0.10
    gate_m: float = 0.08
    accel_mps2: float = 3.0
    pos_sigma_m: float = 0.004
    vel_sigma_mps: float = 0.03
    yaw_accel_radps2: float = 30.0
    min_speed_mps: float = 0.05
    spin_radius_m: float = 0.08
    shape_sigma_deg: float = 3.0
    yaw_reset_updates: int = 8
    yaw_settle_updates: int = 3
    confirm_hits: int = 3
    tentative_max_misses: int = 3
    stop_tau_s: float = 0.05
    fleet_size: int | None = None
    lost_s: float = 2.0
    reclaim_m: float = 1.0
    max_speed_mps: float = 0.6
    sparse_fraction: float = 0.3
    robust_heading: bool = True
    activity_prior: bool = True

    def validate(self) -> None:
        for name in ("chassis_m", "gate_m", "accel_mps2", "pos_sigma_m", "vel_sigma_mps",
                     "yaw_accel_radps2", "stop_tau_s", "lost_s", "reclaim_m", "spin_radius_m", "max_speed_mps"):
            val = getattr(self, name)
            if not (val > 0 and math.isfinite(val)):
                raise ValueError(f"fleet tracker {name} must be a positive number, got {val!r}")
        if not 0 <= self.sparse_fraction < 1:
            raise ValueError(f"fleet tracker sparse_fraction must be in [0, 1), got {self.sparse_fraction!r}")
        if self.confirm_hits < 1 or self.tentative_max_misses < 1:
            raise ValueError("confirm_hits and tentative_max_misses must be >= 1")
        if self.yaw_reset_updates < 1 or self.yaw_settle_updates < 0:
            raise ValueError("yaw_reset_updates must be >= 1 and yaw_settle_updates >= 0")
        if self.fleet_size is not None and self.fleet_size < 1:
            raise ValueError(f"fleet_size must be >= 1 or None, got {self.fleet_size!r}")


#: activity that ended this long before the window's end means the robot stopped, µs
_REST_US = 30_000


def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


class _Axis:
    """Constant-velocity Kalman filter along one arena axis: position (m), velocity (m/s)."""

    __slots__ = ("p", "v", "pp", "pv", "vv")

    def __init__(self, p: float, v: float, sp: float, sv: float) -> None:
        self.p, self.v = p, v
        self.pp, self.pv, self.vv = sp * sp, 0.0, sv * sv

    def predict(self, dt: float, q: float) -> None:
        self.p += self.v * dt
        self.pp += 2.0 * dt * self.pv + dt * dt * self.vv + q * dt ** 4 / 4.0
        self.pv += dt * self.vv + q * dt ** 3 / 2.0
        self.vv += q * dt * dt

    def update_p(self, z: float, r: float) -> None:
        s = self.pp + r
        kp, kv = self.pp / s, self.pv / s
        y = z - self.p
        self.p += kp * y
        self.v += kv * y
        pp, pv, vv = self.pp, self.pv, self.vv
        self.pp, self.pv, self.vv = pp - kp * pp, pv - kp * pv, vv - kv * pv

    def update_v(self, z: float, r: float) -> None:
        s = self.vv + r
        kp, kv = self.pv / s, self.vv / s
        y = z - self.v
        self.p += kp * y
        self.v += kv * y
        pp, pv, vv = self.pp, self.pv, self.vv
        self.pp, self.pv, self.vv = pp - kp * pv, pv - kp * vv, vv - kv * vv


class _Track:
    """One tracked robot: its filters and life cycle."""

    def __init__(self, tid: int, ob: Observation, cfg: FleetConfig) -> None:
        self.id = tid
        self.cfg = cfg
        known = math.isfinite(ob.vx) and math.isfinite(ob.vy)
        sv = max(cfg.vel_sigma_mps, ob.speed_sigma if math.isfinite(ob.speed_sigma) else 0.0) if known else 0.3
        self.ax = _Axis(ob.x, ob.vx if known else 0.0, cfg.pos_sigma_m, sv)
        self.ay = _Axis(ob.y, ob.vy if known else 0.0, cfg.pos_sigma_m, sv)
        self.t_us = int(ob.t_us)
        # heading filter: yaw (rad), yaw rate (rad/s) and their covariance
        self.yaw = math.nan
        self.yaw_rate = 0.0
        self.py = [1.0, 0.0, 1.0]
        self._disagree = 0
        self._agreed = 0           # motion headings that agreed since the last heading reset
        self._yaw_candidate = math.nan  # a first motion heading waiting for a second to agree
        # variance of the shape orientation about the motion heading, rad^2 (learnt)
        self._shape_var = math.radians(cfg.shape_sigma_deg) ** 2
        self.state = TENTATIVE
        self.age = 0
        self.hits = 1
        self.misses = 0
        self.hidden = 0             # windows spent hidden in another robot's cluster since last seen
        self.n_usual = 0.0          # events in this robot's detections while it moves (running mean)
        self.last_seen_us = int(ob.t_us)
        self.u, self.v, self.n_events = ob.u, ob.v, ob.n_events
        self.robot: str | None = None
        #: restored from a snapshot and not seen since
        self.restored = False
        #: sensor time of the first update after the restore, µs (None: not restored, or not yet)
        self.restored_at_us: int | None = None
        self._at_rest = False       # the robot stopped inside its last window
        self._rest_rate = 0.0       # yaw rate just before it stopped, rad/s
        self._seen: tuple[float, float, float] | None = None  # x, y, yaw after the last detection
        self._lost = True           # the heading may be on a wrong branch of the shape (see _update_yaw_robust)
        self._branch = 0            # consecutive motion headings a multiple of 90 degrees off, on the shape
        if cfg.robust_heading:
            self._update_yaw_robust(ob)
        else:
            self._update_yaw(ob)
        self._seen = (self.ax.p, self.ay.p, self.yaw)

    @property
    def xy(self) -> tuple[float, float]:
        return self.ax.p, self.ay.p

    def predicted(self, t_us: int) -> tuple[float, float]:
        dt = max(0.0, (int(t_us) - self.t_us) * 1e-6)
        return self.ax.p + self.ax.v * dt, self.ay.p + self.ay.v * dt

    # -- motion ----------------------------------------------------------
    def predict(self, t_us: int) -> None:
        dt = (int(t_us) - self.t_us) * 1e-6
        if dt <= 0:
            return
        q = self.cfg.accel_mps2 ** 2
        if self.cfg.robust_heading and not math.isnan(self.yaw) and self.yaw_rate:
            # coordinated turn: a tracked robot drives along its heading, so its velocity turns
            # with it (a constant-velocity model carries a track on a circle outwards)
            c, s = math.cos(self.yaw_rate * dt), math.sin(self.yaw_rate * dt)
            self.ax.v, self.ay.v = c * self.ax.v - s * self.ay.v, s * self.ax.v + c * self.ay.v
        self.ax.predict(dt, q)
        self.ay.predict(dt, q)
        if not math.isnan(self.yaw):
            self.yaw = _wrap(self.yaw + self.yaw_rate * dt)
            a, b, c = self.py
            qy = self.cfg.yaw_accel_radps2 ** 2
            self.py = [a + 2 * dt * b + dt * dt * c + qy * dt ** 4 / 4, b + dt * c + qy * dt ** 3 / 2,
                       c + qy * dt * dt]
        self.t_us = int(t_us)

    def coast(self, t_us: int, moving: bool = False) -> None:
        """No detection: the robot is at rest (braking to rest), or, when ``moving`` (hidden in
        another robot's cluster), it keeps its velocity."""
        if not moving and self.cfg.robust_heading and self._seen is not None:
            # no events: no motion since the last window (an event camera sees every motion).
            # The robot is where its last events were, with the heading it had then; nothing
            # is extrapolated through the stop (braking on from there left it 2-4 cm and
            # 8-10 degrees past where it stopped, for as long as it stood)
            self.ax.p, self.ay.p, yaw = self._seen
            self.ax.v = self.ay.v = 0.0
            if not math.isnan(yaw):
                self.yaw = yaw
            self.yaw_rate = 0.0
        elif not moving:
            dt = (int(t_us) - self.last_seen_us) * 1e-6
            decay = math.exp(-max(dt, 0.0) / self.cfg.stop_tau_s)
            self.ax.v *= decay
            self.ay.v *= decay
            self.yaw_rate *= decay
        self.misses += 1
        self.hidden += bool(moving)
        self.n_events = 0
        if self.state != TENTATIVE:
            self.state = COASTING

    def update(self, ob: Observation) -> None:
        cfg = self.cfg
        r = cfg.pos_sigma_m ** 2
        sparse = 0 < ob.n_events < cfg.sparse_fraction * self.n_usual
        if sparse:   # part of the outline: its centroid is off; little motion
            r *= (cfg.sparse_fraction * self.n_usual / ob.n_events) ** 2
        if cfg.activity_prior and cfg.robust_heading and ob.t_act_us is not None and ob.t_us > ob.t_act_us:
            # no events since the activity ended: the filter's motion since then is unseen (an
            # event camera sees every motion), so its position may be off by up to that motion
            tau = (ob.t_us - ob.t_act_us) * 1e-6
            self.ax.pp += (self.ax.v * tau) ** 2
            self.ay.pp += (self.ay.v * tau) ** 2
        self.ax.update_p(ob.x, r)
        self.ay.update_p(ob.y, r)
        at_rest = ob.t_act_us is not None and ob.t_us - ob.t_act_us > _REST_US
        if sparse or (at_rest and cfg.robust_heading):
            # few events, little motion; or no events since the activity ended: at rest
            self.ax.update_v(0.0, cfg.vel_sigma_mps ** 2)
            self.ay.update_v(0.0, cfg.vel_sigma_mps ** 2)
        elif math.isfinite(ob.vx) and math.isfinite(ob.vy):
            sv = max(cfg.vel_sigma_mps, ob.speed_sigma if math.isfinite(ob.speed_sigma) else 0.0)
            vx, vy = ob.vx, ob.vy
            if cfg.robust_heading and ob.t_vel_us is not None and not math.isnan(self.yaw):
                # the window's velocity is its chord's direction at the mean event time: turned
                # on to the window's end at the yaw rate (on a 30 cm circle at 46 cm/s it
                # pointed ~4 degrees outwards, and the filter carried the track out)
                ang = self.yaw_rate * (ob.t_us - ob.t_vel_us) * 1e-6
                c, s_ = math.cos(ang), math.sin(ang)
                vx, vy = c * vx - s_ * vy, s_ * vx + c * vy
            self.ax.update_v(vx, sv * sv)
            self.ay.update_v(vy, sv * sv)
        if ob.n_events > 0 and math.isfinite(ob.vx) and math.hypot(ob.vx, ob.vy) > cfg.min_speed_mps:
            self.n_usual += 0.01 * (ob.n_events - self.n_usual) if self.n_usual else ob.n_events
        if cfg.robust_heading:
            self._update_yaw_robust(ob, sparse)
        else:
            self._update_yaw(ob, sparse)
        self._seen = (self.ax.p, self.ay.p, self.yaw)
        self.hits += 1
        self.misses = 0
        self.hidden = 0
        self.last_seen_us = int(ob.t_us)
        self.u, self.v, self.n_events = ob.u, ob.v, ob.n_events
        self.restored = False
        if self.state == TENTATIVE and self.hits >= cfg.confirm_hits:
            self.state = CONFIRMED
        elif self.state == COASTING:
            self.state = CONFIRMED

    def _rest_reference(self, ob: Observation) -> int:
        """The time the window's measurements refer to: its end, or the end of its activity when
        the robot stopped inside it (no events for a while before the end). On the first such
        window the heading the filter carried on at its yaw rate since then is taken back."""
        at_rest = ob.t_act_us is not None and ob.t_us - ob.t_act_us > _REST_US
        if at_rest:
            if not self._at_rest and not math.isnan(self.yaw):
                self.yaw = _wrap(self.yaw - self.yaw_rate * (ob.t_us - ob.t_act_us) * 1e-6)
                self._rest_rate = self.yaw_rate
            self.yaw_rate = self._rest_rate
        self._at_rest = at_rest
        return ob.t_act_us if at_rest else ob.t_us

    def _update_yaw(self, ob: Observation, sparse: bool = False) -> None:
        """Heading filter. Two measurements, both at the window's mean event time ``t_vel``
        (the filter's yaw rate carries them to the pose time, so the heading does not lag):
        the motion direction (when moving; it fixes the sign) and the shape orientation
        (modulo the footprint's symmetry, resolved by the prediction; it keeps the heading
        right through zero-point turns, when the motion direction is unknown)."""
        # a robot that stopped inside the window (no events for a while before its end) is at
        # rest since its activity ended, turning included. On the first such window, take back
        # the heading the filter carried on at its yaw rate since then (else a robot braking
        # out of a circle keeps turning in the filter); the window's measurements, at its mean
        # event time, are carried to the stop at the rate before it; the rate is then zero.
        t_ref = self._rest_reference(ob)
        at_rest = self._at_rest
        lag = ((t_ref - ob.t_vel_us) * 1e-6) if ob.t_vel_us is not None else 0.0
        speed = math.hypot(ob.vx, ob.vy) if math.isfinite(ob.vx) else math.inf
        spinning = not math.isnan(self.yaw) and abs(self.yaw_rate) * self.cfg.spin_radius_m > speed
        # a sparse cluster's apparent motion is its centroid sliding, not the robot driving
        if math.isfinite(ob.yaw) and speed >= self.cfg.min_speed_mps and not spinning and not sparse:
            pred = self.yaw - self.yaw_rate * lag
            if math.isnan(self.yaw):
                # the first heading needs a clear motion, twice in about the same direction (a
                # starting robot's cluster grows unevenly and its apparent motion can point
                # anywhere): until then the heading is reported unknown, not wrong
                if speed >= 2.0 * self.cfg.min_speed_mps:
                    if math.isfinite(self._yaw_candidate) and abs(_wrap(ob.yaw - self._yaw_candidate)) < math.radians(45):
                        self._yaw_reset(ob.yaw)
                    else:
                        self._yaw_candidate = ob.yaw
            elif abs(_wrap(ob.yaw - pred)) > math.radians(45):
                # motion disagrees with the filter: an outlier, or the filter is on a wrong
                # branch when it persists, or the robot turned while hidden in another's cluster
                self._disagree += 1
                limit = self.cfg.yaw_reset_updates if self._agreed >= self.cfg.yaw_settle_updates else 2
                if (self._disagree >= limit or self.hidden >= self.cfg.yaw_reset_updates
                        or self.restored):   # restored from a snapshot: it may have moved meanwhile
                    self._yaw_reset(ob.yaw)
            else:
                self._disagree = 0
                self._agreed += 1
                sy = math.radians(4.0) ** 2
                if math.isfinite(ob.speed_sigma) and speed > 0:
                    sy += (ob.speed_sigma / speed) ** 2
                self._yaw_measure(ob.yaw, lag, sy)
        if math.isfinite(ob.shape_yaw) and not math.isnan(self.yaw):
            period = 2.0 * math.pi / max(1, ob.shape_order)
            if math.isfinite(ob.yaw) and speed >= 2.0 * self.cfg.min_speed_mps and abs(self.yaw_rate) < 0.5:
                # learn how well this robot's shape tells its heading: its disagreement with
                # a clear motion heading while driving about straight (a round or odd-shaped
                # shell is then ignored)
                r = (ob.shape_yaw - ob.yaw + period / 2.0) % period - period / 2.0
                # minus the motion heading's own noise; clipped (a turn's mixed window gives
                # outliers), so it grows only when the disagreement persists
                var_motion = math.radians(4.0) ** 2
                if math.isfinite(ob.speed_sigma) and speed > 0:
                    var_motion += (ob.speed_sigma / speed) ** 2
                r2 = max(r * r - var_motion, 0.0)
                self._shape_var += 0.05 * (min(r2, 9.0 * self._shape_var) - self._shape_var)
            pred = self.yaw - self.yaw_rate * lag
            innov = (ob.shape_yaw - pred + period / 2.0) % period - period / 2.0
            # a shape that keeps disagreeing with the motion (rms > period / 8: 11 degrees for
            # a square) is not used at all
            if abs(innov) < period / 3.0 and self._shape_var < (period / 8.0) ** 2:
                self._yaw_measure(pred + innov, lag, math.radians(self.cfg.shape_sigma_deg) ** 2)
        if at_rest:
            self.yaw_rate = 0.0

    def _update_yaw_robust(self, ob: Observation, sparse: bool = False) -> None:
        """Heading filter for partial clusters and slow spins (``FleetConfig.robust_heading``).

        The same two measurements as :meth:`_update_yaw`, at the window's mean event time, but:

        - the shape's spread about the motion heading is learnt only from detections of the
          whole robot (``Observation.whole``; a lone edge bar's 4th harmonic is 45 degrees
          off), with a truncated estimate (a residual beyond 3 sigma does not count), so a
          share of partial clusters cannot inflate it; the shape is then used (variance
          ``shape_sigma_deg`` squared) through spins too, and switched off only when it is no
          better than chance (rms above period / 6: a round shell). Shapes of partial clusters
          are not used; those of sparse ones count less (variance times
          (fraction * usual / events)^2).
        - the yaw rate brakes like a coasting track (``stop_tau_s``) when a window shows neither
          a rotating outline nor a clear motion (a spinning robot's whole outline makes
          events; when they collapse at the end of a spin, it has stopped turning), and is
          bounded by what a differential drive can do (2 * ``max_speed_mps`` / ``chassis_m``).
        - the filter's own yaw rate does not lock it: a clear motion (twice ``min_speed_mps``,
          whole robot) that disagrees counts against the heading even when the filter thinks
          the robot spins on the spot.
        - a spin that ended on a wrong branch of the square's shape (the filter a multiple of
          90 degrees off, both the motion and the shape agreeing modulo 90 degrees) is put on
          the motion's branch after 2 such windows.
        - a stop: the heading is taken back to the end of the activity, as in :meth:`_update_yaw`.
        """
        cfg = self.cfg
        whole = bool(getattr(ob, "whole", True))
        t_ref = self._rest_reference(ob)
        at_rest = self._at_rest
        lag = max(0.0, (t_ref - ob.t_vel_us) * 1e-6) if ob.t_vel_us is not None else 0.0
        speed = math.hypot(ob.vx, ob.vy) if math.isfinite(ob.vx) and math.isfinite(ob.vy) else 0.0
        period = 2.0 * math.pi / max(1, ob.shape_order)
        var_m = math.radians(4.0) ** 2
        if math.isfinite(ob.speed_sigma) and speed > 0:
            var_m += (ob.speed_sigma / speed) ** 2
        shape = ob.shape_yaw if (math.isfinite(ob.shape_yaw) and whole) else math.nan
        # the filter may have lost count of the shape's branches (it can then be a multiple of
        # 90 degrees off) once its heading was uncertain by more than period / 8, or a shape
        # fell outside the gate, since a motion heading last agreed with it
        if not math.isnan(self.yaw) and self.py[0] > (period / 8.0) ** 2:
            self._lost = True
        spinning = not math.isnan(self.yaw) and abs(self.yaw_rate) * cfg.spin_radius_m > speed
        clear = math.isfinite(ob.yaw) and speed >= cfg.min_speed_mps and not sparse
        used = self._yaw_from_motion(ob, clear, lag, speed, period, var_m, shape, spinning, whole)
        if self._yaw_from_shape(ob, lag, speed, period, var_m, shape, spinning, sparse):
            used = True
        self._brake_yaw_rate(ob, used, shape, at_rest)

    def _yaw_from_motion(self, ob: Observation, clear: bool, lag: float, speed: float, period: float,
                         var_m: float, shape: float, spinning: bool, whole: bool) -> bool:
        """The motion-heading half of :meth:`_update_yaw_robust`; returns whether the motion
        heading ``ob.yaw`` (variance ``var_m``) was used.

        A clear motion (``clear``) starts the heading (twice in agreement at twice
        ``min_speed_mps``), is measured when within 45 degrees of the prediction (not while
        spinning), else counts against the heading: after enough disagreements the heading is
        reset to it, or, if the motion and the shape agree modulo ``period`` twice, the heading
        is put on the motion's branch of the shape."""
        cfg = self.cfg
        used = False
        if clear and math.isnan(self.yaw):
            if speed >= 2.0 * cfg.min_speed_mps:
                if math.isfinite(self._yaw_candidate) and abs(_wrap(ob.yaw - self._yaw_candidate)) < math.radians(45):
                    self._yaw_reset(ob.yaw)
                else:
                    self._yaw_candidate = ob.yaw
        elif clear:
            pred = self.yaw - self.yaw_rate * lag
            d = _wrap(ob.yaw - pred)
            if abs(d) <= math.radians(45):
                if not spinning:
                    self._disagree = self._branch = 0
                    self._lost = False
                    self._agreed += 1
                    self._yaw_measure(ob.yaw, lag, var_m)
                    used = True
            elif not spinning or (speed >= 2.0 * cfg.min_speed_mps and whole):
                self._disagree += 1
                k = round(d / period)
                on_branch = (self._lost and math.isfinite(shape) and speed >= 2.0 * cfg.min_speed_mps
                             and abs(d - k * period) < math.radians(30)
                             and abs((shape - ob.yaw + period / 2.0) % period - period / 2.0)
                             < 3.0 * math.sqrt(self._shape_var + var_m))
                self._branch = self._branch + 1 if on_branch else 0
                limit = cfg.yaw_reset_updates if self._agreed >= cfg.yaw_settle_updates else 2
                if self._branch >= 2:
                    # the filter followed the shape on a wrong branch (a spin it lost count
                    # of): the motion tells the branch, the shape keeps the fine heading
                    self.yaw = _wrap(self.yaw + k * period)
                    self.yaw_rate = 0.0
                    self.py = [max(self.py[0], math.radians(10) ** 2), 0.0, 1.0]
                    self._disagree = self._branch = 0
                    self._yaw_measure(ob.yaw, lag, var_m)
                    used = True
                elif self._disagree >= limit or self.hidden >= cfg.yaw_reset_updates or self.restored:
                    self._yaw_reset(ob.yaw)
                    used = True
        return used

    def _yaw_from_shape(self, ob: Observation, lag: float, speed: float, period: float, var_m: float,
                        shape: float, spinning: bool, sparse: bool) -> bool:
        """The shape half of :meth:`_update_yaw_robust`; returns whether the shape heading
        ``shape`` (a whole robot's, NaN otherwise) was used.

        Learns the shape's spread about a clear motion heading while driving about straight
        (truncated at 3 sigma), then measures the shape (modulo ``period``, variance
        ``shape_sigma_deg`` squared, larger if ``sparse``) unless the shape is no better than
        chance; a shape outside the gate marks the branch count as lost."""
        cfg = self.cfg
        used = False
        if math.isfinite(shape) and not math.isnan(self.yaw):
            if (math.isfinite(ob.yaw) and speed >= 2.0 * cfg.min_speed_mps and abs(self.yaw_rate) < 0.5
                    and not sparse and not spinning):
                # learn the shape's spread about a clear motion heading while driving about
                # straight: truncated at 3 sigma (a turn's mixed window, a part of the outline
                # are outliers and do not count); it grows when the spread is really larger
                r = (shape - ob.yaw + period / 2.0) % period - period / 2.0
                if r * r < 9.0 * (self._shape_var + var_m):
                    self._shape_var += 0.05 * (max(r * r - var_m, 0.0) - self._shape_var)
                self._shape_var = max(self._shape_var, math.radians(cfg.shape_sigma_deg) ** 2)
            if self._shape_var < (period / 6.0) ** 2:
                # the shape's own noise (the learnt spread also holds the motion heading's
                # errors beyond their model, and used as the shape's variance it made the
                # filter lag in spins: 2.6 -> 3.9 degrees inside turns on marked squares)
                var_s = math.radians(cfg.shape_sigma_deg) ** 2
                if sparse:
                    var_s *= (cfg.sparse_fraction * self.n_usual / ob.n_events) ** 2
                pred = self.yaw - self.yaw_rate * lag
                innov = (shape - pred + period / 2.0) % period - period / 2.0
                if abs(innov) < period / 3.0:
                    self._yaw_measure(pred + innov, lag, var_s)
                    used = True
                else:
                    self._lost = True
        return used

    def _brake_yaw_rate(self, ob: Observation, used: bool, shape: float, at_rest: bool) -> None:
        """End of :meth:`_update_yaw_robust`: with neither a measurement used nor a rotating
        outline, the yaw rate decays (``stop_tau_s``); it is bounded by what a differential drive
        can do (2 * ``max_speed_mps`` / ``chassis_m``) and zero at rest."""
        cfg = self.cfg
        if not used and not math.isfinite(shape) and not math.isnan(self.yaw):
            # neither a rotating outline nor a clear motion: no evidence that it still turns
            dt = max(0.0, (ob.t_us - self.last_seen_us) * 1e-6)
            self.yaw_rate *= math.exp(-dt / cfg.stop_tau_s)
        w_max = 2.0 * cfg.max_speed_mps / cfg.chassis_m
        self.yaw_rate = min(max(self.yaw_rate, -w_max), w_max)
        if at_rest:
            self.yaw_rate = 0.0

    def _yaw_reset(self, yaw: float) -> None:
        self.yaw = _wrap(yaw)
        self.yaw_rate = 0.0
        self.py = [math.radians(10) ** 2, 0.0, 1.0]
        self._disagree = 0
        self._agreed = 0

    def _yaw_measure(self, yaw_meas: float, lag: float, var: float) -> None:
        """Kalman update with a yaw measured ``lag`` s before the filter time: H = [1, -lag]."""
        a, b, c = self.py
        ha = a - lag * b          # P H^T, first component
        hb = b - lag * c          # P H^T, second component
        s = ha - lag * hb + var   # H P H^T + R
        k0, k1 = ha / s, hb / s
        innov = _wrap(yaw_meas - (self.yaw - self.yaw_rate * lag))
        self.yaw = _wrap(self.yaw + k0 * innov)
        self.yaw_rate += k1 * innov
        self.py = [a - k0 * ha, b - k0 * hb, c - k1 * hb]

    def report(self) -> TrackedRobot:
        return TrackedRobot(track_id=self.id, x=self.ax.p, y=self.ay.p, t_us=self.t_us,
                            vx=self.ax.v, vy=self.ay.v, yaw=self.yaw, state=self.state,
                            age=self.age, hits=self.hits, misses=self.misses, u=self.u, v=self.v,
                            n_events=self.n_events, robot=self.robot)


class FleetTracker:
    """Multi-robot tracker with a small norfair-like API: ``update(observations, t_us)``.

    Args:
        config: :class:`FleetConfig` (physical units).
        report_tentative: also report tentative tracks.
    """

    def __init__(self, config: FleetConfig | None = None, report_tentative: bool = False) -> None:
        self.config = config or FleetConfig()
        self.config.validate()
        self.report_tentative = report_tentative
        self.tracks: list[_Track] = []
        #: restored tracks not seen within ``lost_s`` of the restore: no longer predicted,
        #: reported or saved (a state file's claim nobody confirmed), but still reclaimable
        #: (:meth:`_reclaim`) with their IDs and names by a robot that starts moving near them
        self.dormant: list[_Track] = []
        self._next_id = 1

    def set_robot_name(self, track_id: int, robot: str) -> bool:
        """Give track ``track_id`` the robot name ``robot`` (taken from any other track).
        Returns False when there is no such track."""
        target = next((tr for tr in self.tracks if tr.id == track_id), None)
        if target is None:
            return False
        for tr in self.tracks + self.dormant:
            if tr.robot == robot and tr is not target:
                tr.robot = None
        target.robot = robot
        return True

    #: version of :meth:`snapshot`'s layout
    SNAPSHOT_VERSION = 1

    def snapshot(self) -> dict:
        """The fleet (confirmed and coasting tracks) as a small JSON-able dict, for
        :meth:`restore` after a restart. Arena frame (m, m/s, rad), times in µs."""
        def num(x: float) -> float | None:
            return float(x) if math.isfinite(x) else None

        tracks = [{"id": tr.id, "robot": tr.robot, "x": tr.ax.p, "y": tr.ay.p, "vx": tr.ax.v, "vy": tr.ay.v,
                   "yaw": num(tr.yaw), "u": num(tr.u), "v": num(tr.v), "t_us": tr.t_us,
                   "last_seen_us": tr.last_seen_us, "hits": tr.hits}
                  for tr in self.tracks if tr.state != TENTATIVE]
        return {"v": self.SNAPSHOT_VERSION, "next_id": self._next_id, "tracks": tracks}

    def restore(self, snap: dict) -> list[int]:
        """Bring back the tracks of :meth:`snapshot` (replacing any current ones); returns
        their IDs. They coast at rest where they were last seen, with their IDs, names and
        headings, until a detection matches them (see the module's notes on restarts).
        Raises ValueError for a snapshot this version cannot read."""
        if not isinstance(snap, dict) or snap.get("v") != self.SNAPSHOT_VERSION:
            raise ValueError(f"tracker snapshot version {snap.get('v') if isinstance(snap, dict) else None!r} "
                             f"is not {self.SNAPSHOT_VERSION}")
        tracks = []
        try:
            for rec in snap["tracks"]:
                x, y = float(rec["x"]), float(rec["y"])
                if not (math.isfinite(x) and math.isfinite(y)):
                    raise ValueError(f"track {rec.get('id')!r} has no finite position")
                t = int(rec["t_us"])
                tr = _Track(int(rec["id"]), Observation(x=x, y=y, t_us=t), self.config)
                tr.ax.v = tr.ay.v = 0.0  # at rest until seen: robots do not vanish
                tr.ax.vv = tr.ay.vv = 0.3 ** 2
                yaw = rec.get("yaw")
                if yaw is not None and math.isfinite(float(yaw)):
                    tr._yaw_reset(float(yaw))
                tr.last_seen_us = int(rec.get("last_seen_us", t))
                tr.hits = max(int(rec.get("hits", self.config.confirm_hits)), self.config.confirm_hits)
                tr.robot = rec.get("robot") or None
                tr.u = float(rec["u"]) if rec.get("u") is not None else math.nan
                tr.v = float(rec["v"]) if rec.get("v") is not None else math.nan
                tr.state, tr.misses, tr.n_events, tr.restored = COASTING, 1, 0, True
                tracks.append(tr)
            next_id = max([int(snap.get("next_id", 1))] + [tr.id + 1 for tr in tracks])
        except (KeyError, TypeError) as exc:
            raise ValueError(f"tracker snapshot is malformed: {exc!r}") from None
        if len({tr.id for tr in tracks}) != len(tracks):
            raise ValueError("tracker snapshot has duplicate track IDs")
        self.tracks = sorted(tracks, key=lambda tr: tr.id)
        self.dormant = []
        self._next_id = next_id
        return [tr.id for tr in self.tracks]

    def predictions(self, t_us: int) -> np.ndarray:
        """Predicted (x, y) of the confirmed and coasting tracks at ``t_us``, m: (k, 2)."""
        out = []
        for tr in self.tracks:
            if tr.state == TENTATIVE:
                continue
            out.append(tr.predicted(t_us))
        return np.array(out, dtype=float).reshape(-1, 2)

    def update(self, observations: list[Observation], t_us: int) -> list[TrackedRobot]:
        """Advance to ``t_us`` (µs), assign the observations, return the current tracks."""
        cfg = self.config
        for tr in self.tracks:
            if tr.restored and tr.t_us > t_us:
                # restored from a camera clock that has since restarted: rebase to now
                tr.t_us = tr.last_seen_us = int(t_us)
            if tr.restored and tr.restored_at_us is None:
                tr.restored_at_us = int(t_us)
            tr.predict(t_us)
            tr.age += 1
        # confirmed tracks first, so that they win over tentative ones
        order = sorted(range(len(self.tracks)), key=lambda i: self.tracks[i].state == TENTATIVE)
        tracks = [self.tracks[i] for i in order]
        unmatched_obs = set(range(len(observations)))
        matched_tracks: set[int] = set()
        for group in (False, True):
            idx = [i for i, tr in enumerate(tracks) if (tr.state == TENTATIVE) == group and i not in matched_tracks]
            obs = sorted(unmatched_obs)
            if not idx or not obs:
                continue
            cost = np.empty((len(idx), len(obs)))
            for a, i in enumerate(idx):
                tr = tracks[i]
                gate = cfg.gate_m if tr.misses == 0 else min(cfg.gate_m + 0.5 * cfg.chassis_m * tr.misses,
                                                             1.5 * cfg.chassis_m)
                for b, j in enumerate(obs):
                    d = math.hypot(observations[j].x - tr.ax.p, observations[j].y - tr.ay.p)
                    cost[a, b] = d if d <= gate else 1e6
            rows, cols = linear_sum_assignment(cost)
            for r, c in zip(rows, cols):
                if cost[r, c] >= 1e6:
                    continue
                tracks[idx[r]].update(observations[obs[c]])
                matched_tracks.add(idx[r])
                unmatched_obs.discard(obs[c])
        for i, tr in enumerate(tracks):
            if i not in matched_tracks:
                # hidden in another robot's cluster (crossing, touching): it keeps moving;
                # otherwise no events means no motion: it brakes to rest
                merged = any(math.hypot(o.x - tr.ax.p, o.y - tr.ay.p) < cfg.chassis_m for o in observations)
                tr.coast(t_us, moving=merged)
        # drop tentative tracks that keep missing
        self.tracks = [tr for tr in tracks if not (tr.state == TENTATIVE and tr.misses >= cfg.tentative_max_misses)]
        self._births(observations, sorted(unmatched_obs), t_us)
        self._expire_restored(t_us)
        self._reclaim()
        self._fleet_cap(t_us)
        self.tracks.sort(key=lambda tr: tr.id)
        return [tr.report() for tr in self.tracks if self.report_tentative or tr.state != TENTATIVE]

    def _births(self, observations: list[Observation], idx: list[int], t_us: int) -> None:
        cfg = self.config
        for j in idx:
            ob = observations[j]
            near = any(math.hypot(ob.x - tr.ax.p, ob.y - tr.ay.p) < cfg.chassis_m for tr in self.tracks)
            if near:
                continue
            self.tracks.append(_Track(self._next_id, ob, cfg))
            self._next_id += 1

    def _expire_restored(self, t_us: int) -> None:
        """Restored tracks that no detection matched within ``lost_s`` of the restore are lost
        like a coasting track unseen that long: moved to :attr:`dormant` (not predicted,
        reported or saved; still reclaimable). A state file's tracks are claims: a crafted or
        stale one must not keep phantoms published for the whole run."""
        lost_us = self.config.lost_s * 1e6
        gone = [tr for tr in self.tracks if tr.restored and tr.restored_at_us is not None
                and t_us - tr.restored_at_us >= lost_us]
        if gone:
            self.tracks = [tr for tr in self.tracks if not (tr.restored and tr in gone)]
            self.dormant.extend(gone)

    def _reclaim(self) -> None:
        """Restored tracks not seen since the restore (dormant ones too) are taken over (IDs and
        names kept) by tracks that have just confirmed within ``reclaim_m``, or within the
        distance a robot can have driven since the restored track was last seen: optimal
        assignment, nearest first."""
        waiting = [tr for tr in self.tracks if tr.restored] + self.dormant
        if not waiting:
            return
        fresh = [tr for tr in self.tracks if not tr.restored and tr.state == CONFIRMED
                 and tr.hits == self.config.confirm_hits and tr.robot is None]
        if not fresh:
            return
        cfg = self.config
        cost = np.array([[math.hypot(n.ax.p - o.ax.p, n.ay.p - o.ay.p) for o in waiting] for n in fresh])
        reach = np.array([[max(cfg.reclaim_m, cfg.max_speed_mps * max(0, n.t_us - o.last_seen_us) * 1e-6
                               + cfg.chassis_m) for o in waiting] for n in fresh])
        cost[cost > reach] = 1e6
        for r, c in zip(*linear_sum_assignment(cost)):
            if cost[r, c] >= 1e6:
                continue
            self._take_over(waiting[c], fresh[r])
            self.tracks.remove(fresh[r])
            if waiting[c] in self.dormant:
                self.dormant.remove(waiting[c])
                self.tracks.append(waiting[c])

    @staticmethod
    def _take_over(old: _Track, new: _Track) -> None:
        """``old`` (keeping its ID and name) becomes the robot that ``new`` is tracking."""
        old.ax, old.ay, old.yaw, old.yaw_rate, old.py = new.ax, new.ay, new.yaw, new.yaw_rate, new.py
        old.state, old.misses, old.last_seen_us, old.t_us = CONFIRMED, 0, new.last_seen_us, new.t_us
        old.u, old.v, old.n_events = new.u, new.v, new.n_events
        old._shape_var, old._disagree, old.restored = new._shape_var, new._disagree, False
        old._lost, old._seen = new._lost, new._seen

    def _fleet_cap(self, t_us: int) -> None:
        """With a known fleet size, confirmed tracks beyond it (the newest) are not robots,
        unless an older track has been lost for ``lost_s``: that one (keeping its ID) takes
        over the new track's state (a robot carried elsewhere, or lost and found)."""
        cap = self.config.fleet_size
        if cap is None:
            return
        active = sorted((tr for tr in self.tracks if tr.state != TENTATIVE), key=lambda tr: tr.id)
        for tr in active[cap:]:
            lost = [c for c in active[:cap] if c.state == COASTING
                    and (t_us - c.last_seen_us) * 1e-6 >= self.config.lost_s]
            if lost:
                old = min(lost, key=lambda c: c.last_seen_us)
                self._take_over(old, tr)
            self.tracks.remove(tr)

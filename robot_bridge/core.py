"""The robot's domain core: missions, safety, clocks and logs of one robot (no Zenoh).

:class:`RobotHandle` keeps one robot's :class:`~robot_bridge.link.RobotLink`, unwraps its
telemetry clocks and sequence numbers, logs every sample (``robot_bridge.logs``), runs missions
with ``robot_bridge.control`` on every sample (50-100 Hz), sending SET_MOTORS back, and keeps the
robot safe: a stop, an e-stop (latched until ``clear``), a track outside the geofence, a low
battery, a mission that raises and a link that drops all stop the motors. Who asks (the Zenoh
side, ``robot_bridge.service``, or a test) and where telemetry goes (``publish``) are injected:
this module imports no ``zenoh``.

Stopping goes through the public methods (:meth:`RobotHandle.stop`,
:meth:`RobotHandle.emergency_stop`, :meth:`RobotHandle.stop_now`, :meth:`RobotHandle.hold`,
:meth:`RobotHandle.halt_motors`, :meth:`RobotHandle.halt`): each takes the robot's command lock
for its state changes, so a mission being laid out at the same moment either starts before the
STOP (which then latches "no motors" in the link) or does not start at all.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from arena import robot_protocol as P
from arena.keys import ALL_ROBOTS
from arena.messages import MissionCommand, Telemetry, Track

from .control import MissionRunner, PoseEstimator, TrackWatch, compose, inverse, path_error
from .link import LINK_TIMEOUT_S, LinkDown, RobotLink
from .logs import MissionLog, Sample
from .missions import MissionError, MissionLimits, build_mission, check_mission, mission_speed
from .odometry import Odometry, WheelGeometry

log = logging.getLogger("robot_bridge")


#: Latest start of a mission after its command, s: a fleet starts together a few seconds ahead;
#: a start hours away is a clock mix-up, and the robot would stay "busy" until stopped.
MAX_START_DELAY_S = 600.0
#: Largest |x|, |y| of a given start pose, m: a lab arena is a few metres (a yaw of 7.6e11 rad,
#: found by the fuzz suite, laid out turns that disagreed with the mission's own size check).
MAX_POSE_M = 100.0


class CommandError(Exception):
    """A command that cannot be carried out; ``str()`` is the reply's error text."""


@dataclass
class BridgeOptions:
    """Bridge settings (``[services.bridge]`` of the lab config or flags).

    Attributes:
        arena_size_m: arena rectangle (x, y), m, origin at a mat corner.
        geofence_margin_m: a robot whose track centre comes closer than this to the arena
            edge is stopped (its shell is then at the edge), m.
        low_battery_mv: below this a running mission stops with a warning, mV.
        log_dir: directory of the mission logs.
        track_latency_s: assumed age of a track that carries no timing fields, s.
        track_stale_s: closed loop runs on odometry alone when the newest track is older, s.
        track_delay_s: extra age of track poses beyond their timing fields, s (the tracking
            pipeline's own lag, measured once against ground truth).
        baudrate: serial baud rate (the firmware's 57600).
        estop_repeats: STOP frames sent on an e-stop.
        link_timeout_s: a robot's link is down after this long without a good frame from it, s
            (``--link-timeout``, lab ``link_timeout_s``; see ``robot_bridge.link``).
        track_lost_s: a closed loop whose robot moves this long without a track falls back to
            odometry, and says so (a warning, a ``odometry_fallback`` row in the mission log,
            ``fusion.odometry_fallbacks`` / ``odometry_only_s`` in the manifest), s.
    """

    arena_size_m: tuple[float, float] = (1.83, 1.83)
    geofence_margin_m: float = 0.03
    low_battery_mv: int = 4400
    log_dir: str = "bridge_logs"
    track_latency_s: float = 0.08
    track_stale_s: float = 0.3
    track_delay_s: float = 0.0
    baudrate: int = 57600
    estop_repeats: int = 3
    link_timeout_s: float = LINK_TIMEOUT_S
    track_lost_s: float = 0.5
    max_log_bytes: int = 50 * 1024 * 1024


@dataclass
class RobotSetup:
    """One robot to bridge: its name, serial URL and geometry."""

    name: str
    url: str
    geometry: WheelGeometry = field(default_factory=WheelGeometry)


class RobotHandle:
    """State, missions and safety of one robot (no Zenoh inside; ``publish`` is injected).

    Thread-safe: link frames, tracks and commands arrive on different threads. ``lock`` guards
    the mission state and is held by every control step. Missions are laid out by this robot's
    own worker thread (:meth:`submit`), outside ``lock`` (the layout of a long mission takes tens
    of ms). Stop and e-stop never wait for ``lock``: they bump the stop generation, send STOP
    (which latches "no motors" in the link, see :meth:`RobotLink.stop_motors`) and leave the
    ending of the mission (its log, its path error) to the worker and to the next control step.

    The command lock (``_cmd_lock``, held for a few assignments only) orders stops against mission
    starts: every stopping method (:meth:`stop`, :meth:`emergency_stop`, :meth:`stop_now`,
    :meth:`hold`, :meth:`halt_motors`, :meth:`halt`) bumps the start generation (and latches the
    e-stop) under it before its STOP, and a mission starts (lifting the link's latch) under it only
    if the start generation is still the one taken when its request arrived. So a mission either
    starts before the STOP, which then latches "no motors", or not at all. Callers stop a robot only
    through these methods, never by setting :attr:`estop` or sending STOP themselves.
    """

    #: missions waiting for the worker, at most (more are refused as busy)
    MAX_PENDING_MISSIONS = 4

    def __init__(self, setup: RobotSetup, options: BridgeOptions, publish=None, on_error=None,
                 on_open_error=None):
        self.name = setup.name
        self.geometry = setup.geometry
        self.opt = options
        self.limits = MissionLimits.for_arena(options.arena_size_m)
        self.publish = publish
        self.on_error = on_error or (lambda msg: log.warning("%s", msg))
        self.lock = threading.RLock()
        self.link = RobotLink(setup.url, setup.name, baudrate=options.baudrate,
                              on_frame=self._on_frame, on_state=self._on_link_state,
                              on_open_error=on_open_error, silence_s=options.link_timeout_s)
        self.odometry = Odometry(self.geometry)
        self.estimator = PoseEstimator(stale_s=options.track_stale_s, delay_s=options.track_delay_s)
        self.runner: MissionRunner | None = None
        self.track_watch: TrackWatch | None = None   # the running closed-loop mission's
        #: closed-loop missions that fell back to odometry (lost their track), since the bridge started
        self.odometry_fallbacks = 0
        self.mission_log: MissionLog | None = None
        self.mission_id: str | None = None
        self.start_at_ns: int | None = None
        self.estop = False
        self.last_result: dict = {}
        self._seq = P.Unwrapper(16)
        self._clock = P.Unwrapper(32)
        self._prev: tuple[int, int, int] | None = None   # robot time µs, enc L, R
        self._speeds = (0.0, 0.0)
        self._trace_odo: list[tuple[float, float]] = []
        self._trace_track: list[tuple[float, float]] = []
        self._odo_to_mission = (0.0, 0.0, 0.0)
        self.samples = 0
        self.published = 0
        self.battery_mv = 0
        self.halting = False   # the bridge is closing: STOP was sent, no more motor commands
        self.holding = False   # STOP was sent; no motor commands until stop() ends the mission
        # stop generation: every stop/e-stop bumps it; a running mission whose generation is old is
        # ended by the next control step. Start generation: every stop, e-stop, stop_now, hold and
        # halt bumps it; a mission laid out before one of them never starts
        self._cmd_lock = threading.Lock()   # held only for a few assignments, never while waiting
        self._gen = 0
        self._run_gen = 0
        self._start_gen = 0
        self._stop_reason = ""
        self._stop_event: str | None = None   # a row for the running mission's log when a stop ends it
        self._jobs: queue.Queue = queue.Queue()
        self._pending_missions = 0
        self._worker: threading.Thread | None = None

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        if self._worker is None:
            self._worker = threading.Thread(target=self._work, name=f"missions-{self.name}", daemon=True)
            self._worker.start()
        self.link.start()

    def halt(self) -> None:
        """Stop the robot and close its mission log (the link stays open)."""
        with self._cmd_lock:
            self._gen += 1
            self._start_gen += 1
        with self.lock:
            self._end_mission("interrupted: bridge shut down")
        self._stop_motors()

    def close(self) -> None:
        """Stop the robot, close its mission log, its worker and its link."""
        self.halt()
        self._stop_worker()
        self.link.close()

    def _stop_worker(self) -> None:
        if self._worker is not None:
            self._jobs.put(None)
            self._worker.join(timeout=2.0)
            self._worker = None

    def _work(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            try:
                job()
            except Exception:  # noqa: BLE001 - a job bug must not end the worker
                log.exception("robot %s: command job failed", self.name)

    def submit(self, job, mission: bool = False) -> bool:
        """Run ``job()`` on this robot's worker thread, after the jobs before it. A mission job is
        refused (False) while :attr:`MAX_PENDING_MISSIONS` wait already."""
        if mission:
            with self._cmd_lock:
                if self._pending_missions >= self.MAX_PENDING_MISSIONS:
                    return False
                self._pending_missions += 1

            def counted(job=job):
                try:
                    job()
                finally:
                    with self._cmd_lock:
                        self._pending_missions -= 1
            self._jobs.put(counted)
        else:
            self._jobs.put(job)
        return True

    @property
    def generation(self) -> int:
        """The start generation (see the class docstring): take it when a mission request arrives."""
        return self._start_gen

    # ------------------------------------------------------------------ commands
    def _refuse_if_not_ready(self) -> None:
        """Raise :class:`CommandError` if no mission may start now (lock held)."""
        if self.estop:
            raise CommandError(f"e-stop latched on {self.name}: send 'clear' first")
        if not self.link.connected:
            raise CommandError(f"link down: {self.name}: {self.link.last_error}")
        if self.runner is not None:
            raise CommandError(f"busy: {self.name} runs mission {self.mission_id} ({self.runner.phase}); "
                               "send 'stop' first")
        if 0 < self.battery_mv < self.opt.low_battery_mv:
            raise CommandError(f"low battery: {self.name} at {self.battery_mv} mV "
                               f"(< {self.opt.low_battery_mv} mV): charge it first")

    def check(self, cmd: MissionCommand) -> None:
        """The pure checks of ``cmd`` (its parameters against this arena's limits, its speed):
        cheap whatever the values, so the command callback runs them before queueing anything.
        Raises :class:`CommandError`."""
        params = dict(cmd.params)
        params.pop("start_pose", None)
        if cmd.start_ns is not None and cmd.start_ns - time.time_ns() > MAX_START_DELAY_S * 1e9:
            raise CommandError(f"bad parameter: start_ns is {(cmd.start_ns - time.time_ns()) / 1e9:.3g} s from now; "
                               f"a mission starts at most {MAX_START_DELAY_S:g} s ahead (start_ns is this host's "
                               "wall clock, ns since 1970: a value from another clock?)")
        try:
            mission_speed(cmd.power, cmd.speed_mps, self.geometry.max_speed_mps)
            check_mission(cmd.mission, params, self.limits)
        except MissionError as exc:
            raise CommandError(f"bad parameter: {exc}") from None

    def start_mission(self, cmd: MissionCommand, generation: int | None = None) -> dict:
        """Check, lay out and start ``cmd``; returns reply details or raises :class:`CommandError`.

        The parameters are checked first (:meth:`check`, bounded work), the mission is laid out
        without holding :attr:`lock`, and it starts only if no stop or e-stop came since
        ``generation`` (default: now) -- the start generation (:attr:`generation`) taken when the
        request arrived."""
        gen = self._start_gen if generation is None else generation
        self.check(cmd)
        with self.lock:
            self._refuse_if_not_ready()
            # A standing robot is invisible to an event camera, so any track since the bridge
            # started will do: the fused pose has been carried on by odometry (which does not
            # drift while the robot stands).
            fresh = self.estimator.last_track_t is not None
            params = dict(cmd.params)
            known_start = params.pop("start_pose", None)
            if known_start is not None:
                # the operator (or the demo) knows where the robot stands: x m, y m, yaw rad, arena frame
                if (not isinstance(known_start, list) or len(known_start) != 3
                        or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                                   for v in known_start)):
                    raise CommandError(f"bad parameter: start_pose must be [x_m, y_m, yaw_rad], got {known_start!r}")
                if not (abs(known_start[0]) <= MAX_POSE_M and abs(known_start[1]) <= MAX_POSE_M
                        and abs(known_start[2]) <= 2 * math.pi):
                    raise CommandError(f"bad parameter: start_pose {known_start!r}: x and y within +-{MAX_POSE_M:g} m "
                                       "(the arena frame), yaw_rad within +-2 pi")
                known_start = [float(known_start[0]), float(known_start[1]),
                               math.atan2(math.sin(known_start[2]), math.cos(known_start[2]))]
                if not fresh:
                    self.estimator.set_pose(tuple(known_start))
            if cmd.control == "closed" and not fresh and known_start is None:
                raise CommandError(f"bad parameter: control=closed needs a track of {self.name} on {ALL_ROBOTS} "
                                   "and none came yet (a standing robot gives no events: drive it a little, "
                                   "e.g. a short paper mission), give params start_pose=[x, y, yaw], "
                                   "or use control=paper")
            start = self.estimator.pose()
        # laid out outside the lock: control steps and telemetry go on meanwhile
        try:
            speed = mission_speed(cmd.power, cmd.speed_mps, self.geometry.max_speed_mps)
            mission = build_mission(cmd.mission, params, start, speed, self.limits)
        except MissionError as exc:
            raise CommandError(f"bad parameter: {exc}") from None
        if fresh or known_start is not None:
            self._check_inside(mission)
        runner = MissionRunner(mission, self.geometry, mode=cmd.control, estimator=self.estimator,
                               odometry=self.odometry)
        with self.lock:
            self._refuse_if_not_ready()          # again: things may have changed meanwhile
            with self._cmd_lock:
                if self._start_gen != gen:
                    raise CommandError(f"stopped: a stop or e-stop for {self.name} came after this mission "
                                       "was sent and before it started; send it again")
                self._run_gen = self._gen
                self._stop_event = None
                self.link.allow_motors()
            mission_id = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime()) + f"-{cmd.mission}"
            self.runner = runner
            # tracks from before the mission's start are an earlier mission's (the robot stands until then)
            self.track_watch = (TrackWatch(self.opt.track_lost_s, start_t=max(time.time_ns(), cmd.start_ns or 0) / 1e9)
                                if cmd.control == "closed" else None)
            self.mission_id = mission_id
            self.start_at_ns = cmd.start_ns
            self._trace_odo, self._trace_track = [], []
            # dead reckoning from the start pose, in the mission's (arena) frame
            self._odo_to_mission = compose(start, inverse(self.odometry.pose))
            self.mission_log = MissionLog(
                self.opt.log_dir, self.name, mission_id, max_bytes=self.opt.max_log_bytes,
                manifest={"pattern": cmd.mission, "params": dict(cmd.params), "control": cmd.control,
                          "speed_mps": speed, "start_pose": list(start), "start_ns": cmd.start_ns,
                          "operator": cmd.operator, "url": self.link.url,
                          "geometry": vars(self.geometry),
                          "pose_source_at_start": "track" if fresh else ("given" if known_start else "odometry")})
            log.info("robot %s: mission %s started (%s, %.2f m/s)", self.name, mission_id, cmd.control, speed)
            return {"mission_id": mission_id, "speed_mps": speed, "length_m": round(mission.length_m, 4),
                    "phases": len(mission.segments), "start_pose": [round(v, 4) for v in start]}

    def _check_inside(self, mission) -> None:
        m = self.opt.geofence_margin_m
        sx, sy = self.opt.arena_size_m
        x0, y0, x1, y1 = mission.bounds()
        if x0 < m or y0 < m or x1 > sx - m or y1 > sy - m:
            raise CommandError(f"bad parameter: the {mission.pattern} from ({mission.start[0]:.2f}, "
                               f"{mission.start[1]:.2f}) spans x {x0:.2f}..{x1:.2f} y {y0:.2f}..{y1:.2f} m and "
                               f"leaves the arena (0..{sx}, 0..{sy} m, margin {m} m)")

    def _cancel(self, reason: str, repeat: int = 1, event: str | None = None,
                estop: bool = False) -> tuple[str | None, bool]:
        """Bump the stop and start generations (and latch the e-stop when ``estop``) under the
        command lock, send STOP (latching "no motors" in the link) and have the mission ended by the
        worker (after the jobs queued before) or by the next control step, whichever comes first.
        Never waits for :attr:`lock`. Returns (mission id, STOP sent)."""
        with self._cmd_lock:
            if estop:
                self.estop = True
            self._gen += 1
            self._start_gen += 1
            self._stop_reason = reason
            self._stop_event = event
        sent = self._stop_motors(repeat)
        had = self.mission_id

        def end():
            with self.lock:
                self._end_mission(reason)
                self.holding = False
            self._stop_motors(repeat)
        self.submit(end)
        return had, sent

    def stop(self, reason: str = "stopped by command", event: str | None = None) -> dict:
        """Stop the motors at once; the mission (if any) ends right after (see :meth:`_cancel`),
        with ``event`` (e.g. ``router_lost``) as a row of its log when given."""
        had, _ = self._cancel(reason, event=event)
        return {"stopped_mission": had}

    def stop_now(self, repeat: int = 1, estop: bool = False) -> bool:
        """Send STOP ``repeat`` times now, latching the e-stop first when ``estop``: the first step
        of a stop or e-stop of several robots at once (every robot gets STOP before any mission
        ends); the :meth:`stop` or :meth:`emergency_stop` that follows ends the mission. Under the
        command lock: a mission being laid out meanwhile does not start. Never waits for
        :attr:`lock`. False when the link is down (the robot's 300 ms watchdog stops it)."""
        with self._cmd_lock:
            if estop:
                self.estop = True
            self._start_gen += 1
        return self._stop_motors(repeat)

    def hold(self) -> bool:
        """Send STOP now and command no motors until :meth:`stop` ends the mission: the first
        step of stopping several robots at once (ending a mission writes its log, which takes
        long enough that the last robot of a fleet stopped one by one kept driving). Under the
        command lock, as :meth:`stop_now`."""
        with self._cmd_lock:
            self.holding = True
            self._start_gen += 1
        return self._stop_motors()

    def halt_motors(self) -> bool:
        """The first step of closing the bridge: once no control step is half-way (this waits for
        :attr:`lock`), none commands motors any more; then STOP. :meth:`halt` ends the mission."""
        with self.lock:
            self.halting = True
        with self._cmd_lock:
            self._start_gen += 1
        return self._stop_motors()

    def emergency_stop(self) -> dict:
        """Stop now and latch: no mission starts until :meth:`clear`.

        The latch is set (under the command lock) and STOP sent without taking :attr:`lock` (a
        control step or a mission being laid out cannot delay it, and no SET_MOTORS can follow the
        STOP); the mission ends right after, on the worker or at the next control step."""
        had, sent = self._cancel("e-stop", self.opt.estop_repeats, estop=True)
        return {"stopped_mission": had, "latched": True, "stop_sent": sent}

    def clear(self) -> dict:
        """Lift the e-stop latch."""
        with self._cmd_lock:
            was = self.estop
            self.estop = False
        return {"was_latched": was}

    def set_led(self, rgb) -> dict:
        try:
            msg = P.SetLed(*rgb)
            msg.pack()
        except (TypeError, P.ProtocolError) as exc:
            raise CommandError(f"bad parameter: led needs rgb [r, g, b] 0-255: {exc}") from None
        try:
            self.link.send(msg)
        except LinkDown as exc:
            raise CommandError(str(exc)) from None
        return {"rgb": list(rgb)}

    # ------------------------------------------------------------------ internals
    def _stop_motors(self, repeat: int = 1) -> bool:
        """Send STOP (and latch "no motors" in the link); False when the link is down (the
        robot's 300 ms watchdog stops it)."""
        try:
            self.link.stop_motors(repeat)
            return True
        except LinkDown:
            return False

    def _end_mission(self, status: str, results: dict | None = None) -> None:
        """Close the running mission (lock held)."""
        if self.runner is None:
            return
        with self._cmd_lock:
            event, self._stop_event = self._stop_event, None
        if event is not None and self.mission_log is not None:   # why the telemetry stops here
            self.mission_log.event(time.time_ns(), event, self.runner.phase)
        res = dict(results or {})
        cmd_path = self.runner.mission.path()
        for key, trace in (("path_error_odometry", self._trace_odo), ("path_error_tracks", self._trace_track)):
            if len(trace) >= 2:
                res[key] = path_error(np.array(trace), cmd_path).as_dict()
        res["link"] = self.link.stats.as_dict()
        est = self.estimator
        res["fusion"] = {"tracks_used": est.tracks_used, "tracks_rejected": est.tracks_rejected,
                         "heading_relocks": est.heading_relocks}
        if self.track_watch is not None:
            res["fusion"].update(self.track_watch.as_dict(time.time_ns() / 1e9))
            self.track_watch = None
        if self.mission_log is not None:
            self.mission_log.event(time.time_ns(), status.split(":")[0].replace(" ", "_"), self.runner.phase)
            self.mission_log.close(status, **res)
        self.last_result = {"mission_id": self.mission_id, "status": status, **res}
        if status != "finished":
            log.warning("robot %s: mission %s ended: %s", self.name, self.mission_id, status)
        else:
            log.info("robot %s: mission %s finished", self.name, self.mission_id)
        self.runner = None
        self.mission_log = None
        self.mission_id = None

    def _on_link_state(self, connected: bool, reason: str) -> None:
        if connected:
            return
        with self.lock:
            if self.mission_log is not None:
                self.mission_log.event(time.time_ns(), "link_down", self.runner.phase if self.runner else "")
            self._end_mission(f"aborted: link down ({reason})")

    def on_track(self, track: Track, now_ns: int) -> None:
        """A track of this robot: feed pose fusion, record the trace, check the geofence."""
        if track.edge_publish_ns and track.window_end_us is not None:
            t_pose = track.edge_publish_ns / 1e9 - (track.window_end_us - track.stamp_us) / 1e6
        else:
            t_pose = now_ns / 1e9 - self.opt.track_latency_s
        with self.lock:
            self.estimator.add_track(t_pose, track.x, track.y, track.yaw)
            if self.runner is None:
                return
            self._trace_track.append((track.x, track.y))
            m = self.opt.geofence_margin_m
            sx, sy = self.opt.arena_size_m
            if not (m <= track.x <= sx - m and m <= track.y <= sy - m):
                self.on_error(f"robot {self.name} at ({track.x:.3f}, {track.y:.3f}) m left the geofence: stopped")
                self._end_mission(f"aborted: geofence ({track.x:.3f}, {track.y:.3f}) m")
                self._stop_motors(self.opt.estop_repeats)

    def _on_frame(self, fr: P.Frame, now_ns: int, gap: int) -> None:
        if not isinstance(fr.msg, P.Telemetry):
            return
        tel = fr.msg
        accel, gyro, mag = tel.accel_si, tel.gyro_si, tel.mag_si   # converted once per frame
        with self.lock:
            seq = self._seq(fr.seq)
            t_us = self._clock(fr.time_us)
            if self._prev is not None and t_us > self._prev[0]:
                dt = (t_us - self._prev[0]) / 1e6
                mpc = self.geometry.m_per_count
                self._speeds = ((tel.enc_left - self._prev[1]) * mpc / dt, (tel.enc_right - self._prev[2]) * mpc / dt)
            self._prev = (t_us, tel.enc_left, tel.enc_right)
            self.battery_mv = tel.battery_mv
            if gap and self.mission_log is not None:
                self.mission_log.gap(now_ns, seq - gap, gap, self.runner.phase if self.runner else "")
            phase = None
            if self.runner is not None:
                phase = self._control(tel, now_ns, t_us, gyro[2])
            else:
                self.estimator.add_odometry(now_ns / 1e9, self.odometry.update(
                    tel.enc_left, tel.enc_right, gyro[2], t_us / 1e6))
            if self.mission_log is not None:
                self.mission_log.sample(Sample(now_ns, t_us, seq, tel.enc_left, tel.enc_right, *self._speeds,
                                               accel, gyro, mag, tel.battery_mv,
                                               tel.motor_left, tel.motor_right, phase or ""))
            self.samples += 1
            mission = self.mission_id
        if self.publish is not None:
            msg = Telemetry(robot=self.name, seq=seq, robot_time_us=t_us, host_time_ns=now_ns,
                            enc_left=tel.enc_left, enc_right=tel.enc_right,
                            speed_left=min(100.0, max(-100.0, float(self._speeds[0]))),
                            speed_right=min(100.0, max(-100.0, float(self._speeds[1]))),
                            accel=accel, gyro=gyro, mag=mag, battery_mv=tel.battery_mv,
                            power_left=tel.motor_left, power_right=tel.motor_right, mission=mission, phase=phase)
            self.publish(self.name, msg)
            self.published += 1

    def _watch_track(self, now_ns: int, out) -> None:
        """Closed loop: say so when the robot's track is lost and it runs on odometry (lock held)."""
        watch = self.track_watch
        # a robot being stopped (the bridge closing, a stop for several robots) stands whatever
        # its mission still asks for: the event camera loses it then, and that is no fallback
        stopping = self.halting or self.holding or self._gen != self._run_gen
        moving = (out.target_left_mps != 0.0 or out.target_right_mps != 0.0) and not stopping
        change = watch.update(now_ns / 1e9, self.estimator.last_track_t, moving)
        if change == "lost":
            self.odometry_fallbacks += 1
            self.on_error(f"robot {self.name}: no track of it for {watch.lost_s:g} s while it drives: closed loop "
                          f"on odometry alone (mission {self.mission_id}, {self.runner.phase})")
        elif change == "regained":
            log.info("robot %s: track back after %.2f s on odometry", self.name, watch.odometry_s)
        if change is not None and self.mission_log is not None:
            self.mission_log.event(now_ns, "odometry_fallback" if change == "lost" else "track_regained",
                                   self.runner.phase)

    @property
    def on_odometry(self) -> bool:
        """A closed-loop mission runs on odometry alone now (its track lost)."""
        return self.track_watch is not None and self.track_watch.on_odometry

    def _control(self, tel: P.Telemetry, now_ns: int, t_us: int, gyro_z: float) -> str:
        """One control step of the running mission (lock held); returns the phase.
        ``gyro_z``: the telemetry's yaw rate, rad/s."""
        runner = self.runner
        if self.start_at_ns is not None and now_ns < self.start_at_ns:
            self.estimator.add_odometry(now_ns / 1e9, self.odometry.update(
                tel.enc_left, tel.enc_right, gyro_z, t_us / 1e6))
            return "waiting"
        if self.estop:
            self._end_mission("e-stop")
            self._stop_motors(self.opt.estop_repeats)
            return "e-stop"
        if self._gen != self._run_gen:     # a stop came: end it here if the worker has not yet
            self._end_mission(self._stop_reason or "stopped")
            self._stop_motors()
            return "stopped"
        if 0 < tel.battery_mv < self.opt.low_battery_mv:
            self.on_error(f"robot {self.name}: battery {tel.battery_mv} mV < {self.opt.low_battery_mv} mV: mission stopped")
            self._end_mission(f"aborted: low battery ({tel.battery_mv} mV)")
            self._stop_motors()
            return "low battery"
        try:
            out = runner.update(now_ns / 1e9, tel.enc_left, tel.enc_right, t_robot=t_us / 1e6,
                                gyro_z=gyro_z)
        except Exception as exc:  # noqa: BLE001 - a mission bug must stop the robot, not the bridge
            log.exception("robot %s: mission crashed", self.name)
            self._end_mission(f"failed: mission crashed: {exc!r}")
            self._stop_motors(self.opt.estop_repeats)
            return "crashed"
        self._trace_odo.append(compose(self._odo_to_mission, self.odometry.pose)[:2])
        if self.track_watch is not None and not out.done:
            self._watch_track(now_ns, out)
        if out.done:
            self._end_mission("finished")
            self._stop_motors()
            return "done"
        if self.halting or self.holding or self._gen != self._run_gen:
            return out.phase
        try:
            self.link.set_motors(out.left, out.right)   # refused by the link after a STOP
        except LinkDown:
            pass  # the link-state callback ends the mission
        return out.phase


"""The robot bridge service: serial links <-> Zenoh, missions, safety, logs.

For every robot (from the lab config or ``--robot NAME=URL``) the bridge keeps a
:class:`~robot_bridge.link.RobotLink`, publishes each telemetry sample on
``arena/telemetry/<robot>``, logs it (``robot_bridge.logs``), and runs missions with
``robot_bridge.control`` on every sample (50-100 Hz), sending SET_MOTORS back.

Commands are queries on ``arena/cmd/<robot>/{mission,stop,estop,clear,led}`` (and
``arena/cmd/all/...``; one queryable on ``arena/cmd/**``) answered with
:class:`arena.messages.CommandReply`: ``ok`` or an error starting with one of ``unknown robot``,
``busy``, ``bad parameter``, ``link down``, ``e-stop latched``, ``low battery``. Robots no bridge
serves get no reply at all (several bridges may share a Zenoh network), which the CLI reports as
such. A query whose key is not a command key (wildcards such as ``arena/cmd/**`` or
``arena/cmd/*/stop``, too few or too many parts, an unknown verb) gets an error reply
(``reply.err``) saying what a command key looks like. Tracks from ``arena/robots/*`` feed
closed-loop control and the geofence.

Safety: motors are stopped on exit (also Ctrl-C/SIGTERM), when a mission raises, when a
robot's link drops (and the robot's own 300 ms watchdog stops it anyway), when the Zenoh
router is lost (client mode: every robot gets STOP within ~50 ms of Zenoh seeing the loss),
on e-stop (latched until ``clear``), when a track leaves the geofence, and when the battery
is low. A robot whose link cannot be opened is an error (counted in the status, retried with
backoff).
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from dataclasses import dataclass, field

import numpy as np
import zenoh

from arena.keys import ALL_ROBOTS, COMMAND_VERBS, ROOT, InvalidKey, parse_key, telemetry_key, validate_name
from arena.messages import Command, CommandReply, MessageError, MissionCommand, Telemetry, Track, decode

from . import protocol as P
from .control import MissionRunner, PoseEstimator, compose, inverse, path_error
from .link import LINK_TIMEOUT_S, LinkDown, RobotLink
from .logs import MissionLog, Sample
from .missions import MissionError, MissionLimits, build_mission, check_mission, mission_speed
from .odometry import Odometry, WheelGeometry

log = logging.getLogger("robot_bridge")


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
        # stop generation: every stop/e-stop bumps it; a mission laid out before a stop never starts,
        # and a running mission whose generation is old is ended by the next control step
        self._cmd_lock = threading.Lock()   # held only for a few assignments, never while waiting
        self._gen = 0
        self._run_gen = 0
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
        """The stop generation (see the class docstring): take it when a mission request arrives."""
        return self._gen

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
        try:
            mission_speed(cmd.power, cmd.speed_mps, self.geometry.max_speed_mps)
            check_mission(cmd.mission, params, self.limits)
        except MissionError as exc:
            raise CommandError(f"bad parameter: {exc}") from None

    def start_mission(self, cmd: MissionCommand, generation: int | None = None) -> dict:
        """Check, lay out and start ``cmd``; returns reply details or raises :class:`CommandError`.

        The parameters are checked first (:meth:`check`, bounded work), the mission is laid out
        without holding :attr:`lock`, and it starts only if no stop or e-stop came since
        ``generation`` (default: now) -- the stop generation taken when the request arrived."""
        gen = self._gen if generation is None else generation
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
                if not fresh:
                    self.estimator.set_pose(tuple(float(v) for v in known_start))
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
                if self._gen != gen:
                    raise CommandError(f"stopped: a stop or e-stop for {self.name} came after this mission "
                                       "was sent and before it started; send it again")
                self._run_gen = gen
                self._stop_event = None
                self.link.allow_motors()
            mission_id = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime()) + f"-{cmd.mission}"
            self.runner = runner
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

    def _cancel(self, reason: str, repeat: int = 1, event: str | None = None) -> tuple[str | None, bool]:
        """Bump the stop generation, send STOP (latching "no motors" in the link) and have the
        mission ended by the worker (after the jobs queued before) or by the next control step,
        whichever comes first. Never waits for :attr:`lock`. Returns (mission id, STOP sent)."""
        with self._cmd_lock:
            self._gen += 1
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

    def hold(self) -> bool:
        """Send STOP now and command no motors until :meth:`stop` ends the mission: the first
        step of stopping several robots at once (ending a mission writes its log, which takes
        long enough that the last robot of a fleet stopped one by one kept driving)."""
        self.holding = True
        return self._stop_motors()

    def emergency_stop(self) -> dict:
        """Stop now and latch: no mission starts until :meth:`clear`.

        The latch is set and STOP sent without taking the lock (a control step or a mission
        being laid out cannot delay it, and no SET_MOTORS can follow the STOP); the mission ends
        right after, on the worker or at the next control step."""
        self.estop = True
        had, sent = self._cancel("e-stop", self.opt.estop_repeats)
        return {"stopped_mission": had, "latched": True, "stop_sent": sent}

    def clear(self) -> dict:
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


def _router_lost(session: zenoh.Session) -> bool:
    try:
        return len(list(session.info.routers_zid())) == 0
    except Exception:  # noqa: BLE001 - a closing session
        return True


class Bridge:
    """The Zenoh side: publishers, command queryables, track subscriber, status.

    Args:
        session: an open Zenoh session.
        robots: the robots to bridge.
        options: settings.
        service: an ``arena.service.Service`` for counters (optional).
        watch_router: stop every robot when the session has no router (client mode).
        router_poll_s: how often the router is checked, s (a lost router stops the robots
            within this plus the time Zenoh takes to see the connection close).
    """

    #: the one queryable of the command keys (the key is parsed in :meth:`_on_query`)
    COMMANDS = f"{ROOT}/cmd/**"

    def __init__(self, session: zenoh.Session, robots: list[RobotSetup], options: BridgeOptions | None = None,
                 service=None, watch_router: bool = False, router_poll_s: float = 0.05):
        if not robots:
            raise ValueError("no robots to bridge: give --robot NAME=URL or a lab config with serial_url")
        self.session = session
        self.opt = options or BridgeOptions()
        self.svc = service
        self.watch_router = watch_router
        self.router_poll_s = router_poll_s
        self.router_lost = False
        self.handles: dict[str, RobotHandle] = {}
        self._pubs = {}
        for r in robots:
            validate_name(r.name, "robot name")
            if r.name in self.handles or r.name == "all":
                raise ValueError(f"robot name {r.name!r} used twice or reserved")
            self.handles[r.name] = RobotHandle(r, self.opt, publish=self._publish, on_error=self._error,
                                               on_open_error=self._open_error_handler(r))
            self._pubs[r.name] = session.declare_publisher(telemetry_key(r.name))
        self._decls = []
        self._stop = threading.Event()
        self._closed = False
        self._monitor: threading.Thread | None = None

    def _error(self, msg: str) -> None:
        if self.svc is not None:
            self.svc.error(msg)
        else:
            log.warning("%s", msg)

    def _open_error_handler(self, robot: RobotSetup):
        """Count every failed attempt to open ``robot``'s link; an error (status ``errors`` and
        ``last_error``) each time the reason changes."""
        reported = {"reason": None}

        def on_open_error(reason: str, retry_in_s: float) -> None:
            if self.svc is not None:
                self.svc.count("link_open_failures")
            if reason == reported["reason"]:
                return
            reported["reason"] = reason
            self._error(f"robot {robot.name}: link cannot be opened: {reason}; retrying with backoff "
                        f"(next in {retry_in_s:.2f} s): check the device or URL given for {robot.name} "
                        "(--robot NAME=URL or the lab's serial_url)")

        return on_open_error

    def _publish(self, robot: str, msg: Telemetry) -> None:
        try:
            self._pubs[robot].put(msg.encode())
        except Exception as exc:  # noqa: BLE001 - a closing session must not kill the link thread
            self._error(f"publish telemetry of {robot} failed: {exc}")
            return
        if self.svc is not None:
            self.svc.count("telemetry_out")

    def start(self) -> "Bridge":
        for h in self.handles.values():
            h.start()
        self._decls.append(self.session.declare_queryable(self.COMMANDS, self._on_query))
        self._decls.append(self.session.declare_subscriber(ALL_ROBOTS, self._on_track))
        self._monitor = threading.Thread(target=self._watch, name="bridge-monitor", daemon=True)
        self._monitor.start()
        return self

    def close(self) -> None:
        """Stop every robot, close logs, links and Zenoh declarations (once; later calls return)."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        # Every robot gets STOP first (ending a mission writes its log and scores its path,
        # ~0.4 s each, and robot by robot that left the last one driving for over a second),
        # then the missions end, then the links close side by side (pyserial's socket:// close
        # sleeps 0.3 s "to give the server some time").
        handles = list(self.handles.values())
        for h in handles:
            with h.lock:          # no control step is half-way: the next one sees it and commands nothing
                h.halting = True
            h._stop_motors()
        for h in handles:
            h.halt()
        closers = [threading.Thread(target=h.close, name=f"close-{h.name}", daemon=True) for h in handles]
        for t in closers:
            t.start()
        deadline = time.monotonic() + 3.0   # every robot has had STOP: do not hold up the exit
        for t in closers:
            t.join(timeout=max(0.0, deadline - time.monotonic()))
        slow = [t.name for t in closers if t.is_alive()]
        if slow:
            log.warning("bridge shutdown: %s still closing after 3 s; exiting anyway", ", ".join(slow))
        for d in self._decls:
            try:
                d.undeclare()
            except Exception:  # noqa: BLE001
                pass
        self._decls.clear()
        if self._monitor is not None:
            self._monitor.join(timeout=2.0)

    def __enter__(self) -> "Bridge":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def _watch(self) -> None:
        """Every ``router_poll_s``: stop every robot when the router is lost; every 0.25 s:
        status gauges and state (degraded while a robot's link is down or the router lost)."""
        next_gauges = 0.0
        while not self._stop.wait(self.router_poll_s):
            if self.watch_router:
                lost = _router_lost(self.session)
                if lost and not self.router_lost and not self._stop.is_set():
                    self._stop_all_router_lost()
                self.router_lost = lost
            if self.svc is not None and time.monotonic() >= next_gauges:
                next_gauges = time.monotonic() + 0.25
                self._gauges()

    def _stop_all_router_lost(self) -> None:
        """STOP to every robot first, then end their missions (see :meth:`RobotHandle.hold`)."""
        handles = list(self.handles.values())
        for h in handles:
            h.hold()
        running = [h.name for h in handles if h.runner is not None]
        for h in handles:
            h.stop("aborted: Zenoh router lost", event="router_lost")
        self._error(f"Zenoh router lost: stopped {', '.join(self.handles)}"
                    + (f" (missions of {', '.join(running)} aborted)" if running else "")
                    + "; check the router (`arena router`, --connect) and restart the missions")

    def _gauges(self) -> None:
        down = []
        for name, h in self.handles.items():
            st = h.link.stats
            if not h.link.connected and (st.open_failures or st.disconnects):
                down.append(name)
            self.svc.gauge(f"{name}.link", "up" if h.link.connected else f"down: {h.link.last_error}")
            self.svc.gauge(f"{name}.rtt_ms", round(st.rtt_ms, 2) if st.rtt_ms is not None else -1)
            self.svc.gauge(f"{name}.quality", round(st.quality, 4))
            self.svc.gauge(f"{name}.crc_errors", st.crc_errors)
            self.svc.gauge(f"{name}.clamped", st.clamped)
            self.svc.gauge(f"{name}.missing", st.missing)
            self.svc.gauge(f"{name}.phase", h.runner.phase if h.runner else ("e-stop" if h.estop else "idle"))
            self.svc.gauge(f"{name}.battery_mv", h.battery_mv)
            self.svc.gauge(f"{name}.samples", h.samples)
            self.svc.gauge(f"{name}.published", h.published)
            res = h.last_result
            if res:
                self.svc.gauge(f"{name}.last_mission", f"{res['mission_id']}: {res['status']}")
                for src in ("odometry", "tracks"):
                    err = res.get(f"path_error_{src}")
                    if err:
                        self.svc.gauge(f"{name}.path_error_{src}_cm", round(err["mean_m"] * 100, 2))
        if not self._stop.is_set():
            self.svc.set_state("degraded" if down or self.router_lost else "running")

    def _on_track(self, sample) -> None:
        now = time.time_ns()
        try:
            track = decode(sample.payload.to_bytes())
        except MessageError as exc:
            self._error(f"bad track on {sample.key_expr}: {exc}")
            return
        if not isinstance(track, Track) or track.robot is None:
            return
        h = self.handles.get(track.robot)
        if h is not None:
            h.on_track(track, now)

    def _on_query(self, query) -> None:
        """The command callback: decode and check, then act. Stop, e-stop, clear and LED are
        carried out here (none waits for a robot's lock); a mission that passes the pure checks
        is laid out and started by its robot's worker thread, which then replies (the query is
        answered once every robot it names has replied)."""
        key = str(query.key_expr)
        try:
            robot, verb = parse_cmd_key(key)
        except InvalidKey as exc:
            log.info("refused a query on %s: not a command key", key)
            if self.svc is not None:
                self.svc.count("commands_bad_key")
            try:
                query.reply_err(str(exc))
            except Exception as e:  # noqa: BLE001 - the querier may have gone
                self._error(f"error reply to {key} failed: {e}")
            return
        if robot != "all" and robot not in self.handles:
            return    # another bridge's robot (or nobody's): no reply, see the module docstring
        targets = list(self.handles) if robot == "all" else [robot]
        payload = query.payload.to_bytes() if query.payload is not None else b""
        if verb in ("stop", "estop") and len(targets) > 1:
            for name in targets:   # every robot stops before any mission log is closed
                h = self.handles[name]
                if verb == "estop":
                    h.estop = True
                h._stop_motors(self.opt.estop_repeats if verb == "estop" else 1)
        if verb != "mission":
            for name in targets:
                self._reply(query, self.execute(name, verb, payload))
            return
        try:
            cmd = MissionCommand.decode(payload)
        except MessageError as exc:
            for name in targets:
                self._reply(query, self._refused(name, verb, f"bad parameter: {exc}"))
            return
        pending = _PendingQuery(query, len(targets))
        for name in targets:
            h = self.handles[name]
            try:
                h.check(cmd)
            except CommandError as exc:
                pending.reply(self, self._refused(name, verb, str(exc)))
                continue
            gen = h.generation     # a stop after this moment cancels this mission
            job = (lambda name=name, gen=gen: pending.reply(self, self._mission(name, cmd, gen)))
            if not h.submit(job, mission=True):
                pending.reply(self, self._refused(name, verb, f"busy: {name} has "
                                                              f"{h.MAX_PENDING_MISSIONS} missions waiting to start"))

    def _reply(self, query, reply: CommandReply) -> None:
        try:
            query.reply(query.key_expr, reply.encode())
        except Exception as exc:  # noqa: BLE001 - the querier may have gone
            self._error(f"reply to {reply.verb} for {reply.robot} failed: {exc}")

    def _refused(self, robot: str, verb: str, error: str) -> CommandReply:
        if self.svc is not None:
            self.svc.count("commands_refused")
        return CommandReply(ok=False, robot=robot, verb=verb, error=error)

    def _mission(self, robot: str, cmd: MissionCommand, generation: int | None = None) -> CommandReply:
        try:
            detail = self.handles[robot].start_mission(cmd, generation)
        except CommandError as exc:
            return self._refused(robot, "mission", str(exc))
        if self.svc is not None:
            self.svc.count("commands_ok")
        return CommandReply(ok=True, robot=robot, verb="mission", detail=detail)

    def execute(self, robot: str, verb: str, payload: bytes) -> CommandReply:
        """Carry out one command for one robot and build the reply (never raises). A mission is
        laid out and started on the calling thread (the command callback uses the robot's worker)."""
        h = self.handles.get(robot)
        if h is None:
            return CommandReply(ok=False, robot=robot, verb=verb,
                                error=f"unknown robot {robot!r}; this bridge has {', '.join(self.handles)}")
        if verb not in COMMAND_VERBS:
            return CommandReply(ok=False, robot=robot, verb=verb,
                                error=f"bad parameter: unknown verb {verb!r}; expected {', '.join(COMMAND_VERBS)}")
        if verb == "mission":
            try:
                cmd = MissionCommand.decode(payload)
            except MessageError as exc:
                return self._refused(robot, verb, f"bad parameter: {exc}")
            return self._mission(robot, cmd)
        try:
            params: dict = {}
            if payload:
                try:
                    params = Command.decode(payload).params
                except MessageError as exc:
                    raise CommandError(f"bad parameter: {exc}") from None
            if verb == "stop":
                detail = h.stop()
            elif verb == "estop":
                detail = h.emergency_stop()
            elif verb == "clear":
                detail = h.clear()
            else:
                detail = h.set_led(params.get("rgb"))
        except CommandError as exc:
            return self._refused(robot, verb, str(exc))
        if self.svc is not None:
            self.svc.count("commands_ok")
        return CommandReply(ok=True, robot=robot, verb=verb, detail=detail)


class _PendingQuery:
    """A query that ``n`` robots answer, maybe from their worker threads: finalised (Zenoh's
    final reply, so the querier need not wait for its timeout) after the last one."""

    def __init__(self, query, n: int):
        self.query = query
        self.left = n
        self._lock = threading.Lock()

    def reply(self, bridge: "Bridge", reply: CommandReply) -> None:
        bridge._reply(self.query, reply)
        with self._lock:
            self.left -= 1
            last = self.left == 0
        if last:
            try:
                with self.query:     # leaving the context finalises the query
                    pass
            except Exception:  # noqa: BLE001 - the querier may have gone
                pass


def parse_cmd_key(key: str) -> tuple[str, str]:
    """``arena/cmd/<robot>/<verb>`` -> (robot, verb); ``robot`` may be ``all``.

    Raises :class:`arena.keys.InvalidKey` with what a command key looks like for anything else
    (wildcards, too few or too many parts, an unknown verb)."""
    try:
        parsed = parse_key(key)
        if parsed.kind != "cmd":
            raise InvalidKey(f"{key!r} is a {parsed.kind!r} key")
    except InvalidKey as exc:
        detail = str(exc)
        if detail.startswith(repr(key)):
            detail = detail[len(repr(key)):].lstrip(": ")
        raise InvalidKey(f"{key!r} is not a command key ({detail}). A command is a query on "
                         f"{ROOT}/cmd/<robot>/<verb>: one robot name (or 'all', no wildcards) and one of "
                         f"{', '.join(COMMAND_VERBS)}, e.g. {ROOT}/cmd/all/stop") from None
    return parsed.parts["robot"], parsed.parts["verb"]


def parse_robot_flag(value: str) -> tuple[str, str]:
    """``NAME=URL`` -> (name, url); raises ValueError with the expected form."""
    name, sep, url = value.partition("=")
    if not sep or not name or not url:
        raise ValueError(f"--robot expects NAME=URL (e.g. zumo1=/dev/rfcomm0 or zumo1=socket://127.0.0.1:5001), "
                         f"got {value!r}")
    validate_name(name, "robot name")
    return name, url


def fmt_reply(reply: CommandReply) -> str:
    """One human line for a reply (cm and degrees allowed in CLI output)."""
    if reply.ok:
        extra = " ".join(f"{k}={v}" for k, v in reply.detail.items())
        return f"{reply.robot}: {reply.verb} ok {extra}".rstrip()
    return f"{reply.robot}: {reply.verb} REFUSED: {reply.error}"

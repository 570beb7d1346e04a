"""The robot bridge service: serial links <-> Zenoh, missions, safety, logs.

For every robot (from the lab config or ``--robot NAME=URL``) the bridge keeps a
:class:`~robot_bridge.core.RobotHandle` (the robot's domain core, no Zenoh: its
:class:`~robot_bridge.link.RobotLink`, missions, safety, clocks, logs), publishes each telemetry
sample on ``arena/telemetry/<robot>``, and wires the command queryable, the track subscriber and
the router watchdog to the core. It stops robots only through the core's public stopping methods
(:meth:`~robot_bridge.core.RobotHandle.stop_now`, ``stop``, ``emergency_stop``, ``hold``,
``halt_motors``, ``halt``), which take the robot's command lock.

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
import threading
import time

import zenoh

from arena.keys import ALL_ROBOTS, COMMAND_VERBS, ROOT, InvalidKey, parse_key, telemetry_key, validate_name
from arena.messages import Command, CommandReply, MessageError, MissionCommand, Telemetry, Track, decode

from .core import BridgeOptions, CommandError, RobotHandle, RobotSetup

log = logging.getLogger("robot_bridge")


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
            h.halt_motors()       # no control step is half-way: the next one sees it and commands nothing
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
            # a closed loop driving without its track (on odometry alone), and how often it happened
            self.svc.gauge(f"{name}.on_odometry", h.on_odometry)
            self.svc.gauge(f"{name}.odometry_fallbacks", h.odometry_fallbacks)
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
                self.handles[name].stop_now(self.opt.estop_repeats if verb == "estop" else 1,
                                            estop=verb == "estop")
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

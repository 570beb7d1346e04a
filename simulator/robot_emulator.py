"""Robot firmware emulator: one simulated robot served on a TCP port.

Stands in for the Zumo 32U4 reference firmware (``robot_bridge/firmware/``): it speaks
the arena robot wire protocol (``docs/robot-protocol.md``, implemented by
``arena.robot_protocol``, which the firmware's C code is cross-tested against) on a
TCP socket, so the bridge opens it as ``socket://127.0.0.1:PORT`` with pyserial exactly
as it opens ``/dev/rfcomm0``.

Behaviour (as the firmware): SET_MOTORS -> ``world.set_power``; STOP -> power 0;
TELEMETRY at ``telemetry_hz`` from ``world.encoder_counts/imu/battery_mv``; PING ->
PONG; HELLO -> HELLO_REPLY; a 300 ms watchdog stops the motors when motor commands
stop. One client at a time (like an SPP port): a new connection replaces the old one.
The world is stepped by someone else; this class only reads and commands it.

Link faults (:class:`LinkFaults`) model a Bluetooth SPP link: latency with jitter in
both directions (in-order delivery), and on the robot -> host direction random byte
loss and frame corruption; ``disconnect_after_s`` drops every connection after that
long; :meth:`RobotEmulatorServer.pause_output` holds every robot -> host byte for a while and
then delivers them in a burst (an SPP link stalling while the radio retransmits). What was
injected is counted in :attr:`RobotEmulatorServer.stats`. Host frames with a field outside its
physical range (SET_MOTORS -5750) are clamped by the decoder, as the firmware's ``constrain``
does, and counted (``stats.rx_clamped``).
"""

from __future__ import annotations

import heapq
import logging
import random
import socket
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

from arena import robot_protocol as P

log = logging.getLogger("simulator.robot_emulator")

FIRMWARE_VERSION = 1
WATCHDOG_S = 0.300
LOW_BATTERY_MV = 4400
_TICK_S = 0.002
_MAX_SLEEP_S = 0.02


@dataclass(frozen=True)
class LinkFaults:
    """Faults injected on the emulated radio link.

    Attributes:
        byte_loss: probability that each robot -> host byte is dropped.
        corruption: probability that a robot -> host frame has one bit flipped
            (never the 0x00 delimiter, so exactly one frame is spoiled).
        disconnect_after_s: close each connection this many seconds after it opened
            (the server keeps listening so the host can reconnect); None = never.
        latency_ms: one-way delay of every frame, both directions, ms.
        jitter_ms: extra uniform random delay 0..jitter_ms, ms (order is kept, as on SPP).
    """

    byte_loss: float = 0.0
    corruption: float = 0.0
    disconnect_after_s: float | None = None
    latency_ms: float = 0.0
    jitter_ms: float = 0.0

    def __post_init__(self):
        for name in ("byte_loss", "corruption"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"LinkFaults.{name} must be in [0, 1], got {v}")
        for name in ("latency_ms", "jitter_ms"):
            if getattr(self, name) < 0:
                raise ValueError(f"LinkFaults.{name} must be >= 0, got {getattr(self, name)}")
        if self.disconnect_after_s is not None and self.disconnect_after_s <= 0:
            raise ValueError(f"LinkFaults.disconnect_after_s must be > 0, got {self.disconnect_after_s}")


@dataclass
class EmulatorStats:
    """What the emulator did and injected (cumulative over connections)."""

    connections: int = 0
    frames_sent: int = 0          # robot -> host frames produced (before faults)
    telemetry_sent: int = 0
    frames_corrupted: int = 0     # frames with an injected bit flip
    bytes_dropped: int = 0        # bytes removed by byte_loss
    disconnects: int = 0          # connections closed by disconnect_after_s or disconnect()
    commands: int = 0             # valid host frames handled
    rx_rejected: int = 0          # host frames rejected by CRC/framing
    rx_clamped: int = 0           # fields of host frames out of their physical range, clamped
    output_pauses: int = 0        # pause_output() calls
    watchdog_trips: int = 0
    last_command_t: float = 0.0   # monotonic time of the last valid SET_MOTORS/STOP
    watchdog_stop_t: float = 0.0  # monotonic time the watchdog last stopped the motors


@dataclass
class _Conn:
    sock: socket.socket
    opened: float
    decoder: P.StreamDecoder = field(default_factory=P.StreamDecoder)
    tx_due: float = 0.0           # delivery time of the last queued outgoing frame
    rx_due: float = 0.0
    alive: bool = True


class RobotEmulatorServer:
    """Serve robot ``robot_index`` of ``world`` over TCP with the robot wire protocol.

    Args:
        world: a ``simulator.world.World`` (thread-safe).
        robot_index: which robot of the world this emulator is.
        host, port: listen address; port 0 picks a free port (read :attr:`port`).
        telemetry_hz: TELEMETRY rate, Hz (the firmware's 50-100 Hz).
        faults: link faults to inject.
        seed: seed of the fault draws.
        record_telemetry: keep every clean TELEMETRY sent, keyed by seq, in
            :attr:`sent_telemetry`, and the seqs of corrupted frames in :attr:`corrupted_seqs`
            (for tests that check nothing corrupt was logged; memory grows with time).
        clock: the robot's clock, seconds (default: wall time since the emulator started).
            ``arena sim`` passes the world's simulated time: when the simulation falls behind
            real time on a loaded machine, a wall clock would stamp encoder counts and gyro
            rates measured in simulated seconds with wall seconds, and the host's odometry
            would turn too far and drive too slowly (a real robot's clock and physics agree).
    """

    def __init__(self, world, robot_index: int, host: str = "127.0.0.1", port: int = 0,
                 telemetry_hz: float = 100, faults: LinkFaults | None = None, seed: int = 0,
                 record_telemetry: bool = False, clock: Callable[[], float] | None = None):
        if not 1 <= telemetry_hz <= 1000:
            raise ValueError(f"telemetry_hz must be in [1, 1000], got {telemetry_hz}")
        world.pose(robot_index)  # raises IndexError for a bad index
        self.world = world
        self.index = robot_index
        self.spec = world.robots[robot_index]
        self.host = host
        self._req_port = port
        self.telemetry_hz = float(telemetry_hz)
        self.faults = faults or LinkFaults()
        self.stats = EmulatorStats()
        self.sent_telemetry: dict[int, P.Telemetry] | None = {} if record_telemetry else None
        #: seq numbers of the frames that got an injected bit flip (with ``record_telemetry``)
        self.corrupted_seqs: set[int] = set()
        self._rng = random.Random(seed)
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._listener: socket.socket | None = None
        self._conn: _Conn | None = None
        self._threads: list[threading.Thread] = []
        self._tx_queue: list[tuple[float, int, bytes, _Conn]] = []   # heap of (due, n, bytes, conn)
        self._rx_queue: deque[tuple[float, P.Frame, _Conn]] = deque()
        self._n = 0
        self._seq = 0
        self._t0 = time.monotonic()
        self._clock = clock
        self._motors = (0, 0)
        self._last_motor_cmd = 0.0
        self._flags = 0
        self._led = (0, 0, 0)
        self._tx_hold_until = 0.0     # pause_output(): robot -> host bytes wait until then

    # ------------------------------------------------------------------ lifecycle
    @property
    def port(self) -> int:
        """The TCP port actually listened on (valid after :meth:`start`)."""
        if self._listener is None:
            raise RuntimeError("emulator not started")
        return self._listener.getsockname()[1]

    @property
    def url(self) -> str:
        """pyserial URL of this robot: ``socket://HOST:PORT``."""
        return f"socket://{self.host}:{self.port}"

    @property
    def led(self) -> tuple[int, int, int]:
        """Last LED colour set by the host."""
        return self._led

    def start(self) -> "RobotEmulatorServer":
        """Bind, listen and start the server threads. Returns self."""
        if self._listener is not None:
            return self
        srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        srv.bind((self.host, self._req_port))
        srv.listen(2)
        srv.settimeout(0.1)
        self._listener = srv
        self._stop.clear()
        for target, name in ((self._accept_loop, "accept"), (self._main_loop, "main")):
            t = threading.Thread(target=target, name=f"robot-emu-{self.spec.name}-{name}", daemon=True)
            t.start()
            self._threads.append(t)
        log.info("robot %s emulated on %s", self.spec.name, self.url)
        return self

    def stop(self) -> None:
        """Stop the motors, close the connection and the listener, join the threads."""
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2.0)
        self._threads.clear()
        with self._lock:
            self._close_conn(count=False)
        if self._listener is not None:
            self._listener.close()
            self._listener = None
        self.world.set_power(self.index, 0, 0)

    def __enter__(self) -> "RobotEmulatorServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def disconnect(self) -> None:
        """Drop the current client now (as a Bluetooth link that goes out of range)."""
        with self._lock:
            if self._conn is not None:
                self._close_conn(count=True)

    def pause_output(self, seconds: float) -> None:
        """Hold every robot -> host byte for ``seconds`` from now, then deliver them in order (an
        SPP link that stalls; the robot keeps running and still receives commands)."""
        if not seconds > 0:
            raise ValueError(f"pause_output needs a positive duration, got {seconds}")
        with self._lock:
            self._tx_hold_until = max(self._tx_hold_until, time.monotonic() + seconds)
            self.stats.output_pauses += 1

    @property
    def connected(self) -> bool:
        """True while a host is connected."""
        return self._conn is not None

    # ------------------------------------------------------------------ internals
    def _now_us(self) -> int:
        t = self._clock() if self._clock is not None else time.monotonic() - self._t0
        return int(t * 1e6) & 0xFFFFFFFF

    def _close_conn(self, count: bool) -> None:
        conn = self._conn
        if conn is None:
            return
        conn.alive = False
        try:
            conn.sock.close()
        except OSError:
            pass
        self._conn = None
        if count:
            self.stats.disconnects += 1

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                sock, _ = self._listener.accept()
            except (socket.timeout, OSError):
                continue
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                self._close_conn(count=False)
                conn = _Conn(sock, time.monotonic())
                self._conn = conn
                self.stats.connections += 1
            threading.Thread(target=self._rx_loop, args=(conn,), daemon=True,
                             name=f"robot-emu-{self.spec.name}-rx").start()
            self._send_raw(b"\x00", conn)  # resync delimiter, as the firmware sends at boot

    def _rx_loop(self, conn: _Conn) -> None:
        conn.sock.settimeout(0.1)
        while conn.alive and not self._stop.is_set():
            try:
                chunk = conn.sock.recv(4096)
            except socket.timeout:
                continue
            except OSError:
                break
            if not chunk:
                break
            before = conn.decoder.stats.rejected
            clamped = conn.decoder.stats.clamped
            frames = conn.decoder.feed(chunk)
            with self._lock:
                self.stats.rx_rejected += conn.decoder.stats.rejected - before
                self.stats.rx_clamped += conn.decoder.stats.clamped - clamped
                for fr in frames:
                    if self.faults.latency_ms or self.faults.jitter_ms:
                        due = max(conn.rx_due, time.monotonic() + self._delay())
                        conn.rx_due = due
                        self._rx_queue.append((due, fr, conn))
                    else:
                        self._handle(fr, conn)
        with self._lock:
            if self._conn is conn:
                self._close_conn(count=False)

    def _delay(self) -> float:
        f = self.faults
        return (f.latency_ms + (self._rng.uniform(0.0, f.jitter_ms) if f.jitter_ms else 0.0)) / 1000.0

    def _handle(self, fr: P.Frame, conn: _Conn) -> None:
        msg = fr.msg
        self.stats.commands += 1
        if isinstance(msg, P.SetMotors):
            self._set_motors(msg.left, msg.right)
            self._last_motor_cmd = time.monotonic()
            self.stats.last_command_t = self._last_motor_cmd
            self._flags &= ~P.FLAG_WATCHDOG
        elif isinstance(msg, P.Stop):
            self._set_motors(0, 0)
            self.stats.last_command_t = time.monotonic()
        elif isinstance(msg, P.Ping):
            self._send(P.Pong(msg.token), conn=conn)
        elif isinstance(msg, P.Hello):
            self._send(P.HelloReply(FIRMWARE_VERSION, int(self.telemetry_hz), self.spec.counts_per_rev,
                                    int(WATCHDOG_S * 1000), self.spec.name[:16]), conn=conn)
        elif isinstance(msg, P.SetLed):
            self._led = (msg.r, msg.g, msg.b)
        else:
            self._send(P.Error(P.ERR_UNKNOWN_TYPE, msg.TYPE, "unexpected"), conn=conn)

    def _set_motors(self, left: int, right: int) -> None:
        self._motors = (left, right)
        self.world.set_power(self.index, left, right)

    def _send(self, msg: P.Message, time_us: int | None = None, *, conn: _Conn) -> None:
        """Encode one robot -> host frame (stamped ``time_us``, default now) and queue it
        through the fault model."""
        with self._lock:
            seq = self._seq
            self._seq = (self._seq + 1) & 0xFFFF
            data = bytearray(P.encode_frame(msg, seq, self._now_us() if time_us is None else time_us))
            self.stats.frames_sent += 1
            if isinstance(msg, P.Telemetry):
                self.stats.telemetry_sent += 1
                if self.sent_telemetry is not None:
                    self.sent_telemetry[seq] = msg
            f = self.faults
            if f.corruption and self._rng.random() < f.corruption:
                i = self._rng.randrange(len(data) - 1)
                data[i] ^= 1 << self._rng.randrange(8)
                self.stats.frames_corrupted += 1
                if self.sent_telemetry is not None:
                    self.corrupted_seqs.add(seq)
            if f.byte_loss:
                kept = bytearray(b for b in data if self._rng.random() >= f.byte_loss)
                self.stats.bytes_dropped += len(data) - len(kept)
                data = kept
            self._send_raw(bytes(data), conn)

    def _send_raw(self, data: bytes, conn: _Conn) -> None:
        """Deliver ``data`` after the link latency, in order."""
        with self._lock:
            now = time.monotonic()
            due = max(conn.tx_due, now + self._delay(), self._tx_hold_until)
            conn.tx_due = due
            if due <= now:
                self._write(conn, data)
            else:
                self._n += 1
                heapq.heappush(self._tx_queue, (due, self._n, data, conn))

    def _write(self, conn: _Conn, data: bytes) -> None:
        if not conn.alive or not data:
            return
        try:
            conn.sock.sendall(data)
        except OSError:
            if self._conn is conn:
                self._close_conn(count=False)

    def _telemetry(self) -> tuple[P.Telemetry, int]:
        """One TELEMETRY message and the robot-clock time it describes (read together under
        the world's lock, so the stamp and the sensor values agree)."""
        w, i = self.world, self.index
        with w.lock:
            enc_l, enc_r = w.encoder_counts(i)
            imu = w.imu(i)
            mv = w.battery_mv(i)
            t_us = self._now_us()
        accel, gyro, mag = P.imu_to_raw(imu["accel"], imu["gyro"], imu["mag"])
        if mv < LOW_BATTERY_MV:
            self._flags |= P.FLAG_LOW_BATTERY
        wrap = lambda c: ((c + 2**31) % 2**32) - 2**31  # noqa: E731  int32 like the firmware
        left, right = self._motors
        return P.Telemetry(wrap(enc_l), wrap(enc_r), accel, gyro, mag, min(mv, 0xFFFF), left, right,
                           self._flags), t_us

    def _main_loop(self) -> None:
        period = 1.0 / self.telemetry_hz
        next_tel = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            with self._lock:
                conn = self._conn
                # commands whose latency has elapsed
                while self._rx_queue and self._rx_queue[0][0] <= now:
                    _, fr, c = self._rx_queue.popleft()
                    if c.alive:
                        self._handle(fr, c)
                # watchdog (runs whether or not a host is connected)
                if self._motors != (0, 0) and now - self._last_motor_cmd > WATCHDOG_S:
                    self._set_motors(0, 0)
                    self._flags |= P.FLAG_WATCHDOG
                    self.stats.watchdog_trips += 1
                    self.stats.watchdog_stop_t = now
                if conn is not None and self.faults.disconnect_after_s is not None \
                        and now - conn.opened >= self.faults.disconnect_after_s:
                    self._close_conn(count=True)
                    conn = None
                if now >= next_tel:
                    next_tel += period
                    if next_tel < now:          # fell behind (loaded machine): skip, keep the rate
                        next_tel = now + period
                    if conn is not None:
                        self._send(*self._telemetry(), conn=conn)
                while self._tx_queue and self._tx_queue[0][0] <= now:
                    _, _, data, c = heapq.heappop(self._tx_queue)
                    self._write(c, data)
            self._stop.wait(self._sleep_s(next_tel))

    def _sleep_s(self, next_tel: float) -> float:
        """How long the main loop may sleep: until the next telemetry, the watchdog deadline
        or a fault's deadline; one tick while delayed bytes wait in the latency queues. (A
        fixed 2 ms tick woke four robots 2000 times a second and slowed the demo's simulator.)"""
        now = time.monotonic()
        until = min(next_tel, now + _MAX_SLEEP_S)   # commands and faults may change meanwhile
        if self._rx_queue or self._tx_queue or self.faults.latency_ms or self.faults.jitter_ms:
            until = min(until, now + _TICK_S)
        if self._motors != (0, 0):
            until = min(until, self._last_motor_cmd + WATCHDOG_S + 0.001)
        conn = self._conn
        if conn is not None and self.faults.disconnect_after_s is not None:
            until = min(until, conn.opened + self.faults.disconnect_after_s)
        return max(0.0, until - now)

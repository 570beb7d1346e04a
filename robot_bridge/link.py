"""Serial link to one robot: open by pyserial URL, read frames, reconnect, measure quality.

The same code drives ``/dev/rfcommN`` (Bluetooth SPP after ``rfcomm bind``),
``/dev/ttyACM0`` (USB) and ``socket://127.0.0.1:PORT`` (the simulator's robot emulator):
``serial.serial_for_url(url, baudrate=..., timeout=...)``.

A reader thread opens the port, handshakes (HELLO -> HELLO_REPLY), then decodes frames
and hands each one to ``on_frame(frame, host_time_ns, gap)`` where ``gap`` is the number
of robot packets missing before it (from the 16-bit sequence numbers). It sends a PING
every ``ping_interval_s`` and keeps the round-trip time. When the port fails, or no good
frame (the robot's 50-100 Hz telemetry is its heartbeat; pongs count too, garbage bytes do
not) came for ``silence_s`` (default :data:`LINK_TIMEOUT_S`, ``--link-timeout``), it closes the
port and reconnects with exponential backoff; while down, :meth:`RobotLink.send` raises
:class:`LinkDown` with the reason.

Why 2 s: Bluetooth SPP delivers in order but stalls while the radio retransmits; pauses of
about half a second are common (the issue that set this, and e.g. HC-05 users' reports), so
the old 0.5 s declared healthy links down and aborted missions (and did so at load 15 when the
host, not the link, stalled). The radio itself gives up only after its link supervision
timeout (20 s by default in Bluetooth Classic). 2 s is four such pauses and still quick for an
operator; it is no safety limit: the robot's own 300 ms motor watchdog stops it whenever motor
commands stop, whatever the host decides.

Motor commands after a STOP: :meth:`RobotLink.stop_motors` also latches "no motors" under the
write lock, so a control step that was half-way when STOP went out cannot put SET_MOTORS on the
wire after it; :meth:`RobotLink.allow_motors` (a new mission) lifts the latch. A port that cannot be
opened (a missing device, a refused socket, no HELLO_REPLY) is retried with the same backoff;
each failed attempt is counted (``stats.open_failures``) and reported to ``on_open_error``.
"""

from __future__ import annotations

import logging
import select
import threading
import time
from dataclasses import dataclass
from typing import Callable

import serial

from arena import robot_protocol as P

log = logging.getLogger("robot_bridge.link")


#: longest wait for the first byte of a read (the reader then checks stop, silence and pings)
READ_WAIT_S = 0.02
#: default link timeout: no good frame for this long means the link is down, s (see above)
LINK_TIMEOUT_S = 2.0


def _fileno(port) -> int | None:
    """The port's file descriptor, or None when it has none (``loop://``, RFC 2217, Windows)."""
    try:
        fd = port.fileno()
    except (AttributeError, OSError, ValueError, serial.SerialException):
        return None
    return fd if isinstance(fd, int) and fd >= 0 else None


class LinkDown(RuntimeError):
    """The robot's serial link is not connected; the text says why."""


@dataclass
class LinkStats:
    """Link counters and quality figures (cumulative unless stated)."""

    connects: int = 0
    disconnects: int = 0
    open_failures: int = 0       # attempts to open the port (and handshake) that failed
    frames: int = 0              # good frames received
    telemetry: int = 0
    missing: int = 0             # robot packets never received (sequence gaps)
    crc_errors: int = 0
    framing_errors: int = 0
    other_rejected: int = 0      # wrong version / unknown type
    clamped: int = 0             # decoded fields outside their physical range, clamped
    motors_inhibited: int = 0    # SET_MOTORS refused because STOP was sent since the last mission start
    sent: int = 0
    rtt_ms: float | None = None  # last ping round trip
    rtt_ms_max: float = 0.0

    @property
    def rejected(self) -> int:
        return self.crc_errors + self.framing_errors + self.other_rejected

    @property
    def quality(self) -> float:
        """Fraction of robot packets received intact, 0..1 (1 on a healthy link)."""
        total = self.frames + self.missing
        return self.frames / total if total else 1.0

    def as_dict(self) -> dict:
        return {"connects": self.connects, "disconnects": self.disconnects,
                "open_failures": self.open_failures, "frames": self.frames,
                "telemetry": self.telemetry, "missing": self.missing, "crc_errors": self.crc_errors,
                "framing_errors": self.framing_errors, "other_rejected": self.other_rejected,
                "clamped": self.clamped, "motors_inhibited": self.motors_inhibited, "sent": self.sent, "rtt_ms": self.rtt_ms, "quality": round(self.quality, 5)}


FrameCallback = Callable[[P.Frame, int, int], None]


class RobotLink:
    """One robot's link. Use as a context manager or call :meth:`start`/:meth:`close`.

    Args:
        url: pyserial URL or device path (``/dev/rfcomm0``, ``socket://127.0.0.1:5001``).
        name: robot name for logs.
        baudrate: UART rate (the firmware's 57600; ignored by ``socket://``).
        on_frame: called from the reader thread for each good frame.
        on_state: called with (connected: bool, reason: str) on every change.
        on_open_error: called from the reader thread with (reason, retry_in_s) after every
            attempt to open the port that failed (the link logs it as well).
        hello_timeout_s: how long to wait for HELLO_REPLY after opening.
        silence_s: no good frame for this long means the link is dead, s (telemetry is
            50-100 Hz; see the module docstring for the default).
        backoff_s: (first, max) delay between reconnection attempts, s.
    """

    def __init__(self, url: str, name: str = "robot", baudrate: int = 57600,
                 on_frame: FrameCallback | None = None,
                 on_state: Callable[[bool, str], None] | None = None,
                 on_open_error: Callable[[str, float], None] | None = None,
                 hello_timeout_s: float = 1.0, silence_s: float = LINK_TIMEOUT_S, ping_interval_s: float = 1.0,
                 backoff_s: tuple[float, float] = (0.05, 2.0)):
        if not (silence_s > 0 and silence_s < float("inf")):
            raise ValueError(f"link timeout must be a positive number of seconds, got {silence_s}")
        self.url = url
        self.name = name
        self.baudrate = baudrate
        self.on_frame = on_frame
        self.on_state = on_state
        self.on_open_error = on_open_error
        self.hello_timeout_s = hello_timeout_s
        self.silence_s = silence_s
        self.ping_interval_s = ping_interval_s
        self.backoff_s = backoff_s
        self.stats = LinkStats()
        self.hello: P.HelloReply | None = None
        self.last_error = "not started"
        self.last_rx_ns = 0
        self._port = None
        self._tx_lock = threading.Lock()
        self._motors_inhibited = False   # STOP was sent: no SET_MOTORS until allow_motors()
        self._stop = threading.Event()
        self._connected = threading.Event()
        self._attempted = threading.Event()   # the first attempt to open the port is over
        self._thread: threading.Thread | None = None
        self._seq = 0
        self._last_seq: int | None = None
        self._ping_token = 0
        self._ping_sent: dict[int, float] = {}
        self._decoder = P.StreamDecoder()
        self._pending: list[P.Frame] = []

    # ------------------------------------------------------------------ public
    @property
    def connected(self) -> bool:
        """True between a successful handshake and the next failure."""
        return self._connected.is_set()

    def wait_connected(self, timeout: float) -> bool:
        """Block until connected (True) or ``timeout`` s passed (False)."""
        return self._connected.wait(timeout)

    def wait_attempted(self, timeout: float) -> bool:
        """Block until the first attempt to open the port is over, whatever its outcome (True),
        or ``timeout`` s passed (False). Then :attr:`connected` or :attr:`last_error` tell which."""
        return self._attempted.wait(timeout)

    def start(self) -> "RobotLink":
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name=f"link-{self.name}", daemon=True)
            self._thread.start()
        return self

    def close(self) -> None:
        """Stop the motors (best effort), close the port and join the reader thread."""
        if self.connected:
            try:
                self.send(P.Stop())
            except LinkDown:
                pass
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=3.0)
            self._thread = None
        self._drop("closed", notify=True)

    def __enter__(self) -> "RobotLink":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def send(self, msg: P.Message) -> None:
        """Send one message; raises :class:`LinkDown` when not connected or the write fails."""
        if not self.connected:
            raise LinkDown(f"link to {self.name} ({self.url}) down: {self.last_error}")
        self._write(msg)

    def set_motors(self, left: int, right: int) -> bool:
        """Motor power per side, -400..400 (also feeds the robot's 300 ms watchdog). Returns
        False (and sends nothing) after :meth:`stop_motors` until :meth:`allow_motors`."""
        if not self.connected:
            raise LinkDown(f"link to {self.name} ({self.url}) down: {self.last_error}")
        return self._write(P.SetMotors(int(left), int(right)), motors=True)

    def stop_motors(self, repeat: int = 1) -> None:
        """Send STOP ``repeat`` times (a corrupted frame is dropped, never retried), and refuse
        SET_MOTORS from now on until :meth:`allow_motors` (latched even when the link is down)."""
        with self._tx_lock:
            self._motors_inhibited = True
        for _ in range(repeat):
            self.send(P.Stop())

    def allow_motors(self) -> None:
        """Lift the latch of :meth:`stop_motors` (a mission starts)."""
        with self._tx_lock:
            self._motors_inhibited = False

    @property
    def motors_allowed(self) -> bool:
        return not self._motors_inhibited

    # ------------------------------------------------------------------ internals
    def _write(self, msg: P.Message, port=None, motors: bool = False) -> bool:
        with self._tx_lock:
            if motors and self._motors_inhibited:
                self.stats.motors_inhibited += 1
                return False
            port = port or self._port
            if port is None:
                raise LinkDown(f"link to {self.name} ({self.url}) down: {self.last_error}")
            data = P.encode_frame(msg, self._seq, time.monotonic_ns() // 1000)
            self._seq = (self._seq + 1) & 0xFFFF
            try:
                port.write(data)
            except (serial.SerialException, OSError) as exc:
                self.last_error = f"write failed: {exc}"
                raise LinkDown(f"link to {self.name} ({self.url}) down: {self.last_error}") from exc
            self.stats.sent += 1
            return True

    def _drop(self, reason: str, notify: bool) -> None:
        was = self._connected.is_set()
        self._connected.clear()
        with self._tx_lock:
            port, self._port = self._port, None
        if port is not None:
            try:
                port.close()
            except Exception:  # noqa: BLE001 - closing a broken port may raise anything
                pass
        self.last_error = reason
        if was:
            self.stats.disconnects += 1
            log.warning("robot %s: link down (%s)", self.name, reason)
            if notify and self.on_state:
                self.on_state(False, reason)

    def _open(self) -> bool:
        try:
            port = serial.serial_for_url(self.url, baudrate=self.baudrate, timeout=READ_WAIT_S, write_timeout=0.5)
        except (serial.SerialException, OSError, ValueError) as exc:
            self.last_error = f"cannot open {self.url}: {exc}"
            return False
        decoder = P.StreamDecoder()
        try:
            port.reset_input_buffer()
            deadline = time.monotonic() + self.hello_timeout_s
            next_hello = 0.0
            while time.monotonic() < deadline and not self._stop.is_set():
                if time.monotonic() >= next_hello:
                    port.write(b"\x00")
                    self._write(P.Hello(), port)
                    next_hello = time.monotonic() + 0.25
                frames = decoder.feed(self._read(port))
                now_ns = time.time_ns()
                for k, fr in enumerate(frames):
                    self._handle(fr, now_ns)   # telemetry before the reply is data too
                    if isinstance(fr.msg, P.HelloReply):
                        self.hello = fr.msg
                        self._decoder = decoder
                        with self._tx_lock:
                            self._port = port
                        self._pending = frames[k + 1:]
                        return True
        except (serial.SerialException, OSError, LinkDown) as exc:
            self.last_error = f"handshake on {self.url} failed: {exc}"
            port.close()
            return False
        port.close()
        self.last_error = f"no HELLO_REPLY from {self.url} within {self.hello_timeout_s:.1f} s"
        return False

    @staticmethod
    def _read(port) -> bytes:
        """Return as soon as bytes are there (up to ``READ_WAIT_S``), without waiting for more.

        Ports with a file descriptor (tty, rfcomm, ``socket://``) are read non-blocking after a
        ``select``: everything that arrived in one call. pyserial's ``socket://`` reports
        ``in_waiting`` as 0 or 1, so reading ``in_waiting`` bytes went byte by byte and cost the
        demo's bridge half a core for four robots. Other ports (``loop://``, RFC 2217) read
        one byte with the port's timeout, then what ``in_waiting`` reports."""
        fd = _fileno(port)
        if fd is not None:
            if port.timeout != 0:
                port.timeout = 0
            ready, _, _ = select.select([fd], [], [], READ_WAIT_S)
            return port.read(1 << 16) if ready else b""
        chunk = port.read(1)
        if chunk:
            n = port.in_waiting
            if n:
                chunk += port.read(n)
        return chunk

    def _handle(self, fr: P.Frame, now_ns: int) -> None:
        if self._last_seq is not None:
            gap = P.seq_gap(self._last_seq, fr.seq)
            if gap > 0x8000:   # an old duplicate or a robot reboot: resynchronise
                gap = 0
        else:
            gap = 0
        self._last_seq = fr.seq
        self.stats.missing += gap
        self.stats.frames += 1
        msg = fr.msg
        if isinstance(msg, P.Telemetry):
            self.stats.telemetry += 1
        elif isinstance(msg, P.Pong):
            sent = self._ping_sent.pop(msg.token, None)
            if sent is not None:
                rtt = (time.monotonic() - sent) * 1000.0
                self.stats.rtt_ms = rtt
                self.stats.rtt_ms_max = max(self.stats.rtt_ms_max, rtt)
        elif isinstance(msg, P.Ping):
            try:
                self._write(P.Pong(msg.token))
            except LinkDown:
                pass
        elif isinstance(msg, P.Error):
            log.warning("robot %s reports error %d on type 0x%02x: %s", self.name, msg.code, msg.ref_type, msg.text)
        if self.on_frame:
            try:
                self.on_frame(fr, now_ns, gap)
            except Exception:  # noqa: BLE001 - a consumer bug must not kill the link
                log.exception("robot %s: frame handler failed", self.name)

    def _count(self, dec: P.StreamDecoder, before: P.DecoderStats) -> None:
        s = dec.stats
        self.stats.crc_errors += s.crc_errors - before.crc_errors
        self.stats.framing_errors += s.framing_errors - before.framing_errors
        self.stats.other_rejected += (s.version_errors - before.version_errors) + (s.unknown_type - before.unknown_type)
        if s.clamped != before.clamped:
            self.stats.clamped += s.clamped - before.clamped
            log.warning("robot %s: %d decoded field(s) out of their physical range, clamped (%d so far)",
                        self.name, s.clamped - before.clamped, self.stats.clamped)

    def _run(self) -> None:
        delay = self.backoff_s[0]
        reported = None
        while not self._stop.is_set():
            if not self._open():
                if self._stop.is_set():
                    break
                self.stats.open_failures += 1
                self._attempted.set()
                level = logging.INFO if self.last_error == reported else logging.WARNING
                reported = self.last_error
                log.log(level, "robot %s: %s; retry in %.2f s", self.name, self.last_error, delay)
                if self.on_open_error:
                    try:
                        self.on_open_error(self.last_error, delay)
                    except Exception:  # noqa: BLE001 - a consumer bug must not kill the link
                        log.exception("robot %s: open-error handler failed", self.name)
                self._stop.wait(delay)
                delay = min(delay * 2.0, self.backoff_s[1])
                continue
            delay = self.backoff_s[0]
            reported = None
            self.stats.connects += 1
            self.last_error = ""
            self.last_rx_ns = time.time_ns()
            self._connected.set()
            self._attempted.set()
            log.info("robot %s connected on %s (firmware %d, %d Hz)", self.name, self.url,
                     self.hello.firmware_version, self.hello.telemetry_hz)
            if self.on_state:
                self.on_state(True, "connected")
            self._pump()

    def _pump(self) -> None:
        dec = self._decoder
        for fr in self._pending:
            self._handle(fr, time.time_ns())
        self._pending = []
        last_rx = time.monotonic()
        next_ping = time.monotonic()
        while not self._stop.is_set():
            port = self._port
            if port is None:
                return
            try:
                chunk = self._read(port)
            except (serial.SerialException, OSError, TypeError, AttributeError, ValueError) as exc:
                self._drop(f"serial error: {exc}", notify=True)
                return
            now = time.monotonic()
            if chunk:
                before = P.DecoderStats(**vars(dec.stats))
                frames = dec.feed(chunk)
                self._count(dec, before)
                now_ns = time.time_ns()
                if frames:          # the heartbeat: good frames, not just bytes
                    last_rx = now
                    self.last_rx_ns = now_ns
                for fr in frames:
                    self._handle(fr, now_ns)
            if now - last_rx > self.silence_s:
                self._drop(f"no frame from the robot for {self.silence_s:.1f} s (link timeout; "
                           "--link-timeout to change)", notify=True)
                return
            if now >= next_ping:
                next_ping = now + self.ping_interval_s
                self._ping_token = (self._ping_token + 1) & 0xFFFFFFFF
                self._ping_sent = {k: v for k, v in self._ping_sent.items() if now - v < 5.0}
                self._ping_sent[self._ping_token] = now
                try:
                    self._write(P.Ping(self._ping_token))
                except LinkDown as exc:
                    self._drop(str(exc), notify=True)
                    return

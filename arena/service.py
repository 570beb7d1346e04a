"""The runtime every service shares: presence (liveliness), once-a-second status, counters.

Usage::

    with open_session(args) as session, Service(session, "tracker", "cam0") as svc:
        svc.count("windows_in")
        svc.gauge("latency_ms", 3.2)
        svc.error("slice 42 is corrupt: ...")   # counted, logged at most once every 5 s

The status message (``arena/status/<role>/<name>``) carries every counter's total, its rate over
the last period, the gauges, the error count and the last error. The liveliness token
``arena/alive/<role>/<name>`` disappears when the process dies (within the lease when frozen).
"""

from __future__ import annotations

import atexit
import logging
import os
import socket
import threading
import time
from collections.abc import Callable

import zenoh

from arena.keys import alive_key, status_key
from arena.messages import Status

__all__ = ["Service", "stop_on_signals", "wait_until_stopped"]


class Service:
    """Presence and health of one running service; a context manager (stops the status thread and
    undeclares the token on exit)."""

    def __init__(self, session: zenoh.Session, role: str, name: str, period_s: float = 1.0,
                 logger: logging.Logger | None = None, error_log_interval_s: float = 5.0):
        self.session, self.role, self.name = session, role, name
        self.period_s = period_s
        self.log = logger or logging.getLogger(f"arena.{role}.{name}")
        self._status_key = status_key(role, name)
        self._alive_key = alive_key(role, name)
        self._lock = threading.Lock()
        self._counters: dict[str, int | float] = {}
        self._last_counters: dict[str, int | float] = {}
        self._gauges: dict[str, float | int | str] = {}
        self._errors = 0
        self._last_error: str | None = None
        self._last_error_log = -1e9
        self._suppressed = 0
        self._error_log_interval = error_log_interval_s
        self._state = "starting"
        self._started = time.monotonic()
        self._last_tick = self._started
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._token = None
        self._publisher = None
        self._hooks: list[Callable[["Service"], None]] = []
        self.last_status: Status | None = None

    # -- counters ---------------------------------------------------------------------------
    def count(self, key: str, n: int | float = 1) -> None:
        """Add ``n`` to the counter ``key`` (a total; its rate is reported too)."""
        with self._lock:
            self._counters[key] = self._counters.get(key, 0) + n

    def gauge(self, key: str, value: float | int | str) -> None:
        """Set the gauge ``key`` to its latest ``value`` (queue depth, latency, ...)."""
        with self._lock:
            self._gauges[key] = value

    def counter(self, key: str) -> int | float:
        """Current total of counter ``key`` (0 if never counted)."""
        with self._lock:
            return self._counters.get(key, 0)

    def error(self, message: str) -> None:
        """Count an error and log it, at most once per interval (with how many were suppressed)."""
        now = time.monotonic()
        with self._lock:
            self._errors += 1
            self._last_error = message[:500]
            if now - self._last_error_log < self._error_log_interval:
                self._suppressed += 1
                return
            suppressed, self._suppressed = self._suppressed, 0
            self._last_error_log = now
        extra = f" ({suppressed} similar errors not logged)" if suppressed else ""
        self.log.warning("%s%s", message, extra)

    def set_state(self, state: str) -> None:
        """Service state shown by ``arena status`` (starting, running, waiting, degraded, stopping)."""
        self._state = state

    def on_tick(self, hook: Callable[["Service"], None]) -> None:
        """Call ``hook(self)`` just before each status is published (to refresh gauges)."""
        self._hooks.append(hook)

    # -- lifecycle ----------------------------------------------------------------------------
    def __enter__(self) -> "Service":
        self._token = self.session.liveliness().declare_token(self._alive_key)
        self._publisher = self.session.declare_publisher(self._status_key)
        self._state = "running" if self._state == "starting" else self._state
        self._thread = threading.Thread(target=self._run, name=f"status-{self.role}-{self.name}", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._state = "stopping"
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        try:
            self.publish_status()
        except Exception:  # noqa: BLE001 - the session may already be gone
            pass
        for obj in (self._publisher, self._token):
            try:
                if obj is not None:
                    obj.undeclare()
            except Exception:  # noqa: BLE001
                pass

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            try:
                self.publish_status()
            except Exception as exc:  # noqa: BLE001 - status must never kill the service
                self.log.debug("status publish failed: %s", exc)

    def snapshot(self) -> Status:
        """Build the current :class:`Status` (and start a new rate period)."""
        for hook in list(self._hooks):
            try:
                hook(self)
            except Exception as exc:  # noqa: BLE001
                self.log.debug("status hook failed: %s", exc)
        now = time.monotonic()
        with self._lock:
            dt = max(now - self._last_tick, 1e-6)
            rates = {k: round((v - self._last_counters.get(k, 0)) / dt, 3) for k, v in self._counters.items()}
            self._last_counters = dict(self._counters)
            self._last_tick = now
            st = Status(role=self.role, name=self.name, host=socket.gethostname(), pid=os.getpid(),
                        time_ns=time.time_ns(), uptime_s=now - self._started, state=self._state,
                        counters=dict(self._counters), rates=rates, gauges=dict(self._gauges),
                        errors=self._errors, last_error=self._last_error)
        return st

    def publish_status(self) -> Status:
        """Publish one status now (also done once per period by the background thread)."""
        st = self.snapshot()
        self.last_status = st
        if self._publisher is not None:
            self._publisher.put(st.encode())
        return st


def stop_on_signals() -> threading.Event:
    """Make SIGTERM (and SIGINT) set the returned event and raise KeyboardInterrupt in the main
    thread, so services shut down through their ``finally``/``with`` blocks (motors stopped, files
    flushed, sessions closed) whether stopped by Ctrl-C, systemd or a launcher."""
    import signal

    stop = threading.Event()
    signalled = []

    def handler(signum, frame):  # noqa: ARG001
        if stop.is_set():
            return  # second signal while shutting down: let the cleanup finish
        stop.set()
        if not signalled:
            signalled.append(signum)
            atexit.register(ignore_late_signals)
        raise KeyboardInterrupt(f"signal {signum}")

    def ignore_late_signals() -> None:
        # The interpreter puts back the default action of every signal with a Python handler as it
        # finalizes: a second SIGTERM arriving then (a launcher's repeated stop) killed a process
        # that had finished its work (exit 143). Once a signal began the stop, later ones are
        # ignored to the end; ignoring survives finalization.
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, signal.SIG_IGN)

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, handler)
        signal.signal(signal.SIGINT, handler)
    return stop


def wait_until_stopped(stop: threading.Event, duration_s: float | None = None, tick_s: float = 0.2) -> None:
    """Wait for ``stop`` (or ``duration_s``) in short ticks.

    An untimed ``Event.wait()`` can sleep through SIGTERM: when the kernel delivers the signal to
    one of Zenoh's threads, Python runs the handler only once the main thread wakes up.
    """
    import time

    deadline = None if duration_s is None else time.monotonic() + duration_s
    while not stop.wait(tick_s):
        if deadline is not None and time.monotonic() >= deadline:
            return

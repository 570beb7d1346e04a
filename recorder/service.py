"""Zenoh side of the recorder: ``record`` (subscribe and write) and ``replay`` (read and publish).

Recording: one Zenoh subscriber on the key expressions; its callback only timestamps the sample and
puts it in a queue bounded in samples and bytes (a full queue drops the sample and counts it in
``dropped``), one writer thread empties the queue every 50 ms into :class:`~recorder.mcapio.RunWriter`.
Stopping (duration over, SIGTERM, Ctrl-C) undeclares the subscriber, writes what is queued for at
most a few seconds (the rest counted as dropped) and finishes the MCAP file.

With a :class:`~recorder.foxglove_views.FoxgloveConverter`, the Foxglove views of each sample (poses,
transforms, scene, event images) are made on a second, best-effort thread after the sample itself is
written: a slow view never delays or drops an arena sample; views the thread cannot keep up with are
dropped and counted (``views_dropped``).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import zenoh

from arena.service import Service
from recorder.mcapio import RecordedMessage, RunWriter, read_run

#: how often the writer thread looks for new samples (s)
_DRAIN_S = 0.05


def wait_stop(stop: threading.Event, timeout_s: float | None = None, tick_s: float = 0.2) -> bool:
    """Wait until ``stop`` is set or ``timeout_s`` seconds passed (None: forever); True if stopped.

    Waits in short ticks: a signal (SIGTERM from a launcher) may be delivered to any thread, and
    Python runs its handler in the main thread only once that thread wakes up; an untimed
    ``Event.wait()`` in the main thread could then sleep through the signal forever."""
    deadline = None if timeout_s is None else time.monotonic() + timeout_s
    while not stop.is_set():
        left = tick_s if deadline is None else min(tick_s, deadline - time.monotonic())
        if left <= 0:
            return False
        stop.wait(left)
    return True


@dataclass
class RecordResult:
    """What one recording wrote: messages, payload bytes, samples dropped (queue full, or still queued
    when the stop's time was up), seconds recorded, and the Foxglove messages derived from them, with
    the samples given no view: ``views_dropped`` (the view path was behind, or stopping) and
    ``views_skipped`` (a window of an implausible size, see :class:`~recorder.foxglove_views.FoxgloveConverter`)."""

    path: Path
    messages: int
    bytes: int
    dropped: int
    seconds: float
    derived: int = 0
    views_dropped: int = 0
    views_skipped: int = 0


#: bytes of one queued sample besides its payload (tuple, key, ints), for the queue's byte bound
_ENTRY_BYTES = 200


class _Recording:
    """The state of one :func:`record` run: the write queue, the view queue and their threads."""

    def __init__(self, svc: Service, writer: RunWriter, foxglove, queue_size: int, queue_bytes: int,
                 view_queue: int, view_queue_bytes: int, stop_within_s: float) -> None:
        self.svc, self.writer, self.foxglove = svc, writer, foxglove
        self.queue_size, self.queue_bytes = queue_size, queue_bytes
        self.view_queue, self.view_queue_bytes = view_queue, view_queue_bytes
        self.stop_within_s = stop_within_s
        self.pending: deque = deque()     # (key, payload, log ns), arena samples to write
        self.views: deque = deque()       # the same, for the view thread
        self.qbytes = [0, 0]              # bytes in pending, in views
        self.qlock = threading.Lock()
        self.wlock = threading.Lock()     # the MCAP writer, shared by the two threads
        self.closing = threading.Event()
        self.views_closed = False
        self.deadline = float("inf")
        if foxglove is not None:
            from recorder.foxglove_views import schema_data
            self.schema_data = schema_data

    def on_sample(self, sample: zenoh.Sample) -> None:
        payload = sample.payload.to_bytes()
        size = len(payload) + _ENTRY_BYTES
        with self.qlock:
            full = len(self.pending) >= self.queue_size or self.qbytes[0] + size > self.queue_bytes
            if not full:
                self.qbytes[0] += size
                self.pending.append((str(sample.key_expr), payload, time.time_ns()))
        if full:
            self.svc.count("dropped")
            self.svc.error(f"write queue full ({self.queue_size} samples or {self.queue_bytes / 1e6:.0f} MB): "
                           "dropping samples")

    def write_loop(self) -> None:
        svc = self.svc
        while True:
            if not self.pending:
                if self.closing.is_set():
                    return
                self.closing.wait(_DRAIN_S)
                continue
            if time.monotonic() > self.deadline:   # stopping, and its time is up: count what is left
                with self.qlock:
                    left = len(self.pending)
                    self.pending.clear()
                    self.qbytes[0] = 0
                svc.count("dropped", left)
                svc.error(f"stopping: {left} queued samples not written within {self.stop_within_s:g} s")
                return
            item = self.pending.popleft()
            key, payload, log_ns = item
            with self.qlock:
                self.qbytes[0] -= len(payload) + _ENTRY_BYTES
            try:
                with self.wlock:
                    self.writer.add(key, payload, log_ns)
            except Exception as exc:  # noqa: BLE001 - one bad sample must not end the recording
                svc.error(f"cannot record a sample on {key}: {exc}")
                continue
            svc.count("messages")
            svc.count("bytes", len(payload))
            if self.foxglove is not None:
                self._queue_view(item)

    def _queue_view(self, item) -> None:
        size = len(item[1]) + _ENTRY_BYTES
        with self.qlock:
            full = len(self.views) >= self.view_queue or self.qbytes[1] + size > self.view_queue_bytes
            if not full:
                self.qbytes[1] += size
                self.views.append(item)
        if full:
            self.svc.count("views_dropped")

    def view_loop(self) -> None:
        while True:   # stopping: views are made until the queue is empty or the stop's time is up
            if self.closing.is_set() and (not self.views or time.monotonic() > self.deadline):
                break
            if not self.views:
                self.closing.wait(_DRAIN_S)
                continue
            key, payload, log_ns = self.views.popleft()
            with self.qlock:
                self.qbytes[1] -= len(payload) + _ENTRY_BYTES
            self.write_views(key, payload, log_ns)
        with self.qlock:   # the views not made in time are counted
            left = len(self.views)
            self.views.clear()
            self.qbytes[1] = 0
        self.svc.count("views_dropped", left)

    def write_views(self, key: str, payload: bytes, log_ns: int) -> None:
        foxglove, svc = self.foxglove, self.svc
        rejected = foxglove.rejected
        try:
            msgs = foxglove.convert(key, payload, log_ns)
            with self.wlock:
                if self.views_closed:
                    return
                for m in msgs:
                    self.writer.add_derived(m.topic, m.schema, self.schema_data(m.schema), m.data, m.log_time_ns,
                                            m.publish_time_ns)
            svc.count("foxglove", len(msgs))
        except Exception as exc:  # noqa: BLE001 - a view that fails must not end the recording
            svc.error(f"cannot convert a sample on {key} for Foxglove: {exc}")
        if foxglove.rejected > rejected:  # recorded as received, but not shown in Foxglove
            svc.error(f"no Foxglove view of a bad message: {foxglove.last_error}")
        notes = getattr(foxglove, "notes", None)
        while notes:
            svc.log.warning("%s", notes.pop(0))

    def on_tick(self, s) -> None:
        s.gauge("queue", len(self.pending))
        s.gauge("queue_bytes", self.qbytes[0])
        if self.foxglove is not None:
            s.gauge("view_queue", len(self.views))
            s.gauge("foxglove_rejected", self.foxglove.rejected)
            s.gauge("views_skipped", getattr(self.foxglove, "skipped", 0))

    def finish(self, subs, thread: threading.Thread, viewer: threading.Thread | None, stopped_by: str,
               t0: float) -> None:
        """Stop taking samples, write what is queued until the deadline, count the rest, and write
        the ``arena.summary`` metadata."""
        svc, writer = self.svc, self.writer
        self.deadline = time.monotonic() + self.stop_within_s
        for s in subs:     # nothing new is taken
            s.undeclare()
        self.closing.set()      # the writer drains what is left until the deadline
        thread.join()      # returns at the deadline at the latest (after the one write in progress)
        with self.qlock:        # taken after the writer had returned (a callback still running): counted
            late = len(self.pending)
            self.pending.clear()
        if late:
            svc.count("dropped", late)
        if viewer is not None:
            viewer.join(max(0.0, self.deadline - time.monotonic()))   # a view being made is abandoned
        with self.wlock:
            self.views_closed = True
            summary = {"messages": writer.messages, "bytes": writer.bytes,
                       "dropped": int(svc.counter("dropped")), "derived": writer.derived,
                       "views_dropped": int(svc.counter("views_dropped")),
                       "views_skipped": int(getattr(self.foxglove, "skipped", 0)), "stopped_by": stopped_by,
                       "seconds": f"{time.monotonic() - t0:.3f}"}
            try:
                writer.add_metadata("arena.summary", {k: str(v) for k, v in summary.items()})
            except Exception as exc:  # noqa: BLE001 - the file is finished anyway
                svc.error(f"cannot write the summary metadata: {exc}")


def record(session: zenoh.Session, path: str | Path, keys: Iterable[str], stop: threading.Event,
           duration_s: float | None = None, name: str = "recorder", queue_size: int = 10_000,
           on_ready: Callable[[], None] | None = None, metadata: dict[str, str] | None = None,
           foxglove=None, queue_bytes: int = 256 << 20, view_queue: int = 256, view_queue_bytes: int = 32 << 20,
           stop_within_s: float = 5.0) -> RecordResult:
    """Record every sample on ``keys`` into the MCAP file ``path`` until ``stop`` is set or
    ``duration_s`` seconds have passed; always finishes the file. Publishes status and liveliness
    as ``recorder/<name>`` (counters ``messages``, ``bytes``, ``dropped``, ``foxglove``,
    ``views_dropped``; gauges ``queue``, ``queue_bytes``, ``view_queue``, ``foxglove_rejected``,
    ``views_skipped``).

    The write queue holds at most ``queue_size`` samples and ``queue_bytes`` bytes: beyond either a
    sample is dropped and counted in ``dropped``. ``foxglove``: a
    :class:`~recorder.foxglove_views.FoxgloveConverter` whose messages are written too (None: only
    the arena samples). Views are best effort: made on their own thread from a queue of at most
    ``view_queue`` samples and ``view_queue_bytes`` bytes, so a slow view never delays or drops an
    arena sample; a sample arriving when that queue is full gets no view (``views_dropped``).

    Stopping: the subscribers are undeclared (nothing new is taken), the samples still queued are
    written and their views made for at most ``stop_within_s`` seconds (samples left are counted in
    ``dropped``, views left in ``views_dropped``; a view being made is abandoned), then the file is
    finished, with these counts in its ``arena.summary`` metadata."""
    t0 = time.monotonic()
    keys = [str(zenoh.KeyExpr(k)) for k in keys]   # a bad one raises here, before the file is truncated
    with Service(session, "recorder", name) as svc, RunWriter(path, metadata=metadata) as writer:
        rec = _Recording(svc, writer, foxglove, queue_size, queue_bytes, view_queue, view_queue_bytes,
                         stop_within_s)
        svc.on_tick(rec.on_tick)
        thread = threading.Thread(target=rec.write_loop, name="mcap-writer", daemon=True)
        thread.start()
        viewer = None
        if foxglove is not None:
            viewer = threading.Thread(target=rec.view_loop, name="mcap-views", daemon=True)
            viewer.start()
        subs = [session.declare_subscriber(k, rec.on_sample) for k in keys]
        stopped_by = "duration"
        try:
            if on_ready is not None:
                on_ready()
            if wait_stop(stop, duration_s):
                stopped_by = "stop"
        except KeyboardInterrupt:
            stopped_by = "stop"
        finally:
            rec.finish(subs, thread, viewer, stopped_by, t0)
        return RecordResult(Path(path), writer.messages, writer.bytes, int(svc.counter("dropped")),
                            time.monotonic() - t0, writer.derived, int(svc.counter("views_dropped")),
                            int(getattr(foxglove, "skipped", 0)))


@dataclass
class ReplayResult:
    """What one replay published: messages, passes over the file, seconds, and the lag behind the
    recorded timing at the end (s; 0 when replaying as fast as possible)."""

    messages: int
    passes: int
    seconds: float
    max_lag_s: float


def replay(session: zenoh.Session, path: str | Path, stop: threading.Event, speed: float = 1.0,
           keys: Iterable[str] | None = None, loop: bool = False,
           on_message: Callable[[RecordedMessage], None] | None = None) -> ReplayResult:
    """Publish the recorded samples of ``path`` on their original keys with their original payloads,
    in the order they were received, with the recorded spacing divided by ``speed`` (0: as fast as possible).
    ``loop`` starts again at the end until ``stop`` is set. Publishers block rather than drop when
    the network is congested (a replay is meant to be lossless)."""
    keys = list(keys) if keys else None
    pubs: dict[str, zenoh.Publisher] = {}
    n, passes, max_lag = 0, 0, 0.0
    t_begin = time.monotonic()
    try:
        while not stop.is_set():
            t0_wall, t0_log, n_pass = None, None, n
            for m in read_run(path, keys):
                if stop.is_set():
                    break
                if speed > 0:
                    if t0_wall is None:
                        t0_wall, t0_log = time.monotonic(), m.log_time_ns
                    due = t0_wall + (m.log_time_ns - t0_log) / 1e9 / speed
                    wait = due - time.monotonic()
                    if wait > 0 and wait_stop(stop, wait):
                        break
                    max_lag = max(max_lag, -wait)
                pub = pubs.get(m.key)
                if pub is None:
                    pub = pubs[m.key] = session.declare_publisher(
                        m.key, congestion_control=zenoh.CongestionControl.BLOCK,
                        reliability=zenoh.Reliability.RELIABLE)
                pub.put(m.payload)
                n += 1
                if on_message is not None:
                    on_message(m)
            else:
                passes += 1
                if not loop or n == n_pass:  # nothing to loop over
                    break
    except KeyboardInterrupt:  # SIGTERM/Ctrl-C through arena.service.stop_on_signals: report what was done
        pass
    finally:
        for pub in pubs.values():
            pub.undeclare()
    return ReplayResult(n, passes, time.monotonic() - t_begin, max_lag)

"""Zenoh side of the recorder: ``record`` (subscribe and write) and ``replay`` (read and publish).

Recording: one Zenoh subscriber on the key expressions; its callback only timestamps the sample and
puts it in a bounded queue (a full queue drops the sample and counts it in ``dropped``), one
writer thread empties the queue every 50 ms into :class:`~recorder.mcapio.RunWriter`. Stopping (duration over,
SIGTERM, Ctrl-C) undeclares the subscriber, drains the queue and finishes the MCAP file.

With a :class:`~recorder.foxglove_views.FoxgloveConverter`, the writer thread also writes the Foxglove
views of each sample (poses, transforms, scene, event images) after the sample itself: the Zenoh
callback stays as cheap as before, and a sample is on disk before its views are made.
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
    """What one recording wrote: messages, payload bytes, samples dropped, seconds recorded, and
    the Foxglove messages derived from them."""

    path: Path
    messages: int
    bytes: int
    dropped: int
    seconds: float
    derived: int = 0


def record(session: zenoh.Session, path: str | Path, keys: Iterable[str], stop: threading.Event,
           duration_s: float | None = None, name: str = "recorder", queue_size: int = 10_000,
           on_ready: Callable[[], None] | None = None, metadata: dict[str, str] | None = None,
           foxglove=None) -> RecordResult:
    """Record every sample on ``keys`` into the MCAP file ``path`` until ``stop`` is set or
    ``duration_s`` seconds have passed; always finishes the file. Publishes status and liveliness
    as ``recorder/<name>`` (counters ``messages``, ``bytes``, ``dropped``, ``foxglove``; gauges
    ``queue``, ``foxglove_rejected``).

    ``foxglove``: a :class:`~recorder.foxglove_views.FoxgloveConverter` whose messages are written too
    (None: only the arena samples)."""
    # The Zenoh callback appends to a deque and the writer drains it every 50 ms: a
    # queue.Queue woke the writer thread for each of the ~1 000 samples a second of a demo.
    pending: deque = deque()
    closing = threading.Event()
    if foxglove is not None:
        from recorder.foxglove_views import schema_data
    t0 = time.monotonic()
    with Service(session, "recorder", name) as svc, RunWriter(path, metadata=metadata) as writer:
        def on_sample(sample: zenoh.Sample) -> None:
            if len(pending) >= queue_size:
                svc.count("dropped")
                svc.error(f"write queue full ({queue_size} samples): dropping samples")
                return
            pending.append((str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()))

        def write_loop() -> None:
            while True:
                if not pending:
                    if closing.is_set():
                        return
                    closing.wait(_DRAIN_S)
                    continue
                key, payload, log_ns = pending.popleft()
                try:
                    writer.add(key, payload, log_ns)
                except Exception as exc:  # noqa: BLE001 - one bad sample must not end the recording
                    svc.error(f"cannot record a sample on {key}: {exc}")
                    continue
                svc.count("messages")
                svc.count("bytes", len(payload))
                if foxglove is not None:
                    write_views(key, payload, log_ns)

        def write_views(key: str, payload: bytes, log_ns: int) -> None:
            rejected = foxglove.rejected
            try:
                for m in foxglove.convert(key, payload, log_ns):
                    writer.add_derived(m.topic, m.schema, schema_data(m.schema), m.data, m.log_time_ns,
                                       m.publish_time_ns)
                    svc.count("foxglove")
            except Exception as exc:  # noqa: BLE001 - a view that fails must not end the recording
                svc.error(f"cannot convert a sample on {key} for Foxglove: {exc}")
            if foxglove.rejected > rejected:  # recorded as received, but not shown in Foxglove
                svc.error(f"no Foxglove view of a bad message: {foxglove.last_error}")

        def on_tick(s) -> None:
            s.gauge("queue", len(pending))
            if foxglove is not None:
                s.gauge("foxglove_rejected", foxglove.rejected)

        svc.on_tick(on_tick)
        thread = threading.Thread(target=write_loop, name="mcap-writer", daemon=True)
        thread.start()
        subs = [session.declare_subscriber(k, on_sample) for k in keys]
        try:
            if on_ready is not None:
                on_ready()
            wait_stop(stop, duration_s)
        except KeyboardInterrupt:
            pass
        finally:
            for s in subs:
                s.undeclare()
            closing.set()      # the writer drains what is left, then returns
            thread.join()
        return RecordResult(Path(path), writer.messages, writer.bytes, int(svc.counter("dropped")),
                            time.monotonic() - t0, writer.derived)


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

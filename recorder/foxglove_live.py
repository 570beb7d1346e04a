"""Zenoh side of ``arena foxglove``: serve the arena live over Foxglove's WebSocket protocol.

One Zenoh subscriber per selector (tracks, event windows); its callback only timestamps the sample
and puts it in a bounded queue (a full queue drops the sample and counts it in ``dropped``). One
worker thread converts each sample with :class:`~recorder.foxglove_views.FoxgloveConverter` and logs
the result on a channel of the official ``foxglove-sdk``'s WebSocket server, one channel per
topic, protobuf with the schema's ``FileDescriptorSet``: the same topics and bytes as the
``foxglove/...`` channels of ``arena record``.

Needs the optional ``foxglove-sdk`` package (imported here only).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import zenoh

try:
    import foxglove
except ImportError as exc:  # the optional 'foxglove' extra
    raise ImportError(f"arena foxglove needs the foxglove-sdk package ({exc}): pip install foxglove-sdk",
                      name="foxglove-sdk") from exc

from arena.keys import ALL_EVENTS, ALL_ROBOTS
from arena.service import Service
from recorder.foxglove_views import FoxgloveConverter, FoxgloveMessage, schema_data
from recorder.service import wait_stop


class FoxgloveServerError(RuntimeError):
    """The WebSocket server could not start (address in use, bad host); the text says what to do."""


@dataclass
class ServeResult:
    """What one ``serve`` did: samples received, Foxglove messages logged, seconds served."""

    samples: int
    messages: int
    seconds: float


class LiveServer:
    """The official SDK's Foxglove WebSocket server on ``host:port`` (0: any free port), with one
    protobuf channel per topic, created on its first message. A context manager (stops the server).
    Raises :class:`FoxgloveServerError` when it cannot listen."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, name: str = "arena"):
        self._ctx = foxglove.Context()
        try:
            self._server = foxglove.start_server(name=name, host=host, port=port, context=self._ctx)
        except Exception as exc:  # noqa: BLE001 - the SDK raises its own error type for a busy or bad address
            raise FoxgloveServerError(f"cannot serve on {host}:{port}: {exc} "
                                      "(is another Foxglove server running? try --port 0)") from None
        self.url = f"ws://{host}:{self._server.port}"
        self._channels: dict[str, foxglove.Channel] = {}

    @property
    def channels(self) -> int:
        """How many topics have been advertised."""
        return len(self._channels)

    def log(self, m: FoxgloveMessage) -> None:
        """Send one message to the clients subscribed to its topic."""
        ch = self._channels.get(m.topic)
        if ch is None:
            ch = self._channels[m.topic] = foxglove.Channel(
                m.topic, schema=foxglove.Schema(name=m.schema, encoding="protobuf", data=schema_data(m.schema)),
                message_encoding="protobuf", context=self._ctx)
        ch.log(m.data, log_time=m.log_time_ns)

    def stop(self) -> None:
        """Stop serving (idempotent)."""
        self._server.stop()

    def __enter__(self) -> "LiveServer":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def serve(session: zenoh.Session, converter: FoxgloveConverter, live: LiveServer, stop: threading.Event,
          name: str = "foxglove", queue_size: int = 2_000, on_ready: Callable[[str], None] | None = None,
          keys: tuple[str, ...] = (ALL_ROBOTS, ALL_EVENTS)) -> ServeResult:
    """Serve the Foxglove views of the samples on ``keys`` on ``live`` until ``stop`` is set.
    ``on_ready(url)`` is called once the subscribers are declared. Publishes status and liveliness
    as ``viewer/<name>`` (counters ``samples``, ``messages``, ``dropped``; gauges ``queue``,
    ``rejected``, ``channels``, ``url``)."""
    pending: deque = deque()
    wake = threading.Event()
    done = threading.Event()
    counts = {"samples": 0, "messages": 0}
    t0 = time.monotonic()
    with Service(session, "viewer", name) as svc:
        def on_sample(sample: zenoh.Sample) -> None:
            if len(pending) >= queue_size:
                svc.count("dropped")
                svc.error(f"conversion queue full ({queue_size} samples): dropping samples")
                return
            pending.append((str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()))
            wake.set()

        def work() -> None:
            while not done.is_set() or pending:
                if not pending:
                    wake.wait(0.2)
                    wake.clear()
                    continue
                key, payload, log_ns = pending.popleft()
                counts["samples"] += 1
                svc.count("samples")
                rejected = converter.rejected
                try:
                    for m in converter.convert(key, payload, log_ns):
                        live.log(m)
                        counts["messages"] += 1
                        svc.count("messages")
                except Exception as exc:  # noqa: BLE001 - one bad sample must not end the server
                    svc.error(f"cannot convert a sample on {key} for Foxglove: {exc}")
                if converter.rejected > rejected:
                    svc.error(f"no Foxglove view of a bad message: {converter.last_error}")
                while converter.notes:   # windows of an implausible size: no view (once per camera and size)
                    svc.log.warning("%s", converter.notes.pop(0))

        svc.on_tick(lambda s: (s.gauge("queue", len(pending)), s.gauge("rejected", converter.rejected),
                               s.gauge("skipped", converter.skipped),
                               s.gauge("channels", live.channels), s.gauge("url", live.url)))
        thread = threading.Thread(target=work, name="foxglove", daemon=True)
        thread.start()
        subs = [session.declare_subscriber(k, on_sample) for k in keys]
        try:
            if on_ready is not None:
                on_ready(live.url)
            wait_stop(stop)
        except KeyboardInterrupt:
            pass
        finally:
            for s in subs:
                s.undeclare()
            done.set()
            wake.set()
            thread.join(timeout=10)
    return ServeResult(counts["samples"], counts["messages"], time.monotonic() - t0)

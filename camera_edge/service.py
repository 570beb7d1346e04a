"""The edge service: read a source, filter, slice, encode and publish event windows on Zenoh.

Threads: the main thread reads the source and runs :class:`~camera_edge.pipeline.EdgePipeline`;
a publisher thread encodes and puts windows. Between them a bounded queue: for a live source
a full queue drops the oldest window (counted in ``windows_dropped`` and in every message's
``dropped``), so the camera is never stalled; for a file the reader waits instead. The windows
of one chunk are handed over together, and the publisher takes up to a quarter of the queue at
once: one lock and one wake-up per batch, not per window (on one core each hand-over cost ~15 µs
of thread switching, 6-12 % of a simulator window's cost). The Zenoh
publisher uses congestion control DROP, and encoding is skipped while nobody subscribes
(publisher matching status).
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from pathlib import Path

import zenoh

from arena.codec import encode
from arena.events import empty_events
from arena.keys import events_key
from arena.messages import EventWindow
from arena.service import Service
from camera_edge.clock import SensorClock
from camera_edge.filters import HotPixelFilter
from camera_edge.pipeline import EdgePipeline, Window
from camera_edge.sources import EventSource, FileSource

log = logging.getLogger("camera_edge.service")
#: how long a new window publisher waits for the router to report an existing subscriber, s
MATCH_WAIT_S = 1.0


class WindowPublisher:
    """Encodes and publishes windows from a bounded queue on its own thread."""

    def __init__(self, session: zenoh.Session, camera: str, width: int, height: int, svc: Service,
                 codec: str, queue_size: int = 32) -> None:
        self.camera, self.width, self.height, self.svc, self.codec = camera, width, height, svc, codec
        self._pub = session.declare_publisher(events_key(camera), congestion_control=zenoh.CongestionControl.DROP,
                                              express=True)
        self._matching = bool(self._pub.matching_status.matching)
        self._listener = self._pub.declare_matching_listener(self._on_matching)
        # the router tells a new publisher of the subscribers it already has within a round trip
        # (longer on a busy host): without this wait, the first windows of a replay were counted
        # unsubscribed and not sent although a tracker was listening
        deadline = time.monotonic() + MATCH_WAIT_S
        while not self._matching and time.monotonic() < deadline:
            time.sleep(0.01)
        self._q: collections.deque[Window] = collections.deque()
        self._size = queue_size
        self._batch = max(1, queue_size // 4)
        self._cv = threading.Condition()
        self._closing = False
        self.seq = 0
        self.dropped = 0
        self._thread = threading.Thread(target=self._run, name=f"edge-pub-{camera}", daemon=True)
        self._thread.start()

    def _on_matching(self, status) -> None:
        self._matching = bool(status.matching)
        log.info("%s: %s", self.camera, "a subscriber is listening" if self._matching else "no subscriber")

    @property
    def matching(self) -> bool:
        """Whether some subscriber matches the windows' key."""
        return self._matching

    def submit(self, windows: list[Window], block: bool) -> None:
        """Queue windows (in order); when full, wait (``block``) or drop the oldest (counted).
        One lock and one wake-up of the publisher for all of them."""
        if not windows:
            return
        with self._cv:
            for window in windows:
                while block and len(self._q) >= self._size and not self._closing:
                    self._cv.notify_all()
                    self._cv.wait(0.1)
                if len(self._q) >= self._size:
                    self._q.popleft()
                    self.dropped += 1
                    self.seq += 1
                    self.svc.count("windows_dropped")
                self._q.append(window)
            self._cv.notify_all()

    def depth(self) -> int:
        return len(self._q)

    def _run(self) -> None:
        while True:
            with self._cv:
                while not self._q and not self._closing:
                    self._cv.wait(0.1)
                if not self._q:
                    return
                batch = []
                while self._q and len(batch) < self._batch:
                    batch.append((self._q.popleft(), self.seq))
                    self.seq += 1
                self._cv.notify_all()
            for w, seq in batch:
                try:
                    self._publish(w, seq)
                except Exception as exc:  # noqa: BLE001 - keep publishing the next windows
                    self.svc.error(f"window {seq}: {exc}")

    def _publish(self, w: Window, seq: int) -> None:
        self.svc.count("windows")
        if not self._matching:
            self.svc.count("windows_unsubscribed")
            return
        t0 = time.perf_counter()
        data = encode(w.events, self.codec, t_ref_us=w.t_start_us)
        msg = EventWindow(camera=self.camera, seq=seq, t_start_us=w.t_start_us, t_end_us=w.t_end_us,
                          width=self.width, height=self.height, count=int(w.events.size), codec=self.codec,
                          data=data, dropped=self.dropped, filtered=int(w.filtered), publish_ns=time.time_ns(),
                          sensor_to_host_ns=w.sensor_to_host_ns)
        payload = msg.encode()
        enc_ms = (time.perf_counter() - t0) * 1e3
        self._pub.put(payload)
        self.svc.count("events_out", w.events.size)
        self.svc.count("bytes_out", len(payload))
        self.svc.count("encode_ms", enc_ms)
        self.svc.gauge("encode_ms_last", round(enc_ms, 3))
        if w.events.size:
            self.svc.gauge("bytes_per_event", round(len(data) / w.events.size, 3))

    def close(self, timeout_s: float = 5.0) -> None:
        """Publish what is queued (up to ``timeout_s``), then stop."""
        with self._cv:
            self._closing = True
            self._cv.notify_all()
        self._thread.join(timeout_s)
        for obj in (self._listener, self._pub):
            try:
                obj.undeclare()
            except Exception:  # noqa: BLE001 - session may be closing
                pass


def run_edge(session: zenoh.Session, source: EventSource, pipeline: EdgePipeline, camera: str, codec: str,
             queue_size: int = 32, duration_s: float | None = None, stop: threading.Event | None = None,
             hot_save: str | Path | None = None) -> dict:
    """Run the edge until the source ends, ``duration_s`` passes or ``stop`` is set.

    ``hot_save``: once a hot-pixel filter has learnt its mask, write the hot pixels there (``x,y``
    lines, or ``.npy``) for ``--hot-pixels FILE`` next time.

    Returns the final counters (events in/out, windows, drops, ...)."""
    stop = stop or threading.Event()
    live = not isinstance(source, FileSource)
    # host capture time of the windows: from a live camera, or a file played at the sensor's pace
    clock = SensorClock() if live or getattr(source, "speed", 0.0) == 1.0 else None

    def stamp(wins: list) -> list:
        if clock is not None and clock.offset_ns is not None:
            for w in wins:
                w.sensor_to_host_ns = clock.offset_ns
        return wins
    # load the compiled codec and filters now (seconds on a busy machine), not on the first windows
    encode(empty_events(1), codec)
    for f in pipeline.filters:
        f._apply(empty_events(0))
    with Service(session, "edge", camera) as svc:
        pub = WindowPublisher(session, camera, source.width, source.height, svc, codec, queue_size)
        cpu0, wall0 = time.process_time(), time.monotonic()
        last = [cpu0, wall0]
        hot_reported: set[int] = set()

        def tick(s: Service) -> None:
            cpu, wall = time.process_time(), time.monotonic()
            s.gauge("cpu_percent", round(100 * (cpu - last[0]) / max(wall - last[1], 1e-6), 1))
            last[0], last[1] = cpu, wall
            s.gauge("queue_depth", pub.depth())
            s.gauge("subscribed", int(pub.matching))
            s.gauge("source_invalid", source.invalid)
            s.gauge("source_skipped", source_skipped(source))
            _gauge_filters(s, pipeline, camera, hot_reported, hot_save)
            for attr in ("reconnects", "connected"):
                if hasattr(source, attr):
                    s.gauge(f"source_{attr}", int(getattr(source, attr)))

        svc.on_tick(tick)
        log.info("edge %s: %s (%d x %d) -> %s, codec %s", camera, source.name, source.width, source.height,
                 events_key(camera), codec)
        try:
            while not stop.is_set():
                if duration_s is not None and time.monotonic() - wall0 >= duration_s:
                    break
                ev = source.read(timeout=0.05)
                if ev is None:
                    wins = stamp(pipeline.flush())
                    svc.count("events_filtered", sum(w.filtered for w in wins))
                    pub.submit(wins, block=True)
                    break
                svc.count("events_in", ev.size)
                if clock is not None and ev.size:
                    clock.observe(int(ev["t"][-1]), time.time_ns())
                wins = stamp(pipeline.push(ev, source.time_us))
                svc.count("events_filtered", sum(w.filtered for w in wins))
                pub.submit(wins, block=not live)
        finally:
            pub.close()
            result = {"events_in": pipeline.n_in, "events_kept": pipeline.n_out, "windows": pub.seq,
                      "windows_dropped": pub.dropped,
                      "windows_unsubscribed": int(svc.counter("windows_unsubscribed")),
                      "invalid": source.invalid, "skipped": dict(getattr(source, "skipped", {})),
                      "cpu_s": time.process_time() - cpu0,
                      "wall_s": time.monotonic() - wall0}
    return result


def source_skipped(source: EventSource) -> int:
    """How many parts of its input ``source`` skipped, all units together (not those a unit
    ending in ")" says were kept, nor invalid events: ``source.invalid``)."""
    return sum(n for unit, n in getattr(source, "skipped", {}).items() if not unit.endswith(")"))


def _gauge_filters(s: Service, pipeline: EdgePipeline, camera: str, hot_reported: set[int],
                   hot_save: str | Path | None) -> None:
    """Gauge each filter's events in and out; once a hot-pixel filter has learnt its mask,
    gauge and log its hot pixels, and write them to ``hot_save`` (if given) for
    ``--hot-pixels FILE`` next time, once per filter (``hot_reported``: ids of those done)."""
    for f in pipeline.filters:
        s.gauge(f"filter_{f.name}_in", f.n_in)
        s.gauge(f"filter_{f.name}_out", f.n_out)
        if isinstance(f, HotPixelFilter) and not f.learning:
            hot = f.hot_pixels_
            s.gauge("hot_pixels", len(hot))
            if id(f) not in hot_reported:
                hot_reported.add(id(f))
                log.info("edge %s: %d hot pixel(s) masked%s%s", camera, len(hot),
                         ": " if len(hot) else "", " ".join(f"{x},{y}" for x, y in hot[:20].tolist()))
                if hot_save is not None:
                    try:
                        f.save(hot_save)
                        log.info("edge %s: hot pixels saved to %s (use: --hot-pixels %s)", camera,
                                 hot_save, hot_save)
                    except OSError as exc:
                        s.error(f"cannot save the hot pixels to {hot_save}: {exc}")

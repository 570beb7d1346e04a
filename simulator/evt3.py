"""EVT 3.0 encoder (Prophesee) and a TCP camera server streaming it.

EVT 3.0 is a stream of little-endian 16-bit words, type in bits 15..12:

====  ==============  ==========================================================
0x0   EVT_ADDR_Y      bits 10..0 y (bit 11 system type, 0 = master camera)
0x2   EVT_ADDR_X      bit 11 polarity, bits 10..0 x: one event at (x, y, p, t)
0x3   VECT_BASE_X     bit 11 polarity, bits 10..0 base x for the vectors below
0x4   VECT_12         bits 11..0: events at base .. base+11 (bit i -> base+i); base += 12
0x5   VECT_8          bits 7..0: events at base .. base+7; base += 8
0x6   EVT_TIME_LOW    bits 11..0: timestamp bits 11..0 (µs)
0x8   EVT_TIME_HIGH   bits 11..0: timestamp bits 23..12 (µs); the 24-bit time wraps
====  ==============  ==========================================================

Like the sensor, the encoder writes a TIME_HIGH word for every 4096 µs period even when no
event happened (so a decoder sees every period and can count 24-bit wraps), repeats
TIME_HIGH / TIME_LOW / ADDR_Y at the start of every packet (so packets can be decoded
after a lost one), and packs runs of events with the same time, row and polarity into
VECT_12 / VECT_8 words. Events with the same timestamp come out ordered by (y, p, x).
"""

from __future__ import annotations

import logging
import queue
import socket
import threading

import numpy as np
from numba import njit

from arena.events import select_events


log = logging.getLogger("simulator.evt3")

EVT_ADDR_Y, EVT_ADDR_X, VECT_BASE_X, VECT_12, VECT_8 = 0x0, 0x2, 0x3, 0x4, 0x5
EVT_TIME_LOW, EVT_TIME_HIGH = 0x6, 0x8
TIME_WRAP_US = 1 << 24


def canonical_order(events: np.ndarray) -> np.ndarray:
    """Events reordered as the encoder emits them: by t, then y, p, x (a stable view for
    comparing with decoded streams)."""
    if len(events) == 0:
        return events
    t = events["t"].astype(np.int64)
    x, y = events["x"].astype(np.int64), events["y"].astype(np.int64)
    if t.min() < 0 or t.max() >= 1 << 40 or x.max() > 0x7FF or y.max() > 0x7FF:
        return events[np.lexsort((events["x"], events["p"], events["y"], events["t"]))]
    # one packed key sorts ~3x faster than a 4-key lexsort (the simulator's camera runs this
    # on every 10 ms block): t (40 bits) | y (11) | p (1) | x (11)
    key = (t << 23) | (y << 12) | (events["p"].astype(np.int64) << 11) | x
    return select_events(events, np.argsort(key, kind="stable"))


@njit(cache=True, nogil=True)
def _encode(x, y, p, t, state, out):
    """Encode events sorted by (t, y, p, x) into ``out`` (uint16); returns words written.

    ``state`` = [last TIME_HIGH period (t >> 12, unwrapped; -1 = none yet), last TIME_LOW
    (-1 = none), last y (-1 = none), resync flag (1 = repeat the context first)].
    """
    n = x.shape[0]
    w = 0
    th, tl, ly, force = state[0], state[1], state[2], state[3]
    i = 0
    while i < n:
        ti = t[i]
        period = ti >> 12
        if th < 0:
            th = period
            out[w] = (EVT_TIME_HIGH << 12) | (th & 0xFFF)
            w += 1
            tl = -1
            force = 0
        filled = False
        while th < period:          # every 4096 µs period gets its TIME_HIGH
            th += 1
            out[w] = (EVT_TIME_HIGH << 12) | (th & 0xFFF)
            w += 1
            tl = -1
            filled = True
        if force:
            if not filled:
                out[w] = (EVT_TIME_HIGH << 12) | (th & 0xFFF)
                w += 1
            tl = -1
            ly = -1
            force = 0
        low = ti & 0xFFF
        if tl != low:
            out[w] = (EVT_TIME_LOW << 12) | low
            w += 1
            tl = low
        yi = y[i]
        if ly != yi:
            out[w] = (EVT_ADDR_Y << 12) | (yi & 0x7FF)
            w += 1
            ly = yi
        pi = p[i]
        j = i + 1                   # run of events with the same t, y, p (sorted by x)
        while j < n and t[j] == ti and y[j] == yi and p[j] == pi:
            j += 1
        k = i
        while k < j:
            if k + 1 == j or x[k + 1] - x[k] >= 12 or x[k + 1] == x[k]:
                out[w] = (EVT_ADDR_X << 12) | (pi << 11) | (x[k] & 0x7FF)
                w += 1
                k += 1
                continue
            base = x[k]
            out[w] = (VECT_BASE_X << 12) | (pi << 11) | (base & 0x7FF)
            w += 1
            while k < j and x[k] - base < 12:
                # VECT_8 when the next events all lie within 8 of the base
                m = k
                while m < j and x[m] - base < 12 and (m == k or x[m] != x[m - 1]):
                    m += 1
                use8 = x[m - 1] - base < 8
                mask = 0
                while k < m:
                    mask |= 1 << (x[k] - base)
                    k += 1
                if use8:
                    out[w] = (VECT_8 << 12) | mask
                    base += 8
                else:
                    out[w] = (VECT_12 << 12) | mask
                    base += 12
                w += 1
                if k < j and x[k] == x[k - 1]:
                    break           # duplicate event: restart with a new base
        i = j
    state[0], state[1], state[2], state[3] = th, tl, ly, force
    return w


@njit(cache=True, nogil=True)
def _time_high_fill(t_to, state, out):
    """Emit the TIME_HIGH words of the periods up to time ``t_to`` (µs) that had no event."""
    w = 0
    if state[0] < 0:
        return 0
    while state[0] < (t_to >> 12):
        state[0] += 1
        out[w] = (EVT_TIME_HIGH << 12) | (state[0] & 0xFFF)
        w += 1
        state[1] = -1
    return w


class Evt3Encoder:
    """Streaming EVT 3.0 encoder. Feed it time-sorted event arrays (µs timestamps, may
    exceed 2^24: the 24-bit wrap is applied on the wire); it keeps the time/row context
    between calls. :meth:`resync` makes the next output self-contained (a new packet)."""

    def __init__(self):
        self._state = np.array([-1, -1, -1, 0], dtype=np.int64)
        self._last_t = -1

    def resync(self) -> None:
        """Repeat TIME_HIGH, TIME_LOW and ADDR_Y before the next event."""
        self._state[3] = 1

    def encode(self, events: np.ndarray, until_us: int | None = None, ordered: bool = False) -> bytes:
        """Encode ``events`` (sorted by t, timestamps >= the previous call's) to bytes.
        ``until_us``: also emit TIME_HIGH words for empty periods up to this time (µs).
        ``ordered``: the events are already in :func:`canonical_order` (skips the sort)."""
        ev = canonical_order(events) if len(events) > 1 and not ordered else events
        t = ev["t"].astype(np.int64)
        if len(t) and (t[0] < 0 or t[0] < self._last_t):
            raise ValueError("EVT3 encoder: timestamps must be >= 0 and non-decreasing across calls")
        if len(t) and (ev["x"].max() > 0x7FF or ev["y"].max() > 0x7FF):
            raise ValueError("EVT3 encoder: x and y must be < 2048 (11-bit addresses)")
        start = self._state[0] if self._state[0] >= 0 else ((int(t[0]) >> 12) if len(t) else 0)
        end = max(int(t[-1]) if len(t) else 0, int(until_us or 0)) >> 12
        out = np.empty(4 * len(ev) + 8 + max(0, end - int(start)), dtype=np.uint16)
        w = _encode(ev["x"].astype(np.int64), ev["y"].astype(np.int64), ev["p"].astype(np.int64),
                    t, self._state, out)
        if until_us is not None:
            w += _time_high_fill(int(until_us), self._state, out[w:])
        if len(t):
            self._last_t = int(t[-1])
        return out[:w].tobytes()


def encode_evt3(events: np.ndarray) -> bytes:
    """Encode a whole time-sorted event array to EVT 3.0 bytes (no header)."""
    return Evt3Encoder().encode(events)


def stream_header(width: int, height: int) -> bytes:
    """Prophesee RAW-style text header announcing EVT 3.0 and the sensor geometry (``% end``
    terminated); ``arena edge`` reads it from a ``tcp://`` stream to learn width and height."""
    return (f"% evt 3.0\n% format EVT3;height={height};width={width}\n% geometry {width}x{height}\n"
            f"% end\n").encode()


class CameraServer:
    """A TCP server on ``host:port`` streaming EVT 3.0 to every connected client, like a
    USB event camera: each client gets the stream from the moment it connects, in packets
    of at most ``packet_bytes`` bytes, each packet decodable on its own.

    ``publish(events, until_us)`` hands over the next time slice of events. With
    ``drop_when_slow`` (real time) a client that cannot keep up loses whole packets
    (counted in ``dropped_packets``) instead of stalling the camera; otherwise the
    publisher blocks until the client has read them (as fast as possible, lossless).
    Port 0 picks a free port; :attr:`port` holds the actual one. ``header`` (e.g. from
    :func:`stream_header`) is sent first to every client, so it learns the sensor geometry.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 0, packet_bytes: int = 16384,
                 drop_when_slow: bool = True, max_queue: int = 256, header: bytes | None = None):
        self.header = header
        self.packet_bytes = int(packet_bytes)
        self.drop_when_slow = drop_when_slow
        self.max_queue = max_queue
        self._sock = socket.create_server((host, port))
        self.host, self.port = self._sock.getsockname()[:2]
        self._clients: list[_Client] = []
        self._lock = threading.Lock()
        self._closed = threading.Event()
        self.dropped_packets = 0
        self._accept_thread = threading.Thread(target=self._accept, name="evt3-accept", daemon=True)
        self._accept_thread.start()

    @property
    def url(self) -> str:
        """Where a client connects: ``tcp://host:port``."""
        return f"tcp://{self.host}:{self.port}"

    @property
    def n_clients(self) -> int:
        with self._lock:
            return len(self._clients)

    def publish(self, events: np.ndarray, until_us: int | None = None, ordered: bool = False) -> None:
        """Send ``events`` (time-sorted, after the previous slice) to every client, split
        into packets; ``until_us`` = end of the slice (µs) for TIME_HIGH keep-alives;
        ``ordered``: already in :func:`canonical_order` (sorted once for every client)."""
        if not ordered and len(events) > 1:
            events = canonical_order(events)
        with self._lock:
            clients = list(self._clients)
        for c in clients:
            if c.dead.is_set():
                with self._lock:
                    if c in self._clients:
                        self._clients.remove(c)
                continue
            for pkt in c.packets(events, until_us, self.packet_bytes, ordered=True):
                if self.drop_when_slow:
                    try:
                        c.q.put_nowait(pkt)
                    except queue.Full:
                        self.dropped_packets += 1
                        c.encoder.resync()
                else:
                    while not c.dead.is_set():
                        try:
                            c.q.put(pkt, timeout=0.2)
                            break
                        except queue.Full:
                            continue

    def close(self) -> None:
        """Stop accepting, disconnect every client."""
        self._closed.set()
        try:
            self._sock.close()
        except OSError:
            pass
        with self._lock:
            clients, self._clients = self._clients, []
        for c in clients:
            c.close()
        self._accept_thread.join(timeout=2)

    def __enter__(self) -> "CameraServer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _accept(self) -> None:
        while not self._closed.is_set():
            try:
                conn, addr = self._sock.accept()
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            log.info("camera client %s:%d connected", *addr[:2])
            c = _Client(conn, self.max_queue)
            if self.header:
                c.q.put(self.header)
            with self._lock:
                self._clients.append(c)


class _Client:
    def __init__(self, conn: socket.socket, max_queue: int):
        self.conn = conn
        self.encoder = Evt3Encoder()
        self.q: queue.Queue[bytes | None] = queue.Queue(max_queue)
        self.dead = threading.Event()
        self.thread = threading.Thread(target=self._send, name="evt3-client", daemon=True)
        self.thread.start()

    def packets(self, events: np.ndarray, until_us, packet_bytes: int, ordered: bool = False):
        """Encode ``events`` into packets of at most ~packet_bytes, each starting with a resync
        (``ordered``: already in :func:`canonical_order`)."""
        if not ordered and len(events) > 1:
            events = canonical_order(events)
        per = max(1, packet_bytes // 8)    # <= ~4 words (8 bytes) per event
        n = len(events)
        if n == 0:
            data = self.encoder.encode(events, until_us)
            if data:
                yield data
            return
        t = events["t"]
        a = 0
        while a < n:
            b = min(n, a + per)
            while b < n and t[b] == t[b - 1]:   # keep one timestamp in one packet
                b += 1
            self.encoder.resync()
            yield self.encoder.encode(events[a:b], until_us if b == n else None, ordered=True)
            a = b

    def _send(self) -> None:
        try:
            while True:
                pkt = self.q.get()
                if pkt is None:
                    break
                self.conn.sendall(pkt)
        except OSError as e:
            log.info("camera client gone: %s", e)
        finally:
            self.dead.set()
            try:
                self.conn.close()
            except OSError:
                pass

    def close(self) -> None:
        self.dead.set()
        try:
            self.q.put_nowait(None)
        except queue.Full:
            pass
        try:
            self.conn.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.conn.close()

"""The red team's viewer findings: a window declaring a huge sensor, slow clients, a flood of
track IDs. In-process :class:`ViewerServer` on an ephemeral loopback port, real sockets."""

from __future__ import annotations

import json
import logging
import socket
import threading
import time
import tracemalloc

import numpy as np
import pytest

from arena import codec
from arena.events import make_events
from arena.messages import EventWindow, Status, Telemetry, Track
from viewer.server import ViewerServer
from viewer.service import handle_sample
from viewer.state import ViewerState


def _window(side_w: int, side_h: int, xs=(5,), ys=(5,), ps=(1,), t_end_us: int = 10_000, seq: int = 0) -> EventWindow:
    ev = make_events(np.array(xs), np.array(ys), np.array(ps), np.full(len(xs), t_end_us - 1))
    return EventWindow(camera="c0", seq=seq, t_start_us=t_end_us - 10_000, t_end_us=t_end_us, width=side_w,
                       height=side_h, count=ev.size, codec=codec.RAW_CODEC, data=codec.encode(ev, codec.RAW_CODEC),
                       publish_ns=1)  # (raw: the planes codecs code x < 2048 only)


class Served:
    """A ViewerServer serving on a thread; ``request`` sends one GET on a new connection."""

    def __init__(self, state: ViewerState, **kw):
        self.server = ViewerServer(state, "127.0.0.1", 0, **kw)
        self.thread = threading.Thread(target=self.server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
        self.thread.start()

    def connect(self) -> socket.socket:
        return socket.create_connection(("127.0.0.1", self.server.port), timeout=10)

    def request(self, path: str = "/state.json") -> tuple[int, bytes]:
        with self.connect() as s:
            s.sendall(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{self.server.port}\r\nConnection: close\r\n\r\n".encode())
            data = _read_all(s)
        assert data, f"GET {path}: the connection was closed without an answer"
        head, _, body = data.partition(b"\r\n\r\n")
        return int(head.split(b" ", 2)[1]), body

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()
        self.thread.join(10)


def _read_all(s: socket.socket, limit: int = 1 << 24) -> bytes:
    data = b""
    while len(data) < limit:
        try:
            chunk = s.recv(65536)
        except ConnectionResetError:
            break
        if not chunk:
            break
        data += chunk
    return data


def _closed(s: socket.socket, wait_s: float) -> bool:
    """Whether the peer closed ``s`` (EOF or reset) within ``wait_s``."""
    s.settimeout(wait_s)
    try:
        return s.recv(1) == b""
    except ConnectionResetError:
        return True
    except TimeoutError:
        return False


def _poll(cond, timeout_s: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


@pytest.fixture
def served(request):
    state, kw = getattr(request, "param", (ViewerState(), {}))
    srv = Served(state, **kw)
    yield srv
    srv.close()


# ---- 1. sensor size -------------------------------------------------------------------------------
def test_a_window_declaring_a_huge_sensor_is_drawn_downsampled_within_bounded_memory():
    st = ViewerState(max_image_side=2048)
    st.on_window(_window(20000, 20000, xs=(5, 19999), ys=(5, 19999), ps=(1, 0)))
    tracemalloc.start()
    try:
        index = st.render_index()
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    # 20000 px / 2048 -> factor 10: a 2000 x 2000 image (without the bound: 20000 x 20000, 400 MB)
    assert index.shape == (2000, 2000)
    assert peak < 16 * 2**20, f"rendering allocated {peak / 2**20:.0f} MB"
    assert index[0, 0] == 1 and index[1999, 1999] == 2 and int(np.count_nonzero(index)) == 2
    assert st.snapshot()["image"] == {**st.snapshot()["image"], "width": 20000, "height": 20000, "scale": 10}
    # the largest a window can declare (65535 x 65535) still renders within max_image_side
    st.on_window(_window(65535, 65535, xs=(65534,), ys=(0,), t_end_us=20_000))
    index = st.render_index()
    assert index.shape == (2048, 2048) and index[0, 2047] == 1
    # a real sensor is drawn at full size
    st.on_window(_window(640, 480, xs=(639,), ys=(479,), t_end_us=30_000))
    assert st.render_index().shape == (480, 640) and st.snapshot()["image"]["scale"] == 1


def test_a_sensor_size_change_starts_a_new_image():
    st = ViewerState()
    st.on_window(_window(640, 480, xs=(600,), ys=(400,)))
    assert st.render_index()[400, 600] == 1
    st.on_window(_window(10, 10, xs=(3,), ys=(4,), ps=(0,), t_end_us=20_000))
    index = st.render_index()  # the 640 x 480 window's pixels do not fit a 10 x 10 image
    assert index.shape == (10, 10) and index[4, 3] == 2 and int(np.count_nonzero(index)) == 1


class FailingRender(ViewerState):
    """A state whose event image cannot be rendered (as a 65535 x 65535 image without the bound
    made it raise MemoryError): the failure is injected, the server's handling is real."""

    def render_index(self):
        raise MemoryError("cannot allocate the image")


@pytest.mark.parametrize("served", [(FailingRender(), {"period_s": 0.05})], indirect=True)
def test_an_image_that_cannot_be_rendered_is_answered_counted_and_the_viewer_goes_on(served, caplog):
    st = served.server.state
    st.on_window(_window(640, 480))
    with caplog.at_level(logging.WARNING, logger="arena.viewer"):
        status, body = served.request("/frame.png")
        assert status == 503 and b"MemoryError" in body
        assert st.counts["bad"] == 1
        # the event stream goes on without its image
        with served.connect() as s:
            s.sendall(f"GET /events HTTP/1.1\r\nHost: 127.0.0.1:{served.server.port}\r\n\r\n".encode())
            data = b""
            while data.count(b"\ndata: {") < 4:   # the hello and 3 snapshots
                chunk = s.recv(65536)
                assert chunk, data[-300:]
                data += chunk
        snaps = [json.loads(m.split(b"\n\n")[0]) for m in data.split(b"\ndata: ")[2:5]]
        assert [("frame" in m, m["image"]["events"]) for m in snaps] == [(False, 1)] * 3
        assert st.counts["bad"] == 2   # tried once more for the stream, not again until a new window
        assert served.request("/state.json")[0] == 200
    said = [r.getMessage() for r in caplog.records]
    assert "event image not rendered (MemoryError: cannot allocate the image) (1 so far)" in said


# ---- 2. slow clients ------------------------------------------------------------------------------
@pytest.mark.parametrize("served", [(ViewerState(), {"header_timeout_s": 0.5, "idle_timeout_s": 20})], indirect=True)
def test_a_request_trickled_byte_by_byte_is_closed_at_the_header_deadline(served):
    with served.connect() as s:
        closed = False
        for i, byte in enumerate(b"GET /state.json HTTP/1.1\r\nHost: x\r\nX-Pad: " + b"a" * 100):
            try:
                s.sendall(bytes([byte]))
            except OSError:
                closed = True
                break
            if _closed(s, 0.1):  # one byte every 0.1 s, each gap far below the 20 s idle timeout
                closed = True
                break
        assert closed, "a connection trickling its request for 14 s (deadline 0.5 s) was never closed"
    assert _poll(lambda: served.server.refused["slow"] == 1), served.server.refused
    assert served.request()[0] == 200 and served.server.refused["slow"] == 1


@pytest.mark.parametrize("served", [(ViewerState(), {"max_connections": 4, "header_timeout_s": 30,
                                                    "idle_timeout_s": 30})], indirect=True)
def test_slow_clients_holding_every_connection_do_not_lock_out_a_request(served):
    srv = served.server
    slow = []
    try:
        for _ in range(6):   # more slow clients than connections, none finishing its request
            s = served.connect()
            s.sendall(b"GE")
            slow.append(s)
        assert _poll(lambda: srv.refused["evicted"] == 2)
        status, body = served.request()
        assert status == 200 and body.startswith(b"{")
        assert srv.refused["evicted"] == 3 and srv.refused["busy"] == 0
        # the ones waiting longest were closed, the others are still open
        assert [_closed(s, 5.0 if i < 3 else 0.05) for i, s in enumerate(slow)] == [True] * 3 + [False] * 3
    finally:
        for s in slow:
            s.close()


@pytest.mark.parametrize("served", [(ViewerState(), {"max_connections": 2, "max_streams": 2, "period_s": 0.5})],
                         indirect=True)
def test_event_streams_are_not_evicted_when_all_connections_are_busy_a_new_one_gets_503(served):
    streams = []
    try:
        for _ in range(2):
            s = served.connect()
            s.sendall(f"GET /events HTTP/1.1\r\nHost: 127.0.0.1:{served.server.port}\r\n\r\n".encode())
            assert s.recv(12) == b"HTTP/1.1 200"
            streams.append(s)
        with served.connect() as extra:
            reply = _read_all(extra)
        assert reply.startswith(b"HTTP/1.1 503") and b"at most 2 connections" in reply
        assert served.server.refused == {"host": 0, "busy": 1, "slow": 0, "evicted": 0, "streams": 0}
        for s in streams:   # still streaming
            s.settimeout(5)
            assert s.recv(65536)
    finally:
        for s in streams:
            s.close()


# ---- 3. track flood -------------------------------------------------------------------------------
def test_a_flood_of_track_ids_keeps_a_bounded_table_the_newest_tracks():
    st = ViewerState(max_tracks=200)
    for i in range(5000):
        handle_sample(st, f"arena/robots/{i}", Track(track_id=i, camera="c0", x=1.0, y=1.0, stamp_us=i).encode())
    assert st.counts["tracks"] == 5000 and st.counts["bad"] == 0
    assert list(st._tracks) == [f"arena/robots/{i}" for i in range(4800, 5000)]
    assert len(st._track_key) == 200 and st.counts["evicted"] == 4800
    assert len(st.snapshot()["tracks"]) == 200
    # a numbered track that gets its name still becomes one entry, at the end (newest)
    handle_sample(st, "arena/robots/zumo1", Track(track_id=4900, camera="c0", robot="zumo1", x=1.2, y=1.0,
                                                  stamp_us=5000).encode())
    assert "arena/robots/4900" not in st._tracks and list(st._tracks)[-1] == "arena/robots/zumo1"
    assert len(st._tracks) == 200 and st.counts["evicted"] == 4800   # moved, not added: nothing evicted
    assert st._track_key[("c0", 4900)] == "arena/robots/zumo1"
    assert list(st._tracks["arena/robots/zumo1"].trail_m) == [(1.0, 1.0), (1.2, 1.0)]
    # the named key showing another track id: the old id no longer points at it
    handle_sample(st, "arena/robots/zumo1", Track(track_id=7, camera="c0", robot="zumo1", x=1.3, y=1.0,
                                                  stamp_us=5001).encode())
    assert ("c0", 4900) not in st._track_key and st._track_key[("c0", 7)] == "arena/robots/zumo1"


def test_tracks_expire_oldest_first_with_the_clock():
    now = [0.0]
    st = ViewerState(track_timeout_s=3.0, clock=lambda: now[0])
    for i in range(5):
        now[0] = float(i)
        st.on_track(f"arena/robots/{i}", Track(track_id=i, x=1.0, y=1.0, stamp_us=i))
    now[0] = 5.5   # tracks 0, 1, 2 not updated for more than 3 s
    assert [t["id"] for t in st.snapshot()["tracks"]] == [3, 4] and len(st._track_key) == 2
    st.on_track("arena/robots/3", Track(track_id=3, x=1.1, y=1.0, stamp_us=9))
    now[0] = 7.5
    assert [t["id"] for t in st.snapshot()["tracks"]] == [3]


def test_floods_of_robot_and_service_names_are_bounded_too():
    st = ViewerState(max_tracks=50)
    for i in range(1000):
        st.on_telemetry(Telemetry(robot=f"r{i}", seq=0, robot_time_us=0, host_time_ns=0, enc_left=0, enc_right=0,
                                  speed_left=0.0, speed_right=0.0, gyro=(0.0, 0.0, 0.0), battery_mv=5000))
        st.on_status(Status(role="edge", name=f"e{i}"))
        st.on_alive("tracker", f"t{i}", True)
    snap = st.snapshot()
    assert sorted(snap["telemetry"]) == sorted(f"r{i}" for i in range(950, 1000))
    assert len(snap["services"]) == 100 and st.counts["evicted"] == 3 * 950


def _stream_request(served: Served) -> socket.socket:
    s = served.connect()
    s.sendall(f"GET /events HTTP/1.1\r\nHost: 127.0.0.1:{served.server.port}\r\n\r\n".encode())
    return s


@pytest.mark.parametrize("served", [(ViewerState(), {"max_connections": 4, "period_s": 0.5, "idle_timeout_s": 20})],
                         indirect=True)
def test_event_streams_leave_connections_for_pages_and_state(served):
    """Live event streams on every connection but the reserve: a stream more gets 503 at once
    (counted) and the page and /state.json are still served (they had got 503 for as long as the
    streams stayed open)."""
    srv = served.server
    assert srv.max_streams == 3   # 4 connections, one kept back
    streams = []
    try:
        for _ in range(3):
            s = _stream_request(served)
            assert s.recv(12) == b"HTTP/1.1 200"
            streams.append(s)
        with _stream_request(served) as extra:
            extra.settimeout(10)
            reply = b""
            while b"\r\n\r\n" not in reply and len(reply) < 65536:   # the head (a stream never ends)
                chunk = extra.recv(65536)
                assert chunk, reply
                reply += chunk
            assert reply.startswith(b"HTTP/1.1 503"), reply[:200]
            reply += _read_all(extra)
        assert b"at most 3 event streams" in reply, reply[:300]
        assert srv.refused == {"host": 0, "busy": 0, "slow": 0, "evicted": 0, "streams": 1}
        for path in ("/state.json", "/", "/state.json"):
            status, body = served.request(path)
            assert status == 200 and body, (path, status)
        assert srv.clients == 3 and srv.refused["busy"] == 0
        for s in streams:   # still streaming
            s.settimeout(5)
            assert s.recv(65536)
        # a closed stream frees its place for another (bounded poll)
        streams.pop(0).close()
        assert _poll(lambda: srv.clients == 2)
        s = _stream_request(served)
        streams.append(s)
        assert s.recv(12) == b"HTTP/1.1 200" and srv.refused["streams"] == 1
    finally:
        for s in streams:
            s.close()


@pytest.mark.parametrize("bad", [{"max_connections": 4, "max_streams": 0}, {"max_connections": 4, "max_streams": 5}])
def test_a_stream_bound_outside_the_connections_is_refused(bad):
    with pytest.raises(ValueError, match="max_streams"):
        ViewerServer(ViewerState(), "127.0.0.1", 0, **bad)


# ---- 4. valid windows of millions of events ---------------------------------------------------------
def _scan_window(n: int, seq: int, t_end_us: int) -> EventWindow:
    """A valid window of ``n`` events scanning a 640 x 480 sensor row by row, again and again
    (ON and OFF alternating), coded with the default codec."""
    i = np.arange(n)
    ev = make_events(i % 640, (i // 640) % 480, (i // (640 * 480)) & 1, np.full(n, t_end_us - 1))
    return EventWindow(camera="c0", seq=seq, t_start_us=t_end_us - 10_000, t_end_us=t_end_us, width=640, height=480,
                       count=n, codec=codec.DEFAULT_CODEC, data=codec.encode(ev), publish_ns=1)


@pytest.fixture(scope="module")
def scan_windows():
    return [_scan_window(2_000_000, seq, 3_000_000 + 10_000 * seq) for seq in range(3)]


def test_windows_of_millions_of_events_are_drawn_within_the_event_budget(scan_windows):
    st = ViewerState(max_window_events=1_000_000, max_events=4_000_000)
    for m in scan_windows:
        handle_sample(st, "arena/events/c0", m.encode())
    index = st.render_index()
    kept = [w.events[0].size for w in st._windows]
    # the oldest window went (6 M declared > 4 M); each kept one is drawn from 1 M of its 2 M events
    assert kept == [1_000_000, 1_000_000], kept
    img = st.snapshot()["image"]
    assert img["drawn"] == 2_000_000 and img["events"] == 4_000_000 and img["windows"] == 2
    assert st.counts["subsampled"] == 2 and st.counts["bad"] == 0
    # the subsample is not in step with the scan (every other event would be every other column):
    # nearly every pixel (each has 6-7 events in a window) is drawn, ON and OFF as the scan left them
    assert np.count_nonzero(index) > 0.95 * 640 * 480
    assert set(np.unique(index)) <= {0, 1, 2} and np.count_nonzero(index == 1) > 0 and np.count_nonzero(index == 2) > 0
    # deterministic: the same windows give the same image; a later render decodes nothing again
    st2 = ViewerState(max_window_events=1_000_000, max_events=4_000_000)
    for m in scan_windows:
        st2.on_window(m)
    assert np.array_equal(st2.render_index(), index)
    assert np.array_equal(st.render_index(), index) and st.counts["subsampled"] == 2
    # a window within the budget is drawn whole
    st3 = ViewerState(max_window_events=4_000_000)
    st3.on_window(scan_windows[0])
    st3.render_index()
    assert st3.snapshot()["image"]["drawn"] == 2_000_000 and st3.counts["subsampled"] == 0

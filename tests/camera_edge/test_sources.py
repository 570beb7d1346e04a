"""Event sources: the simulator's TCP camera (decode, header, reconnect, timeouts), file replay
pacing and loop, clear errors for unknown sources and missing SDKs."""

from __future__ import annotations

import socket
import threading
import time

import numpy as np
import pytest

from arena.events import make_events
from arena.formats import write_events
from camera_edge.sources import FileSource, SourceError, TcpSource, open_source
from simulator.evt3 import CameraServer, canonical_order


def _events(n=5000, t0=1_000, seed=0, span_us=200_000):
    rng = np.random.default_rng(seed)
    ev = make_events(rng.integers(0, 640, n), rng.integers(0, 480, n), rng.integers(0, 2, n),
                     np.sort(rng.integers(t0, t0 + span_us, n)))
    return canonical_order(ev)


def _read_until(src, n, timeout=10.0):
    got = []
    deadline = time.monotonic() + timeout
    while sum(g.size for g in got) < n and time.monotonic() < deadline:
        ev = src.read(timeout=0.05)
        assert ev is not None
        got.append(ev)
    return np.concatenate(got) if got else np.empty(0)


def test_tcp_source_decodes_the_simulator_camera_exactly():
    ev = _events()
    with CameraServer(drop_when_slow=False) as cam:
        with open_source(cam.url + "?width=640&height=480") as src:
            assert isinstance(src, TcpSource) and (src.width, src.height) == (640, 480)
            deadline = time.monotonic() + 5
            while cam.n_clients < 1 and time.monotonic() < deadline:
                time.sleep(0.01)
            cam.publish(ev, until_us=int(ev["t"][-1]) + 10_000)
            got = _read_until(src, ev.size)
            np.testing.assert_array_equal(got, ev)
            assert src.time_us >= int(ev["t"][-1])  # keep-alive time words advance the clock


def test_tcp_source_reads_a_raw_header_and_never_blocks():
    srv = socket.create_server(("127.0.0.1", 0))
    port = srv.getsockname()[1]

    def serve():
        conn, _ = srv.accept()
        conn.sendall(b"% evt 3.0\n% format EVT3;height=720;width=1280\n% end\n")
        conn.sendall(np.array([0x8001, 0x6002, 0x0005, 0x2807], "<u2").tobytes())
        time.sleep(1.0)
        conn.close()

    th = threading.Thread(target=serve, daemon=True)
    th.start()
    with TcpSource(f"tcp://127.0.0.1:{port}?width=10&height=10", backoff_s=0.05) as src:
        assert (src.width, src.height) == (1280, 720)
        got = _read_until(src, 1, timeout=3)
        assert got["x"].tolist() == [7] and got["t"].tolist() == [4098]
        t0 = time.monotonic()
        assert src.read(timeout=0.1).size == 0
        assert time.monotonic() - t0 < 0.5
    srv.close()


def test_tcp_source_reconnects_after_the_stream_is_lost():
    from simulator.evt3 import encode_evt3

    first, second = _events(2000, seed=1), _events(3000, seed=2, t0=500_000)
    srv = socket.create_server(("127.0.0.1", 0))
    port = srv.getsockname()[1]
    srv.settimeout(5)

    def camera():  # two connections: the first dies mid-stream, the second delivers
        for ev in (first, second):
            conn, _ = srv.accept()
            conn.sendall(encode_evt3(ev))
            time.sleep(0.3)
            conn.close()

    th = threading.Thread(target=camera, daemon=True)
    th.start()
    with TcpSource(f"tcp://127.0.0.1:{port}?width=640&height=480", backoff_s=0.05, max_backoff_s=0.2) as src:
        np.testing.assert_array_equal(_read_until(src, first.size), first)
        got = _read_until(src, second.size)
        np.testing.assert_array_equal(got, second)
        assert src.reconnects == 1
    th.join(2)
    srv.close()


def test_tcp_source_starts_even_if_the_camera_is_not_there_yet():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    t0 = time.monotonic()
    with TcpSource(f"tcp://127.0.0.1:{port}", connect_timeout_s=0.5) as src:
        assert not src.connected
        assert src.read(timeout=0.05).size == 0
    assert time.monotonic() - t0 < 2


def test_file_replay_follows_sensor_time(tmp_path):
    ev = _events(3000, span_us=400_000)
    write_events(tmp_path / "r.raw", ev, 640, 480)
    t0 = time.monotonic()
    with open_source(str(tmp_path / "r.raw"), speed=1) as src:
        got = np.concatenate(list(src))
    elapsed = time.monotonic() - t0
    np.testing.assert_array_equal(got, ev)
    assert 0.3 <= elapsed < 1.5, elapsed
    t0 = time.monotonic()
    with open_source(str(tmp_path / "r.raw"), speed=0) as src:
        assert sum(c.size for c in src) == ev.size
    assert time.monotonic() - t0 < 0.3


def test_file_loop_keeps_time_increasing(tmp_path):
    ev = _events(1000, span_us=10_000)
    write_events(tmp_path / "r.npz", ev, 640, 480)
    with FileSource(tmp_path / "r.npz", speed=0, loop=True) as src:
        got = [src.read() for _ in range(3)]
    t = np.concatenate(got)["t"]
    assert t.size == 3000 and np.all(np.diff(t) >= 0)


@pytest.mark.parametrize("url,match", [
    ("udp://x", "unknown event source"),
    ("nope.raw", "no such file"),
    ("prophesee:", "metavision_core"),
    ("inivation:", "dv-processing|no iniVation camera found"),  # SDK missing, or no camera
    ("tcp://host-without-port", "HOST:PORT"),
])
def test_bad_sources_say_what_to_do(url, match):
    if url.startswith("inivation"):
        try:
            import dv_processing as dv
        except ImportError:
            pass
        else:
            if dv.io.camera.discover():
                pytest.skip("an iniVation camera is attached: inivation: opens it")
    with pytest.raises(SourceError, match=match):
        open_source(url)


def test_tcp_garbage_is_counted_not_fatal():
    srv = socket.create_server(("127.0.0.1", 0))
    port = srv.getsockname()[1]
    junk = np.random.default_rng(7).integers(0, 256, 200_000, dtype=np.uint8).tobytes()

    def serve():
        conn, _ = srv.accept()
        conn.sendall(junk)
        time.sleep(0.5)
        conn.close()

    th = threading.Thread(target=serve, daemon=True)
    th.start()
    with TcpSource(f"tcp://127.0.0.1:{port}?width=64&height=64", backoff_s=0.05) as src:
        deadline = time.monotonic() + 3
        n = 0
        while time.monotonic() < deadline and src.reconnects == 0 and src.bytes_in < len(junk):
            ev = src.read(timeout=0.05)
            n += ev.size
            assert ev.size == 0 or (ev["x"].max() < 64 and ev["y"].max() < 64)
        assert src.bytes_in == len(junk) and src.invalid > 0
    th.join(2)
    srv.close()


def test_inivation_source_reads_dv_processing_batches_exactly(tmp_path):
    # the adapter's SDK calls and field names, against the real dv-processing reading a recording
    dv = pytest.importorskip("dv_processing", reason="dv-processing (the 'inivation' extra) is not installed")
    from camera_edge.sources import InivationSource

    ev = _events(30_000, span_us=300_000)
    write_events(tmp_path / "r.aedat4", ev, 640, 480)
    src = InivationSource("rec", reader=dv.io.MonoCameraRecording(str(tmp_path / "r.aedat4")))
    assert (src.width, src.height) == (640, 480)
    parts = []
    while (chunk := src.read(timeout=0.01)) is not None:
        parts.append(chunk)
    np.testing.assert_array_equal(np.concatenate(parts), ev)
    assert src.time_us == int(ev["t"][-1])


def test_inivation_without_a_camera_is_one_clear_line():
    dv = pytest.importorskip("dv_processing", reason="dv-processing (the 'inivation' extra) is not installed")
    if dv.io.camera.discover():
        pytest.skip("an iniVation camera is attached")
    with pytest.raises(SourceError, match="no iniVation camera found"):
        open_source("inivation:")
    from camera_edge.sources import _first_line

    with pytest.raises(RuntimeError) as info:            # the SDK's own error, with its C++ trace
        dv.io.camera.open("NO-SUCH-SERIAL")
    assert _first_line(info.value) == "Could not find device with given serial number"

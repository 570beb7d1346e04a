"""EVT 3.0 encoder, RAW files and the TCP camera stream, checked with the independent
PyPI decoder ``evt3`` (test-only dependency)."""

from __future__ import annotations

import socket
import time

import numpy as np
import pytest

from arena.events import make_events
from simulator.evt3 import (EVT_TIME_HIGH, VECT_8, VECT_12, VECT_BASE_X, CameraServer,
                            Evt3Encoder, canonical_order, encode_evt3)
from simulator.recording import raw_header, write_events
from simulator.scenarios import Scenario, generate

evt3 = pytest.importorskip("evt3", reason="the independent EVT3 decoder (pip install evt3)")


def decoded(events_obj) -> np.ndarray:
    return make_events(events_obj.x, events_obj.y, events_obj.polarity,
                       events_obj.timestamp.astype(np.int64))


def random_events(seed=0, n=50_000, t_max=40_000_000):
    """Random events past two 2^24 µs wraps, plus rows of adjacent pixels (vectors)."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, t_max, n))
    ev = make_events(rng.integers(0, 640, n), rng.integers(0, 480, n), rng.integers(0, 2, n), t)
    tv = np.repeat(np.arange(500, t_max, 1_000_003), 31)
    xs = np.r_[np.arange(100, 120), np.arange(200, 233, 3)]          # 20 adjacent + 11 spaced
    vec = make_events(np.tile(xs, len(tv) // 31), np.full(len(tv), 7), np.ones(len(tv), int), tv)
    allev = np.concatenate([ev, vec])
    return allev[np.argsort(allev["t"], kind="stable")]


def word_types(data: bytes) -> np.ndarray:
    return np.bincount(np.frombuffer(data, "<u2") >> 12, minlength=16)


def test_encoder_round_trips_exactly_with_wraps_and_vectors():
    ev = random_events()
    data = encode_evt3(ev)
    types = word_types(data)
    assert types[VECT_BASE_X] > 0 and types[VECT_12] > 0 and types[VECT_8] > 0
    # one TIME_HIGH per 4096 µs period at least (keep-alive), 40 s > 2 wraps of 2^24 µs
    assert types[EVT_TIME_HIGH] >= 40_000_000 // 4096
    out = decoded(evt3.Decoder(640, 480).feed(data))
    assert out["t"].max() > 2 * (1 << 24)
    assert np.array_equal(canonical_order(out), canonical_order(ev))


def test_packets_with_resync_decode_each_on_their_own_context():
    ev = random_events(seed=1, n=20_000, t_max=3_000_000)
    enc = Evt3Encoder()
    packets = []
    for a in range(0, len(ev), 3000):
        enc.resync()
        packets.append(enc.encode(ev[a:a + 3000]))
    dec = evt3.Decoder(640, 480)
    got = np.concatenate([decoded(dec.feed(p)) for p in packets])
    assert np.array_equal(canonical_order(got), canonical_order(ev))
    # a packet decodes alone too (it repeats TIME_HIGH, TIME_LOW and ADDR_Y)
    alone = decoded(evt3.Decoder(640, 480).feed(packets[3]))
    assert len(alone) > 0 and alone["t"].min() >= ev["t"][9000]


def test_encoder_rejects_time_going_backwards():
    enc = Evt3Encoder()
    enc.encode(make_events([1], [1], [1], [5000]))
    with pytest.raises(ValueError, match="non-decreasing"):
        enc.encode(make_events([1], [1], [1], [10]))


def test_simulated_raw_file_decodes_to_the_model_events(tmp_path):
    rec = generate(Scenario(n_robots=2, pattern="circle", duration_s=1.0, seed=3,
                            width=320, height=240))
    path = write_events(tmp_path / "sim.raw", rec.events, rec.width, rec.height)
    head = path.read_bytes()[:300].split(b"% end\n")[0].decode()
    for line in ("% evt 3.0", "% format EVT3;height=240;width=320", "% geometry 320x240"):
        assert line in head
    f = evt3.decode_file(str(path))
    assert (f.sensor_width, f.sensor_height) == (320, 240)
    assert np.array_equal(canonical_order(decoded(f)), canonical_order(rec.events))


def test_raw_header_is_prophesee_style():
    h = raw_header(1280, 720).decode()
    assert h.startswith("% Date") and h.endswith("% end\n")


def _read_available(sock: socket.socket, seconds: float) -> bytes:
    sock.settimeout(0.2)
    buf = bytearray()
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        try:
            chunk = sock.recv(1 << 16)
        except socket.timeout:
            continue
        if not chunk:
            break
        buf += chunk
    return bytes(buf)


def test_camera_server_streams_evt3_over_tcp_from_connection_time():
    ev = random_events(seed=2, n=30_000, t_max=2_000_000)
    with CameraServer(port=0, packet_bytes=4096, drop_when_slow=False) as cam:
        assert cam.url.startswith("tcp://127.0.0.1:") and cam.port > 0
        cam.publish(ev[:1000], until_us=int(ev["t"][999]))     # nobody listening: not buffered
        with socket.create_connection((cam.host, cam.port), timeout=5) as s:
            deadline = time.monotonic() + 5
            while cam.n_clients == 0 and time.monotonic() < deadline:
                time.sleep(0.01)
            rest = ev[1000:]
            for a in range(0, len(rest), 5000):
                cam.publish(rest[a:a + 5000], until_us=int(rest["t"][min(a + 4999, len(rest) - 1)]))
            data = _read_available(s, 1.5)
    got = decoded(evt3.Decoder(640, 480).feed(data))
    assert np.array_equal(canonical_order(got), canonical_order(ev[1000:]))


def test_camera_server_keeps_time_alive_without_events():
    with CameraServer(port=0) as cam, socket.create_connection((cam.host, cam.port)) as s:
        deadline = time.monotonic() + 5
        while cam.n_clients == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        cam.publish(make_events([5], [6], [1], [10]), until_us=10)
        cam.publish(make_events([], [], [], []), until_us=100_000)
        data = _read_available(s, 0.5)
    assert word_types(data)[EVT_TIME_HIGH] >= 100_000 // 4096


def test_encoder_rejects_addresses_beyond_11_bits():
    with pytest.raises(ValueError, match="2048"):
        encode_evt3(make_events([2048], [0], [1], [10]))


def test_camera_server_survives_a_client_that_goes_away():
    with CameraServer(port=0) as cam:
        s = socket.create_connection((cam.host, cam.port))
        deadline = time.monotonic() + 5
        while cam.n_clients == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        s.close()
        ev = random_events(seed=3, n=5000, t_max=500_000)
        deadline = time.monotonic() + 5
        while cam.n_clients and time.monotonic() < deadline:
            cam.publish(ev[:100], until_us=int(ev["t"][99]))     # must not raise
            ev = ev[100:]
            time.sleep(0.05)
        assert cam.n_clients == 0


def test_camera_server_drops_whole_packets_for_a_client_that_does_not_read():
    """Real-time mode (the simulator's default): a client that stops reading loses whole packets,
    counted, and never stalls the camera; what it does get decodes to events that were sent."""
    import threading

    # the same 5 000 random events again and again, 10 ms later each time, until the socket's
    # buffers (megabytes on loopback) and the 4-packet queue are full and packets drop
    rng = np.random.default_rng(5)
    span = 10_000
    base = make_events(rng.integers(0, 640, 5000), rng.integers(0, 480, 5000), rng.integers(0, 2, 5000),
                       np.sort(rng.integers(0, span, 5000)))
    with CameraServer(port=0, packet_bytes=4096, max_queue=4) as cam:
        s = socket.socket()
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)     # a small window fills fast
        s.connect((cam.host, cam.port))
        with s:
            deadline = time.monotonic() + 5
            while cam.n_clients == 0 and time.monotonic() < deadline:
                time.sleep(0.01)
            done = threading.Event()
            sent_chunks = [0]

            def publish_all():
                ev = base.copy()
                for k in range(3000):                # at most 15 M events (~40 MB of EVT 3.0)
                    ev["t"] = base["t"] + k * span
                    cam.publish(ev, until_us=(k + 1) * span)
                    sent_chunks[0] = k + 1
                    if cam.dropped_packets >= 20:
                        break
                done.set()

            threading.Thread(target=publish_all, daemon=True).start()
            assert done.wait(60), "the camera stalled on a client that does not read"
            assert cam.dropped_packets >= 20, (cam.dropped_packets, sent_chunks)
            data = _read_available(s, 1.0)
    got = decoded(evt3.Decoder(640, 480).feed(data))
    assert 0 < len(got) < sent_chunks[0] * len(base)
    assert np.all(np.diff(got["t"]) >= 0)                # resynced packets keep time in order
    assert got["t"].max() < sent_chunks[0] * span
    sent = {tuple(r) for r in base[["x", "y", "p", "t"]].tolist()}
    got_base = got.copy()
    got_base["t"] %= span
    assert all(tuple(r) in sent for r in got_base[["x", "y", "p", "t"]].tolist())


def test_canonical_order_is_t_then_y_p_x_for_any_events():
    # the packed-key sort must equal the 4-key lexsort, duplicates and out-of-range values too
    rng = np.random.default_rng(3)
    for hi_x, t_hi in ((640, 20_000), (640, 1 << 41), (4096, 20_000)):
        n = 5000
        ev = make_events(rng.integers(0, hi_x, n), rng.integers(0, 480, n), rng.integers(0, 2, n),
                         np.sort(rng.integers(0, t_hi, n)))
        ev = np.concatenate([ev, ev[:300]])[rng.permutation(n + 300)]
        ref = ev[np.lexsort((ev["x"], ev["p"], ev["y"], ev["t"]))]
        assert np.array_equal(canonical_order(ev), ref)

"""`arena view` refuses requests for a foreign Host (DNS rebinding) with 421, serves a bounded
number of connections (the 65th gets 503 at once when 64 are busy; one waiting for its request
is replaced), closes idle connections after --idle-timeout and slow requests after
--header-timeout, and keeps slow event streams alive with comments. Real `arena view` processes
on ephemeral ports, real sockets."""

from __future__ import annotations

import os
import re
import socket
import subprocess
import time

import pytest

from tests.conftest import arena_cmd, wait_for_line
from viewer.server import ViewerServer
from viewer.state import ViewerState


class View:
    """A running `arena view --port 0 ARGS` (its port from the line it prints)."""

    def __init__(self, router, *args: str):
        self.proc = subprocess.Popen(arena_cmd("view", "--port", "0", *args, *router.args), stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
        line = wait_for_line(self.proc, "viewer on", timeout=60)
        self.port = int(re.search(r":(\d+)/", line).group(1))

    def connect(self) -> socket.socket:
        return socket.create_connection(("127.0.0.1", self.port), timeout=10)

    def request(self, host: str | None, path: str = "/state.json") -> tuple[int, bytes]:
        """One raw HTTP/1.1 GET with this Host header (None: none); (status, body)."""
        with self.connect() as s:
            head = f"GET {path} HTTP/1.1\r\n" + (f"Host: {host}\r\n" if host is not None else "") + "Connection: close\r\n\r\n"
            s.sendall(head.encode())
            data = _read_all(s)
        status = int(data.split(b" ", 2)[1])
        return status, data.split(b"\r\n\r\n", 1)[1]

    def stop(self) -> None:
        self.proc.terminate()
        try:
            self.proc.communicate(timeout=15)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.communicate(timeout=5)


def _read_all(s: socket.socket, limit: int = 1 << 20) -> bytes:
    data = b""
    while len(data) < limit:
        chunk = s.recv(65536)
        if not chunk:
            break
        data += chunk
    return data


@pytest.fixture
def view(router, request):
    v = View(router, *getattr(request, "param", ()))
    yield v
    v.stop()


@pytest.mark.parametrize("view", [("--allow-host", "viewer.lab", "--idle-timeout", "1", "--rate", "0.2")], indirect=True)
def test_foreign_host_refused_idle_closed_streams_kept_alive(view):
    p = view.port
    for host in (f"127.0.0.1:{p}", f"localhost:{p}", "localhost", f"[::1]:{p}", f"viewer.lab:{p}", "viewer.lab"):
        status, body = view.request(host)
        assert status == 200 and body.startswith(b"{"), (host, status, body[:200])
    for host in ("evil.example", f"evil.example:{p}", f"rebind.attacker.test:{p}", f"127.0.0.1:{p + 1 if p < 65535 else p - 1}",
                 f"localhost.evil.example:{p}", None, "", "[::1", f"127.0.0.1:{p}:{p}"):
        status, body = view.request(host)
        assert status == 421, (host, status, body[:200])
    assert b"--allow-host" in view.request("evil.example")[1]  # says what to do

    # an idle connection (nothing sent) is closed after --idle-timeout 1 s
    with view.connect() as s:
        t0 = time.monotonic()
        assert s.recv(1) == b""
        idle = time.monotonic() - t0
    assert 0.8 <= idle < 6, f"idle connection closed after {idle:.2f} s"

    # an event stream at 0.2 updates/s (5 s apart) outlives the 1 s idle timeout: keep-alive comments
    with view.connect() as s:
        s.sendall(f"GET /events HTTP/1.1\r\nHost: 127.0.0.1:{p}\r\n\r\n".encode())
        data, deadline = b"", time.monotonic() + 3.0
        while time.monotonic() < deadline:
            chunk = s.recv(65536)
            assert chunk, f"the event stream was closed after {3.0 - (deadline - time.monotonic()):.2f} s: {data[-300:]!r}"
            data += chunk
    assert data.startswith(b"HTTP/1.1 200") and b"event: hello" in data
    assert data.count(b": keep-alive\n\n") >= 3, data[-500:]


@pytest.mark.parametrize("view", [("--idle-timeout", "20", "--rate", "1")], indirect=True)
def test_event_streams_fill_at_most_56_of_the_64_connections_and_pages_are_still_served(view):
    """56 event streams (busy: they never wait for a request, so none is replaced) fill the
    streams' share of the default 64 connections; the 57th stream gets 503 at once, a page and
    /state.json are still served, and a closed stream frees its place."""
    held = []

    def get_state() -> bytes:
        with view.connect() as s:
            s.sendall(f"GET /state.json HTTP/1.1\r\nHost: 127.0.0.1:{view.port}\r\nConnection: close\r\n\r\n".encode())
            return _read_all(s)

    try:
        for _ in range(56):
            s = view.connect()
            s.sendall(f"GET /events HTTP/1.1\r\nHost: 127.0.0.1:{view.port}\r\n\r\n".encode())
            assert s.recv(12) == b"HTTP/1.1 200"
            held.append(s)
        with view.connect() as extra:
            extra.sendall(f"GET /events HTTP/1.1\r\nHost: 127.0.0.1:{view.port}\r\n\r\n".encode())
            t0 = time.monotonic()
            head = _read_all(extra)
            assert time.monotonic() - t0 < 5
        assert head.startswith(b"HTTP/1.1 503"), head[:200]
        assert b"at most 56 event streams" in head, head[:400]
        assert get_state().startswith(b"HTTP/1.1 200")          # the reserved connections serve pages
        # a closed stream frees its place (bounded poll)
        held.pop(0).close()
        deadline = time.monotonic() + 10
        while True:
            s = view.connect()
            s.sendall(f"GET /events HTTP/1.1\r\nHost: 127.0.0.1:{view.port}\r\n\r\n".encode())
            if s.recv(12) == b"HTTP/1.1 200":
                held.append(s)
                break
            s.close()
            assert time.monotonic() < deadline, "no stream was served after one of 56 closed"
            time.sleep(0.05)
    finally:
        for s in held:
            s.close()


@pytest.mark.parametrize("view", [("--idle-timeout", "20", "--header-timeout", "1", "--max-connections", "8")],
                         indirect=True)
def test_slow_clients_neither_lock_out_arena_view_nor_stay(view):
    """10 connections trickling a request (more than --max-connections 8): a request is served
    at once (it replaces the slow client waiting longest) and every slow one is closed, however
    short its gaps (0.1 s, against --idle-timeout 20 s)."""
    slow = [view.connect() for _ in range(10)]
    try:
        for s in slow:
            s.sendall(b"GET /state")
        assert view.request(f"127.0.0.1:{view.port}")[0] == 200
        open_ = list(slow)
        for _ in range(100):   # one byte every 0.1 s on each open one, until the viewer closed them all
            still = []
            for s in open_:
                try:
                    s.sendall(b"x")
                    s.settimeout(0.01)
                    gone = s.recv(1) == b""
                except TimeoutError:
                    gone = False
                except OSError:
                    gone = True
                if not gone:
                    still.append(s)
            open_ = still
            if not open_:
                break
            time.sleep(0.1)   # the trickle's pace, not a synchronisation
        assert not open_, f"{len(open_)} of 10 slow connections still open after 10 s"
    finally:
        for s in slow:
            s.close()


def test_on_every_address_ip_literals_are_this_host_names_are_not():
    """Served on 0.0.0.0, any IP address of the Host header is one of this machine's (a page of
    another site cannot be at an IP literal); a DNS name must be allowed explicitly."""
    server = ViewerServer(ViewerState(), "0.0.0.0", 0, allow_hosts=["arena.lab"])
    try:
        p = server.port
        assert server.host_allowed(f"198.51.100.7:{p}") and server.host_allowed(f"[2001:db8::1]:{p}")
        assert server.host_allowed(f"arena.lab:{p}") and server.host_allowed("ARENA.LAB.")
        assert not server.host_allowed(f"evil.example:{p}")
        assert not server.host_allowed(f"198.51.100.7:{p + 1 if p < 65535 else p - 1}")
    finally:
        server.server_close()
    with pytest.raises(ValueError):
        ViewerServer(ViewerState(), "127.0.0.1", 0, max_connections=0)


@pytest.mark.parametrize("args", [["--max-connections", "0"], ["--idle-timeout", "0"], ["--header-timeout", "0"]])
def test_bad_limits_are_a_usage_error(args):
    r = subprocess.run(arena_cmd("view", "--port", "0", *args), capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "--max-connections must be >= 1 and --idle-timeout > 0" in r.stderr

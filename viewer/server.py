"""The viewer's HTTP server (stdlib ``ThreadingHTTPServer``): one page and its data.

Routes: ``/`` the page; ``/static/<file>`` its JS and CSS (package data); ``/frame.png`` the
current accumulated event image; ``/state.json`` one snapshot; ``/events`` Server-Sent Events,
one JSON snapshot per message every ``period_s``, with the event image rendered at the same moment
as a ``data:image/png;base64`` URL in ``frame`` (only when new windows arrived since the previous
message), so the page draws tracks over the very image they belong to. Nothing is fetched from
outside.

Hardening: a request whose ``Host`` header names neither the bound address, ``localhost``,
``127.0.0.1``/``::1`` nor a name allowed with ``allow_hosts`` is refused with 421 (a page of
another site whose name was re-pointed at this address, "DNS rebinding", cannot read the
viewer); at most ``max_connections`` connections are served at once; a
connection that sends or reads nothing for ``idle_timeout_s`` is closed (event streams are never
idle: they send a message every ``period_s``, at least a keep-alive comment); a connection that
has not sent a complete request line and headers within ``header_timeout_s`` of being accepted (or
of its previous response) is closed, however slowly it trickles bytes (counted in
``refused["slow"]`` if it had sent part of one). Slow clients cannot lock others out: when all
``max_connections`` are open, a new connection takes the place of the one that has waited
longest for its request (closed, counted in ``refused["evicted"]``); only when every open
connection is busy with a request (event streams, responses being sent) does a new one get 503
at once (``refused["busy"]``). Event streams never take the last connections: at most
``max_streams`` are served at once (default ``max_connections`` less an eighth of it, at least
one less, and at least 1), a stream beyond that gets 503 at once (``refused["streams"]``), so
pages and ``/state.json`` are still served however many streams clients hold open.

Last resort: an event image that cannot be rendered or encoded (whatever the reason, MemoryError
included) is answered 503 on ``/frame.png``, left out of the stream's message, counted in the
state's ``bad`` and logged (the first and every 1000th), never a traceback and a dropped connection.
"""

from __future__ import annotations

import base64
import io
import ipaddress
import json
import logging
import socket
import sys
import threading
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import urlsplit

from viewer.png import encode_indexed_png
from viewer.state import PALETTE, ViewerState

log = logging.getLogger("arena.viewer")

_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
          ".css": "text/css; charset=utf-8"}
_STATIC = ("index.html", "viewer.js", "viewer.css")


_STATIC_DIR = Path(__file__).resolve().parent / "static"  # package data


def _log_counted(n: int, what: str) -> None:
    # the first one and every 1000th at warning level: a misbehaving client must not flood the log
    log.log(logging.WARNING if n == 1 or n % 1000 == 0 else logging.DEBUG, "%s (%d so far)", what, n)


class _Conn:
    """One served connection: while it waits for a request (line and headers), since when
    (monotonic s), until when and whether any of it came yet; ``evicted`` once another
    connection took its place."""

    __slots__ = ("sock", "waiting_since", "deadline", "started", "evicted")

    def __init__(self, sock: socket.socket):
        self.sock = sock
        self.waiting_since: float | None = None
        self.deadline: float | None = None
        self.started = False
        self.evicted = False

    def wait(self, header_timeout_s: float) -> None:
        """Begin waiting for a request (lock held)."""
        self.waiting_since = time.monotonic()
        self.deadline = self.waiting_since + header_timeout_s
        self.started = False


class _DeadlineReader(io.RawIOBase):
    """The connection's reads: while a request is awaited, each read waits at most until the
    request's deadline (and at most ``idle_timeout_s``); past the deadline, TimeoutError."""

    def __init__(self, conn: _Conn, server: "ViewerServer"):
        super().__init__()
        self._conn, self._server = conn, server

    def readable(self) -> bool:
        return True

    def readinto(self, b) -> int:
        conn, srv = self._conn, self._server
        deadline = conn.deadline
        by_deadline = False
        if deadline is not None:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                if conn.started:
                    srv.count_slow()
                raise TimeoutError(f"no complete request within {srv.header_timeout_s:g} s")
            by_deadline = remaining < srv.idle_timeout_s
            conn.sock.settimeout(min(srv.idle_timeout_s, remaining))
        try:
            n = conn.sock.recv_into(b)
        except TimeoutError:
            if by_deadline and conn.started:  # (nothing sent at all: an idle connection, not a slow one)
                srv.count_slow()
            raise
        if n and deadline is not None:
            conn.started = True
        return n


class ViewerServer(ThreadingHTTPServer):
    """HTTP server of the viewer on ``(host, port)`` (port 0: any free port, see ``.port``)."""

    daemon_threads = True
    allow_reuse_address = True

    def __init__(self, state: ViewerState, host: str = "127.0.0.1", port: int = 8080, period_s: float = 0.1,
                 title: str = "arena view", allow_hosts: tuple[str, ...] | list[str] = (),
                 max_connections: int = 64, idle_timeout_s: float = 30.0, header_timeout_s: float = 10.0,
                 max_streams: int | None = None):
        if max_connections < 1 or idle_timeout_s <= 0 or not header_timeout_s > 0:
            raise ValueError("max_connections must be >= 1, idle_timeout_s > 0 and header_timeout_s > 0")
        if max_streams is None:
            max_streams = max(1, max_connections - max(1, max_connections // 8))
        if not 1 <= max_streams <= max_connections:
            raise ValueError(f"max_streams must be in [1, max_connections={max_connections}], got {max_streams}")
        self.max_streams = max_streams
        self.state = state
        self.period_s = period_s
        self.title = title
        self.stopping = threading.Event()
        self.clients = 0
        self.allow_hosts = {h.strip().lower().rstrip(".") for h in allow_hosts if h.strip()}
        self.max_connections = max_connections
        self.idle_timeout_s = idle_timeout_s
        self.header_timeout_s = header_timeout_s
        # counts of refused requests / connections (see the module docstring)
        self.refused = {"host": 0, "busy": 0, "slow": 0, "evicted": 0, "streams": 0}
        self._conn_lock = threading.Lock()
        self._conns: dict[socket.socket, _Conn] = {}
        self._open = 0      # connections counted against max_connections
        self._closing = 0   # evicted connections whose threads have not ended yet
        # the listen backlog: connections the kernel completes before they are accepted (the
        # default 5 made a burst of connections, a browser's or a slow client's, wait for SYN retries)
        self.request_queue_size = max(16, max_connections)
        self._files = {name: (_STATIC_DIR / name).read_bytes() for name in _STATIC}
        self._frame_lock = threading.Lock()
        self._frame: tuple[int, str | None] = (-1, None)
        super().__init__((host, port), _Handler)

    def render_png(self) -> bytes | None:
        """The event image as PNG bytes; None before the first window. Raises whatever rendering
        raises (callers answer it with :meth:`render_failed`)."""
        index = self.state.render_index()
        return None if index is None else encode_indexed_png(index, PALETTE)

    def render_failed(self, exc: BaseException) -> None:
        """Count (the state's ``bad``) and log an event image that could not be made."""
        _log_counted(self.state.on_bad(), f"event image not rendered ({type(exc).__name__}: {str(exc)[:300]})")
        log.debug("event image not rendered", exc_info=True)

    def frame_url(self, windows: int) -> str | None:
        """The event image as a PNG data URL, rendered once per count of received ``windows``
        however many pages are open; None before the first window or if it cannot be rendered
        (counted and logged, tried again at the next count)."""
        with self._frame_lock:
            if self._frame[0] != windows:
                try:
                    png = self.render_png()
                    url = None if png is None else "data:image/png;base64," + base64.b64encode(png).decode()
                except Exception as exc:   # last resort (MemoryError included): no image this time
                    self.render_failed(exc)
                    url = None
                self._frame = (windows, url)
            return self._frame[1]

    def count_slow(self) -> None:
        with self._conn_lock:
            self.refused["slow"] += 1
            n = self.refused["slow"]
        _log_counted(n, f"closed a connection that sent no complete request within {self.header_timeout_s:g} s")

    @property
    def port(self) -> int:
        return self.server_address[1]

    @property
    def url(self) -> str:
        host = self.server_address[0]
        return f"http://{'127.0.0.1' if host in ('0.0.0.0', '') else host}:{self.port}/"

    def shutdown(self) -> None:
        """Stop serving and end every event stream."""
        self.stopping.set()
        super().shutdown()

    # ---- connection bound -------------------------------------------------------------------
    def process_request(self, request, client_address) -> None:
        """Serve the connection on a thread if fewer than ``max_connections`` are open, or else
        in place of the open connection that has waited longest for its request (closed); if
        every open one is busy with a request, answer 503 at once and close it (the accepting
        thread never waits on a client)."""
        victim = None
        with self._conn_lock:
            if self._open >= self.max_connections and self._closing < self.max_connections:
                waiting = [c for c in self._conns.values() if c.waiting_since is not None and not c.evicted]
                if waiting:
                    victim = min(waiting, key=lambda c: c.waiting_since)
                    victim.evicted = True
                    self._open -= 1
                    self._closing += 1
                    self.refused["evicted"] += 1
                    n_evicted = self.refused["evicted"]
            busy = self._open >= self.max_connections
            if not busy:
                self._open += 1
                self._conns[request] = _Conn(request)
                self._conns[request].wait(self.header_timeout_s)
        if victim is not None:
            _log_counted(n_evicted, f"closed the connection waiting longest for its request: {self.max_connections} "
                                    "connections open (the most)")
            try:
                victim.sock.shutdown(socket.SHUT_RDWR)  # its thread's read ends; the thread ends
            except OSError:
                pass
        if busy:
            self.refused["busy"] += 1
            log.warning("refused a connection from %s: %d connections open (the most)", client_address[0],
                        self.max_connections)
            try:
                request.settimeout(1.0)
                body = f"the viewer serves at most {self.max_connections} connections at once; try again later\n"
                request.sendall((f"HTTP/1.1 503 Service Unavailable\r\nContent-Type: text/plain\r\n"
                                 f"Content-Length: {len(body)}\r\nRetry-After: 5\r\nConnection: close\r\n\r\n"
                                 + body).encode())
            except OSError:
                pass
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            self._release(request)
            raise

    def _release(self, request) -> None:
        with self._conn_lock:
            conn = self._conns.pop(request, None)
            if conn is not None:
                if conn.evicted:
                    self._closing -= 1
                else:
                    self._open -= 1

    def shutdown_request(self, request) -> None:
        # counted free before the socket closes: a client that read its answer to the end and
        # connects again at once must find the place it left
        self._release(request)
        super().shutdown_request(request)

    def process_request_thread(self, request, client_address) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._release(request)

    def handle_error(self, request, client_address) -> None:
        """A connection's failure: a client that went away is no error of the viewer's."""
        exc = sys.exc_info()[1]
        if isinstance(exc, OSError):
            log.debug("connection from %s ended: %s", client_address[0], exc)
        else:
            log.warning("connection from %s failed", client_address[0], exc_info=True)

    # ---- Host header --------------------------------------------------------------------------
    def host_allowed(self, header: str | None) -> bool:
        """Whether a request's ``Host`` header names this server (see the module docstring)."""
        if not header:
            return False
        value = header.strip().lower()
        if value.rstrip(".") in self.allow_hosts:
            return True  # an allowed name with its port (e.g. behind a proxy)
        name, port = _split_host(value)
        if name is None:
            return False
        if port is not None and port != self.port:
            return name in self.allow_hosts
        if name in self.allow_hosts or name in ("localhost", "127.0.0.1", "::1"):
            return True
        bound = self.server_address[0].lower()
        if name == bound:
            return True
        if bound in ("0.0.0.0", "", "::"):  # every address of this machine: any IP literal is one of them
            try:
                ipaddress.ip_address(name)
                return True
            except ValueError:
                return name in (socket.gethostname().lower(), socket.getfqdn().lower())
        return False


def _split_host(value: str) -> tuple[str | None, int | None]:
    """``name[:port]`` or ``[v6][:port]`` -> (name without a final dot, port); (None, None) if malformed."""
    if value.startswith("["):
        end = value.find("]")
        if end < 0:
            return None, None
        name, rest = value[1:end], value[end + 1:]
        if rest and not rest.startswith(":"):
            return None, None
        port_text = rest[1:] if rest else ""
    elif value.count(":") == 1:
        name, port_text = value.split(":")
    elif ":" in value:
        return None, None
    else:
        name, port_text = value, ""
    if port_text:
        if not port_text.isdigit() or not 0 < int(port_text) <= 65535:
            return None, None
        port = int(port_text)
    else:
        port = None
    name = name.rstrip(".")
    return (name or None), port


class _Handler(BaseHTTPRequestHandler):
    server: ViewerServer
    protocol_version = "HTTP/1.1"

    def setup(self) -> None:
        self.timeout = self.server.idle_timeout_s  # every read and write of this connection
        super().setup()
        self._conn = self.server._conns[self.request]
        plain, self.rfile = self.rfile, io.BufferedReader(_DeadlineReader(self._conn, self.server))
        plain.close()  # (else the socket's descriptor outlives the connection)

    def handle_one_request(self) -> None:
        conn = self._conn
        with self.server._conn_lock:
            if conn.waiting_since is None:  # the next request of a kept-alive connection
                conn.wait(self.server.header_timeout_s)
        super().handle_one_request()

    def parse_request(self) -> bool:
        ok = super().parse_request()
        conn = self._conn
        with self.server._conn_lock:
            if conn.evicted:  # another connection took its place: no answer
                self.close_connection = True
                return False
            conn.waiting_since = conn.deadline = None  # a request: served, not evictable
        self.connection.settimeout(self.server.idle_timeout_s)
        return ok

    def log_message(self, fmt, *args) -> None:  # route to logging instead of stderr
        log.debug("%s %s", self.address_string(), fmt % args)

    def _send(self, body: bytes, ctype: str, status: int = 200) -> None:
        self.send_response(status)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)

    def do_GET(self) -> None:  # noqa: N802 - http.server naming
        if not self.server.host_allowed(self.headers.get("Host")):
            self.server.refused["host"] += 1
            log.warning("refused a request from %s for Host %r (not this viewer's name)", self.client_address[0],
                        self.headers.get("Host"))
            self.close_connection = True
            self._send(f"this viewer answers to http://127.0.0.1:{self.server.port}/ (or the address it serves on), "
                       f"not to Host {self.headers.get('Host')!r}; start it with --allow-host NAME to allow that "
                       "name\n".encode(), "text/plain", HTTPStatus.MISDIRECTED_REQUEST)
            return
        path = urlsplit(self.path).path
        if path in ("/", "/index.html"):
            self._send(self.server._files["index.html"], _TYPES[".html"])
        elif path.startswith("/static/") and path[8:] in self.server._files:
            name = path[8:]
            self._send(self.server._files[name], _TYPES[name[name.rfind("."):]])
        elif path == "/frame.png":
            try:
                png = self.server.render_png()
            except Exception as exc:   # last resort (MemoryError included): an answer, not a dropped connection
                self.server.render_failed(exc)
                self.close_connection = True
                self._send(f"the event image cannot be rendered ({type(exc).__name__}); see the viewer's log\n".encode(),
                           "text/plain", HTTPStatus.SERVICE_UNAVAILABLE)
                return
            if png is None:
                self._send(b"no event window received yet", "text/plain", HTTPStatus.SERVICE_UNAVAILABLE)
            else:
                self._send(png, "image/png")
        elif path == "/state.json":
            self._send(json.dumps(self.server.state.snapshot()).encode(), "application/json")
        elif path == "/events":
            self._stream()
        else:
            self._send(b"not found", "text/plain", HTTPStatus.NOT_FOUND)

    def _stream(self) -> None:
        srv = self.server
        with srv._conn_lock:
            full = srv.clients >= srv.max_streams
            if full:
                srv.refused["streams"] += 1
                n = srv.refused["streams"]
            else:
                srv.clients += 1
        if full:   # the connections left are kept for pages and /state.json
            _log_counted(n, f"refused an event stream from {self.client_address[0]}: {srv.max_streams} open (the most)")
            self.close_connection = True
            self.send_response(HTTPStatus.SERVICE_UNAVAILABLE)
            self.send_header("Retry-After", "5")
            body = (f"the viewer serves at most {srv.max_streams} event streams at once; try again later\n").encode()
            self.send_header("Content-Type", "text/plain")
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Connection", "close")
            self.end_headers()
            self.wfile.write(body)
            return
        self.send_response(200)
        self.send_header("Content-Type", "text/event-stream")
        self.send_header("Cache-Control", "no-store")
        self.send_header("Connection", "close")
        self.end_headers()
        self.close_connection = True
        try:
            self.wfile.write(f"retry: 1000\nevent: hello\ndata: {json.dumps({'title': srv.title})}\n\n".encode())
            sent_windows = -1
            while not srv.stopping.is_set():
                snap = srv.state.snapshot()
                if snap["counts"]["windows"] != sent_windows:
                    url = srv.frame_url(snap["counts"]["windows"])
                    if url is not None:
                        snap["frame"] = url
                        sent_windows = snap["counts"]["windows"]
                data = json.dumps(snap, separators=(",", ":"))
                self.wfile.write(f"data: {data}\n\n".encode())
                self.wfile.flush()
                # slow rates: a keep-alive comment at least every half idle timeout, so neither this
                # server nor a proxy or browser ever sees the stream idle
                remaining = srv.period_s
                while remaining > 0 and not srv.stopping.is_set():
                    step = min(remaining, srv.idle_timeout_s / 2)
                    if srv.stopping.wait(step):
                        break
                    remaining -= step
                    if remaining > 0:
                        self.wfile.write(b": keep-alive\n\n")
                        self.wfile.flush()
        except (BrokenPipeError, ConnectionResetError, OSError):
            pass  # the page was closed
        finally:
            with srv._conn_lock:
                srv.clients -= 1

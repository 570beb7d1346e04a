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
viewer); at most ``max_connections`` connections are served at once (more get 503 at once); a
connection that sends or reads nothing for ``idle_timeout_s`` is closed (event streams are never
idle: they send a message every ``period_s``, at least a keep-alive comment).
"""

from __future__ import annotations

import base64
import ipaddress
import json
import logging
import socket
import threading
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


class ViewerServer(ThreadingHTTPServer):
    """HTTP server of the viewer on ``(host, port)`` (port 0: any free port, see ``.port``)."""

    daemon_threads = True
    allow_reuse_address = True

    def __init__(self, state: ViewerState, host: str = "127.0.0.1", port: int = 8080, period_s: float = 0.1,
                 title: str = "arena view", allow_hosts: tuple[str, ...] | list[str] = (),
                 max_connections: int = 64, idle_timeout_s: float = 30.0):
        if max_connections < 1 or idle_timeout_s <= 0:
            raise ValueError("max_connections must be >= 1 and idle_timeout_s > 0")
        self.state = state
        self.period_s = period_s
        self.title = title
        self.stopping = threading.Event()
        self.clients = 0
        self.allow_hosts = {h.strip().lower().rstrip(".") for h in allow_hosts if h.strip()}
        self.max_connections = max_connections
        self.idle_timeout_s = idle_timeout_s
        self.refused = {"host": 0, "busy": 0}  # counts of refused requests / connections
        self._slots = threading.BoundedSemaphore(max_connections)
        self._files = {name: (_STATIC_DIR / name).read_bytes() for name in _STATIC}
        self._frame_lock = threading.Lock()
        self._frame: tuple[int, str | None] = (-1, None)
        super().__init__((host, port), _Handler)

    def frame_url(self, windows: int) -> str | None:
        """The event image as a PNG data URL, rendered once per count of received ``windows``
        however many pages are open; None before the first window."""
        with self._frame_lock:
            if self._frame[0] != windows:
                index = self.state.render_index()
                url = None if index is None else \
                    "data:image/png;base64," + base64.b64encode(encode_indexed_png(index, PALETTE)).decode()
                self._frame = (windows, url)
            return self._frame[1]

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
        """Serve the connection on a thread if fewer than ``max_connections`` are open; else
        answer 503 at once and close it (the accepting thread never waits on a client)."""
        if not self._slots.acquire(blocking=False):
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
            self._slots.release()
            raise

    def process_request_thread(self, request, client_address) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._slots.release()

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
            index = self.server.state.render_index()
            if index is None:
                self._send(b"no event window received yet", "text/plain", HTTPStatus.SERVICE_UNAVAILABLE)
            else:
                self._send(encode_indexed_png(index, PALETTE), "image/png")
        elif path == "/state.json":
            self._send(json.dumps(self.server.state.snapshot()).encode(), "application/json")
        elif path == "/events":
            self._stream()
        else:
            self._send(b"not found", "text/plain", HTTPStatus.NOT_FOUND)

    def _stream(self) -> None:
        self.send_response(200)
        self.send_header("Content-Type", "text/event-stream")
        self.send_header("Cache-Control", "no-store")
        self.send_header("Connection", "close")
        self.end_headers()
        self.close_connection = True
        srv = self.server
        srv.clients += 1
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
            srv.clients -= 1

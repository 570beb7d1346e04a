"""The viewer's HTTP server (stdlib ``ThreadingHTTPServer``): one page and its data.

Routes: ``/`` the page; ``/static/<file>`` its JS and CSS (package data); ``/frame.png`` the
current accumulated event image; ``/state.json`` one snapshot; ``/events`` Server-Sent Events,
one JSON snapshot per message every ``period_s``, with the event image rendered at the same moment
as a ``data:image/png;base64`` URL in ``frame`` (only when new windows arrived since the previous
message), so the page draws tracks over the very image they belong to. Nothing is fetched from
outside.
"""

from __future__ import annotations

import base64
import json
import logging
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
                 title: str = "arena view"):
        self.state = state
        self.period_s = period_s
        self.title = title
        self.stopping = threading.Event()
        self.clients = 0
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


class _Handler(BaseHTTPRequestHandler):
    server: ViewerServer
    protocol_version = "HTTP/1.1"

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
                srv.stopping.wait(srv.period_s)
        except (BrokenPipeError, ConnectionResetError, OSError):
            pass  # the page was closed
        finally:
            srv.clients -= 1

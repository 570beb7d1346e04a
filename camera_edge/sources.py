"""Event sources: one small interface over files, TCP byte streams and vendor cameras.

python-can style: :class:`EventSource` is the abstract base (``read`` and ``close``);
:func:`open_source` picks a backend from a URL scheme (:data:`SOURCE_SCHEMES`) or a file
extension (:data:`SOURCE_EXTENSIONS`), else from the source plug-ins that installed packages
register in the entry-point group ``arena.sources``::

    with open_source("tcp://127.0.0.1:9000") as src:        # live EVT 3.0 stream
        while (ev := src.read()) is not None:
            ...
    open_source("rec.raw", speed=1)       # replay a file at real time (speed 0: as fast as possible)
    open_source("prophesee:")             # first Prophesee camera (OpenEB metavision_core)
    open_source("inivation:DVXplorer_xxx")  # an iniVation camera (dv-processing)

``read()`` returns an event chunk (:data:`arena.events.EVENT_DTYPE`, sensor px, µs; it may be
empty when nothing arrived within ``timeout``) or ``None`` at the end of a file or after
``close()``. ``time_us`` is the latest sensor time known (also from time words without
events), so slicing can advance through silent periods.

A lab adds its own camera without touching this package: its distribution declares ::

    [project.entry-points."arena.sources"]
    mycam = "mycam_arena:MyCamSource"     # opened as mycam_arena.MyCamSource("mycam:...", **opts)

and ``arena edge mycam:ID`` opens it. The entry point loads a callable ``(url, **opts) ->
EventSource`` (typically an :class:`EventSource` subclass); it is looked up, and imported,
only when a source with that scheme is opened. Built-in schemes take precedence over a
plug-in of the same name.
"""

from __future__ import annotations

import abc
import contextlib
import logging
import re
import socket
import time
import urllib.parse
import warnings
from collections.abc import Callable
from importlib.metadata import EntryPoint, entry_points
from pathlib import Path

import numpy as np

from arena.events import EVENT_DTYPE, empty_events
from arena.formats import READ_EXTENSIONS, FormatError, SkippedData, iter_events
from arena.formats.raw import make_decoder, parse_raw_header

log = logging.getLogger("camera_edge.sources")


class SourceError(RuntimeError):
    """A source cannot be opened (unknown URL, missing SDK, unreadable file); the message says why."""


class EventSource(abc.ABC):
    """Abstract event source. Subclasses set ``width``/``height`` (px) and ``name``, call
    ``super().__init__()``, and implement :meth:`read` and :meth:`close`."""

    width: int = 0
    height: int = 0
    #: short description for logs and status
    name: str = ""

    def __init__(self) -> None:
        self.time_us: int | None = None
        #: events dropped by the source (outside the sensor, corrupt input)
        self.invalid = 0
        #: other parts of the input skipped, by unit (e.g. ``{"corrupt packets": 3}``: what a
        #: file reader reports as :class:`~arena.formats.SkippedData`); units ending in ")" say
        #: what was done instead (``"events out of time order (kept)"``) and are no loss
        self.skipped: dict[str, int] = {}

    @abc.abstractmethod
    def read(self, timeout: float = 0.1) -> np.ndarray | None:
        """Next chunk of events (sensor px, µs, in stream order); empty if none within
        ``timeout`` s; None when finished or closed. Updates :attr:`time_us`."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the device, socket or file (idempotent); ``read`` returns None afterwards."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __iter__(self):
        while (ev := self.read()) is not None:
            yield ev

    def _note_time(self, ev: np.ndarray) -> None:
        if ev.size:
            t = int(ev["t"][-1])
            if self.time_us is None or t > self.time_us:
                self.time_us = t


class FileSource(EventSource):
    """Replay of an event file (any format of :mod:`arena.formats`) at ``speed`` x real time.

    ``speed`` 1 plays at the sensor's pace (wall time follows sensor time), 2 twice as fast,
    0 as fast as possible. ``loop`` restarts at the end with times shifted to keep increasing.
    """

    def __init__(self, path: str | Path, speed: float = 1.0, chunk_events: int = 1 << 16,
                 loop: bool = False) -> None:
        super().__init__()
        if speed < 0:
            raise SourceError(f"speed must be >= 0, got {speed}")
        self.path, self.speed, self.loop = str(path), float(speed), loop
        self._chunk_events = chunk_events
        self._units_logged: set[str] = set()   # kinds of skip logged already (once each)
        try:
            with self._skips_counted():
                self._reader = iter_events(path, chunk_events=chunk_events)
        except FormatError as exc:
            raise SourceError(str(exc)) from None
        self.width, self.height = self._reader.width, self._reader.height
        self.name = f"file {Path(path).name}"
        self._it = iter(self._reader)
        self._buf = empty_events(0)
        self._t0_sensor: int | None = None
        self._t0_wall = 0.0
        self._file_t0: int | None = None
        self._shift = 0
        self._t_last = 0
        self._done = False

    @contextlib.contextmanager
    def _skips_counted(self):
        """Within: the readers' :class:`SkippedData` warnings are counted in :attr:`skipped` (by
        unit) and logged once per unit, not printed each (a file of 125 000 undescribed packets
        printed 250 000 lines) nor held (the warnings registry keeps each distinct text)."""
        show = warnings.showwarning

        def tally(message, category, *args, **kw) -> None:
            if not isinstance(message, SkippedData):
                show(message, category, *args, **kw)
                return
            unit = message.unit
            if unit not in self._units_logged:
                self._units_logged.add(unit)
                log.warning("%s (the first; further ones are counted, not logged)", message)
            if unit != "invalid events":   # those are in `invalid` (the reader's count)
                self.skipped[unit] = self.skipped.get(unit, 0) + message.count

        with warnings.catch_warnings():
            warnings.simplefilter("always", SkippedData)
            warnings.showwarning = tally
            yield

    def _stop(self, exc: Exception) -> None:
        """Log why the replay stops: ``exc`` once, with the file's path once."""
        text = str(exc)
        log.warning("%s; stopping the replay", text if self.path in text else f"{self.path}: {text}")

    def _reopen(self) -> bool:
        """Open the file again for the next pass of a loop; False (logged) if it is gone, damaged
        or now of another sensor size (it may have been replaced since the last pass)."""
        self._reader.close()
        try:
            with self._skips_counted():
                reader = iter_events(self.path, chunk_events=self._chunk_events)
        except (FormatError, OSError) as exc:
            self._stop(exc)
            return False
        if (reader.width, reader.height) != (self.width, self.height):
            reader.close()
            self._stop(FormatError(f"{self.path}: the sensor is now {reader.width} x {reader.height} px, "
                                   f"not {self.width} x {self.height} (the file was replaced)"))
            return False
        self._reader, self._it = reader, iter(reader)
        return True

    def _next_chunk(self) -> np.ndarray | None:
        while True:
            try:
                with self._skips_counted():
                    chunk = next(self._it)
            except StopIteration:
                self.invalid += self._reader.invalid
                if not self.loop or self._file_t0 is None or not self._reopen():
                    return None
                self._shift = self._t_last + 1 - self._file_t0
                continue
            except (FormatError, OSError) as exc:
                self._stop(exc)
                return None
            if chunk.size == 0:
                continue
            if self._file_t0 is None:
                self._file_t0 = int(chunk["t"][0])
            if self._shift:
                chunk = chunk.copy()
                chunk["t"] += self._shift
            return chunk

    def read(self, timeout: float = 0.1) -> np.ndarray | None:
        if self._done:
            return None
        if self._buf.size == 0:
            chunk = self._next_chunk()
            if chunk is None:
                self._done = True
                return None
            self._buf = chunk
        buf = self._buf
        if self.speed == 0:
            out, self._buf = buf, empty_events(0)
        else:
            now = time.monotonic()
            if self._t0_sensor is None:
                self._t0_sensor, self._t0_wall = int(buf["t"][0]), now
            due = self._t0_sensor + int((now - self._t0_wall) * 1e6 * self.speed)
            if int(buf["t"][0]) > due:
                time.sleep(min((int(buf["t"][0]) - due) / 1e6 / self.speed, timeout))
                due = self._t0_sensor + int((time.monotonic() - self._t0_wall) * 1e6 * self.speed)
            k = int(np.searchsorted(buf["t"], due, side="right"))
            out, self._buf = buf[:k], buf[k:]
            if self._buf.size:  # nothing else happened before the next event: time has reached `due`
                self.time_us = max(self.time_us or due, min(due, int(self._buf["t"][0]) - 1))
        self._note_time(out)
        if out.size:
            self._t_last = int(out["t"][-1])
        return out

    def close(self) -> None:
        self._done = True
        self._reader.close()


class TcpSource(EventSource):
    """A live stream of EVT words over TCP (``tcp://host:port``), e.g. the simulator's camera.

    The stream may start with a Prophesee RAW text header (``% ...`` lines, ``% end``), which
    gives the EVT version and sensor size; otherwise they come from the URL query
    (``?evt=3&width=640&height=480``), else the ``width``/``height`` arguments, else EVT 3.0 and
    1280 x 720 px. A lost or refused
    connection is retried with exponential backoff (``backoff_s`` doubling up to
    ``max_backoff_s``); ``read`` never blocks longer than its timeout.
    """

    def __init__(self, url: str, width: int | None = None, height: int | None = None,
                 connect_timeout_s: float = 2.0, backoff_s: float = 0.1, max_backoff_s: float = 2.0,
                 recv_bytes: int = 1 << 18) -> None:
        super().__init__()
        u = urllib.parse.urlsplit(url)
        if not u.hostname or not u.port:
            raise SourceError(f"{url!r}: a TCP source needs tcp://HOST:PORT")
        q = dict(urllib.parse.parse_qsl(u.query))
        self.host, self.port, self.name = u.hostname, u.port, f"tcp {u.hostname}:{u.port}"
        try:
            self.version = {"3": "3.0", "2": "2.0", "21": "2.1"}.get(q.get("evt", "3"), q.get("evt", "3"))
            self.width, self.height = int(q.get("width", width or 1280)), int(q.get("height", height or 720))
        except ValueError:
            raise SourceError(f"{url!r}: width and height must be integers") from None
        make_decoder(self.version).feed(b"")  # validates the version; loads the compiled decoder
        self.connect_timeout_s, self.backoff_s, self.max_backoff_s = connect_timeout_s, backoff_s, max_backoff_s
        self._recv_bytes = recv_bytes
        self._sock: socket.socket | None = None
        self._decoder = None
        self._pending = b""
        self._carry = b""  # event bytes that arrived with the header
        self._next_try = 0.0
        self._delay = backoff_s
        self._closed = False
        self.reconnects = 0
        self.bytes_in = 0
        self._connect(first=True)

    @property
    def connected(self) -> bool:
        """Whether the TCP connection is up."""
        return self._sock is not None

    def _connect(self, first: bool = False) -> None:
        try:
            sock = socket.create_connection((self.host, self.port), timeout=self.connect_timeout_s)
        except OSError as exc:
            self._next_try = time.monotonic() + self._delay
            if first:
                log.warning("%s: %s; retrying every %.1f-%.1f s", self.name, exc, self.backoff_s,
                            self.max_backoff_s)
            self._delay = min(self._delay * 2, self.max_backoff_s)
            return
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock = sock
        self._delay = self.backoff_s
        self._decoder = None
        self._pending = b""
        if not first:
            self.reconnects += 1
            log.info("%s: reconnected", self.name)
        # a header, if any, arrives first: read it now so width/height are known
        deadline = time.monotonic() + self.connect_timeout_s
        while self._decoder is None and time.monotonic() < deadline and self._sock is not None:
            self._carry += self._recv(max(0.0, deadline - time.monotonic()))
        if self._decoder is None and self._sock is not None and self._pending:
            self._start_decoder(b"")

    def _start_decoder(self, head: bytes) -> None:
        if head:
            try:
                hdr = parse_raw_header(head)
            except FormatError as exc:
                log.warning("%s: bad stream header (%s); using %s", self.name, exc, self.version)
            else:
                self.version, self.width, self.height = hdr.version, hdr.width, hdr.height
        self._decoder = make_decoder(self.version)

    def _recv(self, timeout: float) -> bytes:
        """Receive what arrives within ``timeout`` s; handle the header; return event bytes."""
        assert self._sock is not None
        self._sock.settimeout(max(timeout, 1e-3))
        try:
            data = self._sock.recv(self._recv_bytes)
        except socket.timeout:
            return b""
        except OSError as exc:
            self._lost(str(exc))
            return b""
        if not data:
            self._lost("connection closed by the camera")
            return b""
        self.bytes_in += len(data)
        if self._decoder is not None:
            return data
        self._pending += data
        buf = self._pending
        if not buf.startswith(b"%"):
            self._start_decoder(b"")
            self._pending = b""
            return buf
        # header complete when a line not starting with '%' follows, or '% end'
        pos = 0
        while pos < len(buf) and buf[pos:pos + 1] == b"%":
            end = buf.find(b"\n", pos)
            if end < 0:
                return b""
            line = buf[pos:end]
            pos = end + 1
            if line.strip() == b"% end":
                break
        else:
            if pos >= len(buf):
                return b""  # maybe more header lines to come
        self._start_decoder(buf[:pos])
        self._pending = b""
        return buf[pos:]

    def _lost(self, why: str) -> None:
        log.warning("%s: %s; reconnecting", self.name, why)
        if self._sock is not None:
            self._sock.close()
        self._sock = None
        self._next_try = time.monotonic() + self._delay
        self._delay = min(self._delay * 2, self.max_backoff_s)

    def read(self, timeout: float = 0.1) -> np.ndarray | None:
        if self._closed:
            return None
        if self._sock is None:
            wait = self._next_try - time.monotonic()
            if wait > 0:
                time.sleep(min(wait, timeout))
                return empty_events(0)
            self._connect()
            return empty_events(0)
        data = self._carry or self._recv(timeout)
        self._carry = b""
        if not data or self._decoder is None:
            return empty_events(0)
        ev = self._decoder.feed(data)
        bad = (ev["x"] >= self.width) | (ev["y"] >= self.height)
        if bad.any():
            self.invalid += int(bad.sum())
            ev = ev[~bad]
        t = self._decoder.time_us
        if t is not None and (self.time_us is None or t > self.time_us):
            self.time_us = t
        return ev

    def close(self) -> None:
        self._closed = True
        if self._sock is not None:
            self._sock.close()
            self._sock = None


class PropheseeSource(EventSource):
    """A live Prophesee camera through OpenEB's ``metavision_core`` (``prophesee:[SERIAL]``)."""

    def __init__(self, serial: str = "", delta_t_us: int = 10_000) -> None:
        super().__init__()
        try:
            from metavision_core.event_io import EventsIterator  # type: ignore[import-not-found]
        except ImportError:
            raise SourceError(
                "Prophesee cameras need OpenEB's Python bindings (metavision_core), which are not on "
                "PyPI: build OpenEB (https://github.com/prophesee-ai/openeb) with Python bindings or "
                "install the Metavision SDK, then check `python -c 'import metavision_core'`. "
                "Or record with Metavision Studio and replay the .raw file.") from None
        try:
            self._it_obj = EventsIterator(input_path=serial, delta_t=delta_t_us)
            self.height, self.width = self._it_obj.get_size()
        except Exception as exc:  # noqa: BLE001 - the SDK raises assorted types, with long texts
            raise SourceError(f"cannot open Prophesee camera {serial or '(first)'}: {_first_line(exc)}") from None
        self._it = iter(self._it_obj)
        self.name = f"prophesee {serial or '(first)'}"

    def read(self, timeout: float = 0.1) -> np.ndarray | None:
        try:
            raw = next(self._it)
        except StopIteration:
            return None
        ev = np.empty(raw.size, EVENT_DTYPE)
        for f in "xypt":
            ev[f] = raw[f]
        self._note_time(ev)
        return ev

    def close(self) -> None:
        self._it = iter(())
        self._it_obj = None   # the SDK releases the camera with its iterator


class InivationSource(EventSource):
    """A live iniVation camera through ``dv-processing`` 2.x (``inivation:[SERIAL]``).

    ``reader``: any dv-processing input with ``getNextEventBatch`` (a camera, or a
    ``dv.io.MonoCameraRecording``) instead of opening a camera; how the tests check this adapter
    against the real SDK without a camera.
    """

    def __init__(self, name: str = "", reader=None) -> None:
        super().__init__()
        self._cam = reader if reader is not None else self._open_camera(name)
        res = self._cam.getEventResolution()
        if res is None:
            raise SourceError(f"iniVation camera {name or '(first)'} has no event stream")
        self.width, self.height = int(res[0]), int(res[1])
        self.name = f"inivation {name or '(first)'}"

    @staticmethod
    def _open_camera(name: str):
        try:
            import dv_processing as dv  # type: ignore[import-not-found]
        except ImportError:
            raise SourceError("iniVation cameras need dv-processing: pip install 'arena-fleet[inivation]' "
                              "(or pip install dv-processing)") from None
        try:
            found = [d.serialNumber for d in dv.io.camera.discover()]
        except Exception as exc:  # noqa: BLE001
            raise SourceError(f"dv-processing cannot list cameras: {_first_line(exc)}") from None
        if not found:
            raise SourceError("no iniVation camera found: dv-processing sees none on USB (check the cable, "
                              "and that your user may open it: iniVation's udev rules)")
        if name and name not in found:
            raise SourceError(f"no iniVation camera with serial {name!r}; found: {', '.join(found)}")
        try:
            return dv.io.camera.open(name) if name else dv.io.camera.open()
        except Exception as exc:  # noqa: BLE001 - the SDK raises assorted types, with stack traces
            raise SourceError(f"cannot open iniVation camera {name or found[0]}: {_first_line(exc)}") from None

    def read(self, timeout: float = 0.1) -> np.ndarray | None:
        if self._cam is None or not self._cam.isRunning():
            return None
        batch = self._cam.getNextEventBatch()
        if batch is None:
            time.sleep(min(timeout, 0.002))
            return empty_events(0)
        arr = batch.numpy()
        ev = np.empty(arr.size, EVENT_DTYPE)
        ev["x"], ev["y"], ev["p"], ev["t"] = arr["x"], arr["y"], arr["polarity"], arr["timestamp"]
        self._note_time(ev)
        return ev

    def close(self) -> None:
        """Stop reading and let go of the camera (dv-processing has no close call: it releases
        the device, or the recording, when its last reference goes)."""
        self._cam = None


def _first_line(exc: BaseException) -> str:
    """An SDK exception's first meaningful line (dv-processing appends a C++ stack trace)."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    for ln in lines:
        if ln.startswith("RuntimeError:"):
            return ln.split(":", 1)[1].strip()
    return lines[0] if lines else type(exc).__name__


#: how a source is opened: ``opener(url_or_path, **opts) -> EventSource``
SourceOpener = Callable[..., EventSource]
#: the entry-point group in which installed packages register source schemes
SOURCE_ENTRY_POINTS = "arena.sources"


def _open_prophesee(url: str, **opts) -> EventSource:
    return PropheseeSource(url.split(":", 1)[1], **opts)


def _open_inivation(url: str, **opts) -> EventSource:
    return InivationSource(url.split(":", 1)[1], **opts)


#: built-in URL schemes (``scheme:...``), each with its usage for messages
SOURCE_SCHEMES: dict[str, SourceOpener] = {"tcp": TcpSource, "prophesee": _open_prophesee,
                                           "inivation": _open_inivation}
SCHEME_USAGE = {"tcp": "tcp://HOST:PORT", "prophesee": "prophesee:[SERIAL]", "inivation": "inivation:[NAME]"}
#: file extensions (any format of :mod:`arena.formats` that can be read); they take ``speed``
SOURCE_EXTENSIONS: dict[str, SourceOpener] = {ext: FileSource for ext in READ_EXTENSIONS}

# a scheme has two characters or more, so a Windows drive letter (C:\rec.raw) is a path
_SCHEME = re.compile(r"([A-Za-z][A-Za-z0-9+.-]+):")


def source_plugins() -> dict[str, EntryPoint]:
    """Source schemes of installed plug-ins (entry-point group ``arena.sources``), by scheme
    (lower case), built-in schemes left out (those win)."""
    found = {ep.name.lower(): ep for ep in entry_points(group=SOURCE_ENTRY_POINTS)}
    return {k: ep for k, ep in sorted(found.items()) if k not in SOURCE_SCHEMES}


def _open_plugin(ep: EntryPoint, url: str, opts: dict) -> EventSource:
    dist = getattr(ep, "dist", None)
    origin = f"{ep.value}" + (f" from {dist.name} {dist.version}" if dist is not None else "")
    try:
        opener = ep.load()
    except Exception as exc:  # noqa: BLE001 - a broken plug-in is an error to report, whatever it raises
        raise SourceError(f"event source plug-in {ep.name!r} ({origin}) cannot be loaded: "
                          f"{type(exc).__name__}: {exc}; reinstall the package that provides it") from None
    try:
        src = opener(url, **opts)
    except SourceError:
        raise
    except Exception as exc:  # noqa: BLE001 - same: one clear line, not a plug-in's traceback
        raise SourceError(f"event source plug-in {ep.name!r} ({origin}) cannot open {url!r}: "
                          f"{type(exc).__name__}: {exc}") from None
    if not isinstance(src, EventSource):
        raise SourceError(f"event source plug-in {ep.name!r} ({origin}) returned a {type(src).__name__}, "
                          "not a camera_edge.sources.EventSource")
    return src


def _unknown(s: str) -> SourceError:
    plugins = source_plugins()
    installed = (f"installed: {', '.join(f'{k}:' for k in plugins)}" if plugins else
                 f"none installed; a camera package adds one in the entry-point group {SOURCE_ENTRY_POINTS!r}")
    return SourceError(f"unknown event source {s!r}: use {', '.join(SCHEME_USAGE.values())}, a file "
                       f"({', '.join(SOURCE_EXTENSIONS)}) or a source plug-in's scheme ({installed})")


def open_source(url_or_path: str, speed: float = 1.0, **opts) -> EventSource:
    """Open an event source by URL scheme (``tcp://``, ``prophesee:``, ``inivation:``, or a
    plug-in's from the ``arena.sources`` entry points) or by file extension (.raw, .dat,
    .aedat4, .csv, .npy, .npz). ``speed`` applies to files; ``opts`` go to the backend (e.g.
    ``width``/``height`` for tcp://, ``loop`` for files).
    Raises :class:`SourceError` with a clear message if it cannot."""
    s = str(url_or_path)
    m = _SCHEME.match(s)
    scheme = m.group(1).lower() if m else None
    if scheme in SOURCE_SCHEMES:
        return SOURCE_SCHEMES[scheme](s, **opts)
    ext = Path(s).suffix.lower()
    if scheme is not None:
        ep = source_plugins().get(scheme)
        if ep is not None:
            return _open_plugin(ep, s, opts)
    if ext in SOURCE_EXTENSIONS:
        if not Path(s).is_file():
            raise SourceError(f"no such file: {s!r}")
        return SOURCE_EXTENSIONS[ext](s, speed=speed, **opts)
    raise _unknown(s)

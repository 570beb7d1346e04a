"""``.npy`` (a structured array with fields x, y, p, t) and ``.npz`` (arrays ``x``, ``y``, ``p``
(1 = ON, 0 = OFF), ``t`` (µs), or one structured array ``events`` as the simulator saves them;
optional scalars ``width``, ``height``)."""

from __future__ import annotations

import lzma
import warnings
import zipfile
import zlib
from pathlib import Path
from tokenize import TokenError

import numpy as np

from arena.events import EVENT_DTYPE
from arena.formats.base import (
    DEFAULT_CHUNK_EVENTS,
    EventReader,
    EventWriter,
    FormatError,
    SkippedData,
    check_events,
    check_size,
)

#: deflate expands at most 1032 to one: a zip member declaring more is a bomb or corrupt
_MAX_ZIP_RATIO = 1100
#: what numpy and zipfile raise on a damaged file besides ValueError/OSError (a header numpy
#: tokenizes, a broken zip or deflate stream, a dtype it cannot build)
_NUMPY_ERRORS = (OSError, ValueError, EOFError, TypeError, SyntaxError, TokenError, zipfile.BadZipFile,
                 zlib.error, lzma.LZMAError, KeyError, OverflowError, NotImplementedError, RuntimeError)


def _npy_header(fp, available: int, where: str) -> tuple[tuple, np.dtype, bool, int]:
    """Shape, dtype, Fortran-order flag of the ``.npy`` stream at ``fp`` (left at the array's
    data) and the bytes after the array's data, refusing (:class:`FormatError`) an array larger
    than the ``available`` bytes that hold it, before anything is allocated, and arrays that
    cannot be events (or any array: a negative dimension)."""
    fmt = np.lib.format
    version = fmt.read_magic(fp)
    if version == (1, 0):
        shape, fortran, dtype = fmt.read_array_header_1_0(fp)
    elif version == (2, 0):
        shape, fortran, dtype = fmt.read_array_header_2_0(fp)
    else:  # 3.0: only for field names beyond latin-1, never an event array's x, y, p, t
        raise FormatError(f"{where}: .npy format version {version[0]}.{version[1]} is not supported (1.0, 2.0)")
    if any(int(d) < 0 for d in shape):  # numpy's header parser lets them through; np.load refuses them
        raise FormatError(f"{where}: .npy header declares shape {shape}, with a negative dimension: a "
                          "damaged header")
    count = 1
    for d in shape:
        count *= int(d)
    need = count * dtype.itemsize
    if need > available - fp.tell():
        raise FormatError(f"{where}: array of shape {shape} ({need} bytes) is larger than the "
                          f"{max(0, available - fp.tell())} bytes that hold it: truncated or corrupt")
    if dtype.hasobject:
        raise FormatError(f"{where}: array of Python objects ({dtype}) is not an event array")
    if fortran and sum(int(d) > 1 for d in shape) > 1:
        raise FormatError(f"{where}: a Fortran-order array of shape {shape} is not an event array")
    return shape, dtype, bool(fortran), available - fp.tell() - need


class _Member:
    """One ``.npy`` array of a file or an npz, read in chunks of whole elements (in file order,
    which is ``reshape(-1)``'s order: C order, or Fortran order of at most one dimension > 1)."""

    def __init__(self, opener, available: int, where: str) -> None:
        self._opener, self._where = opener, where
        with opener() as f:
            self.shape, self.dtype, _, self.trailing = _npy_header(f, available, where)
            self._offset = f.tell()
        self.size = 1
        for d in self.shape:
            self.size *= int(d)
        if self.dtype.itemsize == 0 and self.size:
            raise FormatError(f"{where}: array of {self.dtype}, elements of 0 bytes")

    def blocks(self, n: int):
        """Arrays of up to ``n`` elements, the whole array in order; decompressed as read."""
        with self._opener() as f:
            f.read(self._offset)                 # the header, read again (a zip member streams)
            left = self.size
            while left:
                k = min(n, left)
                want = k * self.dtype.itemsize
                buf = f.read(want)
                if len(buf) != want:
                    raise FormatError(f"{self._where}: array data is truncated ({len(buf)} of {want} bytes)")
                left -= k
                yield np.frombuffer(buf, self.dtype)

    def whole(self) -> np.ndarray:
        return np.concatenate(list(self.blocks(max(1, self.size)))) if self.size else np.empty(0, self.dtype)


def _member(zf: zipfile.ZipFile, name: str, where: str) -> _Member:
    """Array ``name`` of an npz, its declared sizes checked before anything is decompressed."""
    info = zf.getinfo(name + ".npy")
    if info.file_size > _MAX_ZIP_RATIO * info.compress_size + 4096:
        raise FormatError(f"{where}: member {name} declares {info.file_size} bytes from {info.compress_size} "
                          "compressed: a decompression bomb or corrupt")
    return _Member(lambda: zf.open(info), info.file_size, f"{where}: {name}")


def _scalar_size(zf: zipfile.ZipFile, name: str, where: str) -> int | None:
    if name + ".npy" not in zf.namelist():
        return None
    m = _member(zf, name, where)
    if m.size != 1 or m.dtype.kind not in "iu":
        raise FormatError(f"{where}: {name} must be one integer, got {m.dtype} of shape {m.shape}")
    if m.trailing:
        raise FormatError(f"{where}: {name} has {m.trailing} bytes after its one value: a damaged member")
    return int(m.whole().reshape(-1)[0])


#: what ``arena sim``'s full recordings hold beside their events (simulator.recording.save_recording):
#: known, so not reported as members it does not read
_SIMULATOR_EXTRAS = ("is_signal", "truth", "robot_names", "calibration", "homography")

#: Most bytes an npz may decompress to in all, per byte of the file (plus :data:`_ARCHIVE_SLACK`):
#: real event columns deflate 2-10 to one (a constant polarity column 1000 to one, but it is 1 of
#: the 13 bytes of an event), while a bomb of constant columns reaches deflate's 1032
_MAX_ARCHIVE_RATIO = 100
_ARCHIVE_SLACK = 16 << 20


class NumpyReader(EventReader):
    """Reader of ``.npy``/``.npz`` events, streamed: each chunk is read (and decompressed) from the
    file as it is yielded, so memory stays one chunk's whatever the file expands to. Sizes in the
    file are checked before reading (no array larger than the file, no npz member expanding more
    than deflate can, no npz expanding over :data:`_MAX_ARCHIVE_RATIO` times the file in all),
    values are range-checked (``invalid`` counts events dropped). With no sensor size given or
    in the file, a first pass finds the largest x and y."""

    def __init__(self, path: str | Path, chunk_events: int = DEFAULT_CHUNK_EVENTS,
                 width: int | None = None, height: int | None = None) -> None:
        super().__init__()
        path = Path(path)
        self.path = str(path)
        self._chunk = max(1, int(chunk_events))
        self._zf = None
        try:
            try:
                self._open(path)
                for m in self._members:
                    if m.trailing:      # numpy writes nothing after the data: a damaged shape
                        self._skip(m.trailing, "bytes", f"{m.trailing} bytes after the {m.size} elements of "
                                   f"shape {m.shape} that the .npy header declares are not read (a damaged "
                                   "header, or data appended)")
                width = width or self._file_w
                height = height or self._file_h
                if not (width and height):
                    mx = my = -1
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore", SkippedData)
                        for ev in self._events():
                            if ev.size:
                                mx, my = max(mx, int(ev["x"].max())), max(my, int(ev["y"].max()))
                    self.invalid = 0
                    width, height = width or mx + 1 or 1, height or my + 1 or 1
            except FormatError:
                raise
            except MemoryError:
                raise FormatError(f"{path}: numpy event file does not fit in memory") from None
            except _NUMPY_ERRORS as exc:
                raise FormatError(f"{path}: not a readable numpy event file ({exc.__class__.__name__}: {exc})") from None
            self.width, self.height = check_size(width, height, self.path)
        except BaseException:
            self.close()
            raise

    def _open(self, path: Path) -> None:
        self._file_w = self._file_h = None
        if path.suffix.lower() != ".npz":
            self._members = [_Member(lambda: open(path, "rb"), path.stat().st_size, self.path)]
            self._check_structured(self._members[0])
            return
        self._zf = zf = zipfile.ZipFile(path)
        total = sum(i.file_size for i in zf.infolist())
        if total > _MAX_ARCHIVE_RATIO * path.stat().st_size + _ARCHIVE_SLACK:
            raise FormatError(f"{path}: npz declares {total} bytes in all from a {path.stat().st_size}-byte file "
                              f"(over {_MAX_ARCHIVE_RATIO} to one): a decompression bomb or corrupt")
        listed = zf.namelist()
        twice = sorted({n for n in listed if listed.count(n) > 1}) if len(set(listed)) != len(listed) else []
        if twice:   # zipfile reads the last of them: which one the writer meant is unknown
            raise FormatError(f"{path}: npz holds more than one member named {', '.join(twice)}: corrupt")
        names = [n[:-4] for n in listed if n.endswith(".npy")]
        structured = "events" in names and "x" not in names
        used = ({"events", "width", "height", *_SIMULATOR_EXTRAS} if structured
                else {"x", "y", "p", "t", "width", "height"})
        other = [n for n in listed if not (n.endswith(".npy") and n[:-4] in used)]
        if other:   # a damaged member name (width.npy -> wiath.npy) would otherwise go unseen
            self._skip(len(other), "archive members", f"npz members {other[:5]}{' ...' if len(other) > 5 else ''} "
                       "are not event arrays (x, y, p, t, width, height, or events): not read")
        if structured:  # a structured array (simulator)
            self._members = [_member(zf, "events", self.path)]
            self._check_structured(self._members[0])
        else:
            missing = [k for k in "xypt" if k not in names]
            if missing:
                raise FormatError(f"{path}: npz lacks array(s) {missing} (or a structured "
                                  f"'events' array); has {names}")
            self._members = [_member(zf, k, self.path) for k in "xypt"]
            for k, m in zip("xypt", self._members):
                if m.dtype.kind not in "biuf":
                    raise FormatError(f"{self.path}: column {k} holds {m.dtype} values, expected integers")
                if len(m.shape) != 1:
                    raise FormatError(f"{self.path}: column {k} has shape {m.shape}, expected one dimension")
            sizes = [m.size for m in self._members]
            if len(set(sizes)) != 1:
                raise FormatError(f"{self.path}: columns x, y, p, t have different lengths "
                                  f"({', '.join(map(str, sizes))})")
        self._file_w = _scalar_size(zf, "width", self.path)
        self._file_h = _scalar_size(zf, "height", self.path)

    def _check_structured(self, m: _Member) -> None:
        names = m.dtype.names or ()
        missing = [f for f in "xypt" if f not in names]
        if missing:
            raise FormatError(f"{self.path}: event array lacks field(s) {missing}; has {list(names)} "
                              "(a structured array with fields x, y, p, t)")

    def _events(self):
        """Chunks of range-checked events (not yet checked against the sensor)."""
        if len(self._members) == 1:
            for arr in self._members[0].blocks(self._chunk):
                p = arr["p"]
                if p.dtype.kind == "b":     # numpy reads any nonzero byte as True: a 7 is damage
                    p = p.view(np.uint8)
                yield self._columns(arr["x"], arr["y"], p, arr["t"])
        else:
            for x, y, p, t in zip(*(m.blocks(self._chunk) for m in self._members)):
                yield self._columns(x, y, p, t)

    def chunks(self):
        try:
            for ev in self._events():
                yield self._valid(ev)
        except FormatError:
            raise
        except MemoryError:
            raise FormatError(f"{self.path}: numpy event file does not fit in memory") from None
        except _NUMPY_ERRORS as exc:
            raise FormatError(f"{self.path}: not a readable numpy event file "
                              f"({exc.__class__.__name__}: {exc})") from None

    def close(self) -> None:
        if self._zf is not None:
            self._zf.close()
            self._zf = None


class NumpyWriter(EventWriter):
    """Writer of ``.npz`` (compressed, arrays x, y, p, t, width, height) or ``.npy`` (structured)."""

    def __init__(self, path: str | Path, width: int, height: int) -> None:
        self._path, self._w, self._h = Path(path), width, height
        self._parts: list[np.ndarray] = []

    def write(self, events: np.ndarray) -> None:
        self._parts.append(check_events(events).copy())

    def close(self) -> None:
        ev = np.concatenate(self._parts) if self._parts else np.empty(0, EVENT_DTYPE)
        if self._path.suffix.lower() == ".npy":
            np.save(self._path, ev)
        else:
            np.savez_compressed(self._path, x=ev["x"], y=ev["y"], p=ev["p"], t=ev["t"],
                                width=self._w, height=self._h)

"""``.npy`` (a structured array with fields x, y, p, t) and ``.npz`` (arrays ``x``, ``y``, ``p``
(1 = ON, 0 = OFF), ``t`` (µs), or one structured array ``events`` as the simulator saves them;
optional scalars ``width``, ``height``)."""

from __future__ import annotations

import lzma
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
    check_events,
    check_size,
)

#: deflate expands at most 1032 to one: a zip member declaring more is a bomb or corrupt
_MAX_ZIP_RATIO = 1100
#: what numpy and zipfile raise on a damaged file besides ValueError/OSError (a header numpy
#: tokenizes, a broken zip or deflate stream, a dtype it cannot build)
_NUMPY_ERRORS = (OSError, ValueError, EOFError, TypeError, SyntaxError, TokenError, zipfile.BadZipFile,
                 zlib.error, lzma.LZMAError, KeyError, OverflowError, NotImplementedError, RuntimeError)


def _npy_header(fp, available: int, where: str) -> tuple[tuple, np.dtype]:
    """Shape and dtype of the ``.npy`` stream at ``fp``, refusing (:class:`FormatError`) an array
    larger than the ``available`` bytes that hold it, before numpy allocates it."""
    fmt = np.lib.format
    version = fmt.read_magic(fp)
    if version == (1, 0):
        shape, _, dtype = fmt.read_array_header_1_0(fp)
    elif version == (2, 0):
        shape, _, dtype = fmt.read_array_header_2_0(fp)
    else:  # 3.0: only for field names beyond latin-1, never an event array's x, y, p, t
        raise FormatError(f"{where}: .npy format version {version[0]}.{version[1]} is not supported (1.0, 2.0)")
    count = 1
    for d in shape:
        count *= int(d)
    need = count * dtype.itemsize
    if need > available - fp.tell():
        raise FormatError(f"{where}: array of shape {shape} ({need} bytes) is larger than the "
                          f"{max(0, available - fp.tell())} bytes that hold it: truncated or corrupt")
    return shape, dtype


def _load_npy(path: Path) -> np.ndarray:
    with open(path, "rb") as f:
        _npy_header(f, path.stat().st_size, str(path))
        f.seek(0)
        return np.lib.format.read_array(f, allow_pickle=False)


def _load_member(zf: zipfile.ZipFile, name: str, where: str) -> np.ndarray:
    """Array ``name`` of an npz, its declared sizes checked before anything is decompressed."""
    info = zf.getinfo(name + ".npy")
    if info.file_size > _MAX_ZIP_RATIO * info.compress_size + 4096:
        raise FormatError(f"{where}: member {name} declares {info.file_size} bytes from {info.compress_size} "
                          "compressed: a decompression bomb or corrupt")
    with zf.open(info) as f:
        _npy_header(f, info.file_size, f"{where}: {name}")
    with zf.open(info) as f:
        return np.lib.format.read_array(f, allow_pickle=False)


def _scalar_size(zf: zipfile.ZipFile, name: str, where: str) -> int | None:
    if name + ".npy" not in zf.namelist():
        return None
    a = _load_member(zf, name, where)
    if a.shape not in ((), (1,)) or a.dtype.kind not in "iu":
        raise FormatError(f"{where}: {name} must be one integer, got {a.dtype} of shape {a.shape}")
    return int(a.reshape(-1)[0])


class NumpyReader(EventReader):
    """Reader of ``.npy``/``.npz`` events; the file is loaded whole, then yielded in chunks.
    Sizes in the file are checked before loading (no array larger than the file), values are
    range-checked (``invalid`` counts events dropped)."""

    def __init__(self, path: str | Path, chunk_events: int = DEFAULT_CHUNK_EVENTS,
                 width: int | None = None, height: int | None = None) -> None:
        super().__init__()
        path = Path(path)
        self.path = str(path)
        try:
            if path.suffix.lower() == ".npz":
                with zipfile.ZipFile(path) as zf:
                    names = [n[:-4] for n in zf.namelist() if n.endswith(".npy")]
                    if "events" in names and "x" not in names:  # a structured array (simulator)
                        self._ev = self._structured(_load_member(zf, "events", self.path))
                    else:
                        missing = [k for k in "xypt" if k not in names]
                        if missing:
                            raise FormatError(f"{path}: npz lacks array(s) {missing} (or a structured "
                                              f"'events' array); has {names}")
                        self._ev = self._columns(*(_load_member(zf, k, self.path) for k in "xypt"))
                    width = width or _scalar_size(zf, "width", self.path)
                    height = height or _scalar_size(zf, "height", self.path)
            else:
                self._ev = self._structured(_load_npy(path))
        except FormatError:
            raise
        except _NUMPY_ERRORS as exc:
            raise FormatError(f"{path}: not a readable numpy event file ({exc.__class__.__name__}: {exc})") from None
        self.width, self.height = check_size(
            width or (int(self._ev["x"].max()) + 1 if self._ev.size else 1),
            height or (int(self._ev["y"].max()) + 1 if self._ev.size else 1), self.path)
        self._chunk = chunk_events

    def _structured(self, arr: np.ndarray) -> np.ndarray:
        names = arr.dtype.names or ()
        missing = [f for f in "xypt" if f not in names]
        if missing:
            raise FormatError(f"{self.path}: event array lacks field(s) {missing}; has {list(names)} "
                              "(a structured array with fields x, y, p, t)")
        return self._columns(arr["x"].reshape(-1), arr["y"].reshape(-1), arr["p"].reshape(-1),
                             arr["t"].reshape(-1))

    def chunks(self):
        for i in range(0, self._ev.size, self._chunk):
            yield self._valid(self._ev[i:i + self._chunk])


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

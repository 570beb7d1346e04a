"""``.npy`` (a structured array with fields x, y, p, t) and ``.npz`` (arrays ``x``, ``y``, ``p``
(1 = ON, 0 = OFF), ``t`` (µs), or one structured array ``events`` as the simulator saves them;
optional scalars ``width``, ``height``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from arena.events import EVENT_DTYPE, make_events
from arena.formats.base import DEFAULT_CHUNK_EVENTS, EventReader, EventWriter, FormatError, check_events


class NumpyReader(EventReader):
    """Reader of ``.npy``/``.npz`` events; the file is loaded whole, then yielded in chunks."""

    def __init__(self, path: str | Path, chunk_events: int = DEFAULT_CHUNK_EVENTS,
                 width: int | None = None, height: int | None = None) -> None:
        super().__init__()
        path = Path(path)
        try:
            if path.suffix.lower() == ".npz":
                with np.load(path, allow_pickle=False) as z:
                    if "events" in z.files and "x" not in z.files:  # a structured array (simulator)
                        self._ev = check_events(z["events"])
                    else:
                        missing = [k for k in "xypt" if k not in z.files]
                        if missing:
                            raise FormatError(f"{path}: npz lacks array(s) {missing} (or a structured "
                                              f"'events' array); has {z.files}")
                        self._ev = make_events(z["x"], z["y"], z["p"] > 0, z["t"])
                    width = width or (int(z["width"]) if "width" in z.files else None)
                    height = height or (int(z["height"]) if "height" in z.files else None)
            else:
                arr = np.load(path, allow_pickle=False)
                self._ev = check_events(arr)
        except (OSError, ValueError, EOFError) as exc:
            if isinstance(exc, FormatError):
                raise
            raise FormatError(f"{path}: not a readable numpy event file ({exc})") from None
        self.width = int(width or (int(self._ev["x"].max()) + 1 if self._ev.size else 1))
        self.height = int(height or (int(self._ev["y"].max()) + 1 if self._ev.size else 1))
        self._chunk = chunk_events

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

"""Common reader/writer interfaces and errors of the event file formats."""

from __future__ import annotations

import numpy as np

from arena.events import EVENT_DTYPE

#: Default number of events per chunk yielded by the streaming readers.
DEFAULT_CHUNK_EVENTS = 1 << 18


class FormatError(ValueError):
    """An event file is unknown, corrupt or truncated; the message says which and where."""


class EventReader:
    """A streaming reader of one event file.

    Iterating yields event chunks (:data:`arena.events.EVENT_DTYPE`, sensor frame, µs)
    in file order. ``width`` and ``height`` (px) are known after opening.
    ``invalid`` counts events dropped because they lay outside the sensor.
    """

    width: int
    height: int

    def __init__(self) -> None:
        self.invalid = 0

    def chunks(self):  # pragma: no cover - abstract
        raise NotImplementedError

    def __iter__(self):
        return self.chunks()

    def read_all(self) -> np.ndarray:
        """Read the remaining events into one array."""
        parts = list(self.chunks())
        return np.concatenate(parts) if parts else np.empty(0, EVENT_DTYPE)

    def _valid(self, ev: np.ndarray) -> np.ndarray:
        bad = (ev["x"] >= self.width) | (ev["y"] >= self.height)
        nbad = int(np.count_nonzero(bad))
        if nbad:
            self.invalid += nbad
            ev = ev[~bad]
        return ev

    def close(self) -> None:
        """Release the file."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class EventWriter:
    """A streaming writer of one event file: ``write(events)`` any number of times, then ``close()``."""

    def write(self, events: np.ndarray) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def close(self) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def check_events(events: np.ndarray) -> np.ndarray:
    """Return ``events`` as :data:`EVENT_DTYPE` or raise ``FormatError``."""
    if not isinstance(events, np.ndarray) or events.dtype.names is None:
        raise FormatError("events must be a structured numpy array with fields x, y, p, t")
    from arena.events import as_events

    try:
        return as_events(events)
    except ValueError as exc:
        raise FormatError(str(exc)) from None

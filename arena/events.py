"""The one event record used everywhere in the project.

An event is ``(x, y, p, t)``: pixel column ``x`` and row ``y`` (sensor frame, px),
polarity ``p`` (1 = ON / brightness up, 0 = OFF / brightness down) and timestamp
``t`` in microseconds of the sensor clock.
"""

from __future__ import annotations

import numpy as np

#: Structured dtype of an event array. Field order follows the (x, y, p, t) convention.
EVENT_DTYPE = np.dtype([("x", "<u2"), ("y", "<u2"), ("p", "u1"), ("t", "<i8")])


def empty_events(n: int = 0) -> np.ndarray:
    """Return a zeroed event array of length ``n``."""
    return np.zeros(n, dtype=EVENT_DTYPE)


def make_events(x, y, p, t) -> np.ndarray:
    """Build an event array from four equal-length sequences (px, px, 0/1, µs)."""
    x = np.asarray(x)
    n = x.shape[0]
    ev = np.empty(n, dtype=EVENT_DTYPE)
    ev["x"] = x
    ev["y"] = y
    ev["p"] = p
    ev["t"] = t
    return ev


def as_events(arr: np.ndarray) -> np.ndarray:
    """Convert any structured array with fields x, y, p, t to :data:`EVENT_DTYPE`."""
    if arr.dtype == EVENT_DTYPE:
        return arr
    names = arr.dtype.names or ()
    missing = [f for f in ("x", "y", "p", "t") if f not in names]
    if missing:
        raise ValueError(f"event array lacks field(s) {missing}; has {list(names)}")
    return make_events(arr["x"], arr["y"], arr["p"], arr["t"])

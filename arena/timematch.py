"""Live errors that compare like with like: a truth pose with the track where it was at the
pose's own stamp, on one clock (not the latest of each as they arrive, which measures the lag).

Pure: no I/O, no clock. Used by the viewer (``viewer.state``) and the demo's live scorer
(``demo.scorer``); the offline scorer (``groundtruth.metrics``) pairs the same poses.
"""

from __future__ import annotations

import math
from bisect import bisect_left, bisect_right
from dataclasses import dataclass


class PoseHistory:
    """The recent positions of one object on one clock: ``(t_us, x, y)`` sorted by time.

    Bounded both ways: samples older than ``span_us`` before the newest one are dropped, and at
    most ``max_len`` are kept (the oldest go first). A sample more than ``span_us`` older than
    the newest means the clock went back (a restarted source, a looping replay): the history
    restarts from it. :meth:`at` interpolates linearly, inside the history only, and not across
    a hole longer than ``max_gap_us`` (the offline scorer's default, see
    ``groundtruth.metrics.align``).
    """

    def __init__(self, span_us: int = 5_000_000, max_len: int = 4096, max_gap_us: int = 500_000):
        if span_us <= 0 or max_len < 2 or max_gap_us <= 0:
            raise ValueError(f"PoseHistory needs span_us > 0, max_len >= 2, max_gap_us > 0, "
                             f"got {span_us}, {max_len}, {max_gap_us}")
        self.span_us, self.max_len, self.max_gap_us = int(span_us), int(max_len), int(max_gap_us)
        self.t: list[int] = []
        self.x: list[float] = []
        self.y: list[float] = []

    def __len__(self) -> int:
        return len(self.t)

    def clear(self) -> None:
        self.t.clear(), self.x.clear(), self.y.clear()

    def add(self, t_us: int, x: float, y: float) -> None:
        """Add a sample (out of order is fine within the span; the same time replaces it)."""
        t_us, x, y = int(t_us), float(x), float(y)
        if not (math.isfinite(x) and math.isfinite(y)):
            return
        t = self.t
        if t and t_us < t[-1] - self.span_us:
            self.clear()  # the clock went back
        if not t or t_us > t[-1]:
            t.append(t_us), self.x.append(x), self.y.append(y)
        else:
            k = bisect_left(t, t_us)
            if t[k] == t_us:
                self.x[k], self.y[k] = x, y
            else:
                t.insert(k, t_us), self.x.insert(k, x), self.y.insert(k, y)
        cut = max(bisect_left(t, t[-1] - self.span_us), len(t) - self.max_len)
        if cut > 0:
            del t[:cut], self.x[:cut], self.y[:cut]

    def span(self) -> tuple[int, int] | None:
        """(oldest, newest) time held, µs; None when empty."""
        return (self.t[0], self.t[-1]) if self.t else None

    def at(self, t_us: int) -> tuple[float, float] | None:
        """Position at ``t_us`` interpolated between the samples around it; None outside the
        history or inside a hole longer than ``max_gap_us``."""
        t = self.t
        if not t or t_us < t[0] or t_us > t[-1]:
            return None
        k = bisect_left(t, t_us)
        if t[k] == t_us:
            return self.x[k], self.y[k]
        t0, t1 = t[k - 1], t[k]
        if t1 - t0 > self.max_gap_us:
            return None
        w = (t_us - t0) / (t1 - t0)
        return self.x[k - 1] + w * (self.x[k] - self.x[k - 1]), self.y[k - 1] + w * (self.y[k] - self.y[k - 1])


#: what a live error figure says when the two poses have no common time on one clock
NO_OVERLAP = "n/a (no overlap)"


@dataclass(frozen=True)
class TimedError:
    """A truth pose and the track interpolated at its stamp: the distance between them (m), the
    truth pose's stamp (µs, on ``clock``: ``"sensor"`` the track's ``stamp_us``, ``"host"`` its
    ``host_ns`` / 1000) and the track's newest time on that clock minus that stamp (µs, >= 0)."""

    err_m: float
    t_us: int
    clock: str
    behind_us: int


def timed_error(track_sensor: PoseHistory, track_host: PoseHistory | None, truth: PoseHistory,
                clock: str = "auto") -> TimedError | None:
    """Distance between the newest truth pose whose stamp lies in the track's history and the
    track's position interpolated at that stamp, on one clock; None when there is no such pose
    (the clocks differ, or the truth and the track have no common time span yet).

    ``truth`` holds the poses' own stamps. ``clock``: which of the track's clocks they are on:
    ``"sensor"`` (the simulator's truth, a webcam stamped with the simulator's clock), ``"host"``
    (a webcam or motion capture stamped by a host's clock: compared with the track's ``host_ns``),
    or ``"auto"``: the sensor clock if the stamps fall inside the track's sensor-time history,
    else the host clock if they fall inside its host-time history. Pairs are the ones the offline
    scorer would score, up to which of the two is interpolated (it interpolates the truth at the
    track's times).
    """
    if clock not in ("auto", "sensor", "host"):
        raise ValueError(f"clock must be 'auto', 'sensor' or 'host', got {clock!r}")
    for name, hist in (("sensor", track_sensor), ("host", track_host)):
        if clock not in ("auto", name) or hist is None or not len(hist) or not len(truth):
            continue
        lo, hi = hist.span()
        k = bisect_right(truth.t, hi) - 1
        while k >= 0 and truth.t[k] >= lo:
            xy = hist.at(truth.t[k])
            if xy is not None:
                return TimedError(math.hypot(xy[0] - truth.x[k], xy[1] - truth.y[k]), truth.t[k], name,
                                  hi - truth.t[k])
            k -= 1
    return None

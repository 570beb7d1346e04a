"""Sensor clock -> host clock: the offset that turns a window's sensor time into host capture time.

An event camera stamps events with its own µs counter, which starts at an arbitrary value and
drifts from the host's clock. Tracks carry that sensor time; a lab that scores them against a
motion-capture system (whose poses are stamped with a host's wall clock) needs the host time at
which the light hit the sensor as well. The events reach the host after a delay that is never
negative and usually small (USB transfer, driver buffering), so the smallest
``host_ns - sensor_us * 1000`` seen over a recent stretch is the offset with the least delay in it:
the estimator keeps the minimum over a sliding window (10 s by default, so that the drift between
the two clocks, ~10-100 ppm, moves it by at most ~1 ms before older samples age out).

Pure: the caller passes both clocks' readings (:func:`time.time_ns` for the host).
"""

from __future__ import annotations

import collections

__all__ = ["SensorClock"]


class SensorClock:
    """Sliding-minimum estimate of ``host_ns - sensor_us * 1000``.

    ``observe(sensor_us, host_ns)`` after each read of the newest events (``sensor_us`` the newest
    event's time, ``host_ns`` when it was read); ``offset_ns`` is ``None`` until the first sample,
    then host capture time = ``sensor_us * 1000 + offset_ns``. ``window_s``: how far back the minimum
    looks. Samples whose sensor time goes back (a restarted camera) restart the estimate.
    """

    def __init__(self, window_s: float = 10.0, max_samples: int = 4096) -> None:
        if not window_s > 0:
            raise ValueError(f"window_s must be > 0, got {window_s}")
        self.window_ns = int(window_s * 1e9)
        # monotonic deque of (host_ns, offset_ns) with increasing offsets: the front is the minimum
        self._q: collections.deque[tuple[int, int]] = collections.deque()
        self._max = int(max_samples)
        self._last_sensor_us: int | None = None
        self.resets = 0

    @property
    def offset_ns(self) -> int | None:
        return self._q[0][1] if self._q else None

    def observe(self, sensor_us: int, host_ns: int) -> int:
        """Add one sample; return the current offset (ns)."""
        sensor_us, host_ns = int(sensor_us), int(host_ns)
        if self._last_sensor_us is not None and sensor_us < self._last_sensor_us:
            self._q.clear()  # the sensor's clock went back: a restarted camera or a looping file
            self.resets += 1
        self._last_sensor_us = sensor_us
        off = host_ns - sensor_us * 1000
        q = self._q
        while q and q[-1][1] >= off:
            q.pop()
        q.append((host_ns, off))
        while len(q) > 1 and (q[0][0] < host_ns - self.window_ns or len(q) > self._max):
            q.popleft()
        return q[0][1]

    def host_ns(self, sensor_us: int) -> int | None:
        """Host capture time (ns) of sensor time ``sensor_us`` (None before the first sample)."""
        off = self.offset_ns
        return None if off is None else int(sensor_us) * 1000 + off

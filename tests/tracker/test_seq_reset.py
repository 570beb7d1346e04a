"""A window whose ``seq`` jumps absurdly far (issue 20: by 2^40) is one sequence reset, not 2^40
windows missed; ordinary gaps are still counted as missed."""

from __future__ import annotations

import numpy as np

from tests.tracker.synth import line_pose, window
from tests.tracker.test_service_unit import make, win
from tracker.service import LiveTracker


class _Counts:
    def __init__(self):
        self.c = {}

    def count(self, key, n=1):
        self.c[key] = self.c.get(key, 0) + n

    def gauge(self, key, value):
        pass

    def error(self, msg):
        pass


def test_a_seq_jump_of_2_to_the_40_is_one_sequence_reset_not_missed_windows():
    ev = window(np.random.default_rng(6), [line_pose(200, 200, 100.0, 0.0)], 0, 200_000)
    svc = _Counts()
    live = LiveTracker(make(), "c0", svc=svc)
    for k in range(5):
        live.handle(win(ev, k).encode(), now_ns=5)
    live.handle(win(ev, 5, seq=4 + (1 << 40)).encode(), now_ns=5)       # hostile or corrupt sender
    for k in range(6, 9):                                                # then counting on from there
        live.handle(win(ev, k, seq=k - 1 + (1 << 40)).encode(), now_ns=5)
    live.handle(win(ev, 10, seq=10 + (1 << 40)).encode(), now_ns=5)      # 2 lost on the way
    assert svc.c.get("sequence_resets") == 1
    assert svc.c.get("windows_missed") == 2
    assert svc.c.get("windows_in") == 10

"""A window whose ``seq`` jumps absurdly far (issue 20: by 2^40) is one sequence reset, not 2^40
windows missed; ordinary gaps are still counted as missed."""

from __future__ import annotations

import numpy as np

from tests.tracker.synth import Counts, line_pose, window
from tests.tracker.test_service_unit import make, win
from tracker.service import LiveTracker


def test_a_seq_jump_of_2_to_the_40_is_one_sequence_reset_not_missed_windows():
    ev = window(np.random.default_rng(6), [line_pose(200, 200, 100.0, 0.0)], 0, 200_000)
    svc = Counts()
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


def test_a_window_with_late_events_first_is_processed_as_offline_not_skipped():
    """The edge's Slicer keeps a late event in the window open when it came, at the window's head
    when it came first: the live tracker processes that window (as arena track --input does) and
    counts the late events; an event at or after the window's end is still refused."""
    from arena.codec import encode
    from arena.messages import EventWindow

    ev = window(np.random.default_rng(7), [line_pose(200, 200, 100.0, 0.0)], 0, 200_000)
    svc = Counts()
    live = LiveTracker(make(), "c0", svc=svc)
    for k in range(5):
        live.handle(win(ev, k).encode(), now_ns=5)
    a, b = 50_000, 60_000
    sl = ev[(ev["t"] >= a) & (ev["t"] < b)]
    late = ev[(ev["t"] >= a - 3_000) & (ev["t"] < a - 2_000)]          # came late, first in the window
    assert late.size >= 1
    both = np.concatenate([late, sl])
    mk = lambda e, seq, a, b: EventWindow(camera="c0", seq=seq, t_start_us=a, t_end_us=b, width=640, height=480,
                                          count=e.size, codec="planes-zstd/1", data=encode(e), publish_ns=1)
    live.handle(mk(both, 5, a, b).encode(), now_ns=5)
    assert svc.c.get("windows_in") == 6 and svc.c.get("events_late") == late.size
    assert not svc.c.get("windows_bad")
    nxt = ev[(ev["t"] >= b) & (ev["t"] < b + 10_000)]
    beyond = ev[(ev["t"] >= b + 10_000) & (ev["t"] < b + 11_000)]
    assert beyond.size >= 1
    live.handle(mk(np.concatenate([nxt, beyond]), 6, b, b + 10_000).encode(), now_ns=5)
    assert svc.c.get("windows_bad") == 1 and svc.c.get("windows_in") == 6

"""The shared Slicer (arena/slicing.py): windows on multiples of slice_us of the sensor clock,
empty ones emitted, late events kept in the open window and counted, independent of chunking;
and the offline tracker's iter_slices, which is the same Slicer."""

from __future__ import annotations

import numpy as np
import pytest

from arena.events import make_events
from arena.slicing import Slicer
from tracker.pipeline import iter_slices


def _ev(ts, x=1, y=1):
    ts = np.asarray(ts)
    return make_events(np.full(ts.size, x), np.full(ts.size, y), np.zeros(ts.size), ts)


def _windows(slices):
    return [(s.t_start_us, s.t_end_us, s.events["t"].tolist()) for s in slices]


def _sequential(ts, slice_us):
    """Reference: one event at a time, in stream order; an event at or after the open window's
    end closes it (and the empty ones up to its own); an older one goes into the open window."""
    wins, start, cur, late = [], None, [], 0
    for t in ts:
        if start is None:
            start = t - t % slice_us
        while t >= start + slice_us:
            wins.append((start, start + slice_us, cur))
            start, cur = start + slice_us, []
        late += t < start
        cur.append(t)
    if start is not None:
        wins.append((start, start + slice_us, cur))
    return wins, late


def test_slices_are_contiguous_and_empty_ones_are_emitted():
    s = Slicer(10_000)
    out = s.push(_ev([12_000, 15_000, 51_000]))
    assert [(w.t_start_us, w.t_end_us, w.events.size) for w in out] == [
        (10_000, 20_000, 2), (20_000, 30_000, 0), (30_000, 40_000, 0), (40_000, 50_000, 0)]
    assert s.push(_ev([55_000])) == []
    closed = s.advance(70_000)  # sensor time advanced without events
    assert [(w.t_start_us, w.events.size) for w in closed] == [(50_000, 2), (60_000, 0)]
    assert [(w.t_start_us, w.events.size) for w in s.flush()] == [(70_000, 0)]


def test_the_issues_example_windows_end_on_multiples_of_the_slice_offline_too():
    # issue 21: events at 12 345..31 000 µs; the edge's windows end at 20 000/30 000/40 000,
    # the offline tracker's ended at 22 345/32 345
    ev = _ev(np.linspace(12_345, 31_000, 50).astype(np.int64))
    s = Slicer(10_000)
    edge = [(w.t_end_us, w.events["t"].tolist()) for w in s.push(ev) + s.flush()]
    offline = [(t_end, e["t"].tolist()) for t_end, e in iter_slices([ev[:20], ev[20:]], 10_000)]
    assert [t for t, _ in offline] == [20_000, 30_000, 40_000]
    assert offline == edge
    assert sum(len(e) for _, e in offline) == ev.size


def test_late_events_go_into_the_open_window_and_are_counted_offline_as_at_the_edge():
    chunks = [_ev([12_000, 25_000]), _ev([15_000, 26_000, 41_000]), _ev([5_000, 42_000])]
    s = Slicer(10_000)
    out = [w for c in chunks for w in s.push(c)] + s.flush()
    assert _windows(out) == [(10_000, 20_000, [12_000]), (20_000, 30_000, [25_000, 15_000, 26_000]),
                             (30_000, 40_000, []), (40_000, 50_000, [41_000, 5_000, 42_000])]
    assert s.late == 2
    off = Slicer(10_000)
    got = [(t, e["t"].tolist()) for t, e in iter_slices(chunks, 10_000, slicer=off)]
    assert got == [(w.t_end_us, w.events["t"].tolist()) for w in out]
    assert off.late == 2


def test_out_of_order_stream_is_cut_in_stream_order_whatever_the_chunks():
    rng = np.random.default_rng(1)
    t = np.sort(rng.integers(3_000, 400_000, 6_000))
    swap = rng.choice(t.size, 300, replace=False)   # jitter: some events arrive up to 25 ms late
    t[swap] = np.maximum(0, t[swap] - rng.integers(1, 25_000, swap.size))
    ref, n_late = _sequential(t.tolist(), 10_000)
    assert n_late > 50
    ev = _ev(t)
    for cuts in ([], [1], [5, 6, 777, 3_000], list(range(0, t.size, 97))):
        s = Slicer(10_000)
        got = []
        for a, b in zip([0, *cuts], [*cuts, t.size]):
            got += s.push(ev[a:b])
        got += s.flush()
        assert _windows(got) == ref, f"cuts {cuts[:5]}"
        assert s.late == n_late
        assert all(w.events.size == 0 or int(w.events["t"].max()) < w.t_end_us for w in got)


def test_slicing_is_independent_of_chunk_boundaries():
    rng = np.random.default_rng(0)
    ev = _ev(np.sort(rng.integers(0, 1_000_000, 20_000)))
    whole = Slicer(10_000)
    ref = whole.push(ev) + whole.flush()
    for cuts in ([5], [3, 777, 778, 19_000], list(range(0, 20_000, 999))):
        s = Slicer(10_000)
        got = []
        for a, b in zip([0, *cuts], [*cuts, ev.size]):
            got += s.push(ev[a:b])
        got += s.flush()
        assert [(w.t_start_us, w.events.size) for w in got] == [(w.t_start_us, w.events.size) for w in ref]
    assert sum(w.events.size for w in ref) == ev.size and len(ref) == 100 and whole.late == 0


def test_a_long_silence_restarts_windows_instead_of_flooding():
    s = Slicer(10, max_gap_slices=5)
    out = s.push(_ev([0, 1_000_000]))
    assert len(out) == 1 and s.skipped_gaps == 1


def test_start_us_is_floored_to_a_multiple_and_fills_with_empty_windows():
    got = [(t, e.size) for t, e in iter_slices([_ev([23_000])], 10_000, start_us=4_000)]
    assert got == [(10_000, 0), (20_000, 0), (30_000, 1)]


def test_bad_slice_and_conflicting_arguments_are_clear_errors():
    with pytest.raises(ValueError, match="slice duration must be > 0"):
        Slicer(0)
    with pytest.raises(ValueError, match="slice duration must be > 0"):
        list(iter_slices([_ev([1])], 0))
    with pytest.raises(ValueError, match="either a Slicer of 5000 µs or start_us"):
        list(iter_slices([_ev([1])], 5_000, slicer=Slicer(10_000)))

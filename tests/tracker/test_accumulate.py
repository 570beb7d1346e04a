"""PixelWindow: the incremental per-pixel statistics equal those of the window's events."""

from __future__ import annotations

import numpy as np
import pytest

from tests.tracker.synth import line_pose, window
from tracker.accumulate import PixelWindow
from tracker.pipeline import iter_slices


def direct_stats(ev, t_ref, width):
    k = ev["y"].astype(np.int64) * width + ev["x"]
    t = (ev["t"] - t_ref) * 1e-6
    keys, inv = np.unique(k, return_inverse=True)
    return {int(kk): (c, o, s1, s2) for kk, c, o, s1, s2 in zip(
        keys, np.bincount(inv), np.bincount(inv, ev["p"]), np.bincount(inv, t), np.bincount(inv, t * t))}


@pytest.mark.parametrize("ta_us,slice_us", [(100_000, 10_000), (35_000, 10_000), (20_000, 7_000)])
def test_incremental_window_equals_direct(ta_us, slice_us):
    rng = np.random.default_rng(1)
    ev = window(rng, [line_pose(100, 100, 200.0, 50.0), line_pose(400, 300, -150.0, 0.0)], 0, 400_000)
    pw = PixelWindow(640, 480, ta_us)
    for t_end, sl in iter_slices([ev[:20_000], ev[20_000:]], slice_us, start_us=0):
        pw.push(sl, t_end)
        inside = ev[(ev["t"] >= t_end - ta_us) & (ev["t"] < t_end)]
        assert pw.n_events == inside.size
        u, v, c, o, s1, s2 = pw.pixels()
        ref = direct_stats(inside, pw.t_ref_us, 640)
        got = {int(vv) * 640 + int(uu): (cc, oo, a, b) for uu, vv, cc, oo, a, b in zip(u, v, c, o, s1, s2)}
        assert got.keys() == ref.keys()
        for key, (cc, oo, a, b) in got.items():
            rc, ro, ra, rb = ref[key]
            assert (cc, oo) == (rc, ro)
            assert a == pytest.approx(ra, abs=1e-9) and b == pytest.approx(rb, abs=1e-9)
    assert np.array_equal(np.sort(pw.events()["t"]), inside["t"])


def test_rebase_keeps_statistics_and_bad_slices_are_refused():
    rng = np.random.default_rng(2)
    pw = PixelWindow(640, 480, 100_000)
    base = 30_000_000   # beyond the 20 s re-base horizon from the first slice
    ev0 = window(rng, [line_pose(100, 100, 200.0, 0.0)], 0, 10_000)
    pw.push(ev0, 10_000)
    ev1 = window(rng, [line_pose(100, 100, 200.0, 0.0)], base, base + 10_000)
    pw.push(ev1, base + 10_000)
    assert pw.n_events == ev1.size and pw.t_ref_us == base + 10_000 - 100_000
    _, _, c, _, s1, _ = pw.pixels()
    assert c.sum() == ev1.size
    assert s1.sum() == pytest.approx(((ev1["t"] - pw.t_ref_us) * 1e-6).sum())
    bad = ev1.copy()
    bad["x"][0] = 700
    with pytest.raises(ValueError, match="outside"):
        pw.push(bad, base + 20_000)


def test_slot_reads_are_the_pixels_columns_in_slot_order():
    """The detector reads the selected pixels' statistics by slot (issue 22: one record per slot,
    gathered in one pass): the same values and dtypes as :meth:`PixelWindow.pixels`' columns."""
    rng = np.random.default_rng(3)
    ev = window(rng, [line_pose(100, 100, 200.0, 50.0), line_pose(400, 300, -150.0, 0.0)], 0, 150_000,
                noise_per_px_s=0.5)
    pw = PixelWindow(640, 480, 100_000)
    for t_end, sl in iter_slices([ev], 10_000, start_us=0):
        pw.push(sl, t_end)
    u, v, c, o, s1, s2 = pw.pixels()
    assert pw.n_active > 1000 and o.sum() > 0
    slots = rng.permutation(pw.n_active)
    cnt, st, st2 = pw.slot_stats(slots)
    on = pw.slot_on(slots)
    assert [a.dtype for a in (cnt, on, st, st2)] == [np.int64, np.int64, np.float64, np.float64]
    assert np.array_equal(cnt, c[slots]) and np.array_equal(on, o[slots])
    assert np.array_equal(st, s1[slots]) and np.array_equal(st2, s2[slots])
    assert np.array_equal(pw.slot_map[v * 640 + u], np.arange(pw.n_active))
    got = pw.slot_records(slots)
    assert [a.dtype for a in got] == [np.int64, np.int64, np.float64, np.float64]
    for a, ref in zip(got, (c, o, s1, s2)):
        assert np.array_equal(a, ref[slots])
    gu, gv = pw.coords(v[slots] * 640 + u[slots])
    assert np.array_equal(gu, u[slots]) and np.array_equal(gv, v[slots])
    with pytest.raises(IndexError):
        pw.slot_records(np.array([pw.n_active]))

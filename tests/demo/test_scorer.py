"""The live scorer's error figures: each truth pose against the track at that pose's stamp, not
the latest messages received (which differ by however late each arrived)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from arena.messages import GroundTruthPose, Track
from demo.scorer import LiveScorer, format_rows
from arena.formats.tables import TRACK_DTYPE, TRUTH_DTYPE
from groundtruth.metrics import evaluate

HOST0_NS = 1_700_000_000_000_000_000  # host wall clock (ns) at sensor time 0
T0_US = 1_000_000  # sensor clock of the first message
LAG_NS = 500_000_000  # 0.5 s arrival lag


def pose(robot: int, t_us: int) -> tuple[float, float]:
    """Robot 0 or 1 on a circle of 0.4 m at 0.3 m/s (sensor time µs -> arena m)."""
    cx, cy = (0.55, 0.9) if robot == 0 else (1.3, 0.9)
    a = 0.75 * t_us * 1e-6 + robot
    return cx + 0.4 * math.cos(a), cy + 0.4 * math.sin(a)


def scenario(seconds: float = 3.0, *, track_lag_ns: int = LAG_NS, truth_lag_ns: int = 0, webcam_clock: str = "sensor",
             host_ns: bool = True, offset_m: tuple[float, float] = (0.0, 0.0), noise_m: float = 0.0, seed: int = 1):
    """Arrivals ``(arrival host ns, kind, payload)`` in arrival order: 2 robots, tracks at 200 Hz
    (stamp_us, host_ns), the simulator's truth at 100 Hz and the webcam at 30 Hz (stamped on the
    sensor clock like ``--clock stream``, or on the host clock), each with its arrival lag; and
    the same tracks and webcam poses as the offline scorer's arrays."""
    rng = np.random.default_rng(seed)
    out, trk_rows, cam_rows = [], [], []
    end = T0_US + int(seconds * 1e6)
    for t in range(T0_US, end, 5_000):
        for r in (0, 1):
            x, y = pose(r, t)
            x, y = x + offset_m[0] + rng.normal(0, noise_m), y + offset_m[1] + rng.normal(0, noise_m)
            m = Track(track_id=r + 1, robot=f"zumo{r + 1}", camera="cam0", stamp_us=t, x=x, y=y, yaw=0.0,
                      host_ns=HOST0_NS + t * 1000 if host_ns else None)
            out.append((HOST0_NS + t * 1000 + track_lag_ns, "track", m.encode()))
            trk_rows.append((t, str(r + 1), f"zumo{r + 1}", x, y))
    for t in range(T0_US, end, 10_000):
        for r in (0, 1):
            x, y = pose(r, t)
            m = GroundTruthPose(robot=f"zumo{r + 1}", stamp_us=t, x=x, y=y, detector="sim")
            out.append((HOST0_NS + t * 1000 + truth_lag_ns, "truth", m.encode()))
    for t in range(T0_US, end, 33_333):
        for r in (0, 1):
            x, y = pose(r, t)
            x, y = x + rng.normal(0, noise_m / 2), y + rng.normal(0, noise_m / 2)
            stamp = t if webcam_clock == "sensor" else (HOST0_NS + t * 1000) // 1000
            m = GroundTruthPose(robot=f"zumo{r + 1}", stamp_us=stamp, x=x, y=y, detector="aruco")
            out.append((HOST0_NS + t * 1000 + truth_lag_ns, "webcam", m.encode()))
            cam_rows.append((t, f"zumo{r + 1}", x, y))
    out.sort(key=lambda e: e[0])
    return out, trk_rows, cam_rows


def feed(scorer: LiveScorer, arrivals, until_ns: int, start: int = 0) -> int:
    """Deliver the arrivals up to ``until_ns``; returns the index of the next one."""
    i = start
    while i < len(arrivals) and arrivals[i][0] <= until_ns:
        now, kind, payload = arrivals[i]
        if kind == "track":
            scorer.on_track(payload, now)
        else:
            scorer.on_pose(payload, now, exact=kind == "truth")
        i += 1
    return i


def live_rows(arrivals, times_s, **kw) -> list[list[dict]]:
    """The scorer's rows at each of ``times_s`` (seconds of sensor time after T0)."""
    sc = LiveScorer(**kw)
    i, out = 0, []
    for ts in times_s:
        now_ns = HOST0_NS + T0_US * 1000 + int(ts * 1e9)
        i = feed(sc, arrivals, now_ns, i)
        out.append(sc.rows(now_ns / 1e9))
    return out


def latest_vs_latest_cm(arrivals, now_ns: int, robot: str) -> tuple[float, float]:
    """What the old scorer printed: the latest track received vs the latest truth and webcam pose."""
    from arena.messages import decode

    last = {}
    for t, kind, payload in arrivals:
        if t > now_ns:
            break
        m = decode(payload)
        if getattr(m, "robot", None) == robot:
            last[kind] = m
    trk = last["track"]
    return tuple(math.hypot(trk.x - last[k].x, trk.y - last[k].y) * 100 for k in ("truth", "webcam"))


@pytest.mark.parametrize("lags", [(LAG_NS, 0), (0, LAG_NS)], ids=["tracks-late", "truth-late"])
def test_late_arrivals_with_correct_stamps_score_about_zero(lags):
    arrivals, _, _ = scenario(track_lag_ns=lags[0], truth_lag_ns=lags[1])
    times = [1.5, 2.0, 2.5, 3.0]
    # the scenario does what it should: the latest messages are ~15 cm apart (0.3 m/s x 0.5 s)
    for ts in times:
        naive = latest_vs_latest_cm(arrivals, HOST0_NS + T0_US * 1000 + int(ts * 1e9), "zumo1")
        assert all(13 < v < 17 for v in naive), naive
    for rows in live_rows(arrivals, times):
        assert [r["robot"] for r in rows] == ["zumo1", "zumo2"]
        assert [r["track"] for r in rows] == [1, 2]
        for r in rows:
            assert r["err_truth_cm"] == pytest.approx(0.0, abs=0.01), r
            assert r["err_gt_cm"] == pytest.approx(0.0, abs=0.01), r
            assert r["err_truth_clock"] == r["err_gt_clock"] == "sensor"
            # the compared stamp is ~0.5 s behind the newest track when the tracks are the late ones
            if lags[0]:
                assert 0 <= r["err_gt_behind_ms"] < 40
            else:
                assert 450 <= r["err_truth_behind_ms"] <= 510


def test_live_webcam_error_is_the_offline_report_figure():
    """Same tracks and webcam poses: the live column's mean is the offline mean error (noise only)."""
    off = (0.015, 0.010)
    arrivals, trk_rows, cam_rows = scenario(offset_m=off, noise_m=0.002)
    times = np.arange(0.5, 3.0, 0.1)
    live = [r["err_gt_cm"] for rows in live_rows(arrivals, times) for r in rows]
    assert all(v is not None for v in live)

    tracks = np.zeros(len(trk_rows), TRACK_DTYPE)
    for i, (t, tid, robot, x, y) in enumerate(trk_rows):
        tracks[i] = (t, tid, robot, x, y, np.nan, np.nan, np.nan, np.nan, np.nan, "confirmed", -1)
    cam = np.zeros(len(cam_rows), TRUTH_DTYPE)
    for i, (t, robot, x, y) in enumerate(cam_rows):
        cam[i] = (t, robot, x, y, np.nan, np.nan, np.nan)
    offline_cm = evaluate(tracks, cam, gate_m=0.10).mae_cm
    assert offline_cm == pytest.approx(math.hypot(*off) * 100, abs=0.1)
    assert np.mean(live) == pytest.approx(offline_cm, abs=0.1), (np.mean(live), offline_cm)


def test_webcam_on_the_host_clock_is_matched_by_host_ns_or_not_at_all():
    arrivals, _, _ = scenario(webcam_clock="host")
    rows = live_rows(arrivals, [2.0])[0]
    assert all(r["err_gt_cm"] == pytest.approx(0.0, abs=0.01) and r["err_gt_clock"] == "host" for r in rows), rows
    # told the webcam is on the sensor clock: no number
    rows = live_rows(arrivals, [2.0], gt_clock="sensor")[0]
    assert all(r["err_gt_cm"] is None and r["err_gt_note"] == "n/a (no overlap)" for r in rows), rows
    assert all(r["err_truth_cm"] == pytest.approx(0.0, abs=0.01) for r in rows)  # the exact truth still is
    # tracks without host_ns cannot be put on the host clock: no number either
    arrivals, _, _ = scenario(webcam_clock="host", host_ns=False)
    rows = live_rows(arrivals, [2.0])[0]
    assert all(r["err_gt_cm"] is None and r["err_gt_note"] == "n/a (no overlap)" for r in rows), rows
    text = format_rows(rows, {"n": 0})
    assert text.count("n/a (no overlap)") == 2 and "err webcam" in text


def test_truth_newer_than_every_track_is_no_overlap_not_a_number():
    """A robot's first truth poses before its track has caught up: nothing to compare yet."""
    sc = LiveScorer()
    now = HOST0_NS + 2 * 10**9
    sc.on_track(Track(track_id=1, robot="zumo1", stamp_us=1_000_000, x=0.5, y=0.5).encode(), now)
    sc.on_track(Track(track_id=1, robot="zumo1", stamp_us=1_010_000, x=0.51, y=0.5).encode(), now)
    sc.on_pose(GroundTruthPose(robot="zumo1", stamp_us=1_500_000, x=0.6, y=0.5).encode(), now, exact=True)
    (row,) = sc.rows(now / 1e9)
    assert row["track"] == 1  # paired by the latest poses (10 cm apart, inside the gate) ...
    assert row["err_truth_cm"] is None and row["err_truth_note"] == "n/a (no overlap)"  # ... but not scored
    assert "n/a (no overlap)" in format_rows([row], {"n": 0})
    sc.on_track(Track(track_id=1, robot="zumo1", stamp_us=1_450_000, x=0.555, y=0.5).encode(), now)
    (row,) = sc.rows(now / 1e9)
    assert row["err_truth_cm"] is None  # still before the truth pose's stamp
    sc.on_track(Track(track_id=1, robot="zumo1", stamp_us=1_600_000, x=0.61, y=0.5).encode(), now)
    (row,) = sc.rows(now / 1e9)
    # the track at 1.5 s: 0.555 + 0.055 * 50/150 = 0.57333 m, 2.67 cm from the truth
    assert row["err_truth_cm"] == pytest.approx((0.6 - (0.555 + 0.055 * 50 / 150)) * 100, abs=1e-6)
    assert row["err_truth_behind_ms"] == pytest.approx(100.0)

"""The viewer's state: error figures at one time stamp, one entry per track, stale entries dropped."""

from __future__ import annotations

import math

import pytest

from arena.messages import GroundTruthPose, Track
from arena.timematch import NO_OVERLAP, PoseHistory, timed_error
from viewer.state import ViewerState

T0_US = 1_000_000
HOST0_NS = 1_700_000_000_000_000_000


class Clock:
    """A monotonic clock the test moves by hand."""

    def __init__(self, t: float = 100.0):
        self.t = t

    def __call__(self) -> float:
        return self.t


def pose(t_us: int) -> tuple[float, float]:
    """A circle of 0.4 m at 0.3 m/s."""
    a = 0.75 * t_us * 1e-6
    return 0.9 + 0.4 * math.cos(a), 0.9 + 0.4 * math.sin(a)


def track(t_us: int, track_id: int = 1, robot: str | None = "zumo1", xy=None, host: bool = True) -> Track:
    x, y = xy or pose(t_us)
    return Track(track_id=track_id, robot=robot, camera="cam0", stamp_us=t_us, x=x, y=y,
                 host_ns=HOST0_NS + t_us * 1000 if host else None)


def test_tracks_half_a_second_late_are_compared_at_the_webcam_stamp():
    """Tracks at 200 Hz arriving 0.5 s after the webcam's 30 Hz poses of the same instants."""
    st = ViewerState()
    arrivals = [(t + 500_000, "track", track(t)) for t in range(T0_US, T0_US + 3_000_000, 5_000)]
    arrivals += [(t, "gt", GroundTruthPose(robot="zumo1", stamp_us=t, x=pose(t)[0], y=pose(t)[1]))
                 for t in range(T0_US, T0_US + 3_000_000, 33_333)]
    for _, kind, m in sorted((a for a in arrivals if a[0] <= T0_US + 2_500_000), key=lambda a: a[0]):  # at 2.5 s
        if kind == "track":
            st.on_track("arena/robots/zumo1", m)
        else:
            st.on_groundtruth(m)
    snap = st.snapshot()
    (t,), (g,) = snap["tracks"], snap["groundtruth"]
    # what the page used to show: the latest track vs the latest pose, 0.5 s apart on the circle
    assert math.hypot(t["x"] - g["x"], t["y"] - g["y"]) == pytest.approx(2 * 0.4 * math.sin(0.75 * 0.5 / 2), abs=0.01)
    assert t["error_m"] == pytest.approx(0.0, abs=1e-4) and t["error_note"] is None
    assert t["error_clock"] == "sensor" and 0 <= t["error_behind_ms"] < 40


def test_webcam_on_the_host_clock_uses_the_tracks_host_ns_and_otherwise_says_no_overlap():
    for host, expect in ((True, 0.02), (False, None)):
        st = ViewerState()
        for t in range(T0_US, T0_US + 1_000_000, 10_000):
            st.on_track("arena/robots/zumo1", track(t, host=host))
        x, y = pose(T0_US + 500_000)
        st.on_groundtruth(GroundTruthPose(robot="zumo1", stamp_us=HOST0_NS // 1000 + T0_US + 500_000, x=x + 0.02, y=y))
        (t,) = st.snapshot()["tracks"]
        if expect is None:
            assert t["error_m"] is None and t["error_note"] == NO_OVERLAP
        else:
            assert t["error_m"] == pytest.approx(expect, abs=1e-4) and t["error_clock"] == "host"
    # a track of a robot without ground truth: no figure and nothing to explain
    st.on_track("arena/robots/zumo2", track(T0_US, track_id=2, robot="zumo2"))
    z2 = {t["label"]: t for t in st.snapshot()["tracks"]}["zumo2"]
    assert z2["error_m"] is None and z2["error_note"] is None


def test_a_numbered_track_that_gets_its_name_is_replaced_four_robots_four_tracks():
    st = ViewerState()
    for tid in (1, 2, 3, 4):  # tentative, numbered
        for k in range(3):
            st.on_track(f"arena/robots/{tid}", track(T0_US + k * 10_000, tid, None, xy=(0.2 * tid, 0.5)))
    assert [t["label"] for t in st.snapshot()["tracks"]] == ["#1", "#2", "#3", "#4"]
    for tid in (1, 2, 3, 4):  # named: the tracker publishes them on their robot's key
        st.on_track(f"arena/robots/zumo{tid}", track(T0_US + 40_000, tid, f"zumo{tid}", xy=(0.2 * tid, 0.6)))
    snap = st.snapshot()["tracks"]
    assert [(t["key"], t["label"], t["id"]) for t in snap] == [
        (f"arena/robots/zumo{i}", f"zumo{i}", i) for i in (1, 2, 3, 4)]
    assert st.track_count() == 4
    assert all(len(t["trail_m"]) == 4 for t in snap)  # the numbered track's trail goes on under its name
    # and back: the tracker drops the name again (same track id on its number's key)
    st.on_track("arena/robots/3", track(T0_US + 50_000, 3, None, xy=(0.6, 0.7)))
    assert sorted(t["label"] for t in st.snapshot()["tracks"]) == ["#3", "zumo1", "zumo2", "zumo4"]
    # another camera's track 1 is another track
    st.on_track("arena/robots/1", Track(track_id=1, camera="cam1", stamp_us=T0_US, x=1.0, y=1.0))
    assert len(st.snapshot()["tracks"]) == 5


def test_entries_not_updated_within_the_timeout_are_dropped():
    clock = Clock()
    st = ViewerState(track_timeout_s=3.0, clock=clock)
    st.on_track("arena/robots/7", track(T0_US, 7, None))
    st.on_groundtruth(GroundTruthPose(robot="zumo9", stamp_us=T0_US, x=0.5, y=0.5))
    clock.t += 2.0
    st.on_track("arena/robots/zumo1", track(T0_US + 2_000_000))
    assert st.track_count() == 2 and len(st.snapshot()["groundtruth"]) == 1
    clock.t += 1.5  # #7 and zumo9's pose are 3.5 s old, zumo1 1.5 s
    assert st.track_count() == 1
    snap = st.snapshot()
    assert [t["key"] for t in snap["tracks"]] == ["arena/robots/zumo1"] and snap["groundtruth"] == []
    assert list(st._tracks) == ["arena/robots/zumo1"] and st._gt == {}  # gone, not just hidden


def test_pose_history_interpolates_inside_only_and_is_bounded():
    h = PoseHistory(span_us=1_000_000, max_len=50, max_gap_us=200_000)
    h.add(0, 0.0, 0.0)
    h.add(100_000, 1.0, 2.0)
    assert h.at(25_000) == pytest.approx((0.25, 0.5))
    assert h.at(100_000) == (1.0, 2.0) and h.at(-1) is None and h.at(100_001) is None
    h.add(50_000, 0.4, 0.4)  # late, inserted in order
    assert h.t == [0, 50_000, 100_000] and h.at(25_000) == pytest.approx((0.2, 0.2))
    h.add(400_000, 4.0, 0.0)  # a 300 ms hole: no position inside it
    assert h.at(300_000) is None and h.at(400_000) == (4.0, 0.0)
    for k in range(1, 200):
        h.add(400_000 + k * 1_000, 0.0, 0.0)
    assert len(h) == 50  # max_len
    for k in range(1, 30):
        h.add(600_000 + k * 100_000, 0.0, 0.0)
    assert h.span() == (2_500_000, 3_500_000)  # span_us
    h.add(10_000, 9.0, 9.0)  # the clock went back by more than the span: a restarted source
    assert h.t == [10_000]
    h.add(20_000, math.nan, 0.0)
    assert len(h) == 1


def test_timed_error_takes_the_newest_truth_inside_the_track_and_one_clock_only():
    trk, truth = PoseHistory(), PoseHistory()
    for t in range(0, 1_000_001, 10_000):
        trk.add(t, t * 1e-6, 0.0)  # 1 m/s along x
    for t in (500_000, 900_000, 1_200_000):  # the last one is newer than the track: not yet comparable
        truth.add(t, t * 1e-6 + 0.03, 0.04)
    te = timed_error(trk, None, truth)
    assert (te.t_us, te.clock, te.behind_us) == (900_000, "sensor", 100_000)
    assert te.err_m == pytest.approx(0.05)
    assert timed_error(trk, None, truth, clock="host") is None
    with pytest.raises(ValueError):
        timed_error(trk, None, truth, clock="webcam")

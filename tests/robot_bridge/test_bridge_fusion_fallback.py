"""A closed loop that loses its robot's track falls back to odometry and says so (issue 20)."""

from __future__ import annotations

import pytest

from robot_bridge.control import ControlOutput, MissionRunner, TrackWatch
from robot_bridge.core import BridgeOptions, RobotHandle, RobotSetup
from robot_bridge.missions import MissionLimits, build_mission
from robot_bridge.odometry import WheelGeometry

DRIVE = ControlOutput(100, 100, "line", False, 0.2, 0.2)
STAND = ControlOutput(0, 0, "pause", False, 0.0, 0.0)


def test_a_track_missing_for_half_a_second_while_driving_is_a_fallback_until_one_comes_back():
    w = TrackWatch(lost_s=0.5)
    t, changes = 100.0, []
    for k in range(300):                      # 3 s at 100 Hz; tracks every 20 ms with 80 ms latency
        now = t + k * 0.01
        track = now - 0.08 if not 1.0 <= k * 0.01 < 2.0 else t + 0.92   # none between 1.0 and 2.0 s
        c = w.update(now, track, moving=True)
        if c:
            changes.append((round(k * 0.01, 2), c))
    assert [c for _, c in changes] == ["lost", "regained"]
    assert changes[0][0] == pytest.approx(1.43, abs=0.02)      # the last track (0.92 s) + 0.5 s
    assert changes[1][0] == pytest.approx(2.0, abs=0.02)
    # driven without a track from the last one (measured at 0.92 s) to the next (measured at 1.92 s,
    # arriving at 2.0 s), not from when the 0.5 s ran out (1.43 s)
    assert w.fallbacks == 1 and w.odometry_s == pytest.approx(1.0, abs=0.03)
    assert w.as_dict(3.0)["odometry_before_first_track_s"] == 0.0   # it had tracks before


def test_standing_is_no_fallback_and_no_track_at_all_is_one():
    w = TrackWatch(lost_s=0.5)
    for k in range(200):                      # stands 2 s without tracks: an event camera sees nothing
        assert w.update(k * 0.01, None, moving=False) is None
    assert w.fallbacks == 0
    out = [w.update(2.0 + k * 0.01, None, moving=True) for k in range(100)]   # drives, never a track
    assert out.count("lost") == 1 and abs(out.index("lost") - 50) <= 1   # 0.5 s after it started driving
    # 1 s on odometry alone: from when it started to drive (2.0 s), all of it before any track
    assert w.as_dict(3.0) == {"odometry_fallbacks": 1, "odometry_only_s": pytest.approx(1.0, abs=0.02),
                              "odometry_before_first_track_s": pytest.approx(1.0, abs=0.02),
                              "on_odometry_at_end": True}


def test_driving_before_the_first_track_is_timed_from_the_start_and_said_apart():
    w = TrackWatch(lost_s=0.5)
    for k in range(100):                      # stands 1 s
        w.update(k * 0.01, None, moving=False)
    changes = {}
    for k in range(100, 400):                 # drives from 1.0 s; its first track comes at 1.8 s
        now = k * 0.01
        c = w.update(now, now - 0.05 if now >= 1.8 else None, moving=True)
        if c:
            changes[c] = round(now, 2)
        if k == 250:                          # then none from 2.5 s to 3.4 s: a second fallback
            break
    for k in range(251, 400):
        now = k * 0.01
        c = w.update(now, 2.5 if now < 3.4 else now - 0.05, moving=True)
        if c:
            changes[c + "2"] = round(now, 2)
    assert changes["lost"] == pytest.approx(1.5, abs=0.02) and changes["regained"] == pytest.approx(1.8, abs=0.02)
    assert changes["lost2"] == pytest.approx(3.0, abs=0.02) and changes["regained2"] == pytest.approx(3.4, abs=0.02)
    d = w.as_dict(4.0)
    assert d["odometry_fallbacks"] == 2
    # from 1.0 s to the first track's measurement (1.75 s), from 2.5 s to the next one's (3.35 s)
    assert d["odometry_only_s"] == pytest.approx(0.75 + 0.85, abs=0.03)
    assert d["odometry_before_first_track_s"] == pytest.approx(0.75, abs=0.03)  # the first only


def test_the_mission_manifest_and_the_handle_say_the_closed_loop_fell_back(tmp_path):
    h = RobotHandle(RobotSetup("r1", "tcp://127.0.0.1:9"), BridgeOptions(log_dir=str(tmp_path)),
                    on_error=lambda msg: errors.append(msg))
    errors: list[str] = []
    mission = build_mission("circle", {"radius_m": 0.2}, (0.9, 0.5, 0.0), 0.2, MissionLimits.for_arena((1.83, 1.83)))
    with h.lock:
        h.runner = MissionRunner(mission, WheelGeometry(), mode="closed", estimator=h.estimator, odometry=h.odometry)
        h.mission_id = "m1"
        h.track_watch = TrackWatch(h.opt.track_lost_s)
        t0 = 1_000_000_000_000
        h._watch_track(t0, STAND)
        for k in range(1, 80):                # drives 0.8 s, no track of it ever came
            h._watch_track(t0 + k * 10_000_000, DRIVE)
        assert h.on_odometry and h.odometry_fallbacks == 1
        h._end_mission("finished")
    fusion = h.last_result["fusion"]
    assert fusion["tracks_used"] == 0 and fusion["odometry_fallbacks"] == 1 and fusion["on_odometry_at_end"]
    assert len(errors) == 1 and "odometry alone" in errors[0]
    assert not h.on_odometry                  # the mission ended


def test_a_paper_mission_has_no_track_watch(tmp_path):
    h = RobotHandle(RobotSetup("r1", "tcp://127.0.0.1:9"), BridgeOptions(log_dir=str(tmp_path)))
    assert h.track_watch is None and not h.on_odometry


def test_a_robot_being_stopped_is_no_fallback(tmp_path):
    """The bridge closing halts the motors before the mission ends: the robot stands, the event
    camera loses it, and that is not a fallback to odometry (every robot of a demo said
    "still on odometry at the end" when it was counted)."""
    h = RobotHandle(RobotSetup("r1", "tcp://127.0.0.1:9"), BridgeOptions(log_dir=str(tmp_path)))
    mission = build_mission("circle", {"radius_m": 0.2}, (0.9, 0.5, 0.0), 0.2, MissionLimits.for_arena((1.83, 1.83)))
    with h.lock:
        h.runner = MissionRunner(mission, WheelGeometry(), mode="closed", estimator=h.estimator, odometry=h.odometry)
        h.track_watch = TrackWatch(h.opt.track_lost_s)
        t0 = 1_000_000_000_000
        h._watch_track(t0, STAND)
        h.halting = True                      # arena bridge run closing: halt_motors() came first
        for k in range(1, 100):               # the mission still asks to drive for 1 s, no track comes
            h._watch_track(t0 + k * 10_000_000, DRIVE)
        assert not h.on_odometry and h.odometry_fallbacks == 0


def _drive(w, t0, t1, track_of, moving=True, dt=0.01):
    """Steps from t0 to t1 (excluded); ``track_of(now)`` is the newest track's measurement time."""
    changes = []
    for k in range(round((t1 - t0) / dt)):
        now = t0 + k * dt
        c = w.update(now, track_of(now), moving if not callable(moving) else moving(now))
        if c:
            changes.append((round(now, 2), c))
    return changes


def test_an_earlier_missions_track_is_not_this_ones():
    # the robot's last track is 60 s old (an earlier mission); this one drives from 160 s, its first track at 161 s
    w = TrackWatch(lost_s=0.5, start_t=160.0)
    _drive(w, 160.0, 162.0, lambda now: 100.0 if now < 161.0 else now - 0.05)
    d = w.as_dict(162.0)
    assert d["odometry_only_s"] == pytest.approx(1.0, abs=0.06)             # not 61 s
    assert d["odometry_before_first_track_s"] == pytest.approx(1.0, abs=0.06)
    w = TrackWatch(lost_s=0.5, start_t=160.0)                                # 0.3 s before it started
    _drive(w, 160.0, 162.0, lambda now: 159.7 if now < 161.0 else now - 0.05)
    assert w.as_dict(162.0)["odometry_before_first_track_s"] == pytest.approx(1.0, abs=0.06)


def test_standing_during_a_fallback_is_not_driving_on_odometry():
    w = TrackWatch(lost_s=0.5)
    # tracks until 1.0 s, drives without one to 2.0 s, stands to 7.0 s, drives, a track measured at 7.5 s
    _drive(w, 0.0, 9.0, lambda now: min(now, 1.0) if now < 7.5 else now,
           moving=lambda now: not 2.0 <= now < 7.0)
    assert w.fallbacks == 1 and w.odometry_s == pytest.approx(1.0 + 0.5, abs=0.03)


def test_the_end_is_the_returning_tracks_measurement_time_and_a_clock_step_back_counts_nothing():
    w = TrackWatch(lost_s=0.5)
    # tracks arrive 0.3 s after they are measured; none measured between 1.0 and 2.0 s
    _drive(w, 0.0, 3.0, lambda now: (now - 0.3) if not 1.3 <= now < 2.3 else 1.0)
    assert w.odometry_s == pytest.approx(1.0, abs=0.03)                    # not 1.3 s
    w = TrackWatch(lost_s=0.5)
    _drive(w, 0.0, 2.0, lambda now: min(now, 0.5))                         # lost at 1.0 s, since 0.5 s
    assert w.on_odometry
    assert w.update(-1.0, -1.0, True) == "regained"                        # the wall clock stepped back 3 s
    assert w.odometry_s == 0.0 and w.as_dict(-1.0)["odometry_only_s"] == 0.0

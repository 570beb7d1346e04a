"""Missions: commanded paths and phases."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from robot_bridge.missions import MissionError, MissionLimits, build_mission, check_mission, mission_speed

START = (0.9, 0.6, math.pi / 2)


def test_circle_is_tangent_closed_and_of_the_right_radius():
    m = build_mission("circle", {"radius_m": 0.3, "laps": 2}, START, 0.23)
    p = m.path(0.002)
    centre = np.array([0.9 - 0.3, 0.6])       # ccw: centre to the left of a robot facing +y
    assert np.allclose(np.hypot(*(p - centre).T), 0.3, atol=1e-9)
    assert [s.label for s in m.segments] == ["lap 1", "lap 2"]
    assert m.segments[-1].end == pytest.approx(START, abs=1e-9)
    assert m.length_m == pytest.approx(2 * 2 * math.pi * 0.3)
    cw = build_mission("circle", {"radius_m": 0.3, "direction": "cw"}, START, 0.23).path()
    assert np.allclose(np.hypot(cw[:, 0] - 1.2, cw[:, 1] - 0.6), 0.3)


def test_square_has_sides_and_zero_point_turns():
    m = build_mission("square", {"side_m": 0.6}, (0.3, 0.3, 0.0), 0.46)
    kinds = [s.kind for s in m.segments]
    assert kinds == ["line", "turn"] * 4
    corners = [s.start[:2] for s in m.segments if s.kind == "line"]
    assert np.allclose(corners, [(0.3, 0.3), (0.9, 0.3), (0.9, 0.9), (0.3, 0.9)], atol=1e-9)
    assert all(s.turn_rad == pytest.approx(math.pi / 2) for s in m.segments if s.kind == "turn")
    assert m.bounds() == pytest.approx((0.3, 0.3, 0.9, 0.9))


def test_figure8_back_and_forth_waypoints():
    f8 = build_mission("figure8", {"radius_m": 0.2}, START, 0.2)
    assert [np.sign(s.curvature) for s in f8.segments] == [1, -1]
    assert f8.segments[-1].end == pytest.approx(START, abs=1e-9)
    bf = build_mission("back_and_forth", {"length_m": 0.5}, (0.5, 0.5, 0.0), 0.2)
    assert [s.kind for s in bf.segments] == ["line", "turn", "line", "turn"]
    assert bf.segments[2].end[:2] == pytest.approx((0.5, 0.5))
    wp = build_mission("waypoints", {"points": [[1.0, 0.5], [1.0, 1.0]]}, (0.5, 0.5, 0.0), 0.2)
    assert [s.kind for s in wp.segments] == ["line", "turn", "line"]   # already facing the first point
    assert wp.segments[-1].end[:2] == pytest.approx((1.0, 1.0))


def test_stop_and_go_pauses():
    m = build_mission("square", {"side_m": 0.6, "pause_s": 0.5, "pause_every_m": 0.2}, (0.3, 0.3, 0.0), 0.2)
    lines = [s for s in m.segments if s.kind == "line"]
    pauses = [s for s in m.segments if s.kind == "pause"]
    assert len(lines) == 12 and len(pauses) == 12
    assert all(s.length_m == pytest.approx(0.2) for s in lines)
    assert m.length_m == pytest.approx(2.4)


@pytest.mark.parametrize("pattern,params,match", [
    ("spiral", {}, "unknown mission"),
    ("circle", {"radius_m": -1}, "radius_m"),
    ("circle", {"radius": 0.3}, "unknown parameter"),
    ("square", {"side_m": "big"}, "side_m must be a number"),
    ("circle", {"direction": "up"}, "direction"),
    ("circle", {"laps": 1.5}, "laps must be an integer"),
    ("waypoints", {"points": [[0, "a"]]}, r"points\[0\]"),
    ("waypoints", {}, "points must be"),
])
def test_bad_parameters_are_clear(pattern, params, match):
    with pytest.raises(MissionError, match=match):
        build_mission(pattern, params, START, 0.2)


def test_speed_from_power_or_speed():
    assert mission_speed(power=0.5) == pytest.approx(0.23)
    assert mission_speed(power=1.0) == pytest.approx(0.46)
    assert mission_speed(speed_mps=0.1) == 0.1
    with pytest.raises(MissionError, match="either"):
        mission_speed(power=0.5, speed_mps=0.1)
    with pytest.raises(MissionError, match="speed_mps"):
        mission_speed(speed_mps=3.0)


def test_positions_at_matches_pose_at_on_lines_arcs_and_turns():
    segs = build_mission("circle", {"radius_m": 0.3}, START, 0.23).segments
    segs += build_mission("square", {"side_m": 0.6}, (0.3, 0.3, 0.0), 0.46).segments
    for seg in segs:
        ss = np.linspace(-0.1, seg.length_m + 0.1, 37)          # clipped at both ends too
        want = np.array([seg.pose_at(s)[:2] for s in ss]) if seg.kind != "turn" else \
            np.tile(seg.start[:2], (ss.size, 1))
        assert np.allclose(seg.positions_at(ss), want, atol=1e-12), seg.kind


ARENA = MissionLimits.for_arena((1.83, 1.83))


@pytest.mark.parametrize("pattern,params,match", [
    ("circle", {"pause_s": 0.5, "pause_every_m": 0.000001}, r"pause_every_m=1e-06 out of range: 0 .* \[0.05, 500.0\] m"),
    ("circle", {"laps": 10**9}, r"laps=1000000000 out of range \[1, 100\]"),
    ("circle", {"radius_m": 1e9}, r"radius_m=1000000000.0 out of range \[0.05, 1.294\] m"),
    ("square", {"side_m": 3.0}, r"side_m=3.0 out of range \[0.05, 2.588\] m"),
    ("back_and_forth", {"length_m": 0.0}, r"length_m=0.0 out of range"),
    ("circle", {"pause_s": 1e6}, r"pause_s=1000000.0 out of range \[0.0, 60.0\] s"),
    ("circle", {"laps": float("inf")}, "laps must be an integer"),
    ("waypoints", {"points": [[0.5, 0.5]] * 10**6}, "points has 1000000 waypoints; at most 256"),
    ("waypoints", {"points": [[0.5, 0.5], [5.0, 0.5]]}, r"points\[1\]=\[5.0, 0.5\] outside the arena"),
    ("circle", {"radius_m": 1.2, "laps": 100}, "mission path of 754.0 m exceeds 500 m"),
    ("square", {"side_m": 0.65, "laps": 100, "pause_s": 0.1, "pause_every_m": 0.05}, "phases, at most 10000"),
])
def test_hostile_parameters_are_refused_by_the_pure_check_before_anything_is_built(pattern, params, match):
    t0 = time.perf_counter()
    with pytest.raises(MissionError, match=match):
        check_mission(pattern, params, ARENA)
    assert time.perf_counter() - t0 < 0.05          # cost independent of the values asked for
    with pytest.raises(MissionError, match=match):   # build_mission runs the same check first
        build_mission(pattern, params, START, 0.2, ARENA)


def test_check_mission_predicts_the_phases_and_length_build_mission_lays_out():
    cases = [("circle", {"laps": 100, "pause_s": 0.1, "pause_every_m": 0.05}),
             ("square", {"side_m": 0.5, "laps": 3, "pause_s": 0.2}),
             ("figure8", {"radius_m": 0.2, "laps": 2, "pause_s": 0.1, "pause_every_m": 0.3}),
             ("back_and_forth", {"length_m": 0.4, "laps": 5}),
             ("waypoints", {"points": [[0.9, 1.2], [1.3, 1.2], [1.3, 0.7]]})]
    for pattern, params in cases:
        size = check_mission(pattern, params, ARENA, START)
        m = build_mission(pattern, params, START, 0.2, ARENA)
        assert size.length_m == pytest.approx(m.length_m), pattern
        # an upper bound (a waypoint already faced needs no turn), exact for the patterns
        assert size.segments >= len(m.segments) and (pattern == "waypoints" or size.segments == len(m.segments))
    assert check_mission(*cases[0], ARENA).segments == 7600      # huge but valid

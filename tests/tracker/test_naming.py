"""tracker.naming on synthetic histories: tracks bound to robots by their telemetry, no webcam."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tracker.naming import NamingParams, TelemetryNamer

T0_NS = 1_700_000_000_000_000_000   # host epoch ns of t = 0


def trajectory(kind: str, duration_s: float, dt: float = 0.002, start=(0.5, 0.5, 0.0)):
    """(t s, x, y, yaw, v, w) of a robot driving ``kind``."""
    t = np.arange(0.0, duration_s, dt)
    if kind == "ccw":
        v, w = np.full_like(t, 0.25), np.full_like(t, 1.0)
    elif kind == "cw":
        v, w = np.full_like(t, 0.25), np.full_like(t, -1.0)
    elif kind == "square":   # 1.2 s straight, 0.3 s pause, 0.6 s turn at 2.6 rad/s, 0.3 s pause
        ph = t % 2.4
        v = np.where(ph < 1.2, 0.3, 0.0)
        w = np.where((ph >= 1.5) & (ph < 2.1), 2.6, 0.0)
    elif kind == "stopgo":
        v = np.where((t % 2.0) < 1.0, 0.3, 0.0)
        w = np.zeros_like(t)
    elif kind == "still":
        v, w = np.zeros_like(t), np.zeros_like(t)
    else:
        raise ValueError(kind)
    yaw = start[2] + np.concatenate([[0.0], np.cumsum(w[:-1] * dt)])
    x = start[0] + np.concatenate([[0.0], np.cumsum(v[:-1] * np.cos(yaw[:-1]) * dt)])
    y = start[1] + np.concatenate([[0.0], np.cumsum(v[:-1] * np.sin(yaw[:-1]) * dt)])
    return t, x, y, yaw, v, w


def feed(namer, robots: dict, tracks: dict, duration_s: float, *, seed=0, latency=(0.002, 0.02),
         clock_offset_us=None, flip_every_s=0.7, stall=None, by_arrival=False, track_lost: dict | None = None, check=None):
    """Feed telemetry (50 Hz, robot clock, random arrival latency) and tracks (100 Hz, host
    capture time, noise, heading flips; none while ``track_lost`` {track_id: (from s, to s)}) of ``robots`` {name: kind} tracked as ``tracks``
    {track_id: name}; call ``namer.update`` every 0.1 s. Returns {time s: bindings made}."""
    rng = np.random.default_rng(seed)
    traj = {name: trajectory(kind, duration_s, start=(0.4 + 0.3 * k, 0.5, 0.3 * k))
            for k, (name, kind) in enumerate(robots.items())}
    offs = clock_offset_us or {name: 1000 + 7_777_777 * k for k, name in enumerate(robots)}
    events = []
    for name, (t, x, y, yaw, v, w) in traj.items():
        half = 0.5 * 0.09 * w
        arrived = 0.0
        for k in range(0, t.size, 10):        # 50 Hz telemetry, in order (a serial link is a FIFO)
            lat = rng.uniform(*latency)
            if stall is not None and (t[k] + stall[2]) % stall[0] < stall[1]:   # the host does not run the bridge
                lat = max(lat, stall[1] - (t[k] + stall[2]) % stall[0] + 0.001)
            lat = max(lat, arrived - t[k])
            arrived = t[k] + lat
            gyro = w[k] + rng.normal(0, 0.003) + 0.002
            t_robot = t[k] + lat if by_arrival else t[k]   # by_arrival: as if the robot's clock were the arrival
            events.append((t[k] + lat, "tel", name, (int(t_robot * 1e6) + offs[name], int(T0_NS + (t[k] + lat) * 1e9),
                           v[k] - half[k] + rng.normal(0, 0.005), v[k] + half[k] + rng.normal(0, 0.005), gyro)))
    for tid, name in tracks.items():
        t, x, y, yaw, v, w = traj[name]
        lost = (track_lost or {}).get(tid, (math.inf, math.inf))
        for k in range(0, t.size, 5):         # 100 Hz tracks (at rest too: coasting), 30 ms behind
            if not lost[0] <= t[k] < lost[1]:
                flip = math.pi if int(t[k] / flip_every_s) % 3 == 1 else 0.0
                yw = yaw[k] + flip + rng.normal(0, 0.05)
                vx = v[k] * math.cos(yaw[k]) + rng.normal(0, 0.02)
                vy = v[k] * math.sin(yaw[k]) + rng.normal(0, 0.02)
                events.append((t[k] + 0.03, "trk", tid, (int(T0_NS + t[k] * 1e9), x[k] + rng.normal(0, 0.003),
                                                         y[k] + rng.normal(0, 0.003), yw, vx, vy)))
    events.sort(key=lambda e: e[0])
    made = {}
    next_up = 0.1
    for t_arr, kind, who, a in events:
        while t_arr >= next_up:
            out = namer.update(int(T0_NS + next_up * 1e9))
            if out:
                made[round(next_up, 2)] = out
            if check is not None:
                check(namer)
            next_up += 0.1
        if kind == "tel":
            namer.add_telemetry(who, a[0], a[1], a[2], a[3], a[4])
        else:
            namer.add_track(who, a[0], a[1], a[2], a[3], a[4], a[5])
    return made


def unique_binding(namer):
    assert len(set(namer.bound.values())) == len(namer.bound), namer.bound


def right_binding(tracks: dict):
    """A check that every binding, at every step, is a true one (and one track per robot)."""
    def check(namer):
        unique_binding(namer)
        for name, tid in namer.bound.items():
            assert tracks[tid] == name, f"track {tid} bound to {name}"
    return check


def test_every_track_gets_its_robots_name_from_telemetry_within_a_few_seconds():
    namer = TelemetryNamer()
    robots = {"zumo-a": "ccw", "zumo-b": "cw", "zumo-c": "square", "zumo-d": "stopgo"}
    tracks = {11: "zumo-c", 12: "zumo-a", 13: "zumo-d", 14: "zumo-b"}
    made = feed(namer, robots, tracks, 6.0, check=right_binding(tracks))
    assert namer.bound == {name: tid for tid, name in tracks.items()}
    first = {}
    for t, out in made.items():
        for tid, name in out.items():
            assert tracks[tid] == name, f"wrong name at {t} s: track {tid} -> {name}"
            first.setdefault(name, t)
    assert max(first.values()) <= 4.0, first


def test_a_loaded_host_that_delays_telemetry_by_half_a_second_does_not_misalign_it():
    """A loaded host runs the bridge 0.9 s in every 1.6 s: telemetry arrives up to 0.7 s late, in
    bursts. The robot clock, with the offset from the fastest samples, places them, not their
    arrival."""
    namer = TelemetryNamer()
    robots = {"zumo-a": "square", "zumo-b": "stopgo"}
    tracks = {1: "zumo-b", 2: "zumo-a"}
    feed(namer, robots, tracks, 6.0, stall=(1.6, 0.7, 0.0), seed=3, check=right_binding(tracks))
    assert namer.bound == {"zumo-a": 2, "zumo-b": 1}
    assert max(true_pair_costs(namer, {1: "zumo-b", 2: "zumo-a"})) < 1.0


def true_pair_costs(namer, truth: dict):
    return [c for (name, tid), c in namer.last_costs.items() if truth.get(tid) == name]


def test_robots_that_drive_alike_are_not_told_apart_by_guessing():
    namer = TelemetryNamer()
    made = feed(namer, {"zumo-a": "ccw", "zumo-b": "ccw"}, {1: "zumo-a", 2: "zumo-b"}, 5.0)
    assert made == {} and namer.bound == {}
    assert namer.last_costs and max(namer.last_costs.values()) < 1.5   # all pairs fit: ambiguous


def test_standing_still_is_no_evidence():
    namer = TelemetryNamer()
    made = feed(namer, {"zumo-a": "still"}, {1: "zumo-a"}, 4.0)
    assert made == {} and namer.last_costs == {}


def test_a_track_that_moves_unlike_any_robot_is_not_named():
    """zumo-a (a circle) reports; the only track is of a square-driving robot without telemetry."""
    namer = TelemetryNamer()
    feed_only_a(namer)
    assert namer.bound == {}
    assert namer.last_costs and min(namer.last_costs.values()) > NamingParams().accept


def feed_only_a(namer):
    """zumo-a's telemetry (circle) against a track of a square-driving robot without telemetry."""
    t, x, y, yaw, v, w = trajectory("ccw", 5.0)
    ts, xs, ys, yaws, vs, ws = trajectory("square", 5.0)
    for k in range(0, t.size, 5):
        if k % 10 == 0:
            namer.add_telemetry("zumo-a", int(t[k] * 1e6), int(T0_NS + (t[k] + 0.01) * 1e9),
                                v[k] - 0.045 * w[k], v[k] + 0.045 * w[k], w[k])
        if vs[k] + abs(ws[k]) > 0:
            namer.add_track(7, int(T0_NS + ts[k] * 1e9), xs[k], ys[k], yaws[k],
                            vs[k] * math.cos(yaws[k]), vs[k] * math.sin(yaws[k]))
        if k % 50 == 0:
            assert namer.update(int(T0_NS + t[k] * 1e9)) == {}


def test_a_robot_whose_track_was_lost_is_bound_to_its_new_track_and_never_to_two():
    namer = TelemetryNamer()
    robots = {"zumo-a": "square", "zumo-b": "ccw"}
    # zumo-a's first track 1 is lost at 3 s; a new track 3 follows it from 3.2 s on
    tracks = {1: "zumo-a", 3: "zumo-a", 2: "zumo-b"}
    made = feed(namer, robots, tracks, 9.0, track_lost={1: (3.0, 99.0), 3: (0.0, 3.2)}, check=unique_binding)
    names_of = {}
    for t, out in sorted(made.items()):
        for tid, name in out.items():
            names_of.setdefault(name, []).append((t, tid))
    assert [tid for _, tid in names_of["zumo-a"]] == [1, 3]
    assert names_of["zumo-a"][0][0] < 3.0 < names_of["zumo-a"][1][0]
    assert namer.bound == {"zumo-a": 3, "zumo-b": 2}


def test_track_position_at_interpolates_by_host_and_by_sensor_time():
    namer = TelemetryNamer()
    namer.add_track(4, 1_000_000_000, 1.0, 2.0, stamp_us=500)
    namer.add_track(4, 1_100_000_000, 1.2, 2.0, stamp_us=100_500)
    assert namer.track_position_at(4, 1_050_000_000) == pytest.approx((1.1, 2.0))
    assert namer.track_position_at(4, 50_500, clock="sensor") == pytest.approx((1.1, 2.0))
    assert namer.track_position_at(4, 2_000_000_000) is None       # far outside its history
    assert namer.track_position_at(9, 1_050_000_000) is None       # no such track


def test_a_robot_clock_restart_starts_its_history_afresh():
    namer = TelemetryNamer(NamingParams())
    for k in range(100):
        namer.add_telemetry("a", 5_000_000 + k * 20_000, T0_NS + k * 20_000_000, 0.2, 0.2, 0.0)
    namer.add_telemetry("a", 1_000, T0_NS + 100 * 20_000_000, 0.2, 0.2, 0.0)
    assert namer.clock_resets == 1

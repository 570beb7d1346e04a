"""A small publisher for the viewer tests: synthetic event windows of two robots driving circles
in a 1.83 m arena seen by a 320 x 240 px camera, their tracks, ground truth, telemetry and a status.

``python -m tests.viewer.feed ENDPOINT SECONDS``; prints ``feeding`` once publishing.
Robot ``zumo1``'s tracks carry ``u_px``/``v_px``; ``zumo2``'s do not (the viewer must project them
with the lab calibration, :data:`CALIBRATION`).
"""

from __future__ import annotations

import math
import sys
import time

import numpy as np

from arena import codec
from arena.events import make_events
from arena.messages import EventWindow, GroundTruthPose, Telemetry, Track
from arena.service import Service
from arena.session import ZenohSettings, open_session

W, H = 320, 240
ARENA = 1.83
# arena (x, y) m -> pixel: u = 40 + x * 130, v = 230 - y * 120 (y up in the arena, v down in the image)
CALIBRATION = {"image_size": [W, H], "points": [
    {"pixel": [40 + x * 130, 230 - y * 120], "arena_m": [x, y]} for x, y in
    ((0, 0), (ARENA, 0), (ARENA, ARENA), (0, ARENA))]}


def to_px(x: float, y: float) -> tuple[float, float]:
    return 40 + x * 130, 230 - y * 120


def pose(robot: int, t: float) -> tuple[float, float, float]:
    """Pose (x m, y m, yaw rad) of robot 0 or 1 at time t s: circles of 0.4 m at 0.25 m/s."""
    cx, cy, r, w = (0.55, 0.9, 0.4, 0.6) if robot == 0 else (1.3, 0.9, 0.35, -0.7)
    a = w * t + robot
    yaw = a + math.copysign(math.pi / 2, w)
    return cx + r * math.cos(a), cy + r * math.sin(a), math.atan2(math.sin(yaw), math.cos(yaw))


def window(seq: int, t_us: int, poses, rng) -> EventWindow:
    xs, ys, ps = [], [], []
    for x, y, _ in poses:
        u, v = to_px(x, y)
        ang = rng.uniform(0, 2 * math.pi, 600)
        rad = rng.uniform(5, 9, 600)
        xs.append(u + rad * np.cos(ang))
        ys.append(v + rad * np.sin(ang))
        ps.append((np.cos(ang) > 0).astype(int))
    xs.append(rng.uniform(0, W - 1, 100))
    ys.append(rng.uniform(0, H - 1, 100))
    ps.append(rng.integers(0, 2, 100))
    x = np.clip(np.concatenate(xs), 0, W - 1).astype(int)
    y = np.clip(np.concatenate(ys), 0, H - 1).astype(int)
    t = np.sort(rng.integers(t_us - 10_000, t_us, x.size))
    ev = make_events(x, y, np.concatenate(ps), t)
    return EventWindow(camera="cam0", seq=seq, t_start_us=t_us - 10_000, t_end_us=t_us, width=W, height=H,
                       count=ev.size, codec=codec.DEFAULT_CODEC, data=codec.encode(ev), publish_ns=time.time_ns())


def main(endpoint: str, seconds: float) -> None:
    rng = np.random.default_rng(1)
    with open_session(ZenohSettings(mode="peer", connect=[endpoint])) as s, Service(s, "sim", "feed"):
        window(0, 0, [pose(0, 0.0)], rng)  # compile/load the codec before the clock starts
        time.sleep(0.5)
        print("feeding", flush=True)
        t0 = time.monotonic()
        seq = 0
        while (now := time.monotonic() - t0) < seconds:
            t_us = int(now * 1e6)
            poses = [pose(0, now), pose(1, now)]
            win = window(seq, t_us, poses, rng)
            s.put("arena/events/cam0", win.encode())
            if seq % 3 == 0:
                for i, (x, y, yaw) in enumerate(poses):
                    name = f"zumo{i + 1}"
                    u, v = to_px(x, y) if i == 0 else (None, None)
                    s.put(f"arena/robots/{name}", Track(track_id=i + 1, robot=name, camera="cam0", stamp_us=t_us,
                                                         x=x, y=y, yaw=yaw, vx=0.25 * math.cos(yaw),
                                                         vy=0.25 * math.sin(yaw), u_px=u, v_px=v,
                                                         n_events=600, edge_publish_ns=win.publish_ns,
                                                         tracker_publish_ns=time.time_ns()).encode())
                    s.put(f"arena/groundtruth/{name}", GroundTruthPose(robot=name, stamp_us=t_us, x=x + 0.01, y=y,
                                                                       yaw=yaw, detector="sim").encode())
                    s.put(f"arena/telemetry/{name}", Telemetry(
                        robot=name, seq=seq, robot_time_us=t_us, host_time_ns=time.time_ns(), enc_left=seq,
                        enc_right=seq, speed_left=0.25 + 0.05 * math.sin(now), speed_right=0.25 - 0.05 * math.sin(now),
                        gyro=(0.0, 0.0, 0.6 if i == 0 else -0.7), battery_mv=4800 - seq).encode())
            seq += 1
            time.sleep(0.01)


if __name__ == "__main__":
    main(sys.argv[1], float(sys.argv[2]))

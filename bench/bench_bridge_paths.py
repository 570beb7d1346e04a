"""Path error of missions: paper mode (encoder PID only) vs closed loop (tracks + odometry).

Runs the robot bridge's mission runner against the simulator's physics (skid-steer slip,
motor lag and mismatch, encoder quantisation) in simulated time, with a Bluetooth-like
link (telemetry and commands each delayed ``--link-ms``) and, for closed loop, camera
tracks made from the true pose delayed by ``--track-delay-ms`` with Gaussian noise
(``--track-noise-cm``, ``--track-yaw-noise-deg``) at ``--track-hz``: a stand-in for the
tracker. Prints the mean path error of each mission in both modes and their ratio, and
(``no-track``) closed loop on gyro-aided odometry alone, to show what the tracks add.
``--tracker`` replaces the stand-in by the real tracker (``tracker.pipeline``) fed by the
simulator's event camera model (~1 min per closed-loop run on this machine).

Examples::

    python bench/bench_bridge_paths.py
    python bench/bench_bridge_paths.py --track-delay-ms 120 --track-noise-cm 1.0 --seeds 3
"""

from __future__ import annotations

import argparse
import math
import sys
from collections import deque
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from robot_bridge.control import MissionRunner, PoseEstimator, path_error  # noqa: E402
from robot_bridge.missions import build_mission, mission_speed  # noqa: E402
from robot_bridge.odometry import WheelGeometry  # noqa: E402
from simulator.world import RobotSpec, World  # noqa: E402


def simulate(pattern: str, params: dict, power: float, mode: str, seed: int = 0, link_ms: float = 20.0,
             telemetry_hz: float = 100.0, track_hz: float = 100.0, track_delay_ms: float = 60.0,
             track_noise_m: float = 0.005, track_yaw_noise_rad: float = math.radians(3.0),
             track_width_m: float | None = None, start=(0.9, 0.6, math.pi / 2), max_time_s: float = 60.0,
             tracker: bool = False, tracker_latency_ms: float = 20.0, track_age_s: float = 0.0):
    """Run one mission in simulated time; return (PathError, traced (n, 2), mission, seconds).

    With ``tracker=True`` closed loop runs on the real pipeline: the simulator's DVS sensor
    renders events, ``tracker.pipeline.Pipeline`` (fleet tracker) turns each 10 ms slice into
    tracks, which reach the bridge ``tracker_latency_ms`` after the slice ends.
    """
    world = World([RobotSpec("r0", (30, 30, 30), start=start)], seed=seed)
    rng = np.random.default_rng(seed + 1000)
    sim = pipe = None
    if tracker and mode == "closed":
        from simulator.camera import CeilingCamera
        from simulator.simulation import Simulation
        from tracker.calibration import Calibration
        from tracker.pipeline import Pipeline

        cam = CeilingCamera(640, 480, world.arena_m, seed=seed)
        sim = Simulation(world, cam, seed=seed)
        pipe = Pipeline(Calibration.from_dict(cam.calibration()), fleet_size=1)
        slice_events = []
    geometry = WheelGeometry(track_width_m=track_width_m or 0.11)
    mission = build_mission(pattern, params, start, mission_speed(power=power))
    runner = MissionRunner(mission, geometry, mode=mode, estimator=PoseEstimator(delay_s=track_age_s))
    dt = 0.001
    tel_period = 1.0 / telemetry_hz
    trk_period = 1.0 / track_hz
    up: deque = deque()     # telemetry in flight: (arrival t, encL, encR, robot t)
    down: deque = deque()   # commands in flight: (arrival t, left, right)
    tracks: deque = deque()  # tracks in flight: (arrival t, pose t, x, y, yaw)
    truth: deque = deque()  # true poses for the delayed track stand-in
    traced = []
    next_tel = next_trk = 0.0
    t = 0.0
    started = False
    while t < max_time_s:
        if sim is not None:
            ev, _, _ = sim.run(1)
            slice_events.append(ev)
            if len(slice_events) == 10:          # one 10 ms slice -> tracker
                for tr in pipe.push(np.concatenate(slice_events), sim.t_us + 1):
                    if tr.state == "confirmed":
                        tracks.append((t + tracker_latency_ms / 1000.0, tr.t_us / 1e6, tr.x, tr.y,
                                       tr.yaw if math.isfinite(tr.yaw) else None))
                slice_events = []
        else:
            world.step(dt)
        t += dt
        x, y, yaw = world.pose(0)
        truth.append((t, x, y, yaw))
        if started:
            traced.append((x, y))
        if t >= next_tel:
            next_tel += tel_period
            el, er = world.encoder_counts(0)
            gz = float(world.imu(0)["gyro"][2])
            up.append((t + link_ms / 1000.0, el, er, t, gz))
        if mode == "closed" and sim is None and t >= next_trk:
            next_trk += trk_period
            tp = t - track_delay_ms / 1000.0
            while len(truth) > 1 and truth[1][0] <= tp:
                truth.popleft()
            if truth[0][0] <= tp:
                _, tx, ty, tyaw = truth[0]
                tracks.append((t, tp, tx + rng.normal(0, track_noise_m), ty + rng.normal(0, track_noise_m),
                               tyaw + rng.normal(0, track_yaw_noise_rad)))
        while tracks and tracks[0][0] <= t:
            _, tp, tx, ty, tyaw = tracks.popleft()
            runner.add_track(tp, tx, ty, tyaw)
        while up and up[0][0] <= t:
            _, el, er, tr, gz = up.popleft()
            out = runner.update(t, el, er, t_robot=tr, gyro_z=gz)
            started = True
            down.append((t + link_ms / 1000.0, out.left, out.right))
            if out.done:
                break
        while down and down[0][0] <= t:
            _, left, right = down.popleft()
            world.set_power(0, left, right)
        if runner.done:
            break
    # let the robot come to rest (the last command was 0)
    world.set_power(0, 0, 0)
    for _ in range(200):
        world.step(dt)
        traced.append(world.pose(0)[:2])
    traced_arr = np.array(traced)
    return path_error(traced_arr, mission.path()), traced_arr, mission, t


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=1, help="worlds per case (different motor mismatch/slip)")
    ap.add_argument("--link-ms", type=float, default=20.0, help="one-way serial link latency, ms")
    ap.add_argument("--track-delay-ms", type=float, default=60.0, help="pose age when a track arrives, ms")
    ap.add_argument("--track-noise-cm", type=float, default=0.5, help="track position noise, 1 sigma, cm")
    ap.add_argument("--track-yaw-noise-deg", type=float, default=3.0, help="track heading noise, 1 sigma, deg")
    ap.add_argument("--track-hz", type=float, default=100.0, help="track rate, Hz")
    ap.add_argument("--telemetry-hz", type=float, default=50.0,
                    help="robot telemetry (= control) rate, Hz (default 50, the reference firmware's)")
    ap.add_argument("--tracker", action="store_true",
                    help="closed loop on the real tracker fed by the simulated event camera (slower)")
    args = ap.parse_args(argv)
    cases = [("circle", {"radius_m": 0.3}), ("square", {"side_m": 0.6})]
    if args.tracker:
        print(f"link {args.link_ms:.0f} ms, telemetry {args.telemetry_hz:.0f} Hz, closed loop on tracker.pipeline "
              f"tracks from the simulated DVS; {args.seeds} seed(s)")
    else:
        print(f"link {args.link_ms:.0f} ms, telemetry {args.telemetry_hz:.0f} Hz, tracks {args.track_hz:.0f} Hz "
              f"delayed {args.track_delay_ms:.0f} ms, "
              f"noise {args.track_noise_cm} cm / {args.track_yaw_noise_deg} deg; {args.seeds} seed(s)")
    print(f"{'mission':<22}{'power':>6}  {'paper mean cm':>14}{'closed mean cm':>16}{'ratio':>8}"
          f"  {'paper max':>10}{'closed max':>11}{'no-track mean':>15}")
    ratios = []
    for pattern, params in cases:
        for power in (0.5, 1.0):
            res = {}
            for mode in ("paper", "closed", "no-track"):
                # no-track: closed loop on gyro-aided odometry alone (tracks too old to use)
                errs = [simulate(pattern, params, power, "closed" if mode == "no-track" else mode, seed=s,
                                 link_ms=args.link_ms, track_hz=args.track_hz, telemetry_hz=args.telemetry_hz,
                                 track_delay_ms=1e5 if mode == "no-track" else args.track_delay_ms,
                                 track_noise_m=args.track_noise_cm / 100,
                                 track_yaw_noise_rad=math.radians(args.track_yaw_noise_deg),
                                 tracker=args.tracker and mode == "closed")[0]
                        for s in range(args.seeds)]
                res[mode] = (np.mean([e.mean_m for e in errs]), np.mean([e.max_m for e in errs]))
            ratio = res["paper"][0] / res["closed"][0]
            ratios.append(ratio)
            name = f"{pattern} {params}"
            print(f"{name:<22}{power * 100:>5.0f}%  {res['paper'][0] * 100:>14.2f}{res['closed'][0] * 100:>16.2f}"
                  f"{ratio:>7.1f}x  {res['paper'][1] * 100:>10.2f}{res['closed'][1] * 100:>11.2f}"
                  f"{res['no-track'][0] * 100:>15.2f}")
    print(f"closed loop cuts the mean path error {min(ratios):.1f}x to {max(ratios):.1f}x (target >= 5x)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

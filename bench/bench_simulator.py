"""Real-time factor of the simulated arena on one core: world + event sensor at 640x480
(1 kHz internal steps, autopilot driving circles at full power), with and without the
webcam rendering at 24 fps, for 1, 4, 8 and 16 robots.

Baseline: the same pixel model run over the whole frame every step (what a frame-based
emulator such as v2e does), against ours (regions of interest around the robots plus
statistical background noise). Real-time factor = simulated seconds / wall seconds
(>= 1 means real time). The machine is shared, so the factor is computed from the CPU
time this process used (time.process_time, pinned to one core): what one dedicated core
achieves. The wall-clock factor is printed too.

    python bench/bench_simulator.py            # ~1-2 min
    python bench/bench_simulator.py --quick    # 1 and 8 robots only, shorter runs
"""

from __future__ import annotations

import argparse
import os
import time


from simulator.autopilot import Autopilot, make_plans
from simulator.camera import CeilingCamera
from simulator.dvs import DvsParams
from simulator.scenarios import Scenario
from simulator.simulation import Simulation
from simulator.world import World


def build(n: int, full_frame: bool = False, seed: int = 0) -> Simulation:
    specs = Scenario(n_robots=n, pattern="circle").robot_specs()
    world = World(specs, seed=seed)
    # every robot starts at 0.2 s (no stagger) so all of them move during the measurement
    pilot = Autopilot(world, make_plans("circle", n, world.arena_m, stagger_s=0.0), 1.0)
    # full frame: the flicker path simulates every pixel; depth 0 keeps the light steady
    params = DvsParams(flicker_hz=1.0, flicker_depth=0.0) if full_frame else DvsParams()
    return Simulation(world, CeilingCamera(640, 480, seed=seed), params, pilot, seed=seed)


def rtf(sim: Simulation, seconds: float, webcam=None, fps: float = 24.0) -> tuple[float, int, float]:
    """Run ``seconds`` of simulated time in 10 ms blocks; return (real-time factor by CPU
    time, events, real-time factor by wall time)."""
    sim.run(400)          # warm up: every robot up to speed, JIT caches loaded
    if webcam is not None:
        webcam.render()
    blocks = int(round(seconds / 0.01))
    next_frame = sim.world.t
    n_ev = 0
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in range(blocks):
        ev, _, _ = sim.run(10)
        n_ev += len(ev)
        if webcam is not None and sim.world.t >= next_frame:
            webcam.render()
            next_frame += 1.0 / fps
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return seconds / cpu, n_ev, seconds / wall


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="1 and 8 robots, shorter runs")
    args = ap.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})     # one core
    try:
        from simulator.webcam import WebcamModel
    except ImportError:
        WebcamModel = None
    counts = (1, 8) if args.quick else (1, 4, 8, 16)
    secs = 1.0 if args.quick else 2.0

    print("Simulated arena, 640x480 event sensor, 1 kHz steps, one core. RTF >= 1 is real time.")
    base_rtf = rtf(build(1, full_frame=True), 0.1)[0]
    ours1 = rtf(build(1), secs)[0]
    print(f"\n1 robot, DVS only: baseline full-frame RTF {base_rtf:6.3f} | ours ROI RTF {ours1:6.2f} "
          f"| speed-up x{ours1 / base_rtf:.0f}")
    print(f"\n{'robots':>6} | {'world+DVS RTF':>13} | {'events/s':>10} | {'+webcam 24fps RTF':>17} "
          f"| {'(wall RTF)':>10} | real time?")
    for n in counts:
        r, ev, _ = rtf(build(n), secs)
        if WebcamModel is not None:
            sim = build(n)
            rw, _, ww = rtf(sim, secs, WebcamModel(sim.world, 640, 480))
            wtxt = f"{rw:17.2f}"
        else:
            rw, wtxt, ww = r, f"{'(no webcam)':>17}", float("nan")
        print(f"{n:6d} | {r:13.2f} | {ev / secs:10.0f} | {wtxt} | {ww:10.2f} | {'yes' if rw >= 1 else 'NO'}")


if __name__ == "__main__":
    main()

"""One simulated arena in motion: world physics, ceiling event camera and (optionally) the
autopilot, advanced together in 1 ms steps. Used by :func:`simulator.scenarios.generate`
(as fast as possible) and by ``arena sim`` (paced to the wall clock)."""

from __future__ import annotations

import numpy as np

from arena.events import EVENT_DTYPE
from simulator.autopilot import Autopilot
from simulator.camera import CeilingCamera
from simulator.dvs import DvsParams, DvsSensor
from simulator.world import World

#: Truth table dtype: time (µs), robot index, pose (m, rad, arena frame), velocity (m/s).
TRUTH_DTYPE = np.dtype([("t_us", "<i8"), ("robot", "<i4"), ("x_m", "<f8"), ("y_m", "<f8"),
                        ("yaw_rad", "<f8"), ("vx_mps", "<f8"), ("vy_mps", "<f8")])


class Simulation:
    """World + event sensor (+ autopilot) stepped together.

    Args:
        world: the physics; its robots are drawn by the sensor.
        camera: ceiling camera geometry (sensor size, homography).
        dvs: pixel-model parameters.
        autopilot: drives the robots when given; otherwise motor powers come from outside
            (e.g. the robot emulators obeying the bridge).
        seed: seed of the sensor's randomness.
        truth_every: record truth every this many internal steps (2 -> 500 Hz at 1 ms).
    """

    def __init__(self, world: World, camera: CeilingCamera, dvs: DvsParams | None = None,
                 autopilot: Autopilot | None = None, seed: int = 0, truth_every: int = 2):
        self.world = world
        self.camera = camera
        self.sensor = DvsSensor(camera, world.robots, world.lighting, dvs, seed=seed)
        self.autopilot = autopilot
        self.step_us = self.sensor.params.step_us
        self.truth_every = max(1, int(truth_every))
        self.t_us = int(round(world.t * 1e6))
        self._k = 0
        self.sensor.reset(world.poses(), self.t_us)

    def run(self, n_steps: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Advance ``n_steps`` internal steps. Returns ``(events, is_signal, truth)``: events of
        the interval sorted by time (µs), their signal labels, and truth rows
        (:data:`TRUTH_DTYPE`) sampled every ``truth_every`` steps."""
        n = len(self.world.robots)
        dt = self.step_us * 1e-6
        poses = np.empty((n_steps, n, 3))
        times = np.empty(n_steps, dtype=np.int64)
        rows = []
        for s in range(n_steps):
            if self.autopilot is not None:
                self.autopilot.update(self.world.t)
            with self.world.lock:
                self.world.step(dt)
                self.t_us += self.step_us
                poses[s] = self.world.poses()
                vel = self.world.velocities() if self._k % self.truth_every == 0 else None
            times[s] = self.t_us
            if vel is not None:
                tr = np.empty(n, dtype=TRUTH_DTYPE)
                tr["t_us"], tr["robot"] = self.t_us, np.arange(n)
                tr["x_m"], tr["y_m"], tr["yaw_rad"] = poses[s, :, 0], poses[s, :, 1], poses[s, :, 2]
                tr["vx_mps"], tr["vy_mps"] = vel[:, 0], vel[:, 1]
                rows.append(tr)
            self._k += 1
        if n_steps == 0:
            return np.zeros(0, EVENT_DTYPE), np.zeros(0, bool), np.zeros(0, TRUTH_DTYPE)
        ev, sig = self.sensor.advance(poses, times)
        truth = np.concatenate(rows) if rows else np.zeros(0, TRUTH_DTYPE)
        return ev, sig, truth


def warm_up(world: World, camera: CeilingCamera, dvs: DvsParams | None = None) -> None:
    """Step a throw-away copy of ``world`` (same robots, lighting and camera, robots driving)
    for a few milliseconds and encode its events, so every numba kernel of the physics, the
    pixel model and the EVT 3.0 stream is compiled (or loaded from numba's on-disk cache)
    before ``arena sim`` says "running". On a fresh install that takes ~10 s of CPU, during
    which a running simulator would stall its robots' serial links and its camera."""
    from simulator.evt3 import Evt3Encoder

    twin = World(world.robots, arena_m=world.arena_m, lighting=world.lighting, seed=world.seed)
    for i in range(len(twin.robots)):
        twin.set_power(i, 400, 300)
    sim = Simulation(twin, camera, dvs, seed=0)
    enc = Evt3Encoder()
    for _ in range(3):
        ev, _, _ = sim.run(10)
        enc.encode(ev, until_us=sim.t_us)

"""Shared helpers of the robot bridge tests: a simulated world stepped in real time."""

from __future__ import annotations

import threading
import time
from contextlib import contextmanager

from simulator.world import RobotSpec, World


@contextmanager
def running_world(n: int = 1, seed: int = 0, starts=None):
    """A World with ``n`` robots stepped at ~1 kHz (sim time = real time) in a thread."""
    starts = starts or [(0.9, 0.6 + 0.4 * i, 1.5708) for i in range(n)]
    world = World([RobotSpec(f"r{i + 1}", (20, 20, 20), start=starts[i]) for i in range(n)], seed=seed)
    stop = threading.Event()

    def run():
        last = time.monotonic()
        while not stop.is_set():
            now = time.monotonic()
            world.step(now - last)
            last = now
            stop.wait(0.001)

    t = threading.Thread(target=run, daemon=True, name="world")
    t.start()
    try:
        yield world
    finally:
        stop.set()
        t.join()


def wait_for(cond, timeout: float, step: float = 0.002) -> bool:
    """Poll ``cond()`` until true (True) or ``timeout`` s (False)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(step)
    return bool(cond())

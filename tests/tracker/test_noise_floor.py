"""Background activity is not uniform: shot noise is densest over the dark floor around the mats
(and in dim corners). minPts must be set for the noisiest background, not its mean, or the noise
there clusters into robots."""

from __future__ import annotations

import numpy as np
import pytest

from arena.events import make_events
from tracker.detect import Detector, DetectorConfig


def _noise(rng, rate_hz, x0, x1, t1_us, width=640, height=480):
    n = rng.poisson(rate_hz * (x1 - x0) * height * t1_us * 1e-6)
    return rng.integers(x0, x1, n), rng.integers(0, height, n), rng.integers(0, 2, n), rng.integers(0, t1_us, n)


def _window(seed, floor_hz=8.0, mat_hz=1.0):
    """100 ms of noise: a dark floor band (the left 150 px and the right 150 px, as beside a
    square mat) at ``floor_hz`` per pixel, the mat between at ``mat_hz``."""
    rng = np.random.default_rng(seed)
    parts = [_noise(rng, floor_hz, 0, 150, 100_000), _noise(rng, mat_hz, 150, 490, 100_000),
             _noise(rng, floor_hz, 490, 640, 100_000)]
    x, y, p, t = (np.concatenate(a) for a in zip(*parts))
    order = np.argsort(t, kind="stable")
    return make_events(x[order], y[order], p[order], t[order])


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_noise_over_a_dark_floor_is_not_taken_for_robots(seed):
    ev = _window(seed)
    det = Detector(235.0, 640, 480, DetectorConfig(incremental=False))
    assert det.detect(ev, 100_000) == []
    # set for the typical (mat) cell, the floor's noise clusters into false robots
    typical = Detector(235.0, 640, 480, DetectorConfig(incremental=False, noise_quantile=0.5))
    assert seed > 0 and len(typical.detect(ev, 100_000)) > 0


def test_noise_quantile_is_checked():
    with pytest.raises(ValueError, match="noise_quantile"):
        DetectorConfig(noise_quantile=1.5).validate()

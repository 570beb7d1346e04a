"""Speed rewrites of the default detector's helpers (issue 22) give exactly what they replaced."""

from __future__ import annotations

import numpy as np
import pytest

from tracker.detect import _lowest_quantile


def _reference(counts: np.ndarray, q: float) -> float:
    """The detector's noise statistic before issue 22: np.quantile of the smallest 90 % of cells."""
    m = max(1, int(0.9 * counts.size))
    keep = np.partition(counts, max(0, m - 1))[:m]
    return float(np.quantile(keep, q))


@pytest.mark.parametrize("q", [0.0, 0.3, 0.5, 0.9, 0.95, 0.999, 1.0])
def test_lowest_quantile_is_numpys_quantile_bit_for_bit(q):
    rng = np.random.default_rng(7)
    checked = 0
    for size in (1, 2, 3, 7, 10, 11, 100, 567, 1000):
        for scale in (0, 1, 3, 20, 300):
            counts = rng.poisson(scale, size).astype(np.int64)
            counts[rng.integers(0, size, max(1, size // 20))] += rng.integers(0, 500)   # robot cells
            m = max(1, int(0.9 * counts.size))
            got = _lowest_quantile(counts, m, q)
            assert got == _reference(counts, q), (size, scale, q)
            checked += 1
    assert checked == 45

"""Start-up of ``arena track`` (issue 22): scipy.optimize and scipy.spatial are imported only by
what uses them. Each test runs a fresh interpreter (this one has imported everything)."""

from __future__ import annotations

import json
import subprocess
import sys


def _run(code: str) -> object:
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_fleet_tracker_assigns_without_importing_scipy_optimize():
    # scipy.optimize's __init__ imports linprog, minimize, scipy.sparse and scipy.spatial
    # (~0.25 s of CPU) for the one function the fleet tracker needs
    code = """
import json, sys
import tracker.pipeline                     # what `arena track` imports before its first slice
from tracker.fleet import FleetConfig, FleetTracker
from tracker.objects import Observation
at_import = sorted(m for m in sys.modules if m.startswith(("scipy.optimize", "scipy.spatial")))
ft = FleetTracker(FleetConfig())
for k in range(6):    # two robots driving: every step after the first assigns
    t = k * 10_000
    tracks = ft.update([Observation(x=0.5 + 0.003 * k, y=0.5, t_us=t),
                        Observation(x=1.2, y=0.8 - 0.003 * k, t_us=t)], t)
after = sorted(m for m in sys.modules if m.startswith("scipy.optimize"))
import numpy as np, scipy.optimize, tracker.fleet
cost = np.array([[4.0, 1.0, 3.0], [2.0, 0.0, 5.0], [3.0, 2.0, 2.0]])
same = [a.tolist() for a in tracker.fleet.linear_sum_assignment(cost)] == \\
       [a.tolist() for a in scipy.optimize.linear_sum_assignment(cost)]
print(json.dumps([at_import, after, sorted((tr.track_id, tr.hits) for tr in tracks), same]))
"""
    at_import, after, tracks, same = _run(code)
    assert at_import == []
    assert tracks == [[1, 6], [2, 6]]        # the same two tracks, updated at every step
    assert after == []
    assert same is True                      # scipy's own solver, loaded without its package


def test_idtrack_imports_scipy_spatial_when_it_builds_its_tree():
    code = """
import json, sys
from tracker.idtrack import IDTrack
from tracker.objects import Observation
at_import = "scipy.spatial" in sys.modules
tr = IDTrack(sigma=0.1)
ids = [[t.track_id for t in tr.update([Observation(x=0.5 + 0.01 * k, y=0.5, t_us=k), Observation(x=1.0, y=1.0, t_us=k)], k)]
       for k in range(3)]
print(json.dumps([at_import, ids, "scipy.spatial" in sys.modules]))
"""
    at_import, ids, after = _run(code)
    assert at_import is False
    assert ids == [[1, 2], [1, 2], [1, 2]]
    assert after is True

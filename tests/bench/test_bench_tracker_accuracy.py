"""Smoke tests of bench/bench_tracker_accuracy.py: unmarked robots with mixed shells by default,
pooled figures equal to groundtruth's own for one run, the targets, and a sweep axis the
simulator lacks printed as not available (tiny scenarios: 1 robot, 1 s)."""

from __future__ import annotations

import dataclasses
import importlib.util
import io
import math
import sys
from pathlib import Path

import pytest

from groundtruth.metrics import evaluate
from simulator.camera import shell_reflectance
from simulator.scenarios import COLOURS, Scenario, generate

BENCH = Path(__file__).resolve().parents[2] / "bench" / "bench_tracker_accuracy.py"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_tracker_accuracy", BENCH)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod   # its dataclasses look their module up
    spec.loader.exec_module(mod)
    yield mod
    sys.modules.pop(spec.name, None)


def test_scenarios_are_unmarked_with_dark_and_light_shells(bench):
    cells = bench.scenarios(quick=True)
    refl = sorted(shell_reflectance(c) for _, c in COLOURS)
    for cell in cells:
        assert all(sc.markers is False for sc in cell.scenarios), cell.label
        shells = [shell_reflectance(c) for sc in cell.scenarios for c in sc.colours[:sc.n_robots]]
        # every row sees the darkest shell and a light one (yellow or white: near the mats' 0.85)
        assert min(shells) == refl[0] and max(shells) > 0.5, (cell.label, shells)
    one = next(c for c in cells if c.label == "1 circle 1.0")
    firsts = [shell_reflectance(sc.colours[0]) for sc in one.scenarios]
    assert firsts == [refl[0], refl[len(refl) // 2], refl[-1]]
    assert all(sc.markers for c in bench.scenarios(quick=True, markers=True) for sc in c.scenarios)


@pytest.fixture(scope="module")
def one_run(bench):
    rec = generate(Scenario(1, "circle", 1.0, 1.0, seed=1, markers=False))
    tracks, _ = bench.run_tracker(rec, "fleet", "default")
    return evaluate(tracks, bench.truth_table(rec), gate_m=0.10)


def test_pool_of_one_run_is_its_scores_and_targets(bench, one_run):
    s = one_run
    assert s.n_tp > 0
    for p in (bench.pool([s]), bench.pool([s, s])):
        assert p.mae_cm == pytest.approx(s.mae_cm) and p.mota == pytest.approx(s.mota)
        assert p.heading_mae_deg == pytest.approx(s.heading_mae_deg)
        assert p.precision == pytest.approx(s.precision) and p.recall == pytest.approx(s.recall)
    sw = dataclasses.replace(s, id_switches=1)   # counts are summed over runs, MOTA from the sums
    two = bench.pool([sw, sw])
    assert two.id_switches == 2
    assert two.mota == pytest.approx(1 - (2 * s.n_fn + 2 * s.n_fp + 2) / (2 * s.n_gt))
    good = bench.Pooled(1, 1, 0.4, 1.0, 2.5, 0, 0.995, 0, 1.0, 1)
    assert bench.target_failures(good, "square") == []
    assert bench.target_failures(good, "circle") == ["hdg"]
    bad = bench.Pooled(1, 1, 0.6, 1.0, math.nan, 0, 0.98, 1, 1.0, 1)
    assert bench.target_failures(bad, "square") == ["MOTA", "IDsw", "MAE", "hdg"]


def test_sweep_prints_conditions_and_missing_axes(bench):
    base = [Scenario(1, "circle", 1.0, 1.0, seed=1, markers=False, colours=[(225, 225, 220)])]
    axes = [bench.Axis("nope", "no_such_field", [("x", 1)]),
            bench.Axis("markers", "markers", [("off", False)])]
    out = io.StringIO()
    res = bench.sweep(axes, base, ["fleet"], out=out)
    text = out.getvalue()
    assert "not available in this simulator (no Scenario.no_such_field)" in text
    assert res["nope"] == [] and len(res["markers"]) == 1
    legend = text.index("conditions:", text.index("'markers'"))
    assert "circle 100% power, 1 s" in text[legend:] and "seed 1" in text[legend:] and "shells white" in text[legend:]
    label, mode, p, fails = res["markers"][0]
    assert (label, mode) == ("off (base)", "fleet") and math.isfinite(p.mae_cm)   # the base value marked
    assert bench.flag(fails) in text.splitlines()[-2]

"""Smoke test of bench/bench_end_to_end.py with its smallest options on a tiny paper-format CSV
(2 robots, 1.2 s): the table has both rows with the counts of the tracks CSVs written, the paper's
extrapolation from its first windows, the conditions, and a finite positive ratio (no timings)."""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from arena.formats import write_events
from simulator.scenarios import Scenario, generate

BENCH = Path(__file__).resolve().parents[2] / "bench" / "bench_end_to_end.py"
# two processes (interpreter start, imports, scikit-learn) + a 1.2 s simulation: 8 s idle, 13 s at load 1.9 / 2 cores
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    d = tmp_path_factory.mktemp("e2e")
    rec = generate(Scenario(2, "circle", 1.0, 1.2, seed=1, stagger_s=0.05))
    write_events(d / "rec.csv", rec.events, rec.width, rec.height)
    (d / "cal.json").write_text(json.dumps(rec.calibration))
    out = d / "out"
    proc = subprocess.run([sys.executable, str(BENCH), "--csv", str(d / "rec.csv"),
                           "--calibration", str(d / "cal.json"), "--runs", "1", "--no-warmup",
                           "--paper-windows", "5", "--out-dir", str(out)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout, out, rec


def _row(text: str, name: str) -> list[str]:
    rows = [line.split() for line in text.splitlines() if line.split()[:1] == [name]]
    assert len(rows) == 1, text
    return rows[0]


def _counts(path: Path) -> tuple[int, int]:
    with open(path, newline="") as fh:
        times = [r[0] for r in list(csv.reader(fh))[1:]]
    return len(times), len(set(times))


def test_table_has_both_rows_and_a_finite_positive_ratio(run):
    text, out, _ = run
    ours, paper = _row(text, "ours"), _row(text, "paper")
    # pipeline, wall min, med, CPU min, med, steps, updates, rows, ms/update wall, CPU, ratio wall, ratio CPU
    assert len(ours) == len(paper) == 12, text
    assert ours[10] == "1.0x" and ours[11] == "1.0x"
    ratio = float(paper[10].rstrip("x"))
    assert math.isfinite(ratio) and ratio > 0
    assert float(paper[11].rstrip("x~")) > 0
    assert f"{ratio:.1f}x -> " in text.splitlines()[-1]
    # ms per update = median wall / updates
    assert float(ours[8]) == pytest.approx(1e3 * float(ours[2]) / int(ours[6]), rel=0.02, abs=0.01)


def test_counts_are_those_of_the_tracks_written(run):
    text, out, _ = run
    ours, paper = _row(text, "ours"), _row(text, "paper")
    rows, updates = _counts(out / "ours_tracks.csv")
    assert (int(ours[7]), int(ours[6])) == (rows, updates) and 0 < updates < rows   # 2 robots: rows > updates
    assert 119 <= int(ours[5]) <= 121          # 1.2 s of 10 ms slices
    # the paper ran its first 5 of 12 windows (0..1.2 s) and is extrapolated per window
    assert "RUN ON THE FIRST 5 OF 12 WINDOWS" in text and paper[11].endswith("~")
    p_rows, p_updates = _counts(out / "paper_tracks.csv")
    assert 0 < p_updates <= 5
    assert int(paper[5]) == 12
    assert (int(paper[6]), int(paper[7])) == (round(p_updates * 12 / 5), round(p_rows * 12 / 5))


def test_conditions_are_printed(run):
    text, _, rec = run
    assert "load average (1/5/15 min)" in text and " cores (" in text
    n = rec.events.size
    dur = (int(rec.events["t"][-1]) - int(rec.events["t"][0])) / 1e6
    assert f"{n} events over {dur:.2f} s = {n / dur / 1e3:.0f} k ev/s" in text
    assert "given with --csv" in text
    assert "pandas.read_csv" in text or "numpy.loadtxt" in text

"""The paper study runner on the real simulator and tracker (short plans), in-process and as
`arena experiment` (subprocess)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from demo.experiment import PARTS, StudyPlan, run_paper_study, scenario_seed

TINY = StudyPlan(duration_s=1.0, minpts_full=(150, 250), minpts_partial=(30, 60), ta_ms=(100,),
                 table_robots=(1,), table_powers=(100,), lighting_robots=(1,))


def test_every_part_writes_its_section_plots_and_json(tmp_path):
    study = run_paper_study(tmp_path, seed=3, parts=PARTS, progress=False, plan=TINY)
    assert not study.failures, study.failures
    md = (tmp_path / "report.md").read_text()
    for heading in ("## minPts sweep", "## Accumulation time", "## Robots x pattern x power",
                    "## Lighting"):
        assert heading in md
    assert "| 1 | circle | paper | 1 | 1 | 1.22 | 1 |" in md  # the paper's numbers beside ours
    assert "| dimmed | 1 | paper | 1 | 1 | 3.01 | 1 |" in md
    for png in ("minpts.png", "ta.png", "table.png"):
        assert (tmp_path / png).read_bytes()[:4] == b"\x89PNG"
    data = json.loads((tmp_path / "study.json").read_text())
    # t_a: 2 patterns x 2 trackers; table: 2 patterns x 2 trackers; lighting: 3 levels x 2 trackers
    assert len(data["runs"]) == 4 + 4 + 6
    assert {r["tracker"] for r in data["runs"]} == {"idtrack", "fleet"}
    assert len(data["minpts"]) == 4 and data["minpts"][0]["minpts"] == [150, 250]
    one = next(r for r in data["runs"] if r["part"] == "table" and r["pattern"] == "circle")
    assert one["scores"]["n_gt"] > 50 and 0 <= one["scores"]["recall"] <= 1
    # the full-light lighting row is the table's run of the same scenario, not a second run
    full = [r for r in data["runs"] if r["part"] == "lighting" and r["lighting"] == "full"]
    table_sq = [r for r in data["runs"] if r["part"] == "table" and r["pattern"] == "square"]
    assert [r["scores"] for r in full] == [r["scores"] for r in table_sq]


def test_runs_are_reproducible_from_the_seed(tmp_path):
    plan = StudyPlan(duration_s=1.2, minpts_full=(), minpts_partial=(), ta_ms=(), table_robots=(1,),
                     table_powers=(100,), lighting_robots=())
    a = run_paper_study(tmp_path / "a", seed=5, parts=("table",), progress=False, plan=plan)
    b = run_paper_study(tmp_path / "b", seed=5, parts=("table",), progress=False, plan=plan)
    assert [r["scores"] for r in a.runs] == [r["scores"] for r in b.runs]
    assert scenario_seed(5, 1, "circle", 100, "full") != scenario_seed(6, 1, "circle", 100, "full")
    assert scenario_seed(5, 1, "circle", 100, "full") != scenario_seed(5, 2, "circle", 100, "full")


def test_a_failing_run_is_reported_and_the_study_goes_on(tmp_path):
    # t_a = 0 is refused by the tracker's pipeline: those runs fail, the others complete
    plan = StudyPlan(duration_s=1.0, minpts_full=(), minpts_partial=(), ta_ms=(0, 100),
                     table_robots=(), table_powers=(), lighting_robots=())
    study = run_paper_study(tmp_path, seed=1, parts=("ta",), progress=False, plan=plan)
    assert len(study.failures) == 4 and "accumulation time" in study.failures[0]["error"]
    assert len(study.runs) == 4
    assert "## Failed runs" in (tmp_path / "report.md").read_text()


def arena(*args, timeout=240):
    return subprocess.run([sys.executable, "-m", "arena", *map(str, args)], capture_output=True,
                          text=True, timeout=timeout)


@pytest.mark.slow
def test_cli_quick_study_writes_its_report(tmp_path):
    r = arena("experiment", "paper", "--out", tmp_path, "--quick", "--only", "table", "--seed", "2",
              "--seconds", "1.2", "--no-progress")
    assert r.returncode == 0, r.stderr
    assert "report written to" in r.stdout
    md = (tmp_path / "report.md").read_text()
    assert "### 100 % power" in md and "| 2 | square | fleet |" in md
    assert "1.2 s per scenario" in md and json.loads((tmp_path / "study.json").read_text())["plan"]["duration_s"] == 1.2


def test_cli_rejects_bad_options(tmp_path):
    r = arena("experiment", "paper", "--out", tmp_path, "--seconds", "0.1")
    assert r.returncode == 2 and "--seconds must be 0.5-120" in r.stderr
    r = arena("experiment", "paper", "--out", tmp_path, "--only", "tables")
    assert r.returncode == 2 and "unknown part(s) tables" in r.stderr and "Traceback" not in r.stderr
    blocker = tmp_path / "file"
    blocker.write_text("x")
    r = arena("experiment", "paper", "--out", blocker / "sub", "--quick")
    assert r.returncode == 2 and "cannot create output folder" in r.stderr

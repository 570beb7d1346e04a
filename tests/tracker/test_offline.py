"""`arena track --input`: CSV columns and units on a simulated recording, both methods."""

from __future__ import annotations

import csv
import json
import math
import subprocess

import numpy as np
import pytest

from arena.formats import write_events
from arena.formats.tables import TRUTH_DTYPE, read_tracks_csv
from groundtruth.metrics import evaluate
from tests.conftest import arena_cmd

HEADER = ["t_us", "track_id", "robot", "x_m", "y_m", "yaw_rad", "vx_mps", "vy_mps", "u_px", "v_px", "state",
          "n_events", "host_ns"]


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    from simulator.scenarios import Scenario, generate

    rec = generate(Scenario(n_robots=2, pattern="circle", power=1.0, duration_s=2.5, seed=21))
    d = tmp_path_factory.mktemp("rec")
    write_events(d / "rec.raw", rec.events, rec.width, rec.height)
    (d / "calib.json").write_text(json.dumps(rec.calibration))
    truth = np.empty(rec.truth.size, TRUTH_DTYPE)
    for k in ("t_us", "x_m", "y_m", "yaw_rad", "vx_mps", "vy_mps"):
        truth[k] = rec.truth[k]
    truth["robot"] = np.asarray(rec.robot_names)[rec.truth["robot"]]
    return d, truth


@pytest.mark.parametrize("mode", [[], pytest.param(["--tracker", "idtrack", "--detector", "paper"],
                                                   marks=pytest.mark.slow)], ids=["fleet", "paper"])
def test_offline_csv_columns_units_and_accuracy(recording, mode):
    d, truth = recording
    out = d / f"tracks{len(mode)}.csv"
    r = subprocess.run(arena_cmd("track", "--input", str(d / "rec.raw"), "--calibration", str(d / "calib.json"),
                                 "--tracks-out", str(out), *mode), capture_output=True, text=True, timeout=240)
    assert r.returncode == 0, r.stderr
    with out.open() as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == HEADER
    body = rows[1:]
    assert len(body) > 200
    t = np.array([int(r[0]) for r in body])
    assert np.all(np.diff(t) >= 0) and np.all(np.diff(np.unique(t)) % 10_000 == 0)   # 10 ms slices
    x = np.array([float(r[3]) for r in body])
    y = np.array([float(r[4]) for r in body])
    assert x.min() > 0 and x.max() < 1.83 and y.min() > 0 and y.max() < 1.83                  # metres
    yaw = np.array([float(r[5]) for r in body if r[5]])
    assert yaw.size > 0.8 * len(body) and np.all(np.abs(yaw) <= math.pi)                      # radians
    assert {r[10] for r in body} <= {"confirmed", "coasting", "tentative"}
    assert all(int(r[11]) >= 0 for r in body)
    assert all(r[12] == "" for r in body)   # a file read offline has no host capture time
    scores = evaluate(read_tracks_csv(out), truth, gate_m=0.10)
    assert scores.id_switches == 0 and scores.mota > 0.95
    if not mode:  # the default method: sub-centimetre, heading within a few degrees, speeds in m/s
        assert scores.mae_cm < 1.2 and scores.heading_mae_deg < 5
        v = np.hypot([float(r[6]) for r in body], [float(r[7]) for r in body])
        assert 0.2 < np.median(v) < 0.6


def test_offline_bad_inputs_are_clear_messages(recording, tmp_path):
    d, _ = recording
    cases = [
        (["--input", str(tmp_path / "missing.raw"), "--calibration", str(d / "calib.json"),
          "--tracks-out", str(tmp_path / "t.csv")], "no such file"),
        (["--input", str(d / "rec.raw"), "--calibration", str(d / "rec.raw"), "--tracks-out", str(tmp_path / "t.csv")],
         "JSON"),
        (["--input", str(d / "rec.raw"), "--tracks-out", str(tmp_path / "t.csv")], "--calibration"),
        (["--input", str(d / "rec.raw"), "--calibration", str(d / "calib.json")], "--tracks-out"),
        (["--input", str(d / "rec.raw"), "--calibration", str(d / "calib.json"), "--tracks-out",
          str(tmp_path / "t.csv"), "--slice-ms", "0"], "> 0"),
    ]
    for args, msg in cases:
        r = subprocess.run(arena_cmd("track", *args), capture_output=True, text=True, timeout=60)
        assert r.returncode != 0 and msg in r.stderr and "Traceback" not in r.stderr, (args, r.stderr)

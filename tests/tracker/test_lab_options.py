"""`arena track` honours the lab file's [services.tracker]: the method it asks for is the one that
runs (offline and live), a flag wins over it, and a wrong value is a clear error."""

from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import subprocess
import threading
import time
from types import SimpleNamespace
from unittest import mock

import pytest

from arena.formats import write_events
from arena.messages import Status, decode
from arena.session import open_session
from tests.conftest import arena_cmd

ENV = {**os.environ, "PYTHONUNBUFFERED": "1"}
ENV.pop("ARENA_LAB", None)


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    from simulator.scenarios import Scenario, generate

    rec = generate(Scenario(n_robots=2, pattern="circle", power=1.0, duration_s=0.6, seed=21))
    d = tmp_path_factory.mktemp("rec")
    write_events(d / "rec.raw", rec.events, rec.width, rec.height)
    (d / "calib.json").write_text(json.dumps(rec.calibration))
    return d


def _track(d, *args, calibration: bool = True) -> tuple[SimpleNamespace, list[dict]]:
    """``arena track --input`` in this process (its own parser, run and exit codes; a subprocess
    would spend most of its time importing and loading kernels): its exit status and stderr."""
    from arena.cli import main

    out = d / "tracks.csv"
    if out.exists():
        out.unlink()
    cal = ["--calibration", str(d / "calib.json")] if calibration else []
    err = io.StringIO()
    with mock.patch.dict(os.environ), contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        os.environ.pop("ARENA_LAB", None)
        try:
            rc = main(["track", "--input", str(d / "rec.raw"), *cal, "--tracks-out", str(out), *args])
        except SystemExit as exc:
            rc = exc.code if isinstance(exc.code, int) else int(exc.code is not None)
    rows = list(csv.DictReader(out.open())) if out.exists() else []
    return SimpleNamespace(returncode=rc, stderr=err.getvalue()), rows


def test_lab_tracker_idtrack_runs_idtrack_and_a_flag_wins(recording, tmp_path):
    d = recording
    lab = tmp_path / "lab.toml"
    lab.write_text('[services.tracker]\ntracker = "idtrack"\naccumulation_ms = 60\n')

    r, rows = _track(d, "--lab", str(lab))
    assert r.returncode == 0, r.stderr
    assert "idtrack tracker, default detector:" in r.stderr, r.stderr
    assert len(rows) > 20
    # IDTrack (the paper's Algorithm 1) estimates no velocity and confirms every node at once;
    # the fleet tracker's Kalman filter gives velocities
    assert all(row["vx_mps"] == "" and row["vy_mps"] == "" for row in rows)
    assert {row["state"] for row in rows} == {"confirmed"}

    r, rows = _track(d, "--lab", str(lab), "--tracker", "fleet")  # the flag wins over the lab file
    assert r.returncode == 0, r.stderr
    assert "fleet tracker, default detector:" in r.stderr, r.stderr
    assert sum(1 for row in rows if row["vx_mps"] != "") > 0.5 * len(rows) > 10

    r, _ = _track(d)  # no lab file: the default method
    assert r.returncode == 0 and "fleet tracker, default detector:" in r.stderr, r.stderr

    # offline too, the lab file gives the camera's calibration (a file it names) and its options
    lab.write_text(f'[[cameras]]\nname = "cam0"\ncalibration = "{d / "calib.json"}"\n'
                   '[services.tracker]\ntracker = "idtrack"\n')
    r, rows = _track(d, "--lab", str(lab), calibration=False)
    assert r.returncode == 0 and "idtrack tracker, default detector:" in r.stderr, r.stderr
    assert rows and all(row["vx_mps"] == "" for row in rows)


def test_lab_accumulation_ms_is_used_and_the_flag_wins(recording, tmp_path):
    """t_a decides when the first track appears (a window must hold enough events): the lab's
    value is the one used, and --accumulation-ms overrides it."""
    d = recording
    lab = tmp_path / "lab.toml"
    first = {}
    for acc in (20, 200):
        lab.write_text(f'[services.tracker]\ntracker = "idtrack"\naccumulation_ms = {acc}\n')
        r, rows = _track(d, "--lab", str(lab))
        assert r.returncode == 0, r.stderr
        first[acc] = [row["n_events"] for row in rows[:5]]
    assert first[20] != first[200]  # a 10x longer window holds more events per detection
    assert max(map(int, first[200])) > max(map(int, first[20]))
    lab.write_text('[services.tracker]\ntracker = "idtrack"\naccumulation_ms = 200\n')
    r, rows = _track(d, "--lab", str(lab), "--accumulation-ms", "20")
    assert r.returncode == 0, r.stderr
    assert [row["n_events"] for row in rows[:5]] == first[20]


def test_lab_tracker_option_mistakes_are_one_clear_line(recording, tmp_path):
    d = recording
    for text, needle in [('tracker = "kalman"\n', "services.tracker.tracker: expected one of fleet, idtrack"),
                         ("accumulation_ms = -5\n", "services.tracker.accumulation_ms: expected a finite number > 0"),
                         ("accumulation = 100\n", "services.tracker: unknown key(s) accumulation; known: tracker")]:
        lab = tmp_path / "lab.toml"
        lab.write_text("[services.tracker]\n" + text)
        r, _ = _track(d, "--lab", str(lab))
        assert r.returncode == 2, r.stderr
        assert f"arena track: {lab}: {needle}" in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_live_tracker_reports_the_lab_method_in_its_status(router, tmp_path, recording):
    lab = tmp_path / "lab.toml"
    lab.write_text('[services.tracker]\ntracker = "idtrack"\n')
    statuses: list[Status] = []
    lock = threading.Lock()

    def on_status(sample):
        with lock:
            statuses.append(decode(bytes(sample.payload)))

    with open_session(router.settings("client")) as s:
        s.declare_subscriber("arena/status/tracker/tracker-cam0", on_status)
        proc = subprocess.Popen(arena_cmd("track", "--camera", "cam0", "--calibration", str(recording / "calib.json"),
                                          "--lab", str(lab), "-m", "client", *router.args),
                                env=ENV, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        try:
            deadline = time.monotonic() + 90
            while time.monotonic() < deadline and proc.poll() is None:
                with lock:
                    if statuses:
                        break
                time.sleep(0.1)
            assert proc.poll() is None, "the tracker died"
        finally:
            proc.terminate()
            _, err = proc.communicate(timeout=20)
    with lock:
        assert statuses, f"no status within 90 s: {err}"
        gauges = statuses[-1].gauges
    assert gauges["tracker"] == "idtrack" and gauges["detector"] == "default", gauges

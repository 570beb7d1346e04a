"""What an outside tester tried and got a traceback, a false "written" or an absurd value accepted
for: each is now one line, exit 2, before anything starts (subprocesses of the real commands)."""

from __future__ import annotations

import subprocess
import sys

import pytest

PTS = ["112,431:0,0", "528,431:1.83,0", "528,15:1.83,1.83", "112,15:0,1.83"]


def arena(*args, timeout=60):
    return subprocess.run([sys.executable, "-m", "arena", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout)


@pytest.mark.parametrize("args, message", [
    (["bridge", "estop", "all", "--timeout", "nan"], "expected seconds in (0, 600]"),
    (["bridge", "estop", "all", "--timeout", "-1"], "expected seconds in (0, 600]"),
    (["status", "--wait", "inf"], "expected seconds in [0, 600]"),
    (["demo", "--duration", "nan"], "--duration must be a positive number of seconds, got nan"),
    (["calibrate", "--size", "99999999x99999999", "--points", *PTS, "-o", "x.json"], "1-65535 each"),
    (["calibrate", "--size", "640x480", "--points", PTS[0], PTS[1], "112,15:1.83,1.83", "528,15:0,1.83",
      "-o", "x.json"], "the calibration points cross"),
    (["sim", "--calibration-out", "nodir/c.json", "--duration", "1"], "the folder nodir does not exist"),
    (["sim", "--truth-csv", ".", "--duration", "1"], "is a folder: give a file name"),
])
def test_bad_values_are_one_line_and_exit_2(tmp_path, args, message, monkeypatch):
    monkeypatch.chdir(tmp_path)
    r = arena(*args)
    assert r.returncode == 2 and message in r.stderr and "Traceback" not in r.stderr, (r.returncode, r.stderr[-2000:])
    assert not (tmp_path / "x.json").exists()


def test_calibrate_says_when_it_could_not_write_the_preview(tmp_path):
    r = arena("calibrate", "--size", "640x480", "--points", *PTS, "-o", tmp_path / "c.json",
              "--preview", tmp_path / "nodir" / "p.png")
    assert r.returncode == 2 and "cannot write the preview" in r.stderr and "Traceback" not in r.stderr, r.stderr
    r = arena("calibrate", "--size", "640x480", "--points", *PTS, "-o", tmp_path / "c.json", "--preview", tmp_path)
    assert r.returncode == 2 and "cannot write the preview" in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_track_refuses_a_camera_height_calibrate_would_refuse(tmp_path):
    cal = tmp_path / "c.json"
    assert arena("calibrate", "--size", "640x480", "--points", *PTS, "-o", cal).returncode == 0
    (tmp_path / "ev.csv").write_text("x,y,p,t\n1,1,1,10\n")
    r = arena("track", "--input", tmp_path / "ev.csv", "--calibration", cal, "--tracks-out", tmp_path / "t.csv",
              "--camera-height-m", "0.1")
    assert r.returncode == 2 and "--camera-height-m must be 0.3-20 m" in r.stderr, r.stderr

"""Which webcam ground truth `arena demo` runs: by colour on unmarked shells (the default, as the
lab's robots), by ArUco markers with ``--markers``; a shell too light for colour is refused at
start; the verdict, the printed results and the report say which one was used."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from demo import cli as demo_cli
from demo.verdict import verdict


def _parse(*argv: str) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    demo_cli.register(p.add_subparsers())
    return p.parse_args(["demo", *argv])


def _pairs(args: list[str], flag: str) -> list[str]:
    return [args[i + 1] for i, a in enumerate(args) if a == flag]


def test_colour_ground_truth_by_default_and_markers_when_asked():
    args = _parse("--robots", "4")
    assert args.markers is False
    gt = demo_cli._groundtruth_args(4, args.markers)
    assert gt[:2] == ["--detector", "hsv"] and "--marker" not in gt
    assert _pairs(gt, "--robot") == ["black0=#191919", "yellow1=#f0d71e", "red2=#c82323", "blue3=#234bc8"]

    args = _parse("--robots", "4", "--markers")
    assert args.markers is True
    gt = demo_cli._groundtruth_args(4, args.markers)
    assert gt[:2] == ["--detector", "aruco"] and "--robot" not in gt
    assert _pairs(gt, "--marker") == ["0=black0", "1=yellow1", "2=red2", "3=blue3"]


def test_the_simulator_gets_markers_only_with_markers(tmp_path):
    run = demo_cli._Run(tmp_path, "tcp/127.0.0.1:1", 2, 3, 4, ["black0"])
    assert "--markers" not in demo_cli._sim_cmd(run, _parse("--robots", "1"))
    assert "--markers" in demo_cli._sim_cmd(run, _parse("--robots", "1", "--markers"))


def test_a_near_white_shell_without_markers_stops_the_demo_at_start(tmp_path, capsys):
    args = _parse("--robots", "6", "--out", str(tmp_path))
    assert demo_cli.run(args) == 2
    err = capsys.readouterr().err
    assert "white5 cannot be found by colour" in err and "too close to the white mats" in err, err
    assert "--markers" in err and "at most 5 robots" in err, err
    assert not list(tmp_path.iterdir())          # stopped before anything started
    assert demo_cli._usage_error(_parse("--robots", "6", "--markers")) is None
    assert demo_cli._usage_error(_parse("--robots", "5")) is None


def test_verdict_needs_a_webcam_ground_truth_that_found_the_robots():
    base = dict(exit_codes={}, manifests=[{"robot": "a", "status": "finished"}], robots=1,
                sim_realtime={"worst_lag_s": 0.1}, windows={"edge_dropped": 0}, truth_rows=10,
                scores={"n_gt": 10})
    assert verdict(**base, webcam={"recall": 0.99}, webcam_method="colour") == (True, [])
    ok, p = verdict(**base, webcam={"recall": 0.2}, webcam_method="colour")
    assert not ok and p == ["the webcam ground truth (colour) found the robots in only 20% of their positions "
                            "(under 50%): scoring against it would measure little; see logs/groundtruth.log"]
    ok, p = verdict(**base, webcam=None, webcam_method="markers")
    assert not ok and p[0].startswith("no webcam ground truth (markers): groundtruth.csv is missing")


@pytest.mark.parametrize("markers", [False, True])
def test_results_and_report_say_which_ground_truth(tmp_path, capsys, markers):
    from arena.formats.tables import TRACK_DTYPE, write_tracks_csv

    run = tmp_path / "demo-x"
    (run / "telemetry").mkdir(parents=True)
    (run / "logs").mkdir()
    t = np.arange(100) * 10_000
    x = 0.5 + 0.002 * np.arange(100)
    tracks = np.zeros(100, TRACK_DTYPE)
    tracks["t_us"], tracks["track_id"], tracks["robot"], tracks["state"] = t, "1", "black0", "confirmed"
    tracks["x_m"], tracks["y_m"] = x, 0.5
    write_tracks_csv(run / "tracks.csv", tracks)
    rows = "".join(f"{ti},black0,{xi:.4f},0.5,0.0,0.2,0.0\n" for ti, xi in zip(t, x))
    (run / "truth.csv").write_text("t_us,robot,x_m,y_m,yaw_rad,vx_mps,vy_mps\n" + rows)
    cam = "".join(f"{ti},black0,{xi + 0.003:.4f},0.5,0.0,0,0,{'aruco' if markers else 'hsv'}\n"
                  for ti, xi in zip(t[::4], x[::4]))
    (run / "groundtruth.csv").write_text("t_us,robot,x_m,y_m,yaw_rad,u_px,v_px,detector\n" + cam)
    (run / "logs" / "groundtruth.log").write_text(
        "arena groundtruth: 25 frames, 25 detections, robots seen: black0; "
        "headings: 20 from the front mark, 4 from motion, 1 unknown\n" if not markers else "")
    args = argparse.Namespace(robots=1, mission="circle", power=1.0, lighting="full", duration=1.0, seed=0,
                              tracker="fleet", control="closed", view_port=8080, markers=markers)
    summary = demo_cli._finish(run, args, 1.0, {}, {})
    kind = "markers" if markers else "colour"
    assert summary["groundtruth"]["method"] == kind and summary["webcam"]["method"] == kind
    assert summary["webcam"]["recall"] > 0.9 and abs(summary["webcam"]["mae_cm"] - 0.3) < 0.01, summary["webcam"]
    assert json.loads((run / "summary.json").read_text())["groundtruth"]["method"] == kind
    out = capsys.readouterr().out
    line = next(ln for ln in out.splitlines() if ln.startswith("webcam ground truth by "))
    assert line.startswith(f"webcam ground truth by {kind} (") and "MAE 0.30 cm" in line, line
    report = (run / "report.md").read_text()
    assert f"Webcam ground truth by {kind}." in report
    section = report.split("## Webcam ground truth")[1]
    if markers:
        assert "by markers: ArUco markers" in section and "Headings:" not in section
        assert "shells with ArUco markers" in report
    else:
        assert "by colour: colour blobs" in section and "dark front window strip" in section
        assert summary["groundtruth"]["headings"] == {"front_mark": 20, "motion": 4, "unknown": 1}
        assert "Headings: 20 from the front mark, 4 from motion, 1 unknown." in section
        assert "headings: 20 from the front mark, 4 from motion, 1 unknown" in line
        assert "shells without markers" in report

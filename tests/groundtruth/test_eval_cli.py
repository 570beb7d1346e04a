"""`arena eval` on files, as a user runs it (subprocess), and the readers' errors."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from arena.formats.tables import (
    TRACK_DTYPE, TRUTH_DTYPE, CsvFormatError, read_tracks_csv, read_truth_csv, write_tracks_csv, write_truth_csv,
)

TRACK_HEADER = "t_us,track_id,robot,x_m,y_m,yaw_rad,vx_mps,vy_mps,u_px,v_px,state,n_events"


def arena(*args, timeout=120):
    return subprocess.run([sys.executable, "-m", "arena", *map(str, args)], capture_output=True,
                          text=True, timeout=timeout)


@pytest.fixture()
def files(tmp_path):
    """Two robots on circles for 2 s; truth at 200 Hz, tracks at 100 Hz with a 1 cm offset and one
    id switch on robot b at 1 s."""
    truth, tracks = [], []
    for k in range(400):
        t = k * 5000
        for r, (cx, phase) in {"zumo1": (0.6, 0.0), "zumo2": (1.2, 1.0)}.items():
            a = phase + 0.46 / 0.3 * t * 1e-6
            x, y = cx + 0.3 * np.cos(a), 0.9 + 0.3 * np.sin(a)
            yaw = (a + np.pi / 2 + np.pi) % (2 * np.pi) - np.pi
            truth.append((t, r, x, y, yaw, -0.46 * np.sin(a), 0.46 * np.cos(a)))
            if k % 2 == 0:
                tid = "1" if r == "zumo1" else ("2" if t < 1_000_000 else "5")
                tracks.append((t, tid, "", x + 0.01, y, yaw + np.radians(3), np.nan, np.nan, np.nan,
                               np.nan, "confirmed", 120))
    tp, gp = tmp_path / "tracks.csv", tmp_path / "truth.csv"
    write_tracks_csv(tp, np.array(tracks, dtype=TRACK_DTYPE))
    write_truth_csv(gp, np.array(truth, dtype=TRUTH_DTYPE))
    return tp, gp


def test_csv_round_trip(files):
    tp, gp = files
    tr = read_tracks_csv(tp)
    gt = read_truth_csv(gp)
    assert len(tr) == 400 and len(gt) == 800
    assert set(tr["track_id"]) == {"1", "2", "5"} and tr["n_events"][0] == 120
    assert np.isnan(tr["vx_mps"]).all() and set(gt["robot"]) == {"zumo1", "zumo2"}


def test_eval_prints_table_and_writes_json_and_report(files, tmp_path):
    tp, gp = files
    out_json, rep = tmp_path / "s.json", tmp_path / "rep"
    r = arena("eval", "--tracks", tp, "--truth", gp, "--json", out_json, "--report", rep)
    assert r.returncode == 0, r.stderr
    assert "MOTA" in r.stdout and "IDF1" in r.stdout and "zumo2" in r.stdout
    s = json.loads(out_json.read_text())["scores"]
    assert s["id_switches"] == 1 and s["n_fp"] == 0 and s["n_fn"] == 0
    assert s["mae_cm"] == pytest.approx(1.0, abs=1e-3)
    assert s["heading_mae_deg"] == pytest.approx(3.0, abs=1e-3)
    assert s["mota"] == pytest.approx(1 - 1 / s["n_gt"])
    assert s["per_robot"]["zumo2"]["id_switches"] == 1
    md = (rep / "report.md").read_text()
    assert "![trajectories](trajectories.png)" in md and "| MOTA |" in md
    for png in ("trajectories.png", "errors.png"):
        data = (rep / png).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000
    assert json.loads((rep / "scores.json").read_text())["scores"]["id_switches"] == 1


def test_eval_gate_option_changes_matching(files):
    tp, gp = files
    r = arena("eval", "--tracks", tp, "--truth", gp, "--gate-cm", "0.5")
    assert r.returncode == 0, r.stderr
    assert "recall             0.0000" in r.stdout  # every track is 1 cm off


@pytest.mark.parametrize("case, message", [
    ("missing", "not found"),
    ("empty", "is empty"),
    ("header", "header lacks column(s) x_m, y_m"),
    ("value", "line 2, column x_m: cannot read 'abc'"),
])
def test_eval_bad_input_gives_a_clear_error(files, tmp_path, case, message):
    tp, gp = files
    bad = tmp_path / "bad.csv"
    if case == "empty":
        bad.write_text("")
    elif case == "header":
        bad.write_text("t_us,track_id,xx,yy\n0,1,0.1,0.2\n")
    elif case == "value":
        bad.write_text(TRACK_HEADER + "\n0,1,,abc,0.5,,,,,,,\n")
    r = arena("eval", "--tracks", bad, "--truth", gp)
    assert r.returncode == 2
    assert message in r.stderr and "Traceback" not in r.stderr


def test_eval_truth_without_rows_is_an_error(files, tmp_path):
    tp, _ = files
    gp = tmp_path / "t.csv"
    gp.write_text("t_us,robot,x_m,y_m,yaw_rad\n")
    r = arena("eval", "--tracks", tp, "--truth", gp)
    assert r.returncode == 2 and "no rows" in r.stderr


def test_readers_raise_one_error_type(tmp_path):
    p = tmp_path / "g.csv"
    p.write_text("t_us,robot,x_m,y_m\n0,,0.1,0.2\n")
    with pytest.raises(CsvFormatError, match="empty robot name"):
        read_truth_csv(p)
    with pytest.raises(CsvFormatError, match="not found"):
        read_tracks_csv(tmp_path / "nope.csv")


def test_webcam_ground_truth_format_is_accepted(tmp_path):
    p = tmp_path / "gt.csv"
    p.write_text("t_us,robot,x_m,y_m,yaw_rad,u_px,v_px,detector\n"
                 "0,zumo1,0.5,0.5,0.1,320,240,aruco\n41667,zumo1,0.51,0.5,,321,240,hsv\n")
    gt = read_truth_csv(p)
    assert len(gt) == 2 and np.isnan(gt["yaw_rad"][1]) and gt["x_m"][1] == pytest.approx(0.51)


@pytest.mark.parametrize("which", ["tracks", "truth"])
def test_eval_on_a_binary_file_is_one_clear_line(files, tmp_path, which):
    tp, gp = files
    raw = tmp_path / "events.csv"   # e.g. a recording given by mistake: a text header, then binary words
    raw.write_bytes(b"% evt 3.0\n% format EVT3\n" + bytes(range(128, 256)) * 40)
    r = arena("eval", "--tracks", raw if which == "tracks" else tp, "--truth", raw if which == "truth" else gp)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert f"{which} file {raw} is not a text CSV (byte 0x80 is not UTF-8)" in r.stderr, r.stderr


def test_eval_with_no_ground_truth_in_the_tracks_span_prints_na_and_exits_1(files, tmp_path):
    tp, gp = files
    later = tmp_path / "later.csv"      # truth of another run: rows, but none while the tracks were made
    gt = read_truth_csv(gp)
    gt["t_us"] += 10_000_000
    write_truth_csv(later, gt)
    out_json = tmp_path / "s.json"
    r = arena("eval", "--tracks", tp, "--truth", later, "--json", out_json)
    assert r.returncode == 1, r.stdout + r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "nothing measured: no frame inside the truth's time span" in r.stderr, r.stderr
    for metric in ("MOTA", "IDF1", "HOTA", "MAE (cm)"):
        line = next(ln for ln in r.stdout.splitlines() if ln.startswith(metric))
        assert line.split()[-1] == "n/a", line
    s = json.loads(out_json.read_text())["scores"]
    assert s["n_gt"] == 0 and s["mota"] is None and s["idf1"] is None and s["hota"] is None, s


# ----------------------------------------------------------------------------------------------
# motion capture as ground truth: a rosbag2 of PoseStamped on another clock and in another frame


@pytest.fixture(scope="module")
def sim_run(tmp_path_factory):
    """The simulator's exact truth of a short 2-robot scenario and tracker-like tracks made from
    it (every 10 ms, 2 mm noise, robots named)."""
    from simulator.scenarios import Scenario, generate
    from test_mocap import tracks_from_truth

    rec = generate(Scenario(n_robots=2, pattern="circle", power=1.0, duration_s=6.0, seed=7))
    truth = np.empty(rec.truth.size, dtype=TRUTH_DTYPE)
    for name in ("t_us", "x_m", "y_m", "yaw_rad", "vx_mps", "vy_mps"):
        truth[name] = rec.truth[name]
    truth["robot"] = np.asarray(rec.robot_names, dtype=object)[rec.truth["robot"]]
    d = tmp_path_factory.mktemp("mocap")
    tracks = tracks_from_truth(truth, named=True)
    write_tracks_csv(d / "tracks.csv", tracks)
    write_truth_csv(d / "truth.csv", truth)
    return d, truth, tracks


def test_eval_scores_a_mocap_bag_with_unknown_offset_and_frame(sim_run, tmp_path):
    import math

    from groundtruth.mocap import Transform2D
    from test_mocap import to_mocap, write_pose_bag

    d, truth, _ = sim_run
    frame = Transform2D(math.radians(30), 0.5, -0.2, 1.0)
    offset_us = -(1_700_000_000_000_000 + 123_400)      # mocap on the wall clock, 123.4 ms off the second
    bag = write_pose_bag(tmp_path / "mocap_bag", to_mocap(truth, frame, offset_us))
    out, direct = tmp_path / "mocap.json", tmp_path / "direct.json"
    r = arena("eval", "--tracks", d / "tracks.csv", "--truth", bag, "--time-offset", "auto", "--align", "rigid",
              "--json", out, "--report", tmp_path / "rep")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "time offset: -1700000000.123" in r.stdout and "frame (rigid fit, pairs by name" in r.stdout, r.stdout
    al = json.loads(out.read_text())["alignment"]
    assert al["time_offset_source"] == "auto"
    assert abs(al["time_offset_s"] * 1e6 - offset_us) < 1000, al
    f = al["frame"]
    assert abs(f["translation_m"][0] - 0.5) < 1e-3 and abs(f["translation_m"][1] + 0.2) < 1e-3, f
    assert abs(math.radians(f["rotation_deg"]) - frame.rotation_rad) * 1.0 < 1e-3, f    # < 1 mm at 1 m
    assert f["scale"] == 1.0 and f["rms_mm"] < 4.0
    assert "## Truth alignment" in (tmp_path / "rep" / "report.md").read_text()
    # the same scores as against the simulator's truth itself
    r2 = arena("eval", "--tracks", d / "tracks.csv", "--truth", d / "truth.csv", "--json", direct)
    assert r2.returncode == 0, r2.stderr
    s, s0 = json.loads(out.read_text())["scores"], json.loads(direct.read_text())["scores"]
    # a robot counts once it has moved: from the simulator's velocities directly, from the mocap's
    # positions over 0.2 s, so a few frames more or less at each start
    for key in ("n_gt", "n_tp", "n_fp", "n_fn", "id_switches"):
        assert abs(s[key] - s0[key]) <= 0.01 * s0["n_gt"], (key, s[key], s0[key])
    for key in ("precision", "recall", "mota", "idf1", "hota"):
        assert s[key] == pytest.approx(s0[key], abs=0.005), key
    assert s["mae_cm"] == pytest.approx(s0["mae_cm"], abs=0.02)
    assert s["heading_mae_deg"] == pytest.approx(s0["heading_mae_deg"], abs=0.2)


def test_eval_mocap_bag_without_offset_says_what_to_do(sim_run, tmp_path):
    from groundtruth.mocap import Transform2D
    from test_mocap import to_mocap, write_pose_bag

    d, truth, _ = sim_run
    bag = write_pose_bag(tmp_path / "bag", to_mocap(truth, Transform2D(0.5, 0.5, -0.2), -1_700_000_000_000_000))
    r = arena("eval", "--tracks", d / "tracks.csv", "--truth", bag)     # default offset 0: nothing overlaps
    assert r.returncode == 1, r.stdout + r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "--time-offset" in r.stderr


def test_eval_pose_csv_with_given_offset(sim_run, tmp_path):
    import math

    from groundtruth.mocap import Transform2D
    from test_mocap import to_mocap

    d, truth, _ = sim_run
    frame = Transform2D(math.radians(-75), 1.1, 0.3, 1.0)
    m = to_mocap(truth, frame, 2_500_000)
    p = tmp_path / "poses.csv"
    with p.open("w") as fh:
        fh.write("t_ns,body,x,y,z,yaw\n")
        for row in m:
            fh.write(f"{int(row['t_us']) * 1000},{row['robot']},{row['x_m']:.6f},{row['y_m']:.6f},0.05,"
                     f"{row['yaw_rad']:.6f}\n")
    out = tmp_path / "s.json"
    r = arena("eval", "--tracks", d / "tracks.csv", "--truth", p, "--time-offset", "2.5", "--json", out)
    assert r.returncode == 0, r.stdout + r.stderr
    al = json.loads(out.read_text())["alignment"]
    assert al["time_offset_s"] == 2.5 and al["frame"]["mode"] == "rigid"      # rigid: the default for a pose CSV
    assert abs(al["frame"]["rotation_deg"] + 75) < 0.06 and abs(al["frame"]["translation_m"][0] - 1.1) < 1e-3
    assert json.loads(out.read_text())["scores"]["recall"] > 0.99


def test_eval_bag_without_rosbags_is_one_line(sim_run, tmp_path):
    d, _, _ = sim_run
    (tmp_path / "bag").mkdir()
    code = ("import sys; sys.modules['rosbags'] = None; from arena.cli import main; "
            f"sys.exit(main(['eval', '--tracks', {str(d / 'tracks.csv')!r}, '--truth', {str(tmp_path / 'bag')!r}]))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stdout + r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "pip install 'arena-fleet[ros2]'" in r.stderr, r.stderr


def test_eval_on_the_host_clock_lines_tracks_up_with_host_stamped_truth(files, tmp_path):
    """Live tracks carry host_ns (the host capture time); truth stamped by a host clock (mocap,
    ROS) lines up with it under --track-clock host, and not on the sensor clock."""
    tp, gp = files
    host0_us = 1_700_000_000_000_000
    lines = tp.read_text().splitlines()
    assert lines[0].endswith(",host_ns") and all(ln.endswith(",") for ln in lines[1:])   # written without host times
    rows = [lines[0]] + [ln[:-1] + f",{(int(ln.split(',')[0]) + host0_us) * 1000 + 789}" for ln in lines[1:]]
    tp.write_text("\n".join(rows) + "\n")
    truth = read_truth_csv(gp)
    truth["t_us"] += host0_us
    gh = tmp_path / "host_truth.csv"
    write_truth_csv(gh, truth)
    tracks = read_tracks_csv(tp, clock="host")
    assert tracks["t_us"][0] == host0_us and len(tracks) == 400
    r = arena("eval", "--tracks", tp, "--truth", gh, "--track-clock", "host", "--json", tmp_path / "h.json")
    assert r.returncode == 0, r.stderr
    assert "tracks on the host clock" in r.stdout
    scores = json.loads((tmp_path / "h.json").read_text())["scores"]
    assert abs(scores["mae_cm"] - 1.0) < 0.05, scores
    assert arena("eval", "--tracks", tp, "--truth", gh).returncode == 1   # sensor clock: no overlap
    plain = tmp_path / "plain.csv"
    plain.write_text("\n".join(lines) + "\n")
    r = arena("eval", "--tracks", plain, "--truth", gh, "--track-clock", "host")
    assert r.returncode == 2 and "no row has a host_ns" in r.stderr


def test_host_clock_rows_out_of_range_or_missing_are_named(files, tmp_path):
    tp, gp = files
    lines = tp.read_text().splitlines()
    huge = tmp_path / "huge.csv"
    huge.write_text("\n".join([lines[0]] + [ln[:-1] + ",9" * 1 + "9" * 40 for ln in lines[1:]]) + "\n")
    r = arena("eval", "--tracks", huge, "--truth", gp, "--track-clock", "host")
    assert r.returncode == 2 and "host_ns" in r.stderr and "Traceback" not in r.stderr, r.stderr
    mixed = tmp_path / "mixed.csv"
    mixed.write_text("\n".join([lines[0]] + [ln[:-1] + ("," + str(int(ln.split(",")[0]) * 1000) if k % 2 else ",")
                                                          for k, ln in enumerate(lines[1:])]) + "\n")
    r = arena("eval", "--tracks", mixed, "--truth", gp, "--track-clock", "host")
    assert "200 of 400 rows; 200 without a host_ns" in r.stdout, r.stdout + r.stderr

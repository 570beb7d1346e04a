"""The demo's scoring report: its tables from mission manifests and the webcam ground truth."""

import numpy as np

from demo.report import _fallbacks, mission_rows, realtime_rows, webcam_as_tracks
from arena.formats.tables import TRUTH_DTYPE
from groundtruth.metrics import evaluate


def test_webcam_rows_become_one_track_per_robot_and_unseen_rows_are_left_out():
    cam = np.zeros(4, TRUTH_DTYPE)
    cam["t_us"] = [0, 0, 40_000, 40_000]
    cam["robot"] = ["a", "b", "a", "b"]
    cam["x_m"] = [0.5, 1.0, 0.51, np.nan]      # b not seen in the second frame
    cam["y_m"] = [0.5, 1.0, 0.5, np.nan]
    tr = webcam_as_tracks(cam)
    assert tr["track_id"].tolist() == ["a", "b", "a"] and tr["x_m"].tolist() == [0.5, 1.0, 0.51]
    truth = cam.copy()
    truth["x_m"], truth["y_m"] = [0.5, 1.0, 0.52, 1.0], [0.5, 1.0, 0.5, 1.0]
    s = evaluate(tr, truth, gate_m=0.10, moved_only=False)
    assert s.precision == 1.0 and s.n_fn == 1 and abs(s.mae_cm - 1 / 3) < 1e-6


def test_mission_rows_show_path_errors_in_cm_and_a_dash_for_what_a_manifest_lacks():
    rows = mission_rows([
        {"robot": "r2", "pattern": "square", "status": "done", "rows": 10, "link": {"missing": 3},
         "fusion": {"tracks_used": 7, "odometry_fallbacks": 2, "odometry_only_s": 1.26},
         "path_error_tracks": {"mean_m": 0.0123, "max_m": 0.05}},
        {"robot": "r1"},    # a mission that never started writes little
    ])
    assert rows == [["r1", "?", "?", "-", "-", "-", "-", "- / -", "- / -"],
                    ["r2", "square", "done", "10", "3", "7", "2 (1.3 s)", "1.23 / 5.00", "- / -"]]


def test_the_demo_summary_says_which_closed_loops_fell_back_to_odometry():
    from demo.cli import _odometry_fallbacks

    from demo.cli import _fallback_words

    manifests = [{"robot": "a", "control": "closed", "fusion": {"odometry_fallbacks": 1, "odometry_only_s": 0.8,
                                                                "on_odometry_at_end": True}},
                 {"robot": "b", "control": "closed", "fusion": {"odometry_fallbacks": 0, "odometry_only_s": 0.0}},
                 {"robot": "d", "control": "closed", "fusion": {"odometry_fallbacks": 2, "odometry_only_s": 1.7,
                                                                "odometry_before_first_track_s": 0.6}},
                 {"robot": "c", "control": "paper", "fusion": {}}]
    got = _odometry_fallbacks(manifests)
    assert got == {"a": {"fallbacks": 1, "seconds": 0.8, "before_first_track_s": 0.0, "at_end": True},
                   "b": {"fallbacks": 0, "seconds": 0.0, "before_first_track_s": 0.0, "at_end": False},
                   "d": {"fallbacks": 2, "seconds": 1.7, "before_first_track_s": 0.6, "at_end": False}}
    assert _fallback_words("a", got["a"]) == "a 1x, 0.8 s (still at the end)"
    assert _fallback_words("d", got["d"]) == "d 2x, 1.7 s (0.6 s before its first track)"
    assert _fallbacks(manifests[2]["fusion"]) == "2 (1.7 s, 0.6 s before the first track)"
    assert _fallbacks(manifests[0]["fusion"]) == "1 (0.8 s)"
    assert _odometry_fallbacks([{"robot": "c", "control": "paper"}]) is None


def test_realtime_rows_only_for_what_was_measured():
    assert realtime_rows({}) == []
    rows = dict(realtime_rows({"first_track_s": 4.25, "windows": {"edge_published": 5, "edge_dropped": 1,
                                                                  "tracker_in": 4, "tracker_missed": 0,
                                                                  "tracker_queue_dropped": 0}}))
    assert rows["first track after the command"] == "4.2 s"
    assert rows["event windows at the edge"] == "5 published, 1 dropped"


def test_run_files_lists_only_what_exists(tmp_path):
    from demo.report import run_files

    (tmp_path / "tracks.csv").write_text("t_us,track_id,x_m,y_m\n")
    (tmp_path / "truth.csv").write_text("")
    (tmp_path / "logs").mkdir()
    (tmp_path / "arena.mcap").mkdir()      # a folder where a file belongs is not that file
    assert run_files(tmp_path) == ["tracks.csv", "truth.csv (empty)", "logs/"]
    assert run_files(tmp_path, also=("summary.json",)) == ["summary.json", "tracks.csv", "truth.csv (empty)",
                                                            "logs/"]


def test_replay_hint_needs_a_recording_and_makes_the_replay_the_router(tmp_path):
    from demo.report import replay_hint

    run = tmp_path / "my runs" / "demo-1"
    run.mkdir(parents=True)
    assert replay_hint(run) is None
    (run / "arena.mcap").write_bytes(b"\x89MCAP0\r\n")
    assert replay_hint(run) == (f"arena replay '{run}' --mode router --listen tcp/127.0.0.1:7447 --start-delay 3 "
                                "& arena view")
    (run / "cam0.calib.json").write_text("{}")
    assert replay_hint(run, view_port=8099, zenoh_port=17447) == (
        f"arena replay '{run}' --mode router --listen tcp/127.0.0.1:17447 --start-delay 3 & arena view "
        f"--port 8099 --calibration '{run}/cam0.calib.json' --connect tcp/127.0.0.1:17447")


def _scores_on(truth_rows: int):
    from arena.formats.tables import TRACK_DTYPE

    truth = np.zeros(truth_rows, TRUTH_DTYPE)
    truth["t_us"] = np.arange(truth_rows) * 10_000
    truth["robot"], truth["x_m"], truth["y_m"], truth["vx_mps"] = "a", 0.5 + 0.001 * np.arange(truth_rows), 0.5, 0.1
    tracks = np.zeros(20, TRACK_DTYPE)
    tracks["t_us"] = np.arange(20) * 10_000
    tracks["track_id"], tracks["state"], tracks["x_m"], tracks["y_m"] = "1", "confirmed", 0.5, 0.5
    return evaluate(tracks, truth, gate_m=0.10), tracks, truth


def test_the_reports_first_lines_say_why_the_run_is_not_ok_and_no_truth_shows_na(tmp_path):
    from demo.report import write_demo_report

    scores, tracks, truth = _scores_on(0)
    summary = {"ok": False, "problems": ["bridge did not stop when asked and was killed; see logs/bridge.log",
                                         "truth.csv has no rows in the scored span: nothing to score against"]}
    path = write_demo_report(tmp_path, "1 robot.", summary, scores, tracks, truth, files=["tracks.csv", "logs/"],
                             replay=None)
    lines = path.read_text().splitlines()
    assert lines[2:7] == ["**NOT OK**: 2 problem(s):", "", f"- {summary['problems'][0]}",
                          f"- {summary['problems'][1]}", ""], lines[:8]
    text = "\n".join(lines)
    for metric in ("MOTA", "IDF1", "HOTA", "MAE (cm)"):
        assert f"| {metric} | n/a |" in text, metric
    files = text.split("## Files")[1].strip().splitlines()
    assert files[0] == "`tracks.csv`, `logs/`."               # only what the run folder holds
    assert files[2] == "No recording (`arena.mcap`) to watch again."


def test_an_ok_report_says_so_first(tmp_path):
    from demo.report import write_demo_report

    scores, tracks, truth = _scores_on(20)
    path = write_demo_report(tmp_path, "1 robot.", {"ok": True, "problems": []}, scores, tracks, truth,
                             replay="arena replay R --mode router & arena view")
    text = path.read_text()
    assert text.splitlines()[2].startswith("**OK**: every service ran and stopped cleanly")
    assert "| MOTA | 1.0000 |" in text and "Watch it again: `arena replay R --mode router & arena view`" in text

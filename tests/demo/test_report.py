"""The demo's scoring report: its tables from mission manifests and the webcam ground truth."""

import numpy as np

from demo.report import mission_rows, realtime_rows, webcam_as_tracks
from groundtruth.metrics import TRUTH_DTYPE, evaluate


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
         "fusion": {"tracks_used": 7}, "path_error_tracks": {"mean_m": 0.0123, "max_m": 0.05}},
        {"robot": "r1"},    # a mission that never started writes little
    ])
    assert rows == [["r1", "?", "?", "-", "-", "-", "- / -", "- / -"],
                    ["r2", "square", "done", "10", "3", "7", "1.23 / 5.00", "- / -"]]


def test_realtime_rows_only_for_what_was_measured():
    assert realtime_rows({}) == []
    rows = dict(realtime_rows({"first_track_s": 4.25, "windows": {"edge_published": 5, "edge_dropped": 1,
                                                                  "tracker_in": 4, "tracker_missed": 0,
                                                                  "tracker_queue_dropped": 0}}))
    assert rows["first track after the command"] == "4.2 s"
    assert rows["event windows at the edge"] == "5 published, 1 dropped"

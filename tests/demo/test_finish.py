"""The end of `arena demo` on a run folder that went wrong: summary.json, the printed results and
report.md say first that the run is not ok and why, show no score made from nothing, and list
only the files that exist."""

from __future__ import annotations

import argparse
import json

import numpy as np

from demo.cli import _finish
from arena.formats.tables import TRACK_DTYPE, write_tracks_csv

ARGS = argparse.Namespace(robots=2, mission="mixed", power=1.0, lighting="full", duration=5.0, seed=0,
                          tracker="fleet", control="closed", view_port=8080)


def _bad_run(run):
    tracks = np.zeros(50, TRACK_DTYPE)
    tracks["t_us"] = np.arange(50) * 10_000
    tracks["track_id"], tracks["state"], tracks["x_m"], tracks["y_m"] = "1", "confirmed", 0.5, 0.5
    write_tracks_csv(run / "tracks.csv", tracks)
    (run / "truth.csv").write_text("t_us,robot,x_m,y_m,yaw_rad,vx_mps,vy_mps\n")   # the simulator wrote no row
    (run / "telemetry").mkdir()
    (run / "telemetry" / "black0_x-circle.json").write_text(json.dumps(
        {"robot": "black0", "pattern": "circle", "control": "closed", "status": "aborted: link down (closed)",
         "start_ns": 1, "fusion": {"tracks_used": 0, "tracks_rejected": 0, "heading_relocks": 0}}))
    (run / "logs").mkdir()
    (run / "logs" / "sim.log").write_text("arena sim: running\n"
                                          "real time: factor 0.81 over 6.2 s simulated, worst lag 1.40 s (t=3.1 s)\n")


def test_a_run_that_went_wrong_says_so_first_everywhere(tmp_path, capsys):
    run = tmp_path / "demo-x"
    run.mkdir()
    _bad_run(run)
    summary = _finish(run, ARGS, 5.0, {"bridge": -9, "sim": 0, "router": 0}, {"bridge": 1, "sim": 2, "router": 3},
                      killed=["bridge"], died={}, failure=None, interrupted=False)
    expected = [
        "bridge did not stop when asked and was killed; see logs/bridge.log",
        "only 1 of 2 robots logged a mission",
        "black0's circle mission ended: aborted: link down (closed)",
        "black0's circle mission was closed-loop but used no tracks (fusion.tracks_used = 0): it drove on "
        "odometry alone",
        "the simulator fell 1.40 s behind the wall clock (at t = 3.1 s; over 1 s): the CPU was short, so the "
        "timings are not the lab's",
        "no edge and tracker status in arena.mcap: whether event windows were lost is unknown",
        "truth.csv has no rows in the scored span: nothing to score against (MOTA, IDF1, HOTA n/a)",
    ]
    assert summary["ok"] is False and summary["problems"] == expected

    on_disk = json.loads((run / "summary.json").read_text())
    assert list(on_disk)[:2] == ["ok", "problems"] and on_disk["problems"] == expected
    s = on_disk["scores"]
    assert s["n_gt"] == 0 and (s["mota"], s["idf1"], s["hota"], s["mae_cm"]) == (None, None, None, None), s

    out = capsys.readouterr().out.splitlines()
    head = out.index("=== arena demo: results ===")
    assert out[head + 1] == f"NOT OK: {len(expected)} problem(s):"
    assert out[head + 2: head + 2 + len(expected)] == [f"  - {p}" for p in expected]
    score = next(ln for ln in out if ln.startswith("precision "))
    assert "MOTA n/a" in score and "IDF1 n/a" in score and "HOTA n/a" in score and "MAE n/a" in score, score
    folder = next(ln for ln in out if ln.startswith("run folder: "))
    assert folder == (f"run folder: {run}  (report.md, report/, summary.json, tracks.csv, truth.csv, telemetry/, "
                      "logs/)"), folder
    assert "watch it again: not possible, the run left no arena.mcap" in out

    report = (run / "report.md").read_text().splitlines()
    assert report[2] == f"**NOT OK**: {len(expected)} problem(s):" and report[4:4 + len(expected)] == [
        f"- {p}" for p in expected]
    assert "| MOTA | n/a |" in report and "| HOTA | n/a |" in report


def test_event_windows_lost_are_read_from_the_status_in_the_recording(tmp_path):
    """_windows reads the edge's and the tracker's status (found by their keys, arena.keys) in
    arena.mcap: the last counters, and with the missions' start the growth since then. Another
    camera's and a non-status channel are ignored."""
    from mcap.writer import Writer

    from demo.cli import _windows

    statuses = [  # (log time ns, topic, counters)
        (10, "arena/status/edge/cam0", {"windows": 100, "windows_dropped": 1}),
        (20, "arena/status/tracker/cam0", {"windows_in": 95, "windows_missed": 2, "windows_dropped_in_queue": 0}),
        (30, "arena/status/edge/cam1", {"windows": 7, "windows_dropped": 7}),
        (40, "arena/telemetry/zumo1", {"windows": 9}),
        (50, "arena/status/edge/cam0", {"windows": 300, "windows_dropped": 4}),
        (60, "arena/status/tracker/cam0", {"windows_in": 290, "windows_missed": 3, "windows_dropped_in_queue": 1}),
    ]
    path = tmp_path / "arena.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        schema = w.register_schema("arena.Status", "jsonschema", b"{}")
        channels = {}
        for t, topic, counters in statuses:
            if topic not in channels:
                channels[topic] = w.register_channel(topic, "json", schema)
            w.add_message(channels[topic], log_time=t, publish_time=t, data=json.dumps({"counters": counters}).encode())
        w.finish()
    assert _windows(path) == {"edge_published": 300, "edge_dropped": 4, "tracker_in": 290, "tracker_missed": 3,
                              "tracker_queue_dropped": 1}
    assert _windows(path, missions_ns=25)["during_missions"] == {"edge_dropped": 3, "tracker_missed": 1,
                                                                 "tracker_queue_dropped": 1}


def test_the_missions_end_is_their_end_row_not_a_fallback_to_odometry(tmp_path):
    """A closed loop's odometry_fallback / track_regained rows are progress, not the mission's end
    (the demo scored 68 frames of a 15 s run when it took the first such row for the end)."""
    from robot_bridge.logs import COLUMNS

    from demo.cli import _missions_end_us

    def row(host_ns, robot_us, event):
        vals = {c: "" for c in COLUMNS}
        vals.update(host_time_ns=host_ns, robot_time_us=robot_us, event=event)
        return ",".join(str(vals[c]) for c in COLUMNS)

    rows = [row(1_000_000_000 + k * 10_000_000, 5_000_000 + k * 10_000, "sample") for k in range(300)]
    rows.insert(100, row(2_000_000_000, "", "odometry_fallback"))
    rows.insert(150, row(2_500_000_000, "", "track_regained"))
    rows.append(row(1_000_000_000 + 300 * 10_000_000, "", "interrupted"))
    (tmp_path / "r1.csv").write_text(",".join(COLUMNS) + "\n" + "\n".join(rows) + "\n")
    # the end row, 10 ms after the last sample (robot time 5 000 000 + 299 * 10 000 µs)
    assert _missions_end_us(tmp_path) == 5_000_000 + 299 * 10_000 + 10_000


def test_windows_the_tracker_never_counted_are_accounted_for():
    """An outside tester could not reconcile 1140 windows published with 1055 processed, 0 missing
    and 0 dropped: the rest came before the tracker subscribed or after its last status."""
    from demo.cli import _unseen

    assert _unseen({"edge_published": 1140, "tracker_in": 1055, "tracker_missed": 0, "tracker_queue_dropped": 0}) == 85
    assert _unseen({"edge_published": 100, "tracker_in": 90, "tracker_missed": 4, "tracker_queue_dropped": 6}) == 0

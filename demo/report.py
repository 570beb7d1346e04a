"""The demo's scoring report: ``report.md`` in the run folder, with its plots in ``report/``.

One page a lab can read after ``arena demo``: how the run was set up, the tracks scored against
the simulator's exact poses (summary, per robot, trajectories and errors over time), whether the
system kept real time (first track, the simulator's lag, latency, event windows lost), how each
robot's mission went (path errors from the bridge's mission manifests) and how close the webcam
ground truth came to the exact poses (what a lab without a simulator scores against).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from groundtruth.metrics import Scores
from groundtruth.report import (ROBOT_HEADERS, fmt, markdown_table, plot_errors, plot_trajectories, robot_rows,
                                summary_rows)


def webcam_as_tracks(webcam: np.ndarray) -> np.ndarray:
    """The webcam ground truth (a :data:`groundtruth.metrics.TRUTH_DTYPE` array) as tracks, one
    track per robot marker, so :func:`groundtruth.metrics.evaluate` can score it like a tracker."""
    from groundtruth.metrics import TRACK_DTYPE

    ok = np.isfinite(webcam["x_m"]) & np.isfinite(webcam["y_m"])
    w = webcam[ok]
    out = np.zeros(w.size, TRACK_DTYPE)
    for name in ("t_us", "x_m", "y_m", "yaw_rad", "vx_mps", "vy_mps"):
        out[name] = w[name]
    out["track_id"] = w["robot"]
    out["robot"] = w["robot"]
    out["state"] = "confirmed"
    out["u_px"] = out["v_px"] = np.nan
    return out


def _cm(d: dict | None, key: str) -> str:
    v = (d or {}).get(key)
    return fmt(v * 100 if isinstance(v, (int, float)) else None, "{:.2f}")


def mission_rows(manifests: list[dict]) -> list[list[str]]:
    """One row per mission manifest (``telemetry/*.json``): robot, mission, status, telemetry
    rows, frames missing on the link, tracks fused, path error against the robot's own tracks
    and against its odometry (mean / max, cm)."""
    rows = []
    for m in sorted(manifests, key=lambda m: str(m.get("robot"))):
        pt, po = m.get("path_error_tracks"), m.get("path_error_odometry")
        rows.append([str(m.get("robot", "?")), str(m.get("pattern", "?")), str(m.get("status", "?")),
                     str(m.get("rows", "-")), str((m.get("link") or {}).get("missing", "-")),
                     str((m.get("fusion") or {}).get("tracks_used", "-")),
                     f"{_cm(pt, 'mean_m')} / {_cm(pt, 'max_m')}", f"{_cm(po, 'mean_m')} / {_cm(po, 'max_m')}"])
    return rows


MISSION_HEADERS = ["robot", "mission", "status", "rows", "missing frames", "tracks fused",
                   "path error, tracks (mean / max cm)", "path error, odometry (mean / max cm)"]


def realtime_rows(summary: dict) -> list[tuple[str, str]]:
    """(what, value) rows of the demo's real-time account (see ``summary.json``)."""
    rows = []
    if summary.get("first_track_s") is not None:
        rows.append(("first track after the command", f"{summary['first_track_s']:.1f} s"))
    rt = summary.get("sim_realtime")
    if rt:
        rows.append(("simulated world vs the wall clock",
                     f"{rt['factor']:.2f}x real time over {rt['simulated_s']:.1f} s, worst lag "
                     f"{rt['worst_lag_s']:.2f} s (at t = {rt['worst_lag_at_s']:.1f} s)"))
    lat = summary.get("latency")
    if lat:
        rows.append(("latency, edge publishes a slice -> its track arrives",
                     f"p50 {lat['p50_ms']:.1f} ms, p99 {lat['p99_ms']:.1f} ms over {lat['n']} tracks"))
    w = summary.get("windows")
    if w:
        rows.append(("event windows at the edge", f"{w['edge_published']} published, {w['edge_dropped']} dropped"))
        rows.append(("event windows at the tracker",
                     f"{w['tracker_in']} processed, {w['tracker_missed']} missing on the way, "
                     f"{w['tracker_queue_dropped']} dropped from its queue"))
    return rows


def write_demo_report(run_dir: str | Path, setup: str, summary: dict, scores: Scores, tracks: np.ndarray,
                      truth: np.ndarray, webcam_scores: Scores | None = None,
                      manifests: list[dict] | None = None) -> Path:
    """Write ``report.md`` (and ``report/trajectories.png``, ``report/errors.png``) into the run
    folder; returns the path of ``report.md``. ``setup`` is one line on how the demo was run."""
    run_dir = Path(run_dir)
    fig_dir = run_dir / "report"
    fig_dir.mkdir(parents=True, exist_ok=True)
    plot_trajectories(fig_dir / "trajectories.png", tracks, truth)
    plot_errors(fig_dir / "errors.png", scores)
    until = summary.get("scored_until_us")
    md = [f"# arena demo: {run_dir.name}", "", setup, "",
          "## Tracking", "",
          f"`tracks.csv` against the simulator's exact poses (`truth.csv`), gate {scores.gate_cm:g} cm, "
          "from each robot's first motion"
          + (f" until the missions ended (t = {until / 1e6:.1f} s)." if until else "."), "",
          markdown_table(["metric", "value"], summary_rows(scores)), "",
          markdown_table(ROBOT_HEADERS, robot_rows(scores)), "",
          "![trajectories](report/trajectories.png)", "",
          "![errors over time](report/errors.png)", ""]
    rt = realtime_rows(summary)
    if rt:
        md += ["## Real time", "", markdown_table(["", "value"], rt), ""]
    if manifests:
        md += ["## Missions", "",
               "From the bridge's mission manifests (`telemetry/*.json`; the CSV beside each holds every "
               "telemetry sample). The path errors are the distance from the mission's path, measured "
               "on the robot's own tracks and on its odometry.", "",
               markdown_table(MISSION_HEADERS, mission_rows(manifests)), ""]
    if webcam_scores is not None:
        s = webcam_scores
        md += ["## Webcam ground truth", "",
               "`groundtruth.csv` (`arena groundtruth`, ArUco markers on the simulated webcam) scored like a "
               "tracker against the exact poses: how far a lab without a simulator can trust its "
               "webcam scoring.", "",
               markdown_table(["precision", "recall", "MAE cm", "heading MAE deg", "frames"],
                              [[fmt(s.precision), fmt(s.recall), fmt(s.mae_cm, "{:.2f}"),
                                fmt(s.heading_mae_deg, "{:.2f}"), str(s.n_frames)]]), ""]
    md += ["## Files", "",
           "`events.raw` (RAW EVT 3.0), `tracks.csv`, `truth.csv`, `groundtruth.csv`, `telemetry/` (a CSV and "
           "a JSON manifest per robot and mission), `arena.mcap` (every `arena/**` message; opens in Foxglove), "
           "`summary.json` (these figures), `cam0.calib.json`, `logs/`. Replay: "
           f"`arena replay {run_dir}` and `arena view`.", ""]
    path = run_dir / "report.md"
    path.write_text("\n".join(md))
    return path


def read_manifests(telemetry_dir: str | Path) -> list[dict]:
    """Every readable mission manifest (``*.json``) in the run's ``telemetry/`` folder."""
    out = []
    for p in sorted(Path(telemetry_dir).glob("*.json")):
        try:
            out.append(json.loads(p.read_text()))
        except (OSError, ValueError):
            continue
    return out

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

from arena.messages import CONFIRMED
from groundtruth.metrics import Scores
from groundtruth.report import (NA, ROBOT_HEADERS, fmt, markdown_table, plot_errors, plot_trajectories, robot_rows,
                                summary_rows)


#: what an ok run is (the verdict's checks, :mod:`demo.verdict`), as the results and report.md say it
OK_TEXT = ("every service ran and stopped cleanly, every mission ran until the demo ended it (closed-loop "
           "ones on their tracks), the simulator kept real time (worst lag at most 1 s), no event window was "
           "lost while the missions ran, and the tracks were scored against the truth")


def webcam_as_tracks(webcam: np.ndarray) -> np.ndarray:
    """The webcam ground truth (a :data:`arena.formats.tables.TRUTH_DTYPE` array) as tracks, one
    track per robot marker, so :func:`groundtruth.metrics.evaluate` can score it like a tracker."""
    from arena.formats.tables import TRACK_DTYPE

    ok = np.isfinite(webcam["x_m"]) & np.isfinite(webcam["y_m"])
    w = webcam[ok]
    out = np.zeros(w.size, TRACK_DTYPE)
    for name in ("t_us", "x_m", "y_m", "yaw_rad", "vx_mps", "vy_mps"):
        out[name] = w[name]
    out["track_id"] = w["robot"]
    out["robot"] = w["robot"]
    out["state"] = CONFIRMED
    out["u_px"] = out["v_px"] = np.nan
    return out


def _cm(d: dict | None, key: str) -> str:
    v = (d or {}).get(key)
    return fmt(v * 100 if isinstance(v, (int, float)) else None, "{:.2f}")


def mission_rows(manifests: list[dict]) -> list[list[str]]:
    """One row per mission manifest (``telemetry/*.json``): robot, mission, status, telemetry
    rows, frames missing on the link, tracks fused, how often (and how long) the closed loop
    drove on odometry alone for want of its track, path error against the robot's own tracks
    and against its odometry (mean / max, cm)."""
    rows = []
    for m in sorted(manifests, key=lambda m: str(m.get("robot"))):
        pt, po = m.get("path_error_tracks"), m.get("path_error_odometry")
        rows.append([str(m.get("robot", "?")), str(m.get("pattern", "?")), str(m.get("status", "?")),
                     str(m.get("rows", "-")), str((m.get("link") or {}).get("missing", "-")),
                     str((m.get("fusion") or {}).get("tracks_used", "-")), _fallbacks(m.get("fusion") or {}),
                     f"{_cm(pt, 'mean_m')} / {_cm(pt, 'max_m')}", f"{_cm(po, 'mean_m')} / {_cm(po, 'max_m')}"])
    return rows


def _fallbacks(fusion: dict) -> str:
    """``N (S s)``: the closed loop's fallbacks to odometry alone and their total time; ``-`` when
    the mission did not say (the paper's open-loop control, an older manifest)."""
    if "odometry_fallbacks" not in fusion:
        return "-"
    first = float(fusion.get("odometry_before_first_track_s") or 0)
    return (f"{fusion['odometry_fallbacks']} ({float(fusion.get('odometry_only_s') or 0):.1f} s"
            + (f", {first:.1f} s before the first track)" if first > 0 else ")"))


MISSION_HEADERS = ["robot", "mission", "status", "rows", "missing frames", "tracks fused", "on odometry alone",
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
        d = w.get("during_missions")
        if d:
            rows.append(("event windows lost while the missions ran",
                         f"{d['edge_dropped']} dropped at the edge, {d['tracker_missed']} missing and "
                         f"{d['tracker_queue_dropped']} dropped from its queue at the tracker"))
    return rows


def write_demo_report(run_dir: str | Path, setup: str, summary: dict, scores: Scores, tracks: np.ndarray,
                      truth: np.ndarray, webcam_scores: Scores | None = None,
                      manifests: list[dict] | None = None, files: list[str] | None = None,
                      replay: str | None = None) -> Path:
    """Write ``report.md`` (and ``report/trajectories.png``, ``report/errors.png``) into the run
    folder; returns the path of ``report.md``. ``setup`` is one line on how the demo was run.
    Its first lines say whether the run was ok and why not (``summary["ok"]``,
    ``summary["problems"]``); ``files`` lists what the run folder holds (:func:`run_files`),
    ``replay`` is the command that watches it again (:func:`replay_hint`)."""
    run_dir = Path(run_dir)
    files = run_files(run_dir, also=("report.md", "report/")) if files is None else files
    replay = replay_hint(run_dir) if replay is None else replay
    fig_dir = run_dir / "report"
    fig_dir.mkdir(parents=True, exist_ok=True)
    plot_trajectories(fig_dir / "trajectories.png", tracks, truth)
    plot_errors(fig_dir / "errors.png", scores)
    until = summary.get("scored_until_us")
    gt = summary.get("groundtruth") or {}
    problems = list(summary.get("problems") or [])
    if summary.get("ok") and not problems:
        verdict = [f"**OK**: {OK_TEXT}.", ""]
    else:
        verdict = [f"**NOT OK**: {len(problems) or 'unknown'} problem(s):", "",
                   *[f"- {p}" for p in problems], ""]
    if gt.get("method"):
        setup = f"{setup} Webcam ground truth by {gt['method']}."
    md = [f"# arena demo: {run_dir.name}", "", *verdict, setup, "",
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
        how = f"by {gt['method']}: {gt['how']}" if gt.get("method") else "on the simulated webcam"
        hs = gt.get("headings")
        md += ["## Webcam ground truth", "",
               f"`groundtruth.csv` (`arena groundtruth` on the simulated webcam, {how}) scored like a "
               "tracker against the exact poses: how far a lab without a simulator can trust its "
               "webcam scoring."
               + (f" Headings: {hs['front_mark']} from the front mark, {hs['motion']} from motion, "
                  f"{hs['unknown']} unknown." if hs else ""), "",
               markdown_table(["precision", "recall", "MAE cm", "heading MAE deg", "frames"],
                              [[fmt(s.precision, missing=NA), fmt(s.recall, missing=NA),
                                fmt(s.mae_cm, "{:.2f}", NA), fmt(s.heading_mae_deg, "{:.2f}", NA),
                                str(s.n_frames)]]), ""]
    md += ["## Files", "", ", ".join(_file_item(f) for f in files) + ".", ""]
    md += [f"Watch it again: `{replay}` (the replay is its own Zenoh router), then open the viewer's page."
           if replay else "No recording (`arena.mcap`) to watch again.", ""]
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


#: what each file of a run folder is, for the report
FILE_NOTES = {"events.raw": "RAW EVT 3.0", "telemetry/": "a CSV and a JSON manifest per robot and mission",
              "arena.mcap": "every `arena/**` message; opens in Foxglove", "summary.json": "these figures",
              "truth.csv": "the simulator's exact poses", "groundtruth.csv": "the webcam ground truth"}


def _file_item(entry: str) -> str:
    """``name (empty)`` or ``name`` of :func:`run_files` as Markdown, with what the file is."""
    name, _, rest = entry.partition(" ")
    notes = [n for n in (FILE_NOTES.get(name), rest.strip("()")) if n]
    return f"`{name}`" + (f" ({'; '.join(notes)})" if notes else "")


#: what a run folder may hold, in the order a reader wants them (folders end with ``/``)
RUN_FILES = ("report.md", "report/", "summary.json", "tracks.csv", "truth.csv", "groundtruth.csv", "telemetry/",
             "events.raw", "arena.mcap", "cam0.calib.json", "tracker-state.json", "logs/")


def run_files(run_dir: str | Path, also: tuple[str, ...] = ()) -> list[str]:
    """The run folder's files and folders that exist (folders with a ``/``, empty files marked), in
    the order a reader wants them; ``also`` names ones about to be written."""
    run_dir = Path(run_dir)
    out = []
    for name in RUN_FILES:
        p = run_dir / name.rstrip("/")
        if name in also:
            out.append(name)
        elif name.endswith("/") and p.is_dir():
            out.append(name)
        elif not name.endswith("/") and p.is_file():
            out.append(name if p.stat().st_size else f"{name} (empty)")
    return out


def replay_hint(run_dir: str | Path, view_port: int = 8080, zenoh_port: int = 7447) -> str | None:
    """One shell line that replays the run into a viewer once the demo has stopped (its router is
    gone): the replay is the Zenoh router, listening on ``zenoh_port`` (``--mode router``), the
    viewer connects to it as a client (the default endpoint when ``zenoh_port`` is 7447) and waits
    for it, and the replay waits 3 s for the viewer before its first message. None when the run
    has no recording."""
    import shlex

    run_dir = Path(run_dir)
    mcap = run_dir / "arena.mcap"
    if not mcap.is_file() or mcap.stat().st_size == 0:
        return None
    endpoint = f"tcp/127.0.0.1:{zenoh_port}"
    calib = run_dir / "cam0.calib.json"
    view = ["arena", "view"] + (["--port", str(view_port)] if view_port != 8080 else []) \
        + (["--calibration", str(calib)] if calib.is_file() else []) \
        + (["--connect", endpoint] if zenoh_port != 7447 else [])
    replay = ["arena", "replay", str(run_dir), "--mode", "router", "--listen", endpoint, "--start-delay", "3"]
    return f"{shlex.join(replay)} & {shlex.join(view)}"

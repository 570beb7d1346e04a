"""Presenting scores: a terminal table, JSON, and Markdown reports with PNG plots (matplotlib, Agg).

Shown units: cm and degrees (the scorer works in metres and radians, arena frame).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Sequence

import numpy as np

from groundtruth.metrics import Scores

ARENA_SIZE_M = 1.83

#: (label, Scores attribute, format) of the summary table, in order
SUMMARY_FIELDS = (
    ("precision", "precision", "{:.4f}"),
    ("recall", "recall", "{:.4f}"),
    ("MAE (cm)", "mae_cm", "{:.2f}"),
    ("heading MAE (deg)", "heading_mae_deg", "{:.2f}"),
    ("MOTA", "mota", "{:.4f}"),
    ("MOTP (similarity)", "motp", "{:.4f}"),
    ("ID switches", "id_switches", "{}"),
    ("fragmentations", "fragmentations", "{}"),
    ("IDF1", "idf1", "{:.4f}"),
    ("HOTA", "hota", "{:.4f}"),
    ("DetA", "deta", "{:.4f}"),
    ("AssA", "assa", "{:.4f}"),
    ("frames", "n_frames", "{}"),
    ("GT / TP / FP / FN", None, None),
)


#: what a report shows for a metric that was not measured (NaN/None: e.g. MOTA without ground truth)
NA = "n/a"


def fmt(value, spec: str = "{:.4f}", missing: str = "-") -> str:
    """Format a number, showing ``missing`` ('-', or :data:`NA` for metrics) for NaN/None."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return missing
    return spec.format(value)


def no_ground_truth(s: Scores) -> str | None:
    """Why the scores measure nothing (one line), or None when there was ground truth to score."""
    if s.n_gt > 0:
        return None
    if s.n_robots == 0:
        return "the truth has no rows: MOTA, IDF1, HOTA and MAE are n/a"
    if s.n_frames == 0:
        return (f"no frame inside the truth's time span ({s.n_frames_dropped} outside it): "
                "MOTA, IDF1, HOTA and MAE are n/a")
    return (f"no robot counted in any of the {s.n_frames} frames (none moved, or none inside its truth span): "
            "MOTA, IDF1, HOTA and MAE are n/a")


def summary_rows(s: Scores) -> list[tuple[str, str]]:
    """(label, formatted value) of the summary metrics, in :data:`SUMMARY_FIELDS` order."""
    rows = []
    for label, attr, spec in SUMMARY_FIELDS:
        if attr is None:
            rows.append((label, f"{s.n_gt} / {s.n_tp} / {s.n_fp} / {s.n_fn}"))
        else:
            rows.append((label, fmt(getattr(s, attr), spec, NA)))
    return rows


def robot_rows(s: Scores) -> list[list[str]]:
    """One row of :data:`ROBOT_HEADERS` per robot."""
    return [[name, str(r.n_gt), fmt(r.recall, missing=NA), fmt(r.mae_cm, "{:.2f}", NA),
             fmt(r.heading_mae_deg, "{:.2f}", NA),
             str(r.id_switches), str(r.fragmentations), r.main_track or "-"]
            for name, r in s.per_robot.items()]


ROBOT_HEADERS = ["robot", "frames", "recall", "MAE cm", "heading deg", "ID sw", "frag", "track"]


def text_table(headers: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """A plain aligned text table."""
    widths = [max(len(str(h)), *(len(str(r[i])) for r in rows)) if rows else len(str(h))
              for i, h in enumerate(headers)]
    line = "  ".join(str(h).ljust(w) for h, w in zip(headers, widths)).rstrip()
    out = [line, "  ".join("-" * w for w in widths)]
    out += ["  ".join(str(c).ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]
    return "\n".join(out)


def markdown_table(headers: Sequence[str], rows: Sequence[Sequence]) -> str:
    """A GitHub Markdown table."""
    out = ["| " + " | ".join(map(str, headers)) + " |", "|" + "---|" * len(headers)]
    out += ["| " + " | ".join(map(str, r)) + " |" for r in rows]
    return "\n".join(out)


def format_scores(s: Scores) -> str:
    """The terminal view of :func:`groundtruth.metrics.evaluate`'s result."""
    head = (f"gate {s.gate_cm:g} cm, {s.n_robots} robot(s), {s.n_tracks} track id(s), "
            f"{s.n_frames} frame(s)")
    extra = []
    why = no_ground_truth(s)
    if why:
        extra.append(f"no ground truth scored: {why}")
    if s.n_frames_dropped:
        extra.append(f"{s.n_frames_dropped} frame(s) outside the truth's time span dropped")
    if s.n_ignored:
        extra.append(f"{s.n_ignored} track row(s) on robots that had not moved yet ignored")
    parts = [head, text_table(["metric", "value"], summary_rows(s)), "",
             text_table(ROBOT_HEADERS, robot_rows(s))]
    if extra:
        parts += [""] + [f"note: {e}" for e in extra]
    return "\n".join(parts)


def write_json(path: str | Path, s: Scores, **meta) -> None:
    """Write the scores (and any metadata such as input paths) as JSON."""
    payload = {**meta, "scores": s.to_dict()}
    Path(path).write_text(json.dumps(payload, indent=2, sort_keys=False) + "\n")


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_trajectories(path: str | Path, tracks: np.ndarray, truth: np.ndarray,
                      title: str = "") -> None:
    """Truth lines per robot and track points per track id over the arena (metres)."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 6.4))
    ax.add_patch(plt.Rectangle((0, 0), ARENA_SIZE_M, ARENA_SIZE_M, fill=False, ec="0.6", lw=1))
    for k, r in enumerate(np.unique(truth["robot"])):
        sel = truth[truth["robot"] == r]
        sel = sel[np.argsort(sel["t_us"])]
        ax.plot(sel["x_m"], sel["y_m"], "-", color="0.55", lw=4, alpha=0.45,
                label="truth" if k == 0 else None)
        if len(sel):
            ax.annotate(str(r), (sel["x_m"][0], sel["y_m"][0]), fontsize=8, color="0.25",
                        xytext=(4, 4), textcoords="offset points")
    ids = np.unique(tracks["track_id"]) if len(tracks) else []
    cmap = plt.get_cmap("tab10")
    for k, tid in enumerate(ids):
        sel = tracks[tracks["track_id"] == tid]
        ax.plot(sel["x_m"], sel["y_m"], ".", ms=2, color=cmap(k % 10),
                label=f"track {tid}" if k < 12 else None)
    ax.set_xlim(-0.05, ARENA_SIZE_M + 0.05)
    ax.set_ylim(-0.05, ARENA_SIZE_M + 0.05)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m, arena)")
    ax.set_ylabel("y (m, arena)")
    ax.set_title(title or "trajectories: truth (grey, robot names at start) vs tracks (points)")
    ax.legend(fontsize=7, loc="upper right", markerscale=4)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_errors(path: str | Path, s: Scores) -> None:
    """Position error (cm) and heading error (deg) of the matches over time, per robot."""
    plt = _pyplot()
    m = s.matches if s.matches is not None else np.zeros(0)
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    t0 = m["t_us"].min() if len(m) else 0
    for r in (np.unique(m["robot"]) if len(m) else []):
        sel = m[m["robot"] == r]
        t = (sel["t_us"] - t0) * 1e-6
        a1.plot(t, sel["err_m"] * 100, lw=0.8, label=r)
        ok = np.isfinite(sel["yaw_err_rad"])
        a2.plot(t[ok], np.degrees(np.abs(sel["yaw_err_rad"][ok])), lw=0.8, label=r)
    a1.set_ylabel("position error (cm)")
    a2.set_ylabel("|heading error| (deg)")
    a2.set_xlabel("time (s)")
    a1.set_title(f"errors of matched tracks (gate {s.gate_cm:g} cm)")
    if len(m):
        a1.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_eval_report(out_dir: str | Path, s: Scores, tracks: np.ndarray, truth: np.ndarray,
                      tracks_name: str = "", truth_name: str = "", *, alignment: Sequence[str] = (),
                      meta: dict | None = None) -> Path:
    """Write ``report.md``, ``trajectories.png``, ``errors.png`` and ``scores.json`` into ``out_dir``.

    ``alignment``: lines saying how the truth was put on the tracks' clock and frame (motion
    capture: offset, fit, residuals), shown in a section of their own; ``meta``: more keys for
    ``scores.json`` (e.g. the alignment as a dict)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    plot_trajectories(out / "trajectories.png", tracks, truth)
    plot_errors(out / "errors.png", s)
    write_json(out / "scores.json", s, tracks=tracks_name, truth=truth_name, **(meta or {}))
    why = no_ground_truth(s)
    md = [
        "# Tracking evaluation",
        "",
        *([f"**Nothing measured**: {why}.", ""] if why else []),
        f"Tracks: `{tracks_name}`  ",
        f"Truth: `{truth_name}`  ",
        f"Gate {s.gate_cm:g} cm; a robot counts once it has moved; {s.n_frames} frames, "
        f"{s.n_robots} robot(s), {s.n_tracks} track id(s).",
        "",
        *(["## Truth alignment", "", *(f"- {line}" for line in alignment), ""] if alignment else []),
        "## Summary",
        "",
        markdown_table(["metric", "value"], summary_rows(s)),
        "",
        "## Per robot",
        "",
        markdown_table(ROBOT_HEADERS, robot_rows(s)),
        "",
        "## Trajectories",
        "",
        "![trajectories](trajectories.png)",
        "",
        "## Errors over time",
        "",
        "![errors](errors.png)",
        "",
        "Definitions: CLEAR MOT (Bernardin & Stiefelhagen 2008) with a distance gate; IDF1 (Ristani "
        "et al. 2016); HOTA (Luiten et al. 2021) with similarity max(0, 1 - d/gate); MOTP is the mean "
        "of that similarity over matches. See `groundtruth/metrics.py`.",
        "",
    ]
    path = out / "report.md"
    path.write_text("\n".join(md))
    return path

"""The paper's study rerun end to end on the simulator (``arena experiment paper``).

Parts (each seeded: a scenario's seed depends only on the base seed and the scenario, so the
same recording is shared between parts and every rerun gives the same numbers):

* ``minpts``  - DBSCAN minPts sweep on one robot (circle, 50 % and 100 % power): the paper's
  n_avg-clusters and A_ratio vs minPts for full clusters (all events, eps 15 px) and partial
  clusters (ON events, eps 6 px), over consecutive 100 ms windows.
* ``ta``      - accumulation-time sweep: position MAE vs t_a, one robot, circle and square, 100 %.
* ``table``   - 1-4 robots x circle/square x 100 %/50 % power: the paper's table with the paper's
  numbers beside ours.
* ``lighting``- full, dimmed and dark light, 1-4 robots on squares at 100 % (the paper's dimmed row).

Tracking parts run both trackers (``idtrack``: the paper's Algorithm 1 with its detector;
``fleet``: the project's default) through the tracker's offline pipeline and score them with
:func:`groundtruth.metrics.evaluate` against the simulator's exact truth (10 cm gate, robots
counted from their first motion).

A launcher, like the demo (and so in its package): it imports the simulator, the tracker's public
API and the scoring of ``groundtruth``; no service imports it.
"""

from __future__ import annotations

import json
import logging
import math
import platform
import time
import zlib
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from arena.formats.tables import TRUTH_DTYPE, tracks_array
from groundtruth.metrics import a_ratio, evaluate, n_avg_clusters
from groundtruth.report import fmt, markdown_table

log = logging.getLogger("arena.experiment")

PARTS = ("minpts", "ta", "table", "lighting")
TRACKERS = ("idtrack", "fleet")
PATTERNS = ("circle", "square")
POWERS = (100, 50)
LIGHTING = ("full", "dimmed", "dark")
CHASSIS_M = 0.10  # Zumo 32U4 footprint side, m (A_ratio's A_actual)

#: The paper's table: (n, pattern) -> (precision, recall, MAE cm, MOTA), each as (100 %, 50 %).
PAPER_TABLE = {
    (1, "circle"): ((1, 1), (1, 1), (1.22, 2.16), (1, 1)),
    (2, "circle"): ((1, 1), (1, 1), (2.00, 2.82), (1, 1)),
    (3, "circle"): ((1, 1), (1, 1), (2.05, 3.78), (1, 1)),
    (4, "circle"): ((1, 1), (0.94, 0.93), (4.32, 5.92), (0.94, 0.93)),
    (1, "square"): ((1, 1), (1, 1), (2.36, 3.5), (1, 1)),
    (2, "square"): ((1, 1), (1, 1), (3.85, 3.2), (1, 1)),
    (3, "square"): ((1, 1), (1, 1), (2.9, 4.96), (1, 1)),
    (4, "square"): ((1, 1), (0.95, 1), (4.31, 6.77), (0.95, 1)),
}
#: The paper's dimmed light on squares: n -> (precision, recall, MAE cm, MOTA).
PAPER_DIMMED = {1: (1, 1, 3.01, 1), 2: (1, 1, 2.59, 1), 3: (1, 1, 3.12, 1), 4: (1, 0.73, 10.05, 0.72)}
#: The paper's best minPts: full clusters 220-230; partial 45 at 100 %, 35 at 50 % power.
PAPER_MINPTS = {("full", 100): "220-230", ("full", 50): "220-230",
                ("partial", 100): "45", ("partial", 50): "35"}
#: The paper's heading MAE ranges (deg), single robot.
PAPER_HEADING = {"circle": "5.8-13.0", "square": "30.5-50.6"}


class ExperimentError(RuntimeError):
    """The study cannot run (a missing component, an unwritable output folder, ...)."""


@dataclass(frozen=True)
class StudyPlan:
    """What the study runs. ``duration_s`` per scenario; sweeps as tuples."""

    duration_s: float
    minpts_full: tuple[int, ...]
    minpts_partial: tuple[int, ...]
    ta_ms: tuple[int, ...]
    table_robots: tuple[int, ...]
    table_powers: tuple[int, ...]
    lighting_robots: tuple[int, ...]
    skip_s: float = 0.5  # start of the run left out of the minPts sweep (robot accelerating)

    @classmethod
    def full(cls) -> "StudyPlan":
        return cls(duration_s=12.0,
                   minpts_full=tuple(range(100, 301, 10)),
                   minpts_partial=tuple(range(10, 101, 5)),
                   ta_ms=(10, 25, 50, 100, 150, 200),
                   table_robots=(1, 2, 3, 4), table_powers=POWERS,
                   lighting_robots=(1, 2, 3, 4))

    @classmethod
    def quick(cls) -> "StudyPlan":
        return cls(duration_s=3.0,
                   minpts_full=(130, 170, 230, 290),
                   minpts_partial=(20, 35, 50, 80),
                   ta_ms=(25, 100),
                   table_robots=(1, 2), table_powers=(100,),
                   lighting_robots=(2,))


def scenario_seed(base: int, n_robots: int, pattern: str, power: int, lighting: str) -> int:
    """Seed of one scenario: depends only on the base seed and the scenario itself."""
    return (int(base) * 1_000_003 + zlib.crc32(f"{n_robots}/{pattern}/{power}/{lighting}".encode())) % 2**31


# ------------------------------------------------------------------------------------------
# The two components the study drives: the simulator and the tracker's offline pipeline


@dataclass
class Recording:
    """What the study needs of a simulated run (arena frame for truth, sensor frame for events)."""

    events: np.ndarray       # arena.events.EVENT_DTYPE, µs
    truth: np.ndarray        # arena.formats.tables.TRUTH_DTYPE
    calibration: dict        # the project's calibration JSON dict
    width: int
    height: int
    seconds: float = 0.0     # CPU time the simulation took


def simulate(n_robots: int, pattern: str, power: int, duration_s: float, lighting: str,
             seed: int) -> Recording:
    """Run one scenario on the simulator (power in %; robots shell colours cycle black, yellow, ...)."""
    from simulator.scenarios import Scenario, generate

    t0 = time.process_time()
    rec = generate(Scenario(n_robots=n_robots, pattern=pattern, power=power / 100.0,
                            duration_s=duration_s, lighting=lighting, seed=seed))
    names = np.asarray(rec.robot_names)
    truth = np.empty(len(rec.truth), dtype=TRUTH_DTYPE)
    truth["robot"] = names[rec.truth["robot"]]
    for name in ("t_us", "x_m", "y_m", "yaw_rad", "vx_mps", "vy_mps"):
        truth[name] = rec.truth[name]
    return Recording(events=rec.events, truth=truth, calibration=rec.calibration,
                     width=int(rec.width), height=int(rec.height), seconds=time.process_time() - t0)


def track(rec: Recording, tracker: str, t_a_ms: float, slice_us: int = 10_000) -> tuple[np.ndarray, float]:
    """Run the tracker's offline pipeline on a recording; returns (tracks, CPU seconds).

    CPU time (``time.process_time``) rather than wall time, so a busy machine does not inflate it.

    ``idtrack`` is the paper's whole method (paper detector + Algorithm 1); ``fleet`` the
    project's default detector and tracker, with default parameters (no fleet size given).
    """
    from tracker.calibration import Calibration
    from tracker.pipeline import Pipeline, iter_slices

    pipe = Pipeline(Calibration.from_dict(rec.calibration), tracker=tracker,
                    detector="paper" if tracker == "idtrack" else "default",
                    accumulation_us=int(round(t_a_ms * 1000)))
    tracks = []
    t0 = time.process_time()
    for t_end, ev in iter_slices([rec.events], slice_us):
        tracks.extend(pipe.push(ev, t_end))
    secs = time.process_time() - t0
    return tracks_array(tracks), secs


# ------------------------------------------------------------------------------------------
# Clustering sweep (the paper's minPts study)


def _unique_pixels(ev: np.ndarray, width: int) -> np.ndarray:
    lin = np.unique(ev["y"].astype(np.int64) * width + ev["x"].astype(np.int64))
    return np.stack([lin % width, lin // width], axis=1)


def cluster_sweep(rec: Recording, minpts: tuple[int, ...], eps: float, polarity: int | None,
                  n_robots: int, robot_area_px: float, window_us: int = 100_000,
                  skip_us: int = 500_000) -> tuple[list[float], list[float]]:
    """n_avg-clusters and A_ratio for each minPts over consecutive windows of ``window_us``.

    DBSCAN runs over the unique active pixels of each window (the paper's input), with the
    tracker's exact grid backend; ``polarity`` 1 = ON events only (partial clusters), None = all.
    """
    from tracker.dbscan import dbscan_grid

    ev = rec.events if polarity is None else rec.events[rec.events["p"] == polarity]
    t = ev["t"]
    t0 = int(rec.events["t"].min()) + skip_us if len(rec.events) else 0
    t_end = int(rec.events["t"].max()) if len(rec.events) else 0
    windows = []
    for start in range(t0, t_end - window_us + 1, window_us):
        lo, hi = np.searchsorted(t, [start, start + window_us])
        windows.append(_unique_pixels(ev[lo:hi], rec.width))
    n_avg, ratio = [], []
    for m in minpts:
        per_window = []
        for px in windows:
            if len(px) == 0:
                per_window.append([])
                continue
            labels = dbscan_grid(px[:, 0], px[:, 1], eps, m)
            per_window.append([px[labels == k] for k in range(int(labels.max()) + 1)])
        n_avg.append(n_avg_clusters(per_window, n_robots))
        ratio.append(a_ratio(per_window, n_robots, robot_area_px))
    return n_avg, ratio


def robot_area_px(calibration: dict) -> float:
    """The chassis area in px² at the arena centre (A_actual of A_ratio)."""
    from tracker.calibration import Calibration

    cal = Calibration.from_dict(calibration)
    return (CHASSIS_M * cal.px_per_m()) ** 2


# ------------------------------------------------------------------------------------------
# The study


@dataclass
class Study:
    """Results of a study run (everything the report shows, JSON-ready)."""

    seed: int
    quick: bool
    plan: dict
    parts: list[str]
    runs: list[dict] = field(default_factory=list)     # one per (scenario, tracker, t_a)
    minpts: list[dict] = field(default_factory=list)   # one per (power, kind)
    failures: list[dict] = field(default_factory=list)  # steps that raised: {"step", "error"}
    seconds: float = 0.0       # wall time
    cpu_seconds: float = 0.0   # CPU time of this process
    machine: str = ""
    report: Path | None = None


def _score_row(rec: Recording, tracker: str, t_a_ms: float, **scenario) -> dict:
    tracks, secs = track(rec, tracker, t_a_ms)
    s = evaluate(tracks, rec.truth, gate_m=0.10, moved_only=True)
    n_updates = len(np.unique(tracks["t_us"])) if len(tracks) else 0
    return {**scenario, "tracker": tracker, "t_a_ms": t_a_ms, "scores": s.to_dict(),
            "sim_cpu_s": round(rec.seconds, 3), "track_cpu_s": round(secs, 3),
            "cpu_ms_per_update": round(1000 * secs / n_updates, 3) if n_updates else None}


def check_output_folder(out) -> None:
    """Raise :class:`ExperimentError` unless ``out`` names a folder to write the report into
    (existing or not): not an empty path (which would be the current folder), not a file."""
    if out is None or not str(out).strip():
        raise ExperimentError("the output folder is an empty path: give a folder for the report (e.g. --out study/)")
    if Path(out).exists() and not Path(out).is_dir():
        raise ExperimentError(f"the output folder {out} is an existing file, not a folder: give another path")


def run_paper_study(out: Path, quick: bool = False, seed: int = 1, parts=PARTS,
                    progress: bool = True, plan: StudyPlan | None = None) -> Study:
    """Run the study and write ``out/report.md`` (+ plots, ``study.json``); returns the results.

    A step that raises is recorded in ``Study.failures`` (and the report) and the study goes on.
    """
    check_output_folder(out)
    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ExperimentError(f"cannot create output folder {out}: {exc}") from None
    plan = plan or (StudyPlan.quick() if quick else StudyPlan.full())
    study = Study(seed=seed, quick=quick, plan=asdict(plan), parts=list(parts),
                  machine=f"{platform.machine()}, {platform.python_implementation()} {platform.python_version()}")
    steps = _steps(plan, parts)
    from tqdm import tqdm

    bar = tqdm(total=len(steps), desc="paper study", unit="run", disable=not progress)
    t_start, cpu_start = time.perf_counter(), time.process_time()
    cache: dict[tuple, Recording] = {}
    with bar:
        for key, what in steps:
            bar.set_postfix_str(what, refresh=True)
            try:
                _run_step(study, plan, key, cache, seed)
            except Exception as exc:  # a failing component must not lose the rest of the study
                log.exception("step %s failed", what)
                study.failures.append({"step": what, "error": f"{type(exc).__name__}: {exc}"})
            bar.update(1)
            study.seconds = round(time.perf_counter() - t_start, 1)
            study.cpu_seconds = round(time.process_time() - cpu_start, 1)
            _save(out, study)  # partial results survive an interrupted study
    _save(out, study)
    study.report = write_study_report(out, study, plan)
    return study


def _save(out: Path, study: Study) -> None:
    d = asdict(study)
    d.pop("report")
    (out / "study.json").write_text(json.dumps(d, indent=1) + "\n")


def _steps(plan: StudyPlan, parts) -> list[tuple[tuple, str]]:
    """The study's units of work in order: (key, label). Recordings are reused in order."""
    steps = []
    if "minpts" in parts:
        for power in POWERS:
            steps.append((("minpts", 1, "circle", power, "full"), f"minPts sweep {power} %"))
    if "ta" in parts:
        for pattern in PATTERNS:
            for ta in plan.ta_ms:
                for trk in TRACKERS:
                    steps.append((("ta", 1, pattern, 100, "full", trk, ta), f"t_a {ta} ms {pattern} {trk}"))
    if "table" in parts:
        for power in plan.table_powers:
            for pattern in PATTERNS:
                for n in plan.table_robots:
                    for trk in TRACKERS:
                        steps.append((("table", n, pattern, power, "full", trk, 100),
                                      f"{n} robot(s) {pattern} {power} % {trk}"))
    if "lighting" in parts:
        for level in LIGHTING:
            for n in plan.lighting_robots:
                for trk in TRACKERS:
                    steps.append((("lighting", n, "square", 100, level, trk, 100),
                                  f"{level} light {n} robot(s) {trk}"))
    return steps


def _recording(cache: dict, plan: StudyPlan, seed: int, n: int, pattern: str, power: int,
               lighting: str) -> Recording:
    key = (n, pattern, power, lighting)
    if key not in cache:
        cache.clear()  # keep one recording in memory (steps are ordered by scenario)
        cache[key] = simulate(n, pattern, power, plan.duration_s, lighting,
                              scenario_seed(seed, n, pattern, power, lighting))
    return cache[key]


def _run_step(study: Study, plan: StudyPlan, key: tuple, cache: dict, seed: int) -> None:
    part, n, pattern, power, lighting = key[:5]
    if part == "lighting":  # the same scenario (hence recording and seed) may already be in the table
        done = _runs(study, "table", n_robots=n, pattern=pattern, power=power, lighting=lighting,
                     tracker=key[5], t_a_ms=key[6])
        if done:
            study.runs.append({**done[0], "part": "lighting"})
            return
    rec = _recording(cache, plan, seed, n, pattern, power, lighting)
    if part == "minpts":
        area = robot_area_px(rec.calibration)
        for kind, mp, eps, pol in (("full", plan.minpts_full, 15.0, None),
                                   ("partial", plan.minpts_partial, 6.0, 1)):
            navg, ratio = cluster_sweep(rec, mp, eps, pol, n, area, skip_us=int(plan.skip_s * 1e6))
            study.minpts.append({"power": power, "kind": kind, "eps_px": eps, "minpts": list(mp),
                                 "n_avg_clusters": navg, "a_ratio": ratio,
                                 "robot_area_px": round(area, 1)})
        return
    trk, ta = key[5], key[6]
    study.runs.append(_score_row(rec, trk, ta, part=part, n_robots=n, pattern=pattern,
                                 power=power, lighting=lighting))


# ------------------------------------------------------------------------------------------
# Report


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _runs(study: Study, part: str, **match) -> list[dict]:
    return [r for r in study.runs if r["part"] == part and all(r[k] == v for k, v in match.items())]


def _best_minpts(entry: dict) -> tuple[int, float, float]:
    """minPts whose (n_avg, A_ratio) is closest to (1, 1)."""
    cost = [abs(a - 1) + abs(b - 1) if math.isfinite(a) and math.isfinite(b) else math.inf
            for a, b in zip(entry["n_avg_clusters"], entry["a_ratio"])]
    i = int(np.argmin(cost))
    return entry["minpts"][i], entry["n_avg_clusters"][i], entry["a_ratio"][i]


def _plot_minpts(path: Path, study: Study) -> None:
    plt = _pyplot()
    fig, axes = plt.subplots(2, 2, figsize=(10, 6.5))
    for col, kind in enumerate(("full", "partial")):
        for e in (e for e in study.minpts if e["kind"] == kind):
            axes[0, col].plot(e["minpts"], e["n_avg_clusters"], "o-", ms=3, label=f"{e['power']} % power")
            axes[1, col].plot(e["minpts"], e["a_ratio"], "o-", ms=3, label=f"{e['power']} % power")
        axes[0, col].set_title(f"{kind} clusters (eps {15 if kind == 'full' else 6} px"
                               f"{'' if kind == 'full' else ', ON events'})")
        axes[0, col].set_ylabel("n_avg-clusters")
        axes[1, col].set_ylabel("A_ratio")
        axes[1, col].set_xlabel("minPts")
        for ax in axes[:, col]:
            ax.axhline(1.0, color="0.5", lw=0.8, ls="--")
            ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_ta(path: Path, study: Study) -> None:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for pattern in PATTERNS:
        for trk in TRACKERS:
            rows = sorted(_runs(study, "ta", pattern=pattern, tracker=trk), key=lambda r: r["t_a_ms"])
            if rows:
                ax.plot([r["t_a_ms"] for r in rows],
                        [r["scores"]["mae_cm"] if r["scores"]["mae_cm"] is not None else np.nan for r in rows],
                        "o-", label=f"{trk}, {pattern}")
    ax.set_xlabel("accumulation time t_a (ms)")
    ax.set_ylabel("position MAE (cm)")
    ax.set_title("MAE vs t_a, 1 robot, 100 % power")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_table(path: Path, study: Study, plan: StudyPlan) -> None:
    plt = _pyplot()
    fig, axes = plt.subplots(1, len(PATTERNS), figsize=(10, 4), sharey=True)
    for ax, pattern in zip(axes, PATTERNS):
        for power in plan.table_powers:
            pi = POWERS.index(power)
            ns = list(plan.table_robots)
            ax.plot(ns, [PAPER_TABLE[(n, pattern)][2][pi] for n in ns], "k--" if power == 100 else "k:",
                    label=f"paper {power} %")
            for trk in TRACKERS:
                rows = sorted(_runs(study, "table", pattern=pattern, power=power, tracker=trk),
                              key=lambda r: r["n_robots"])
                ax.plot([r["n_robots"] for r in rows],
                        [r["scores"]["mae_cm"] if r["scores"]["mae_cm"] is not None else np.nan for r in rows],
                        "o-", label=f"{trk} {power} %")
        ax.set_title(pattern)
        ax.set_xlabel("robots")
        ax.set_xticks(list(plan.table_robots))
    axes[0].set_ylabel("position MAE (cm)")
    axes[-1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _ours(r: dict | None, key: str, spec: str = "{:.3f}") -> str:
    return fmt(r["scores"][key], spec) if r else "-"


def write_study_report(out: Path, study: Study, plan: StudyPlan) -> Path:
    """Write ``report.md`` with tables beside the paper's numbers and the plots."""
    md = ["# The paper's study, rerun on the simulator", "",
          f"Seed {study.seed}{' (quick plan)' if study.quick else ''}; {plan.duration_s:g} s per scenario; "
          f"scored with `groundtruth.metrics.evaluate` against the simulator's exact truth "
          f"(10 cm gate, robots counted from their first motion). Wall time {study.seconds:.0f} s "
          f"(CPU {study.cpu_seconds:.0f} s) on {study.machine}. Every run's scores: `study.json`.", ""]
    if study.minpts:
        _plot_minpts(out / "minpts.png", study)
        rows = []
        for e in study.minpts:
            best, na, ar = _best_minpts(e)
            edge = " (sweep edge)" if best in (e["minpts"][0], e["minpts"][-1]) else ""
            rows.append([e["kind"], f"{e['power']} %", f"{best}{edge}", fmt(na, "{:.2f}"), fmt(ar, "{:.2f}"),
                         PAPER_MINPTS[(e["kind"], e["power"])]])
        md += ["## minPts sweep (1 robot, circle)", "",
               "n_avg-clusters = clusters per robot per 100 ms window; A_ratio = bounding-box area of "
               "the clusters over the chassis area (both ideally 1). Full clusters: all events, eps 15 px; "
               "partial: ON events, eps 6 px.", "",
               markdown_table(["clusters", "power", "best minPts (ours)", "n_avg", "A_ratio",
                               "paper's best minPts"], rows), "", "![minPts sweep](minpts.png)", ""]
    ta_runs = [r for r in study.runs if r["part"] == "ta"]
    if ta_runs:
        _plot_ta(out / "ta.png", study)
        rows = [[r["pattern"], r["tracker"], r["t_a_ms"], _ours(r, "mae_cm", "{:.2f}"),
                 _ours(r, "recall"), _ours(r, "mota")]
                for r in sorted(ta_runs, key=lambda r: (r["pattern"], r["tracker"], r["t_a_ms"]))]
        md += ["## Accumulation time (1 robot, 100 % power)", "",
               "The paper found t_a = 100 ms best (lowest MAE).", "",
               markdown_table(["pattern", "tracker", "t_a (ms)", "MAE (cm)", "recall", "MOTA"], rows),
               "", "![MAE vs t_a](ta.png)", ""]
    if _runs(study, "table"):
        md += _table_section(out, study, plan)
    if _runs(study, "lighting"):
        md += _lighting_section(study, plan)
    if study.failures:
        md += ["## Failed runs", "", markdown_table(["run", "error"], [[f["step"], f["error"].replace("|", "/")]
                                                                   for f in study.failures]), ""]
    timing = [r["cpu_ms_per_update"] for r in study.runs if r.get("cpu_ms_per_update") is not None]
    if timing:
        md += ["## Cost", "", f"Tracker CPU time per update (detection + tracking, offline, this machine): "
               f"median {np.median(timing):.2f} ms over {len(timing)} runs.", ""]
    path = out / "report.md"
    path.write_text("\n".join(md))
    return path


def _table_section(out: Path, study: Study, plan: StudyPlan) -> list[str]:
    """The report's section on the paper's table (robots x pattern x power): per power, the
    paper's row then both trackers' rows on the same recording; writes ``table.png``."""
    md: list[str] = []
    _plot_table(out / "table.png", study, plan)
    md += ["## Robots x pattern x power (the paper's table)", "",
           "Paper: precision, recall, MAE (cm), MOTA as published. Ours: both trackers on the same "
           "recording; heading MAE in degrees (the paper gives a range over its single-robot runs).", ""]
    for power in plan.table_powers:
        pi = POWERS.index(power)
        rows = []
        for pattern in PATTERNS:
            for n in plan.table_robots:
                p = PAPER_TABLE[(n, pattern)]
                heading = PAPER_HEADING[pattern] if n == 1 else "-"
                rows.append([n, pattern, "paper", p[0][pi], p[1][pi], p[2][pi], p[3][pi], heading,
                             "-", "-", "-"])
                for trk in TRACKERS:
                    r = next(iter(_runs(study, "table", n_robots=n, pattern=pattern, power=power,
                                        tracker=trk)), None)
                    rows.append([n, pattern, trk, _ours(r, "precision"), _ours(r, "recall"),
                                 _ours(r, "mae_cm", "{:.2f}"), _ours(r, "mota"),
                                 _ours(r, "heading_mae_deg", "{:.1f}"), _ours(r, "idf1"),
                                 _ours(r, "hota"), _ours(r, "id_switches", "{}")])
        md += [f"### {power} % power", "",
               markdown_table(["n", "pattern", "who", "precision", "recall", "MAE cm", "MOTA",
                               "heading deg", "IDF1", "HOTA", "ID sw"], rows), ""]
    md += ["![MAE by number of robots](table.png)", ""]
    return md


def _lighting_section(study: Study, plan: StudyPlan) -> list[str]:
    """The report's section on lighting: per level and number of robots, the paper's dimmed
    row (it gives no dark numbers) then both trackers' rows."""
    md: list[str] = []
    rows = []
    for level in LIGHTING:
        for n in plan.lighting_robots:
            if level == "dimmed":
                p = PAPER_DIMMED[n]
                rows.append([level, n, "paper", p[0], p[1], p[2], p[3], "-"])
            for trk in TRACKERS:
                r = next(iter(_runs(study, "lighting", n_robots=n, lighting=level, tracker=trk)), None)
                rows.append([level, n, trk, _ours(r, "precision"), _ours(r, "recall"),
                             _ours(r, "mae_cm", "{:.2f}"), _ours(r, "mota"), _ours(r, "id_switches", "{}")])
    md += ["## Lighting (squares, 100 % power)", "",
           "Paper: dimmed numbers as published; in the dark 'the event camera struggled to detect "
           "motion consistently' (no numbers).", "",
           markdown_table(["light", "n", "who", "precision", "recall", "MAE cm", "MOTA", "ID sw"], rows), ""]
    return md

"""Command-line entry points of the groundtruth package, one ``register_*`` function per command.

Each ``register_*(subparsers)`` adds one ``arena`` subcommand (see ``[project.entry-points.
"arena.commands"]`` in pyproject.toml) and sets ``func`` to a ``run(args) -> exit code``.
Heavy imports (matplotlib, the simulator) happen inside the run functions so ``arena --help`` stays fast.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def _formatter(prog: str) -> argparse.HelpFormatter:
    return argparse.RawDescriptionHelpFormatter(prog, max_help_position=32)


# --------------------------------------------------------------------------------------------
# arena eval
# --------------------------------------------------------------------------------------------
def register_eval(sub) -> None:
    """Add ``arena eval``: score a tracks CSV against a truth CSV."""
    p = sub.add_parser(
        "eval", help="score tracks against ground truth (MOTA, IDF1, HOTA, MAE, ...)",
        formatter_class=_formatter,
        description="Score a tracker's CSV against truth: per-frame optimal matching with a distance\n"
                    "gate, precision, recall, position MAE (cm), heading MAE (deg, circular), CLEAR MOT\n"
                    "(MOTA, MOTP, ID switches, fragmentations), IDF1 and HOTA. A robot counts once it\n"
                    "has moved. Frames are the tracks' update times; truth is interpolated there.\n\n"
                    "tracks CSV: t_us,track_id,robot,x_m,y_m,yaw_rad,vx_mps,vy_mps,u_px,v_px,state,n_events\n"
                    "truth CSV:  t_us,robot,x_m,y_m[,yaw_rad,...] (simulator truth or `arena groundtruth`)",
        epilog="Examples:\n"
               "  arena eval --tracks tracks.csv --truth truth.csv\n"
               "  arena eval --tracks tracks.csv --truth truth.csv --gate-cm 5 --json scores.json\n"
               "  arena eval --tracks tracks.csv --truth webcam_gt.csv --report eval_report/\n"
               "Exit code 0 when scored, 2 for unreadable input.")
    p.add_argument("--tracks", required=True, metavar="CSV", help="tracker output (arena track --tracks-out)")
    p.add_argument("--truth", required=True, metavar="CSV", help="truth or ground-truth poses")
    p.add_argument("--gate-cm", type=float, default=10.0, help="match distance gate in cm (default 10)")
    p.add_argument("--all-frames", action="store_true",
                   help="count robots from the start, not only once they have moved")
    p.add_argument("--include-tentative", action="store_true",
                   help="also score rows whose state is 'tentative' (excluded by default)")
    p.add_argument("--json", metavar="OUT", help="write the scores as JSON to OUT")
    p.add_argument("--report", metavar="DIR", help="write report.md with plots into DIR")
    p.set_defaults(func=run_eval)


def run_eval(args: argparse.Namespace) -> int:
    """Run ``arena eval``; returns the exit code."""
    from groundtruth.metrics import CsvFormatError, evaluate, read_tracks_csv, read_truth_csv
    from groundtruth.report import format_scores, write_eval_report, write_json

    if not args.gate_cm > 0:
        print(f"arena eval: --gate-cm must be positive, got {args.gate_cm}", file=sys.stderr)
        return 2
    try:
        tracks = read_tracks_csv(args.tracks)
        truth = read_truth_csv(args.truth)
    except CsvFormatError as exc:
        print(f"arena eval: {exc}", file=sys.stderr)
        return 2
    if len(truth) == 0:
        print(f"arena eval: truth file {args.truth} has a header but no rows", file=sys.stderr)
        return 2
    scores = evaluate(tracks, truth, gate_m=args.gate_cm / 100.0, moved_only=not args.all_frames,
                      exclude_states=() if args.include_tentative else ("tentative",))
    print(format_scores(scores))
    try:
        if args.json:
            write_json(args.json, scores, tracks=str(args.tracks), truth=str(args.truth))
            print(f"scores written to {args.json}")
        if args.report:
            path = write_eval_report(args.report, scores, tracks, truth, str(args.tracks), str(args.truth))
            print(f"report written to {path}")
    except OSError as exc:
        print(f"arena eval: cannot write output: {exc}", file=sys.stderr)
        return 2
    return 0


# --------------------------------------------------------------------------------------------
# arena experiment
# --------------------------------------------------------------------------------------------
def register_experiment(sub) -> None:
    """Add ``arena experiment``: rerun the paper's study on the simulator."""
    p = sub.add_parser(
        "experiment", help="rerun the paper's experiments on the simulator, with a report",
        formatter_class=_formatter,
        description="Rerun the paper's study end to end on the simulated arena: the minPts sweep\n"
                    "(n_avg-clusters and A_ratio, full and partial clusters, 50 % and 100 % power), the\n"
                    "accumulation-time sweep (MAE vs t_a), 1-4 robots x circle/square x 50/100 % power\n"
                    "(the paper's table beside ours), lighting (full, dimmed, dark), for both trackers\n"
                    "(idtrack, fleet). Writes DIR/report.md with plots, tables and a JSON of every run.\n"
                    "Every run is seeded: the same --seed gives the same numbers.",
        epilog="Examples:\n"
               "  arena experiment paper --out study/               # the full study (< 30 min)\n"
               "  arena experiment paper --out /tmp/ci --quick      # a short version for CI (~2 min)\n"
               "  arena experiment paper --out study/ --seed 7 --only table,lighting")
    p.add_argument("study", choices=["paper"], help="which study to run (the paper's)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder for the report")
    p.add_argument("--quick", action="store_true", help="short runs and coarse sweeps (CI)")
    p.add_argument("--seed", type=int, default=1, help="base random seed (default 1)")
    p.add_argument("--only", metavar="PARTS", default=None,
                   help="comma-separated subset of: minpts,ta,table,lighting (default all)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run_experiment)


def run_experiment(args: argparse.Namespace) -> int:
    """Run ``arena experiment``; returns the exit code."""
    from groundtruth.experiment import PARTS, ExperimentError, run_paper_study

    parts = PARTS if args.only is None else tuple(s.strip() for s in args.only.split(",") if s.strip())
    bad = [s for s in parts if s not in PARTS]
    if bad or not parts:
        print(f"arena experiment: unknown part(s) {', '.join(bad) or '(none)'}; choose from "
              f"{','.join(PARTS)}", file=sys.stderr)
        return 2
    try:
        report = run_paper_study(Path(args.out), quick=args.quick, seed=args.seed, parts=parts,
                                 progress=not args.no_progress)
    except ExperimentError as exc:
        print(f"arena experiment: {exc}", file=sys.stderr)
        return 2
    print(f"report written to {report}")
    return 0

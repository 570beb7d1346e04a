"""Whether an ``arena demo`` run went as claimed: ``ok``, and the reasons when it did not.

Pure: it judges facts the launcher collected (exit codes and kills from the supervisor, the
bridge's mission manifests, the simulator's real-time line, the event-window counters from the
recording, the scores) and does no I/O. The demo prints the reasons first, writes them first in
``summary.json`` (``"ok"``, ``"problems"``) and ``report.md``, and exits 1 when there is any.

A run is ok only when everything below was seen to hold; a fact that is missing (no real-time
line, no window counters, no scores) is a problem too, since the run cannot show it held.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

#: the simulator may lag the wall clock by at most this much (s) before the run is not ok
MAX_SIM_LAG_S = 1.0
#: exit codes of a service stopped by the demo: its own clean exit, or SIGTERM's default action
CLEAN_EXIT_CODES = (0, -15)
#: how a mission may end in a good run: all its laps, or the demo stopping the bridge at the end
GOOD_MISSION_ENDS = ("finished", "interrupted: bridge shut down")
#: the webcam ground truth must find the robots in at least this share of the scored positions: a lab
#: without a simulator scores against it, so one that misses most robots would score nothing
MIN_WEBCAM_RECALL = 0.5


def verdict(*, exit_codes: Mapping[str, int | None],
            killed: Sequence[str] = (),
            died: Mapping[str, int | None] | None = None,
            restarts: Mapping[str, int] | None = None,
            failure: str | None = None,
            interrupted: bool = False,
            manifests: Sequence[Mapping] | None = None,
            robots: int | None = None,
            sim_realtime: Mapping | None = None,
            windows: Mapping | None = None,
            truth_rows: int | None = None,
            scores: Mapping | None = None,
            score_error: str | None = None,
            report_error: str | None = None,
            webcam: Mapping | None = None,
            webcam_method: str | None = None,
            max_lag_s: float = MAX_SIM_LAG_S) -> tuple[bool, list[str]]:
    """``(ok, problems)`` of a demo run; ``ok`` is True exactly when ``problems`` is empty.

    Args:
        exit_codes: service name -> exit code as the supervisor stopped it (None: still running).
        killed: services the supervisor had to SIGKILL after their stop grace period.
        died: services that exited before the demo stopped them -> their exit code.
        restarts: service -> times restarted (the demo's supervisor never restarts; kept for
            launchers that do).
        failure: the launcher's own error (a service not ready or gone, a mission refused).
        interrupted: the run was stopped by Ctrl-C / SIGTERM before its missions ended.
        manifests: the bridge's mission manifests (``telemetry/*.json``).
        robots: robots the demo sent a mission to (each must have a manifest).
        sim_realtime: the simulator's ``{"factor", "simulated_s", "worst_lag_s", "worst_lag_at_s"}``.
        windows: event-window counters (``edge_published``, ``edge_dropped``, ``tracker_in``,
            ``tracker_missed``, ``tracker_queue_dropped``) over the run; when it holds
            ``during_missions`` (the three loss counters since the missions started), only those
            count: windows lost while the services start (a starved edge at start-up) reach no
            scored frame, and the printed counters still show them.
        truth_rows: rows of the simulator's truth in the scored span.
        scores: :meth:`groundtruth.metrics.Scores.to_dict` of the tracks against the truth.
        score_error, report_error: why scoring or the report failed.
        webcam: the webcam ground truth's scores against the exact poses (``precision``,
            ``recall``, ``mae_cm``, ...); None when it was not scored.
        webcam_method: how the webcam ground truth found the robots (``"colour"`` or
            ``"markers"``); given, the run needs a webcam ground truth that found the robots in at
            least :data:`MIN_WEBCAM_RECALL` of the positions (checked only when there was truth).
        max_lag_s: the simulator's worst lag allowed, s.
    """
    p: list[str] = []
    if interrupted:
        p.append("interrupted before the missions ended (Ctrl-C or SIGTERM)")
    if failure:
        p.append(f"the run failed: {(failure.strip().splitlines() or [failure])[0]}")
    p += _service_problems(exit_codes, killed, died, restarts)
    p += _missions(manifests, robots)
    p += _realtime_problems(sim_realtime, max_lag_s)
    p += _window_problems(windows)
    p += _score_problems(truth_rows, scores, score_error)
    p += _webcam_problems(webcam, webcam_method, truth_rows)
    if report_error:
        p.append(f"no report.md: {report_error}")
    return not p, p


def _service_problems(exit_codes: Mapping[str, int | None], killed: Sequence[str],
                      died: Mapping[str, int | None] | None, restarts: Mapping[str, int] | None) -> list[str]:
    """Problems of the services themselves: died during the run, killed after their stop
    grace, still running or not exiting cleanly when stopped, restarted (see :func:`verdict`)."""
    p: list[str] = []
    died = dict(died or {})
    killed = list(killed)
    for name, code in died.items():
        p.append(f"{name} died during the run (exit code {code}); see logs/{name}.log")
    for name in killed:
        p.append(f"{name} did not stop when asked and was killed; see logs/{name}.log")
    for name, code in exit_codes.items():
        if name in died or name in killed:
            continue
        if code is None:
            p.append(f"{name} was still running after the demo stopped it")
        elif code not in CLEAN_EXIT_CODES:
            p.append(f"{name} exited with code {code} when stopped; see logs/{name}.log")
    for name, n in (restarts or {}).items():
        if n:
            p.append(f"{name} was restarted {n} time(s) during the run; see logs/{name}.log")
    return p


def _realtime_problems(sim_realtime: Mapping | None, max_lag_s: float) -> list[str]:
    """The simulator's lag unknown, or worse than ``max_lag_s``: the timings are then not a
    lab's (see :func:`verdict`)."""
    p: list[str] = []
    if sim_realtime is None:
        p.append("the simulator's real-time line is missing from logs/sim.log: its lag is unknown")
    elif sim_realtime.get("worst_lag_s", 0) > max_lag_s:
        p.append(f"the simulator fell {sim_realtime['worst_lag_s']:.2f} s behind the wall clock (at t = "
                 f"{sim_realtime.get('worst_lag_at_s', float('nan')):.1f} s; over {max_lag_s:g} s): the CPU "
                 "was short, so the timings are not the lab's")
    return p


def _window_problems(windows: Mapping | None) -> list[str]:
    """Event windows lost (only while the missions ran, if known), or unknown whether any
    were (see :func:`verdict`)."""
    p: list[str] = []
    if windows is None:
        p.append("no edge and tracker status in arena.mcap: whether event windows were lost is unknown")
    else:
        during = windows.get("during_missions")
        counts = during if isinstance(during, Mapping) else windows
        lost = {k: int(counts.get(k) or 0) for k in ("edge_dropped", "tracker_missed", "tracker_queue_dropped")}
        if sum(lost.values()):
            p.append(f"{sum(lost.values())} event window(s) lost"
                     + (" while the missions ran" if counts is during else "")
                     + f": the edge dropped {lost['edge_dropped']}, the tracker found {lost['tracker_missed']} "
                     f"missing and dropped {lost['tracker_queue_dropped']} from its queue")
    return p


def _score_problems(truth_rows: int | None, scores: Mapping | None, score_error: str | None) -> list[str]:
    """The tracks not scored, or scored against no truth (see :func:`verdict`)."""
    p: list[str] = []
    if truth_rows == 0:
        p.append("truth.csv has no rows in the scored span: nothing to score against (MOTA, IDF1, HOTA n/a)")
    elif scores is None:
        p.append(f"not scored: {score_error or 'tracks.csv or truth.csv is missing'}")
    elif not scores.get("n_gt"):
        p.append(f"no ground truth in the {scores.get('n_frames', 0)} scored frame(s): MOTA, IDF1, HOTA n/a")
    return p


def _webcam_problems(webcam: Mapping | None, webcam_method: str | None, truth_rows: int | None) -> list[str]:
    """The webcam ground truth missing, or finding too few robot positions to score against
    (checked only when it was asked for and there was truth; see :func:`verdict`)."""
    p: list[str] = []
    if webcam_method is not None and truth_rows:
        if webcam is None:
            p.append(f"no webcam ground truth ({webcam_method}): groundtruth.csv is missing or has no rows; "
                     "see logs/groundtruth.log")
        elif not (webcam.get("recall") or 0) >= MIN_WEBCAM_RECALL:
            r = webcam.get("recall")
            p.append(f"the webcam ground truth ({webcam_method}) found the robots in only "
                     f"{'n/a' if r is None else format(r, '.0%')} of their positions (under "
                     f"{MIN_WEBCAM_RECALL:.0%}): scoring against it would measure little; see logs/groundtruth.log")
    return p


def _missions(manifests: Sequence[Mapping] | None, robots: int | None) -> list[str]:
    p: list[str] = []
    manifests = list(manifests or [])
    if not manifests:
        if robots != 0:
            p.append("no mission manifest in telemetry/: no mission ran")
        return p
    if robots is not None and len({m.get("robot") for m in manifests}) < robots:
        p.append(f"only {len({m.get('robot') for m in manifests})} of {robots} robots logged a mission")
    for m in manifests:
        who = f"{m.get('robot', '?')}'s " + (f"{m['pattern']} mission" if m.get("pattern") else "mission")
        status = str(m.get("status", "?"))
        if status == "running":
            p.append(f"{who} never ended in its log (the bridge died or was killed)")
        elif status not in GOOD_MISSION_ENDS:
            p.append(f"{who} ended: {status}")
        fusion = m.get("fusion")
        if m.get("control") == "closed" and isinstance(fusion, Mapping) and not fusion.get("tracks_used"):
            p.append(f"{who} was closed-loop but used no tracks (fusion.tracks_used = 0): it drove on "
                     "odometry alone")
    return p

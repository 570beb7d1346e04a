"""The demo's verdict: a run is ok only when everything it claims happened, else each reason."""

from __future__ import annotations

import pytest

from demo.verdict import verdict

WINDOWS = {"edge_published": 1500, "edge_dropped": 0, "tracker_in": 1500, "tracker_missed": 0,
           "tracker_queue_dropped": 0}


def manifest(robot: str, **over) -> dict:
    m = {"robot": robot, "pattern": "circle", "control": "closed", "status": "interrupted: bridge shut down",
         "fusion": {"tracks_used": 900, "tracks_rejected": 0, "heading_relocks": 0}}
    return {**m, **over}


def good_run(**over) -> dict:
    """The facts of a clean 2-robot run (as demo.cli collects them)."""
    facts = dict(exit_codes={"bridge": 0, "sim": 0, "tracker": -15, "router": 0}, killed=[], died={},
                 restarts={}, failure=None, interrupted=False,
                 manifests=[manifest("black0"), manifest("yellow1", pattern="square", status="finished")],
                 robots=2, sim_realtime={"factor": 0.99, "simulated_s": 12.0, "worst_lag_s": 0.2,
                                          "worst_lag_at_s": 3.0},
                 windows=dict(WINDOWS), truth_rows=4800, scores={"n_gt": 2000, "n_frames": 1000, "mota": 1.0},
                 score_error=None, report_error=None)
    facts.update(over)
    return facts


def problems_of(**over) -> list[str]:
    ok, problems = verdict(**good_run(**over))
    assert ok is False and problems, problems
    return problems


def test_a_clean_run_is_ok_with_no_problem():
    assert verdict(**good_run()) == (True, [])


def test_a_service_that_died_during_the_run():
    assert problems_of(died={"tracker": 1}, exit_codes={"tracker": 1, "bridge": 0}) == [
        "tracker died during the run (exit code 1); see logs/tracker.log"]


def test_a_service_that_had_to_be_killed():
    # the supervisor says so (SIGKILL after its grace period): -9 is not listed a second time
    assert problems_of(killed=["bridge"], exit_codes={"bridge": -9, "sim": 0}) == [
        "bridge did not stop when asked and was killed; see logs/bridge.log"]


def test_a_service_that_exited_badly_when_stopped():
    assert problems_of(exit_codes={"bridge": 0, "recorder": 3}) == [
        "recorder exited with code 3 when stopped; see logs/recorder.log"]


def test_a_restarted_service():
    assert problems_of(restarts={"edge": 2, "tracker": 0}) == [
        "edge was restarted 2 time(s) during the run; see logs/edge.log"]


def test_the_launchers_own_failure_first_line_only():
    assert problems_of(failure="no bridge answered the mission for black0\nlog tail ...") == [
        "the run failed: no bridge answered the mission for black0"]


def test_an_interrupted_run():
    assert problems_of(interrupted=True) == ["interrupted before the missions ended (Ctrl-C or SIGTERM)"]


@pytest.mark.parametrize("status", ["aborted: link down (closed)", "aborted: geofence (0.010, 0.500) m",
                                    "e-stop", "failed: mission crashed: ValueError()"])
def test_an_aborted_mission(status):
    assert problems_of(manifests=[manifest("black0", status=status), manifest("yellow1")]) == [
        f"black0's circle mission ended: {status}"]


def test_a_mission_log_never_closed():
    # the bridge writes "running" at the start and the outcome at the end
    probs = problems_of(manifests=[manifest("black0", status="running", fusion=None), manifest("yellow1")])
    assert probs == ["black0's circle mission never ended in its log (the bridge died or was killed)"]


def test_a_closed_loop_mission_that_used_no_tracks():
    m = manifest("yellow1", fusion={"tracks_used": 0, "tracks_rejected": 40, "heading_relocks": 0})
    assert problems_of(manifests=[manifest("black0"), m]) == [
        "yellow1's circle mission was closed-loop but used no tracks (fusion.tracks_used = 0): it drove on "
        "odometry alone"]
    # an open-loop (paper) mission needs no tracks
    assert verdict(**good_run(manifests=[manifest("black0"), dict(m, control="paper")]))[0] is True


def test_missing_missions():
    assert problems_of(manifests=[]) == ["no mission manifest in telemetry/: no mission ran"]
    assert problems_of(manifests=[manifest("black0")]) == ["only 1 of 2 robots logged a mission"]


def test_the_simulator_lagging_over_a_second():
    rt = {"factor": 0.8, "simulated_s": 12.0, "worst_lag_s": 1.35, "worst_lag_at_s": 7.25}
    assert problems_of(sim_realtime=rt) == [
        "the simulator fell 1.35 s behind the wall clock (at t = 7.2 s; over 1 s): the CPU was short, so the "
        "timings are not the lab's"]
    assert verdict(**good_run(sim_realtime=dict(rt, worst_lag_s=1.0)))[0] is True   # at the limit is fine
    assert problems_of(sim_realtime=None) == [
        "the simulator's real-time line is missing from logs/sim.log: its lag is unknown"]


@pytest.mark.parametrize("counter", ["edge_dropped", "tracker_missed", "tracker_queue_dropped"])
def test_lost_event_windows(counter):
    probs = problems_of(windows=dict(WINDOWS, **{counter: 3}))
    assert len(probs) == 1 and probs[0].startswith("3 event window(s) lost: "), probs
    assert {"edge_dropped": "the edge dropped 3", "tracker_missed": "found 3 missing",
            "tracker_queue_dropped": "dropped 3 from its queue"}[counter] in probs[0]


def test_windows_lost_before_the_missions_do_not_count_when_the_missions_lost_none():
    # a starved edge at start-up drops windows that reach no scored frame; the counters say so
    before_only = dict(WINDOWS, edge_dropped=12, during_missions={"edge_dropped": 0, "tracker_missed": 0,
                                                                  "tracker_queue_dropped": 0})
    assert verdict(**good_run(windows=before_only)) == (True, [])
    during = dict(before_only, during_missions={"edge_dropped": 2, "tracker_missed": 1, "tracker_queue_dropped": 0})
    assert problems_of(windows=during) == [
        "3 event window(s) lost while the missions ran: the edge dropped 2, the tracker found 1 missing and "
        "dropped 0 from its queue"]


def test_unknown_event_windows():
    assert problems_of(windows=None) == [
        "no edge and tracker status in arena.mcap: whether event windows were lost is unknown"]


def test_no_ground_truth_is_not_a_score():
    assert problems_of(truth_rows=0, scores={"n_gt": 0, "n_frames": 0, "mota": None}) == [
        "truth.csv has no rows in the scored span: nothing to score against (MOTA, IDF1, HOTA n/a)"]
    assert problems_of(scores={"n_gt": 0, "n_frames": 40, "mota": None}) == [
        "no ground truth in the 40 scored frame(s): MOTA, IDF1, HOTA n/a"]


def test_not_scored_or_no_report():
    assert problems_of(scores=None, score_error="tracks.csv missing") == ["not scored: tracks.csv missing"]
    assert problems_of(report_error="OSError: disk full") == ["no report.md: OSError: disk full"]


def test_every_problem_is_listed_in_order():
    ok, probs = verdict(**good_run(interrupted=True, killed=["bridge"], exit_codes={"bridge": -9},
                                   windows=dict(WINDOWS, edge_dropped=1)))
    assert not ok and [p.split(" ")[0] for p in probs] == ["interrupted", "bridge", "1"], probs

"""The drill check of bench/bench_demo_realtime.py (``closed_loop_drill``): a run passes only when
every mission ran closed-loop on its tracks or the demo's summary names the ones that did not."""

from __future__ import annotations

import importlib.util
from pathlib import Path

BENCH = Path(__file__).resolve().parents[2] / "bench" / "bench_demo_realtime.py"


def _drill():
    spec = importlib.util.spec_from_file_location("bench_demo_realtime", BENCH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.closed_loop_drill


def _m(robot, control="closed", used=120, odo_s=0.0, at_end=False):
    return {"robot": robot, "control": control,
            "fusion": {"tracks_used": used, "odometry_fallbacks": int(odo_s > 0), "odometry_only_s": odo_s,
                       "on_odometry_at_end": at_end}}


def test_every_mission_on_its_tracks_passes_and_the_line_gives_each_robot():
    ok, line = _drill()([_m("zumo1"), _m("zumo2", used=80)], {"ok": True, "problems": []}, robots=2)
    assert ok
    assert "zumo1 closed, 120 tracks, odometry 0.0 s" in line and "zumo2 closed, 80 tracks" in line


def test_a_mission_without_tracks_fails_unless_the_problems_name_it():
    drill = _drill()
    manifests = [_m("zumo1"), _m("zumo2", used=0, odo_s=20.0, at_end=True)]
    ok, line = drill(manifests, {"ok": True, "problems": []}, robots=2)
    assert not ok and "DRILL FAILED: zumo2 (no tracks)" in line
    said = {"ok": False, "problems": ["zumo2 was closed-loop but used no tracks (fusion.tracks_used = 0)"]}
    assert drill(manifests, said, robots=2)[0]


def test_a_fallback_to_odometry_fails_unless_the_summary_lists_it():
    drill = _drill()
    manifests = [_m("zumo1", odo_s=1.4)]
    ok, line = drill(manifests, {"ok": True, "problems": []}, robots=1)
    assert not ok and "zumo1 (1.4 s on odometry) not in odometry_fallbacks" in line
    summary = {"ok": True, "problems": [], "odometry_fallbacks": {"zumo1": {"fallbacks": 1, "seconds": 1.4}}}
    assert drill(manifests, summary, robots=1)[0]


def test_an_open_loop_mission_or_a_missing_manifest_in_a_run_called_ok_fails():
    drill = _drill()
    assert not drill([_m("zumo1", control="open")], {"ok": True, "problems": []}, robots=1)[0]
    ok, line = drill([_m("zumo1")], {"ok": True, "problems": []}, robots=2)
    assert not ok and "1 mission(s) left no manifest" in line
    assert drill([_m("zumo1")], {"ok": False, "problems": ["zumo2's mission never closed its log"]}, robots=2)[0]

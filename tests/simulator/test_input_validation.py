"""Bad simulator input gets a clear error naming what to fix (issue 20): every field of
Scenario and DvsParams is checked for type and finite range on construction, and `arena sim`
refuses a lab robot's marker id beyond the ArUco dictionary in one line, exit 2."""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np
import pytest

from simulator.dvs import DvsParams
from simulator.scenarios import Scenario
from simulator.world import RobotSpec

NAN, INF = float("nan"), float("inf")

SCENARIO_BAD = {
    "n_robots": [-1, 51, 2.0, "2", True, None],
    "pattern": ["zigzag", 1, None],
    "power": [NAN, INF, 0.0, 1.5, "1"],
    "duration_s": [NAN, INF, 0.0, -1.0, "5"],
    "lighting": ["disco", None],
    "seed": [-1, 1.5, "0", NAN],
    "width": [8, 5000, 640.0, "640"],
    "height": [8, 5000, NAN, "480"],
    "colours": ["black", [(1, 2)], [(0, 0, 300)], [(0.5, 0, 0)]],
    "markers": ["yes", 1, None, NAN],
    "stagger_s": [NAN, -0.1, "0.3"],
    "dvs": ["default", {"flicker_hz": 100}],
    "arena_m": [NAN, INF, 0.0, "1.83"],
    "body": ["sphere", None],
    "shadow": ["no", 0, None],
    "camera_height_m": [NAN, INF, 0.1, "2.5"],
    "nadir_offset_m": [(NAN, 0.0), (INF, 0.0), (5.0, 0.0), "0,0", (0.0,), ("0", "0")],
    "spin_dps": [NAN, INF, 0.0, -150.0, "150", True],
}

DVS_BAD = {
    "threshold_on": [NAN, INF, 0.0, "0.25"],
    "threshold_off": [NAN, -0.1, "0.25"],
    "threshold_sigma": [NAN, -0.01, "0"],
    "refractory_us": [NAN, -1, 500.0, "500"],
    "cutoff_hz": [NAN, INF, 0.0, "400"],
    "min_cutoff_hz": [NAN, 0.0, "5"],
    "dark_current": [NAN, -0.1, "0.003"],
    "noise_rate_hz": [NAN, INF, -1.0, "0.5"],
    "noise_on_fraction": [NAN, 1.5, "0.5"],
    "shot_noise": ["no", 1, None, NAN],
    "leak_rate_hz": [NAN, INF, -1.0, "0.15"],
    "vignetting": [NAN, -1.0, 9.0, "2"],
    "lamp_falloff": [NAN, 0.8, -0.1, "0.1"],
    "hot_pixels": [NAN, -1, 5.0, "5"],
    "hot_rate_hz": [NAN, INF, -1.0, "50"],
    "step_us": [NAN, 0, 5000, 1000.0, "1000"],
    "trace_every": [NAN, 0, 11, True, 2.0],
    "flicker_hz": [NAN, INF, -1.0, "100"],
    "flicker_depth": [NAN, 1.0, -0.1, "0.2"],
}


def test_every_field_of_scenario_and_dvsparams_has_bad_values_tried():
    assert set(SCENARIO_BAD) == {f.name for f in dataclasses.fields(Scenario)}
    assert set(DVS_BAD) == {f.name for f in dataclasses.fields(DvsParams)}


@pytest.mark.parametrize("field,value", [(f, v) for f, vs in SCENARIO_BAD.items() for v in vs])
def test_scenario_refuses_a_bad_field_naming_it(field, value):
    with pytest.raises(ValueError, match=rf"Scenario\.{field}\b"):
        Scenario(**{field: value})


@pytest.mark.parametrize("field,value", [(f, v) for f, vs in DVS_BAD.items() for v in vs])
def test_dvsparams_refuses_a_bad_field_naming_it(field, value):
    with pytest.raises(ValueError, match=rf"DvsParams\.{field} must be"):
        DvsParams(**{field: value})


def test_defaults_none_for_off_and_numpy_numbers_still_construct():
    assert Scenario().spin_dps == 150.0 and DvsParams().noise_rate_hz is None
    assert Scenario(spin_dps=None).robot_specs()[0].spin_dps_full is None   # the old kinematics
    sc = Scenario(n_robots=np.int64(2), power=np.float64(0.5), seed=np.int64(3), markers=np.bool_(True),
                  colours=[(np.int64(1), 2, 3), (4, 5, 6)], nadir_offset_m=[0.1, -0.1], dvs=DvsParams(),
                  duration_s=2)
    assert [s.marker_id for s in sc.robot_specs()] == [0, 1]
    assert dataclasses.replace(sc, lighting="dark").lighting == "dark"
    assert DvsParams(noise_rate_hz=0, refractory_us=np.int64(0), flicker_hz=100).flicker_hz == 100


def test_robot_spec_refuses_a_marker_the_dictionary_lacks():
    with pytest.raises(ValueError, match=r"RobotSpec\.marker_id must be an integer in \[0, 49\].*got 60"):
        RobotSpec("r", (0, 0, 0), marker_id=60)
    assert RobotSpec("r", (0, 0, 0), marker_id=49).marker_id == 49


def _lab(tmp_path, marker_id):
    p = tmp_path / "lab.toml"
    p.write_text(f'[[robots]]\nname = "zumo1"\ncolor = "red"\nmarker_id = {marker_id}\n')
    return p


def test_sim_lab_marker_beyond_the_dictionary_is_one_line_exit_2(tmp_path, capsys):
    """The outside tester's case: `arena sim --lab LAB.toml --markers` with marker_id 60 (was a
    traceback from the camera's marker pattern)."""
    from simulator.cli import main

    with pytest.raises(SystemExit) as exc:
        main(["--lab", str(_lab(tmp_path, 60)), "--markers", "--fast", "--duration", "0.01", "--no-webcam",
              "--no-robots", "--camera-port", "0"])
    err = capsys.readouterr().err
    assert exc.value.code == 2, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert "marker_id" in err and "'zumo1'" in err and "60" in err and "[0, 49]" in err, err


def test_sim_checks_lab_markers_itself(tmp_path, capsys, monkeypatch):
    """Whatever the lab reader lets through, the simulator names the robot, the id and the range."""
    import arena.config
    from simulator.cli import _robots_from_args

    real = arena.config.load_lab_config

    def loose(path):   # a lab whose reader did not bound the marker ids
        cfg = real(_lab(tmp_path, 7))
        cfg.robots[0].marker_id = 60
        return cfg

    monkeypatch.setattr(arena.config, "load_lab_config", loose)
    args = argparse.Namespace(lab=str(tmp_path / "lab.toml"), width=None, height=None, camera_port=None,
                              robots=None, autopilot="none", markers=True, seed=0)
    with pytest.raises(SystemExit) as exc:
        _robots_from_args(args)
    err = capsys.readouterr().err
    assert exc.value.code == 2
    assert "robot 'zumo1' has marker_id 60" in err and "0..49" in err, err


@pytest.mark.parametrize("flags,expected", [(["--flicker", "nan"], "--flicker"), (["--flicker", "inf"], "--flicker"),
                                            (["--duration", "nan"], "--duration"), (["--duration", "inf"], "--duration")])
def test_sim_flags_nan_and_inf_are_usage_errors(flags, expected, capsys):
    from simulator.cli import _check_args, add_arguments

    p = argparse.ArgumentParser()
    add_arguments(p)
    with pytest.raises(SystemExit) as exc:
        _check_args(p.parse_args(flags))
    err = capsys.readouterr().err
    assert exc.value.code == 2 and expected in err, err


def test_the_marker_range_is_one_number_everywhere():
    """The CLI keeps its own copy (its parser must not import numba); the lab check and the
    robot model agree with it."""
    import arena.config
    import simulator.cli
    import simulator.world

    assert simulator.cli.MARKER_IDS == simulator.world.MARKER_IDS == arena.config.ARUCO_MARKER_IDS == 50

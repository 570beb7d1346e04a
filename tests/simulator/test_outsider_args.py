"""`arena sim` refuses absurd physical values at parse time (an outsider's report: `--flicker 1e9`
was accepted): every numeric flag is bounded to a physical range, and the error names the flag,
the range and the unit. Parse errors only: nothing is simulated."""

from __future__ import annotations

import argparse

import pytest

from simulator.cli import add_arguments


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="arena sim")
    add_arguments(p)
    return p


@pytest.mark.parametrize("flag,value,expected", [
    ("--flicker", "1e9", "[0, 500] Hz"),
    ("--flicker", "501", "[0, 500] Hz"),
    ("--flicker", "-1", "[0, 500] Hz"),
    ("--flicker", "nan", "[0, 500] Hz"),
    ("--duration", "1e12", "seconds in [0, 86400]"),
    ("--duration", "-1", "seconds in [0, 86400]"),
    ("--duration", "inf", "seconds in [0, 86400]"),
    ("--power", "nan", "[0.05, 1]"),
    ("--power", "inf", "[0.05, 1]"),
    ("--telemetry-hz", "1e9", "[1, 1000] Hz"),
    ("--telemetry-hz", "nan", "[1, 1000] Hz"),
    ("--publish-truth-hz", "-inf", "[1, 100] Hz"),
    ("--seed", "-1", "[0, 4294967295]"),
    ("--seed", "1e3", "an integer"),
    ("--robots", "-1", "[0, 50] robots"),
    ("--width", "100000", "[16, 4096] px"),
    ("--height", "nan", "[16, 4096] px"),
    ("--camera-port", "70000", "[0, 65535]"),
    ("--webcam-port", "-5", "[0, 65535]"),
    ("--robot-base-port", "1e5", "[0, 65535]"),
])
def test_absurd_values_are_usage_errors_naming_range_and_unit(flag, value, expected, capsys):
    with pytest.raises(SystemExit) as exc:
        _parser().parse_args([f"{flag}={value}"])
    err = capsys.readouterr().err
    assert exc.value.code == 2, err
    assert f"argument {flag}:" in err and expected in err and repr(value) in err, err


def test_physical_values_still_parse():
    a = _parser().parse_args(["--flicker", "500", "--duration", "0", "--power", "0.5", "--telemetry-hz", "1000",
                              "--seed", "4294967295", "--robots", "50", "--camera-port", "0",
                              "--publish-truth-hz", "100", "--width", "16", "--height", "4096"])
    assert (a.flicker, a.duration, a.power, a.telemetry_hz, a.seed, a.robots, a.camera_port) == \
        (500.0, 0.0, 0.5, 1000.0, 4294967295, 50, 0)
    assert isinstance(a.seed, int) and isinstance(a.robots, int) and isinstance(a.flicker, float)
    a = _parser().parse_args(["--flicker", "100", "--duration", "86400"])
    assert (a.flicker, a.duration) == (100.0, 86400.0)


def test_dvs_flicker_is_bounded_by_half_the_internal_rate():
    """The camera samples the light once a step: a flicker beyond half that rate would alias."""
    from simulator.dvs import DvsParams

    assert DvsParams(flicker_hz=500.0).flicker_hz == 500.0
    with pytest.raises(ValueError, match=r"flicker_hz must be .*\[0, 500\] Hz"):
        DvsParams(flicker_hz=1e9)
    with pytest.raises(ValueError, match=r"flicker_hz must be .*\[0, 1000\] Hz"):
        DvsParams(flicker_hz=1001.0, step_us=500)
    assert DvsParams(flicker_hz=1000.0, step_us=500).flicker_hz == 1000.0


def test_robot_ports_beyond_65535_are_a_usage_error(capsys):
    from simulator.cli import main

    with pytest.raises(SystemExit) as exc:
        main(["--robots", "4", "--robot-base-port", "65534", "--no-webcam", "--camera-port", "0",
              "--fast", "--duration", "0.01"])
    err = capsys.readouterr().err
    assert exc.value.code == 2, err
    assert "--robot-base-port 65534 + 4 robots" in err and "at most 65532" in err, err


def test_the_cli_flicker_bound_is_the_dvs_models():
    """The parser keeps its own number (it must not import numba); the model's default step agrees."""
    from simulator.cli import FLICKER_MAX_HZ
    from simulator.dvs import DvsParams

    assert FLICKER_MAX_HZ == 0.5e6 / DvsParams().step_us == 500.0

"""`arena experiment` and `arena demo` refuse absurd options before running anything (an
outsider's report: `arena experiment --out ''` was accepted and wrote into the current folder).
In-process, argument errors only: a run that would start is stopped by a stub."""

from __future__ import annotations

import argparse

import pytest


def _main(*args: str) -> int:
    from arena.cli import main

    try:
        return main(list(args))
    except SystemExit as exc:
        return exc.code


@pytest.fixture
def no_study(monkeypatch):
    """Fail the test instead of running a study (the CLI imports run_paper_study when it runs)."""
    import demo.experiment

    def refuse(*a, **kw):
        raise AssertionError(f"the study started with out={a[0]!r}")
    monkeypatch.setattr(demo.experiment, "run_paper_study", refuse)


@pytest.mark.parametrize("out,expected", [("", "empty path"), ("   ", "empty path"), ("FILE", "existing file")])
def test_experiment_refuses_an_empty_or_file_output(out, expected, tmp_path, monkeypatch, capsys, no_study):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "FILE").write_text("x")
    code = _main("experiment", "paper", "--out", out, "--quick")
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.startswith("arena experiment: --out: ") and expected in err and "Traceback" not in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["FILE"]   # nothing written


def test_experiment_refuses_a_negative_seed(tmp_path, capsys, no_study):
    code = _main("experiment", "paper", "--out", str(tmp_path / "s"), "--seed", "-1")
    err = capsys.readouterr().err
    assert code == 2 and "--seed must be an integer in 0..4294967295, got -1" in err, err


def test_the_study_itself_refuses_an_empty_or_file_output(tmp_path, monkeypatch):
    import demo.experiment
    from demo.experiment import ExperimentError, run_paper_study

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(demo.experiment, "_steps", lambda plan, parts: [])   # nothing to run either way
    with pytest.raises(ExperimentError, match="empty path"):
        run_paper_study("", progress=False)
    (tmp_path / "f").write_text("x")
    with pytest.raises(ExperimentError, match="existing file"):
        run_paper_study(tmp_path / "f", progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f"]


def _demo_args(*flags: str) -> argparse.Namespace:
    from demo.cli import register

    p = argparse.ArgumentParser()
    register(p.add_subparsers())
    return p.parse_args(["demo", "--markers", *flags])   # markers: no colour check (no simulator import)


@pytest.mark.parametrize("flags,expected", [
    (["--duration", "1e9"], "--duration must be at most 86400 s"),
    (["--duration", "nan"], "--duration must be a positive number of seconds"),
    (["--seed", "-1"], "--seed must be an integer in 0..4294967295"),
    (["--view-port", "0"], "--view-port must be a TCP port in 1..65535"),
    (["--view-port", "70000"], "--view-port must be a TCP port in 1..65535"),
    (["--power", "nan"], "--power must be a fraction of full power in [0.05, 1]"),
    (["--out", ""], "--out is empty"),
])
def test_demo_absurd_options_are_usage_errors(flags, expected):
    from demo.cli import _usage_error

    err = _usage_error(_demo_args(*flags))
    assert err is not None and expected in err, err


def test_demo_output_under_a_file_is_a_usage_error(tmp_path):
    from demo.cli import _usage_error

    (tmp_path / "f").write_text("x")
    for out in (tmp_path / "f", tmp_path / "f" / "sub"):
        err = _usage_error(_demo_args("--out", str(out)))
        assert err is not None and f"{tmp_path / 'f'} is a file, not a folder" in err, err
    assert _usage_error(_demo_args("--out", str(tmp_path / "new" / "runs"), "--duration", "86400")) is None

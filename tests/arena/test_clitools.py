"""arena.clitools: one help layout and one way for every command to open Zenoh and exit on a
SessionError (one line ``arena CMD: <error>``, exit 2 for wrong settings, 1 when nothing answered)."""

from __future__ import annotations

import argparse
import ast
from pathlib import Path

import pytest

from arena.clitools import exit_on_session_error, formatter, session_or_exit
from arena.session import SessionError, ZenohSettings

REPO = Path(__file__).resolve().parents[2]

#: the command lines that open Zenoh through arena.clitools
CLIS = ["arena/cli.py", "viewer/cli.py", "ros2/cli.py", "recorder/cli.py", "groundtruth/cli.py", "tracker/cli.py",
        "tracker/service.py", "robot_bridge/cli.py", "camera_edge/cli.py", "simulator/cli.py"]


def test_a_wrong_setting_is_one_line_and_exit_2(capsys, tmp_path):
    with pytest.raises(SystemExit) as exc:
        with session_or_exit(ZenohSettings(config_file=str(tmp_path / "none.json5")), "arena x"):
            raise AssertionError("no session may open")
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("arena x: ") and "none.json5" in err and err.count("\n") == 1


def test_no_router_is_exit_1_and_code_overrides_it(capsys):
    no_router = ZenohSettings(mode="client", connect=["tcp/127.0.0.1:9"])
    with pytest.raises(SystemExit) as exc:
        with session_or_exit(no_router, "arena y"):
            pass
    assert exc.value.code == 1
    assert capsys.readouterr().err.startswith("arena y: cannot open Zenoh (client mode, connecting to tcp/127.0.0.1:9)")
    with pytest.raises(SystemExit) as exc:
        with session_or_exit(no_router, "arena y", code=2):
            pass
    assert exc.value.code == 2


def test_a_session_error_in_the_block_exits_and_other_errors_pass(capsys):
    with pytest.raises(SystemExit) as exc:
        with exit_on_session_error("arena z"):
            raise SessionError("no such thing", exit_code=1)
    assert exc.value.code == 1 and capsys.readouterr().err == "arena z: no such thing\n"
    with pytest.raises(ValueError):
        with exit_on_session_error("arena z"):
            raise ValueError("not mine")


def test_formatter_keeps_the_examples_as_written():
    p = argparse.ArgumentParser(prog="arena t", formatter_class=formatter, epilog="Examples:\n  arena t  # a\n  arena t -x")
    p.add_argument("--a-long-option-name", help="h")
    text = p.format_help()
    assert "Examples:\n  arena t  # a\n  arena t -x" in text
    assert "  --a-long-option-name A_LONG_OPTION_NAME\n" in text     # longer than 32 columns: help below


def _session_handlers(path: Path) -> list[str]:
    """Names of the functions of ``path`` that catch SessionError or define a help formatter."""
    tree = ast.parse(path.read_text())
    found = []
    for fn in ast.walk(tree):
        if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        if any(isinstance(n, ast.Attribute) and n.attr == "RawDescriptionHelpFormatter" for n in ast.walk(fn)):
            found.append(f"{fn.name} defines a help formatter")
        for n in ast.walk(fn):
            if isinstance(n, ast.ExceptHandler) and n.type is not None and "SessionError" in ast.unparse(n.type):
                found.append(f"{fn.name} catches SessionError")
    return found


@pytest.mark.parametrize("rel", CLIS)
def test_the_clis_use_the_shared_helpers(rel):
    found = _session_handlers(REPO / rel)
    # arena.cli.main keeps the catch-all for commands that let a SessionError reach it
    assert found == (["main catches SessionError"] if rel == "arena/cli.py" else []), found

"""One exit-code policy for every command: 2 for a usage or input error (a wrong flag value, a
missing or unreadable file, a wrong lab config), 1 for a runtime failure (nothing answered, a
service failed), each with one line on stderr and no traceback."""

from __future__ import annotations

import subprocess

import pytest

from tests.conftest import arena_cmd

NO_ROUTER = ["-m", "client", "-e", "tcp/127.0.0.1:9"]

USAGE = [
    ["sim", "--robots", "99"],
    ["sim", "--lab", "/nonexistent/lab.toml"],
    ["demo", "--robots", "99"],
    ["convert", "/nonexistent/in.raw", "out.npz"],
    ["record", "/nonexistent/dir/out.mcap"],
    ["replay", "/nonexistent/run"],
    ["eval", "--tracks", "/nonexistent/tracks.csv", "--truth", "/nonexistent/truth.csv"],
    ["track", "--input", "/nonexistent/in.raw"],
    ["edge", "--lab", "/nonexistent/lab.toml", "--camera", "cam0"],
    ["bridge", "mission", "zumo1", "circle", "--power", "500", *NO_ROUTER],
    ["bridge", "run", "--lab", "/nonexistent/lab.toml"],
    ["watch", "--zenoh-config", "/nonexistent/zenoh.json5", "--duration", "1"],
]

RUNTIME = [
    ["status", "--wait", "0", *NO_ROUTER],
]


def _run(argv, tmp_path):
    return subprocess.run(arena_cmd(*argv), capture_output=True, text=True, timeout=60, cwd=tmp_path)


@pytest.mark.parametrize("argv", USAGE, ids=lambda a: " ".join(a[:3]))
def test_usage_and_input_errors_exit_2(argv, tmp_path):
    r = _run(argv, tmp_path)
    assert r.returncode == 2, (r.returncode, r.stderr)
    assert "Traceback" not in r.stderr and r.stderr.strip()


@pytest.mark.parametrize("argv", RUNTIME, ids=lambda a: " ".join(a[:3]))
def test_runtime_failures_exit_1(argv, tmp_path):
    r = _run(argv, tmp_path)
    assert r.returncode == 1, (r.returncode, r.stderr)
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1

"""``arena router``: it claims only the connections Zenoh made (a dialled router that does not
answer is retried, not "connected to"), and its dial credentials come in pairs."""

from __future__ import annotations

import os
import subprocess

from tests.conftest import arena_cmd, free_port, wait_for_line


def _router(*args: str, env: dict | None = None, timeout: float = 30) -> subprocess.CompletedProcess:
    return subprocess.run(arena_cmd("router", *args), capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, **(env or {})})


def test_a_dead_endpoint_is_dialled_not_connected():
    r = _router("-l", f"tcp/127.0.0.1:{free_port()}", "-e", "tcp/127.0.0.1:1", "--duration", "1")
    assert r.returncode == 0, r.stderr
    first = r.stdout.splitlines()[0]
    assert "listening on" in first and "dialing tcp/127.0.0.1:1 (retried until it answers)" in first
    assert "connected" not in r.stdout, r.stdout


def test_a_router_that_answers_is_reported_connected(router):
    proc = subprocess.Popen(arena_cmd("router", "-l", f"tcp/127.0.0.1:{free_port()}", "-e", router.endpoint),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        wait_for_line(proc, "listening on")
        line = wait_for_line(proc, "connected to router")
        assert f"({router.endpoint})" in line, line
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def test_only_one_of_user_and_password_is_one_line_naming_both():
    for only in ("ARENA_ZENOH_USER", "ARENA_ZENOH_PASSWORD"):
        other = {"ARENA_ZENOH_USER": "", "ARENA_ZENOH_PASSWORD": ""}
        r = _router("-l", f"tcp/127.0.0.1:{free_port()}", "--duration", "0.1", env={**other, only: "x"})
        assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and "ARENA_ZENOH_USER and ARENA_ZENOH_PASSWORD go together" in lines[0]
        assert f"only {only} is set" in lines[0] and r.stdout == ""


def test_every_client_refuses_only_one_of_user_and_password():
    """Not only the router: a client with a half-written env file (a user without its password, or
    the reverse) gets one line naming both variables, exit 2, instead of an empty password or
    silently no authentication."""
    import subprocess
    import sys

    for only in ("ARENA_ZENOH_USER", "ARENA_ZENOH_PASSWORD"):
        env = {**os.environ, "ARENA_ZENOH_USER": "", "ARENA_ZENOH_PASSWORD": "", only: "x",
               "ARENA_ZENOH_CONNECT": f"tcp/127.0.0.1:{free_port()}"}
        r = subprocess.run([sys.executable, "-m", "arena", "status", "--wait", "0.5"], capture_output=True,
                           text=True, timeout=60, env=env)
        assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
        assert "ARENA_ZENOH_USER" in r.stderr and "ARENA_ZENOH_PASSWORD" in r.stderr and "go together" in r.stderr
        assert f"{only} is set but" in r.stderr and "Traceback" not in r.stderr, r.stderr

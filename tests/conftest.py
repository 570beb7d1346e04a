"""Fixtures shared by every test package: free ports, a real `arena router` subprocess, shared data."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

# services started by tests keep their state files (the tracker's fleet snapshot) out of
# ~/.local/state/arena: per test (fixture below), and for environments copied at import
os.environ["ARENA_STATE_DIR"] = tempfile.mkdtemp(prefix="arena-test-state-")
SHARED_DATA = REPO.parent / "shared" / "data"


def free_port() -> int:
    """An ephemeral TCP port on loopback that is free right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def arena_cmd(*args: str) -> list[str]:
    """Command line running the `arena` CLI of this checkout with the current interpreter."""
    return [sys.executable, "-m", "arena", *args]


def wait_for_line(proc: subprocess.Popen, needle: str, timeout: float = 20.0) -> str:
    """Read proc's stdout until a line contains ``needle``; fail with what was printed otherwise."""
    seen = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            if proc.poll() is not None:
                break
            continue
        seen.append(line)
        if needle in line:
            return line
    raise AssertionError(f"{needle!r} not printed within {timeout}s; got: {''.join(seen)!r}")


@pytest.fixture(autouse=True)
def _isolated_state_dir(tmp_path_factory, monkeypatch):
    """Services' state files (the tracker's fleet snapshot) go to a fresh folder per test, not
    to ~/.local/state/arena, so no test restores another's tracks."""
    monkeypatch.setenv("ARENA_STATE_DIR", str(tmp_path_factory.mktemp("state")))


class Router:
    """A real `arena router` subprocess on an ephemeral loopback port."""

    def __init__(self) -> None:
        self.port = free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.proc = subprocess.Popen(arena_cmd("router", "-l", self.endpoint), stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
        wait_for_line(self.proc, "listening on")

    @property
    def args(self) -> list[str]:
        """CLI flags that connect a service to this router."""
        return ["-e", self.endpoint]

    def settings(self, mode: str = "peer"):
        from arena.session import ZenohSettings

        return ZenohSettings(mode=mode, connect=[self.endpoint])

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=5)


@pytest.fixture
def router():
    """A running `arena router` subprocess; yields a :class:`Router` (``.endpoint``, ``.args``)."""
    r = Router()
    try:
        yield r
    finally:
        r.stop()


@pytest.fixture
def shared_data() -> Path:
    """The shared real recordings folder; skips the test when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared recordings not found at {SHARED_DATA} (clone with ../shared beside the repo)")
    return SHARED_DATA

"""Start, watch and stop a set of service processes (the demo's process supervisor).

Each process gets its own log file; its output is also scanned for a readiness line. Children
are started with ``PR_SET_PDEATHSIG`` so they die with the launcher even if it is killed with
SIGKILL (no orphans), and :meth:`Supervisor.stop_all` stops them in the order given, each with
SIGTERM then SIGKILL after a grace period.
"""

from __future__ import annotations

import ctypes
import functools
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

log = logging.getLogger("arena.demo")

_PR_SET_PDEATHSIG = 1


def _child_setup(nice: int = 0) -> None:  # runs in the child between fork and exec
    # a process group of its own: a terminal's Ctrl-C (SIGINT to the whole foreground group)
    # reaches only the launcher, which then stops its children in order, robots first
    os.setpgrp()
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)  # die with the launcher
    except OSError:  # not Linux: the launcher's own cleanup still applies
        pass
    if nice:
        os.nice(nice)


@dataclass
class ProcSpec:
    """A process to run: name, argv, the line that says it is ready, and how to stop it."""

    name: str
    argv: list[str]
    ready: str | None = None  # substring of an output line that means "ready"
    ready_check: Callable[[], bool] | None = None  # or: a predicate polled until true (e.g. liveliness)
    ready_timeout_s: float = 30.0
    stop_timeout_s: float = 5.0
    env: dict = field(default_factory=dict)
    on_line: Callable[[str], None] | None = None  # called for every output line
    nice: int = 0  # added to the process's niceness (> 0: yields the CPU to the others)


class Proc:
    """A running child: its Popen, log file and readiness state."""

    def __init__(self, spec: ProcSpec, log_dir: Path):
        self.spec = spec
        self.log_path = log_dir / f"{spec.name}.log"
        self._log = open(self.log_path, "w", buffering=1, encoding="utf-8")
        env = {**os.environ, "PYTHONUNBUFFERED": "1", **spec.env}
        self.popen = subprocess.Popen(spec.argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                      env=env, preexec_fn=functools.partial(_child_setup, spec.nice), bufsize=1,
                                      errors="replace")
        self.ready = threading.Event()
        self.lines: list[str] = []
        self.stop_requested = False  # set by :meth:`stop`
        self.exited_early = False    # it had exited before :meth:`stop` was first called
        self.killed = False          # :meth:`stop` had to SIGKILL it after the grace period
        if spec.ready is None and spec.ready_check is None:
            self.ready.set()
        self._reader = threading.Thread(target=self._read, name=f"log-{spec.name}", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.popen.stdout is not None
        for line in self.popen.stdout:
            self._log.write(line)
            if len(self.lines) < 2000:
                self.lines.append(line)
            if self.spec.ready and self.spec.ready in line:
                self.ready.set()
            if self.spec.on_line is not None:
                try:
                    self.spec.on_line(line.rstrip("\n"))
                except Exception:  # noqa: BLE001 - a display callback must not kill the reader
                    pass
        self._log.flush()

    def wait_ready(self) -> None:
        """Block until the readiness line was printed; raise if the process died or timed out."""
        deadline = time.monotonic() + self.spec.ready_timeout_s
        while not self.ready.wait(0.05):
            if self.spec.ready_check is not None and self.spec.ready_check():
                self.ready.set()
                break
            if self.popen.poll() is not None:
                raise RuntimeError(f"{self.spec.name} exited with code {self.popen.returncode} before it was ready; "
                                   f"see {self.log_path}:\n{''.join(self.lines[-15:])}")
            if time.monotonic() > deadline:
                raise RuntimeError(f"{self.spec.name} was not ready after {self.spec.ready_timeout_s:.0f} s; "
                                   f"see {self.log_path}:\n{''.join(self.lines[-15:])}")

    def alive(self) -> bool:
        return self.popen.poll() is None

    def stop(self) -> int | None:
        """SIGTERM, then SIGKILL after the grace period; returns the exit code. Records whether
        the process had already exited (:attr:`exited_early`) or had to be killed (:attr:`killed`)."""
        first = not self.stop_requested
        self.stop_requested = True
        if self.popen.poll() is None:
            try:
                self.popen.send_signal(signal.SIGTERM)
                self.popen.wait(timeout=self.spec.stop_timeout_s)
            except subprocess.TimeoutExpired:
                log.warning("%s did not stop within %.0f s: killing it", self.spec.name, self.spec.stop_timeout_s)
                self.killed = True
                self.popen.kill()
                self.popen.wait(timeout=5)
        elif first:
            self.exited_early = True
        self._reader.join(timeout=2)
        self._log.close()
        return self.popen.returncode


class Supervisor:
    """Owns every child process of the demo; a context manager that always stops them."""

    def __init__(self, log_dir: Path):
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.procs: dict[str, Proc] = {}

    def start(self, spec: ProcSpec, wait: bool = True) -> Proc:
        log.info("starting %s: %s", spec.name, " ".join(spec.argv))
        p = Proc(spec, self.log_dir)
        self.procs[spec.name] = p
        if wait:
            p.wait_ready()
        return p

    def dead(self) -> list[str]:
        """Names of children that have exited."""
        return [n for n, p in self.procs.items() if not p.alive()]

    def killed(self) -> list[str]:
        """Names of children that :meth:`stop_all` had to SIGKILL (they ignored SIGTERM)."""
        return [n for n, p in self.procs.items() if p.killed]

    def died(self) -> dict[str, int | None]:
        """Children that exited by themselves, before they were asked to stop -> exit code."""
        return {n: p.popen.returncode for n, p in self.procs.items() if p.exited_early}

    def stop_all(self, first: list[str] | tuple = ()) -> dict[str, int | None]:
        """Stop the children named in ``first`` in that order, then the rest in reverse start order."""
        codes = {}
        order = [n for n in first if n in self.procs] + [n for n in reversed(self.procs) if n not in first]
        for name in order:
            codes[name] = self.procs[name].stop()
        return codes

    def __enter__(self) -> "Supervisor":
        return self

    def __exit__(self, *exc) -> None:
        self.stop_all()


def python_cmd(*args: str) -> list[str]:
    """argv that runs ``arena ARGS`` with this interpreter (works without the console script on PATH)."""
    return [sys.executable, "-m", "arena", *args]

"""`arena bridge run` as a subprocess, with the flags the demo gives it (`-e ROUTER`, no `-m`):
the router watchdog, SIGTERM, robots whose device is missing, exit codes and the commands' help."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from contextlib import ExitStack, contextmanager

import pytest
from bridge_testkit import running_world, wait_for

from arena.keys import alive_key, status_key
from arena.messages import Status
from arena.session import open_session
from simulator.robot_emulator import RobotEmulatorServer
from tests.conftest import Router, arena_cmd  # Router: the `router` fixture's type

ENV = {**os.environ, "PYTHONUNBUFFERED": "1"}


def bridge_cmd(robots: dict[str, str], router: Router, log_dir, *extra: str) -> list[str]:
    """The bridge's command line as demo/cli.py builds it."""
    flags = [a for name, url in robots.items() for a in ("--robot", f"{name}={url}")]
    return arena_cmd("bridge", "run", *flags, "--name", "demo", "--log-dir", str(log_dir), *extra, *router.args)


class BridgeProcess:
    """`arena bridge run` as a subprocess; every line it prints is kept (a reader thread)."""

    def __init__(self, argv):
        self.proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=ENV)
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.lines.append(line)

    def wait_line(self, needle: str, timeout: float = 60.0) -> str:
        found = lambda: next((ln for ln in self.lines if needle in ln), None)  # noqa: E731
        if not wait_for(lambda: found() or self.proc.poll() is not None, timeout, step=0.02) or not found():
            raise AssertionError(f"{needle!r} not printed within {timeout} s; got: {self.output()!r}")
        return found()

    def wait(self, timeout: float) -> str:
        """Wait for the exit (raises subprocess.TimeoutExpired); returns everything printed."""
        self.proc.wait(timeout=timeout)
        self._reader.join(timeout=5)
        return self.output()

    def output(self) -> str:
        return "".join(self.lines)


@contextmanager
def bridge_process(argv):
    bp = BridgeProcess(argv)
    try:
        yield bp
    finally:
        if bp.proc.poll() is None:
            bp.proc.kill()
        bp.proc.wait(timeout=10)


@contextmanager
def fleet(n: int):
    """A world of ``n`` robots, one emulator each."""
    starts = [(0.5 + 0.4 * i, 0.9, 1.5708) for i in range(n)]
    with running_world(n, starts=starts) as world, ExitStack() as stack:
        emus = [stack.enter_context(RobotEmulatorServer(world, i)) for i in range(n)]
        yield world, {f"r{i + 1}": e.url for i, e in enumerate(emus)}


def start_missions(router: Router, robots) -> None:
    """`arena bridge mission all circle` (the CLI client, as an operator does)."""
    r = subprocess.run(arena_cmd("bridge", "mission", "all", "circle", "--radius", "0.15", "--laps", "20",
                                 "--power", "50", "--timeout", "10", *router.args),
                       capture_output=True, text=True, timeout=60, env=ENV)
    assert r.returncode == 0, r.stdout + r.stderr
    assert all(f"{name}: mission ok" in r.stdout for name in robots), r.stdout


def all_stopped(world, n: int) -> bool:
    return all(world.power(i) == (0, 0) for i in range(n))


def all_driving(world, n: int) -> bool:
    return all(world.power(i) != (0, 0) for i in range(n))


def test_router_loss_stops_every_robot_within_300ms_with_the_demos_flags(router, tmp_path):
    # The demo runs the bridge with `-e tcp/...` and no `-m`: client mode by the defaults, so the
    # watchdog must be on (it was decided from `-m` alone and was off).
    with fleet(3) as (world, robots), bridge_process(bridge_cmd(robots, router, tmp_path)) as bridge:
        line = bridge.wait_line("commands on")
        assert "router watchdog on (client mode)" in line, line
        start_missions(router, robots)
        assert wait_for(lambda: all_driving(world, 3), 2.0)
        router.proc.kill()          # kill -9: the lab falls apart
        t_kill = time.monotonic()
        assert wait_for(lambda: all_stopped(world, 3), 3.0, step=0.001), \
            [world.power(i) for i in range(3)]
        took = time.monotonic() - t_kill
        assert took < 0.3, f"robots stopped {took * 1000:.0f} ms after the router died"
        # and nothing drives them again while the router is gone
        assert not wait_for(lambda: not all_stopped(world, 3), 0.5)
        bridge.proc.send_signal(signal.SIGTERM)
        out = bridge.wait(timeout=15)
    assert bridge.proc.returncode == 0, out
    assert "Zenoh router lost: stopped r1, r2, r3 (missions of r1, r2, r3 aborted)" in out, out
    # each mission's log says why its telemetry stops there
    import csv
    for name in robots:
        rows = list(csv.DictReader(open(sorted(tmp_path.glob(f"{name}_*.csv"))[-1], newline="")))
        assert [r["event"] for r in rows].count("router_lost") == 1, name


@pytest.mark.parametrize("target", ["process", "other thread"])
def test_sigterm_stops_the_bridge_within_2s_with_rc0(router, tmp_path, target):
    # A launcher's SIGTERM may reach any thread (Zenoh runs several); the main thread used to sleep
    # in an untimed Event.wait() and never ran the handler (the demo killed it after 5 s).
    from tests.recorder.signals import term_other_thread

    with fleet(2) as (world, robots), bridge_process(bridge_cmd(robots, router, tmp_path)) as bridge:
        bridge.wait_line("commands on")
        start_missions(router, robots)
        assert wait_for(lambda: all_driving(world, 2), 2.0)
        t0 = time.monotonic()
        if target == "process":
            bridge.proc.send_signal(signal.SIGTERM)
        else:
            try:
                term_other_thread(bridge.proc.pid)
            except RuntimeError as exc:
                pytest.skip(str(exc))
        try:
            out = bridge.wait(timeout=10)
        except subprocess.TimeoutExpired:
            pytest.fail("the bridge did not exit within 10 s of SIGTERM")
        took = time.monotonic() - t0
        assert bridge.proc.returncode == 0, out
        assert took < 2.0, f"the bridge took {took:.2f} s to exit after SIGTERM"
        assert all_stopped(world, 2)
        assert "ended: interrupted: bridge shut down" in out


def statuses(session, name: str, out: list) -> None:
    session.declare_subscriber(status_key("bridge", name), lambda s: out.append(Status.decode(s.payload.to_bytes())))


def test_missing_device_is_an_error_in_status_logged_and_retried_with_backoff(router, tmp_path):
    with fleet(1) as (world, robots), open_session(router.settings("client")) as session:
        seen: list[Status] = []
        statuses(session, "demo", seen)
        argv = bridge_cmd({"zumo1": "/dev/does-not-exist", **robots}, router, tmp_path)
        with bridge_process(argv) as bridge:
            bridge.wait_line("commands on")
            # status once a second: wait for one at least 4 s into the run
            assert wait_for(lambda: seen and seen[-1].uptime_s >= 4.0, 20.0, step=0.05), seen[-1:]
            st = seen[-1]
            bridge.proc.send_signal(signal.SIGTERM)
            out = bridge.wait(timeout=15)
        assert bridge.proc.returncode == 0, out
    assert st.errors >= 1 and st.state == "degraded", st
    assert "robot zumo1: link cannot be opened: cannot open /dev/does-not-exist" in st.last_error, st.last_error
    assert "No such file or directory" in st.last_error
    assert st.gauges["zumo1.link"].startswith("down: cannot open /dev/does-not-exist")
    assert st.gauges["r1.link"] == "up"                      # the other robot is served
    # retried with a growing delay: 0.05, 0.1, 0.2 ... 2 s apart (a fixed 50 ms would be ~80)
    failures = st.counters["link_open_failures"]
    assert 3 <= failures <= 10, failures
    assert "robot zumo1: cannot open /dev/does-not-exist" in out    # the link's own log line


def test_missing_device_with_require_all_exits_1_naming_the_robot(router, tmp_path):
    with fleet(1) as (world, robots), open_session(router.settings("client")) as session:
        tokens = []   # a launcher waits for this token: a bridge that cannot work must never show it
        session.liveliness().declare_subscriber(alive_key("bridge", "demo"), lambda s: tokens.append(s.kind))
        argv = bridge_cmd({**robots, "zumo1": "/dev/does-not-exist"}, router, tmp_path, "--require-all")
        r = subprocess.run(argv, capture_output=True, text=True, timeout=60, env=ENV)
        # (a token declared by the bridge would have been seen long before it exited)
    assert tokens == [], tokens
    assert r.returncode == 1, r.stdout + r.stderr
    mine = [ln for ln in r.stderr.splitlines() if ln.startswith("arena bridge run:")]
    assert len(mine) == 1, r.stderr
    assert "robot zumo1: link to /dev/does-not-exist cannot be opened" in mine[0]
    assert "No such file or directory" in mine[0] and "(--require-all)" in mine[0]
    assert "Traceback" not in r.stderr and "commands on" not in r.stdout


def test_require_all_runs_when_every_robot_connects(router, tmp_path):
    with fleet(2) as (world, robots), \
            bridge_process(bridge_cmd(robots, router, tmp_path, "--require-all", "--duration", "0.5")) as bridge:
        out = bridge.wait(timeout=60)
    assert bridge.proc.returncode == 0 and "commands on" in out, out


def test_bad_robot_flag_and_mode_are_usage_errors(tmp_path):
    r = subprocess.run(arena_cmd("bridge", "run", "--robot", "zumo1", "--duration", "0.1"),
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "--robot expects NAME=URL" in r.stderr and "Traceback" not in r.stderr
    r = subprocess.run(arena_cmd("bridge", "run", "--robot", "zumo1=socket://127.0.0.1:9", "--duration", "0.1"),
                       capture_output=True, text=True, timeout=60, env={**ENV, "ARENA_ZENOH_MODE": "bogus"})
    assert r.returncode == 2 and "Zenoh mode 'bogus'" in r.stderr, r.stderr


def test_only_mission_has_start_pose_in_its_help():
    for verb in ("stop", "estop", "clear", "led"):
        r = subprocess.run([sys.executable, "-m", "robot_bridge", verb, "--help"], capture_output=True, text=True,
                           timeout=60)
        assert r.returncode == 0 and "--timeout" in r.stdout and "--start-pose" not in r.stdout, (verb, r.stdout)
    r = subprocess.run([sys.executable, "-m", "robot_bridge", "mission", "--help"], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0 and "--start-pose" in r.stdout

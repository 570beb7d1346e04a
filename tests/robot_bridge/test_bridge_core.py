"""The robot's domain core (robot_bridge.core): no Zenoh inside, and stops that go through its lock.

The race checked here: a mission command for a robot is being started (its checks passed) at the
moment a stop or e-stop for ``all`` robots arrives. Whatever the interleaving, once the stop's
first STOP is on the wire the robot gets no motor command, the mission does not start, and the
robot ends stopped (link latched, no mission, e-stop latched for an e-stop). The interleaving is
forced with events (no sleeps): the mission start is held right after its last readiness check
(inside the robot's mission lock, before its start under the command lock) while the command
callback sends its first STOP; the callback is then held (after that STOP) until the mission start has returned
and one telemetry sample (a control step) has been handled.
"""

from __future__ import annotations

import subprocess
import sys
import threading

import pytest

from arena import robot_protocol as P
from arena.messages import CommandReply, MissionCommand
from robot_bridge.core import BridgeOptions, CommandError, RobotSetup
from robot_bridge.service import Bridge

GUARD_S = 10.0   # deadlock guard only: every wait below is released by an event, not by time


def test_the_core_imports_no_zenoh():
    code = "import robot_bridge.core, sys; assert 'zenoh' not in sys.modules, 'zenoh imported'; print('ok')"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr


class _Session:
    """What Bridge.__init__ needs of a Zenoh session (it is never started here)."""

    def declare_publisher(self, key):
        return self

    def put(self, payload):
        pass


class _Payload:
    def __init__(self, data: bytes):
        self._data = data

    def to_bytes(self) -> bytes:
        return self._data


class _Query:
    def __init__(self, key: str, payload: bytes = b""):
        self.key_expr = key
        self.payload = _Payload(payload) if payload else None
        self.replies: list[CommandReply] = []
        self.errors: list[str] = []

    def reply(self, key, data: bytes) -> None:
        self.replies.append(CommandReply.decode(data))

    def reply_err(self, text: str) -> None:
        self.errors.append(text)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


class _Port:
    """The serial port of a link that counts as up: keeps every frame written to it."""

    def __init__(self):
        self.frames: list[P.Frame] = []
        self._dec = P.StreamDecoder()

    def write(self, data: bytes) -> int:
        self.frames.extend(self._dec.feed(data))
        return len(data)

    def types_after_first_stop(self) -> list[str]:
        names = [type(f.msg).__name__ for f in self.frames]
        return names[names.index("Stop") + 1:] if "Stop" in names else []


def _telemetry(seq: int, t_us: int) -> P.Frame:
    tel = P.Telemetry(enc_left=10 * seq, enc_right=10 * seq, accel=(0, 0, 16384), gyro=(0, 0, 0), mag=(0, 0, 0),
                      battery_mv=5000, motor_left=0, motor_right=0)
    return P.decode_packet(P.encode_packet(tel, seq, t_us))


@pytest.mark.parametrize("verb", ["stop", "estop"])
def test_a_stop_for_all_during_a_mission_start_leaves_the_robot_stopped(tmp_path, verb):
    bridge = Bridge(_Session(), [RobotSetup("r1", "loop://"), RobotSetup("r2", "loop://")],
                    BridgeOptions(log_dir=str(tmp_path)))   # never started: no threads, no ports
    h = bridge.handles["r1"]
    port = _Port()
    h.link._port = port
    h.link._connected.set()
    for i in range(2):                      # the robot's clock and encoders are known
        h._on_frame(_telemetry(i, 1000 + 20_000 * i), 1_000_000_000 + 20_000_000 * i, 0)
    query = _Query(f"arena/cmd/all/{verb}")
    callback = threading.Thread(target=bridge._on_query, args=(query,), name="command-callback")
    first_stop, release = threading.Event(), threading.Event()
    stop_motors = h.link.stop_motors

    def stop_motors_then_wait(repeat=1):
        """The callback's first STOP to r1 is on the wire: hold the callback until the mission
        start has returned and a control step has run (outside the link's write lock)."""
        stop_motors(repeat)
        if threading.current_thread() is callback and not first_stop.is_set():
            first_stop.set()
            assert release.wait(GUARD_S), "the mission start never returned"

    h.link.stop_motors = stop_motors_then_wait

    checks = {"n": 0}
    refuse_if_not_ready = h._refuse_if_not_ready

    def checked():
        refuse_if_not_ready()
        checks["n"] += 1
        if checks["n"] == 2:     # the last check before the start passed: now the stop arrives
            callback.start()
            assert first_stop.wait(GUARD_S), "the stop sent no STOP"

    h._refuse_if_not_ready = checked
    cmd = MissionCommand(mission="circle", params={"radius_m": 0.2}, power=0.5)
    gen = h.generation                      # taken when the mission request arrived, before the stop
    try:
        try:
            detail = h.start_mission(cmd, gen)
        except CommandError as exc:
            detail = {"refused": str(exc)}
        h._on_frame(_telemetry(2, 41_000), 1_040_000_000, 0)   # a control step before the stop's end
    finally:
        release.set()
        if callback.ident is not None:
            callback.join(GUARD_S)
    assert not callback.is_alive()
    while not h._jobs.empty():              # the robot's worker (never started here): end the mission
        job = h._jobs.get()
        if job is not None:
            job()

    assert "refused" in detail, f"a mission started after the {verb}'s STOP: {detail}"
    assert detail["refused"].startswith("stopped: a stop or e-stop for r1 came after this mission"), detail
    assert "SetMotors" not in port.types_after_first_stop(), port.types_after_first_stop()
    assert h.runner is None and h.mission_id is None
    assert not h.link.motors_allowed
    assert h.estop is (verb == "estop")
    assert sorted(r.robot for r in query.replies) == ["r1", "r2"] and all(r.ok for r in query.replies), query.replies
    bridge.close()

"""The reference firmware sketch itself, compiled for the host against small stand-ins of the
Arduino core and the Zumo32U4 library (tests/robot_bridge/firmware_host/), and driven over
pipes with the Python protocol: handshake, ping, motors, telemetry, watchdog, errors."""

from __future__ import annotations

import os
import shutil
import subprocess
import threading
import time
from pathlib import Path

import pytest

from arena import robot_protocol as P

ROOT = Path(__file__).resolve().parents[2]
FW = ROOT / "robot_bridge" / "firmware" / "arena_robot"
HOST = Path(__file__).resolve().parent / "firmware_host"


@pytest.fixture(scope="module")
def firmware(tmp_path_factory):
    gxx, gcc = shutil.which("g++"), shutil.which("gcc")
    if gxx is None or gcc is None:
        pytest.skip("g++/gcc not found: cannot build the firmware sketch for the host")
    d = tmp_path_factory.mktemp("fwhost")
    obj = d / "arena_proto.o"
    subprocess.run([gcc, "-std=c99", "-Wall", "-Wextra", "-Werror", "-c", str(FW / "arena_proto.c"), "-o", str(obj)],
                   check=True)
    exe = d / "arena_robot"
    subprocess.run([gxx, "-std=c++11", "-Wall", "-Wextra", "-Werror", f"-I{HOST}", f"-I{FW}", "-x", "c++",
                    str(FW / "arena_robot.ino"), str(HOST / "host_main.cpp"), "-x", "none", str(obj),
                    "-o", str(exe)], check=True)
    return exe


class Robot:
    """The firmware process; frames it sends are decoded by a reader thread."""

    def __init__(self, exe: Path):
        self.proc = subprocess.Popen([str(exe)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, bufsize=0)
        self.dec = P.StreamDecoder()
        self.frames: list[tuple[float, P.Frame]] = []
        self.lock = threading.Lock()
        self.seq = 0
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self):
        fd = self.proc.stdout.fileno()
        while True:
            chunk = os.read(fd, 4096)
            if not chunk:
                return
            now = time.monotonic()
            with self.lock:
                self.frames += [(now, f) for f in self.dec.feed(chunk)]

    def send(self, msg) -> None:
        self.proc.stdin.write(P.encode_frame(msg, self.seq, 0))
        self.seq += 1

    def wait(self, pred, timeout=2.0):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            with self.lock:
                for t, f in self.frames:
                    if pred(f):
                        return t, f
            time.sleep(0.005)
        raise AssertionError("the firmware did not send the expected frame")

    def close(self):
        self.proc.stdin.close()
        self.proc.wait(5)


def test_firmware_speaks_the_protocol_and_its_watchdog_stops_the_motors(firmware):
    robot = Robot(firmware)
    try:
        robot.send(P.Hello())
        _, hello = robot.wait(lambda f: isinstance(f.msg, P.HelloReply))
        assert hello.msg == P.HelloReply(1, 50, 1807, 300, "zumo")
        robot.send(P.Ping(4242))
        robot.wait(lambda f: f.msg == P.Pong(4242))
        robot.send(P.SetMotors(400, -200))
        _, tel = robot.wait(lambda f: isinstance(f.msg, P.Telemetry) and f.msg.motor_left == 400)
        assert tel.msg.motor_right == -200 and tel.msg.battery_mv == 5123
        assert tel.msg.accel == (0, 0, 16384) and tel.msg.mag == (100, 200, -300)
        t_cmd = time.monotonic()
        # no more SET_MOTORS: the watchdog must stop the motors ~300 ms later and flag it
        t_stop, stopped = robot.wait(lambda f: isinstance(f.msg, P.Telemetry) and f.msg.motor_left == 0
                                     and f.msg.flags & P.FLAG_WATCHDOG)
        assert 0.25 <= t_stop - t_cmd <= 0.30 + 0.1   # + one telemetry period (20 ms) and scheduling
        enc = stopped.msg.enc_left
        assert enc > 0
        robot.send(P.SetLed(255, 0, 0))
        robot.send(P.SetMotors(100, 100))
        robot.send(P.Stop())
        robot.wait(lambda f: isinstance(f.msg, P.Telemetry) and f.msg.motor_left == 0 and f.seq > stopped.seq + 3)
        with robot.lock:
            tel = [f for _, f in robot.frames if isinstance(f.msg, P.Telemetry)]
        assert all(P.seq_gap(a.seq, b.seq) <= 2 for a, b in zip(tel, tel[1:]))   # PONG/HELLO interleave
        dt = [(b.time_us - a.time_us) / 1000 for a, b in zip(tel, tel[1:])]
        assert sorted(dt)[len(dt) // 2] == pytest.approx(20, abs=2)              # 50 Hz
        assert robot.dec.stats.rejected == 0
    finally:
        robot.close()


def test_firmware_rejects_corrupt_frames_and_unknown_types(firmware):
    robot = Robot(firmware)
    try:
        bad = bytearray(P.encode_frame(P.SetMotors(400, 400), 0, 0))
        bad[3] ^= 0x40
        robot.proc.stdin.write(b"\x00garbage\x00" + bytes(bad))
        pkt = bytearray(P.encode_packet(P.Stop(), 1, 0))
        pkt[1] = 0x55
        pkt[-2:] = P.crc16(bytes(pkt[:-2])).to_bytes(2, "little")
        robot.proc.stdin.write(P.cobs_encode(bytes(pkt)) + b"\x00")
        _, err = robot.wait(lambda f: isinstance(f.msg, P.Error))
        assert err.msg.code == P.ERR_UNKNOWN_TYPE and err.msg.ref_type == 0x55
        time.sleep(0.1)
        with robot.lock:
            tel = [f.msg for _, f in robot.frames if isinstance(f.msg, P.Telemetry)]
        assert tel and all(t.motor_left == 0 for t in tel)   # the corrupted SET_MOTORS was not obeyed
    finally:
        robot.close()

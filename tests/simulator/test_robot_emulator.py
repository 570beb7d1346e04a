"""Robot emulator: protocol over pyserial's socket:// URL, motors, watchdog, link faults."""

from __future__ import annotations

import threading
import time

import pytest
import serial

from arena import robot_protocol as P
from simulator.robot_emulator import LinkFaults, RobotEmulatorServer
from simulator.world import RobotSpec, World


@pytest.fixture
def world():
    w = World([RobotSpec("r1", (20, 20, 20)), RobotSpec("r2", (200, 200, 0), start=(0.5, 0.5, 0.0))], seed=3)
    stop = threading.Event()

    def run():  # step the world at ~1 kHz sim time = real time
        last = time.monotonic()
        while not stop.is_set():
            now = time.monotonic()
            w.step(now - last)
            last = now
            stop.wait(0.001)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    yield w
    stop.set()
    t.join()


def read_frames(port, dec, seconds, until=None):
    out = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        out += dec.feed(port.read(4096))
        if until and until(out):
            break
    return out


def test_hello_ping_motors_and_telemetry_over_socket_url(world):
    with RobotEmulatorServer(world, 1, telemetry_hz=100) as emu:
        port = serial.serial_for_url(emu.url, timeout=0.02)
        dec = P.StreamDecoder()
        port.write(P.encode_frame(P.Hello(), 0, 0) + P.encode_frame(P.Ping(77), 1, 0)
                   + P.encode_frame(P.SetLed(1, 2, 3), 2, 0))
        frames = []
        t0 = time.monotonic()
        for k in range(25):  # drive forward at 50 % for 0.5 s, commands at 50 Hz
            port.write(P.encode_frame(P.SetMotors(200, 200), 3 + k, 0))
            frames += read_frames(port, dec, 0.02)
        elapsed = time.monotonic() - t0
        port.close()
    msgs = [f.msg for f in frames]
    assert any(isinstance(m, P.HelloReply) and m.name == "r2" and m.counts_per_rev == 1807 for m in msgs)
    assert P.Pong(77) in msgs
    assert emu.led == (1, 2, 3)
    tel = [f for f in frames if isinstance(f.msg, P.Telemetry)]
    assert len(tel) >= 0.6 * 100 * elapsed
    assert all(P.seq_gap(a.seq, b.seq) == 0 or not isinstance(b.msg, P.Telemetry)
               for a, b in zip(frames, frames[1:]))
    last = tel[-1].msg
    assert last.motor_left == 200 and last.enc_left > 0 and last.enc_right > 0
    assert last.accel_si[2] == pytest.approx(9.81, abs=0.5)
    assert 3500 < last.battery_mv < 6000
    assert world.pose(1)[0] > 0.5 + 0.03  # it moved forward (+x)


def test_robot_clock_runs_with_the_simulated_time_when_given_the_worlds_clock():
    # a simulation that falls behind real time (here: stepped at half speed) must not stamp
    # its encoder counts with wall time, or the host's odometry and speeds come out wrong
    w = World([RobotSpec("r1", (20, 20, 20))], seed=1)
    w.step(2.0)
    stop = threading.Event()

    def run():
        while not stop.is_set():
            w.step(0.0005)
            stop.wait(0.001)

    th = threading.Thread(target=run, daemon=True)
    th.start()
    try:
        with RobotEmulatorServer(w, 0, telemetry_hz=100, clock=lambda: w.t) as emu:
            port = serial.serial_for_url(emu.url, timeout=0.02)
            dec = P.StreamDecoder()
            t0 = time.monotonic()
            frames = read_frames(port, dec, 1.0)
            wall = time.monotonic() - t0
            port.close()
    finally:
        stop.set()
        th.join()
    tel = [f for f in frames if isinstance(f.msg, P.Telemetry)]
    assert len(tel) > 30
    first, last = tel[0].time_us, tel[-1].time_us
    assert first >= 2_000_000                    # the world's time, not time since the emulator started
    assert (last - first) / 1e6 < 0.75 * wall    # it advanced with the stepped world (<= half speed)
    assert all(b.time_us >= a.time_us for a, b in zip(tel, tel[1:]))


def test_watchdog_stops_motors_within_300ms(world):
    with RobotEmulatorServer(world, 0) as emu:
        port = serial.serial_for_url(emu.url, timeout=0.02)
        port.write(P.encode_frame(P.SetMotors(400, 400), 0, 0))
        deadline = time.monotonic() + 1.0
        while world.power(0) == (0, 0) and time.monotonic() < deadline:
            time.sleep(0.002)
        assert world.power(0) == (400, 400)
        deadline = time.monotonic() + 1.0
        while world.power(0) != (0, 0) and time.monotonic() < deadline:
            time.sleep(0.002)
        port.close()
    assert world.power(0) == (0, 0)
    assert emu.stats.watchdog_trips == 1
    delay = emu.stats.watchdog_stop_t - emu.stats.last_command_t
    assert 0.29 <= delay <= 0.30 + 0.03  # 300 ms plus one loop tick on a loaded machine


def test_corruption_and_byte_loss_rates(world):
    faults = LinkFaults(corruption=0.1, byte_loss=0.002)
    with RobotEmulatorServer(world, 0, telemetry_hz=200, faults=faults, seed=5) as emu:
        port = serial.serial_for_url(emu.url, timeout=0.02)
        dec = P.StreamDecoder()
        frames = read_frames(port, dec, 2.0, until=lambda fr: emu.stats.frames_sent >= 300)
        port.close()
    s = emu.stats
    n = s.frames_sent
    assert n >= 250
    assert abs(s.frames_corrupted / n - 0.1) < 0.05
    assert abs(s.bytes_dropped / (45 * n) - 0.002) < 0.0015
    assert dec.stats.rejected >= 0.8 * s.frames_corrupted  # dropped+corrupt frames may merge
    assert len(frames) <= n - s.frames_corrupted


def test_disconnect_after_and_latency(world):
    faults = LinkFaults(disconnect_after_s=0.3, latency_ms=40, jitter_ms=10)
    with RobotEmulatorServer(world, 0, faults=faults) as emu:
        port = serial.serial_for_url(emu.url, timeout=0.01)
        dec = P.StreamDecoder()
        read_frames(port, dec, 0.1)
        t0 = time.monotonic()
        port.write(P.encode_frame(P.Ping(1), 0, 0))
        frames = read_frames(port, dec, 0.5, until=lambda fr: any(isinstance(f.msg, P.Pong) for f in fr))
        rtt = time.monotonic() - t0
        assert any(isinstance(f.msg, P.Pong) for f in frames)
        assert 0.08 <= rtt < 0.3  # 2 x 40 ms + jitter
        time.sleep(0.4)
        assert emu.stats.disconnects == 1
        with pytest.raises(serial.SerialException):
            for _ in range(50):
                port.read(100)
                port.write(b"\x00")
                time.sleep(0.01)
        port.close()
        port2 = serial.serial_for_url(emu.url, timeout=0.02)  # the port accepts again
        assert read_frames(port2, P.StreamDecoder(), 0.2)
        port2.close()
    assert emu.stats.connections == 2


def test_bad_arguments():
    w = World([RobotSpec("r1", (0, 0, 0))])
    with pytest.raises(ValueError, match="corruption"):
        LinkFaults(corruption=2)
    with pytest.raises(IndexError):
        RobotEmulatorServer(w, 3)
    with pytest.raises(ValueError, match="telemetry_hz"):
        RobotEmulatorServer(w, 0, telemetry_hz=0)


def test_out_of_range_motor_power_is_clamped_like_the_firmware_and_counted(world):
    import struct
    data = P.HEADER.pack(P.PROTOCOL_VERSION, P.SET_MOTORS, 0, 0) + struct.pack("<hh", -5750, 5750)
    frame = P.cobs_encode(data + struct.pack("<H", P.crc16(data))) + b"\x00"
    with RobotEmulatorServer(world, 0) as emu:
        port = serial.serial_for_url(emu.url, timeout=0.02)
        port.write(frame)
        deadline = time.monotonic() + 1.0
        while world.power(0) == (0, 0) and time.monotonic() < deadline:
            time.sleep(0.002)
        power = world.power(0)
        port.close()
    assert power == (-400, 400)                 # never -5750 into the world (or the motor driver)
    assert emu.stats.rx_clamped == 2 and emu.stats.rx_rejected == 0


def test_pause_output_holds_robot_bytes_then_delivers_them_in_order(world):
    with RobotEmulatorServer(world, 0, telemetry_hz=100) as emu:
        port = serial.serial_for_url(emu.url, timeout=0.02)
        dec = P.StreamDecoder()
        assert read_frames(port, dec, 2.0, until=lambda fr: len(fr) >= 5)
        emu.pause_output(1.0)
        t0 = time.monotonic()
        read_frames(port, dec, 0.05)                           # what was already on its way
        quiet = read_frames(port, dec, 0.8)                    # 0.05..0.85 s into the pause: nothing
        burst = read_frames(port, dec, 2.0, until=lambda fr: len(fr) >= 80)
        after = time.monotonic() - t0
        port.close()
    assert quiet == [] and emu.stats.output_pauses == 1
    seqs = [f.seq for f in burst]
    assert len(burst) >= 80 and after >= 1.0
    assert all(P.seq_gap(a, b) == 0 for a, b in zip(seqs, seqs[1:]))   # held, not lost: in order


def test_watchdog_stops_the_robot_when_its_host_goes_silent_during_a_mission(world):
    # the safety net under any host-side link timeout: a host that stops commanding (here it
    # stops because the robot's telemetry stalls, as during an SPP pause) leaves the robot
    # stopped 300 ms after its last SET_MOTORS, whatever the host thinks of the link
    with RobotEmulatorServer(world, 0, telemetry_hz=100) as emu:
        port = serial.serial_for_url(emu.url, timeout=0.02)
        dec = P.StreamDecoder()
        for k in range(30):                               # a host commanding at every telemetry frame
            if read_frames(port, dec, 0.1, until=lambda fr: any(isinstance(f.msg, P.Telemetry) for f in fr)):
                port.write(P.encode_frame(P.SetMotors(300, 300), k, 0))
        assert world.power(0) == (300, 300)
        emu.pause_output(1.0)             # no telemetry reaches the host, so it commands nothing
        deadline = time.monotonic() + 1.0
        while world.power(0) != (0, 0) and time.monotonic() < deadline:
            read_frames(port, dec, 0.01)
        port.close()
    assert world.power(0) == (0, 0) and emu.stats.watchdog_trips == 1
    assert 0.29 <= emu.stats.watchdog_stop_t - emu.stats.last_command_t <= 0.33

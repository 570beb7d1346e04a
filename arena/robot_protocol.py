"""Robot wire protocol: COBS-framed, CRC-16-checked binary packets (pure, no I/O).

A contract shared by the robot bridge (``robot_bridge.link``, ``robot_bridge.core``), the
simulator's robot emulator (``simulator.robot_emulator``, which imports this module so that it
speaks exactly what the firmware speaks) and the firmware cross-tests, so it lives in ``arena/``.
The byte layout is specified in ``docs/robot-protocol.md``; the firmware's C version of the same
framing lives in ``robot_bridge/firmware/arena_robot/arena_proto.c`` and is cross-tested against
this module on the host.

A packet on the wire is ``COBS(header + body + crc16) + b"\\x00"``:

* header (8 bytes, little-endian): ``version u8, type u8, seq u16, time_us u32``
  where ``time_us`` is the sender's microsecond clock (the robot's ``micros()``,
  wrapping at 2**32 µs ~ 71.6 min; the host sends its own clock modulo 2**32);
* body: fixed layout per message type (see the ``_BODY`` table);
* crc16: CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, xorout 0)
  over header + body, appended little-endian.

:class:`StreamDecoder` turns arbitrary byte chunks (split anywhere, garbage between
frames) into :class:`Frame` objects; anything that fails COBS, length, version or
CRC checks is counted in :class:`DecoderStats`, never returned as data. A well-formed
packet whose field lies outside its physical range (a motor power of -5750 where the motors
take -400..400) is returned with the field clamped to that range (:data:`PHYSICAL_RANGES`),
and counted (``Frame.clamped``, ``DecoderStats.clamped``): consumers never see such values.
"""

from __future__ import annotations

import dataclasses
import math
import struct
from dataclasses import dataclass, field
from typing import ClassVar, Union

#: Protocol version carried in every header. Bump when a body layout changes.
PROTOCOL_VERSION = 1
#: Largest decoded packet (header + body + CRC), bytes. Longer runs are discarded.
MAX_PACKET = 64
HEADER = struct.Struct("<BBHI")
HEADER_SIZE = HEADER.size  # 8
CRC_SIZE = 2

# Message type codes.
HELLO = 0x01
HELLO_REPLY = 0x02
SET_MOTORS = 0x10
SET_LED = 0x11
STOP = 0x12
TELEMETRY = 0x20
PING = 0x30
PONG = 0x31
ERROR = 0x7F

#: Motor power limit as the Zumo32U4Motors library takes it (400 = 100 %).
MAX_POWER = 400

# Raw-unit scales of the Zumo 32U4 IMU as the reference firmware configures it
# (Zumo32U4IMU enableDefault() then configureForTurnSensing(): LSM6DS33 accel +-2 g,
# gyro +-2000 dps so zero-point turns (~600 deg/s) do not saturate; LIS3MDL mag +-4 gauss).
G = 9.80665
ACCEL_MPS2_PER_LSB = 0.061e-3 * G          # 0.061 mg/LSB
GYRO_RADPS_PER_LSB = math.radians(70e-3)   # 70 mdps/LSB
MAG_UT_PER_LSB = 100.0 / 6842.0            # 6842 LSB/gauss, 1 gauss = 100 µT


class ProtocolError(ValueError):
    """A message cannot be encoded (out-of-range field) or a packet is malformed."""


def crc16_ccitt_false(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (check value of b"123456789" is 0x29B1)."""
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
            crc &= 0xFFFF
    return crc


# Table-driven variant used on the hot path (same result as crc16_ccitt_false).
def _make_table() -> list[int]:
    table = []
    for i in range(256):
        crc = i << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
            crc &= 0xFFFF
        table.append(crc)
    return table


_CRC_TABLE = _make_table()


def crc16(data: bytes) -> int:
    """Fast table-driven CRC-16/CCITT-FALSE of ``data``."""
    crc = 0xFFFF
    table = _CRC_TABLE
    for byte in data:
        crc = ((crc << 8) & 0xFFFF) ^ table[(crc >> 8) ^ byte]
    return crc


def cobs_encode(data: bytes) -> bytes:
    """Consistent Overhead Byte Stuffing: returns ``data`` without any 0x00 byte
    (overhead 1 byte per 254); the delimiter is not appended."""
    out = bytearray()
    block = bytearray()
    for byte in data:
        if byte == 0:
            out.append(len(block) + 1)
            out += block
            block.clear()
        else:
            block.append(byte)
            if len(block) == 254:
                out.append(255)
                out += block
                block.clear()
    out.append(len(block) + 1)
    out += block
    return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    """Inverse of :func:`cobs_encode`; raises :class:`ProtocolError` on a bad encoding."""
    out = bytearray()
    i = 0
    n = len(data)
    while i < n:
        code = data[i]
        if code == 0:
            raise ProtocolError("COBS: zero byte inside a frame")
        end = i + code
        if end > n:
            raise ProtocolError("COBS: block runs past the end of the frame")
        block = data[i + 1:end]
        if 0 in block:
            raise ProtocolError("COBS: zero byte inside a frame")
        out += block
        i = end
        if code != 255 and i < n:
            out.append(0)
    return bytes(out)


# --------------------------------------------------------------------------- messages


def _check_int(name: str, value: int, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        try:
            if float(value) != int(value):
                raise TypeError
            value = int(value)
        except (TypeError, ValueError):
            raise ProtocolError(f"{name} must be an integer, got {value!r}") from None
    if not lo <= value <= hi:
        raise ProtocolError(f"{name}={value} out of range [{lo}, {hi}]")
    return value


@dataclass(frozen=True)
class Hello:
    """Host -> robot: start of a session; the robot answers :class:`HelloReply`."""

    TYPE: ClassVar[int] = HELLO
    FMT: ClassVar[struct.Struct] = struct.Struct("<")

    def pack(self) -> bytes:
        return b""

    @classmethod
    def unpack(cls, body: bytes) -> "Hello":
        return cls()


@dataclass(frozen=True)
class HelloReply:
    """Robot -> host: firmware version, telemetry rate (Hz), encoder counts per
    sprocket revolution, watchdog timeout (ms) and robot name (ASCII, <= 16 bytes)."""

    firmware_version: int
    telemetry_hz: int
    counts_per_rev: int
    watchdog_ms: int
    name: str

    TYPE: ClassVar[int] = HELLO_REPLY
    FMT: ClassVar[struct.Struct] = struct.Struct("<HHHH16s")

    def pack(self) -> bytes:
        name = self.name.encode("ascii", "replace")
        if len(name) > 16:
            raise ProtocolError(f"robot name {self.name!r} longer than 16 bytes")
        return self.FMT.pack(
            _check_int("firmware_version", self.firmware_version, 0, 0xFFFF),
            _check_int("telemetry_hz", self.telemetry_hz, 0, 0xFFFF),
            _check_int("counts_per_rev", self.counts_per_rev, 0, 0xFFFF),
            _check_int("watchdog_ms", self.watchdog_ms, 0, 0xFFFF),
            name,
        )

    @classmethod
    def unpack(cls, body: bytes) -> "HelloReply":
        fw, hz, cpr, wd, name = cls.FMT.unpack(body)
        return cls(fw, hz, cpr, wd, name.rstrip(b"\x00").decode("ascii", "replace"))


@dataclass(frozen=True)
class SetMotors:
    """Host -> robot: motor power per side, -400..400 (Zumo32U4Motors units, 400 = 100 %).
    Each SET_MOTORS also feeds the robot's 300 ms watchdog."""

    left: int
    right: int

    TYPE: ClassVar[int] = SET_MOTORS
    FMT: ClassVar[struct.Struct] = struct.Struct("<hh")

    def pack(self) -> bytes:
        return self.FMT.pack(
            _check_int("left", self.left, -MAX_POWER, MAX_POWER),
            _check_int("right", self.right, -MAX_POWER, MAX_POWER),
        )

    @classmethod
    def unpack(cls, body: bytes) -> "SetMotors":
        left, right = cls.FMT.unpack(body)
        return cls(left, right)


@dataclass(frozen=True)
class SetLed:
    """Host -> robot: LED colour, 0-255 per channel."""

    r: int
    g: int
    b: int

    TYPE: ClassVar[int] = SET_LED
    FMT: ClassVar[struct.Struct] = struct.Struct("<BBB")

    def pack(self) -> bytes:
        return self.FMT.pack(*(_check_int(n, v, 0, 255) for n, v in (("r", self.r), ("g", self.g), ("b", self.b))))

    @classmethod
    def unpack(cls, body: bytes) -> "SetLed":
        return cls(*cls.FMT.unpack(body))


@dataclass(frozen=True)
class Stop:
    """Host -> robot: motors to 0 at once (same effect as SET_MOTORS 0 0)."""

    TYPE: ClassVar[int] = STOP
    FMT: ClassVar[struct.Struct] = struct.Struct("<")

    def pack(self) -> bytes:
        return b""

    @classmethod
    def unpack(cls, body: bytes) -> "Stop":
        return cls()


#: Telemetry flag bits.
FLAG_WATCHDOG = 0x01   # motors were stopped by the watchdog since the last motor command
FLAG_LOW_BATTERY = 0x02


@dataclass(frozen=True)
class Telemetry:
    """Robot -> host sample, sent at the firmware's telemetry rate (50-100 Hz).

    Encoder counts are cumulative signed 32-bit (1807 counts per sprocket revolution
    on 150:1 motors; forward is positive). IMU values are raw sensor units in the
    robot body frame (x forward, y left, z up); use the ``*_si`` properties or the
    module scales for SI units. ``motor_left/right`` is the power currently applied
    (-400..400), ``battery_mv`` the battery voltage in mV.
    """

    enc_left: int
    enc_right: int
    accel: tuple[int, int, int]
    gyro: tuple[int, int, int]
    mag: tuple[int, int, int]
    battery_mv: int
    motor_left: int
    motor_right: int
    flags: int = 0

    TYPE: ClassVar[int] = TELEMETRY
    FMT: ClassVar[struct.Struct] = struct.Struct("<ii3h3h3hHhhB")

    def pack(self) -> bytes:
        i16 = (-32768, 32767)
        vals = [
            _check_int("enc_left", self.enc_left, -(2**31), 2**31 - 1),
            _check_int("enc_right", self.enc_right, -(2**31), 2**31 - 1),
        ]
        for name, vec in (("accel", self.accel), ("gyro", self.gyro), ("mag", self.mag)):
            if len(vec) != 3:
                raise ProtocolError(f"{name} needs 3 components, got {len(vec)}")
            vals += [_check_int(name, int(c), *i16) for c in vec]
        vals += [
            _check_int("battery_mv", self.battery_mv, 0, 0xFFFF),
            _check_int("motor_left", self.motor_left, -MAX_POWER, MAX_POWER),
            _check_int("motor_right", self.motor_right, -MAX_POWER, MAX_POWER),
            _check_int("flags", self.flags, 0, 255),
        ]
        return self.FMT.pack(*vals)

    @classmethod
    def unpack(cls, body: bytes) -> "Telemetry":
        v = cls.FMT.unpack(body)
        return cls(v[0], v[1], tuple(v[2:5]), tuple(v[5:8]), tuple(v[8:11]), v[11], v[12], v[13], v[14])

    @property
    def accel_si(self) -> tuple[float, float, float]:
        """Acceleration, m/s² (body frame)."""
        return tuple(c * ACCEL_MPS2_PER_LSB for c in self.accel)  # type: ignore[return-value]

    @property
    def gyro_si(self) -> tuple[float, float, float]:
        """Angular rate, rad/s (body frame)."""
        return tuple(c * GYRO_RADPS_PER_LSB for c in self.gyro)  # type: ignore[return-value]

    @property
    def mag_si(self) -> tuple[float, float, float]:
        """Magnetic field, µT (body frame)."""
        return tuple(c * MAG_UT_PER_LSB for c in self.mag)  # type: ignore[return-value]


def imu_to_raw(accel_mps2, gyro_radps, mag_ut) -> tuple[tuple[int, ...], tuple[int, ...], tuple[int, ...]]:
    """Convert SI IMU readings (m/s², rad/s, µT) to saturated raw int16 sensor units."""

    def conv(vec, scale):
        return tuple(max(-32768, min(32767, int(round(float(c) / scale)))) for c in vec)

    return conv(accel_mps2, ACCEL_MPS2_PER_LSB), conv(gyro_radps, GYRO_RADPS_PER_LSB), conv(mag_ut, MAG_UT_PER_LSB)


@dataclass(frozen=True)
class Ping:
    """Either direction: the receiver answers :class:`Pong` with the same token."""

    token: int

    TYPE: ClassVar[int] = PING
    FMT: ClassVar[struct.Struct] = struct.Struct("<I")

    def pack(self) -> bytes:
        return self.FMT.pack(_check_int("token", self.token, 0, 2**32 - 1))

    @classmethod
    def unpack(cls, body: bytes) -> "Ping":
        return cls(*cls.FMT.unpack(body))


@dataclass(frozen=True)
class Pong:
    """Answer to :class:`Ping`, echoing its token."""

    token: int

    TYPE: ClassVar[int] = PONG
    FMT: ClassVar[struct.Struct] = struct.Struct("<I")

    def pack(self) -> bytes:
        return self.FMT.pack(_check_int("token", self.token, 0, 2**32 - 1))

    @classmethod
    def unpack(cls, body: bytes) -> "Pong":
        return cls(*cls.FMT.unpack(body))


#: Error codes carried by :class:`Error`.
ERR_BAD_VERSION = 1
ERR_UNKNOWN_TYPE = 2
ERR_BAD_LENGTH = 3
ERR_BAD_VALUE = 4


@dataclass(frozen=True)
class Error:
    """Robot -> host: a request was refused. ``code`` is one of the ``ERR_*`` constants,
    ``ref_type`` the message type it refers to, ``text`` ASCII (<= 24 bytes)."""

    code: int
    ref_type: int
    text: str = ""

    TYPE: ClassVar[int] = ERROR
    FMT: ClassVar[struct.Struct] = struct.Struct("<BB24s")

    def pack(self) -> bytes:
        text = self.text.encode("ascii", "replace")[:24]
        return self.FMT.pack(_check_int("code", self.code, 0, 255), _check_int("ref_type", self.ref_type, 0, 255), text)

    @classmethod
    def unpack(cls, body: bytes) -> "Error":
        code, ref, text = cls.FMT.unpack(body)
        return cls(code, ref, text.rstrip(b"\x00").decode("ascii", "replace"))


Message = Union[Hello, HelloReply, SetMotors, SetLed, Stop, Telemetry, Ping, Pong, Error]
MESSAGE_TYPES: dict[int, type] = {
    cls.TYPE: cls for cls in (Hello, HelloReply, SetMotors, SetLed, Stop, Telemetry, Ping, Pong, Error)
}


#: Decoded fields whose physical range is narrower than their wire type: clamped on decode.
PHYSICAL_RANGES: dict[type, tuple[tuple[str, int, int], ...]] = {
    SetMotors: (("left", -MAX_POWER, MAX_POWER), ("right", -MAX_POWER, MAX_POWER)),
    Telemetry: (("motor_left", -MAX_POWER, MAX_POWER), ("motor_right", -MAX_POWER, MAX_POWER)),
}


def clamp_fields(msg: Message) -> tuple[Message, int]:
    """``msg`` with every field of :data:`PHYSICAL_RANGES` clamped into its range, and how many
    fields were out of range (0: ``msg`` itself)."""
    ranges = PHYSICAL_RANGES.get(type(msg))
    if not ranges:
        return msg, 0
    fixed = {}
    for name, lo, hi in ranges:
        v = getattr(msg, name)
        if v < lo or v > hi:
            fixed[name] = min(max(v, lo), hi)
    if not fixed:
        return msg, 0
    return dataclasses.replace(msg, **fixed), len(fixed)


@dataclass(frozen=True)
class Frame:
    """One decoded packet: header fields and the message.

    ``seq`` is the sender's 16-bit packet counter (wraps), ``time_us`` the sender's
    32-bit microsecond clock (wraps); ``clamped`` counts the message's fields that were out of
    their physical range and were clamped (see :func:`clamp_fields`)."""

    seq: int
    time_us: int
    msg: Message
    version: int = PROTOCOL_VERSION
    clamped: int = 0


def encode_packet(msg: Message, seq: int, time_us: int, version: int = PROTOCOL_VERSION) -> bytes:
    """Unframed packet bytes: header + body + CRC (what COBS then stuffs)."""
    body = msg.pack()
    head = HEADER.pack(version & 0xFF, msg.TYPE, seq & 0xFFFF, int(time_us) & 0xFFFFFFFF)
    data = head + body
    return data + struct.pack("<H", crc16(data))


def encode_frame(msg: Message, seq: int, time_us: int, version: int = PROTOCOL_VERSION) -> bytes:
    """Wire bytes of one message: ``COBS(packet) + b"\\x00"``.

    ``seq`` is taken modulo 2**16 and ``time_us`` modulo 2**32. Raises
    :class:`ProtocolError` if a field is out of range."""
    return cobs_encode(encode_packet(msg, seq, time_us, version)) + b"\x00"


def decode_packet(packet: bytes) -> Frame:
    """Parse an unframed packet (after COBS decoding); raises :class:`ProtocolError`
    with the reason (short, CRC, version, unknown type, body length)."""
    if len(packet) < HEADER_SIZE + CRC_SIZE:
        raise ProtocolError(f"packet of {len(packet)} bytes is shorter than header + CRC")
    data, (crc,) = packet[:-2], struct.unpack("<H", packet[-2:])
    if crc16(data) != crc:
        raise ProtocolError("CRC mismatch")
    version, mtype, seq, time_us = HEADER.unpack_from(data)
    if version != PROTOCOL_VERSION:
        raise ProtocolError(f"protocol version {version}, this side speaks {PROTOCOL_VERSION}")
    cls = MESSAGE_TYPES.get(mtype)
    if cls is None:
        raise ProtocolError(f"unknown message type 0x{mtype:02x}")
    body = data[HEADER_SIZE:]
    if len(body) != cls.FMT.size:
        raise ProtocolError(f"{cls.__name__} body of {len(body)} bytes, expected {cls.FMT.size}")
    msg, clamped = clamp_fields(cls.unpack(body))
    return Frame(seq, time_us, msg, version, clamped)


@dataclass
class DecoderStats:
    """Counters of a :class:`StreamDecoder` (all cumulative)."""

    frames: int = 0          # good frames returned
    crc_errors: int = 0      # CRC mismatch
    framing_errors: int = 0  # bad COBS, too short, too long
    version_errors: int = 0  # wrong protocol version
    unknown_type: int = 0    # unknown message type or wrong body length
    clamped: int = 0         # fields of good frames out of their physical range, clamped
    bytes_in: int = 0

    @property
    def rejected(self) -> int:
        """Every frame thrown away, whatever the reason."""
        return self.crc_errors + self.framing_errors + self.version_errors + self.unknown_type


@dataclass
class StreamDecoder:
    """Incremental decoder: ``feed(chunk) -> [Frame, ...]``.

    Chunks may split frames anywhere; bytes between delimiters that do not form a
    valid packet are counted in :attr:`stats` and dropped. Empty frames (two 0x00 in a
    row, used by senders to resynchronise) are ignored silently."""

    max_packet: int = MAX_PACKET
    stats: DecoderStats = field(default_factory=DecoderStats)
    _buf: bytearray = field(default_factory=bytearray, repr=False)
    _overflow: bool = field(default=False, repr=False)

    def feed(self, chunk: bytes) -> list[Frame]:
        """Consume ``chunk`` and return the frames it completed, in order."""
        self.stats.bytes_in += len(chunk)
        frames: list[Frame] = []
        start = 0
        limit = self.max_packet + 1  # COBS adds one byte per 254
        while True:
            idx = chunk.find(b"\x00", start)
            if idx < 0:
                rest = chunk[start:]
                if not self._overflow:
                    self._buf += rest
                    if len(self._buf) > limit:
                        self._buf.clear()
                        self._overflow = True
                return frames
            if self._overflow:
                self._overflow = False
                self._buf.clear()
                self.stats.framing_errors += 1
            else:
                self._buf += chunk[start:idx]
                if len(self._buf) > limit:
                    self.stats.framing_errors += 1
                elif self._buf:
                    frame = self._decode(bytes(self._buf))
                    if frame is not None:
                        frames.append(frame)
                self._buf.clear()
            start = idx + 1

    def _decode(self, raw: bytes) -> Frame | None:
        try:
            packet = cobs_decode(raw)
        except ProtocolError:
            self.stats.framing_errors += 1
            return None
        if len(packet) < HEADER_SIZE + CRC_SIZE:
            self.stats.framing_errors += 1
            return None
        data = packet[:-2]
        if crc16(data) != struct.unpack("<H", packet[-2:])[0]:
            self.stats.crc_errors += 1
            return None
        if data[0] != PROTOCOL_VERSION:
            self.stats.version_errors += 1
            return None
        try:
            frame = decode_packet(packet)
        except ProtocolError:
            self.stats.unknown_type += 1
            return None
        self.stats.frames += 1
        self.stats.clamped += frame.clamped
        return frame


def seq_gap(prev: int, seq: int) -> int:
    """Number of packets missing between 16-bit sequence numbers ``prev`` and ``seq``
    (0 when consecutive; wraps modulo 2**16)."""
    return (seq - prev - 1) & 0xFFFF


class Unwrapper:
    """Extend a wrapping counter (e.g. 32-bit µs clock, 16-bit seq) to a monotonic int.

    A step back by more than half the range is taken as a wrap forward, a step forward by more
    than half the range as a step back over an earlier wrap -- but only if there was one: before
    the first wrap it is a forward jump (a link silent for more than half the range while the
    robot ran on), so the result is never negative (it goes into ``seq`` and ``robot_time_us``
    of published telemetry, which are >= 0)."""

    def __init__(self, bits: int):
        self._mod = 1 << bits
        self._half = self._mod >> 1
        self._last: int | None = None
        self._offset = 0

    def __call__(self, value: int) -> int:
        if self._last is not None:
            delta = value - self._last
            if delta < -self._half:
                self._offset += self._mod
            elif delta > self._half and self._offset >= self._mod:
                self._offset -= self._mod
        self._last = value
        return value + self._offset

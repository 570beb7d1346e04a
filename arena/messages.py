"""Message schemas of the arena and their msgpack codec.

Every message is a msgpack map with ``v`` (schema version) and ``kind`` (both reserved: no field of
a message may use those names; pixel coordinates are ``u_px``/``v_px``). Decoding validates types,
ranges, finiteness and sizes, and raises :class:`MessageError` (one error type) with a message that
names the field. Messages of a newer schema version than this program knows are rejected clearly;
unknown extra fields are ignored, so a newer sender that only *adds* fields still interoperates.

Units: metres, radians (counter-clockwise from the arena +x axis), microseconds for sensor and pose
times, nanoseconds for host wall-clock times (``time.time_ns()``), m/s.

Example::

    >>> t = Track(track_id=3, robot="zumo1", camera="cam0", stamp_us=1_000, x=0.5, y=0.4, yaw=0.1)
    >>> Track.decode(t.encode()) == t
    True
"""

from __future__ import annotations

import functools
import math
from dataclasses import MISSING, dataclass, field, fields
from typing import Any, ClassVar

import msgpack

from arena.codec_names import MAX_WINDOW_EVENTS

__all__ = [
    "MessageError",
    "DecodeLimits",
    "DEFAULT_LIMITS",
    "Message",
    "EventWindow",
    "Track",
    "Telemetry",
    "GroundTruthPose",
    "MissionCommand",
    "Command",
    "CommandReply",
    "Status",
    "decode",
    "MESSAGE_TYPES",
    "TRACK_STATES",
    "TENTATIVE",
    "CONFIRMED",
    "COASTING",
]


class MessageError(ValueError):
    """A payload that is not a valid arena message; the text says which field is wrong."""


@dataclass(frozen=True)
class DecodeLimits:
    """Caps applied when decoding untrusted payloads (a malformed or hostile peer cannot make a
    receiver allocate more than this)."""

    max_payload_bytes: int = 64 * 1024 * 1024  # whole message
    max_window_bytes: int = 48 * 1024 * 1024  # compressed bytes of one event window
    max_window_events: int = MAX_WINDOW_EVENTS  # decoded events of one window (the codec's own limit)
    max_str: int = 4096
    max_map: int = 256


DEFAULT_LIMITS = DecodeLimits()

#: ``Track.state``: a new track not yet reported as a robot, a robot seen in the latest window,
#: a robot not seen lately whose position is predicted (the one definition of these names)
TRACK_STATES = (TENTATIVE, CONFIRMED, COASTING) = ("tentative", "confirmed", "coasting")
_INT64 = 2**63 - 1
_POS_M = 1e4  # any coordinate beyond 10 km is garbage


def _spec(kind: str, *, optional: bool = False, lo: float | None = None, hi: float | None = None,
          choices: tuple | None = None, length: int | None = None, default: Any = MISSING,
          rows: bool = False) -> Any:
    """Declare a message field: its wire type and the checks applied on decode. ``rows``: a
    ``map`` whose values may also be lists of numeric rows (see :func:`_check_rows`)."""
    meta = {"kind": kind, "optional": optional, "lo": lo, "hi": hi, "choices": choices, "length": length}
    if rows:
        meta["rows"] = True
    if default is MISSING and optional:
        default = None
    if isinstance(default, (dict, list)):
        factory = (lambda d=default: type(d)(d))
        return field(default_factory=factory, metadata=meta)
    if default is MISSING:
        return field(metadata=meta)
    return field(default=default, metadata=meta)


#: most rows of a ``rows`` map value (e.g. a mission's waypoints), and numbers per row
MAX_PARAM_ROWS = 1024
MAX_ROW_LEN = 64


def _check_rows(value: list, where: str) -> list:
    """A list of rows of finite numbers (``[[x, y], ...]``): at most :data:`MAX_PARAM_ROWS` rows of
    at most :data:`MAX_ROW_LEN` numbers, nothing nested deeper."""
    if len(value) > MAX_PARAM_ROWS:
        raise MessageError(f"{where}: {len(value)} rows, at most {MAX_PARAM_ROWS}")
    out = []
    for i, row in enumerate(value):
        if len(row) > MAX_ROW_LEN or any(isinstance(c, bool) or not isinstance(c, (int, float)) for c in row):
            raise MessageError(f"{where}[{i}]: a row must be a list of at most {MAX_ROW_LEN} numbers")
        out.append([_check_scalar(c, f"{where}[{i}]") for c in row])
    return out


def _check_scalar(value: Any, where: str) -> Any:
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, int):
        if abs(value) > _INT64:
            raise MessageError(f"{where}: integer out of range")
        return value
    if isinstance(value, float):
        if not math.isfinite(value):
            raise MessageError(f"{where}: must be finite, got {value}")
        return value
    if isinstance(value, list) and len(value) <= 64:
        if any(isinstance(v, (list, dict)) for v in value):
            raise MessageError(f"{where}: nested lists or maps are not allowed")
        return [_check_scalar(v, f"{where}[{i}]") for i, v in enumerate(value)]
    raise MessageError(f"{where}: unsupported value type {type(value).__name__}")


def _validate(cls_name: str, name: str, meta: dict, value: Any, limits: DecodeLimits) -> Any:
    where = f"{cls_name}.{name}"
    kind = meta["kind"]
    if value is None:
        if meta["optional"]:
            return None
        raise MessageError(f"{where}: required field is missing or null")
    if kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise MessageError(f"{where}: expected an integer, got {type(value).__name__}")
        lo, hi = meta["lo"], meta["hi"]
        if (lo is not None and value < lo) or (hi is not None and value > hi) or abs(value) > _INT64:
            raise MessageError(f"{where}: {value} is outside [{lo}, {hi}]")
        return value
    if kind == "float":
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise MessageError(f"{where}: expected a number, got {type(value).__name__}")
        value = float(value)
        if not math.isfinite(value):
            raise MessageError(f"{where}: must be finite, got {value}")
        lo, hi = meta["lo"], meta["hi"]
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            raise MessageError(f"{where}: {value} is outside [{lo}, {hi}]")
        return value
    if kind == "bool":
        if not isinstance(value, bool):
            raise MessageError(f"{where}: expected true/false, got {type(value).__name__}")
        return value
    if kind == "str":
        if not isinstance(value, str):
            raise MessageError(f"{where}: expected a string, got {type(value).__name__}")
        if len(value) > limits.max_str:
            raise MessageError(f"{where}: string longer than {limits.max_str} characters")
        if meta["choices"] and value not in meta["choices"]:
            raise MessageError(f"{where}: {value!r} is not one of {', '.join(meta['choices'])}")
        return value
    if kind == "bytes":
        if not isinstance(value, (bytes, bytearray)):
            raise MessageError(f"{where}: expected bytes, got {type(value).__name__}")
        if len(value) > limits.max_window_bytes:
            raise MessageError(f"{where}: {len(value)} bytes exceed the cap of {limits.max_window_bytes}")
        return bytes(value)
    if kind == "vec":
        n = meta["length"]
        if not isinstance(value, (list, tuple)) or len(value) != n:
            raise MessageError(f"{where}: expected a list of {n} numbers")
        out = []
        for i, v in enumerate(value):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise MessageError(f"{where}[{i}]: expected a finite number, got {v!r}")
            out.append(float(v))
        return tuple(out)
    if kind == "map":
        if not isinstance(value, dict):
            raise MessageError(f"{where}: expected a map, got {type(value).__name__}")
        if len(value) > limits.max_map:
            raise MessageError(f"{where}: more than {limits.max_map} entries")
        out = {}
        for k, v in value.items():
            if not isinstance(k, str) or len(k) > 128:
                raise MessageError(f"{where}: keys must be strings of at most 128 characters")
            if (meta.get("rows") and isinstance(v, list) and v
                    and all(isinstance(row, list) for row in v)):
                out[k] = _check_rows(v, f"{where}[{k!r}]")
            else:
                out[k] = _check_scalar(v, f"{where}[{k!r}]")
        return out
    raise AssertionError(f"unknown field kind {kind}")  # programming error in a schema


@functools.cache
def _fields(cls) -> tuple:
    """A message class's dataclass fields (``dataclasses.fields`` rebuilds the tuple on every
    call: a tenth of the bridge's CPU at 400 telemetry messages a second)."""
    return fields(cls)


@functools.cache
def _field_names(cls) -> tuple[str, ...]:
    return tuple(f.name for f in _fields(cls))


@dataclass
class Message:
    """Base of every arena message: msgpack encoding with ``v`` and ``kind``, validated decoding."""

    KIND: ClassVar[str] = ""
    VERSION: ClassVar[int] = 1

    def to_dict(self) -> dict:
        """The message as a plain dict (wire field names), without ``v``/``kind``."""
        return {name: getattr(self, name) for name in _field_names(type(self))}

    def encode(self) -> bytes:
        """Serialize to msgpack bytes (validating nothing: constructing is the sender's job).
        Tuples pack as msgpack arrays, like lists."""
        d = {"v": self.VERSION, "kind": self.KIND}
        for name in _field_names(type(self)):
            d[name] = getattr(self, name)
        return msgpack.packb(d, use_bin_type=True)

    @classmethod
    def from_dict(cls, d: dict, limits: DecodeLimits = DEFAULT_LIMITS):
        """Validate a decoded map and build the message; raise :class:`MessageError` if invalid."""
        v = d.get("v")
        if isinstance(v, bool) or not isinstance(v, int):
            raise MessageError(f"{cls.__name__}: missing or invalid schema version 'v'")
        if v > cls.VERSION:
            raise MessageError(
                f"{cls.__name__}: schema version {v} is newer than this program's {cls.VERSION}; "
                "upgrade the arena package on this host"
            )
        if v < 1:
            raise MessageError(f"{cls.__name__}: invalid schema version {v}")
        kwargs = {}
        for f in _fields(cls):
            if f.name in d:
                kwargs[f.name] = _validate(cls.__name__, f.name, f.metadata, d[f.name], limits)
            elif f.default is MISSING and f.default_factory is MISSING:
                raise MessageError(f"{cls.__name__}.{f.name}: required field is missing")
        msg = cls(**kwargs)
        msg._check(limits)
        return msg

    def _check(self, limits: DecodeLimits) -> None:
        """Cross-field checks of a subclass (ranges that depend on other fields)."""

    @classmethod
    def decode(cls, payload: bytes | bytearray | memoryview, limits: DecodeLimits = DEFAULT_LIMITS):
        """Decode msgpack bytes into this message type; raise :class:`MessageError` if invalid."""
        d = _unpack(payload, limits)
        kind = d.get("kind")
        if kind != cls.KIND:
            raise MessageError(f"expected a {cls.KIND!r} message, got kind {kind!r}")
        return cls.from_dict(d, limits)


def _unpack(payload, limits: DecodeLimits) -> dict:
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        try:
            payload = bytes(payload)  # zenoh.ZBytes
        except Exception as exc:  # noqa: BLE001 - anything unconvertible is a bad payload
            raise MessageError(f"payload is not bytes ({type(payload).__name__})") from exc
    if len(payload) > limits.max_payload_bytes:
        raise MessageError(f"payload of {len(payload)} bytes exceeds the cap of {limits.max_payload_bytes}")
    try:
        d = msgpack.unpackb(
            payload,
            raw=False,
            strict_map_key=True,
            max_bin_len=limits.max_window_bytes,
            max_str_len=max(limits.max_str, 1 << 16),
            max_array_len=4096,
            max_map_len=max(limits.max_map, 64),
            max_ext_len=0,
        )
    except Exception as exc:  # msgpack raises several unrelated types on garbage
        raise MessageError(f"payload is not valid msgpack: {exc.__class__.__name__}: {exc}") from None
    if not isinstance(d, dict):
        raise MessageError(f"payload is a msgpack {type(d).__name__}, expected a map")
    return d


@dataclass
class EventWindow(Message):
    """One slice of events from a camera, compressed (``arena/events/<camera>``).

    ``t_start_us``/``t_end_us`` are sensor-clock µs, the window is ``[t_start_us, t_end_us)``;
    ``data`` holds ``count`` events compressed with ``codec`` (see :mod:`arena.codec`).
    """

    KIND: ClassVar[str] = "event_window"
    camera: str = _spec("str")
    seq: int = _spec("int", lo=0)
    t_start_us: int = _spec("int")
    t_end_us: int = _spec("int")
    width: int = _spec("int", lo=1, hi=65535)
    height: int = _spec("int", lo=1, hi=65535)
    count: int = _spec("int", lo=0)
    codec: str = _spec("str")
    data: bytes = _spec("bytes")
    dropped: int = _spec("int", lo=0, default=0)  # slices dropped at the edge so far
    filtered: int = _spec("int", lo=0, default=0)  # events removed by edge filters in this window
    publish_ns: int = _spec("int", lo=0, default=0)  # host wall clock at publish
    #: host capture time - sensor time, ns: host time of sensor µs t is t * 1000 + this (None:
    #: unknown, e.g. a file replayed faster than real time); the edge's sliding-minimum estimate
    sensor_to_host_ns: int | None = _spec("int", optional=True)

    def _check(self, limits: DecodeLimits) -> None:
        if self.t_end_us < self.t_start_us:
            raise MessageError(f"EventWindow.t_end_us: {self.t_end_us} is before t_start_us {self.t_start_us}")
        if self.count > limits.max_window_events:
            raise MessageError(f"EventWindow.count: {self.count} events exceed the cap of {limits.max_window_events}")


@dataclass
class Track(Message):
    """A tracked robot (``arena/robots/<id>``): pose in arena metres at ``stamp_us`` (sensor clock)."""

    KIND: ClassVar[str] = "track"
    track_id: int = _spec("int", lo=0)
    robot: str | None = _spec("str", optional=True)
    camera: str = _spec("str", default="")
    stamp_us: int = _spec("int", default=0)
    x: float = _spec("float", lo=-_POS_M, hi=_POS_M, default=0.0)
    y: float = _spec("float", lo=-_POS_M, hi=_POS_M, default=0.0)
    yaw: float | None = _spec("float", optional=True, lo=-10.0, hi=10.0)
    vx: float | None = _spec("float", optional=True, lo=-100.0, hi=100.0)
    vy: float | None = _spec("float", optional=True, lo=-100.0, hi=100.0)
    u_px: float | None = _spec("float", optional=True, lo=-1e5, hi=1e5)  # sensor column
    v_px: float | None = _spec("float", optional=True, lo=-1e5, hi=1e5)  # sensor row
    state: str = _spec("str", choices=TRACK_STATES, default="confirmed")
    n_events: int = _spec("int", lo=0, default=0)
    window_end_us: int | None = _spec("int", optional=True)  # end of the slice this update came from
    edge_publish_ns: int | None = _spec("int", optional=True, lo=0)  # when the edge published that slice
    tracker_publish_ns: int | None = _spec("int", optional=True, lo=0)  # when the tracker published this
    #: host capture time of ``stamp_us``, ns since the epoch (stamp_us * 1000 + the edge's
    #: sensor_to_host_ns; None when the edge did not know it): lines tracks up with host-stamped truth
    host_ns: int | None = _spec("int", optional=True)


@dataclass
class Telemetry(Message):
    """One sample from a robot (``arena/telemetry/<robot>``)."""

    KIND: ClassVar[str] = "telemetry"
    robot: str = _spec("str")
    seq: int = _spec("int", lo=0)
    robot_time_us: int = _spec("int", lo=0)
    host_time_ns: int = _spec("int", lo=0)
    enc_left: int = _spec("int")
    enc_right: int = _spec("int")
    speed_left: float = _spec("float", lo=-100, hi=100, default=0.0)  # wheel speeds, m/s
    speed_right: float = _spec("float", lo=-100, hi=100, default=0.0)
    accel: tuple = _spec("vec", length=3, default=(0.0, 0.0, 0.0))  # m/s^2, body frame
    gyro: tuple = _spec("vec", length=3, default=(0.0, 0.0, 0.0))  # rad/s
    mag: tuple = _spec("vec", length=3, default=(0.0, 0.0, 0.0))  # µT
    battery_mv: int = _spec("int", lo=0, hi=100_000, default=0)
    power_left: int = _spec("int", lo=-400, hi=400, default=0)
    power_right: int = _spec("int", lo=-400, hi=400, default=0)
    mission: str | None = _spec("str", optional=True)
    phase: str | None = _spec("str", optional=True)


@dataclass
class GroundTruthPose(Message):
    """A pose measured independently of the tracker (``arena/groundtruth/<robot>``, or the
    simulator's exact truth on ``arena/sim/truth/<robot>``)."""

    KIND: ClassVar[str] = "groundtruth"
    robot: str = _spec("str")
    stamp_us: int = _spec("int")  # capture time, host clock in µs (webcam) or sensor clock (sim)
    x: float = _spec("float", lo=-_POS_M, hi=_POS_M)
    y: float = _spec("float", lo=-_POS_M, hi=_POS_M)
    yaw: float | None = _spec("float", optional=True, lo=-10.0, hi=10.0)
    u_px: float | None = _spec("float", optional=True, lo=-1e5, hi=1e5)  # sensor column
    v_px: float | None = _spec("float", optional=True, lo=-1e5, hi=1e5)  # sensor row
    detector: str = _spec("str", default="")  # aruco | hsv | sim


@dataclass
class MissionCommand(Message):
    """Start a mission on a robot (query payload of ``arena/cmd/<robot>/mission``).

    ``params`` are the mission's own (e.g. ``radius_m``, ``side_m``, ``laps``, ``direction``);
    ``power`` is the motor power fraction (0.5 = the paper's 50 %), or ``speed_mps`` a target speed.
    ``control`` is ``paper`` (encoder PID only) or ``closed`` (follows the robot's own track).
    """

    KIND: ClassVar[str] = "mission"
    mission: str = _spec("str")
    params: dict = _spec("map", default={}, rows=True)  # values may be rows: points=[[x, y], ...]
    power: float | None = _spec("float", optional=True, lo=0.0, hi=1.0)
    speed_mps: float | None = _spec("float", optional=True, lo=0.0, hi=2.0)
    control: str = _spec("str", choices=("paper", "closed"), default="paper")
    start_ns: int | None = _spec("int", optional=True, lo=0)  # start together at this wall-clock time
    operator: str | None = _spec("str", optional=True)


@dataclass
class Command(Message):
    """A simple command (query payload of ``arena/cmd/<robot>/{stop,estop,clear,led}``)."""

    KIND: ClassVar[str] = "command"
    verb: str = _spec("str")
    params: dict = _spec("map", default={})
    operator: str | None = _spec("str", optional=True)


@dataclass
class CommandReply(Message):
    """The bridge's answer to a command: an ack or a clear error."""

    KIND: ClassVar[str] = "reply"
    ok: bool = _spec("bool")
    robot: str = _spec("str", default="")
    verb: str = _spec("str", default="")
    error: str | None = _spec("str", optional=True)
    detail: dict = _spec("map", default={})


@dataclass
class Status(Message):
    """Once-a-second health of a service (``arena/status/<role>/<name>``)."""

    KIND: ClassVar[str] = "status"
    role: str = _spec("str")
    name: str = _spec("str")
    host: str = _spec("str", default="")
    pid: int = _spec("int", lo=0, default=0)
    time_ns: int = _spec("int", lo=0, default=0)
    uptime_s: float = _spec("float", lo=0.0, default=0.0)
    state: str = _spec("str", default="running")
    counters: dict = _spec("map", default={})  # monotonically increasing totals
    rates: dict = _spec("map", default={})  # per second over the last period
    gauges: dict = _spec("map", default={})  # last values (latency_ms, queue depth, ...)
    errors: int = _spec("int", lo=0, default=0)
    last_error: str | None = _spec("str", optional=True)


MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.KIND: cls
    for cls in (EventWindow, Track, Telemetry, GroundTruthPose, MissionCommand, Command, CommandReply, Status)
}


def decode(payload, limits: DecodeLimits = DEFAULT_LIMITS) -> Message:
    """Decode any arena message, dispatching on its ``kind``; raise :class:`MessageError` if invalid."""
    d = _unpack(payload, limits)
    kind = d.get("kind")
    cls = MESSAGE_TYPES.get(kind) if isinstance(kind, str) else None
    if cls is None:
        raise MessageError(f"unknown message kind {kind!r}; expected one of {', '.join(MESSAGE_TYPES)}")
    return cls.from_dict(d, limits)

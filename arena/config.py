"""The lab config: one TOML file every host of a lab shares.

It describes the arena, the cameras (with their calibration pixel -> arena metres), the webcam, the
robots, the Zenoh endpoints and per-service options. See ``deploy/lab.example.toml`` for a complete,
commented example matching the paper's lab. Every mistake raises :class:`ConfigError` whose message
names the file, the key and what was expected, e.g.::

    deploy/lab.toml: robots[2].marker_id: expected an integer >= 0, got "seven"
"""

from __future__ import annotations

import builtins
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

try:  # Python 3.11+
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]

from arena.codec_names import CODECS, DEFAULT_CODEC
from arena.keys import InvalidKey, validate_name

__all__ = [
    "ConfigError",
    "LabConfig",
    "ArenaConfig",
    "CameraConfig",
    "WebcamConfig",
    "RobotConfig",
    "ZenohSettings",
    "MODES",
    "DEFAULT_ROUTER",
    "DefaultEndpoints",
    "LEASE_MS_RANGE",
    "dial_port_zero",
    "load_lab_config",
    "parse_lab_config",
    "NAMED_COLOURS",
    "ServiceOption",
    "SERVICE_OPTIONS",
    "parse_service_options",
    "apply_service_options",
    "fill_service_options",
    "CAMERA_HEIGHT_RANGE_M",
    "NADIR_MAX_ARENAS",
    "ROBOT_HEIGHT_MAX_CM",
    "ARUCO_MARKER_IDS",
    "nadir_distance_m",
]

#: Physical range of a ceiling camera's lens height above the mats, m (inclusive). Below 0.3 m a
#: lens sees a few tens of cm of floor (a 90 deg lens: 0.6 m), not an arena; 20 m is the ceiling
#: of a tall sports hall or warehouse, where the VGA lens that shows a 1.83 m arena 450 px wide
#: from 2.5 m shows a 10 cm robot 3 px wide. A height outside it is a mistyped unit (cm or mm for
#: m) or a broken estimate (e.g. from a wrong focal length), not a lab.
CAMERA_HEIGHT_RANGE_M = (0.3, 20.0)
#: The farthest a camera's nadir (the arena point under its lens) may lie outside the arena
#: rectangle, in arena sides (its longer side): 2 sides off, a camera 2.5 m above a 1.83 m arena
#: sees the arena's far edge 66 deg off the vertical; farther is a wrong sign, unit or frame.
NADIR_MAX_ARENAS = 2.0
#: Robots are seen below this height, cm (exclusive; the tracker's ``--robot-height-cm`` bound).
ROBOT_HEIGHT_MAX_CM = 100.0
#: Marker ids the lab's ArUco dictionary (DICT_4X4_50: printed by ``arena sim --markers``, detected
#: by ``arena groundtruth --detector aruco``) has: 0..49.
ARUCO_MARKER_IDS = 50


def nadir_distance_m(nadir_m, size_m) -> float:
    """Distance (m) from the point ``nadir_m`` (x, y) to the arena rectangle [0, w] x [0, h]
    (0 inside it)."""
    (x, y), (w, h) = nadir_m, size_m
    dx = max(0.0 - x, 0.0, x - w)
    dy = max(0.0 - y, 0.0, y - h)
    return math.hypot(dx, dy)

#: Shell colours that may be given by name (RGB, 0-255).
NAMED_COLOURS: dict[str, tuple[int, int, int]] = {
    "black": (20, 20, 20),
    "yellow": (235, 200, 40),
    "red": (200, 30, 30),
    "blue": (30, 60, 200),
    "green": (30, 160, 60),
    "orange": (240, 120, 20),
    "purple": (120, 40, 160),
    "grey": (110, 110, 110),
    "white": (230, 230, 230),
    "cyan": (30, 180, 200),
}

#: Zenoh session modes
MODES = ("peer", "client", "router")
#: where a client connects unless told otherwise (``arena router``'s default endpoint)
DEFAULT_ROUTER = "tcp/127.0.0.1:7447"
_ENDPOINT_RE = re.compile(r"^(tcp|udp|tls|quic|ws|unixsock-stream)/.+")
_PORT_RE = re.compile(r"^(?:tcp|udp|tls|quic|ws)/.*:(\d+)(?:[?#].*)?$")
#: link lease bounds, ms (``lease_ms``, ``--lease-ms``): Zenoh's default is 10000; below 100 ms a busy
#: host's keep-alives are late and links drop; above 10 minutes a dead service is never noticed
LEASE_MS_RANGE = (100, 600_000)


class DefaultEndpoints(list):
    """The built-in connect endpoints (``[DEFAULT_ROUTER]``), given by nobody: a Zenoh config
    file's own connect endpoints (``config_file``, ``-c``) replace them, explicit ones do not."""


def dial_port_zero(endpoint: str) -> bool:
    """Whether Zenoh ``endpoint`` (``tcp/HOST:PORT``, ...) has port 0: listening there takes a
    free port the OS chooses, but dialling it reaches nothing."""
    m = _PORT_RE.match(endpoint)
    return bool(m) and int(m.group(1)) == 0


class ConfigError(ValueError):
    """A lab config that cannot be used; the message names the file, the key and the expectation."""


@dataclass
class ArenaConfig:
    """The arena floor: a rectangle of ``size_m`` (x, y) metres with its origin at one mat corner."""

    name: str = "arena"
    size_m: tuple[float, float] = (1.83, 1.83)


@dataclass
class CameraConfig:
    """An event camera: its name (used in keys), sensor size (px), source URL and calibration,
    and where its lens is (``camera_height_m`` above the mats, ``nadir_m`` the arena point under
    it, m; None: the calibration's, if it has them) for the tracker's parallax correction."""

    name: str
    width: int = 640
    height: int = 480
    source: str | None = None
    calibration: dict | None = None  # calibration JSON dict: {"image_size": [w, h], "points": [...]}
    calibration_file: str | None = None
    camera_height_m: float | None = None
    nadir_m: tuple[float, float] | None = None


@dataclass
class WebcamConfig:
    """The RGB webcam of the ground truth: a device index, file or URL, and its calibration."""

    source: str = "0"
    fps: float = 24.0
    calibration: dict | None = None
    calibration_file: str | None = None
    detector: str = "aruco"


@dataclass
class RobotConfig:
    """One robot: name, shell colour (RGB), marker id, serial URL, wheel geometry (m) and the
    effective height (cm) at which the ceiling camera sees it (None: the tracker's default, a
    Zumo's 3.2 cm: the mean height of its event cloud, lower than its 4.5 cm shell top)."""

    name: str
    color_rgb: tuple[int, int, int] = (20, 20, 20)
    marker_id: int | None = None
    serial_url: str | None = None
    sprocket_diameter_m: float = 0.038
    track_width_m: float = 0.09
    counts_per_rev: int = 1807
    length_m: float = 0.10
    width_m: float = 0.10
    hsv_range: tuple | None = None  # ((h_lo, s_lo, v_lo), (h_hi, s_hi, v_hi)) for the colour detector
    robot_height_cm: float | None = None


@dataclass
class ZenohSettings:
    """How a service reaches Zenoh: the lab file's ``[zenoh]`` table (:attr:`LabConfig.zenoh`) and,
    merged with the environment and the command line, a service's resolved settings
    (:func:`arena.session.resolve_settings`; :func:`arena.session.to_zenoh_config` turns them into
    a ``zenoh.Config``). See ``docs/deployment.md``."""

    mode: str = "client"
    connect: list[str] = field(default_factory=lambda: DefaultEndpoints([DEFAULT_ROUTER]))
    listen: list[str] = field(default_factory=list)
    multicast_scouting: bool = False
    lease_ms: int | None = None
    config_file: str | None = None  # JSON5 file with anything else (TLS, auth, access control)
    tls: dict = field(default_factory=dict)  # root_ca_certificate, connect_certificate, ...
    user: str | None = None
    password: str | None = None
    #: ``KEY:VALUE`` settings (``--cfg``): a Zenoh config path and a JSON5 value, applied last
    cfg: list[str] = field(default_factory=list)

    def describe(self) -> str:
        """One line for logs and errors: the mode and the endpoints."""
        ends = ", ".join(self.connect) or "none"
        lst = f", listening on {', '.join(self.listen)}" if self.listen else ""
        return f"{self.mode} mode, connecting to {ends}{lst}"


@dataclass
class LabConfig:
    """A whole lab: the parsed and validated contents of a lab TOML file."""

    arena: ArenaConfig = field(default_factory=ArenaConfig)
    cameras: list[CameraConfig] = field(default_factory=list)
    webcam: WebcamConfig | None = None
    robots: list[RobotConfig] = field(default_factory=list)
    zenoh: ZenohSettings = field(default_factory=ZenohSettings)
    services: dict[str, dict] = field(default_factory=dict)
    path: str | None = None

    def camera(self, name: str | None = None) -> CameraConfig:
        """The camera called ``name`` (or the only/first one when ``name`` is None)."""
        if not self.cameras:
            raise ConfigError(f"{self.path or 'lab config'}: no [[cameras]] defined")
        if name is None:
            return self.cameras[0]
        for c in self.cameras:
            if c.name == name:
                return c
        raise ConfigError(
            f"{self.path or 'lab config'}: no camera named {name!r}; known: {', '.join(c.name for c in self.cameras)}"
        )

    def robot(self, name: str) -> RobotConfig:
        """The robot called ``name``."""
        for r in self.robots:
            if r.name == name:
                return r
        raise ConfigError(
            f"{self.path or 'lab config'}: no robot named {name!r}; known: {', '.join(r.name for r in self.robots) or 'none'}"
        )

    def robot_height_cm(self) -> float | None:
        """The robots' visible height for the tracker, cm: the mean of the ``robot_height_cm``
        of the ``[[robots]]`` that give one (the tracker applies one height to every track),
        None when none does."""
        hs = [r.robot_height_cm for r in self.robots if r.robot_height_cm is not None]
        return sum(hs) / len(hs) if hs else None

    def service(self, role: str) -> dict:
        """The options ``[services.<role>]`` gives (validated against :data:`SERVICE_OPTIONS` when
        the file was loaded; numbers of float options are floats), empty if absent. Options the
        table leaves out are not filled in: their defaults are in :data:`SERVICE_OPTIONS`."""
        return dict(self.services.get(role, {}))


# ----------------------------------------------------------------------------- [services.<role>]


@dataclass(frozen=True)
class ServiceOption:
    """One option of a ``[services.<role>]`` table: its type, allowed values and default.

    ``type``: ``"str"``, ``"name"`` (a valid key chunk, see :func:`arena.keys.validate_name`),
    ``"int"``, ``"float"`` (an integer is accepted and becomes a float), ``"bool"``,
    ``"strings"`` (a list of strings; one string is a list of one), or alternatives joined by
    ``|`` (``"int|bool"``). ``lo``/``hi``: inclusive bounds of a number; ``positive``: > 0;
    ``hi_open``: ``hi`` is excluded; ``choices``: allowed strings. ``dest``: the attribute of the service's command-line
    namespace the option fills (default: the option's own name). ``default``: the value used
    when neither the flag nor the lab file gives one (None: the service decides).
    """

    type: str
    default: Any = None
    help: str = ""
    choices: tuple[str, ...] | None = None
    lo: float | None = None
    hi: float | None = None
    positive: bool = False
    dest: str | None = None
    hi_open: bool = False   # ``hi`` is excluded: [lo, hi)

    def expected(self) -> str:
        """What a valid value looks like, for error messages."""
        out = []
        for kind in self.type.split("|"):
            if kind in ("int", "float"):
                what = "an integer" if kind == "int" else "a finite number"
                if self.positive:
                    what += " > 0"
                elif self.lo is not None and self.hi is not None:
                    what += f" in [{self.lo:g}, {self.hi:g}{')' if self.hi_open else ']'}"
                elif self.lo is not None:
                    what += f" >= {self.lo:g}"
                elif self.hi is not None:
                    what += f" {'<' if self.hi_open else '<='} {self.hi:g}"
                out.append(what)
            elif kind == "bool":
                out.append("true or false")
            elif kind == "strings":
                out.append("a list of strings")
            elif kind == "name":
                out.append("a name of letters, digits, '-', '_' or '.'")
            elif self.choices:
                out.append(f"one of {', '.join(self.choices)}")
            else:
                out.append("a string")
        return " or ".join(out)

    def convert(self, value: Any) -> tuple[bool, Any]:
        """``(True, value as the service takes it)`` if ``value`` is valid, else ``(False, None)``."""
        for kind in self.type.split("|"):
            if kind == "bool":
                if isinstance(value, bool):
                    return True, value
            elif kind in ("int", "float"):
                if isinstance(value, bool) or not isinstance(value, (int, float) if kind == "float" else int):
                    continue
                if not _finite(value) or (self.positive and value <= 0):
                    continue
                if (self.lo is not None and value < self.lo) or (self.hi is not None and value > self.hi):
                    continue
                if self.hi_open and value >= self.hi:
                    continue
                return True, (float(value) if kind == "float" else value)
            elif kind == "strings":
                items = [value] if isinstance(value, str) else value
                if isinstance(items, list) and all(isinstance(v, str) and v for v in items):
                    return True, list(items)
            elif kind == "name":
                try:
                    return True, validate_name(value)
                except InvalidKey:
                    continue
            elif isinstance(value, str) and (not self.choices or value in self.choices):
                return True, value
        return False, None



def _finite(x) -> bool:
    """A finite number that fits a float (TOML integers have any size: 10**400 is not finite here)."""
    try:
        return math.isfinite(x)
    except OverflowError:
        return False

def _opt(type: str, default: Any = None, help: str = "", **kw: Any) -> ServiceOption:  # noqa: A002
    return ServiceOption(type, default, help, **kw)


#: Every ``[services.<role>]`` table a lab file may hold, and its options (the one definition:
#: :func:`parse_lab_config` checks the tables against it, :func:`apply_service_options` fills a
#: service's unset flags from it). A flag given on the command line wins over the lab file.
SERVICE_OPTIONS: dict[str, dict[str, ServiceOption]] = {
    "edge": {  # arena edge
        "slice_ms": _opt("float", 10.0, "slice duration, ms of sensor time", positive=True),
        "codec": _opt("str", DEFAULT_CODEC, "window codec", choices=CODECS),
        "speed": _opt("float", 1.0, "file replay speed (1 real time, 0 as fast as possible)", lo=0),
        "hot_pixels": _opt("str", None, "'learn', or a file of hot pixels to drop"),
        "hot_learn_s": _opt("float", 2.0, "learning time of hot pixels, s", positive=True),
        "hot_save": _opt("str", None, "with hot_pixels = 'learn': write the learnt hot pixels here"),
        "roi": _opt("str", None, "'lab' or a calibration JSON: keep events inside the arena"),
        "roi_margin": _opt("int", 10, "growth of the region of interest, px", lo=0),
        "denoise": _opt("int|bool", None, "background-activity window, µs (true: 10000)", positive=True),
        "queue": _opt("int", 32, "windows queued before the oldest is dropped", lo=1),
    },
    "tracker": {  # arena track (live and offline)
        "tracker": _opt("str", "fleet", "fleet (Kalman + assignment) or idtrack (the paper's Algorithm 1)",
                        choices=("fleet", "idtrack")),
        "detector": _opt("str", "default", "default (physical, adaptive) or paper", choices=("default", "paper")),
        "backend": _opt("str", "grid", "DBSCAN backend", choices=("grid", "sklearn")),
        "slice_ms": _opt("float", 10.0, "offline slice length, ms", positive=True),
        "accumulation_ms": _opt("float", 100.0, "accumulation time t_a, ms", positive=True),
        "chassis_cm": _opt("float", 10.0, "robot footprint side, cm", positive=True),
        "robot_height_cm": _opt("float", None, "visible height of the robots, cm (default: the [[robots]]' "
                                "robot_height_cm, else 3.2: a Zumo's event cloud)", lo=0, hi=ROBOT_HEIGHT_MAX_CM,
                                hi_open=True),
        "camera_height_m": _opt("float", None, "lens height above the mats, m (default: the camera's or its "
                                "calibration's camera_height_m, else 2.5 assumed with a warning)",
                                lo=CAMERA_HEIGHT_RANGE_M[0], hi=CAMERA_HEIGHT_RANGE_M[1]),
        "fleet_size": _opt("int", None, "number of robots (default: the lab's [[robots]])", lo=1),
        "queue": _opt("int", 100, "live: newest slices kept when lagging", lo=1),
        "names_from_groundtruth": _opt("bool", True, "live: name tracks after arena/groundtruth/* poses"),
        "state_max_age_s": _opt("float", 600.0, "live: a state file older than this is not restored, s",
                                lo=0, dest="state_max_age"),
    },
    "bridge": {  # arena bridge run (defaults as robot_bridge.core.BridgeOptions)
        "telemetry_dir": _opt("str", "bridge_logs", "mission logs directory", dest="log_dir"),
        "geofence_margin_m": _opt("float", 0.03, "stop a robot closer than this to the arena edge, m", lo=0,
                                  dest="geofence_margin"),
        "low_battery_mv": _opt("int", 4400, "stop missions below this battery voltage, mV", lo=0),
        "baudrate": _opt("int", 57600, "serial baud rate", positive=True, dest="baud"),
        "track_delay_s": _opt("float", 0.0, "extra age of track poses, s", lo=0, dest="track_delay"),
        "link_timeout_s": _opt("float", 2.0, "a robot's link is down after this long without a frame from it, s",
                               positive=True, dest="link_timeout"),
    },
    "groundtruth": {  # arena groundtruth (the webcam service; its source and detector are in [webcam])
        "clock": _opt("str", "host", "frame times: host clock at capture, or the MJPEG stream's",
                      choices=("host", "stream")),
        "name": _opt("name", "webcam", "service name in arena status"),
    },
    "viewer": {  # arena view
        "host": _opt("str", "127.0.0.1", "address to serve the page on"),
        "port": _opt("int", 8080, "TCP port (0: any free port)", lo=0, hi=65535),
        "accumulate_ms": _opt("float", 100.0, "sensor time the event image shows, ms", positive=True),
        "rate": _opt("float", 10.0, "updates per second sent to the page", positive=True),
    },
    "recorder": {  # arena record
        "keys": _opt("strings", None, "key expressions to record (default arena/**)"),
        "queue": _opt("int", 10_000, "samples buffered before the file writer", lo=1),
    },
}


def parse_service_options(role: str, options: Any, source: str = "lab config") -> dict:
    """Check the ``[services.<role>]`` table ``options`` against :data:`SERVICE_OPTIONS`; returns
    the options it gives, converted (an integer for a float option becomes a float). Raises
    :class:`ConfigError` naming ``source``, the table and the key, listing the known ones."""
    known = SERVICE_OPTIONS.get(role)
    if known is None:
        raise ConfigError(f"{source}: unknown table [services.{role}]; known service tables: "
                          f"{', '.join(f'[services.{r}]' for r in SERVICE_OPTIONS)}")
    if not isinstance(options, dict):
        raise ConfigError(f"{source}: services.{role}: expected a table of options, got {options!r}")
    extra = sorted(set(options) - set(known))
    if extra:
        raise ConfigError(f"{source}: services.{role}: unknown key(s) {', '.join(extra)}; "
                          f"known: {', '.join(known)}")
    out = {}
    for key, value in options.items():
        ok, v = known[key].convert(value)
        if not ok:
            raise ConfigError(f"{source}: services.{role}.{key}: expected {known[key].expected()}, got {value!r}")
        out[key] = v
    return out


def fill_service_options(args: Any, role: str, options: dict) -> dict[str, str]:
    """Set every attribute of ``args`` (an argparse namespace) that the command line left None
    from ``options`` (checked ``[services.<role>]`` values), else the option's default: flags
    win, then the lab file, then the defaults. Returns where each value came from
    (``{dest: "flag" | "lab" | "default"}``)."""
    origin = {}
    for key, opt in SERVICE_OPTIONS[role].items():
        dest = opt.dest or key
        if getattr(args, dest, None) is not None:
            origin[dest] = "flag"
        elif key in options:
            setattr(args, dest, options[key])
            origin[dest] = "lab"
        else:
            setattr(args, dest, opt.default)
            origin[dest] = "default"
    return origin


def apply_service_options(args: Any, lab: "LabConfig | None", role: str) -> dict[str, str]:
    """Fill the unset (None) flags of ``role``'s command line from the lab file's
    ``[services.<role>]`` (already checked when ``lab`` was loaded), else the defaults of
    :data:`SERVICE_OPTIONS`. ``lab`` may be None (defaults only). See :func:`fill_service_options`."""
    return fill_service_options(args, role, lab.service(role) if lab is not None else {})


class _Reader:
    """Typed access to a TOML table with error messages naming file and key."""

    def __init__(self, source: str, table: dict, prefix: str):
        self.source, self.table, self.prefix = source, table, prefix

    def _err(self, key: str, expected: str, value: Any = None, show: bool = True) -> ConfigError:
        where = f"{self.prefix}.{key}" if self.prefix else key
        got = f", got {value!r}" if show else ""
        return ConfigError(f"{self.source}: {where}: expected {expected}{got}")

    def sub(self, key: str, what: str = "a table") -> "_Reader":
        v = self.table.get(key, {})
        if not isinstance(v, dict):
            raise self._err(key, what, v)
        return _Reader(self.source, v, f"{self.prefix}.{key}" if self.prefix else key)

    def has(self, key: str) -> bool:
        return key in self.table

    def str(self, key: str, default: Any = ..., choices: tuple | None = None) -> Any:
        if key not in self.table:
            if default is ...:
                raise self._err(key, "a string (this key is required)", show=False)
            return default
        v = self.table[key]
        if not isinstance(v, str):
            raise self._err(key, "a string", v)
        if choices and v not in choices:
            raise self._err(key, f"one of {', '.join(choices)}", v)
        return v

    def name(self, key: str) -> str:
        v = self.str(key)
        try:
            return validate_name(v, key)
        except InvalidKey as exc:
            raise self._err(key, f"a valid name ({exc})", v, show=False) from None

    def int(self, key: str, default: Any = ..., lo: int | None = None, hi: int | None = None) -> Any:
        if key not in self.table:
            if default is ...:
                raise self._err(key, "an integer (this key is required)", show=False)
            return default
        v = self.table[key]
        rng = f" in [{lo}, {hi}]" if lo is not None and hi is not None else (f" >= {lo}" if lo is not None else "")
        if isinstance(v, bool) or not isinstance(v, int) or (lo is not None and v < lo) or (hi is not None and v > hi):
            raise self._err(key, f"an integer{rng}", v)
        return v

    def float(self, key: str, default: Any = ..., lo: float | None = None, hi: float | None = None,
              positive: bool = False) -> Any:
        if key not in self.table:
            if default is ...:
                raise self._err(key, "a number (this key is required)", show=False)
            return default
        v = self.table[key]
        ok = not isinstance(v, bool) and isinstance(v, (int, float)) and _finite(v)
        if ok and ((lo is not None and v < lo) or (hi is not None and v > hi) or (positive and v <= 0)):
            ok = False
        if not ok:
            rng = " > 0" if positive else (f" in [{lo}, {hi}]" if lo is not None and hi is not None else "")
            raise self._err(key, f"a finite number{rng}", v)
        return float(v)

    def bool(self, key: str, default: bool) -> bool:
        v = self.table.get(key, default)
        if not isinstance(v, bool):
            raise self._err(key, "true or false", v)
        return v

    def str_list(self, key: str, pattern: re.Pattern | None = None, what: str = "strings") -> list[str]:
        v = self.table.get(key, [])
        if isinstance(v, str):
            v = [v]
        if not isinstance(v, list) or not all(isinstance(s, str) for s in v):
            raise self._err(key, f"a list of {what}", v)
        if pattern is not None:
            for s in v:
                if not pattern.match(s):
                    raise self._err(key, f"a list of {what}", s)
        return list(v)

    def pair(self, key: str, default: Any, integers: bool = False, positive: bool = False) -> Any:
        if key not in self.table:
            return default
        v = self.table[key]
        good = (isinstance(v, list) and len(v) == 2 and all(
            not isinstance(x, bool) and isinstance(x, (int, float)) and _finite(x) and (not positive or x > 0)
            for x in v))
        if integers and good:
            good = all(isinstance(x, int) for x in v)
        if not good:
            raise self._err(key, f"a pair of {'positive ' if positive else ''}{'integers' if integers else 'numbers'} [a, b]", v)
        return tuple((int(x) if integers else builtins.float(x)) for x in v)

    def unknown(self, known: tuple[str, ...]) -> None:
        extra = sorted(set(self.table) - set(known))
        if extra:
            where = f"{self.prefix}: " if self.prefix else ""
            raise ConfigError(f"{self.source}: {where}unknown key(s) {', '.join(extra)}; expected some of {', '.join(known)}")


def _calibration(r: _Reader, base_dir: Path | None) -> tuple[dict | None, str | None]:
    """Read an inline calibration (``points = [...]``) or a file reference (``calibration = "x.json"``)."""
    file = r.str("calibration", None)
    if file is not None:
        path = Path(file)
        if not path.is_absolute() and base_dir is not None:
            path = base_dir / path
        return None, str(path)
    if not r.has("points"):
        return None, None
    pts = r.table["points"]
    if not isinstance(pts, list) or len(pts) < 4:
        raise r._err("points", "a list of at least 4 {pixel = [u, v], arena_m = [x, y]} tables", pts)
    out = []
    for i, p in enumerate(pts):
        if not isinstance(p, dict) or "pixel" not in p or "arena_m" not in p:
            raise r._err(f"points[{i}]", "a table {pixel = [u, v], arena_m = [x, y]}", p)
        pr = _Reader(r.source, p, f"{r.prefix}.points[{i}]")
        out.append({"pixel": list(pr.pair("pixel", None)), "arena_m": list(pr.pair("arena_m", None))})
    w = r.int("width", 640, lo=1)
    h = r.int("height", 480, lo=1)
    return {"image_size": [w, h], "points": out}, None


def _colour(r: _Reader, key: str, default: tuple[int, int, int]) -> tuple[int, int, int]:
    if key not in r.table:
        return default
    v = r.table[key]
    if isinstance(v, str):
        if v.lower() in NAMED_COLOURS:
            return NAMED_COLOURS[v.lower()]
        m = re.match(r"^#?([0-9a-fA-F]{6})$", v)
        if m:
            h = m.group(1)
            return (int(h[0:2], 16), int(h[2:4], 16), int(h[4:6], 16))
    if isinstance(v, list) and len(v) == 3 and all(isinstance(c, int) and not isinstance(c, bool) and 0 <= c <= 255 for c in v):
        return tuple(v)  # type: ignore[return-value]
    raise r._err(key, f"a colour name ({', '.join(NAMED_COLOURS)}), '#rrggbb' or [r, g, b] with 0-255", v)


def parse_lab_config(data: dict, source: str = "lab config", base_dir: Path | None = None) -> LabConfig:
    """Validate a parsed TOML document and build a :class:`LabConfig`. Relative calibration file
    names are taken from ``base_dir`` (the lab file's folder)."""
    root = _Reader(source, data, "")
    root.unknown(("arena", "zenoh", "cameras", "webcam", "robots", "services"))
    lab = LabConfig(path=source)
    lab.arena = _parse_arena(root.sub("arena"))
    lab.zenoh = _parse_zenoh(root.sub("zenoh"))
    lab.cameras = _parse_cameras(root, base_dir, lab.arena.size_m)
    if "webcam" in data:
        lab.webcam = _parse_webcam(root.sub("webcam"), base_dir)
    lab.robots = _parse_robots(root)
    for role, opts in root.sub("services").table.items():
        lab.services[role] = parse_service_options(role, opts, source)
    _check_heights(lab, source)
    return lab


def _check_heights(lab: LabConfig, source: str) -> None:
    """Every lens height the file gives is above every robot height it gives (the parallax
    correction divides by their difference), named by their keys."""
    tracker = lab.services.get("tracker", {})
    robots = [(f"robots[{i}].robot_height_cm", r.robot_height_cm) for i, r in enumerate(lab.robots)
              if r.robot_height_cm is not None]
    if tracker.get("robot_height_cm") is not None:
        robots.append(("services.tracker.robot_height_cm", tracker["robot_height_cm"]))
    lenses = [(f"cameras[{i}].camera_height_m", c.camera_height_m) for i, c in enumerate(lab.cameras)
              if c.camera_height_m is not None]
    if tracker.get("camera_height_m") is not None:
        lenses.append(("services.tracker.camera_height_m", tracker["camera_height_m"]))
    if not robots or not lenses:
        return
    rkey, rcm = max(robots, key=lambda kv: kv[1])
    for key, h in lenses:
        if not h > rcm / 100.0:
            raise ConfigError(f"{source}: {key}: expected a lens height above the robots ({rkey} = {rcm:g} cm), "
                              f"got {h:g} m")


def _parse_arena(a: _Reader) -> ArenaConfig:
    a.unknown(("name", "size_m"))
    return ArenaConfig(name=a.name("name") if a.has("name") else "arena",
                       size_m=a.pair("size_m", (1.83, 1.83), positive=True))


def _parse_zenoh(z: _Reader) -> ZenohSettings:
    """The ``[zenoh]`` table; without ``connect`` a client or peer connects to the ``config_file``'s
    connect endpoints if it has some, else to :data:`DEFAULT_ROUTER` (a router connects to nothing).

    Port 0: a ``connect`` endpoint with port 0 is refused (nothing can be dialled there); a
    ``listen`` endpoint with port 0 is kept: the OS gives a free port, which other peers learn
    through the router (gossip), as with Zenoh's own peer default ``tcp/[::]:0``; a client cannot
    be told it, so a router must listen on a fixed port."""
    z.unknown(("mode", "connect", "listen", "multicast_scouting", "lease_ms", "config_file", "tls", "user", "password"))
    tls = z.table.get("tls", {})
    if not isinstance(tls, dict) or not all(isinstance(v, (str, bool)) for v in tls.values()):
        raise z._err("tls", "a table of strings (file paths) and booleans", tls)
    mode = z.str("mode", "client", choices=MODES)
    connect = z.str_list("connect", _ENDPOINT_RE, "endpoints like 'tcp/192.0.2.1:7447'")
    for e in connect:
        if dial_port_zero(e):
            raise z._err("connect", "endpoints with the port a router listens on (port 0 cannot be dialled)", e)
    return ZenohSettings(
        mode=mode,
        connect=connect or ([] if mode == "router" else DefaultEndpoints([DEFAULT_ROUTER])),
        listen=z.str_list("listen", _ENDPOINT_RE, "endpoints like 'tcp/0.0.0.0:7447'"),
        multicast_scouting=z.bool("multicast_scouting", False),
        lease_ms=z.int("lease_ms", None, lo=LEASE_MS_RANGE[0], hi=LEASE_MS_RANGE[1]),
        config_file=z.str("config_file", None),
        tls=dict(tls),
        user=z.str("user", None),
        password=z.str("password", None),
    )


def _tables(root: _Reader, key: str) -> list[_Reader]:
    """Readers of the array of tables ``[[key]]`` (empty when absent)."""
    items = root.table.get(key, [])
    if not isinstance(items, list):
        raise root._err(key, f"an array of tables [[{key}]]", items)
    out = []
    for i, item in enumerate(items):
        if not isinstance(item, dict):
            raise root._err(f"{key}[{i}]", "a table", item)
        out.append(_Reader(root.source, item, f"{key}[{i}]"))
    return out


def _parse_cameras(root: _Reader, base_dir: Path | None,
                   size_m: tuple[float, float] = (1.83, 1.83)) -> list[CameraConfig]:
    cameras: list[CameraConfig] = []
    for r in _tables(root, "cameras"):
        r.unknown(("name", "width", "height", "source", "calibration", "points", "camera_height_m", "nadir_m"))
        name = r.name("name")
        if any(c.name == name for c in cameras):
            raise r._err("name", "a name not used by another camera", name)
        calib, calib_file = _calibration(r, base_dir)
        camera_h = r.table.get("camera_height_m")
        lo, hi = CAMERA_HEIGHT_RANGE_M
        if camera_h is not None and (isinstance(camera_h, bool) or not isinstance(camera_h, (int, float))
                                     or not _finite(camera_h) or not lo <= camera_h <= hi):
            raise r._err("camera_height_m", f"the lens height above the mats in [{lo:g}, {hi:g}] m", camera_h)
        camera_h = None if camera_h is None else float(camera_h)
        nadir = r.pair("nadir_m", None)
        if nadir is not None and nadir_distance_m(nadir, size_m) > NADIR_MAX_ARENAS * max(size_m):
            raise r._err("nadir_m", f"the arena point [x, y] m under the lens, within {NADIR_MAX_ARENAS:g} arena "
                         f"sides ({NADIR_MAX_ARENAS * max(size_m):g} m) of the arena [0, {size_m[0]:g}] x "
                         f"[0, {size_m[1]:g}] m", list(nadir))
        cameras.append(CameraConfig(name=name, width=r.int("width", 640, lo=1, hi=65535),
                                    height=r.int("height", 480, lo=1, hi=65535),
                                    source=_dialled(r, "source", r.str("source", None)), calibration=calib,
                                    calibration_file=calib_file,
                                    camera_height_m=camera_h, nadir_m=nadir))
    return cameras


def _dialled(r: _Reader, key: str, url: str | None) -> str | None:
    """``url`` (a source the service dials: ``tcp://HOST:PORT``, ``http://...``, ``socket://...``)
    unless it names port 0, which reaches nothing: then a ConfigError naming the key."""
    if url and "://" in url:
        from urllib.parse import urlsplit

        try:
            port = urlsplit(url).port
        except ValueError:  # a port out of range: the service that opens it says so
            port = None
        if port == 0:
            raise r._err(key, "a URL with the port its server listens on (port 0 cannot be dialled)", url)
    return url


def _parse_webcam(w: _Reader, base_dir: Path | None) -> WebcamConfig:
    w.unknown(("source", "fps", "calibration", "points", "detector", "width", "height"))
    src = w.table.get("source", "0")
    if isinstance(src, int) and not isinstance(src, bool):
        src = str(src)
    if not isinstance(src, str):
        raise w._err("source", "a device index, file path or URL", src)
    _dialled(w, "source", src)
    calib, calib_file = _calibration(w, base_dir)
    return WebcamConfig(source=src, fps=w.float("fps", 24.0, positive=True), calibration=calib,
                        calibration_file=calib_file,
                        detector=w.str("detector", "aruco", choices=("aruco", "hsv")))


def _parse_robots(root: _Reader) -> list[RobotConfig]:
    robots: list[RobotConfig] = []
    for r in _tables(root, "robots"):
        r.unknown(("name", "color", "marker_id", "serial_url", "sprocket_diameter_m", "track_width_m",
                   "counts_per_rev", "length_m", "width_m", "hsv_range", "robot_height_cm"))
        name = r.name("name")
        if name == "all":
            raise r._err("name", "any name but 'all' (reserved for commands to every robot)", name)
        if any(rb.name == name for rb in robots):
            raise r._err("name", "a name not used by another robot", name)
        marker = r.table.get("marker_id")
        if marker is not None and (isinstance(marker, bool) or not isinstance(marker, int)
                                   or not 0 <= marker < ARUCO_MARKER_IDS):
            raise r._err("marker_id", f"an integer in [0, {ARUCO_MARKER_IDS - 1}] (the ids of the ArUco dictionary "
                         f"DICT_4X4_50) for robot {name!r}", marker)
        if marker is not None and any(rb.marker_id == marker for rb in robots):
            raise r._err("marker_id", "a marker id not used by another robot", marker)
        hsv = _hsv_range(r)
        robots.append(RobotConfig(
            name=name, color_rgb=_colour(r, "color", (20, 20, 20)), marker_id=marker,
            serial_url=_dialled(r, "serial_url", r.str("serial_url", None)),
            sprocket_diameter_m=r.float("sprocket_diameter_m", 0.038, positive=True),
            track_width_m=r.float("track_width_m", 0.09, positive=True),
            counts_per_rev=r.int("counts_per_rev", 1807, lo=1),
            length_m=r.float("length_m", 0.10, positive=True), width_m=r.float("width_m", 0.10, positive=True),
            hsv_range=hsv, robot_height_cm=_robot_height(r)))
    return robots


def _robot_height(r: _Reader) -> float | None:
    """``robot_height_cm``: in [0, :data:`ROBOT_HEIGHT_MAX_CM`) cm (what the tracker accepts)."""
    v = r.table.get("robot_height_cm")
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not _finite(v) or not 0 <= v < ROBOT_HEIGHT_MAX_CM:
        raise r._err("robot_height_cm", f"a finite number in [0, {ROBOT_HEIGHT_MAX_CM:g}) cm (the height at which "
                     "the ceiling camera sees the robot; a Zumo: 3.2)", v)
    return float(v)


def _hsv_range(r: _Reader) -> tuple | None:
    hsv = r.table.get("hsv_range")
    if hsv is None:
        return None
    ok = (isinstance(hsv, list) and len(hsv) == 2 and all(
        isinstance(t, list) and len(t) == 3 and all(isinstance(x, int) and 0 <= x <= 255 for x in t) for t in hsv))
    if not ok:
        raise r._err("hsv_range", "[[h_lo, s_lo, v_lo], [h_hi, s_hi, v_hi]] with integers 0-255", hsv)
    return (tuple(hsv[0]), tuple(hsv[1]))


def load_lab_config(path: str | Path) -> LabConfig:
    """Read and validate the lab TOML file at ``path``; raise :class:`ConfigError` on any mistake."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{p}: lab config not found (see deploy/lab.example.toml for a template)") from None
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read the lab config: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{p}: not a UTF-8 text file") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None
    return parse_lab_config(data, source=str(p), base_dir=p.parent)

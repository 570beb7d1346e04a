"""Zenoh key expressions of the arena: builders, parsers and name validation.

Every key the system uses is built here, so a typo cannot create a key nobody listens to.

| key                              | from -> to                | payload                  |
|----------------------------------|---------------------------|--------------------------|
| ``arena/events/<camera>``        | edge -> tracker           | :class:`EventWindow`     |
| ``arena/robots/<id>``            | tracker -> anyone         | :class:`Track`           |
| ``arena/groundtruth/<robot>``    | groundtruth -> anyone     | :class:`GroundTruthPose` |
| ``arena/telemetry/<robot>``      | bridge -> anyone          | :class:`Telemetry`       |
| ``arena/cmd/<robot>/<verb>``     | anyone -> bridge (query)  | command / reply          |
| ``arena/status/<role>/<name>``   | every service             | :class:`Status`          |
| ``arena/alive/<role>/<name>``    | every service (liveliness)| —                        |
| ``arena/sim/truth/<robot>``      | simulator (scoring only)  | :class:`GroundTruthPose` |
"""

from __future__ import annotations

import re
from dataclasses import dataclass

ROOT = "arena"

#: Command verbs the robot bridge answers.
COMMAND_VERBS = ("mission", "stop", "estop", "clear", "led")

#: Roles that services announce in status and liveliness keys.
ROLES = ("edge", "tracker", "bridge", "groundtruth", "sim", "router", "scorer", "viewer", "recorder", "cli")

# A name is one key chunk: letters, digits, '-', '_', '.', 1-64 characters. This excludes every
# character with a meaning in Zenoh key expressions (``*``, ``$``, ``/``, ``#``, ``?``) and spaces.
_NAME_RE = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")


class InvalidKey(ValueError):
    """A name or key that is not valid in the arena key space."""


def validate_name(name: str, what: str = "name") -> str:
    """Return ``name`` if it is a valid single key chunk, else raise :class:`InvalidKey`.

    Valid names have 1-64 characters among letters, digits, ``-``, ``_`` and ``.`` (so none of the
    Zenoh wildcard or separator characters ``* $ / # ?``).
    """
    if not isinstance(name, str):
        raise InvalidKey(f"{what} must be a string, got {type(name).__name__}")
    if not name:
        raise InvalidKey(f"{what} is empty")
    if not _NAME_RE.match(name):
        bad = sorted({c for c in name if not re.match(r"[A-Za-z0-9_.-]", c)})
        detail = f"contains {''.join(bad)!r}" if bad else "is longer than 64 characters"
        raise InvalidKey(
            f"{what} {name!r} {detail}: use letters, digits, '-', '_' or '.' (no '*', '$', '/', '#', '?')"
        )
    if name in (".", ".."):
        raise InvalidKey(f"{what} {name!r} is not allowed")
    return name


def events_key(camera: str) -> str:
    """Key of the event windows of ``camera``."""
    return f"{ROOT}/events/{validate_name(camera, 'camera name')}"


def robot_key(track_id: str | int) -> str:
    """Key of one track: the robot's name when known, else the track number."""
    return f"{ROOT}/robots/{validate_name(str(track_id), 'robot id')}"


def groundtruth_key(robot: str) -> str:
    """Key of the ground-truth pose of ``robot``."""
    return f"{ROOT}/groundtruth/{validate_name(robot, 'robot name')}"


def sim_truth_key(robot: str) -> str:
    """Key of the simulator's exact pose of ``robot`` (for scoring only)."""
    return f"{ROOT}/sim/truth/{validate_name(robot, 'robot name')}"


def telemetry_key(robot: str) -> str:
    """Key of the telemetry samples of ``robot``."""
    return f"{ROOT}/telemetry/{validate_name(robot, 'robot name')}"


def cmd_key(robot: str, verb: str) -> str:
    """Key of the command queryable ``verb`` of ``robot`` (``robot`` may be ``all``)."""
    validate_name(robot, "robot name")
    if verb not in COMMAND_VERBS:
        raise InvalidKey(f"unknown command verb {verb!r}; expected one of {', '.join(COMMAND_VERBS)}")
    return f"{ROOT}/cmd/{robot}/{verb}"


def status_key(role: str, name: str) -> str:
    """Key of the once-a-second status of service ``name`` with ``role``."""
    return f"{ROOT}/status/{validate_name(role, 'role')}/{validate_name(name, 'service name')}"


def alive_key(role: str, name: str) -> str:
    """Liveliness token key of service ``name`` with ``role``."""
    return f"{ROOT}/alive/{validate_name(role, 'role')}/{validate_name(name, 'service name')}"


# Wildcard selectors users subscribe to.
ALL_ROBOTS = f"{ROOT}/robots/*"
ALL_EVENTS = f"{ROOT}/events/*"
ALL_STATUS = f"{ROOT}/status/**"
ALL_ALIVE = f"{ROOT}/alive/**"
ALL_TELEMETRY = f"{ROOT}/telemetry/*"
ALL_GROUNDTRUTH = f"{ROOT}/groundtruth/*"
EVERYTHING = f"{ROOT}/**"


@dataclass(frozen=True)
class ParsedKey:
    """A concrete arena key split into its kind and named parts."""

    kind: str  # events | robots | groundtruth | telemetry | cmd | status | alive | sim_truth
    parts: dict


_PATTERNS = {
    "events": ("camera",),
    "robots": ("id",),
    "groundtruth": ("robot",),
    "telemetry": ("robot",),
    "cmd": ("robot", "verb"),
    "status": ("role", "name"),
    "alive": ("role", "name"),
}


def parse_key(key: str) -> ParsedKey:
    """Split a concrete arena key into kind and parts; raise :class:`InvalidKey` if it is not one."""
    chunks = str(key).split("/")
    if len(chunks) < 3 or chunks[0] != ROOT:
        raise InvalidKey(f"{key!r} is not an arena key (expected '{ROOT}/<kind>/...')")
    kind, rest = chunks[1], chunks[2:]
    if kind == "sim" and len(rest) == 2 and rest[0] == "truth":
        return ParsedKey("sim_truth", {"robot": validate_name(rest[1], "robot name")})
    names = _PATTERNS.get(kind)
    if names is None:
        raise InvalidKey(f"{key!r}: unknown kind {kind!r}; expected one of {', '.join(_PATTERNS)}")
    if len(rest) != len(names):
        raise InvalidKey(f"{key!r}: '{kind}' keys have {len(names)} part(s) after '{ROOT}/{kind}/'")
    parts = {n: validate_name(v, n) for n, v in zip(names, rest)}
    if kind == "cmd" and parts["verb"] not in COMMAND_VERBS:
        raise InvalidKey(f"{key!r}: unknown command verb {parts['verb']!r}")
    return ParsedKey(kind, parts)

"""JSON Schemas (draft 2020-12) of the arena messages as they go on the wire, and ``arena schemas``.

:func:`json_schemas` derives one schema per message kind from :mod:`arena.messages` (the field
declarations, their ranges and choices, and the decoder's limits), so a lab can check or decode
the traffic from any language without this package. The published copies live in
``docs/schemas/<kind>.json``; ``arena schemas --out docs/schemas`` (or ``python -m arena.schemas``)
rewrites them and ``--check`` fails when they are stale (a test does the same).

A schema describes the msgpack map exactly as :meth:`arena.messages.Message.encode` writes it:
``v`` and ``kind`` first, then every field in declaration order (an arena sender writes all of
them, ``nil`` for an unset optional one). msgpack has the same shape as JSON except for byte
strings: a ``bytes`` field (``EventWindow.data``) is a msgpack **bin** (bin 8/16/32), never a str;
to validate a decoded map with a JSON Schema validator present bin values as base64 strings
(:func:`json_view` does), as the schemas say (``contentEncoding: base64``).

What JSON Schema cannot say and arena decoders also check: numbers are finite (no NaN or
infinity); an ``integer`` field must be a msgpack int (``1.0`` is refused); the cross-field rules
given in a schema's ``description`` (``EventWindow.t_end_us >= t_start_us``).
"""

from __future__ import annotations

import argparse
import base64
import json
import sys
from dataclasses import MISSING, fields
from pathlib import Path
from typing import Any

from arena.codec_names import CODECS
from arena.messages import DEFAULT_LIMITS, MESSAGE_TYPES, Message

__all__ = ["DIALECT", "FIELD_DOCS", "json_schema", "json_schemas", "schema_files", "json_view", "register"]

DIALECT = "https://json-schema.org/draft/2020-12/schema"
_INT64_MAX = 2**63 - 1  # the decoders refuse |n| > 2^63 - 1 (so neither -2^63 nor uint64 beyond it)

_CODEC_DOC = ("event-window codec of ``data``: " + ", ".join(CODECS)
              + " (docs/codec.md); a receiver refuses a codec it does not know")

#: What each field means, with its unit and frame. Every field of every message has an entry
#: (tests/arena/test_schemas.py checks that none is missing or stale).
FIELD_DOCS: dict[str, dict[str, str]] = {
    "EventWindow": {
        "camera": "camera name (the <camera> of the key arena/events/<camera>)",
        "seq": "window number of this camera, from 0, +1 per window published (a gap is a lost window)",
        "t_start_us": "start of the window [t_start_us, t_end_us), sensor clock, µs",
        "t_end_us": "end of the window (exclusive), sensor clock, µs; never before t_start_us",
        "width": "sensor width, px",
        "height": "sensor height, px",
        "count": f"number of events coded in data (a receiver refuses more than {DEFAULT_LIMITS.max_window_events})",
        "codec": _CODEC_DOC,
        "data": "the window's events coded with `codec`",
        "dropped": "windows dropped at the edge so far (total since it started)",
        "filtered": "events removed by the edge's noise filters from this window",
        "publish_ns": "host wall clock when the edge published this window, ns since the Unix epoch (0: unknown)",
        "sensor_to_host_ns": "host capture time minus sensor time, ns: the host time of sensor time t_us is "
                             "t_us * 1000 + this (the edge's sliding-minimum estimate over 10 s; absent or null "
                             "when unknown, e.g. a file replayed faster than real time)",
    },
    "Track": {
        "track_id": "tracker's track number (stable while the track lives)",
        "robot": "robot name when the track is identified, else null",
        "camera": "camera whose window produced this update",
        "stamp_us": "time of the pose, sensor clock, µs",
        "x": "position, arena frame, m",
        "y": "position, arena frame, m",
        "yaw": "heading, rad, counter-clockwise from the arena +x axis; null when unknown",
        "vx": "velocity along arena x, m/s; null when unknown",
        "vy": "velocity along arena y, m/s; null when unknown",
        "u_px": "position in the sensor, column, px; null when unknown",
        "v_px": "position in the sensor, row, px; null when unknown",
        "state": "track state: tentative (not yet confirmed), confirmed, coasting (predicted, not seen)",
        "n_events": "events of the robot's cluster in this update",
        "window_end_us": "end of the event window this update came from, sensor clock, µs",
        "edge_publish_ns": "host wall clock when the edge published that window, ns since the Unix epoch",
        "tracker_publish_ns": "host wall clock when the tracker published this message, ns since the Unix epoch",
        "host_ns": "host capture time of stamp_us, ns since the Unix epoch (stamp_us * 1000 + the window's "
                   "sensor_to_host_ns; null when the edge did not know it)",
    },
    "Telemetry": {
        "robot": "robot name",
        "seq": "sample number from the robot, from 0",
        "robot_time_us": "the robot's clock when sampled, µs",
        "host_time_ns": "host wall clock when the bridge received the sample, ns since the Unix epoch",
        "enc_left": "left wheel encoder, counts (cumulative)",
        "enc_right": "right wheel encoder, counts (cumulative)",
        "speed_left": "left wheel speed, m/s",
        "speed_right": "right wheel speed, m/s",
        "accel": "acceleration [x, y, z], body frame, m/s²",
        "gyro": "angular rate [x, y, z], body frame, rad/s",
        "mag": "magnetic field [x, y, z], body frame, µT",
        "battery_mv": "battery voltage, mV",
        "power_left": "left motor power command, -400..400 (full reverse..full forward)",
        "power_right": "right motor power command, -400..400",
        "mission": "mission running (circle, square, ...), null when idle",
        "phase": "phase of the mission, null when idle",
    },
    "GroundTruthPose": {
        "robot": "robot name",
        "stamp_us": "capture time, µs: host clock for a webcam, sensor clock for the simulator",
        "x": "position, arena frame, m",
        "y": "position, arena frame, m",
        "yaw": "heading, rad, counter-clockwise from the arena +x axis; null when unknown",
        "u_px": "position in the event camera's sensor, column, px; null when unknown",
        "v_px": "position in the event camera's sensor, row, px; null when unknown",
        "detector": "what measured it: aruco, hsv or sim",
    },
    "MissionCommand": {
        "mission": "mission name (circle, square, ...)",
        "params": "the mission's own parameters, e.g. radius_m, side_m, laps, direction",
        "power": "motor power fraction (0.5 = 50 %); null: the mission's default",
        "speed_mps": "target speed, m/s; null: use power",
        "control": "paper (encoder PID only) or closed (also follows the robot's own track)",
        "start_ns": "start at this host wall-clock time, ns since the Unix epoch (robots start together); null: now",
        "operator": "who sent it (logged), null when anonymous",
    },
    "Command": {
        "verb": "the command: stop, estop, clear or led (also the last part of its key)",
        "params": "the command's parameters",
        "operator": "who sent it (logged), null when anonymous",
    },
    "CommandReply": {
        "ok": "true when the command was accepted",
        "robot": "robot that answered",
        "verb": "command answered",
        "error": "why it was refused (one line), null when ok",
        "detail": "extra facts about the answer",
    },
    "Status": {
        "role": "service role (edge, tracker, bridge, groundtruth, ...)",
        "name": "service name (the <name> of arena/status/<role>/<name>)",
        "host": "host name the service runs on",
        "pid": "process id",
        "time_ns": "host wall clock when sent, ns since the Unix epoch",
        "uptime_s": "time since the service started, s",
        "state": "service state (running, ...)",
        "counters": "monotonically increasing totals since start",
        "rates": "per-second rates over the last period",
        "gauges": "last values (latency_ms, queue depth, ...)",
        "errors": "errors so far",
        "last_error": "the last error's text, null when none",
    },
}

_WIRE_DOC = (
    "A msgpack map (the same shape as JSON): keys are msgpack str; `v` and `kind` first, then the "
    "fields in the order listed (an arena sender writes every field, nil for an unset optional one; "
    "a decoder must not depend on the order). Integers are msgpack ints, numbers float 64 (an int "
    "is accepted), strings UTF-8 str; a byte string is a msgpack bin (bin 8/16/32) and appears here as "
    "a base64 string (contentEncoding base64), the usual msgpack-to-JSON mapping. Unknown extra keys "
    "are ignored (a newer sender that only adds fields interoperates); a `v` newer than this schema's "
    "is refused. Numbers must be finite. Limits: the whole message at most "
    f"{DEFAULT_LIMITS.max_payload_bytes} bytes, any array at most 4096 items, any map at most "
    f"{max(DEFAULT_LIMITS.max_map, 64)} entries."
)


def _scalar_value(rows: bool = False) -> dict:
    """A value inside a ``map`` field: a scalar, or a flat list of at most 64 scalars; with
    ``rows`` (a mission's params) also a list of rows of numbers (waypoints)."""
    from arena.messages import MAX_PARAM_ROWS, MAX_ROW_LEN

    scalar = {"type": ["null", "boolean", "integer", "number", "string"]}
    options = [scalar, {"type": "array", "maxItems": 64, "items": scalar}]
    if rows:
        options.append({"type": "array", "maxItems": MAX_PARAM_ROWS,
                        "items": {"type": "array", "maxItems": MAX_ROW_LEN, "items": {"type": "number"}}})
    return {"anyOf": options}


def _field_schema(meta: dict, doc: str) -> dict:
    kind = meta["kind"]
    out: dict[str, Any] = {"description": doc}
    if kind == "int":
        out["type"] = "integer"
        out["minimum"] = meta["lo"] if meta["lo"] is not None else -_INT64_MAX
        out["maximum"] = meta["hi"] if meta["hi"] is not None else _INT64_MAX
    elif kind == "float":
        out["type"] = "number"
        if meta["lo"] is not None:
            out["minimum"] = meta["lo"]
        if meta["hi"] is not None:
            out["maximum"] = meta["hi"]
    elif kind == "bool":
        out["type"] = "boolean"
    elif kind == "str":
        out["type"] = "string"
        out["maxLength"] = DEFAULT_LIMITS.max_str
        if meta["choices"]:
            out["enum"] = list(meta["choices"])
    elif kind == "bytes":
        out["description"] = (f"{doc}. On the wire a msgpack bin (bin 8/16/32) of at most "
                              f"{DEFAULT_LIMITS.max_window_bytes} bytes, never a str; shown here as base64")
        out["type"] = "string"
        out["contentEncoding"] = "base64"
        out["contentMediaType"] = "application/octet-stream"
    elif kind == "vec":
        out["type"] = "array"
        out["items"] = {"type": "number"}
        out["minItems"] = out["maxItems"] = meta["length"]
    elif kind == "map":
        out["type"] = "object"
        out["maxProperties"] = DEFAULT_LIMITS.max_map
        out["propertyNames"] = {"maxLength": 128}
        out["additionalProperties"] = _scalar_value(bool(meta.get("rows")))
    else:  # pragma: no cover - a new field kind in arena.messages must be described here
        raise ValueError(f"arena.schemas: no JSON Schema for field kind {kind!r}")
    if meta["optional"]:
        out["type"] = [out["type"], "null"]
        if "enum" in out:
            out["enum"].append(None)
    return out


def _default(value: Any) -> Any:
    return list(value) if isinstance(value, tuple) else value


def json_schema(cls: type[Message]) -> dict:
    """The JSON Schema of message class ``cls`` as its msgpack map goes on the wire."""
    docs = FIELD_DOCS.get(cls.__name__, {})
    props: dict[str, Any] = {
        "v": {"description": f"schema version; this schema is version {cls.VERSION}", "type": "integer",
              "minimum": 1, "maximum": cls.VERSION},
        "kind": {"description": "message kind", "const": cls.KIND},
    }
    required = ["v", "kind"]
    for f in fields(cls):
        p = _field_schema(dict(f.metadata), docs.get(f.name, f.name))
        if f.default is not MISSING:
            p["default"] = _default(f.default)
        elif f.default_factory is not MISSING:
            p["default"] = _default(f.default_factory())
        else:
            required.append(f.name)
        props[f.name] = p
    doc = " ".join((cls.__doc__ or "").split()).replace("``", "`")
    return {
        "$schema": DIALECT,
        "$id": f"urn:arena:message:{cls.KIND}:v{cls.VERSION}",
        "title": f"arena.{cls.__name__}",
        "description": f"{doc} {_WIRE_DOC}",
        "type": "object",
        "properties": props,
        "required": required,
        "additionalProperties": True,
    }


def json_schemas() -> dict[str, dict]:
    """Every message kind's JSON Schema, keyed by ``kind`` (``track``, ``event_window``, ...)."""
    return {kind: json_schema(cls) for kind, cls in MESSAGE_TYPES.items()}


def schema_files() -> dict[str, str]:
    """The published files: ``<kind>.json`` -> its text (UTF-8, 2-space indent, final newline)."""
    return {f"{kind}.json": json.dumps(s, indent=2, ensure_ascii=False) + "\n" for kind, s in json_schemas().items()}


def json_view(value: Any) -> Any:
    """A decoded msgpack value with every bin (``bytes``) as a base64 string, nested maps and
    arrays included: what the schemas' ``contentEncoding: base64`` fields expect."""
    if isinstance(value, (bytes, bytearray, memoryview)):
        return base64.b64encode(bytes(value)).decode("ascii")
    if isinstance(value, dict):
        return {k: json_view(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_view(v) for v in value]
    return value


# --------------------------------------------------------------------------------------------
# arena schemas
# --------------------------------------------------------------------------------------------
def _add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", metavar="DIR", default="docs/schemas",
                   help="folder for the <kind>.json files (default docs/schemas; created)")
    p.add_argument("--check", action="store_true",
                   help="write nothing; exit 1 when a file in DIR differs from what would be written")


_DESCRIPTION = ("Write the JSON Schemas (draft 2020-12) of every arena message, one <kind>.json per\n"
                "message kind, describing the msgpack map as it goes on the wire.")
_EPILOG = ("Examples:\n"
           "  arena schemas                        # rewrite docs/schemas/*.json\n"
           "  arena schemas --out /tmp/s --check   # exit 1 if those files are stale\n"
           "Exit status: 0; 1 when --check finds a stale or missing file; 2 when DIR cannot be written.")


def register(sub) -> None:
    """Add ``arena schemas`` to the ``arena`` command."""
    p = sub.add_parser("schemas", help="write the JSON Schemas of the arena messages",
                       formatter_class=argparse.RawDescriptionHelpFormatter, description=_DESCRIPTION,
                       epilog=_EPILOG)
    _add_arguments(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """``arena schemas``; returns the exit code."""
    out = Path(args.out)
    files = schema_files()
    if args.check:
        stale = []
        for name, text in files.items():
            path = out / name
            try:
                if path.read_text(encoding="utf-8") != text:
                    stale.append(f"{path} differs")
            except OSError:
                stale.append(f"{path} is missing")
        extra = sorted(p.name for p in out.glob("*.json") if p.name not in files) if out.is_dir() else []
        stale += [f"{out / n} is no message kind's schema (remove it)" for n in extra]
        if stale:
            print(f"arena schemas: {'; '.join(stale)}; run `arena schemas --out {out}`", file=sys.stderr)
            return 1
        print(f"{len(files)} schemas in {out} are up to date")
        return 0
    try:
        out.mkdir(parents=True, exist_ok=True)
        for name, text in files.items():
            (out / name).write_text(text, encoding="utf-8")
    except OSError as exc:
        print(f"arena schemas: cannot write {out}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    print(f"wrote {len(files)} schemas to {out}: {', '.join(files)}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m arena.schemas``: the same as ``arena schemas``."""
    p = argparse.ArgumentParser(prog="python -m arena.schemas", description=_DESCRIPTION, epilog=_EPILOG,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_arguments(p)
    return run(p.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())

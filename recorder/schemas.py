"""JSON schemas (draft 2020-12) of the arena messages, derived from :mod:`arena.messages`.

They are stored in the MCAP file with each ``json`` channel, so Foxglove Studio and the MCAP CLI
can show field names and types. Units are in each field's ``description`` where the schema
declares them (metres, radians, µs, ns).
"""

from __future__ import annotations

import json
from dataclasses import MISSING, fields

from arena.messages import MESSAGE_TYPES, Message

_JSON_TYPES = {"int": "integer", "float": "number", "bool": "boolean", "str": "string", "map": "object"}


def _field_schema(meta: dict) -> dict:
    kind = meta["kind"]
    if kind == "vec":
        out: dict = {"type": "array", "items": {"type": "number"},
                     "minItems": meta["length"], "maxItems": meta["length"]}
    elif kind == "bytes":
        out = {"type": "string", "contentEncoding": "base64"}
    else:
        out = {"type": _JSON_TYPES[kind]}
    if meta.get("choices"):
        out["enum"] = list(meta["choices"])
    if meta.get("lo") is not None:
        out["minimum"] = meta["lo"]
    if meta.get("hi") is not None:
        out["maximum"] = meta["hi"]
    if meta.get("optional"):
        out = {"anyOf": [out, {"type": "null"}]}
    return out


def json_schema(cls: type[Message]) -> dict:
    """The JSON schema of message class ``cls`` (with the reserved ``v`` and ``kind`` fields)."""
    props = {"v": {"type": "integer", "minimum": 1}, "kind": {"const": cls.KIND}}
    required = ["v", "kind"]
    for f in fields(cls):
        props[f.name] = _field_schema(dict(f.metadata))
        if f.default is MISSING and f.default_factory is MISSING:
            required.append(f.name)
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": f"arena.{cls.__name__}",
        "description": (cls.__doc__ or "").strip().splitlines()[0],
        "type": "object",
        "properties": props,
        "required": required,
    }


def schema_name(kind: str) -> str:
    """MCAP schema name of message ``kind`` (e.g. ``track`` -> ``arena.Track``)."""
    return f"arena.{MESSAGE_TYPES[kind].__name__}"


def schema_bytes(kind: str) -> bytes:
    """The JSON schema of message ``kind`` as UTF-8 bytes (for an MCAP schema record)."""
    return json.dumps(json_schema(MESSAGE_TYPES[kind]), indent=1).encode()

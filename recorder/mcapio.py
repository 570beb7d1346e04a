"""The MCAP layout of a recorded run: writing and reading, without Zenoh.

Layout (profile ``arena``; library ``arena-recorder``):

* one channel per Zenoh key (the MCAP topic is the key, e.g. ``arena/robots/zumo1``);
* event windows (``kind`` = ``event_window``): message encoding ``msgpack``, schema
  ``arena.EventWindow`` (self-describing, empty schema data): the payload bytes exactly as published;
* every other arena message (commands and replies too, if a sender publishes them; the robot
  commands themselves are Zenoh queries, which a subscriber does not see): message encoding ``json`` with a JSON schema per kind
  (``arena.Track``, ``arena.Telemetry``, ...), so Foxglove Studio shows the fields;
* log time = receive time (host wall clock, ns); publish time = the sender's own time when the
  message carries one (``publish_ns``, ``tracker_publish_ns``, ``host_time_ns``, ``time_ns``),
  else the receive time; sequence = per-channel message number from 0;
* **derived Foxglove channels** (:mod:`recorder.foxglove_views`, topics ``foxglove/...``): Foxglove's
  well-known schemas (``foxglove.PoseInFrame``, ...) as protobuf, each channel with the metadata
  ``derived_from`` = ``arena``. They are views of the arena channels, not samples anybody
  published: :func:`read_run` (and so ``arena replay``) skips them.

**Lossless replay.** A JSON record is written only when converting its JSON back to msgpack gives
the published bytes again (``msgpack.packb(json.loads(text)) == payload``, which holds for every
message built by :mod:`arena.messages`). Any other payload (a sender with another msgpack
encoder, a non-finite float, bytes that are not an arena message) goes on a second channel of the
same topic with encoding ``msgpack`` and schema ``arena.Raw`` holding the payload as received. So
:func:`read_run` always returns the published bytes, byte for byte.
"""

from __future__ import annotations

import json
import logging
import os
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import msgpack
import zenoh
from mcap.exceptions import EndOfFile
from mcap.reader import NonSeekingReader
from mcap.writer import CompressionType, Writer

from arena.messages import MESSAGE_TYPES
from recorder.schemas import schema_bytes, schema_name

log = logging.getLogger("arena.recorder")

PROFILE = "arena"
LIBRARY = "arena-recorder"
EVENT_SCHEMA = "arena.EventWindow"
RAW_SCHEMA = "arena.Raw"
#: metadata key of the channels derived from the arena ones (skipped by :func:`read_run`)
DERIVED_KEY = "derived_from"

# Fields that carry the sender's own wall-clock time (ns) per message kind.
_PUBLISH_FIELDS = {"event_window": "publish_ns", "track": "tracker_publish_ns",
                   "telemetry": "host_time_ns", "status": "time_ns"}


class RunFileError(ValueError):
    """A path that is not a readable recorded run; the message says what was expected."""


@dataclass(frozen=True)
class RecordedMessage:
    """One recorded sample: its Zenoh key, the payload bytes as published, and times (ns)."""

    key: str
    payload: bytes
    log_time_ns: int
    publish_time_ns: int


def _classify(payload: bytes) -> tuple[str, str, bytes, dict | None]:
    """(kind, encoding, data, decoded map) to store for ``payload``; kind '' means a raw record."""
    try:
        d = msgpack.unpackb(payload, raw=False, strict_map_key=True)
    except Exception:  # noqa: BLE001 - not msgpack at all
        return "", "msgpack", payload, None
    if not isinstance(d, dict):
        return "", "msgpack", payload, None
    kind = d.get("kind")
    if kind == "event_window":
        return kind, "msgpack", payload, d
    # JSON keeps every type msgpack decodes to here (str keys, int vs float, float64 exactly), so
    # when re-packing the decoded map gives the payload back, so does re-packing the JSON.
    if isinstance(kind, str) and kind in MESSAGE_TYPES and msgpack.packb(d, use_bin_type=True) == payload:
        try:
            return kind, "json", json.dumps(d, allow_nan=False, separators=(",", ":")).encode(), d
        except (TypeError, ValueError):  # bytes inside, NaN or inf
            pass
    return "", "msgpack", payload, d


def publish_time_ns(payload_dict: dict | None, log_time_ns: int) -> int:
    """The sender's publish time (ns) in the message if it has one, else ``log_time_ns``."""
    if isinstance(payload_dict, dict):
        t = payload_dict.get(_PUBLISH_FIELDS.get(payload_dict.get("kind"), ""))
        if isinstance(t, int) and not isinstance(t, bool) and t > 0:
            return t
    return log_time_ns


class RunWriter:
    """Write received arena samples into an MCAP file; a context manager (finishes the file).

    ``add(key, payload, log_time_ns)`` is not thread-safe: call it from one writer thread.
    """

    def __init__(self, path: str | os.PathLike, chunk_size: int = 1 << 20,
                 metadata: dict[str, str] | None = None):
        self.path = Path(path)
        self._file = open(self.path, "wb")
        self._writer = Writer(self._file, chunk_size=chunk_size, compression=CompressionType.ZSTD)
        self._writer.start(profile=PROFILE, library=LIBRARY)
        if metadata:
            self._writer.add_metadata("arena.run", {str(k): str(v) for k, v in metadata.items()})
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, str], int] = {}
        self._seq: dict[int, int] = {}
        self.messages = 0   # arena samples
        self.bytes = 0
        self.derived = 0    # derived (Foxglove) messages
        self._closed = False

    def _schema_id(self, kind: str) -> int:
        sid = self._schemas.get(kind)
        if sid is None:
            if kind == "event_window":
                sid = self._writer.register_schema(EVENT_SCHEMA, "", b"")
            elif kind:
                sid = self._writer.register_schema(schema_name(kind), "jsonschema", schema_bytes(kind))
            else:
                sid = self._writer.register_schema(RAW_SCHEMA, "", b"")
            self._schemas[kind] = sid
        return sid

    def add(self, key: str, payload: bytes, log_time_ns: int) -> None:
        """Record one sample received on ``key`` at ``log_time_ns`` (host wall clock, ns)."""
        kind, encoding, data, decoded = _classify(payload)
        ch = self._channels.get((key, kind))
        if ch is None:
            ch = self._writer.register_channel(key, encoding, self._schema_id(kind))
            self._channels[(key, kind)] = ch
        seq = self._seq.get(ch, 0)
        self._seq[ch] = seq + 1
        pub = publish_time_ns(decoded, log_time_ns)
        self._writer.add_message(ch, log_time=log_time_ns, data=data, publish_time=pub, sequence=seq)
        self.messages += 1
        self.bytes += len(payload)

    def add_derived(self, topic: str, schema_name: str, schema_data: bytes, data: bytes, log_time_ns: int,
                    publish_time_ns: int, schema_encoding: str = "protobuf",
                    message_encoding: str = "protobuf") -> None:
        """Record one message derived from the arena samples (a Foxglove view) on its own channel
        ``topic``; ``schema_data`` is used the first time ``schema_name`` is seen."""
        sid = self._schemas.get("\0" + schema_name)
        if sid is None:
            sid = self._schemas["\0" + schema_name] = self._writer.register_schema(schema_name, schema_encoding,
                                                                                   schema_data)
        ch = self._channels.get((topic, "\0" + schema_name))
        if ch is None:
            ch = self._channels[(topic, "\0" + schema_name)] = self._writer.register_channel(
                topic, message_encoding, sid, metadata={DERIVED_KEY: "arena"})
        seq = self._seq.get(ch, 0)
        self._seq[ch] = seq + 1
        self._writer.add_message(ch, log_time=log_time_ns, data=data, publish_time=publish_time_ns, sequence=seq)
        self.derived += 1

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """A metadata record ``name`` (str -> str), e.g. the recording's own summary before :meth:`close`."""
        self._writer.add_metadata(name, {str(k): str(v) for k, v in data.items()})

    def close(self) -> None:
        """Write the summary and indexes and close the file (idempotent)."""
        if self._closed:
            return
        self._closed = True
        try:
            self._writer.finish()
        finally:
            self._file.close()

    def __enter__(self) -> "RunWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def find_run_file(path: str | os.PathLike) -> Path:
    """The MCAP file of a run: ``path`` itself, or the single ``*.mcap`` inside a run folder."""
    p = Path(path)
    if p.is_dir():
        found = sorted(p.glob("*.mcap"))
        if not found:
            raise RunFileError(f"{p}: no .mcap file in this folder (record one with `arena record`)")
        if len(found) > 1:
            raise RunFileError(f"{p}: several .mcap files ({', '.join(f.name for f in found)}); name one")
        return found[0]
    if not p.exists():
        raise RunFileError(f"{p}: no such file or folder")
    return p


def _matcher(keys: Iterable[str] | None):
    if not keys:
        return lambda key: True
    try:
        exprs = [zenoh.KeyExpr(k) for k in keys]
    except Exception as exc:  # zenoh.ZError for an invalid expression
        raise RunFileError(f"invalid key expression in {list(keys)}: {exc}") from None

    seen: dict[str, bool] = {}  # one answer per topic

    def match(key: str) -> bool:
        ok = seen.get(key)
        if ok is None:
            k = zenoh.KeyExpr(key)
            ok = seen[key] = any(k.intersects(e) for e in exprs)
        return ok

    return match


def read_run(path: str | os.PathLike, keys: Iterable[str] | None = None) -> Iterator[RecordedMessage]:
    """Yield the recorded samples of a run in the order they were received (the file's order, which
    is log-time order unless the host clock stepped back), with their payloads as published.

    ``path``: an ``.mcap`` file or a run folder holding one; ``keys``: Zenoh key expressions to keep
    (default: all). Derived channels (the Foxglove views, metadata ``derived_from``) are skipped:
    only what was published on Zenoh comes back. Raises :class:`RunFileError` for a missing or unreadable file.
    """
    f = find_run_file(path)
    match = _matcher(keys)
    size = f.stat().st_size
    with open(f, "rb") as stream:
        # streamed record by record, so a recording cut short (recorder killed, disk full) is
        # still read up to its last complete chunk
        try:
            for _schema, channel, message in NonSeekingReader(stream).iter_messages(log_time_order=False):
                if DERIVED_KEY in channel.metadata or not match(channel.topic):
                    continue
                data = message.data
                if channel.message_encoding == "json":
                    data = msgpack.packb(json.loads(data), use_bin_type=True)
                elif channel.message_encoding != "msgpack":
                    raise RunFileError(f"{f}: channel {channel.topic!r} has encoding "
                                       f"{channel.message_encoding!r}, not one `arena record` writes")
                yield RecordedMessage(channel.topic, bytes(data), message.log_time, message.publish_time)
        except RunFileError:
            raise
        except (EndOfFile, struct.error) as exc:  # struct.error: a record header cut by the end of file
            if isinstance(exc, struct.error) and stream.tell() < size:
                raise RunFileError(f"{f}: corrupt MCAP record before byte {stream.tell()}") from None
            log.warning("%s ends early (the recording was cut short): read up to its last complete chunk", f)
        except Exception as exc:  # mcap raises several error types for corrupt files
            raise RunFileError(f"{f}: not a readable MCAP file ({type(exc).__name__}: {exc})") from None

"""Zenoh side of the viewer: subscriptions that feed a :class:`~viewer.state.ViewerState`."""

from __future__ import annotations

import logging

import zenoh

from arena import keys
from arena.messages import EventWindow, GroundTruthPose, MessageError, Status, Telemetry, Track, decode
from viewer.state import ViewerState

log = logging.getLogger("arena.viewer")


#: the message type each kind of key carries (see :mod:`arena.keys`)
_KIND_TYPES = {"events": EventWindow, "robots": Track, "groundtruth": GroundTruthPose, "telemetry": Telemetry,
               "status": Status}


def _log_rejected(n: int, what: str) -> None:
    # the first one and every 1000th at warning level: a misbehaving publisher must not flood the log
    level = logging.WARNING if n == 1 or n % 1000 == 0 else logging.DEBUG
    log.log(level, "%s (%d so far)", what, n)


def handle_sample(state: ViewerState, key: str, payload: bytes) -> None:
    """Feed one sample received on ``key`` to ``state``. A key that is not an arena key of the
    kinds the viewer shows (:func:`arena.keys.parse_key`), a payload that is no valid message,
    or a message of another type than its key carries, is counted and logged, never raised; so
    is, as a last resort, anything else a sample makes the state raise (counted in ``bad``,
    logged with the exception's type and message)."""
    try:
        kind = keys.parse_key(key).kind
        if kind not in _KIND_TYPES:
            raise keys.InvalidKey(f"{key!r}: the viewer does not subscribe to '{kind}' keys")
    except keys.InvalidKey as exc:
        _log_rejected(state.on_bad_key(), f"sample on a malformed key ignored: {exc}")
        return
    try:
        msg = decode(payload)
    except MessageError as exc:
        log.debug("%s: %s", key, exc)
        state.on_bad()
        return
    if not isinstance(msg, _KIND_TYPES[kind]):
        _log_rejected(state.on_bad(), f"{key}: a {type(msg).__name__} message on a '{kind}' key ignored")
        return
    try:
        if isinstance(msg, EventWindow):
            state.on_window(msg)
        elif isinstance(msg, Track):
            state.on_track(key, msg)
        elif isinstance(msg, GroundTruthPose):
            state.on_groundtruth(msg)
        elif isinstance(msg, Telemetry):
            state.on_telemetry(msg)
        elif isinstance(msg, Status):
            state.on_status(msg)
    except Exception as exc:   # last resort: a sample the state cannot take must not stop the viewer
        _log_rejected(state.on_bad(), f"{key}: sample not shown ({type(exc).__name__}: {str(exc)[:300]})")
        log.debug("%s: sample not shown", key, exc_info=True)


def handle_alive(state: ViewerState, key: str, alive: bool) -> None:
    """A liveliness token ``arena/alive/<role>/<name>`` appeared (``alive``) or went; a token on
    any other key is counted and logged."""
    try:
        parsed = keys.parse_key(key)
        if parsed.kind != "alive":
            raise keys.InvalidKey(f"{key!r} is not a liveliness key 'arena/alive/<role>/<name>'")
    except keys.InvalidKey as exc:
        _log_rejected(state.on_bad_key(), f"liveliness token on a malformed key ignored: {exc}")
        return
    try:
        state.on_alive(parsed.parts["role"], parsed.parts["name"], alive)
    except Exception as exc:   # last resort, as in handle_sample
        _log_rejected(state.on_bad(), f"liveliness token {key} not shown ({type(exc).__name__}: {str(exc)[:300]})")


def subscribe(session: zenoh.Session, state: ViewerState, camera: str | None = None) -> list:
    """Declare the viewer's subscribers on ``session`` (events of ``camera`` or of every camera,
    tracks, ground truth, telemetry, status, liveliness); returns them (undeclare when done)."""

    def on_sample(sample: zenoh.Sample) -> None:
        handle_sample(state, str(sample.key_expr), sample.payload.to_bytes())

    def on_alive(sample: zenoh.Sample) -> None:
        handle_alive(state, str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)

    events = keys.events_key(camera) if camera else keys.ALL_EVENTS
    subs = [session.declare_subscriber(k, on_sample) for k in
            (events, keys.ALL_ROBOTS, keys.ALL_GROUNDTRUTH, keys.ALL_TELEMETRY, keys.ALL_STATUS)]
    subs.append(session.liveliness().declare_subscriber(keys.ALL_ALIVE, on_alive, history=True))
    return subs

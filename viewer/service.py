"""Zenoh side of the viewer: subscriptions that feed a :class:`~viewer.state.ViewerState`."""

from __future__ import annotations

import logging

import zenoh

from arena import keys
from arena.messages import EventWindow, GroundTruthPose, MessageError, Status, Telemetry, Track, decode
from viewer.state import ViewerState

log = logging.getLogger("arena.viewer")


def subscribe(session: zenoh.Session, state: ViewerState, camera: str | None = None) -> list:
    """Declare the viewer's subscribers on ``session`` (events of ``camera`` or of every camera,
    tracks, ground truth, telemetry, status, liveliness); returns them (undeclare when done)."""

    def on_sample(sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            msg = decode(sample.payload.to_bytes())
        except MessageError as exc:
            log.debug("%s: %s", key, exc)
            state.on_bad()
            return
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

    def on_alive(sample: zenoh.Sample) -> None:
        parts = str(sample.key_expr).split("/")
        if len(parts) == 4:
            state.on_alive(parts[2], parts[3], sample.kind == zenoh.SampleKind.PUT)

    events = keys.events_key(camera) if camera else keys.ALL_EVENTS
    subs = [session.declare_subscriber(k, on_sample) for k in
            (events, keys.ALL_ROBOTS, keys.ALL_GROUNDTRUTH, keys.ALL_TELEMETRY, keys.ALL_STATUS)]
    subs.append(session.liveliness().declare_subscriber(keys.ALL_ALIVE, on_alive, history=True))
    return subs

import math

import msgpack
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from arena import messages as m
from arena.messages import MessageError

EXAMPLES = [
    m.EventWindow(camera="cam0", seq=5, t_start_us=100, t_end_us=10_100, width=640, height=480, count=3,
                  codec="planes-zstd/1", data=b"\x00\x01\x02", dropped=1, filtered=7, publish_ns=123),
    m.Track(track_id=3, robot="zumo1", camera="cam0", stamp_us=10_000, x=0.5, y=1.2, yaw=-1.5, vx=0.3,
            vy=-0.1, u_px=320.5, v_px=200.25, state="coasting", n_events=812, window_end_us=10_000,
            edge_publish_ns=1, tracker_publish_ns=2),
    m.Track(track_id=0),
    m.Telemetry(robot="zumo1", seq=9, robot_time_us=1000, host_time_ns=5, enc_left=-300, enc_right=301,
                speed_left=0.2, speed_right=0.21, accel=(0.0, 0.1, 9.8), gyro=(0.0, 0.0, 0.5),
                mag=(20.0, -3.0, 40.0), battery_mv=7400, power_left=200, power_right=-200, mission="circle",
                phase="lap 1"),
    m.GroundTruthPose(robot="zumo2", stamp_us=77, x=0.1, y=0.2, yaw=None, u_px=1.0, v_px=2.0, detector="aruco"),
    m.MissionCommand(mission="circle", params={"radius_m": 0.3, "laps": 2, "direction": "ccw"}, power=0.5,
                     control="closed", start_ns=10, operator="alice"),
    m.Command(verb="led", params={"rgb": [255, 0, 0]}),
    m.CommandReply(ok=False, robot="zumo1", verb="mission", error="robot busy", detail={"phase": "lap 1"}),
    m.Status(role="edge", name="cam0", host="h", pid=1, time_ns=2, uptime_s=3.5, counters={"events_in": 10},
             rates={"events_in": 2.5}, gauges={"latency_ms": 1.2, "source": "tcp"}, errors=1, last_error="x"),
]


@pytest.mark.parametrize("msg", EXAMPLES, ids=lambda x: type(x).__name__)
def test_round_trip_every_message(msg):
    payload = msg.encode()
    assert type(msg).decode(payload) == msg
    assert m.decode(payload) == msg


def test_decode_checks_the_kind():
    with pytest.raises(MessageError, match="expected a 'track' message"):
        m.Track.decode(EXAMPLES[0].encode())


def _raw(kind, **fields):
    return msgpack.packb({"v": 1, "kind": kind, **fields}, use_bin_type=True)


@pytest.mark.parametrize("payload,field", [
    (_raw("track", track_id="1"), "Track.track_id"),
    (_raw("track", track_id=1, x=math.nan), "Track.x"),
    (_raw("track", track_id=1, x=math.inf), "Track.x"),
    (_raw("track", track_id=1, state="lost"), "Track.state"),
    (_raw("track", track_id=True), "Track.track_id"),
    (_raw("telemetry", robot="r", seq=1, robot_time_us=1, host_time_ns=1, enc_left=1, enc_right=1,
          accel=[1.0, 2.0]), "Telemetry.accel"),
    (_raw("telemetry", robot="r", seq=1, robot_time_us=1, host_time_ns=1, enc_left=1, enc_right=1,
          power_left=401), "Telemetry.power_left"),
    (_raw("event_window", camera="c", seq=0, t_start_us=10, t_end_us=5, width=1, height=1, count=0, codec="x",
          data=b""), "EventWindow.t_end_us"),
    (_raw("event_window", camera="c", seq=0, t_start_us=0, t_end_us=5, width=0, height=1, count=0, codec="x",
          data=b""), "EventWindow.width"),
    (_raw("event_window", camera="c", seq=0, t_start_us=0, t_end_us=5, width=1, height=1, count=0, codec="x"),
     "EventWindow.data"),
])
def test_bad_fields_are_named(payload, field):
    with pytest.raises(MessageError) as exc:
        m.decode(payload)
    assert field in str(exc.value)


def test_newer_version_rejected_clearly_and_extra_fields_ignored():
    with pytest.raises(MessageError, match="newer than this program"):
        m.decode(msgpack.packb({"v": 99, "kind": "track", "track_id": 1}))
    msg = m.decode(msgpack.packb({"v": 1, "kind": "track", "track_id": 4, "added_in_v2": [1, 2]}))
    assert msg == m.Track(track_id=4)


def test_size_caps():
    limits = m.DecodeLimits(max_window_bytes=10, max_window_events=100)
    big = m.EventWindow(camera="c", seq=0, t_start_us=0, t_end_us=1, width=1, height=1, count=1, codec="x",
                        data=b"x" * 11)
    with pytest.raises(MessageError):
        m.decode(big.encode(), limits)
    many = m.EventWindow(camera="c", seq=0, t_start_us=0, t_end_us=1, width=1, height=1, count=101, codec="x",
                         data=b"")
    with pytest.raises(MessageError, match="cap"):
        m.decode(many.encode(), limits)
    with pytest.raises(MessageError, match="exceeds the cap"):
        m.decode(b"\x00" * 200, m.DecodeLimits(max_payload_bytes=100))


@settings(max_examples=400, deadline=None)
@given(st.binary(max_size=300))
def test_random_bytes_never_crash(data):
    try:
        m.decode(data)
    except MessageError:
        pass


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(EXAMPLES), st.data())
def test_mutated_messages_raise_only_message_error(msg, data):
    payload = bytearray(msg.encode())
    for _ in range(data.draw(st.integers(1, 4))):
        op = data.draw(st.sampled_from(["flip", "cut", "insert"]))
        if op == "flip" and payload:
            i = data.draw(st.integers(0, len(payload) - 1))
            payload[i] = data.draw(st.integers(0, 255))
        elif op == "cut" and payload:
            payload = payload[: data.draw(st.integers(0, len(payload) - 1))]
        else:
            i = data.draw(st.integers(0, len(payload)))
            payload[i:i] = data.draw(st.binary(min_size=1, max_size=8))
    try:
        out = m.decode(bytes(payload))
    except MessageError:
        return
    assert isinstance(out, m.Message)


json_scalars = st.one_of(st.none(), st.booleans(), st.integers(-2**63, 2**64 - 1), st.floats(allow_nan=True),
                         st.text(max_size=10), st.binary(max_size=10))


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(sorted(m.MESSAGE_TYPES)), st.dictionaries(st.text(max_size=12), json_scalars, max_size=12))
def test_structured_garbage_raises_only_message_error(kind, fields):
    payload = msgpack.packb({"v": 1, "kind": kind, **fields}, use_bin_type=True)
    try:
        m.decode(payload)
    except MessageError:
        pass

"""The viewer parses every key with :mod:`arena.keys`: a sample or liveliness token on a malformed
key, or a message of another type than its key carries, is counted and ignored, never raised."""

from __future__ import annotations

import time

from arena.messages import Status, Telemetry, Track
from arena.session import ZenohSettings, open_session
from viewer.service import handle_alive, handle_sample, subscribe
from viewer.state import ViewerState


def _track(robot: str = "zumo1") -> bytes:
    return Track(track_id=1, robot=robot, camera="cam0", stamp_us=1000, x=0.5, y=0.5).encode()


def _status(role: str = "tracker", name: str = "t1") -> bytes:
    return Status(role=role, name=name, host="h", pid=1).encode()


def test_samples_on_malformed_keys_are_counted_not_raised():
    st = ViewerState()
    for key in ("arena/status/tracker", "arena/status/tracker/t1/extra", "arena/robots", "arena",
                "robots/zumo1", "arena/robots/" + "x" * 65, "arena/robots/..", "arena/cmd/zumo1/stop",
                "arena/sim/truth/zumo1", ""):
        handle_sample(st, key, _track())
    for key in ("arena/alive/tracker", "arena/alive/tracker/t1/extra", "arena/alive", "arena/status/tracker/t1"):
        handle_alive(st, key, True)
    snap = st.snapshot()
    assert snap["counts"]["bad_keys"] == 14 and snap["counts"]["tracks"] == 0
    assert snap["tracks"] == [] and snap["services"] == []
    handle_sample(st, "arena/robots/zumo1", _track())           # well-formed keys still work
    handle_sample(st, "arena/status/tracker/t1", _status())
    handle_alive(st, "arena/alive/tracker/t1", True)
    handle_sample(st, "arena/telemetry/zumo1", _track())        # a Track on a telemetry key
    snap = st.snapshot()
    assert [t["key"] for t in snap["tracks"]] == ["arena/robots/zumo1"]
    assert [(s["role"], s["name"], s["alive"]) for s in snap["services"]] == [("tracker", "t1", True)]
    assert snap["counts"]["bad_keys"] == 14 and snap["counts"]["bad"] == 1 and snap["telemetry"] == {}


def test_viewer_subscriber_ignores_malformed_keys_published_on_zenoh(router):
    st = ViewerState()
    settings = ZenohSettings(mode="client", connect=[router.endpoint])
    with open_session(settings) as viewer_session, open_session(settings) as pub:
        subs = subscribe(viewer_session, st)
        try:
            bad_token = pub.liveliness().declare_token("arena/alive/tracker")           # no name
            pub.put("arena/status/tracker/t1/extra", _status())                          # one chunk too many
            pub.put("arena/robots/" + "x" * 70, _track())                                # name longer than 64
            pub.put("arena/robots/zumo2", Telemetry(robot="zumo2", seq=1, robot_time_us=1, host_time_ns=1,
                                                    enc_left=0, enc_right=0, speed_left=0.0, speed_right=0.0,
                                                    gyro=(0.0, 0.0, 0.0), battery_mv=4800).encode())
            good_token = pub.liveliness().declare_token("arena/alive/viewer/v1")
            pub.put("arena/robots/zumo1", _track())
            deadline = time.monotonic() + 15.0
            while time.monotonic() < deadline:
                snap = st.snapshot()
                if (snap["counts"]["bad_keys"] >= 3 and snap["counts"]["bad"] >= 1 and snap["tracks"]
                        and any(s["role"] == "viewer" for s in snap["services"])):
                    break
                time.sleep(0.05)
            snap = st.snapshot()
            bad_token.undeclare()
            good_token.undeclare()
        finally:
            for s in subs:
                s.undeclare()
    assert snap["counts"]["bad_keys"] == 3, snap["counts"]
    assert snap["counts"]["bad"] == 1, snap["counts"]
    assert [t["key"] for t in snap["tracks"]] == ["arena/robots/zumo1"]
    services = {(s["role"], s["name"]) for s in snap["services"] if s["role"] != "router"}  # the router's own
    assert services == {("viewer", "v1")}, snap["services"]

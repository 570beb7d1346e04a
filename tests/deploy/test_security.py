"""Security of the deployed router (deploy/zenoh/router.json5) across network namespaces: TLS with
mutual authentication, user/password and the access-control policy, with a real `arena router`."""

from __future__ import annotations

import time

import pytest

from tests.deploy.conftest import read_events, wait_event

pytestmark = pytest.mark.netns


def _opened(events: list[dict]) -> bool:
    return any(e["event"] == "open" and e["ok"] for e in events)


def test_only_certified_known_clients_connect(deployment):
    good = deployment.client("camera", "edge", "open")
    no_cert = deployment.client("camera", "edge", "open", "--wait", "3",
                                env=deployment.env("camera", "edge", mtls=False))
    rogue = deployment.client("camera", "edge", "open", "--wait", "3",
                              env=deployment.env("camera", "edge", pki=deployment.root / "rogue-pki"))
    bad_password = deployment.client("camera", "edge", "open", "--wait", "3",
                                     env=deployment.env("camera", "edge", password="guess"))
    assert _opened(read_events(good, 20)), "a client with the lab certificate and its password must connect"
    for name, proc in (("no certificate", no_cert), ("certificate of another CA", rogue),
                       ("wrong password", bad_password)):
        events = read_events(proc, 20)
        assert not _opened(events), f"a client with {name} was let in"
        assert any(e["event"] == "open" and not e["ok"] for e in events), events


def test_only_operators_command_robots(deployment):
    # the robot host's stand-in for the bridge: records every command query it receives
    bridge = deployment.client("robot", "bridge", "queryable", "arena/cmd/**", "--duration", "15")
    wait_event(bridge, "ready")
    time.sleep(0.5)
    intruder = deployment.client("tracker", "tracker", "get", "arena/cmd/zumo1/stop")
    viewer = deployment.client("router", "viewer", "get", "arena/cmd/zumo2/stop")
    intruder_events, viewer_events = read_events(intruder, 20), read_events(viewer, 20)
    operator = deployment.client("router", "operator", "get", "arena/cmd/zumo3/stop")
    operator_events = read_events(operator, 20)
    time.sleep(0.3)
    deployment.lab.kill(bridge)
    received = [e["key"] for e in read_events(bridge, 5) if e["event"] == "query"]

    assert received == ["arena/cmd/zumo3/stop"], f"the bridge received {received}"
    assert [e["key"] for e in operator_events if e["event"] == "reply"] == ["arena/cmd/zumo3/stop"]
    for events in (intruder_events, viewer_events):
        assert _opened(events) and not any(e["event"] == "reply" for e in events), events


def test_only_the_bridge_subscribes_to_commands(deployment):
    spy = deployment.client("tracker", "tracker", "sub", "arena/cmd/**", "--duration", "8")
    bridge = deployment.client("robot", "bridge", "sub", "arena/cmd/**", "--duration", "8")
    wait_event(spy, "ready"), wait_event(bridge, "ready")
    time.sleep(0.5)
    operator = deployment.client("router", "operator", "pub", "arena/cmd/all/stop", "--count", "5")
    assert sum(e["event"] == "sent" for e in read_events(operator, 20)) == 5
    spied = [e for e in read_events(spy, 15) if e["event"] == "sample"]
    served = [e for e in read_events(bridge, 15) if e["event"] == "sample"]
    assert served, "the bridge must receive commands (control: the policy lets it)"
    assert spied == [], "a non-bridge role subscribed to arena/cmd/**"


def test_fake_tracks_and_events_never_reach_subscribers(deployment):
    viewer = deployment.client("router", "viewer", "sub", "arena/robots/**", "--duration", "12")
    viewer_events = deployment.client("router", "viewer", "sub", "arena/events/**", "--duration", "12")
    wait_event(viewer, "ready"), wait_event(viewer_events, "ready")
    time.sleep(0.5)
    fakes = [
        deployment.client("camera", "edge", "pub", "arena/robots/zumo1", "--count", "10"),       # edge, not tracker
        deployment.client("robot", "bridge", "pub", "arena/robots/zumo2", "--count", "10"),      # bridge, not tracker
        deployment.client("tracker", "tracker", "pub", "arena/events/cam9", "--count", "10"),    # tracker, not edge
        deployment.client("robot", "edge", "pub", "arena/events/cam8", "--count", "10"),         # edge user, wrong host
    ]
    genuine = [
        deployment.client("tracker", "tracker", "pub", "arena/robots/zumo3", "--count", "10"),
        deployment.client("camera", "edge", "pub", "arena/events/cam0", "--count", "10"),
    ]
    for proc in fakes + genuine:
        assert sum(e["event"] == "sent" for e in read_events(proc, 25)) == 10
    keys = {e["key"] for p in (viewer, viewer_events) for e in read_events(p, 20) if e["event"] == "sample"}
    assert "arena/robots/zumo3" in keys and "arena/events/cam0" in keys, f"genuine data lost: {keys}"
    assert keys == {"arena/robots/zumo3", "arena/events/cam0"}, f"fake data got through: {keys}"

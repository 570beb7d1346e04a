"""The router-mesh rule of deploy/zenoh/router.json5 is bound to router identities: a router's
certificate AND the router-only user `router` (its password in router.env, on router hosts only).
A client presenting a router's certificate with a client user gets that user's rules and nothing
more: it reads no events and cannot e-stop a robot. The central router's certificate only serves
TLS (`arena certs` makes the host `router` so by default), so no client can present it at all. A real
two-router mesh (docs/deployment.md) still forwards tracks and commands."""

from __future__ import annotations

import re
import subprocess
import time

import pytest

from tests.conftest import arena_cmd
from tests.deploy.conftest import read_events, wait_event

pytestmark = pytest.mark.netns

ROUTERS = '{ id: "routers", cert_common_names: ["router"], usernames: ["router"] }'


def hub_config(text: str) -> str:
    """The central router's router.json5 with a second router's name in `routers` (docs: mesh)."""
    assert ROUTERS in text, "deploy/zenoh/router.json5 no longer has the routers subject this test adapts"
    return text.replace(ROUTERS, ROUTERS.replace('["router"], usernames', '["router", "router2"], usernames'))


def spoke_config(text: str, password: str, hub_endpoint: str) -> str:
    """router2's router.json5 (docs: mesh): its own certificate, the hub in `connect`, the router
    user's password from router.env, and the hub (which it dials) known by certificate."""
    text = hub_config(text).replace("/router.pem", "/router2.pem").replace("/router.key", "/router2.key")
    text = re.sub(r"connect: \{ endpoints: \[\] \}", f'connect: {{ endpoints: ["{hub_endpoint}"] }}', text)
    text = text.replace("dictionary_file: ", f'user: "router", password: "{password}", dictionary_file: ')
    text = text.replace(ROUTERS.replace('["router"], usernames', '["router", "router2"], usernames'),
                        ROUTERS.replace('["router"], usernames', '["router", "router2"], usernames')
                        + ',\n      { id: "upstream", cert_common_names: ["router"] }')
    return text.replace('{ rules: ["mesh"], subjects: ["routers"] }', '{ rules: ["mesh"], subjects: ["routers", "upstream"] }')


@pytest.fixture(scope="module")
def mesh(deployment):
    """The deployment's router restarted as a hub that knows router2, and router2 on the tracker host."""
    lab, dep = deployment.lab, deployment
    subprocess.run(arena_cmd("certs", str(dep.pki), "--hosts", f"router2={lab.addr('tracker')}", "--users", ""),
                   check=True, capture_output=True)
    # the central router's certificate is serverAuth-only: arena certs' default (the deployment's PKI)
    eku = subprocess.run(["openssl", "x509", "-in", str(dep.pki / "router.pem"), "-noout", "-ext", "extendedKeyUsage"],
                         capture_output=True, text=True, check=True).stdout
    assert "Server" in eku and "Client" not in eku, eku
    base = dep.router_config.read_text()
    hub = dep.root / "hub.json5"
    hub.write_text(hub_config(base))
    router_pw = (dep.pki / "router.env").read_text().split("ARENA_ZENOH_PASSWORD=")[1].strip()
    spoke = dep.root / "spoke.json5"
    spoke.write_text(spoke_config(base, router_pw, f"tls/{lab.addr('router')}:7447"))
    lab.kill(dep.router_proc)
    dep.router_proc = lab.spawn("router", arena_cmd("router", "--zenoh-config", str(hub)))
    wait_event(dep.router_proc, "listening on", 30, raw=True)
    router2 = lab.spawn("tracker", arena_cmd("router", "--zenoh-config", str(spoke), "--name", "router2"))
    wait_event(router2, "listening on", 30, raw=True)
    # the mesh is up when a client of the hub sees router2's liveliness token (bounded wait)
    deadline = time.monotonic() + 20
    while True:
        alive = read_events(dep.client("camera", "viewer", "alive", "arena/alive/router/**"), 20)
        if any(e.get("key") == "arena/alive/router/router2" for e in alive):
            break
        assert time.monotonic() < deadline, f"router2 never joined the hub: {alive}"
        time.sleep(0.5)
    yield dep, router_pw
    lab.kill(router2)


def _with_cert(dep, host: str, cert: str, user: str, password: str | None = None, via: str | None = None) -> dict:
    """Environment of a client on ``host`` presenting ``cert``.pem (instead of the host's own)."""
    env = dep.env(host, user, password)
    path = dep.root / f"client-{host}-as-{cert}.json5"
    text = dep.client_config(host).read_text()
    path.write_text(text.replace(f"/{host}.pem", f"/{cert}.pem").replace(f"/{host}.key", f"/{cert}.key"))
    env["ARENA_ZENOH_CONFIG"] = str(path)
    if via:
        env["ARENA_ZENOH_CONNECT"] = via
    return env


def _opened(events: list[dict]) -> bool:
    return any(e["event"] == "open" and e["ok"] for e in events)


def test_router_certificate_with_a_client_user_gets_only_that_users_rules(mesh):
    dep, router_pw = mesh
    lab = dep.lab
    via2 = f"tls/{lab.addr('tracker')}:7447"
    bridge = dep.client("robot", "bridge", "queryable", "arena/cmd/**", "--duration", "30")
    wait_event(bridge, "ready")
    # spies with router2's certificate (a real router certificate, CN in `routers`): client users on
    # either router, and the router user itself as the control (certificate AND password = a router)
    spies = {
        "edge@hub": dep.client("camera", "edge", "sub", "arena/events/**", "--duration", "10",
                               env=_with_cert(dep, "camera", "router2", "edge")),
        "viewer@router2": dep.client("camera", "edge", "sub", "arena/cmd/**", "--duration", "10",
                                     env=_with_cert(dep, "camera", "router2", "viewer", via=via2)),
        "router@hub": dep.client("camera", "router", "sub", "arena/events/**", "--duration", "10",
                                 env=_with_cert(dep, "camera", "router2", "router", router_pw)),
    }
    for proc in spies.values():
        wait_event(proc, "ready")
    time.sleep(1.0)  # declarations reach the routers
    edge = dep.client("camera", "edge", "pub", "arena/events/cam0", "--count", "10")
    operator = dep.client("router", "operator", "pub", "arena/cmd/all/stop", "--count", "5")
    assert sum(e["event"] == "sent" for e in read_events(edge, 25)) == 10
    assert sum(e["event"] == "sent" for e in read_events(operator, 25)) == 5
    # e-stop attempts with router2's certificate: a viewer (read only) on both routers
    estops = [dep.client("camera", "viewer", "get", "arena/cmd/zumo1/estop", env=_with_cert(dep, "camera", "router2", "viewer")),
              dep.client("camera", "viewer", "get", "arena/cmd/zumo2/estop",
                         env=_with_cert(dep, "camera", "router2", "viewer", via=via2))]
    estop_events = [read_events(p, 20) for p in estops]
    # the hub's own certificate is refused as a client certificate, on either router
    hub_cert = [dep.client("camera", "viewer", "open", "--wait", "3", env=_with_cert(dep, "camera", "router", "viewer")),
                dep.client("camera", "viewer", "open", "--wait", "3", env=_with_cert(dep, "camera", "router", "viewer", via=via2))]
    hub_cert_events = [read_events(p, 20) for p in hub_cert]
    received = {name: [e["key"] for e in read_events(p, 20) if e["event"] == "sample"] for name, p in spies.items()}
    lab.kill(bridge)
    queries = [e["key"] for e in read_events(bridge, 5) if e["event"] == "query"]

    assert len(received["router@hub"]) == 10, f"control: router certificate + router password is a router: {received}"
    assert received["edge@hub"] == [], "a client user with a router certificate read all events"
    assert received["viewer@router2"] == [], "a client user with a router certificate subscribed to commands"
    for events in estop_events:
        assert _opened(events) and not any(e["event"] == "reply" for e in events), events
    assert queries == [], f"e-stops of a client user with a router certificate reached the bridge: {queries}"
    for events in hub_cert_events:
        assert not _opened(events), f"the hub's serverAuth-only certificate was accepted from a client: {events}"


def test_the_mesh_forwards_tracks_and_commands(mesh):
    dep, _ = mesh
    lab = dep.lab
    via2 = f"tls/{lab.addr('tracker')}:7447"
    viewer = dep.client("router", "viewer", "sub", "arena/robots/**", "--duration", "12")
    bridge = dep.client("robot", "bridge", "queryable", "arena/cmd/**", "--duration", "20")
    wait_event(viewer, "ready"), wait_event(bridge, "ready")
    time.sleep(1.0)
    tracker = dep.client("tracker", "tracker", "pub", "arena/robots/zumo1", "--count", "10",
                         env={**dep.env("tracker", "tracker"), "ARENA_ZENOH_CONNECT": via2})
    fake = dep.client("tracker", "edge", "pub", "arena/robots/zumo9", "--count", "10",
                      env={**dep.env("tracker", "edge"), "ARENA_ZENOH_CONNECT": via2})
    assert sum(e["event"] == "sent" for e in read_events(tracker, 30)) == 10
    assert sum(e["event"] == "sent" for e in read_events(fake, 30)) == 10
    operator = read_events(dep.client("tracker", "operator", "get", "arena/cmd/zumo1/estop",
                                      env={**dep.env("tracker", "operator"), "ARENA_ZENOH_CONNECT": via2}), 20)
    keys = {e["key"] for e in read_events(viewer, 20) if e["event"] == "sample"}
    lab.kill(bridge)
    queries = [e["key"] for e in read_events(bridge, 5) if e["event"] == "query"]
    assert keys == {"arena/robots/zumo1"}, f"tracks through the mesh: {keys}"
    assert [e["key"] for e in operator if e["event"] == "reply"] == ["arena/cmd/zumo1/estop"], operator
    assert queries == ["arena/cmd/zumo1/estop"], queries

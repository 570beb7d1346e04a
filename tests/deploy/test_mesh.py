"""Two routers in a mesh (docs/deployment.md, scale-out): a second router on the tracker host
connects to the lab router over TLS as user `router`; clients of either router see each other's
data, and each router still enforces the policy on its own clients."""

from __future__ import annotations

import re
import subprocess
import time

import pytest

from tests.conftest import arena_cmd
from tests.deploy.conftest import read_events, wait_event

pytestmark = pytest.mark.netns


def _mesh_config(text: str, password: str, cert: str, connect: list[str]) -> str:
    """router.json5 as docs/deployment.md says to adapt it for a mesh: every router's name in the
    `routers` subject; a connecting router authenticates with the `router` user's password and
    knows the router it dials (`upstream`) by certificate."""
    routers = '{ id: "routers", cert_common_names: ["router"], usernames: ["router"] }'
    mesh = '{ id: "routers", cert_common_names: ["router", "router2"], usernames: ["router"] }'
    text = text.replace(routers, mesh)
    if not connect:
        return text
    text = text.replace("/router.pem", f"/{cert}.pem").replace("/router.key", f"/{cert}.key")
    text = re.sub(r'connect: \{ endpoints: \[\] \}', f'connect: {{ endpoints: {connect!r} }}'.replace("'", '"'), text)
    text = text.replace(mesh, mesh + ',\n      { id: "upstream", cert_common_names: ["router"] }')
    text = text.replace('{ rules: ["mesh"], subjects: ["routers"] }', '{ rules: ["mesh"], subjects: ["routers", "upstream"] }')
    if password:  # else the router's credentials come from ARENA_ZENOH_USER/PASSWORD (router.env)
        text = text.replace('dictionary_file: ', f'user: "router", password: "{password}", dictionary_file: ')
    return text


def test_two_routers_mesh(deployment):
    lab, dep = deployment.lab, deployment
    subprocess.run(arena_cmd("certs", str(dep.pki), "--hosts", f"router2={lab.addr('tracker')}", "--users", ""),
                   check=True, capture_output=True)
    base = dep.router_config.read_text()
    assert "router2" not in base and '"router", "router2"' in _mesh_config(base, "", "router", [])
    pw = dep.passwords["router"]
    r1 = dep.root / "router1-mesh.json5"
    r1.write_text(_mesh_config(base, pw, "router", []))
    r2 = dep.root / "router2-mesh.json5"
    # router 2 proves itself with router.env's credentials from its environment (as systemd's
    # EnvironmentFile gives them), not with a password written into its config
    r2.write_text(_mesh_config(base, "", "router2", [f"tls/{lab.addr('router')}:7447"]))
    assert '"tls/198.18.0.1:7447"' in r2.read_text() and pw not in r2.read_text()
    env_text = (dep.pki / "router.env").read_text()
    creds = dict(line.split("=", 1) for line in env_text.split())
    assert creds == {"ARENA_ZENOH_USER": "router", "ARENA_ZENOH_PASSWORD": pw}

    lab.kill(dep.router_proc)
    router1 = lab.spawn("router", arena_cmd("router", "--zenoh-config", str(r1)))
    wait_event(router1, "listening on", 30, raw=True)
    dep.router_proc = router1
    router2 = lab.spawn("tracker", arena_cmd("router", "--zenoh-config", str(r2), "--name", "router2"),
                        env=creds)
    wait_event(router2, "listening on", 30, raw=True)

    via2 = {"ARENA_ZENOH_CONNECT": f"tls/{lab.addr('tracker')}:7447"}
    viewer = dep.client("router", "viewer", "sub", "arena/robots/**", "--duration", "15")
    wait_event(viewer, "ready")
    time.sleep(1.0)  # the routers exchange their declarations
    tracker = dep.client("tracker", "tracker", "pub", "arena/robots/zumo1", "--count", "10",
                         env={**dep.env("tracker", "tracker"), **via2})
    fake = dep.client("tracker", "edge", "pub", "arena/robots/zumo9", "--count", "10",
                      env={**dep.env("tracker", "edge"), **via2})
    assert sum(e["event"] == "sent" for e in read_events(tracker, 30)) == 10
    assert sum(e["event"] == "sent" for e in read_events(fake, 30)) == 10
    alive = read_events(dep.client("camera", "viewer", "alive", "arena/alive/router/**"), 20)
    keys = {e["key"] for e in read_events(viewer, 20) if e["event"] == "sample"}
    assert keys == {"arena/robots/zumo1"}, f"through the mesh: {keys}"
    routers = {e["key"] for e in alive if e["event"] == "alive"}
    assert "arena/alive/router/router2" in routers, routers

"""Fault tolerance across network namespaces with the deployed configuration (TLS, user/password, ACL)."""

from __future__ import annotations

import signal
import time

import pytest

from tests.deploy.conftest import read_events, wait_event

pytestmark = pytest.mark.netns


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM], ids=["router-killed", "router-stopped"])
def test_services_reconnect_after_router_restart(deployment, sig):
    service = deployment.client("tracker", "tracker", "service", "tracker", "t0", "--duration", "40")
    viewer = deployment.client("camera", "viewer", "sub", "arena/status/tracker/**", "--duration", "40")
    wait_event(service, "ready"), wait_event(viewer, "ready")
    wait_event(viewer, "sample", timeout=10)  # the service's status flows through the router

    deployment.lab.kill(deployment.router_proc, sig)
    killed = time.time()
    time.sleep(1.0)  # down for a while: clients notice (lease 2 s, or the closed TCP link)
    deployment.start_router()
    restarted = time.time()
    deadline = time.monotonic() + 10
    first = None
    while time.monotonic() < deadline:
        event = wait_event(viewer, "sample", timeout=10)
        if event["t"] > restarted:
            first = event
            break
    assert first is not None, "no status after the router restart"
    assert service.poll() is None, "the service died instead of reconnecting"
    gap_s = first["t"] - restarted
    print(f"status again {gap_s:.3f} s after the router restart ({sig.name})")
    assert gap_s < 2.0, f"status flowed again {gap_s:.2f}s after the router was back (> 2 s)"

    alive = read_events(deployment.client("router", "viewer", "alive", "arena/alive/**"), 20)
    deployment.lab.kill(service), deployment.lab.kill(viewer)
    assert killed < restarted
    assert "arena/alive/tracker/t0" in {e["key"] for e in alive if e["event"] == "alive"}, \
        "the service's liveliness token was not declared again after the restart"

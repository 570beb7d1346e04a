"""Fixtures of the multi-host tests: the namespace lab, the lab PKI made by `arena certs`, the
deploy/zenoh configs installed for each host, a real `arena router` and client processes."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import REPO, arena_cmd
from tests.deploy.netlab import NetLab, netns_unavailable_reason

DEPLOY = REPO / "deploy" / "zenoh"
NETCLIENT = Path(__file__).with_name("netclient.py")
ROUTER_ENDPOINT = "tls/198.18.0.1:7447"


@pytest.fixture(scope="session")
def netns_reason() -> str | None:
    return netns_unavailable_reason()


@pytest.fixture(scope="module")
def netlab(netns_reason):
    """Four hosts (router, camera, tracker, robot) in network namespaces; always removed afterwards."""
    if netns_reason:
        pytest.skip(netns_reason)
    lab = NetLab()
    try:
        lab.up()
        yield lab
    finally:
        lab.close()


class Deployment:
    """The PKI and Zenoh configs of the lab, installed per host the way docs/deployment.md says
    (the /etc/arena/pki paths of deploy/zenoh/*.json5 replaced by this test's folder)."""

    def __init__(self, lab: NetLab, root: Path):
        self.lab, self.root = lab, root
        self.pki = root / "pki"
        # `console`: the certificate of clients on the router host (router.pem is the router's alone)
        hosts = ",".join(f"{h}={lab.addr(h)}" for h in ("router", "camera", "tracker", "robot")) + ",console"
        subprocess.run(arena_cmd("certs", str(self.pki), "--hosts", hosts), check=True, capture_output=True)
        subprocess.run(arena_cmd("certs", str(root / "rogue-pki"), "--hosts", "camera=198.18.0.2", "--users", ""),
                       check=True, capture_output=True)
        self.passwords = dict(line.split(":", 1) for line in (self.pki / "users.txt").read_text().split())
        text = (DEPLOY / "router.json5").read_text().replace("/etc/arena/pki/", f"{self.pki}/")
        self.router_config = root / "router.json5"
        self.router_config.write_text(text)
        self.router_proc: subprocess.Popen | None = None

    def client_config(self, host: str, pki: Path | None = None, mtls: bool = True) -> Path:
        """deploy/zenoh/client.json5 installed on ``host`` (its certificate as host.pem/host.key;
        on the router host, the `console` certificate)."""
        pki = pki or self.pki
        cert = "console" if host == "router" and pki == self.pki else host
        text = (DEPLOY / "client.json5").read_text()
        text = text.replace("/etc/arena/pki/host.pem", f"{pki}/{cert}.pem")
        text = text.replace("/etc/arena/pki/host.key", f"{pki}/{cert}.key")
        text = text.replace("/etc/arena/pki/", f"{self.pki}/")  # the lab CA
        if not mtls:
            text = text.replace("enable_mtls: true", "enable_mtls: false")
        path = self.root / f"client-{host}{'-rogue' if pki != self.pki else ''}{'' if mtls else '-nocert'}.json5"
        path.write_text(text)
        return path

    def env(self, host: str, user: str, password: str | None = None, **kw) -> dict:
        """Environment of a service of role ``user`` on ``host`` (as the systemd units set it)."""
        return {"ARENA_ZENOH_MODE": "client", "ARENA_ZENOH_CONNECT": ROUTER_ENDPOINT,
                "ARENA_ZENOH_CONFIG": str(self.client_config(host, **kw)),
                "ARENA_ZENOH_USER": user,
                "ARENA_ZENOH_PASSWORD": self.passwords.get(user, "") if password is None else password}

    def start_router(self, timeout: float = 20.0) -> subprocess.Popen:
        """`arena router --zenoh-config <installed router.json5>` on the router host."""
        proc = self.lab.spawn("router", arena_cmd("router", "--zenoh-config", str(self.router_config)))
        wait_event(proc, "listening on", timeout, raw=True)
        self.router_proc = proc
        return proc

    def client(self, host: str, user: str, *args: str, env: dict | None = None, log: Path | None = None) -> subprocess.Popen:
        """Start tests/deploy/netclient.py on ``host`` as role ``user`` (output to ``log`` for long runs:
        a pipe nobody reads fills up and blocks the client)."""
        return self.lab.spawn(host, [sys.executable, str(NETCLIENT), *args], env=env or self.env(host, user), log=log)


def read_events(proc: subprocess.Popen, timeout: float) -> list[dict]:
    """Every JSON line ``proc`` prints until it exits (killed after ``timeout`` s)."""
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate(timeout=5)
    return parse_events(out)


def parse_events(text: str) -> list[dict]:
    events = []
    for line in text.splitlines():
        if line.startswith("{"):
            try:
                events.append(json.loads(line))
            except json.JSONDecodeError:
                pass
    return events


def wait_event(proc: subprocess.Popen, needle: str, timeout: float = 20.0, raw: bool = False) -> dict | str:
    """Read ``proc``'s stdout until a line has ``needle`` (an event name, or any text with ``raw``)."""
    seen = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            if proc.poll() is not None:
                break
            continue
        seen.append(line)
        if raw and needle in line:
            return line
        if not raw and line.startswith("{") and json.loads(line).get("event") == needle:
            return json.loads(line)
    raise AssertionError(f"{needle!r} not printed within {timeout}s; got: {''.join(seen)[-3000:]!r}")


@pytest.fixture(scope="module")
def deployment(netlab, tmp_path_factory):
    """The lab's PKI and configs plus a running `arena router` with TLS, user/password and ACL."""
    dep = Deployment(netlab, tmp_path_factory.mktemp("deploy"))
    dep.start_router()
    yield dep

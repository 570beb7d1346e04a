"""A four-host lab in Linux network namespaces, for the multi-machine tests (needs root and `ip`).

Hosts ``router`` (198.18.0.1), ``camera`` (.2), ``tracker`` (.3) and ``robot`` (.4), each a network
namespace with one veth link into a Linux bridge in the caller's namespace; addresses only in
198.18.0.0/24 (RFC 2544 benchmarking range, never routed). Names carry a prefix and the creating
process id (``a9<pid>...``), so a run never touches another run's namespaces, and namespaces left
by a crashed run (whose process is gone) are removed before a new lab is built.

Processes are started inside a host with :meth:`NetLab.spawn` and always killed by
:meth:`NetLab.close` (process group SIGKILL), which then deletes the links and namespaces.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

PREFIX = "a9"
SUBNET = "198.18.0"
HOSTS = {"router": 1, "camera": 2, "tracker": 3, "robot": 4}


def _ip(*args: str, ns: str | None = None, check: bool = True) -> subprocess.CompletedProcess:
    cmd = (["ip", "netns", "exec", ns] if ns else []) + list(args)
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=10)
    if check and proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed: {proc.stderr.strip()}")
    return proc


def netns_unavailable_reason() -> str | None:
    """Why namespace tests cannot run here (None when they can)."""
    if os.geteuid() != 0:
        return "needs root (network namespaces)"
    if shutil.which("ip") is None:
        return "the `ip` command (iproute2) is not installed"
    probe = f"{PREFIX}probe{os.getpid()}"
    try:
        _ip("ip", "netns", "add", probe)
        _ip("ip", "netns", "del", probe)
    except (RuntimeError, subprocess.TimeoutExpired) as exc:
        return f"`ip netns` is not usable here: {exc}"
    return None


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def cleanup_leftovers() -> list[str]:
    """Delete namespaces and links of earlier runs whose creating process is gone; returns their names."""
    removed = []
    pat = re.compile(rf"^{PREFIX}(\d+)")
    names = _ip("ip", "netns", "list", check=False).stdout.split()
    links = re.findall(r"^\d+: ([^:@]+)", _ip("ip", "-o", "link", "show", check=False).stdout, re.M)
    for name in names:
        m = pat.match(name)
        if m and not _pid_alive(int(m.group(1))):
            _ip("ip", "netns", "del", name, check=False)
            removed.append(name)
    for link in links:
        m = pat.match(link)
        if m and not _pid_alive(int(m.group(1))):
            _ip("ip", "link", "del", link, check=False)
            removed.append(link)
    return removed


@dataclass
class NetLab:
    """The namespaces, the bridge and every process started in them."""

    tag: str = field(default_factory=lambda: f"{PREFIX}{os.getpid()}")
    procs: list[subprocess.Popen] = field(default_factory=list)
    created_ns: list[str] = field(default_factory=list)
    created_links: list[str] = field(default_factory=list)

    @property
    def bridge(self) -> str:
        return f"{self.tag}br"

    def ns(self, host: str) -> str:
        """Namespace name of ``host``."""
        return f"{self.tag}-{host}"

    def addr(self, host: str) -> str:
        """IPv4 address of ``host``."""
        return f"{SUBNET}.{HOSTS[host]}"

    def veth(self, host: str) -> str:
        """Name of ``host``'s link on the bridge side (in the caller's namespace)."""
        return f"{self.tag}v{HOSTS[host]}"

    def up(self) -> "NetLab":
        """Build the lab (bridge, namespaces, links, addresses) and check every host reaches the router."""
        cleanup_leftovers()
        _ip("ip", "link", "add", self.bridge, "type", "bridge")
        self.created_links.append(self.bridge)
        _ip("ip", "link", "set", self.bridge, "up")
        for host in HOSTS:
            ns, outer = self.ns(host), self.veth(host)
            _ip("ip", "netns", "add", ns)
            self.created_ns.append(ns)
            _ip("ip", "link", "add", outer, "type", "veth", "peer", "name", "eth0", "netns", ns)
            self.created_links.append(outer)
            _ip("ip", "link", "set", outer, "master", self.bridge)
            _ip("ip", "link", "set", outer, "up")
            _ip("ip", "link", "set", "lo", "up", ns=ns)
            _ip("ip", "addr", "add", f"{self.addr(host)}/24", "dev", "eth0", ns=ns)
            _ip("ip", "link", "set", "eth0", "up", ns=ns)
        for host in HOSTS:
            if host != "router":
                self.wait_reachable(host, "router")
        return self

    def wait_reachable(self, src: str, dst: str, timeout: float = 10.0) -> None:
        """Wait until ``src`` reaches ``dst`` (bridge ports take a moment to forward)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            # a TCP connect to a closed port: "refused" means the host answered (no ping needed)
            probe = ("import socket,sys; s=socket.socket(); s.settimeout(1)\n"
                     f"try: s.connect(('{self.addr(dst)}', 9))\n"
                     "except ConnectionRefusedError: sys.exit(0)\nexcept OSError: sys.exit(1)")
            if _ip(sys.executable, "-c", probe, ns=self.ns(src), check=False).returncode == 0:
                return
            time.sleep(0.2)
        raise RuntimeError(f"{src} cannot reach {dst} ({self.addr(dst)}) within {timeout}s")

    def exec(self, host: str, *args: str, check: bool = True) -> subprocess.CompletedProcess:
        """Run a short command (``tc``, ``ip``) inside ``host``."""
        return _ip(*args, ns=self.ns(host), check=check)

    def spawn(self, host: str, argv: list[str], env: dict | None = None, log: Path | None = None) -> subprocess.Popen:
        """Start ``argv`` inside ``host`` in its own process group; stdout is a text pipe (or ``log``)."""
        out = open(log, "w") if log is not None else subprocess.PIPE  # noqa: SIM115 - closed with the process
        proc = subprocess.Popen(["ip", "netns", "exec", self.ns(host), *argv], stdout=out,
                                stderr=subprocess.STDOUT if log is None else out, text=True,
                                env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
                                start_new_session=True)
        if log is not None:
            out.close()  # the child has its own descriptor
        self.procs.append(proc)
        return proc

    def kill(self, proc: subprocess.Popen, sig: int = signal.SIGKILL, timeout: float = 5.0) -> None:
        """Send ``sig`` to ``proc``'s process group and wait for it (SIGKILL if it lingers)."""
        if proc.poll() is None:
            try:
                os.killpg(proc.pid, sig)
                proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(timeout=timeout)
            except ProcessLookupError:
                pass

    def link(self, host: str, up: bool) -> None:
        """Cut (``up=False``) or restore ``host``'s link to the bridge."""
        _ip("ip", "link", "set", self.veth(host), "up" if up else "down")

    def netem_available(self) -> bool:
        """Whether this kernel has the netem qdisc (``sch_netem``; many container kernels lack it)."""
        ok = self.exec("router", "tc", "qdisc", "replace", "dev", "lo", "root", "netem", "delay", "1ms",
                       check=False).returncode == 0
        self.exec("router", "tc", "qdisc", "del", "dev", "lo", "root", check=False)
        return ok

    def netem(self, host: str, spec: str | None) -> None:
        """Apply ``tc netem`` (e.g. ``"loss 5% delay 25ms 25ms"``) to ``host``'s outgoing traffic; None clears it."""
        if spec is None:
            self.exec(host, "tc", "qdisc", "del", "dev", "eth0", "root", check=False)
        else:
            self.exec(host, "tc", "qdisc", "replace", "dev", "eth0", "root", "netem", *spec.split())

    def impair(self, host: str, loss: float, delay_ms: float, jitter_ms: float, duration: float = 60.0,
               port: int | None = None, log: Path | None = None) -> subprocess.Popen:
        """Loss and delay jitter on ``host``'s link without netem: its veth is moved off the bridge
        and a userspace forwarder (``impair.py``) relays frames between it and a new veth pair on
        the bridge (only TCP ``port`` is impaired when given). :meth:`unimpair` puts the link back. Loss applies per frame as relayed (a
        segmentation-offloaded TCP burst is one frame), so the loss is coarser than netem's."""
        a, b = f"{self.tag}i{HOSTS[host]}a", f"{self.tag}i{HOSTS[host]}b"
        _ip("ip", "link", "add", a, "type", "veth", "peer", "name", b)
        self.created_links.append(a)
        for link in (a, b):
            _ip("ip", "link", "set", link, "up")
        _ip("ip", "link", "set", self.veth(host), "nomaster")
        _ip("ip", "link", "set", b, "master", self.bridge)
        out = open(log, "w") if log is not None else subprocess.DEVNULL  # noqa: SIM115
        proc = subprocess.Popen([sys.executable, str(Path(__file__).with_name("impair.py")), self.veth(host), a,
                                 "--loss", str(loss), "--delay-ms", str(delay_ms), "--jitter-ms", str(jitter_ms),
                                 "--duration", str(duration), *(["--port", str(port)] if port else [])], stdout=out, stderr=subprocess.STDOUT, text=True,
                                start_new_session=True)
        if log is not None:
            out.close()
        self.procs.append(proc)
        self._impaired = getattr(self, "_impaired", {})
        self._impaired[host] = (proc, a)
        return proc

    def unimpair(self, host: str) -> dict | None:
        """Undo :meth:`impair`: stop the forwarder (SIGTERM lets it print its counts) and re-attach the link."""
        proc, a = self._impaired.pop(host)
        self.kill(proc, signal.SIGTERM)
        _ip("ip", "link", "del", a, check=False)
        self.created_links.remove(a)
        _ip("ip", "link", "set", self.veth(host), "master", self.bridge)
        return None

    def close(self) -> None:
        """Kill every spawned process, then delete links and namespaces (never raises)."""
        for proc in self.procs:
            try:
                self.kill(proc, signal.SIGKILL)
            except Exception:  # noqa: BLE001 - cleanup must go on
                pass
            for stream in (proc.stdout,):
                try:
                    if stream is not None:
                        stream.close()
                except Exception:  # noqa: BLE001
                    pass
        for link in reversed(self.created_links):
            _ip("ip", "link", "del", link, check=False)
        for ns in reversed(self.created_ns):
            _ip("ip", "netns", "del", ns, check=False)


def python_argv(*args: str) -> list[str]:
    """argv running this interpreter (the namespaces share the file system)."""
    return [sys.executable, *args]

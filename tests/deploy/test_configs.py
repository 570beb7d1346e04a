"""`arena certs` and the shipped deployment files (no namespaces needed): certificates that openssl
verifies, Zenoh configs that Zenoh accepts, systemd units and compose commands that `arena` parses."""

from __future__ import annotations

import configparser
import functools
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import zenoh

from arena.cli import build_parser
from tests.conftest import REPO, arena_cmd

DEPLOY = REPO / "deploy"


def _certs(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(arena_cmd("certs", *args), capture_output=True, text=True, timeout=60)


def _x509(path: Path, *what: str) -> str:
    return subprocess.run(["openssl", "x509", "-in", str(path), "-noout", *what],
                          capture_output=True, text=True, check=True).stdout


def test_certs_make_a_ca_host_certificates_and_passwords(tmp_path):
    pki = tmp_path / "pki"
    r = _certs(str(pki), "--hosts", "router=198.18.0.1+router.lab,camera=198.18.0.2,laptop", "--users", "edge,operator")
    assert r.returncode == 0, r.stderr
    for host in ("router", "camera", "laptop"):
        verify = subprocess.run(["openssl", "verify", "-CAfile", str(pki / "ca.pem"), str(pki / f"{host}.pem")],
                                capture_output=True, text=True)
        assert verify.returncode == 0, verify.stdout + verify.stderr
        assert (pki / f"{host}.key").stat().st_mode & 0o077 == 0, "private keys must be 0600"
        assert f"CN = {host}" in _x509(pki / f"{host}.pem", "-subject")
    san = _x509(pki / "router.pem", "-ext", "subjectAltName,extendedKeyUsage")
    assert "IP Address:198.18.0.1" in san and "DNS:router" in san and "DNS:router.lab" in san
    # the router's certificate only serves (the default --server-only router); other hosts' do both
    assert "TLS Web Server Authentication" in san and "TLS Web Client Authentication" not in san
    assert "TLS Web Client Authentication" in _x509(pki / "camera.pem", "-ext", "extendedKeyUsage")
    assert "IP Address" not in _x509(pki / "laptop.pem", "-ext", "subjectAltName")
    users = dict(line.split(":", 1) for line in (pki / "users.txt").read_text().split())
    assert set(users) == {"edge", "operator"} and len(set(users.values())) == 2
    assert (pki / "edge.env").read_text() == f"ARENA_ZENOH_USER=edge\nARENA_ZENOH_PASSWORD={users['edge']}\n"
    assert (pki / "users.txt").stat().st_mode & 0o077 == 0

    # adding a host and a user later keeps the CA, the other certificates and passwords
    ca, router = (pki / "ca.pem").read_bytes(), (pki / "router.pem").read_bytes()
    assert _certs(str(pki), "--hosts", "tracker=198.18.0.3", "--users", "tracker").returncode == 0
    assert (pki / "ca.pem").read_bytes() == ca and (pki / "router.pem").read_bytes() == router
    again = dict(line.split(":", 1) for line in (pki / "users.txt").read_text().split())
    assert again["edge"] == users["edge"] and "tracker" in again
    assert subprocess.run(["openssl", "verify", "-CAfile", str(pki / "ca.pem"), str(pki / "tracker.pem")],
                          capture_output=True).returncode == 0


@pytest.mark.parametrize("args, message", [
    (["--hosts", "bad name=1.2.3.4"], "is not a host name"),
    (["--hosts", "cam=1.2.3"], "neither an IP address nor a DNS name"),
    (["--hosts", "a=1.1.1.1,a=1.1.1.2"], "given twice"),
    (["--hosts", ","], "no host given"),
    (["--hosts", "a", "--users", "bad:user"], "is not a user name"),
    (["--hosts", "a", "--days", "0"], "--days must be 1-36500"),
])
def test_certs_bad_input_is_a_clear_error(tmp_path, args, message):
    r = _certs(str(tmp_path / "pki"), *args)
    assert r.returncode == 2 and message in r.stderr and "Traceback" not in r.stderr, r.stderr


@pytest.mark.parametrize("name", ["router.json5", "client.json5"])
def test_zenoh_configs_are_accepted_by_zenoh(name):
    conf = zenoh.Config.from_file(str(DEPLOY / "zenoh" / name))
    assert '"tls"' in conf.get_json("transport/link/protocols")
    assert conf.get_json("scouting/multicast/enabled") == "false"
    assert 2000 <= int(conf.get_json("transport/link/tx/lease")) <= 3000
    assert conf.get_json("transport/link/tls/root_ca_certificate") == '"/etc/arena/pki/ca.pem"'
    if name == "router.json5":
        assert conf.get_json("access_control/enabled") == "true"
        assert conf.get_json("access_control/default_permission") == '"deny"'
        assert conf.get_json("transport/link/tls/enable_mtls") == "true"
    else:
        assert conf.get_json("mode") == '"client"'


@functools.lru_cache(maxsize=1)
def _parser():
    return build_parser()  # loads every registered service command (slow: build it once)


def _registered(argv: list[str]) -> bool:
    return argv[0] in _parser()._subparsers._group_actions[0].choices  # noqa: SLF001


def _check_command(argv: list[str], where: str) -> None:
    if not _registered(argv):
        pytest.skip(f"{where}: `arena {argv[0]}` is not registered yet (its package has not landed)")
    try:
        _parser().parse_args(argv)
    except SystemExit as exc:
        pytest.fail(f"{where}: `arena {' '.join(argv)}` is not a valid command line ({exc})")


@pytest.mark.parametrize("unit", sorted(p.name for p in (DEPLOY / "systemd").glob("*.service")))
def test_systemd_units_run_valid_arena_commands(unit):
    cp = configparser.ConfigParser(interpolation=None, strict=False)
    cp.read(DEPLOY / "systemd" / unit)
    assert cp["Service"]["Restart"] == "always" and cp["Unit"]["StartLimitIntervalSec"] == "0"
    argv = shlex.split(cp["Service"]["ExecStart"].replace("%i", "cam0"))
    assert argv[0] == "/opt/arena/bin/arena"
    if "router" not in unit:
        role = unit.split("-")[1].split("@")[0].split(".")[0]
        assert cp["Service"]["EnvironmentFile"] == f"/etc/arena/pki/{role}.env"
    if argv[1] in ("edge", "track") and cp["Service"].get("ProtectSystem") == "strict":
        # numba kernels: their cache must go to a directory systemd makes writable and keeps
        env = dict(kv.split("=", 1) for kv in shlex.split(cp["Service"]["Environment"]))
        assert env.get("NUMBA_CACHE_DIR") == "/var/cache/" + cp["Service"].get("CacheDirectory", "?"), unit
    _check_command(argv[1:], unit)


def test_compose_services_run_valid_arena_commands():
    yaml = pytest.importorskip("yaml")
    compose = yaml.safe_load((DEPLOY / "docker" / "compose.yaml").read_text())
    produced = {"ca.pem", "users.txt"} | {f"{h}.{e}" for h in ("router", "camera", "tracker", "robot", "console")
                                          for e in ("pem", "key")} | {f"{u}.env" for u in
                                          ("edge", "tracker", "bridge", "groundtruth", "viewer")}
    missing = []
    for name, svc in compose["services"].items():
        for ref in [svc.get("env_file", "")] + [v.split(":")[0] for v in svc.get("volumes", [])]:
            if ref.startswith("./pki/") and ref[len("./pki/"):] not in produced:
                missing.append(f"{name}: {ref}")
            if ref == "./lab.toml":
                assert (DEPLOY / "docker" / "lab.toml").is_file()
        if _registered(svc["command"]):
            _parser().parse_args(svc["command"])
    assert not missing, f"compose refers to files `arena certs` does not make: {missing}"


def _systemd_analyze() -> str:
    exe = shutil.which("systemd-analyze")
    if exe is None or not Path("/lib/systemd/system/sysinit.target").exists():
        pytest.skip("needs systemd-analyze and the system's unit files (the systemd package)")
    return exe


def test_systemd_units_pass_systemd_analyze_verify(tmp_path):
    # systemd's own checks (unknown or misspelt keys, bad values, a missing executable, ...) on
    # a root holding the units where the deployment guide installs them and the venv's `arena`
    exe = _systemd_analyze()
    root = tmp_path / "root"
    (root / "usr/lib/systemd").mkdir(parents=True)
    shutil.copytree("/lib/systemd/system", root / "usr/lib/systemd/system", symlinks=True)
    (root / "etc/systemd/system").mkdir(parents=True)
    for unit in (DEPLOY / "systemd").glob("*.service"):
        shutil.copy(unit, root / "etc/systemd/system" / unit.name)
    (root / "opt/arena/bin").mkdir(parents=True)
    arena = root / "opt/arena/bin/arena"
    arena.write_text(f"#!/bin/sh\nexec {sys.executable} -m arena \"$@\"\n")
    arena.chmod(0o755)
    units = [u.name.replace("@.", "@cam0.") for u in (DEPLOY / "systemd").glob("*.service")]
    out = subprocess.run([exe, "verify", f"--root={root}", *units], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout + out.stderr == "", out.stdout + out.stderr


@pytest.mark.parametrize("unit", sorted(p.name for p in (DEPLOY / "systemd").glob("*.service")))
def test_systemd_units_are_sandboxed(unit, tmp_path):
    # `systemd-analyze security` rates a unit's exposure from 0 (locked down) to 10; systemd
    # calls <= 4 "OK". The units run as `arena` with no capabilities, kernel, control groups and
    # other users' processes out of reach, only IP, local and netlink sockets
    exe = _systemd_analyze()
    path = tmp_path / unit.replace("@.", "@cam0.")
    shutil.copy(DEPLOY / "systemd" / unit, path)
    out = subprocess.run([exe, "security", "--offline=true", "--no-pager", str(path)], capture_output=True,
                         text=True, timeout=60)
    m = re.search(r"Overall exposure level for \S+: ([\d.]+)", out.stdout + out.stderr)
    assert m, out.stdout[-2000:] + out.stderr[-2000:]
    assert float(m[1]) <= 4.0, f"{unit}: exposure {m[1]}\n" + "\n".join(
        ln for ln in out.stdout.splitlines() if ln.startswith("✗"))
    cp = configparser.ConfigParser(strict=False, interpolation=None)
    cp.read(DEPLOY / "systemd" / unit)
    svc = cp["Service"]
    assert svc.get("User") == "arena" and svc.get("CapabilityBoundingSet") == ""
    # ProtectClock= implies a DeviceAllow= rule, which closes every other device: never on the
    # units that open cameras or serial links
    if "PrivateDevices" not in svc:
        assert "ProtectClock" not in svc, unit

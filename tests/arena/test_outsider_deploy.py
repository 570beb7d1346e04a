"""What an outsider trying the deployment commands found, each now said or done as a user expects:
a router dialling TLS with a serverAuth-only certificate says so at start instead of retrying in
silence; "Unable to connect" names the credentials a router may have refused (never the
password); ``-c FILE``'s connect endpoints are used unless ``--connect`` is given; rerunning
``arena certs`` with other addresses (or an explicit ``--server-only``) remakes that host's
certificate with the same CA; port 0 is refused where it would be dialled; ``--lease-ms`` has the
lab config's bounds. Real commands (subprocesses), real routers on ephemeral loopback ports."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest

from tests.conftest import arena_cmd, free_port, wait_for_line

#: variables of the test's environment that would choose the Zenoh settings under test
_OURS = ("ARENA_LAB", "ARENA_ZENOH_MODE", "ARENA_ZENOH_CONNECT", "ARENA_ZENOH_LISTEN", "ARENA_ZENOH_CONFIG",
         "ARENA_ZENOH_USER", "ARENA_ZENOH_PASSWORD")


def _env(**extra: str) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in _OURS}
    return {**env, "PYTHONUNBUFFERED": "1", **extra}


def arena(*args: str, timeout: float = 60, **env: str) -> subprocess.CompletedProcess:
    return subprocess.run(arena_cmd(*map(str, args)), capture_output=True, text=True, timeout=timeout,
                          env=_env(**env))


def _openssl_ext(pem: Path, ext: str) -> str:
    """openssl's own reading of one extension of ``pem`` (the independent check of ours)."""
    out = subprocess.run(["openssl", "x509", "-in", str(pem), "-noout", "-ext", ext], capture_output=True,
                         text=True, check=True).stdout
    return out.splitlines()[-1].strip() if out.strip() else ""


@pytest.fixture(scope="module")
def pki(tmp_path_factory) -> Path:
    """``arena certs`` with its defaults: the host ``router`` serverAuth-only, ``router2`` both uses."""
    out = tmp_path_factory.mktemp("pki") / "pki"
    r = arena("certs", out, "--hosts", "router=127.0.0.1,router2=127.0.0.1+r2.lab", "--users", "viewer")
    assert r.returncode == 0, r.stderr
    return out


def _router_config(path: Path, pki: Path, host: str) -> Path:
    path.write_text(json.dumps({
        "mode": "router", "scouting": {"multicast": {"enabled": False}},
        "transport": {"link": {"tls": {"root_ca_certificate": str(pki / "ca.pem"), "enable_mtls": True,
                                       "connect_certificate": str(pki / f"{host}.pem"),
                                       "connect_private_key": str(pki / f"{host}.key")}}}}))
    return path


# ---- 1. a router dialling TLS with a certificate without clientAuth ----------------------------
def test_our_certificate_reader_agrees_with_openssl(pki):
    from arena.certs import allows_client_auth, read_certificate

    router, router2, ca = (read_certificate((pki / f"{n}.pem").read_bytes()) for n in ("router", "router2", "ca"))
    assert _openssl_ext(pki / "router.pem", "extendedKeyUsage") == "TLS Web Server Authentication"
    assert router.uses == {"serverAuth"} and not allows_client_auth(router)
    assert router2.uses == {"serverAuth", "clientAuth"} and allows_client_auth(router2)
    assert ca.uses is None and allows_client_auth(ca)   # no extendedKeyUsage: every use
    assert _openssl_ext(pki / "router2.pem", "subjectAltName") == "IP Address:127.0.0.1, DNS:router2, DNS:r2.lab"
    assert router2.names == {"IP:127.0.0.1", "DNS:router2", "DNS:r2.lab"} and router.names == {"IP:127.0.0.1",
                                                                                                "DNS:router"}


def test_a_router_dialling_tls_with_a_server_only_certificate_says_so_at_start(pki, tmp_path):
    dialled = f"tls/127.0.0.1:{free_port()}"
    bad = arena("router", "--zenoh-config", _router_config(tmp_path / "r.json5", pki, "router"),
                "-l", f"tcp/127.0.0.1:{free_port()}", "-e", dialled, "--duration", "0.3")
    assert bad.returncode == 2 and bad.stdout == "", (bad.returncode, bad.stdout, bad.stderr)
    lines = bad.stderr.strip().splitlines()
    assert len(lines) == 1, bad.stderr
    line = lines[0]
    assert dialled in line and str(pki / "router.pem") in line and "without clientAuth" in line, line
    assert "--server-only none" in line and "Traceback" not in line
    # control: router2's certificate (serverAuth and clientAuth) dials as before
    good = arena("router", "--zenoh-config", _router_config(tmp_path / "r2.json5", pki, "router2"),
                 "-l", f"tcp/127.0.0.1:{free_port()}", "-e", dialled, "--duration", "0.3")
    assert good.returncode == 0 and f"dialing {dialled}" in good.stdout, good.stdout + good.stderr


def test_a_router_names_the_routers_its_config_file_dials(tmp_path):
    conf = tmp_path / "router.json5"
    dialled = f"tcp/127.0.0.1:{free_port()}"
    conf.write_text(json.dumps({"mode": "router", "connect": {"endpoints": [dialled]},
                                "scouting": {"multicast": {"enabled": False}}}))
    r = arena("router", "--zenoh-config", conf, "-l", f"tcp/127.0.0.1:{free_port()}", "--duration", "0.2")
    assert r.returncode == 0 and f"; dialing {dialled} (retried until it answers)" in r.stdout, r.stdout + r.stderr


# ---- 2. "Unable to connect" names the credentials -------------------------------------------------
@pytest.fixture
def password_router(tmp_path):
    """An `arena router` on loopback TCP that checks user/password (user viewer, password right)."""
    (tmp_path / "users.txt").write_text("viewer:right-password\n")
    conf = tmp_path / "router.json5"
    conf.write_text(json.dumps({"scouting": {"multicast": {"enabled": False}},
                                "transport": {"auth": {"usrpwd": {"dictionary_file": str(tmp_path / "users.txt")}}}}))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = subprocess.Popen(arena_cmd("router", "--zenoh-config", str(conf), "-l", endpoint), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env=_env())
    try:
        wait_for_line(proc, "listening on", timeout=30)
        yield endpoint
    finally:
        proc.kill()
        proc.wait(timeout=10)


def test_unable_to_connect_names_the_refused_credentials_but_not_the_password(password_router):
    ok = arena("status", "-e", password_router, "--wait", "0", "--json",
               ARENA_ZENOH_USER="viewer", ARENA_ZENOH_PASSWORD="right-password")
    assert ok.returncode == 0 and '"role": "router"' in ok.stdout, ok.stderr   # control: the right one opens
    wrong = arena("status", "-e", password_router, "--wait", "0",
                  ARENA_ZENOH_USER="viewer", ARENA_ZENOH_PASSWORD="wrong-secret")
    assert wrong.returncode == 1, wrong.stderr
    assert "Unable to connect" in wrong.stderr and "may refuse this host's credentials" in wrong.stderr
    assert "user 'viewer' and its password" in wrong.stderr and "wrong-secret" not in wrong.stderr, wrong.stderr
    # no credentials configured: nothing about them
    plain = arena("status", "-e", f"tcp/127.0.0.1:{free_port()}", "--wait", "0")
    assert plain.returncode == 1 and "Is a router running there" in plain.stderr
    assert "credentials" not in plain.stderr, plain.stderr


def test_unable_to_connect_over_tls_names_the_ca_and_certificate(pki):
    r = arena("status", "-e", f"tls/127.0.0.1:{free_port()}", "--wait", "0",
              "--cfg", f'transport/link/tls/root_ca_certificate:"{pki / "ca.pem"}"',
              "--cfg", "transport/link/tls/enable_mtls:true",
              "--cfg", f'transport/link/tls/connect_certificate:"{pki / "router2.pem"}"',
              "--cfg", f'transport/link/tls/connect_private_key:"{pki / "router2.key"}"')
    assert r.returncode == 1, r.stderr
    assert f"CA {pki / 'ca.pem'}" in r.stderr and f"certificate {pki / 'router2.pem'}" in r.stderr, r.stderr
    assert "clientAuth" in r.stderr and "Traceback" not in r.stderr


# ---- 3. -c FILE's connect endpoints --------------------------------------------------------------
def test_status_connects_where_its_zenoh_config_file_says(router, tmp_path):
    conf = tmp_path / "client.json5"
    conf.write_text(json.dumps({"mode": "client", "connect": {"endpoints": [router.endpoint]},
                                "scouting": {"multicast": {"enabled": False}}}))
    r = arena("status", "-c", conf, "--wait", "0", "--json")
    assert r.returncode == 0, r.stderr
    names = [row["name"] for row in json.loads(r.stdout) if row["role"] == "router"]
    assert any(n.endswith(f"-{router.port}") for n in names), (names, router.port)   # that router, not :7447
    # --connect on the command line wins over the file's
    dead = f"tcp/127.0.0.1:{free_port()}"
    r = arena("status", "-c", conf, "-e", dead, "--wait", "0")
    assert r.returncode == 1 and f"connecting to {dead}" in r.stderr, r.stderr


def test_explicit_connect_endpoints_win_over_the_config_files(tmp_path):
    import argparse

    from arena.config import DEFAULT_ROUTER, parse_lab_config
    from arena.session import resolve_settings

    conf = tmp_path / "client.json5"
    conf.write_text('{ connect: { endpoints: ["tcp/192.0.2.7:7447"] } }')
    args = argparse.Namespace(zenoh_config=str(conf), connect=None)
    assert resolve_settings(args).connect == ["tcp/192.0.2.7:7447"]
    assert resolve_settings(argparse.Namespace(zenoh_config=str(conf), connect=[DEFAULT_ROUTER])).connect == \
        [DEFAULT_ROUTER]
    explicit = parse_lab_config({"zenoh": {"connect": ["tcp/192.0.2.1:7447"], "config_file": str(conf)}})
    assert resolve_settings(None, explicit).connect == ["tcp/192.0.2.1:7447"]
    implicit = parse_lab_config({"zenoh": {"config_file": str(conf)}})
    s = resolve_settings(None, implicit)
    assert s.connect == ["tcp/192.0.2.7:7447"] and "192.0.2.7" in s.describe()
    assert json.loads(s.to_zenoh_config().get_json("connect/endpoints")) == ["tcp/192.0.2.7:7447"]
    assert resolve_settings(None, parse_lab_config({})).connect == [DEFAULT_ROUTER]   # no file: the default


# ---- 4. rerunning arena certs with other addresses -----------------------------------------------
def test_rerunning_certs_with_other_addresses_remakes_that_host_with_the_same_ca(tmp_path):
    out = tmp_path / "pki"
    assert arena("certs", out, "--hosts", "router=127.0.0.1,camera=127.0.0.2", "--users", "").returncode == 0
    before = {n: (out / n).read_bytes() for n in ("ca.pem", "ca.key", "router.pem", "router.key", "camera.pem")}
    same = arena("certs", out, "--hosts", "router=127.0.0.1,camera=127.0.0.2", "--users", "")
    assert same.returncode == 0 and same.stderr == "" and "nothing to do" in same.stdout, same.stderr
    moved = arena("certs", out, "--hosts", "router=127.0.0.1,camera=127.0.0.9+cam.lab", "--users", "")
    assert moved.returncode == 0, moved.stderr
    lines = moved.stderr.strip().splitlines()
    assert len(lines) == 1, f"one line naming the host whose addresses changed, got: {moved.stderr!r}"
    line = lines[0]
    assert line.startswith("arena certs: camera.pem names DNS:camera, IP:127.0.0.2, but --hosts now gives "
                           "DNS:cam.lab, DNS:camera, IP:127.0.0.9"), line
    assert moved.stdout.split() == [str(out / "camera.pem"), str(out / "camera.key")]
    assert _openssl_ext(out / "camera.pem", "subjectAltName") == "IP Address:127.0.0.9, DNS:camera, DNS:cam.lab"
    assert all((out / n).read_bytes() == before[n] for n in ("ca.pem", "ca.key", "router.pem", "router.key"))
    verify = subprocess.run(["openssl", "verify", "-CAfile", str(out / "ca.pem"), str(out / "camera.pem")],
                            capture_output=True, text=True)
    assert verify.returncode == 0, verify.stdout + verify.stderr
    # the advice of `arena router` works: --server-only none remakes the router's with clientAuth ...
    both = arena("certs", out, "--hosts", "router=127.0.0.1", "--users", "", "--server-only", "none")
    assert both.returncode == 0 and "router.pem has extendedKeyUsage serverAuth" in both.stderr, both.stderr
    assert "Client" in _openssl_ext(out / "router.pem", "extendedKeyUsage")
    # ... and a later run without --server-only does not flip it back to the default
    again = arena("certs", out, "--hosts", "router=127.0.0.1", "--users", "")
    assert again.returncode == 0 and again.stderr == "" and "Client" in _openssl_ext(out / "router.pem",
                                                                                   "extendedKeyUsage")


# ---- 5. port 0 -----------------------------------------------------------------------------------
@pytest.mark.parametrize("table, key, value", [
    ({"zenoh": {"connect": ["tcp/127.0.0.1:0"]}}, "zenoh.connect", "tcp/127.0.0.1:0"),
    ({"zenoh": {"connect": ["tls/[::1]:0?iface=lo"]}}, "zenoh.connect", "tls/[::1]:0?iface=lo"),
    ({"cameras": [{"name": "cam0", "source": "tcp://127.0.0.1:0?width=640"}]}, "cameras[0].source",
     "tcp://127.0.0.1:0?width=640"),
    ({"webcam": {"source": "http://127.0.0.1:0/stream.mjpg"}}, "webcam.source", "http://127.0.0.1:0/stream.mjpg"),
])
def test_port_zero_is_refused_where_it_would_be_dialled(table, key, value):
    from arena.config import ConfigError, parse_lab_config

    with pytest.raises(ConfigError) as err:
        parse_lab_config(table)
    assert f"{key}: expected" in str(err.value) and "port 0 cannot be dialled" in str(err.value)
    assert repr(value) in str(err.value)


def test_port_zero_is_a_free_port_to_listen_on_and_refused_on_the_command_line():
    from arena.config import parse_lab_config

    lab = parse_lab_config({"zenoh": {"mode": "peer", "listen": ["tcp/127.0.0.1:0"],
                                      "connect": ["tcp/127.0.0.1:7447", "tcp/127.0.0.1:10"]}})
    assert lab.zenoh.listen == ["tcp/127.0.0.1:0"] and lab.zenoh.connect[1] == "tcp/127.0.0.1:10"
    r = arena("status", "-e", "tcp/127.0.0.1:0", "--wait", "0")
    assert r.returncode == 2 and "tcp/127.0.0.1:0: port 0 cannot be dialled" in r.stderr, r.stderr
    r = arena("status", "--wait", "0", ARENA_ZENOH_CONNECT="tcp/127.0.0.1:0")
    assert r.returncode == 2 and "port 0 cannot be dialled" in r.stderr, r.stderr


# ---- 6. --lease-ms -------------------------------------------------------------------------------
@pytest.mark.parametrize("command", ["status", "router"])
@pytest.mark.parametrize("value", ["-5", "99", "600001"])
def test_lease_ms_has_the_lab_configs_bounds(command, value):
    where = ["-l", f"tcp/127.0.0.1:{free_port()}", "--duration"] if command == "router" else ["--wait"]
    r = arena(command, "--lease-ms", value, *where, "0")   # (a router accepting it listens on no shared port)
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    assert f"argument --lease-ms: expected a lease in milliseconds, an integer in [100, 600000], got '{value}'" \
        in r.stderr and r.stdout == "", r.stderr


def test_lease_ms_bounds_are_the_same_on_the_command_line_and_in_the_lab_config():
    import argparse

    from arena.config import LEASE_MS_RANGE, ConfigError, parse_lab_config
    from arena.session import lease_ms

    assert LEASE_MS_RANGE == (100, 600_000)
    assert lease_ms("100") == 100 and lease_ms("600000") == 600_000
    for bad in ("99", "600001"):
        with pytest.raises(argparse.ArgumentTypeError):
            lease_ms(bad)
        with pytest.raises(ConfigError, match=r"zenoh.lease_ms: expected an integer in \[100, 600000\]"):
            parse_lab_config({"zenoh": {"lease_ms": int(bad)}})
    assert parse_lab_config({"zenoh": {"lease_ms": 600_000}}).zenoh.lease_ms == 600_000

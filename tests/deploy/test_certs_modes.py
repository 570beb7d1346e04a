"""`arena certs` keeps its secrets private from the first byte: the output folder is made 0700,
private keys, users.txt and <role>.env are created 0600 (never created wider and chmod-ed after),
whatever the umask; a --server-only certificate only serves TLS. No namespaces needed."""

from __future__ import annotations

import os
import re
import shutil
import stat
import subprocess
from pathlib import Path

import pytest

from tests.conftest import arena_cmd

SECRET = re.compile(r"(\.key|\.env|users\.txt)$")


def _certs(umask: int, *args: str, prefix: list[str] | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([*(prefix or []), *arena_cmd("certs", *args)], capture_output=True, text=True,
                          timeout=120, preexec_fn=lambda: os.umask(umask))


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


@pytest.mark.parametrize("umask", [0o022, 0o000])
def test_secrets_are_0600_in_a_0700_folder_whatever_the_umask(tmp_path, umask):
    pki = tmp_path / "lab" / "pki"
    r = _certs(umask, str(pki), "--hosts", "router=198.18.0.1,camera=198.18.0.2", "--users", "router,edge,viewer")
    assert r.returncode == 0, r.stderr
    assert _mode(pki) == 0o700, oct(_mode(pki))
    secrets = sorted(p.name for p in pki.iterdir() if SECRET.search(p.name))
    assert secrets == ["ca.key", "camera.key", "edge.env", "router.env", "router.key", "users.txt", "viewer.env"]
    assert {name: oct(_mode(pki / name)) for name in secrets} == {name: "0o600" for name in secrets}
    for cert in ("ca.pem", "router.pem", "camera.pem"):
        assert _mode(pki / cert) == 0o644, cert  # public, but not writable by others
    assert not [p.name for p in pki.iterdir() if p.name.startswith(".")], "temporary files left behind"

    # a second run (adding a user) keeps the old passwords and the modes, even over a file made wider
    old = (pki / "users.txt").read_text()
    os.chmod(pki / "edge.env", 0o644)
    r = _certs(umask, str(pki), "--hosts", "tracker=198.18.0.3", "--users", "tracker")
    assert r.returncode == 0, r.stderr
    assert (pki / "users.txt").read_text().startswith(old)
    for name in ("users.txt", "edge.env", "tracker.env", "tracker.key"):
        assert _mode(pki / name) == 0o600, name


def _syscalls(log: Path) -> list[str]:
    return [line for line in log.read_text().splitlines()
            if re.search(r"\b(open|openat|creat|chmod|fchmod|fchmodat|fchmodat2)\(", line)]


@pytest.mark.skipif(shutil.which("strace") is None, reason="needs strace (apt-get install strace)")
def test_no_moment_where_a_secret_is_readable_by_others(tmp_path):
    """Every file created in the folder by `arena certs` or the openssl it runs (strace -f) is
    created with a mode of at most 0600 if it ever holds a secret, and nothing is chmod-ed wider."""
    pki = tmp_path / "pki"
    log = tmp_path / "strace.log"
    r = _certs(0o022, str(pki), "--hosts", "router=198.18.0.1,camera", "--users", "router,edge",
               prefix=["strace", "-f", "-qq", "-e", "trace=open,openat,creat,chmod,fchmod,fchmodat,rename,renameat,renameat2",
                       "-o", str(log)])
    if r.returncode != 0 and "ptrace" in r.stderr:
        pytest.skip(f"strace cannot trace here: {r.stderr.strip()[:200]}")
    assert r.returncode == 0, r.stderr
    calls = _syscalls(log)
    created = [c for c in calls if "O_CREAT" in c and str(pki) in c]
    assert created, "strace saw no file created in the folder"
    for call in created:
        path = re.search(r'"([^"]+)"', call).group(1)
        mode = int(re.search(r"O_CREAT[^,]*, (0\d+)", call).group(1), 8)
        if path.endswith(".pem") or path.endswith(".csr"):
            continue  # public
        assert mode & 0o077 == 0, f"{Path(path).name} created with mode {mode:o}: {call}"
    for call in calls:
        m = re.search(r"chmod(?:at)?\((?:[^,]+, )?\"([^\"]+)\", (0\d+)", call)
        if m and SECRET.search(m.group(1)):
            assert int(m.group(2), 8) & 0o077 == 0, call
    # the secrets came from files created 0600 (temporary names, renamed into place)
    assert all(_mode(pki / n) == 0o600 for n in ("users.txt", "router.env", "edge.env", "router.key", "ca.key"))


def test_a_server_only_certificate_serves_tls_only(tmp_path):
    pki = tmp_path / "pki"
    r = _certs(0o022, str(pki), "--hosts", "router=198.18.0.1,router2=198.18.0.11,camera", "--users", "",
               "--server-only", "router")
    assert r.returncode == 0, r.stderr

    def eku(name: str) -> str:
        return subprocess.run(["openssl", "x509", "-in", str(pki / f"{name}.pem"), "-noout", "-ext", "extendedKeyUsage"],
                              capture_output=True, text=True, check=True).stdout.splitlines()[-1].strip()

    assert eku("router") == "TLS Web Server Authentication"
    assert eku("router2") == eku("camera") == "TLS Web Server Authentication, TLS Web Client Authentication"
    # openssl itself refuses the router certificate for a TLS client (purpose sslclient)
    verify = subprocess.run(["openssl", "verify", "-CAfile", str(pki / "ca.pem"), "-purpose", "sslclient",
                             str(pki / "router.pem")], capture_output=True, text=True)
    assert verify.returncode != 0, verify.stdout
    # the default: the host named router serves only, the others both; `none`: every host both
    r = _certs(0o022, str(tmp_path / "default"), "--hosts", "router,camera", "--users", "")
    assert r.returncode == 0, r.stderr
    for name, want in (("router", "TLS Web Server Authentication"),
                       ("camera", "TLS Web Server Authentication, TLS Web Client Authentication")):
        got = subprocess.run(["openssl", "x509", "-in", str(tmp_path / "default" / f"{name}.pem"), "-noout",
                              "-ext", "extendedKeyUsage"], capture_output=True, text=True).stdout
        assert got.splitlines()[-1].strip() == want, (name, got)
    r = _certs(0o022, str(tmp_path / "other"), "--hosts", "router", "--users", "", "--server-only", "none")
    assert r.returncode == 0, r.stderr
    assert "Client" in subprocess.run(["openssl", "x509", "-in", str(tmp_path / "other" / "router.pem"), "-noout",
                                       "-ext", "extendedKeyUsage"], capture_output=True, text=True).stdout


def test_a_ca_certificate_without_its_key_is_not_silently_replaced(tmp_path):
    """The help says ca.key stays on the admin machine: adding a host where only ca.pem is made a
    new CA under the old name (rc 0), and every certificate of the lab stopped verifying."""
    pki = tmp_path / "pki"
    assert _certs(0o022, str(pki), "--hosts", "router=127.0.0.1", "--users", "").returncode == 0
    ca = (pki / "ca.pem").read_bytes()
    (pki / "ca.key").unlink()
    r = _certs(0o022, str(pki), "--hosts", "laptop=127.0.0.3", "--users", "")
    assert r.returncode == 2 and "has ca.pem but not ca.key" in r.stderr and "--force" in r.stderr, r.stderr
    assert (pki / "ca.pem").read_bytes() == ca and not (pki / "laptop.pem").exists()


def test_bad_hosts_days_and_server_only_names_are_refused_before_anything_is_written(tmp_path):
    for args, message in ((["--hosts", "x=1.2.3.4", "--days", "99999999"], "--days must be 1-36500"),
                          (["--hosts", "ca=1.2.3.4"], "'ca' is the lab CA's own file name"),
                          (["--hosts", "router,camera", "--server-only", "camer"], "--server-only: camer not among")):
        out = tmp_path / message[:6].strip("-' ")
        r = _certs(0o022, str(out), *args, "--users", "")
        assert r.returncode == 2 and message in r.stderr and "Traceback" not in r.stderr, (args, r.stderr)
        assert not out.exists() or not any(out.iterdir()), (args, list(out.iterdir()))


def test_a_host_certificate_that_failed_leaves_nothing_behind(tmp_path):
    """openssl refusing a certificate left a 0-byte x.pem, which the next run kept as made."""
    from arena.certs import CertError, HostSpec, make_lab_pki

    pki = tmp_path / "pki"
    with pytest.raises(CertError):
        make_lab_pki(pki, [HostSpec("x")], [], days=99_999_999)   # beyond the year 9999: openssl fails
    assert not (pki / "x.pem").exists() and not (pki / "x.key").exists()
    make_lab_pki(pki, [HostSpec("x")], [])                        # the next run makes it
    assert (pki / "x.pem").stat().st_size > 0


def test_forcing_a_new_ca_names_the_certificates_it_leaves_unverifiable(tmp_path):
    pki = tmp_path / "pki"
    assert _certs(0o022, str(pki), "--hosts", "router=127.0.0.1,camera", "--users", "").returncode == 0
    r = _certs(0o022, str(pki), "--hosts", "router=127.0.0.9", "--users", "", "--force")
    assert r.returncode == 0 and "camera.pem were signed by the CA just replaced" in r.stderr, r.stderr

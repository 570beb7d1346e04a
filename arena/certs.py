"""``arena certs``: a lab certificate authority, per-host certificates and per-role passwords for
Zenoh over TLS with mutual authentication (mTLS) and user/password authentication.

Everything is made by the system ``openssl`` binary (present on every Linux), so no extra Python
package is needed. Output folder ``DIR`` (created; existing files are kept unless ``--force``)::

    ca.pem  ca.key                 the lab CA (keep ca.key on the admin machine only)
    <host>.pem  <host>.key         one certificate per host: CN = host name, subjectAltName =
                                   the host's IP addresses and DNS names (EC P-256, server+client use)
    users.txt                      the router's user/password dictionary (``user:password`` lines)
    <user>.env                     ARENA_ZENOH_USER / ARENA_ZENOH_PASSWORD for one role, read by
                                   the systemd units (``EnvironmentFile=``) or ``source``d by hand

The certificate's common name is the host name: the router's access-control policy
(``deploy/zenoh/router.json5``) matches it with ``cert_common_names`` and the role with
``usernames``. Private keys and password files are written with mode 0600.
"""

from __future__ import annotations

import argparse
import ipaddress
import os
import re
import secrets
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["CertError", "HostSpec", "parse_hosts", "make_ca", "make_host_cert", "make_users", "register"]

DEFAULT_USERS = ("router", "edge", "tracker", "bridge", "groundtruth", "operator", "viewer")
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9.-]{0,62}$")
_USER_RE = re.compile(r"^[A-Za-z0-9_-]{1,32}$")


class CertError(RuntimeError):
    """A certificate could not be made; the message says what was wrong (bad input, openssl)."""


@dataclass
class HostSpec:
    """One host: its name (the certificate's CN) and the addresses it is reached at."""

    name: str
    ips: list[str] = field(default_factory=list)
    dns: list[str] = field(default_factory=list)

    def san(self) -> str:
        """The ``subjectAltName`` value: every IP, the host name and every extra DNS name."""
        names = [f"IP:{ip}" for ip in self.ips] + [f"DNS:{d}" for d in dict.fromkeys([self.name, *self.dns])]
        return ",".join(names)


def parse_hosts(text: str) -> list[HostSpec]:
    """Parse ``router=198.18.0.1,camera=198.18.0.2+cam.lab,operator``.

    Each item is ``NAME[=ADDR[+ADDR...]]``; an address is an IPv4/IPv6 address or a DNS name.
    Raises :class:`CertError` naming the bad item.
    """
    hosts: list[HostSpec] = []
    seen: set[str] = set()
    for item in (s.strip() for s in text.split(",")):
        if not item:
            continue
        name, _, addrs = item.partition("=")
        name = name.strip()
        if not _NAME_RE.match(name):
            raise CertError(f"--hosts: {name!r} is not a host name (letters, digits, '.', '-'; at most 63)")
        if name in seen:
            raise CertError(f"--hosts: host {name!r} is given twice")
        seen.add(name)
        spec = HostSpec(name)
        for addr in (a.strip() for a in addrs.split("+") if a.strip()):
            try:
                spec.ips.append(str(ipaddress.ip_address(addr)))
            except ValueError:
                if not _NAME_RE.match(addr) or addr.replace(".", "").isdigit():
                    raise CertError(f"--hosts: {addr!r} (host {name}) is neither an IP address nor a DNS name") from None
                spec.dns.append(addr)
        hosts.append(spec)
    if not hosts:
        raise CertError("--hosts: no host given (e.g. --hosts router=198.18.0.1,camera=198.18.0.2)")
    return hosts


def _openssl(*args: str, cwd: Path | None = None) -> None:
    exe = shutil.which("openssl")
    if exe is None:
        raise CertError("the openssl command is not installed (apt-get install openssl)")
    proc = subprocess.run([exe, *args], cwd=cwd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise CertError(f"openssl {args[0]} failed: {proc.stderr.strip() or proc.stdout.strip()}")


def _private(path: Path) -> None:
    os.chmod(path, 0o600)


def make_ca(out: Path, name: str = "arena lab CA", days: int = 3650) -> tuple[Path, Path]:
    """Create ``out/ca.pem`` and ``out/ca.key`` (self-signed CA, EC P-256, ``days`` valid)."""
    key, cert = out / "ca.key", out / "ca.pem"
    _openssl("genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256", "-out", str(key))
    _private(key)
    _openssl("req", "-x509", "-new", "-key", str(key), "-out", str(cert), "-days", str(days), "-sha256",
             "-subj", f"/CN={name}",
             "-addext", "basicConstraints=critical,CA:TRUE",
             "-addext", "keyUsage=critical,keyCertSign,cRLSign",
             "-addext", "subjectKeyIdentifier=hash")
    return cert, key


def make_host_cert(out: Path, host: HostSpec, days: int = 825) -> tuple[Path, Path]:
    """Create ``out/<host>.pem`` and ``out/<host>.key`` signed by ``out/ca.pem``.

    The certificate serves both ends of a TLS link (extendedKeyUsage serverAuth and clientAuth):
    a router listens with it and a client presents it for mTLS.
    """
    key, cert = out / f"{host.name}.key", out / f"{host.name}.pem"
    _openssl("genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256", "-out", str(key))
    _private(key)
    with tempfile.TemporaryDirectory(prefix="arena-certs-") as tmp:
        csr, ext = Path(tmp) / "host.csr", Path(tmp) / "host.ext"
        ext.write_text("basicConstraints=critical,CA:FALSE\n"
                       "keyUsage=critical,digitalSignature\n"
                       "extendedKeyUsage=serverAuth,clientAuth\n"
                       f"subjectAltName={host.san()}\n"
                       "subjectKeyIdentifier=hash\n"
                       "authorityKeyIdentifier=keyid\n")
        _openssl("req", "-new", "-key", str(key), "-subj", f"/CN={host.name}", "-out", str(csr))
        _openssl("x509", "-req", "-in", str(csr), "-CA", str(out / "ca.pem"), "-CAkey", str(out / "ca.key"),
                 "-set_serial", str(secrets.randbits(63)), "-days", str(days), "-sha256",
                 "-extfile", str(ext), "-out", str(cert))
    return cert, key


def make_users(out: Path, users: list[str], force: bool = False) -> dict[str, str]:
    """Write ``users.txt`` (the router's dictionary) and one ``<user>.env`` per user.

    Existing passwords are kept (so adding a user does not lock the others out) unless ``force``.
    Returns ``{user: password}``.
    """
    dictionary = out / "users.txt"
    passwords: dict[str, str] = {}
    if dictionary.exists() and not force:
        for line in dictionary.read_text().splitlines():
            user, sep, pwd = line.partition(":")
            if sep and user:
                passwords[user] = pwd
    for user in users:
        if not _USER_RE.match(user):
            raise CertError(f"--users: {user!r} is not a user name (letters, digits, '_', '-'; at most 32)")
        passwords.setdefault(user, secrets.token_urlsafe(18))
    dictionary.write_text("".join(f"{u}:{p}\n" for u, p in passwords.items()))
    _private(dictionary)
    for user, pwd in passwords.items():
        env = out / f"{user}.env"
        env.write_text(f"ARENA_ZENOH_USER={user}\nARENA_ZENOH_PASSWORD={pwd}\n")
        _private(env)
    return passwords


def make_lab_pki(out: Path, hosts: list[HostSpec], users: list[str], days: int = 825,
                 force: bool = False) -> list[Path]:
    """Make (or complete) a lab's PKI in ``out``; returns the files written."""
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    if force or not (out / "ca.pem").exists() or not (out / "ca.key").exists():
        written += make_ca(out)
    for host in hosts:
        if force or not (out / f"{host.name}.pem").exists():
            written += make_host_cert(out, host, days)
    if users:
        make_users(out, users, force)
        written += [out / "users.txt", *(out / f"{u}.env" for u in users)]
    return written


# ------------------------------------------------------------------------------------------------
def register(sub) -> None:
    """Add ``arena certs`` to the ``arena`` command."""
    p = sub.add_parser(
        "certs", help="make the lab CA, host certificates and role passwords (TLS + user/password)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=__doc__.split("\n\n", 1)[1].split("The certificate's")[0].rstrip()
        .replace("``", "").replace("::", ":"),
        epilog="Examples:\n"
               "  arena certs pki --hosts router=198.18.0.1,camera=198.18.0.2,tracker=198.18.0.3,robot=198.18.0.4\n"
               "  arena certs pki --hosts laptop                 # add a host later (the CA is reused)\n"
               "  arena certs pki --hosts router=10.0.0.1+router.lab --users operator,viewer\n"
               "  openssl x509 -in pki/camera.pem -noout -text   # inspect one\n"
               "Then see docs/deployment.md (which files go to which host).")
    p.add_argument("dir", metavar="DIR", help="output folder (created; existing CA and certificates are reused)")
    p.add_argument("--hosts", required=True, metavar="NAME=ADDR[+ADDR],...",
                   help="hosts to certify: name (certificate CN) and IP addresses / DNS names")
    p.add_argument("--users", default=",".join(DEFAULT_USERS), metavar="USER,...",
                   help=f"roles given a password (default {','.join(DEFAULT_USERS)}); empty for none")
    p.add_argument("--days", type=int, default=825, help="host certificate validity in days (default 825)")
    p.add_argument("--force", action="store_true", help="replace an existing CA, certificates and passwords")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """``arena certs`` entry point; returns the exit code."""
    try:
        if args.days <= 0:
            raise CertError("--days must be positive")
        hosts = parse_hosts(args.hosts)
        users = [u.strip() for u in args.users.split(",") if u.strip()]
        out = Path(args.dir)
        written = make_lab_pki(out, hosts, users, args.days, args.force)
    except (CertError, OSError) as exc:
        print(f"arena certs: {exc}", file=sys.stderr)
        return 2
    for path in written:
        print(path)
    if not written:
        print(f"nothing to do: every certificate already exists in {out} (--force replaces them)")
    return 0

"""``arena certs``: a lab certificate authority, per-host certificates and per-role passwords for
Zenoh over TLS with mutual authentication (mTLS) and user/password authentication.

Everything is made by the system ``openssl`` binary (present on every Linux), so no extra Python
package is needed. Output folder ``DIR`` (created; existing files are kept unless ``--force``, but
a host certificate naming other addresses than ``--hosts`` now gives, or other uses than an explicit
``--server-only`` asks for, is made again with the same CA, and a line on stderr names the host)::

    ca.pem  ca.key                 the lab CA (keep ca.key on the admin machine only)
    <host>.pem  <host>.key         one certificate per host: CN = host name, subjectAltName =
                                   the host's IP addresses and DNS names (EC P-256, server+client use)
    users.txt                      the router's user/password dictionary (``user:password`` lines)
    <user>.env                     ARENA_ZENOH_USER / ARENA_ZENOH_PASSWORD for one role, read by
                                   the systemd units (``EnvironmentFile=``) or ``source``d by hand

The certificate's common name is the host name: the router's access-control policy
(``deploy/zenoh/router.json5``) matches it with ``cert_common_names`` and the role with
``usernames``. The user ``router`` is the routers' own: its password (``router.env``) goes to
router hosts only, and a router link is trusted only with a router certificate AND that password.
Hosts named by ``--server-only`` (default: the host ``router``, the lab's router, central in a
mesh) get a certificate that only serves TLS (extendedKeyUsage serverAuth), so nobody can present
it as a client; ``--server-only none`` gives every host both uses.

Private keys, ``users.txt`` and ``*.env`` are created with mode 0600 (never wider, whatever the
umask) in a folder created with mode 0700.
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

__all__ = ["CertError", "CertInfo", "HostSpec", "allows_client_auth", "make_ca", "make_host_cert", "make_users",
           "parse_hosts", "read_certificate", "register"]

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

    def names(self) -> frozenset[str]:
        """The subjectAltName entries as :attr:`CertInfo.names` gives them (``IP:...``, ``DNS:...``)."""
        return frozenset(n if n.startswith("IP:") else "DNS:" + n[4:].lower() for n in self.san().split(","))


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
        if name.lower() == "ca":
            raise CertError("--hosts: 'ca' is the lab CA's own file name (ca.pem, ca.key): name the host otherwise")
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


# ------------------------------------------------------------------------------ reading a certificate
#: extendedKeyUsage purposes by their DER-encoded object identifier
_EKU_NAMES = {bytes.fromhex("2b06010505070301"): "serverAuth", bytes.fromhex("2b06010505070302"): "clientAuth",
              bytes.fromhex("551d2500"): "anyExtendedKeyUsage"}
_OID_EKU, _OID_SAN = bytes.fromhex("551d25"), bytes.fromhex("551d11")


@dataclass(frozen=True)
class CertInfo:
    """What :func:`read_certificate` reads from a certificate: its subjectAltName entries
    (``IP:<address>``, ``DNS:<name>`` in lower case) and its extendedKeyUsage purposes
    (``serverAuth``, ``clientAuth``, ``anyExtendedKeyUsage`` or a dotted OID), None when it
    has no extendedKeyUsage (then TLS allows every use)."""

    names: frozenset[str]
    uses: frozenset[str] | None


def _der(data: bytes, pos: int, end: int) -> tuple[int, int, int]:
    """The DER element at ``pos``: (tag, start of its value, end of its value)."""
    if pos + 2 > end:
        raise CertError("truncated certificate (DER)")
    tag, n = data[pos], data[pos + 1]
    pos += 2
    if n & 0x80:
        k = n & 0x7F
        if not 1 <= k <= 4 or pos + k > end:
            raise CertError("bad length in the certificate (DER)")
        n, pos = int.from_bytes(data[pos:pos + k], "big"), pos + k
    if pos + n > end:
        raise CertError("truncated certificate (DER)")
    return tag, pos, pos + n


def _children(data: bytes, start: int, end: int) -> list[tuple[int, int, int]]:
    out, pos = [], start
    while pos < end:
        item = _der(data, pos, end)
        out.append(item)
        pos = item[2]
    return out


def _oid_text(raw: bytes) -> str:
    parts, v = [], 0
    for b in raw:
        v = (v << 7) | (b & 0x7F)
        if not b & 0x80:
            parts.append(v)
            v = 0
    if not parts:
        return ""
    first = min(parts[0] // 40, 2)
    return ".".join(str(x) for x in (first, parts[0] - 40 * first, *parts[1:]))


def read_certificate(pem: bytes | str) -> CertInfo:
    """The subjectAltName and extendedKeyUsage of the first certificate of ``pem`` (PEM text or
    DER bytes), read with the standard library alone; :class:`CertError` if it is not one."""
    import base64
    import binascii

    raw = pem.encode() if isinstance(pem, str) else pem
    m = re.search(rb"-----BEGIN CERTIFICATE-----(.+?)-----END CERTIFICATE-----", raw, re.S)
    if m:
        try:
            raw = base64.b64decode(b"".join(m.group(1).split()), validate=True)
        except (binascii.Error, ValueError):
            raise CertError("not a PEM certificate (bad base64)") from None
    elif b"-----BEGIN" in raw:
        raise CertError("no CERTIFICATE block in the PEM file")
    tag, start, end = _der(raw, 0, len(raw))
    if tag != 0x30:
        raise CertError("not an X.509 certificate")
    tag, start, end = _der(raw, start, end)          # tbsCertificate
    if tag != 0x30:
        raise CertError("not an X.509 certificate")
    names: set[str] = set()
    uses: set[str] | None = None
    for tag, s, e in _children(raw, start, end):
        if tag != 0xA3:                               # [3] extensions
            continue
        ext = _children(raw, s, e)
        if not ext or ext[0][0] != 0x30:
            continue
        # Extension ::= SEQUENCE {extnID OID, critical BOOLEAN (optional), extnValue OCTET STRING}
        for _, xs, xe in _children(raw, ext[0][1], ext[0][2]):
            parts = _children(raw, xs, xe)
            if len(parts) < 2 or parts[0][0] != 0x06 or parts[-1][0] != 0x04:
                continue
            oid, value = raw[parts[0][1]:parts[0][2]], parts[-1]
            if oid not in (_OID_EKU, _OID_SAN):
                continue
            inner = _der(raw, value[1], value[2])       # SEQUENCE OF ...
            items = _children(raw, inner[1], inner[2])
            if oid == _OID_EKU:
                uses = {_EKU_NAMES.get(raw[a:b], _oid_text(raw[a:b])) for t, a, b in items if t == 0x06}
            else:
                for t, a, b in items:
                    if t == 0x82:                       # [2] dNSName
                        names.add("DNS:" + raw[a:b].decode("ascii", "replace").lower())
                    elif t == 0x87 and b - a in (4, 16):  # [7] iPAddress
                        names.add(f"IP:{ipaddress.ip_address(raw[a:b])}")
    return CertInfo(frozenset(names), None if uses is None else frozenset(uses))


def allows_client_auth(info: CertInfo) -> bool:
    """Whether TLS accepts the certificate as a client's (mTLS): no extendedKeyUsage, or one
    with clientAuth (or anyExtendedKeyUsage)."""
    return info.uses is None or bool(info.uses & {"clientAuth", "anyExtendedKeyUsage"})


_USES = {True: frozenset({"serverAuth"}), False: frozenset({"serverAuth", "clientAuth"})}


def _differs(cert: Path, host: HostSpec, server_only: bool | None) -> str | None:
    """Why the existing ``cert`` is not what ``host`` asks for now (its addresses, or its uses
    when ``server_only`` is not None), None when it is."""
    try:
        info = read_certificate(cert.read_bytes())
    except (CertError, OSError) as exc:
        return f"cannot be read ({exc})"
    want = host.names()
    if info.names != want:
        return (f"names {', '.join(sorted(info.names)) or 'no address'}, but --hosts now gives "
                f"{', '.join(sorted(want))}")
    if server_only is not None and info.uses != _USES[server_only]:
        def text(uses):
            return "every use (no extendedKeyUsage)" if uses is None else "+".join(sorted(uses))
        return f"has extendedKeyUsage {text(info.uses)}, but --server-only now asks for {text(_USES[server_only])}"
    return None


def _openssl(*args: str, cwd: Path | None = None) -> None:
    exe = shutil.which("openssl")
    if exe is None:
        raise CertError("the openssl command is not installed (apt-get install openssl)")
    proc = subprocess.run([exe, *args], cwd=cwd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise CertError(f"openssl {args[0]} failed: {proc.stderr.strip() or proc.stdout.strip()}")


def _write_private(path: Path, data: bytes | str) -> None:
    """Write ``path`` readable by its owner only (mode 0600) from the first byte on.

    The data goes to a temporary file made with mode 0600 (``mkstemp``; a umask only removes
    bits) in the same folder, which then replaces ``path`` atomically: the secret is never in a
    file of a wider mode, and an existing file of a wider mode is replaced, not reused.
    """
    raw = data.encode() if isinstance(data, str) else data
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        os.fchmod(fd, 0o600)
        with os.fdopen(fd, "wb") as f:
            f.write(raw)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def _openssl_key(path: Path) -> None:
    """A new EC P-256 private key in ``path`` (PEM, mode 0600): openssl prints it, we write it."""
    exe = shutil.which("openssl")
    if exe is None:
        raise CertError("the openssl command is not installed (apt-get install openssl)")
    proc = subprocess.run([exe, "genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256"],
                          capture_output=True)
    if proc.returncode != 0 or b"PRIVATE KEY" not in proc.stdout:
        raise CertError(f"openssl genpkey failed: {proc.stderr.decode(errors='replace').strip()}")
    _write_private(path, proc.stdout)


def _private_folder(out: Path) -> None:
    """Create ``out`` with mode 0700 (parents as needed); an existing one is left as it is, but a
    warning names it if others may list it."""
    if out.exists():
        if not out.is_dir():
            raise CertError(f"{out} exists and is not a folder")
        mode = out.stat().st_mode & 0o777
        if mode & 0o077:
            print(f"arena certs: warning: {out} has mode {mode:o}: other users may list it "
                  f"(chmod 700 {out})", file=sys.stderr)
        return
    out.parent.mkdir(parents=True, exist_ok=True)
    os.mkdir(out, 0o700)
    os.chmod(out, 0o700)  # mkdir's mode is masked by the umask; 0700 is the most it may be


def make_ca(out: Path, name: str = "arena lab CA", days: int = 3650) -> tuple[Path, Path]:
    """Create ``out/ca.pem`` and ``out/ca.key`` (self-signed CA, EC P-256, ``days`` valid)."""
    key, cert = out / "ca.key", out / "ca.pem"
    _openssl_key(key)
    _openssl("req", "-x509", "-new", "-key", str(key), "-out", str(cert), "-days", str(days), "-sha256",
             "-subj", f"/CN={name}",
             "-addext", "basicConstraints=critical,CA:TRUE",
             "-addext", "keyUsage=critical,keyCertSign,cRLSign",
             "-addext", "subjectKeyIdentifier=hash")
    os.chmod(cert, 0o644)  # public, but nobody else may replace it whatever the umask
    return cert, key


def make_host_cert(out: Path, host: HostSpec, days: int = 825, server_only: bool = False) -> tuple[Path, Path]:
    """Create ``out/<host>.pem`` and ``out/<host>.key`` signed by ``out/ca.pem``.

    The certificate serves both ends of a TLS link (extendedKeyUsage serverAuth and clientAuth):
    a router listens with it and a client presents it for mTLS. With ``server_only`` it has
    serverAuth alone: a router that only listens (the lab router) cannot be impersonated by a
    client holding its certificate, since TLS refuses it as a client certificate.
    """
    key, cert = out / f"{host.name}.key", out / f"{host.name}.pem"
    try:
        _make_host_cert(out, host, key, cert, days, server_only)
    except BaseException:   # no half-made host: a later run must not keep an empty or keyless .pem
        for f in (cert, key):
            f.unlink(missing_ok=True)
        raise
    os.chmod(cert, 0o644)
    return cert, key


def _make_host_cert(out: Path, host: HostSpec, key: Path, cert: Path, days: int, server_only: bool) -> None:
    _openssl_key(key)
    with tempfile.TemporaryDirectory(prefix="arena-certs-") as tmp:
        csr, ext = Path(tmp) / "host.csr", Path(tmp) / "host.ext"
        ext.write_text("basicConstraints=critical,CA:FALSE\n"
                       "keyUsage=critical,digitalSignature\n"
                       f"extendedKeyUsage={'serverAuth' if server_only else 'serverAuth,clientAuth'}\n"
                       f"subjectAltName={host.san()}\n"
                       "subjectKeyIdentifier=hash\n"
                       "authorityKeyIdentifier=keyid\n")
        _openssl("req", "-new", "-key", str(key), "-subj", f"/CN={host.name}", "-out", str(csr))
        _openssl("x509", "-req", "-in", str(csr), "-CA", str(out / "ca.pem"), "-CAkey", str(out / "ca.key"),
                 "-set_serial", str(secrets.randbits(63)), "-days", str(days), "-sha256",
                 "-extfile", str(ext), "-out", str(cert))


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
    _write_private(dictionary, "".join(f"{u}:{p}\n" for u, p in passwords.items()))
    for user, pwd in passwords.items():
        _write_private(out / f"{user}.env", f"ARENA_ZENOH_USER={user}\nARENA_ZENOH_PASSWORD={pwd}\n")
    return passwords


def make_lab_pki(out: Path, hosts: list[HostSpec], users: list[str], days: int = 825,
                 force: bool = False, server_only: tuple[str, ...] | list[str] = (),
                 remake_uses: bool = True) -> list[Path]:
    """Make (or complete) a lab's PKI in ``out`` (created with mode 0700); returns the files
    written. Hosts named in ``server_only`` get a serverAuth-only certificate.

    An existing host certificate is kept unless it names other addresses than ``hosts`` gives
    (its subjectAltName), or (with ``remake_uses``) has other uses than ``server_only`` asks
    for: then that host's certificate and key are made again, signed by the same CA, and one
    line on stderr says which host and why (its new files must go to that host)."""
    _private_folder(out)
    written: list[Path] = []
    have_pem, have_key = (out / "ca.pem").exists(), (out / "ca.key").exists()
    if have_pem != have_key and not force:
        have, lacks = ("ca.pem", "ca.key") if have_pem else ("ca.key", "ca.pem")
        raise CertError(f"{out} has {have} but not {lacks}: a new CA would leave every certificate the old one "
                        f"signed unverifiable. Copy {lacks} back (ca.key stays on the admin machine: run arena "
                        f"certs there), or --force to start a new CA (then every host needs a new certificate)")
    old_certs = {p for p in out.glob("*.pem") if p.name != "ca.pem"}
    new_ca = force or not have_pem
    if new_ca:
        written += make_ca(out)
    for host in hosts:
        cert = out / f"{host.name}.pem"
        make = force or not cert.exists() or cert.stat().st_size == 0 or not (out / f"{host.name}.key").exists()
        if not make:
            why = _differs(cert, host, (host.name in server_only) if remake_uses else None)
            if why:
                print(f"arena certs: {cert.name} {why}: making {host.name}.pem and {host.name}.key again "
                      f"(same CA; copy both to {host.name})", file=sys.stderr)
                make = True
        if make:
            written += make_host_cert(out, host, days, server_only=host.name in server_only)
    stale = sorted(p.name for p in old_certs - set(written)) if new_ca and have_pem else []
    if stale:
        print(f"arena certs: warning: {', '.join(stale)} were signed by the CA just replaced and no longer verify: "
              f"make them again (--hosts with those names, --force)", file=sys.stderr)
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
               "  arena certs pki --hosts router2=198.18.0.11      # a second router of a mesh (a client of router)\n"
               "  openssl x509 -in pki/camera.pem -noout -text   # inspect one\n"
               "Then see docs/deployment.md (which files go to which host).")
    p.add_argument("dir", metavar="DIR",
                   help="output folder (created; the existing CA is reused, and each host certificate that "
                        "still names the host's addresses)")
    p.add_argument("--hosts", required=True, metavar="NAME=ADDR[+ADDR],...",
                   help="hosts to certify: name (certificate CN) and IP addresses / DNS names")
    p.add_argument("--users", default=",".join(DEFAULT_USERS), metavar="USER,...",
                   help=f"roles given a password (default {','.join(DEFAULT_USERS)}); empty for none")
    p.add_argument("--days", type=int, default=825, help="host certificate validity in days (default 825)")
    p.add_argument("--server-only", default=None, metavar="NAME,...",
                   help="hosts whose certificate only serves TLS (cannot be presented as a client): the lab's "
                        "router, central in a mesh, which other routers connect to and which connects to none "
                        "(default: router; 'none' for no such host)")
    p.add_argument("--force", action="store_true", help="replace an existing CA, certificates and passwords")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """``arena certs`` entry point; returns the exit code."""
    try:
        if not 1 <= args.days <= 36500:
            raise CertError(f"--days must be 1-36500 (100 years), got {args.days}")
        hosts = parse_hosts(args.hosts)
        users = [u.strip() for u in args.users.split(",") if u.strip()]
        out = Path(args.dir)
        if args.server_only is None:   # the default: the lab router, if it is among the hosts
            server_only = ["router"]
        else:
            server_only = [n.strip() for n in args.server_only.split(",") if n.strip() and n.strip() != "none"]
            unknown = [n for n in server_only if n not in {h.name for h in hosts}]
            if unknown:
                raise CertError(f"--server-only: {', '.join(unknown)} not among --hosts "
                                f"({', '.join(h.name for h in hosts)})")
        # an existing certificate's uses change only when --server-only is given (not by its default)
        written = make_lab_pki(out, hosts, users, args.days, args.force, server_only,
                               remake_uses=args.server_only is not None)
    except (CertError, OSError) as exc:
        print(f"arena certs: {exc}", file=sys.stderr)
        return 2
    for path in written:
        print(path)
    if not written:
        print(f"nothing to do: every certificate already exists in {out} as asked (--force replaces them)")
    return 0

"""Zenoh session setup shared by every service and CLI command.

Settings come from, in increasing priority: built-in defaults, the lab config's ``[zenoh]`` table,
environment variables, and command-line flags (the same flags as the zenoh-python examples:
``-m/--mode``, ``-e/--connect``, ``-l/--listen``, ``-c/--config`` (alias ``--zenoh-config``) and
``--cfg KEY:VALUE``, any Zenoh setting as a JSON5 value, applied last).

Defaults: **client** mode connecting to a router on ``tcp/127.0.0.1:7447`` (start one with
``arena router``; ``arena demo`` starts its own), multicast scouting **off** (labs share networks;
nothing should join by accident), timestamping **on**. Every message then goes through a router,
which costs ~0.15 ms on loopback and makes behaviour the same on one machine and across many.
Peer mode (``-m peer``) is available on one machine: peers meet through the router by gossip and
then talk directly, but each peer also listens on every interface and the first queries of a
short-lived peer may wait for the gossip (seen: 0.5 s). Across machines always use client mode
towards the routers: in Zenoh 1.x a router does not relay between peers only connected to it.

Sessions must always be closed (a Python process with a callback subscriber hangs at exit
otherwise), so :func:`open_session` is a context manager.

Environment: ``ARENA_LAB`` (lab config path), ``ARENA_ZENOH_MODE``, ``ARENA_ZENOH_CONNECT`` and
``ARENA_ZENOH_LISTEN`` (comma-separated endpoints), ``ARENA_ZENOH_CONFIG`` (JSON5 file),
``ARENA_ZENOH_USER`` and ``ARENA_ZENOH_PASSWORD`` (user/password authentication; ``arena certs``
writes them per role, see ``docs/deployment.md``).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import re
import time
from collections.abc import Iterator
import dataclasses

import zenoh

from arena.config import (DEFAULT_ROUTER, LEASE_MS_RANGE, MODES, ConfigError, DefaultEndpoints, LabConfig,
                          ZenohSettings, dial_port_zero, load_lab_config)

log = logging.getLogger("arena.session")

__all__ = ["DEFAULT_ROUTER", "MODES", "SessionError", "ZenohSettings", "add_zenoh_arguments", "config_value",
           "lease_ms", "load_lab_from_args", "open_session", "own_endpoints", "parse_cfg", "resolve_settings",
           "to_zenoh_config"]


class SessionError(RuntimeError):
    """Zenoh could not be opened with the given settings; the message says what to check.

    ``exit_code`` is what a command exits with: 2 for settings that are wrong (a usage or input
    error: a bad mode, config file or endpoint), 1 for a runtime failure (no router answered)."""

    def __init__(self, message: str, exit_code: int = 2) -> None:
        super().__init__(message)
        self.exit_code = exit_code


def to_zenoh_config(settings: ZenohSettings) -> zenoh.Config:
    """Build the ``zenoh.Config`` for ``settings``; raise :class:`SessionError` (exit 2) naming a
    config file or setting Zenoh refuses. Also callable as ``settings.to_zenoh_config()``."""
    if settings.config_file:
        try:
            conf = zenoh.Config.from_file(settings.config_file)
        except Exception as exc:  # zenoh raises ZError with the parser's text
            raise SessionError(f"{settings.config_file}: not a usable Zenoh JSON5 config: {exc}") from None
    else:
        conf = zenoh.Config()

    def put(key: str, value) -> None:
        try:
            conf.insert_json5(key, json.dumps(value))
        except Exception as exc:
            raise SessionError(f"Zenoh setting {key}={value!r} was refused: {exc}") from None

    put("mode", settings.mode)
    if settings.connect and not (isinstance(settings.connect, DefaultEndpoints) and settings.config_file
                                 and own_endpoints(conf, settings.mode)):  # the file's own replace the default
        put("connect/endpoints", list(settings.connect))
    if settings.listen:
        put("listen/endpoints", list(settings.listen))
    put("scouting/multicast/enabled", bool(settings.multicast_scouting))
    put("timestamping/enabled", {"router": True, "peer": True, "client": True})
    # Senders on a host whose clock runs slightly ahead must not have their samples dropped.
    put("timestamping/drop_future_timestamp", False)
    if conf.get_json("connect/retry") in ("null", ""):
        # Reconnect to a restarted router within ~1 s (Zenoh's default backoff grows to 4 s).
        put("connect/retry", {"period_init_ms": 100, "period_max_ms": 1000, "period_increase_factor": 2})
    key = "transport/link/tx/queue/congestion_control/drop/wait_before_drop"
    if not settings.config_file or conf.get_json(key) == "1000":
        # Samples with congestion control DROP (event windows, tracks) wait up to 50 ms for
        # room in the transmit queue before being dropped, not Zenoh's 1 ms: on a busy 2-core
        # host the transmit task is often off the CPU that long, and windows were lost.
        put(key, DROP_WAIT_US)
    if settings.lease_ms:
        put("transport/link/tx/lease", int(settings.lease_ms))
        put("transport/link/tx/keep_alive", 4)
    for k, v in settings.tls.items():
        put(f"transport/link/tls/{k}", v)
    if settings.user is not None:
        put("transport/auth/usrpwd/user", settings.user)
        put("transport/auth/usrpwd/password", settings.password or "")
    for item in settings.cfg:
        key, value = parse_cfg(item)
        try:
            conf.insert_json5(key, value)
        except Exception as exc:  # zenoh.ZError: an unknown key or a value that is not JSON5
            raise SessionError(f"--cfg {item!r} was refused: {_cfg_refusal(str(exc))}") from None
    return conf


# The method form, for code holding settings: arena.config defines the dataclass without Zenoh
# (its pure-core contract forbids importing it), so the Zenoh half is attached here.
ZenohSettings.to_zenoh_config = to_zenoh_config  # type: ignore[attr-defined]


def config_value(conf: zenoh.Config, path: str):
    """The value at ``path`` of ``conf`` (None when unset)."""
    try:
        return json.loads(conf.get_json(path))
    except Exception:  # an unset path
        return None


def own_endpoints(conf: zenoh.Config, mode: str, key: str = "connect") -> list[str]:
    """``conf``'s own ``connect`` (or ``listen``) endpoints for ``mode`` (a Zenoh config may give
    them per mode), as strings; empty when it gives none."""
    eps = config_value(conf, f"{key}/endpoints") or []
    if isinstance(eps, dict):
        eps = eps.get(mode) or []
    return [str(e) for e in eps] if isinstance(eps, list) else []


def _credentials(settings: ZenohSettings) -> str:
    """The credentials ``settings`` present, for an error message (never the password): the user
    of user/password authentication and the TLS files, or "" when none is configured."""
    try:
        conf = to_zenoh_config(settings)
    except SessionError:
        return ""
    parts = []
    user = settings.user or config_value(conf, "transport/auth/usrpwd/user")
    if user:
        parts.append(f"user {user!r} and its password (user/password authentication; the password is not shown)")
    tls = {k: config_value(conf, f"transport/link/tls/{k}") for k in ("root_ca_certificate", "connect_certificate",
                                                                 "enable_mtls")}
    if any(e.startswith(("tls/", "quic/")) for e in own_endpoints(conf, settings.mode)):
        files = [f"CA {tls['root_ca_certificate']}" if tls["root_ca_certificate"] else "",
                 f"certificate {tls['connect_certificate']}" if tls["enable_mtls"] and tls["connect_certificate"]
                 else ""]
        parts.append("TLS (" + (", ".join(f for f in files if f) or "no CA or certificate set") + ": the router's "
                     "certificate must be of that CA and name the address dialled; with mTLS this host's must be "
                     "of the router's CA and have clientAuth)")
    return "; ".join(parts)


def parse_cfg(item: str) -> tuple[str, str]:
    """Split a ``--cfg KEY:VALUE`` setting at its first colon (values may hold colons, as
    endpoints do); raise :class:`SessionError` (exit 2) naming it when it has no key or value."""
    key, sep, value = item.partition(":")
    if not sep or not key.strip() or not value.strip():
        raise SessionError(f"--cfg {item!r}: expected KEY:VALUE, a Zenoh config path and a JSON5 value, "
                           "e.g. --cfg 'scouting/multicast/enabled:false'")
    return key.strip(), value.strip()


def _cfg_refusal(text: str) -> str:
    """Zenoh's reason for refusing a ``--cfg`` setting, in one line, with what to do."""
    if "unknown key" in text:
        return "unknown key; KEY is a path in Zenoh's config, e.g. transport/unicast/max_links"
    m = re.search(r'msg: "(.*?)", location', text)
    why = m.group(1).split("= ")[-1].strip() if m else text.split(" at ")[0]
    return f"{why}; VALUE is JSON5 (a string needs quotes: --cfg 'mode:\"peer\"')"


#: how long a DROP sample waits for room in a full transmit queue, µs (Zenoh's default: 1000)
DROP_WAIT_US = 50_000


#: where a Zenoh error names the Rust source line it came from (" at /root/.cargo/...rs:777.")
_RUST_WHERE = re.compile(r"\s+at\s+\S+\.rs:\d+\.?\s*$")


def check_key_expressions(keys, what: str = "--keys") -> list[str]:
    """Each of ``keys`` as a Zenoh key expression (checked before anything is opened or written);
    :class:`~arena.keys.InvalidKey` naming the first that is not one and why, in Zenoh's words
    without the Rust source path it appends."""
    from arena.keys import InvalidKey

    out = []
    for k in keys:
        try:
            out.append(str(zenoh.KeyExpr(str(k))))
        except zenoh.ZError as exc:
            why = _RUST_WHERE.sub("", str(exc))
            why = why.split(": ", 1)[1] if why.startswith("Invalid Key Expr") and ": " in why else why
            raise InvalidKey(f"{what} {str(k)!r} is not a Zenoh key expression: {why} "
                             "(e.g. arena/robots/* or arena/**)") from None
    return out


def add_zenoh_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the shared Zenoh and lab-config flags to ``parser``."""
    g = parser.add_argument_group("Zenoh and lab config")
    g.add_argument("--lab", metavar="TOML", default=None,
                   help="lab config shared by every host (env ARENA_LAB); gives cameras, robots, endpoints")
    g.add_argument("-m", "--mode", choices=MODES, default=None,
                   help="Zenoh session mode (default client, towards the router given by --connect)")
    g.add_argument("-e", "--connect", metavar="ENDPOINT", action="append", default=None,
                   help=f"endpoint to connect to, repeatable (default {DEFAULT_ROUTER})")
    g.add_argument("-l", "--listen", metavar="ENDPOINT", action="append", default=None,
                   help="endpoint to listen on, repeatable (e.g. tcp/0.0.0.0:7447)")
    g.add_argument("-c", "--config", "--zenoh-config", dest="zenoh_config", metavar="JSON5", default=None,
                   help="Zenoh config file for anything else: TLS, user/password, access control")
    g.add_argument("--cfg", metavar="KEY:VALUE", action="append", default=None,
                   help="any Zenoh setting, repeatable, applied last: a config path and a JSON5 value, "
                        "e.g. --cfg 'transport/unicast/max_links:2'")
    g.add_argument("--multicast-scouting", action="store_true", default=None,
                   help="enable multicast scouting (off by default)")
    g.add_argument("--lease-ms", type=lease_ms, default=None,
                   help=f"link lease, ms ({LEASE_MS_RANGE[0]}-{LEASE_MS_RANGE[1]}): a dead peer is noticed "
                        "after this long (Zenoh default 10000)")


def lease_ms(text: str) -> int:
    """The argparse ``type`` of ``--lease-ms``: an integer in :data:`arena.config.LEASE_MS_RANGE`,
    the bounds the lab config's ``lease_ms`` has."""
    lo, hi = LEASE_MS_RANGE
    try:
        v = int(text)
    except ValueError:
        v = None
    if v is None or not lo <= v <= hi:
        raise argparse.ArgumentTypeError(f"expected a lease in milliseconds, an integer in [{lo}, {hi}], got {text!r}")
    return v


def _split(value: str | None) -> list[str] | None:
    if value is None:
        return None
    return [s.strip() for s in value.split(",") if s.strip()]


def load_lab_from_args(args: argparse.Namespace | None) -> LabConfig | None:
    """The lab config named by ``--lab`` or ``ARENA_LAB`` (None if neither is set)."""
    path = getattr(args, "lab", None) if args is not None else None
    path = path or os.environ.get("ARENA_LAB")
    if not path:
        return None
    return load_lab_config(path)


def resolve_settings(args: argparse.Namespace | None = None, lab: LabConfig | None = None) -> ZenohSettings:
    """Merge defaults, the lab config, the environment and ``args`` into :class:`ZenohSettings`."""
    s = ZenohSettings()
    if lab is not None:  # a copy: the lab's own settings are not changed below
        z = lab.zenoh
        s = dataclasses.replace(z, connect=type(z.connect)(z.connect), listen=list(z.listen), tls=dict(z.tls),
                                cfg=list(z.cfg))
    env = os.environ
    if env.get("ARENA_ZENOH_MODE"):
        s.mode = env["ARENA_ZENOH_MODE"]
    if env.get("ARENA_ZENOH_CONNECT") is not None:
        s.connect = _split(env["ARENA_ZENOH_CONNECT"]) or []
    if env.get("ARENA_ZENOH_LISTEN") is not None:
        s.listen = _split(env["ARENA_ZENOH_LISTEN"]) or []
    if env.get("ARENA_ZENOH_CONFIG"):
        s.config_file = env["ARENA_ZENOH_CONFIG"]
    user, password = env.get("ARENA_ZENOH_USER"), env.get("ARENA_ZENOH_PASSWORD")
    if bool(user) != bool(password):   # one without the other: a half-written env file
        have, missing = ("ARENA_ZENOH_USER", "ARENA_ZENOH_PASSWORD") if user else ("ARENA_ZENOH_PASSWORD",
                                                                                "ARENA_ZENOH_USER")
        raise SessionError(f"{have} is set but {missing} is not: the two go together (user/password "
                           f"authentication; `arena certs` writes both per role); set both or neither")
    if user:  # per-role credentials (systemd EnvironmentFile, `arena certs`)
        s.user, s.password = user, password
    if args is not None:
        if getattr(args, "mode", None):
            s.mode = args.mode
        if getattr(args, "connect", None) is not None:
            s.connect = list(args.connect)
        if getattr(args, "listen", None) is not None:
            s.listen = list(args.listen)
        if getattr(args, "zenoh_config", None):
            s.config_file = args.zenoh_config
        if getattr(args, "multicast_scouting", None):
            s.multicast_scouting = True
        if getattr(args, "lease_ms", None):
            s.lease_ms = args.lease_ms
        if getattr(args, "cfg", None):
            s.cfg = list(args.cfg)
            for item in s.cfg:
                parse_cfg(item)  # a malformed one is named now, before anything is opened
    if s.mode not in MODES:
        raise SessionError(f"Zenoh mode {s.mode!r} is not one of {', '.join(MODES)}")
    if isinstance(s.connect, DefaultEndpoints) and s.config_file:
        # nobody gave connect endpoints: the Zenoh config file's own (-c FILE) replace the default
        own = own_endpoints(to_zenoh_config(dataclasses.replace(s, connect=[])), s.mode)
        if own:
            s.connect = own
    zero = [e for e in s.connect if dial_port_zero(e)]
    if zero:
        raise SessionError(f"connect endpoint {zero[0]}: port 0 cannot be dialled; give the port the router "
                           f"listens on (e.g. {DEFAULT_ROUTER})")
    return s


@contextlib.contextmanager
def open_session(args: argparse.Namespace | ZenohSettings | None = None, lab: LabConfig | None = None,
                 wait_s: float | None = 0.0) -> Iterator[zenoh.Session]:
    """Open a Zenoh session and always close it.

    ``args`` is an argparse namespace with the flags of :func:`add_zenoh_arguments` (or ready
    :class:`ZenohSettings`). A client needs its router at start: with ``wait_s`` > 0 (or None for
    forever) the router is waited for with backoff, logging what is awaited, so services can start
    in any order.
    """
    if isinstance(args, ZenohSettings):
        settings = args
    else:
        try:
            lab = lab if lab is not None else load_lab_from_args(args)
        except ConfigError as exc:
            raise SessionError(str(exc)) from None
        settings = resolve_settings(args, lab)
    conf = settings.to_zenoh_config()
    deadline = None if wait_s is None else time.monotonic() + wait_s
    delay = 0.1
    while True:
        try:
            session = zenoh.open(conf)
            break
        except Exception as exc:  # zenoh.ZError
            if deadline is not None and time.monotonic() >= deadline:
                creds = _credentials(settings)
                raise SessionError(
                    f"cannot open Zenoh ({settings.describe()}): {str(exc).split(' at ')[0].rstrip(' !.')}. "
                    "Is a router running there (`arena router`)? "
                    + (f"If one is, it may refuse this host's credentials: {creds}. " if creds else "")
                    + "Check --connect/--mode or the lab config.",
                    exit_code=1) from None
            log.warning("waiting for Zenoh (%s): %s", settings.describe(), str(exc).split(" at ")[0])
            time.sleep(delay)
            delay = min(delay * 2, 2.0)
            conf = settings.to_zenoh_config()  # a Config is consumed by open()
    try:
        yield session
    finally:
        session.close()

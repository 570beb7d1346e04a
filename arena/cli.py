"""The ``arena`` command: one subcommand per service plus lab tools.

Built-in subcommands: ``router``, ``status``, ``watch``. Service subcommands (``sim``, ``edge``,
``track``, ``bridge``, ...) are registered by their packages through the ``arena.commands`` entry
point group, python-can style: each entry is a function ``register(subparsers)``.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import signal
import sys
import threading
import time
from importlib.metadata import entry_points
from typing import TYPE_CHECKING

from arena import __version__
from arena.clitools import exit_on_session_error, fail, formatter, seconds, session_or_exit
from arena.config import LEASE_MS_RANGE
from arena.session import SessionError, add_zenoh_arguments, lease_ms

# The parser is built for every command (`arena track` too): what only `status` and `watch` use
# (the message codec, msgpack, the key space) is imported when they run.
if TYPE_CHECKING:
    from arena.messages import Message

log = logging.getLogger("arena")

EPILOG = """\
Start here:
  arena demo                       the whole lab on the built-in simulated arena
  arena router                     a Zenoh router on tcp/127.0.0.1:7447 (the stand-in for zenohd)
  arena status                     which services are alive and how they are doing
  arena watch 'arena/robots/*'     print the tracks as they arrive
Each command has --help with examples."""


# --------------------------------------------------------------------------------------------
# arena router
# --------------------------------------------------------------------------------------------
def _register_router(sub) -> None:
    p = sub.add_parser(
        "router", help="run a Zenoh router (stand-in for zenohd)", formatter_class=formatter,
        description="Run a Zenoh session in router mode: it routes between clients and peers on\n"
                    "several hosts, liveliness, queries, TLS, user/password and access control.\n"
                    "(zenohd is not pip-installable; its plugins (REST, storage) do not load here.)",
        epilog="Examples:\n"
               "  arena router                                  # tcp/127.0.0.1:7447\n"
               "  arena router -l tcp/0.0.0.0:7447              # reachable from other hosts\n"
               "  arena router -l tls/0.0.0.0:7447 --zenoh-config deploy/router.json5\n"
               "  arena router -e tcp/198.18.0.2:7447           # mesh with another router\n\n"
               "A router that dials another one (-e, or connect in its --zenoh-config) proves itself\n"
               "with ARENA_ZENOH_USER / ARENA_ZENOH_PASSWORD from the environment (router.env of\n"
               "`arena certs`, a systemd EnvironmentFile), so no password is written in its config.")
    p.add_argument("-l", "--listen", metavar="ENDPOINT", action="append", default=None,
                   help="endpoint to listen on, repeatable (default: the --zenoh-config file's, else tcp/127.0.0.1:7447)")
    p.add_argument("-e", "--connect", metavar="ENDPOINT", action="append", default=None,
                   help="other routers to connect to (mesh), repeatable")
    p.add_argument("--zenoh-config", metavar="JSON5", default=None,
                   help="Zenoh config for TLS, user/password and access control (see deploy/)")
    p.add_argument("--lease-ms", type=lease_ms, default=None,
                   help=f"link lease in ms, {LEASE_MS_RANGE[0]}-{LEASE_MS_RANGE[1]} (Zenoh default 10000)")
    p.add_argument("--name", default=None,
                   help="name in arena status (default: <hostname>-<port of the first listen endpoint>)")
    p.add_argument("--duration", type=float, default=None, help=argparse.SUPPRESS)
    p.set_defaults(func=_run_router)


def _run_router(args) -> int:
    from arena.service import Service, stop_on_signals, wait_until_stopped
    from arena.session import ZenohSettings

    # Without -l, a --zenoh-config file's own listen endpoints are kept (e.g. deploy/zenoh/router.json5).
    listen = list(args.listen or ([] if args.zenoh_config else ["tcp/127.0.0.1:7447"]))
    settings = ZenohSettings(mode="router", connect=list(args.connect or []), listen=listen,
                             config_file=args.zenoh_config, lease_ms=args.lease_ms)
    # the credentials it dials other routers with (router.env): both or neither
    user, password = os.environ.get("ARENA_ZENOH_USER"), os.environ.get("ARENA_ZENOH_PASSWORD")
    if bool(user) != bool(password):
        raise fail(f"arena router: ARENA_ZENOH_USER and ARENA_ZENOH_PASSWORD go together, but only "
                   f"{'ARENA_ZENOH_USER' if user else 'ARENA_ZENOH_PASSWORD'} is set: set both (router.env of "
                   "`arena certs` has both) or neither")
    if user:
        settings.user, settings.password = user, password
    with exit_on_session_error("arena router"):
        problem = _dial_certificate_problem(settings)
    if problem:
        raise fail(f"arena router: {problem}")
    if not settings.listen:
        settings.listen = json.loads(settings.to_zenoh_config().get_json("listen/endpoints") or "[]")
        if isinstance(settings.listen, dict):  # per-mode values
            settings.listen = settings.listen.get("router") or []
    if not settings.connect and args.zenoh_config:  # the file's own, so that the line below names them
        from arena.session import own_endpoints

        settings.connect = own_endpoints(settings.to_zenoh_config(), "router")
    import re
    import socket

    port = (re.findall(r":(\d+)$", settings.listen[0]) or ["0"])[0] if settings.listen else "0"
    name = args.name or re.sub(r"[^A-Za-z0-9_.-]", "-", f"{socket.gethostname()}-{port}")[:64]
    stop = stop_on_signals()
    try:
        with session_or_exit(settings, "arena router") as session, Service(session, "router", name):
            # Zenoh opens a router whether or not the routers it dials answer, and keeps retrying
            # them: claim no connection here; the transport events below say when one is made
            print(f"arena router {session.zid()} listening on {', '.join(settings.listen)}"
                  + (f"; dialing {', '.join(settings.connect)} (retried until it answers)" if settings.connect
                     else ""), flush=True)
            links = session.info.declare_transport_events_listener(_router_links_printer(session), history=True)
            try:
                wait_until_stopped(stop, args.duration)
            finally:
                links.undeclare()
    except KeyboardInterrupt:
        pass
    return 0


def _dial_certificate_problem(settings) -> str | None:
    """Why the router of ``settings`` cannot dial its TLS/QUIC endpoints with mTLS, or None: the
    certificate it presents (``transport/link/tls/connect_certificate``) lacks clientAuth in its
    extendedKeyUsage (`arena certs` makes the host ``router`` serverAuth-only by default), so the
    router dialled refuses it as a client certificate and Zenoh retries forever without a word."""
    from pathlib import Path

    from arena.certs import CertError, allows_client_auth, read_certificate
    from arena.session import config_value, own_endpoints

    conf = settings.to_zenoh_config()

    def get(path: str):
        return config_value(conf, path)

    dialled = [e for e in own_endpoints(conf, "router") if e.startswith(("tls/", "quic/"))]
    cert = get("transport/link/tls/connect_certificate")
    if not dialled or not get("transport/link/tls/enable_mtls") or not isinstance(cert, str) or not cert:
        return None
    try:
        info = read_certificate(Path(cert).read_bytes())
    except (OSError, CertError):  # Zenoh says what is wrong with an unreadable certificate itself
        return None
    if allows_client_auth(info):
        return None
    host = Path(cert).stem
    return (f"it dials {', '.join(dialled)} with mTLS presenting {cert} (transport/link/tls/connect_certificate), "
            f"whose extendedKeyUsage is {'+'.join(sorted(info.uses or ()))} without clientAuth: the router it "
            f"dials refuses it as a client certificate, and this one would retry forever. Make that certificate "
            f"with clientAuth: `arena certs PKI --hosts {host}=ADDR --server-only none` (or --server-only naming "
            f"only the routers that dial none), or present another host certificate that has clientAuth")


def _router_links_printer(session):
    """A Zenoh transport-events callback printing one line when a router is connected or lost
    (``arena router: connected to router ZID (ENDPOINT)``): what happened, as Zenoh reports it."""
    import zenoh

    seen: dict[str, str] = {}

    def on_event(event) -> None:
        t = event.transport
        if t.whatami != zenoh.WhatAmI.ROUTER:
            return
        zid = str(t.zid)
        if event.kind == zenoh.SampleKind.PUT:
            seen[zid] = ", ".join(str(link.dst) for link in session.info.links() if str(link.zid) == zid)
            print(f"arena router: connected to router {zid}" + (f" ({seen[zid]})" if seen[zid] else ""), flush=True)
        else:
            where = seen.pop(zid, "")
            print(f"arena router: lost router {zid}" + (f" ({where})" if where else "")
                  + "; Zenoh retries the routers it dials", flush=True)
    return on_event


# --------------------------------------------------------------------------------------------
# arena status
# --------------------------------------------------------------------------------------------
def _register_status(sub) -> None:
    p = sub.add_parser(
        "status", help="which services are alive, and their last status", formatter_class=formatter,
        description="List the services that are alive (liveliness tokens arena/alive/**) with their\n"
                    "last status line (arena/status/**): rates, drops, errors, latency.",
        epilog="Examples:\n"
               "  arena status\n"
               "  arena status --json\n"
               "  arena status -e tcp/198.18.0.1:7447 -m client   # a lab's router from another host")
    p.add_argument("--wait", type=seconds(0.0, 600.0, lo_open=False), default=1.5,
                   help="seconds to collect status messages, 0-600 (default 1.5)")
    p.add_argument("--json", action="store_true", help="machine-readable output (one JSON document)")
    add_zenoh_arguments(p)
    p.set_defaults(func=_run_status)


def _fmt_rate(v: float) -> str:
    if v >= 1e6:
        return f"{v / 1e6:.1f}M"
    if v >= 1e3:
        return f"{v / 1e3:.1f}k"
    return f"{v:.0f}" if v == int(v) else f"{v:.1f}"


def _run_status(args) -> int:
    from arena.keys import ALL_ALIVE, ALL_STATUS, InvalidKey, parse_key
    from arena.messages import MessageError, decode

    statuses: dict[tuple[str, str], dict] = {}
    alive: set[tuple[str, str]] = set()
    lock = threading.Lock()

    def on_status(sample) -> None:
        try:
            st = decode(bytes(sample.payload))
        except MessageError:
            return
        with lock:
            statuses[(st.role, st.name)] = st.to_dict()

    with session_or_exit(args, "arena status") as session:
        sub = session.declare_subscriber(ALL_STATUS, on_status)
        for reply in session.liveliness().get(ALL_ALIVE, timeout=2.0):
            if reply.ok is not None:
                try:
                    key = parse_key(str(reply.ok.key_expr))
                except InvalidKey:   # not a service's token (someone else's key under arena/alive)
                    continue
                if key.kind == "alive":
                    alive.add((key.parts["role"], key.parts["name"]))
        time.sleep(max(0.0, args.wait))
        sub.undeclare()
    with lock:
        keys = sorted(alive | set(statuses))
        rows = []
        for k in keys:
            st = statuses.get(k, {})
            rows.append({"role": k[0], "name": k[1], "alive": k in alive, **{kk: st.get(kk) for kk in
                         ("host", "pid", "state", "uptime_s", "counters", "rates", "gauges", "errors", "last_error")}})
    if args.json:
        print(json.dumps(rows, indent=2, default=str))
        return 0
    if not rows:
        print("no arena service is alive (is a router running and are you connected to it?)")
        return 1
    header = f"{'ROLE':<12} {'NAME':<16} {'ALIVE':<5} {'STATE':<9} {'HOST':<14} {'UP':>7}  {'ERR':>4}  RATES / GAUGES"
    print(header)
    for r in rows:
        rates = " ".join(f"{k}={_fmt_rate(v)}/s" for k, v in sorted((r["rates"] or {}).items()) if v)
        gauges = " ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}"
                          for k, v in sorted((r["gauges"] or {}).items()))
        up = f"{r['uptime_s']:.0f}s" if r["uptime_s"] is not None else "-"
        print(f"{r['role']:<12} {r['name']:<16} {'yes' if r['alive'] else 'NO':<5} {r['state'] or '-':<9} "
              f"{(r['host'] or '-')[:14]:<14} {up:>7}  {r['errors'] if r['errors'] is not None else '-':>4}  "
              f"{(rates + ' ' + gauges).strip()}")
        if r["last_error"]:
            print(f"{'':<12}   last error: {r['last_error']}")
    return 0


# --------------------------------------------------------------------------------------------
# arena watch
# --------------------------------------------------------------------------------------------
def _register_watch(sub) -> None:
    p = sub.add_parser(
        "watch", help="decode and print arena messages on a key expression", formatter_class=formatter,
        description="Subscribe to KEYEXPR and print every arena message decoded, one per line.\n"
                    "Event windows are summarised (their compressed bytes are not printed).",
        epilog="Examples:\n"
               "  arena watch 'arena/robots/*'\n"
               "  arena watch 'arena/telemetry/zumo1' --json\n"
               "  arena watch 'arena/**' --count 20")
    p.add_argument("keyexpr", nargs="?", default="arena/**", help="Zenoh key expression (default arena/**)")
    p.add_argument("--json", action="store_true", help="print one JSON object per line")
    p.add_argument("--count", type=int, default=None, help="stop after this many messages")
    p.add_argument("--duration", type=float, default=None, help="stop after this many seconds")
    p.add_argument("--notice-after", type=float, default=5.0, metavar="S",
                   help="with TLS or user/password (a lab router with an access-control list, which drops "
                        "a subscription it does not allow without telling the client), say so on stderr "
                        "if nothing arrived within S seconds (default 5; 0: never)")
    add_zenoh_arguments(p)
    p.set_defaults(func=_run_watch)


def _jsonable(msg: Message) -> dict:
    from arena.messages import EventWindow

    d = {"kind": msg.KIND, **msg.to_dict()}
    if isinstance(msg, EventWindow):
        d["data"] = f"<{len(msg.data)} bytes>"
    for k, v in list(d.items()):
        if isinstance(v, float) and not math.isfinite(v):
            d[k] = None
        elif isinstance(v, tuple):
            d[k] = list(v)
    return d


def _line(key: str, msg: Message) -> str:
    d = _jsonable(msg)
    d.pop("kind")
    parts = []
    for k, v in d.items():
        if v is None or v == {} or v == "":
            continue
        if isinstance(v, float):
            v = f"{v:.4g}"
        parts.append(f"{k}={v}")
    return f"{key} {msg.KIND}: " + " ".join(parts)


def _secured(settings) -> bool:
    """Whether ``settings`` (resolved Zenoh settings) log in with a user or over TLS/QUIC: then a
    lab router's access-control list may silently drop what is not allowed."""
    from arena.session import config_value

    conf = settings.to_zenoh_config()

    def get(path: str):
        return config_value(conf, path)

    connect = get("connect/endpoints") or []
    if isinstance(connect, dict):  # per-mode values
        connect = [e for v in connect.values() for e in (v or [])]
    return bool(settings.user or get("transport/auth/usrpwd/user")
                or any(str(e).startswith(("tls/", "quic/")) for e in connect))


def watch_notice(keyexpr: str, seconds: float) -> str:
    """The line ``arena watch`` prints when nothing arrived under an access-control list."""
    return (f"arena watch: nothing received on {keyexpr} in {seconds:g} s; under an access-control list, "
            "subscribe to a prefix your user may read, e.g. arena/robots/*")


def _run_watch(args) -> int:
    from arena.config import ConfigError
    from arena.messages import MessageError, decode
    from arena.service import stop_on_signals, wait_until_stopped
    from arena.session import load_lab_from_args, resolve_settings

    if args.notice_after < 0:
        print("arena watch: --notice-after must be >= 0", file=sys.stderr)
        return 2
    from arena.keys import InvalidKey
    from arena.session import check_key_expressions
    try:
        check_key_expressions([args.keyexpr], "key expression")
    except InvalidKey as exc:
        print(f"arena watch: {exc}", file=sys.stderr)
        return 2
    try:
        with exit_on_session_error("arena watch"):
            settings = resolve_settings(args, load_lab_from_args(args))
    except ConfigError as exc:
        print(f"arena watch: {exc}", file=sys.stderr)
        return 2
    stop = stop_on_signals()
    n = 0
    lock = threading.Lock()

    def on_sample(sample) -> None:
        nonlocal n
        key = str(sample.key_expr)
        payload = bytes(sample.payload)
        try:
            msg = decode(payload)
            out = json.dumps({"key": key, **_jsonable(msg)}, default=str) if args.json else _line(key, msg)
        except MessageError as exc:
            out = (json.dumps({"key": key, "error": str(exc), "bytes": len(payload)}) if args.json
                   else f"{key} <not an arena message, {len(payload)} bytes: {exc}>")
        with lock:
            if args.count is not None and n >= args.count:
                return
            n += 1
            print(out, flush=True)
            if args.count is not None and n >= args.count:
                stop.set()

    def notice() -> None:
        # Zenoh gives a client no sign that a router denied its subscription: say so when silent
        with lock:
            if n == 0 and not stop.is_set():
                print(watch_notice(args.keyexpr, args.notice_after), file=sys.stderr, flush=True)

    timer = None
    try:
        with session_or_exit(settings, "arena watch") as session:
            session.declare_subscriber(args.keyexpr, on_sample)
            if args.notice_after > 0 and _secured(settings):
                timer = threading.Timer(args.notice_after, notice)
                timer.daemon = True
                timer.start()
            wait_until_stopped(stop, args.duration)
    except KeyboardInterrupt:
        pass
    except Exception as exc:  # an invalid key expression is reported by zenoh as ZError
        print(f"arena watch: {exc}", file=sys.stderr)
        return 2
    finally:
        if timer is not None:
            timer.cancel()
    return 0


# --------------------------------------------------------------------------------------------
#: the subcommands arena.cli defines itself (no entry point)
_BUILTIN_COMMANDS = ("router", "status", "watch")


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``arena`` parser with the built-in and every registered service subcommand.

    With ``command`` (the subcommand about to run, :func:`_command_of`), only that command's
    entry point is loaded (none for a built-in one): loading every service's ``register``
    costs ~0.1 s of CPU at each start (2-core VM at load ~8; issue 22). A name no entry
    point has loads them all, so that argparse lists every choice in its error."""
    parser = argparse.ArgumentParser(
        prog="arena", formatter_class=formatter,
        description="Fleet tracking of ground robots with a ceiling event camera, over Zenoh.",
        epilog=EPILOG)
    parser.add_argument("--version", action="version", version=f"arena {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-vv for debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    _register_router(sub)
    _register_status(sub)
    _register_watch(sub)
    eps = sorted(entry_points(group="arena.commands"), key=lambda e: e.name)
    if command is not None:
        named = [ep for ep in eps if ep.name == command]
        if named or command in _BUILTIN_COMMANDS:
            eps = named
    for ep in eps:
        try:
            register = ep.load()
        except ImportError as exc:  # a package it needs is missing: keep it listed, say what to install
            _register_unavailable(sub, ep.name, exc)
            continue
        register(sub)
    return parser


#: pip names of the modules whose distribution is named otherwise (for the install hint)
_PIP_NAMES = {"cv2": "opencv-python-headless", "zenoh": "eclipse-zenoh", "serial": "pyserial", "usb": "pyusb",
              "sklearn": "scikit-learn", "yaml": "PyYAML", "dv_processing": "dv-processing"}


def missing_package_hint(exc: ImportError) -> str:
    """``needs the Python package X, which is not installed: pip install X`` for an ImportError."""
    module = (exc.name or str(exc)).split(".")[0]
    pip_name = _PIP_NAMES.get(module, module)
    return (f"needs the Python package {pip_name!r} (module {module!r}), which is not installed: "
            f"pip install {pip_name}   (or reinstall arena: pip install -e . in its checkout)")


def _register_unavailable(sub, name: str, exc: ImportError) -> None:
    """List command ``name`` whose import failed; calling it prints one line and exits 2."""
    hint = missing_package_hint(exc)
    module = (exc.name or str(exc)).split(".")[0]
    # no option prefix: every argument, --help included, reaches the one-line message
    p = sub.add_parser(name, help=f"(not available: pip install {_PIP_NAMES.get(module, module)})",
                       add_help=False, prefix_chars="\0", description=f"arena {name} {hint}")
    p.add_argument("rest", nargs="*", help=argparse.SUPPRESS)

    def unavailable(args) -> int:
        print(f"arena {name}: {hint}", file=sys.stderr)
        return 2
    p.set_defaults(func=unavailable)


def _command_of(argv: list[str]) -> str | None:
    """The subcommand of ``arena ARGV``: its first argument that is not an option (the top-level
    options take no value), or None (``arena``, ``arena --help``, ``arena --version``)."""
    for arg in argv:
        if arg == "--":
            return None
        if not arg.startswith("-"):
            return arg
    return None


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``arena`` console command."""
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(_command_of(argv))
    args = parser.parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="%(asctime)s %(name)s %(levelname)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt as exc:
        # SIGTERM (a launcher, systemd) is a normal stop: exit 0; Ctrl-C keeps the shell's 130
        return 0 if exc.args == (f"signal {int(signal.SIGTERM)}",) else 130
    except SessionError as exc:
        print(f"arena {args.command}: {exc}", file=sys.stderr)
        return exc.exit_code
    except ImportError as exc:
        # a package a command imports only when it runs (lazily, for a fast start) is missing
        if not exc.name or exc.name.split(".")[0] in _OWN_PACKAGES:
            raise
        print(f"arena {args.command}: {missing_package_hint(exc)}", file=sys.stderr)
        return 2


#: the project's own top-level packages: an ImportError of one of them is a bug, not a missing install
_OWN_PACKAGES = {"arena", "camera_edge", "tracker", "robot_bridge", "groundtruth", "simulator", "demo", "viewer",
                 "recorder", "ros2"}


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

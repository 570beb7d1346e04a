"""The `arena` CLI as a user runs it: real subprocesses against a real router."""

import json
import os
import subprocess
import sys
import textwrap
import time
from importlib.metadata import entry_points

import pytest

from arena import __version__
from tests.conftest import arena_cmd, free_port, wait_for_line

SERVICE = textwrap.dedent("""
    import sys, time
    from arena.messages import Telemetry
    from arena.service import Service
    from arena.session import ZenohSettings, open_session
    with open_session(ZenohSettings(connect=[sys.argv[1]])) as s, Service(s, "bridge", "lab-a", period_s=0.2) as svc:
        print("ready", flush=True)
        for i in range(600):
            svc.count("telemetry", 10)
            svc.gauge("rtt_ms", 4.5)
            s.put("arena/telemetry/zumo1", Telemetry(robot="zumo1", seq=i, robot_time_us=i, host_time_ns=1,
                                                     enc_left=i, enc_right=-i).encode())
            time.sleep(0.05)
""")


@pytest.fixture
def service(router):
    proc = subprocess.Popen([sys.executable, "-c", SERVICE, router.endpoint], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "ready"
    yield proc
    proc.kill()
    proc.wait(timeout=5)


def run(*args, timeout=30):
    return subprocess.run(arena_cmd(*args), capture_output=True, text=True, timeout=timeout)


def test_version_and_help():
    assert run("--version").stdout.strip() == f"arena {__version__}"
    out = run("--help").stdout
    for cmd in ("router", "status", "watch"):
        assert cmd in out
    for cmd in ("router", "status", "watch"):
        h = run(cmd, "--help")
        assert h.returncode == 0 and "Examples:" in h.stdout


def test_every_registered_command_loads_and_has_help():
    """No placeholder commands: every entry point in pyproject.toml must import and give --help."""
    names = [ep.name for ep in entry_points(group="arena.commands")]
    for ep in entry_points(group="arena.commands"):
        ep.load()  # raises if a declared command's module is missing
    for name in names:
        h = run(name, "--help")
        assert h.returncode == 0, (name, h.stderr)
        assert "usage: arena " + name in h.stdout


def _example_commands():
    """Every ``arena ...`` example line in every command's --help (joined over trailing
    backslashes, cut at the comment or the column of prose after two spaces)."""
    import argparse
    import re
    import shlex

    from arena.cli import build_parser

    def walk(parser, prefix):
        yield prefix, parser
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sp in action.choices.items():
                    yield from walk(sp, prefix + [name])

    top = build_parser()
    commands = set(next(a for a in top._actions if isinstance(a, argparse._SubParsersAction)).choices)
    for prefix, parser in walk(top, []):
        lines = parser.format_help().splitlines()
        i = 0
        while i < len(lines):
            m = re.match(r"^\s+(arena\s.*)$", lines[i])
            if m:
                cmd = m.group(1)
                while cmd.rstrip().endswith("\\") and i + 1 < len(lines):
                    i += 1
                    cmd = cmd.rstrip()[:-1] + " " + lines[i].strip()
                cmd = re.split(r"\s{2,}", cmd)[0]
                for part in re.split(r"\s*(?:&&|&|\||;)\s*", cmd):
                    try:
                        argv = shlex.split(part)[1:]
                    except ValueError:
                        continue
                    if part.startswith("arena ") and argv and argv[0] in commands:
                        yield " ".join(prefix) or "arena", part, argv
            i += 1


def test_every_example_in_every_help_parses():
    """The examples a user copies from --help are real commands (arena sim --help recommended
    `arena edge --source ...`, a flag that does not exist)."""
    import contextlib
    import io

    from arena.cli import build_parser

    examples = list(_example_commands())
    assert len(examples) > 40
    assert any(argv[:1] == ["edge"] and where == "sim" for where, _, argv in examples)
    bad = []
    for where, text, argv in examples:
        err = io.StringIO()
        try:
            with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
                build_parser().parse_args(argv)
        except SystemExit as exc:
            if exc.code:
                bad.append(f"{where} --help: {text!r}: {err.getvalue().strip().splitlines()[-1]}")
    assert not bad, "\n".join(bad)


MISSING_MCAP = "import sys; sys.modules['mcap'] = None; from arena.cli import main; sys.exit(main(sys.argv[1:]))"


def test_a_command_whose_package_is_missing_when_it_runs_says_what_to_install(tmp_path):
    """A machine without mcap (a fresh one, before it was declared): `arena record` prints one line
    naming the package and the pip command (exit 2), not a traceback."""
    out = subprocess.run([sys.executable, "-c", MISSING_MCAP, "record", "out.mcap", "--duration", "5"],
                         capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert out.returncode == 2, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("arena record: needs the Python package 'mcap'")
    assert "pip install mcap" in lines[0] and "Traceback" not in out.stderr
    assert not (tmp_path / "out.mcap").exists()


def test_a_command_whose_import_fails_stays_listed_and_says_what_to_install(tmp_path):
    """A command (a real entry point of an installed distribution) whose module imports a package
    that is not there stays listed in --help and, called, prints one line with the pip command."""
    site = tmp_path / "site"
    dist = site / "arena_extra_cmd-0.1.dist-info"
    dist.mkdir(parents=True)
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: arena-extra-cmd\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[arena.commands]\nextracmd = arena_extra_cmd:register\n")
    (site / "arena_extra_cmd.py").write_text("import notinstalled_pkg_xyz  # its dependency is missing\n"
                                            "def register(sub):\n    sub.add_parser('extracmd')\n")
    env = {**os.environ, "PYTHONPATH": str(site)}
    helps = subprocess.run(arena_cmd("--help"), capture_output=True, text=True, timeout=60, env=env)
    listed = [ln for ln in helps.stdout.splitlines() if ln.strip().startswith("extracmd")]
    assert listed and "pip install notinstalled_pkg_xyz" in listed[0], helps.stdout
    for argv in (["extracmd"], ["extracmd", "--help"], ["extracmd", "a", "--flag"]):
        out = subprocess.run(arena_cmd(*argv), capture_output=True, text=True, timeout=60, env=env)
        assert out.returncode == 2 and out.stdout == ""
        lines = out.stderr.strip().splitlines()
        assert len(lines) == 1 and "pip install notinstalled_pkg_xyz" in lines[0], out.stderr


def test_watch_prints_a_message_published_by_another_process(router, service):
    out = run("watch", "arena/telemetry/*", "--count", "2", "--duration", "20", *router_args(router))
    lines = out.stdout.strip().splitlines()
    assert out.returncode == 0 and len(lines) == 2, out.stderr
    assert lines[0].startswith("arena/telemetry/zumo1 telemetry: robot=zumo1 seq=")
    js = run("watch", "arena/telemetry/*", "--json", "--count", "1", "--duration", "20", *router_args(router))
    rec = json.loads(js.stdout.strip().splitlines()[0])
    assert rec["key"] == "arena/telemetry/zumo1" and rec["kind"] == "telemetry" and rec["enc_left"] == -rec["enc_right"]


def test_status_lists_a_live_service(router, service):
    for _ in range(3):  # the machine may be busy: give the service a few status periods
        out = run("status", "--json", "--wait", "1.0", *router_args(router))
        row = {(r["role"], r["name"]): r for r in json.loads(out.stdout)}.get(("bridge", "lab-a"))
        if row and row["counters"]:
            break
    assert row["alive"] is True and row["gauges"]["rtt_ms"] == 4.5
    assert row["counters"]["telemetry"] >= 10 and row["counters"]["telemetry"] % 10 == 0
    table = run("status", "--wait", "1.0", *router_args(router)).stdout
    line = next(ln for ln in table.splitlines() if ln.startswith("bridge"))
    assert "lab-a" in line and "yes" in line and "rtt_ms=4.5" in line


def test_status_without_router_says_what_to_check():
    """No router answering is a runtime failure (exit 1); wrong settings are a usage error (2)."""
    out = run("status", "-m", "client", "-e", "tcp/127.0.0.1:9", "--wait", "0")
    assert out.returncode == 1
    assert "Is a router running there" in out.stderr and "Traceback" not in out.stderr
    assert "! ." not in out.stderr
    bad = run("status", "--zenoh-config", "/nonexistent/zenoh.json5", "--wait", "0")
    assert bad.returncode == 2 and "zenoh.json5" in bad.stderr and "Traceback" not in bad.stderr


def router_args(router):
    return ["-e", router.endpoint]


def test_a_service_started_before_its_router_waits_for_it_then_runs(tmp_path):
    # start order is free (docs/deployment.md): a long-running service in client mode retries
    # until its router is up, then runs as usual
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    out = tmp_path / "early.mcap"
    proc = subprocess.Popen(arena_cmd("record", str(out), "--duration", "30", "-m", "client", "-e", endpoint),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    router = None
    try:
        time.sleep(3.0)
        assert proc.poll() is None, proc.communicate()
        router = subprocess.Popen(arena_cmd("router", "-l", endpoint), stdout=subprocess.PIPE,
                                  stderr=subprocess.STDOUT, text=True)
        wait_for_line(router, "listening on")
        wait_for_line(proc, "recording arena/**", timeout=20)
        proc.terminate()
        stdout, stderr = proc.communicate(timeout=20)
    finally:
        for p in (proc, router):
            if p is not None and p.poll() is None:
                p.kill()
                p.wait(timeout=5)
    assert proc.returncode == 0, stderr
    assert "waiting for Zenoh" in stderr
    assert out.stat().st_size > 0


def test_services_without_kernels_start_without_numba_or_scipy():
    # importing numba (~0.4 s) or scipy.spatial (~0.5 s) in every process slowed the demo's
    # start-up on 2 cores by seconds; the router, bridge, ground truth and recorder need neither
    code = ("import sys, arena.cli, robot_bridge.cli, robot_bridge.service, groundtruth.cli, "
            "recorder.cli, recorder.service; "
            "print(sorted(m for m in ('numba', 'scipy.spatial') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert out.stdout.strip() == "[]", out.stdout


# ---- arena watch under an access-control list ------------------------------------------------
NOTICE = "under an access-control list, subscribe to a prefix your user may read, e.g. arena/robots/*"


@pytest.fixture
def acl_router(tmp_path):
    """A real `arena router` on loopback with deploy/zenoh/router.json5 (TLS, user/password and
    the access-control list) and the lab PKI of `arena certs`; yields (endpoint, client env)."""
    from tests.conftest import REPO

    pki = tmp_path / "pki"
    subprocess.run(arena_cmd("certs", str(pki), "--hosts", "router=127.0.0.1,console=127.0.0.1", "--users", "viewer"),
                   check=True, capture_output=True, timeout=60)
    deploy = REPO / "deploy" / "zenoh"
    (tmp_path / "router.json5").write_text((deploy / "router.json5").read_text().replace("/etc/arena/pki/", f"{pki}/"))
    client = (deploy / "client.json5").read_text().replace("/etc/arena/pki/host.", f"{pki}/console.")
    (tmp_path / "client.json5").write_text(client.replace("/etc/arena/pki/", f"{pki}/"))
    endpoint = f"tls/127.0.0.1:{free_port()}"
    proc = subprocess.Popen(arena_cmd("router", "--zenoh-config", str(tmp_path / "router.json5"), "-l", endpoint),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        wait_for_line(proc, "listening on", timeout=30)
        password = (pki / "viewer.env").read_text().split("ARENA_ZENOH_PASSWORD=")[1].strip()
        env = {**os.environ, "ARENA_ZENOH_CONFIG": str(tmp_path / "client.json5"), "ARENA_ZENOH_MODE": "client",
               "ARENA_ZENOH_CONNECT": endpoint, "ARENA_ZENOH_USER": "viewer", "ARENA_ZENOH_PASSWORD": password}
        yield endpoint, env
    finally:
        proc.kill()
        proc.wait(timeout=5)


def test_watch_says_when_an_access_control_list_may_hide_everything(acl_router):
    _, env = acl_router
    denied = subprocess.run(arena_cmd("watch", "arena/**", "--notice-after", "1", "--duration", "4"),
                            capture_output=True, text=True, timeout=60, env=env)
    assert denied.returncode == 0, denied.stderr
    assert denied.stdout == "", "the policy lets a viewer subscribe to arena/** (the notice would be wrong)"
    assert f"arena watch: nothing received on arena/** in 1 s; {NOTICE}" in denied.stderr.splitlines(), denied.stderr
    # control: a prefix the viewer may read (the router's own status, once a second) -> no notice
    allowed = subprocess.run(arena_cmd("watch", "arena/status/**", "--count", "1", "--duration", "15",
                                       "--notice-after", "1"), capture_output=True, text=True, timeout=60, env=env)
    assert allowed.returncode == 0 and allowed.stdout.startswith("arena/status/router/"), allowed.stdout + allowed.stderr
    assert NOTICE not in allowed.stderr


def test_watch_without_credentials_or_tls_prints_no_notice(router):
    out = run("watch", "arena/robots/*", "--notice-after", "0.5", "--duration", "2", *router_args(router))
    assert out.returncode == 0 and out.stdout == "" and NOTICE not in out.stderr, out.stderr
    assert run("watch", "--notice-after", "-1", "--duration", "0").returncode == 2

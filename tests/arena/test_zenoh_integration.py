"""Real Zenoh: an `arena router` subprocess, client sessions in separate processes."""

import os
import signal
import subprocess
import sys
import textwrap
import threading
import time

import pytest
import zenoh

from arena.messages import Track, decode
from arena.session import SessionError, ZenohSettings, open_session

PEER = textwrap.dedent("""
    import sys, time, zenoh
    from arena.messages import Track
    from arena.session import ZenohSettings, open_session
    endpoint = sys.argv[1]
    with open_session(ZenohSettings(mode="client", connect=[endpoint])) as s:
        fleet = {"zumo1": Track(track_id=1, robot="zumo1", x=0.25, y=0.5, yaw=0.1),
                 "7": Track(track_id=7, x=1.0, y=1.5)}
        def on_query(q):
            for name, t in fleet.items():
                q.reply(f"arena/robots/{name}", t.encode())
        s.declare_queryable("arena/robots/*", on_query)
        token = s.liveliness().declare_token("arena/alive/tracker/t1")
        pub = s.declare_publisher("arena/robots/zumo1")
        print("ready", flush=True)
        i = 0
        while True:
            pub.put(Track(track_id=1, robot="zumo1", stamp_us=i, x=0.01 * i, y=0.5).encode())
            i += 1
            time.sleep(0.02)
""")


def start_peer(router):
    proc = subprocess.Popen([sys.executable, "-c", PEER, router.endpoint], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "ready", proc.stderr.read()
    return proc


def test_pub_sub_query_and_liveliness_through_a_router(router):
    got, alive_events = [], []
    lock = threading.Lock()
    with open_session(ZenohSettings(mode="client", connect=[router.endpoint])) as s:
        def on_track(sample):
            with lock:
                got.append((str(sample.key_expr), decode(bytes(sample.payload))))

        def on_alive(sample):
            with lock:
                alive_events.append((str(sample.key_expr), sample.kind, time.monotonic()))

        s.declare_subscriber("arena/robots/*", on_track)
        s.liveliness().declare_subscriber("arena/alive/**", on_alive, history=True)
        peer = start_peer(router)
        try:
            deadline = time.monotonic() + 10
            while time.monotonic() < deadline and len(got) < 5:
                time.sleep(0.05)
            with lock:
                assert len(got) >= 5, "tracks did not arrive through the router"
                key, msg = got[-1]
            assert key == "arena/robots/zumo1" and isinstance(msg, Track) and msg.robot == "zumo1"
            stamps = [t.stamp_us for _, t in got]
            assert stamps == sorted(stamps)

            replies = [r.ok for r in s.get("arena/robots/*", timeout=5.0) if r.ok is not None]
            fleet = {str(r.key_expr): decode(bytes(r.payload)) for r in replies}
            assert set(fleet) == {"arena/robots/zumo1", "arena/robots/7"}
            assert fleet["arena/robots/7"].x == 1.0 and fleet["arena/robots/zumo1"].yaw == 0.1

            # the router answers a liveliness query from the tokens it holds (polled: on a loaded
            # machine one query has come back empty although the token's tracks had arrived)
            deadline, tokens = time.monotonic() + 10, []
            while "arena/alive/tracker/t1" not in tokens and time.monotonic() < deadline:
                tokens = [str(r.ok.key_expr) for r in s.liveliness().get("arena/alive/**", timeout=5.0) if r.ok]
            assert "arena/alive/tracker/t1" in tokens
        finally:
            t_kill = time.monotonic()
            os.kill(peer.pid, signal.SIGKILL)
            peer.wait(timeout=5)
        deadline = t_kill + 5
        gone = None
        while time.monotonic() < deadline and gone is None:
            with lock:
                for key, kind, t in alive_events:
                    if key == "arena/alive/tracker/t1" and kind == zenoh.SampleKind.DELETE:
                        gone = t
            time.sleep(0.01)
        assert gone is not None, "liveliness token did not disappear after SIGKILL"
        assert gone - t_kill < 2.0


# --------------------------------------------------------------------------------------------
# The zenoh-python examples' flags: -c/--config (alias of --zenoh-config) and --cfg KEY:VALUE
# --------------------------------------------------------------------------------------------
def _parse(*argv: str):
    import argparse

    from arena.session import add_zenoh_arguments

    p = argparse.ArgumentParser()
    add_zenoh_arguments(p)
    return p.parse_args(list(argv))


def _has_admin_space(session) -> bool:
    """Whether ``session`` answers for its own admin space ``@/<zid>/peer`` (its transports under
    ``@/<zid>/session/**`` are answered either way, and the router answers for its own)."""
    zid = str(session.info.zid())
    keys = [str(r.ok.key_expr) for r in session.get("@/**", timeout=3.0) if r.ok is not None]
    return f"@/{zid}/peer" in keys


def test_cfg_flags_are_applied_to_a_real_session(router):
    from arena.session import resolve_settings

    base = ("-m", "peer", "-e", router.endpoint)
    # --cfg is applied last: it overrides the flag before it
    args = _parse(*base, "--multicast-scouting", "--cfg", "scouting/multicast/enabled:false",
                  "--cfg", "adminspace/enabled:true")
    settings = resolve_settings(args)
    assert settings.cfg == ["scouting/multicast/enabled:false", "adminspace/enabled:true"]
    assert settings.to_zenoh_config().get_json("scouting/multicast/enabled") == "false"
    with open_session(args) as s:
        assert _has_admin_space(s)
    with open_session(_parse(*base)) as s:  # and without the flag it does not
        assert not _has_admin_space(s)


def _reaches(endpoint: str, session) -> bool:
    """A client connected straight to ``endpoint`` (no router) gets what ``session`` publishes."""
    got = []
    with open_session(ZenohSettings(mode="client", connect=[endpoint]), wait_s=5) as c:
        c.declare_subscriber("arena/robots/cfgtest", lambda sample: got.append(bytes(sample.payload)))
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and not got:
            session.put("arena/robots/cfgtest", Track(track_id=1).encode())
            time.sleep(0.05)
    return bool(got) and decode(got[0]).track_id == 1


def test_cfg_value_with_colons_replaces_the_listen_endpoints(router):
    from tests.conftest import free_port

    flag, cfg = f"tcp/127.0.0.1:{free_port()}", f"tcp/127.0.0.1:{free_port()}"
    args = _parse("-m", "peer", "-e", router.endpoint, "-l", flag, "--cfg", f'listen/endpoints:["{cfg}"]')
    with open_session(args) as s:
        assert _reaches(cfg, s)  # split at the first colon only: the endpoint's own colon is kept
        with pytest.raises(SessionError):  # nothing listens where -l said any more
            with open_session(ZenohSettings(mode="client", connect=[flag])):
                pass


@pytest.mark.parametrize("flag", ["-c", "--config", "--zenoh-config"])
def test_c_and_config_are_aliases_of_zenoh_config(router, tmp_path, flag):
    from tests.conftest import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    conf = tmp_path / "z.json5"
    conf.write_text('{ // a Zenoh JSON5 file\n  listen: { endpoints: ["%s"] },\n}\n' % endpoint)
    args = _parse("-m", "peer", "-e", router.endpoint, flag, str(conf))
    assert args.zenoh_config == str(conf)
    with open_session(args) as s:
        assert _reaches(endpoint, s)


@pytest.mark.parametrize("cfg,needle", [
    ("scouting/multicast/enabled", "expected KEY:VALUE"),
    ("no/such/key:1", "unknown key"),
    ("mode:peer", "a string needs quotes"),
    ("scouting/multicast/enabled:5", "expected a boolean"),
])
def test_a_bad_cfg_is_named_and_exits_2(router, cfg, needle):
    from tests.conftest import arena_cmd

    with pytest.raises(SessionError) as err:
        with open_session(_parse("-e", router.endpoint, "--cfg", cfg)):
            pass
    assert err.value.exit_code == 2 and f"--cfg {cfg!r}" in str(err.value) and needle in str(err.value)
    r = subprocess.run(arena_cmd("watch", "arena/robots/*", "--duration", "1", "-e", router.endpoint, "--cfg", cfg),
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and f"--cfg {cfg!r}" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr

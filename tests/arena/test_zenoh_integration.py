"""Real Zenoh: an `arena router` subprocess, client sessions in separate processes."""

import os
import signal
import subprocess
import sys
import textwrap
import threading
import time

import zenoh

from arena.messages import Track, decode
from arena.session import ZenohSettings, open_session

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

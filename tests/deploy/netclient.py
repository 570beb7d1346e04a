"""A small Zenoh client for the multi-host tests, run inside a namespace as a subprocess.

It connects through :func:`arena.session.open_session` (so the same settings path as the services:
``ARENA_ZENOH_*`` variables, the client JSON5, user/password) and prints one JSON object per line
with a wall-clock time ``t`` (s), so the test can order what happened on several hosts.

    python netclient.py open                       try to connect; prints {"event": "open", "ok": ...}
    python netclient.py sub KEYEXPR...             print every sample received
    python netclient.py pub KEYEXPR --count 20     publish (a declared publisher, as services do)
    python netclient.py get KEYEXPR                query and print the replies (or errors)
    python netclient.py alive KEYEXPR              print the liveliness tokens alive on KEYEXPR
    python netclient.py queryable KEYEXPR          answer queries and print each one received
    python netclient.py service ROLE NAME          an arena.service.Service (status + liveliness)

Every mode stops after ``--duration`` seconds (default 20) at the latest.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time


_print_lock = threading.Lock()


def emit(event: str, **fields) -> None:
    """Print one JSON line (callbacks of several subscribers run on different threads)."""
    line = json.dumps({"event": event, "t": time.time(), **fields})
    with _print_lock:
        print(line, flush=True)


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("mode", choices=["open", "sub", "pub", "get", "alive", "queryable", "service"])
    p.add_argument("args", nargs="*")
    p.add_argument("--duration", type=float, default=20.0)
    p.add_argument("--count", type=int, default=20)
    p.add_argument("--period", type=float, default=0.1)
    p.add_argument("--wait", type=float, default=5.0, help="seconds to wait for the router at start")
    a = p.parse_args()

    from arena.session import SessionError, open_session

    stop = threading.Event()
    try:
        with open_session(None, wait_s=a.wait) as session:
            emit("open", ok=True, zid=str(session.zid()))
            if a.mode == "open":
                return 0
            if a.mode == "sub":
                subs = [session.declare_subscriber(
                    k, lambda s: emit("sample", key=str(s.key_expr), size=len(bytes(s.payload)))) for k in a.args]
                emit("ready")
                stop.wait(a.duration)
                for sub in subs:
                    sub.undeclare()
            elif a.mode == "pub":
                pub = session.declare_publisher(a.args[0])
                time.sleep(0.5)  # let the router's declarations arrive
                emit("ready")
                for i in range(a.count):
                    pub.put(f"fake {i}".encode())
                    emit("sent", i=i)
                    time.sleep(a.period)
                pub.undeclare()
            elif a.mode == "get":
                for reply in session.get(a.args[0], timeout=min(a.duration, 3.0)):
                    if reply.ok is not None:
                        emit("reply", key=str(reply.ok.key_expr), payload=bytes(reply.ok.payload).decode(errors="replace"))
                    else:
                        emit("reply_error", payload=bytes(reply.err.payload).decode(errors="replace"))
                emit("done")
            elif a.mode == "alive":
                for reply in session.liveliness().get(a.args[0], timeout=min(a.duration, 3.0)):
                    if reply.ok is not None:
                        emit("alive", key=str(reply.ok.key_expr))
                emit("done")
            elif a.mode == "queryable":
                def on_query(query):
                    emit("query", key=str(query.key_expr))
                    query.reply(query.key_expr, b"ok")

                q = session.declare_queryable(a.args[0], on_query)
                emit("ready")
                stop.wait(a.duration)
                q.undeclare()
            elif a.mode == "service":
                from arena.service import Service

                with Service(session, a.args[0], a.args[1], period_s=0.1) as svc:
                    emit("ready")
                    deadline = time.monotonic() + a.duration
                    while time.monotonic() < deadline:
                        svc.count("ticks")
                        time.sleep(0.1)
    except SessionError as exc:
        emit("open", ok=False, error=str(exc))
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

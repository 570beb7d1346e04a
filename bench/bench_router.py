"""Load test of one Zenoh router: N cameras publishing event windows to one tracker-like subscriber.

Each camera is its own process publishing ``arena/events/<camera>`` EventWindow messages, as
``arena edge`` does (10 ms slices, congestion control DROP, events compressed with the default
lossless codec from synthetic robot-like blobs), at ``--rate`` windows/s (0 = as fast as it can).
One subscriber process (the tracker's place) receives all cameras. Two layouts, one run each:

  router   every process is a client of one `arena router` (the multi-host layout, via loopback)
  p2p      publishers connect straight to the subscriber in peer mode (no router: the baseline)
  tls      with ``--tls``: the router of the lab deployment (deploy/zenoh/router.json5: TLS with
           client certificates, user/password and the access-control policy; certificates made
           by ``arena certs`` for 127.0.0.1), publishers as the edge, the subscriber as the tracker

Printed per camera and layout: windows sent and received, drops (sequence gaps at the
subscriber), events/s delivered, latency publish -> receive (p50/p99, ms, one host clock), then
the totals side by side with the router/p2p ratio.

    python bench/bench_router.py                         # 4 cameras, 100 Hz, 5000 ev/window, 4 s
    python bench/bench_router.py --cameras 2 --rate 0    # as fast as possible
    python bench/bench_router.py --events 20000 --seconds 6
    python bench/bench_router.py --tls                   # also through the secured router
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def synthetic_windows(n_windows: int, events: int, width: int = 640, height: int = 480, seed: int = 0,
                      slice_us: int = 10_000) -> list[tuple[int, bytes, str]]:
    """``n_windows`` consecutive 10 ms slices of ``events`` events from 4 moving robot-sized blobs
    plus 5 % uniform noise, compressed with the edge's default codec: (count, data, codec)."""
    from arena.codec import DEFAULT_CODEC, encode
    from arena.events import make_events

    rng = np.random.default_rng(seed)
    centres = rng.uniform([100, 100], [width - 100, height - 100], size=(4, 2))
    vel = rng.uniform(-2, 2, size=(4, 2))  # px per slice
    out = []
    for i in range(n_windows):
        n_noise = events // 20
        n_blob = events - n_noise
        which = rng.integers(0, 4, n_blob)
        xy = centres[which] + rng.normal(0, 18, size=(n_blob, 2))
        noise = rng.uniform([0, 0], [width, height], size=(n_noise, 2))
        xy = np.clip(np.vstack([xy, noise]), 0, [width - 1, height - 1]).astype(np.uint16)
        t = np.sort(rng.integers(i * slice_us, (i + 1) * slice_us, len(xy)))
        ev = make_events(xy[:, 0], xy[:, 1], rng.integers(0, 2, len(xy)), t)
        out.append((len(ev), encode(ev, DEFAULT_CODEC), DEFAULT_CODEC))
        centres += vel
    return out


# --------------------------------------------------------------------------------------------
def run_publisher(args) -> int:
    import zenoh

    from arena.messages import EventWindow
    from arena.session import open_session

    windows = synthetic_windows(20, args.events, seed=hash(args.camera) & 0xFFFF)
    settings = _settings(args.mode, [args.endpoint], [])
    sent = 0
    period = 1.0 / args.rate if args.rate > 0 else 0.0
    with open_session(settings, wait_s=10) as session:
        pub = session.declare_publisher(f"arena/events/{args.camera}",
                                        congestion_control=zenoh.CongestionControl.DROP)
        time.sleep(args.warmup)
        t0 = time.perf_counter()
        deadline = t0 + args.seconds
        next_t = t0
        while time.perf_counter() < deadline:
            count, data, codec = windows[sent % len(windows)]
            msg = EventWindow(camera=args.camera, seq=sent, t_start_us=sent * 10_000, t_end_us=(sent + 1) * 10_000,
                              width=640, height=480, count=count, codec=codec, data=data,
                              publish_ns=time.time_ns())
            pub.put(msg.encode())
            sent += 1
            if period:
                next_t += period
                delay = next_t - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)
        elapsed = time.perf_counter() - t0
        time.sleep(0.5)  # let the last windows drain before the session closes
    print(json.dumps({"camera": args.camera, "sent": sent, "elapsed": elapsed,
                      "bytes": int(np.mean([len(w[1]) for w in windows]))}), flush=True)
    return 0


def _settings(mode: str, connect: list[str], listen: list[str]):
    """Session settings of a bench process; a TLS run adds the role's config file and
    credentials through the same variables the systemd units set."""
    from arena.session import ZenohSettings

    st = ZenohSettings(mode=mode, connect=connect, listen=listen)
    st.config_file = os.environ.get("ARENA_ZENOH_CONFIG") or None
    if os.environ.get("ARENA_ZENOH_USER"):
        st.user, st.password = os.environ["ARENA_ZENOH_USER"], os.environ.get("ARENA_ZENOH_PASSWORD", "")
    return st


def run_subscriber(args) -> int:
    from arena.messages import EventWindow, MessageError, decode
    from arena.session import open_session

    stats: dict[str, dict] = {}
    lock = threading.Lock()

    def on_sample(sample) -> None:
        now = time.time_ns()
        try:
            msg = decode(bytes(sample.payload))
        except MessageError:
            return
        if not isinstance(msg, EventWindow):
            return
        with lock:
            st = stats.setdefault(msg.camera, {"received": 0, "events": 0, "lat": [], "max_seq": -1,
                                               "first": now, "last": now})
            st["received"] += 1
            st["events"] += msg.count
            st["lat"].append((now - msg.publish_ns) / 1e6)
            st["max_seq"] = max(st["max_seq"], msg.seq)
            st["last"] = now

    listen = [args.endpoint] if args.mode == "peer" else []
    connect = [] if args.mode == "peer" else [args.endpoint]
    settings = _settings(args.mode, connect, listen)
    with open_session(settings, wait_s=10) as session:
        sub = session.declare_subscriber("arena/events/*", on_sample)
        print(json.dumps({"ready": True}), flush=True)
        sys.stdin.readline()  # the bench says when every publisher is done (or closes the pipe)
        sub.undeclare()
    with lock:
        out = {}
        for cam, st in stats.items():
            lat = np.array(st["lat"])
            span = max((st["last"] - st["first"]) / 1e9, 1e-6)
            out[cam] = {"received": st["received"], "events": st["events"], "events_per_s": st["events"] / span,
                        "lat_p50": float(np.percentile(lat, 50)), "lat_p99": float(np.percentile(lat, 99)),
                        "max_seq": st["max_seq"]}
    print(json.dumps({"stats": out}), flush=True)
    return 0


# --------------------------------------------------------------------------------------------
def _me(*args: str) -> list[str]:
    return [sys.executable, str(Path(__file__).resolve()), *args]


def _tls_lab(root: Path, endpoint: str, env: dict) -> tuple[list[str], dict, dict]:
    """The deployment's router and client configs (deploy/zenoh) with certificates for
    127.0.0.1: the router's argv, and the environments of an edge (camera host) and a tracker."""
    pki = root / "pki"
    made = subprocess.run([sys.executable, "-m", "arena", "certs", str(pki), "--hosts",
                           "router=127.0.0.1,camera=127.0.0.1,tracker=127.0.0.1"], capture_output=True, text=True, env=env)
    if made.returncode != 0:
        raise SystemExit(f"bench_router --tls: arena certs failed: {(made.stderr or made.stdout).strip()[-500:]}")
    passwords = dict(line.split(":", 1) for line in (pki / "users.txt").read_text().split())
    deploy = REPO / "deploy" / "zenoh"
    router = root / "router.json5"
    router.write_text((deploy / "router.json5").read_text().replace("/etc/arena/pki/", f"{pki}/")
                      .replace('"tls/0.0.0.0:7447"', f'"{endpoint}"'))

    def client(host: str, user: str) -> dict:
        path = root / f"client-{host}.json5"
        path.write_text((deploy / "client.json5").read_text()
                        .replace("/etc/arena/pki/host.pem", f"{pki}/{host}.pem")
                        .replace("/etc/arena/pki/host.key", f"{pki}/{host}.key")
                        .replace("/etc/arena/pki/", f"{pki}/"))
        return {**env, "ARENA_ZENOH_CONFIG": str(path), "ARENA_ZENOH_USER": user,
                "ARENA_ZENOH_PASSWORD": passwords[user]}

    return ([sys.executable, "-m", "arena", "router", "--zenoh-config", str(router)],
            client("camera", "edge"), client("tracker", "tracker"))


def run_layout(layout: str, cameras: int, rate: float, events: int, seconds: float) -> dict:
    """Run one layout and return {camera: stats} merged from the publishers and the subscriber."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "PYTHONPATH": str(REPO)}
    pub_env = sub_env = env
    procs: list[subprocess.Popen] = []
    tmp = tempfile.TemporaryDirectory(prefix="bench-router-")
    try:
        port = free_port()
        endpoint = f"tcp/127.0.0.1:{port}"
        router_cmd = [sys.executable, "-m", "arena", "router", "-l", endpoint]
        if layout == "tls":
            endpoint = f"tls/127.0.0.1:{port}"
            router_cmd, pub_env, sub_env = _tls_lab(Path(tmp.name), endpoint, env)
        if layout in ("router", "tls"):
            router = subprocess.Popen(router_cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
            procs.append(router)
            line = router.stdout.readline()
            if "listening" not in line:
                raise SystemExit(f"bench_router: the router did not start: {line}")
            mode = "client"
        else:
            mode = "peer"
        warmup = 2.0
        sub = subprocess.Popen(_me("--role", "sub", "--mode", mode, "--endpoint", endpoint),
                               stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=sub_env)
        procs.append(sub)
        if "ready" not in sub.stdout.readline():
            raise SystemExit("bench_router: the subscriber did not start")
        pubs = [subprocess.Popen(_me("--role", "pub", "--mode", mode, "--endpoint", endpoint,
                                     "--camera", f"cam{i}", "--rate", str(rate), "--events", str(events),
                                     "--seconds", str(seconds), "--warmup", str(warmup)),
                                 stdout=subprocess.PIPE, text=True, env=pub_env) for i in range(cameras)]
        procs += pubs
        sent = {}
        for p in pubs:
            out, _ = p.communicate(timeout=seconds + 60)
            d = json.loads(out.strip().splitlines()[-1])
            sent[d["camera"]] = d
        time.sleep(0.5)
        out, _ = sub.communicate("stop\n", timeout=30)
        stats = json.loads(out.strip().splitlines()[-1])["stats"]
    finally:
        for p in procs:
            if p.poll() is None:
                p.terminate()
                try:
                    p.wait(timeout=5)
                except subprocess.TimeoutExpired:
                    p.kill()
        tmp.cleanup()
    result = {}
    for cam, d in sorted(sent.items()):
        st = stats.get(cam, {"received": 0, "events": 0, "events_per_s": 0.0, "lat_p50": float("nan"),
                             "lat_p99": float("nan")})
        result[cam] = {**st, "sent": d["sent"], "bytes": d["bytes"], "drops": d["sent"] - st["received"]}
    return result


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cameras", type=int, default=4, help="publishing cameras (default 4)")
    p.add_argument("--rate", type=float, default=100.0, help="windows/s per camera (0 = max; default 100)")
    p.add_argument("--events", type=int, default=5000, help="events per window (default 5000 = 500k ev/s at 100 Hz)")
    p.add_argument("--seconds", type=float, default=4.0, help="publishing time per layout (default 4)")
    p.add_argument("--tls", action="store_true",
                   help="also run through the lab deployment's secured router (TLS, mTLS, passwords, ACL)")
    p.add_argument("--role", choices=["pub", "sub"], help=argparse.SUPPRESS)
    p.add_argument("--mode", help=argparse.SUPPRESS)
    p.add_argument("--endpoint", help=argparse.SUPPRESS)
    p.add_argument("--camera", help=argparse.SUPPRESS)
    p.add_argument("--warmup", type=float, default=2.0, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.role == "pub":
        return run_publisher(args)
    if args.role == "sub":
        return run_subscriber(args)
    if not (1 <= args.cameras <= 16 and args.rate >= 0 and 1 <= args.events <= 1_000_000 and 0.5 <= args.seconds <= 60):
        p.error("need 1 <= --cameras <= 16, --rate >= 0, 1 <= --events <= 1e6, 0.5 <= --seconds <= 60")

    results = {}
    for layout in ("router", "p2p", "tls") if args.tls else ("router", "p2p"):
        print(f"running {layout}: {args.cameras} cameras x {args.rate or 'max'} Hz x {args.events} events, "
              f"{args.seconds:g} s ...", flush=True)
        results[layout] = run_layout(layout, args.cameras, args.rate, args.events, args.seconds)

    print(f"\n{'layout':<7} {'camera':<6} {'sent':>6} {'recv':>6} {'drops':>6} {'KB/win':>7} "
          f"{'Mev/s':>7} {'lat p50':>8} {'lat p99':>8}")
    for layout, res in results.items():
        for cam, r in res.items():
            print(f"{layout:<7} {cam:<6} {r['sent']:>6} {r['received']:>6} {r['drops']:>6} {r['bytes'] / 1e3:>7.1f} "
                  f"{r['events_per_s'] / 1e6:>7.3f} {r['lat_p50']:>6.2f}ms {r['lat_p99']:>6.2f}ms")
    tot = {}
    for layout, res in results.items():
        sent = sum(r["sent"] for r in res.values())
        recv = sum(r["received"] for r in res.values())
        evs = sum(r["events_per_s"] for r in res.values())
        p50 = float(np.median([r["lat_p50"] for r in res.values()]))
        p99 = float(max(r["lat_p99"] for r in res.values()))
        tot[layout] = (sent, recv, evs, p50, p99)
    names = list(tot)
    ratios = [("router", "p2p")] + ([("tls", "router")] if "tls" in tot else [])
    print(f"\n{'total':<22}" + "".join(f"{n:>12}" for n in names) + "".join(f"{a + '/' + b:>12}" for a, b in ratios))
    rows = [("windows received", 1, "{:>12d}", lambda v: v), ("events/s delivered", 2, "{:>11.2f}M", lambda v: v / 1e6),
            ("latency p50 (ms)", 3, "{:>12.2f}", lambda v: v), ("latency p99 (ms)", 4, "{:>12.2f}", lambda v: v)]
    print(f"{'drop rate':<22}" + "".join(f"{1 - tot[n][1] / max(tot[n][0], 1):>11.2%} " for n in names))
    for label, k, fmt, conv in rows:
        print(f"{label:<22}" + "".join(fmt.format(conv(tot[n][k])) for n in names)
              + "".join(f"{tot[a][k] / max(tot[b][k], 1e-9):>12.2f}" for a, b in ratios))
    return 0


if __name__ == "__main__":
    sys.exit(main())

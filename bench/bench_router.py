"""Load test of one Zenoh router: N cameras publishing event windows to one tracker-like subscriber.

Each camera is its own process publishing ``arena/events/<camera>`` EventWindow messages, as
``arena edge`` does (10 ms slices, congestion control DROP, events compressed with the default
lossless codec from synthetic robot-like blobs), at ``--rate`` windows/s (0 = as fast as it can).
One subscriber process (the tracker's place) receives all cameras. Two layouts, one run each:

  router   every process is a client of one `arena router` (the multi-host layout, via loopback)
  p2p      publishers connect straight to the subscriber in peer mode (no router: the baseline)

Printed per camera and layout: windows sent and received, drops (sequence gaps at the
subscriber), events/s delivered, latency publish -> receive (p50/p99, ms, one host clock), then
the totals side by side with the router/p2p ratio.

    python bench/bench_router.py                         # 4 cameras, 100 Hz, 5000 ev/window, 4 s
    python bench/bench_router.py --cameras 2 --rate 0    # as fast as possible
    python bench/bench_router.py --events 20000 --seconds 6
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
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
    from arena.session import ZenohSettings, open_session

    windows = synthetic_windows(20, args.events, seed=hash(args.camera) & 0xFFFF)
    settings = ZenohSettings(mode=args.mode, connect=[args.endpoint], listen=[])
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


def run_subscriber(args) -> int:
    from arena.messages import EventWindow, MessageError, decode
    from arena.session import ZenohSettings, open_session

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
    settings = ZenohSettings(mode=args.mode, connect=connect, listen=listen)
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


def run_layout(layout: str, cameras: int, rate: float, events: int, seconds: float) -> dict:
    """Run one layout and return {camera: stats} merged from the publishers and the subscriber."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "PYTHONPATH": str(REPO)}
    procs: list[subprocess.Popen] = []
    try:
        port = free_port()
        endpoint = f"tcp/127.0.0.1:{port}"
        if layout == "router":
            router = subprocess.Popen([sys.executable, "-m", "arena", "router", "-l", endpoint],
                                      stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
            procs.append(router)
            line = router.stdout.readline()
            if "listening" not in line:
                raise SystemExit(f"bench_router: the router did not start: {line}")
            mode = "client"
        else:
            mode = "peer"
        warmup = 2.0
        sub = subprocess.Popen(_me("--role", "sub", "--mode", mode, "--endpoint", endpoint),
                               stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
        procs.append(sub)
        if "ready" not in sub.stdout.readline():
            raise SystemExit("bench_router: the subscriber did not start")
        pubs = [subprocess.Popen(_me("--role", "pub", "--mode", mode, "--endpoint", endpoint,
                                     "--camera", f"cam{i}", "--rate", str(rate), "--events", str(events),
                                     "--seconds", str(seconds), "--warmup", str(warmup)),
                                 stdout=subprocess.PIPE, text=True, env=env) for i in range(cameras)]
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
    for layout in ("router", "p2p"):
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
    (rs, rr, re_, r50, r99), (ps, pr, pe, p50, p99) = tot["router"], tot["p2p"]
    print(f"\n{'total':<22} {'router':>12} {'p2p':>12} {'router/p2p':>11}")
    print(f"{'windows received':<22} {rr:>12} {pr:>12} {rr / max(pr, 1):>11.2f}")
    print(f"{'drop rate':<22} {1 - rr / max(rs, 1):>11.2%} {1 - pr / max(ps, 1):>11.2%}")
    print(f"{'events/s delivered':<22} {re_ / 1e6:>10.2f}M {pe / 1e6:>10.2f}M {re_ / max(pe, 1):>11.2f}")
    print(f"{'latency p50 (ms)':<22} {r50:>12.2f} {p50:>12.2f} {r50 / max(p50, 1e-9):>11.2f}")
    print(f"{'latency p99 (ms)':<22} {r99:>12.2f} {p99:>12.2f} {r99 / max(p99, 1e-9):>11.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The whole edge on one core: EVT 3.0 bytes -> decode -> filters -> 10 ms slices -> encode ->
Zenoh put to a subscriber in another process. Prints M events/s of CPU time, the CPU share at real
time and the bytes sent, ours vs a straightforward baseline (PyPI evt3 decoder, no filter, zstd of
the event array).

Data: the simulator's camera stream (3 robots, EVT 3.0 as its TCP camera sends it), and the shared
real sample (a dense 8.8 ms burst). Run: ``python bench/bench_edge.py [--seconds S]``.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import zenoh
import zstandard

from arena.codec import encode
from arena.formats.evt3 import Evt3Decoder
from arena.formats.raw import parse_raw_header
from arena.messages import EventWindow
from camera_edge.filters import BackgroundActivityFilter, HotPixelFilter
from camera_edge.pipeline import EdgePipeline
from camera_edge.slicing import Slicer

SAMPLE = Path(__file__).resolve().parents[2] / "shared" / "data" / "evt3_sample.raw"
SUB = """
import sys, time, zenoh
conf = zenoh.Config()
conf.insert_json5("mode", '"peer"'); conf.insert_json5("listen/endpoints", '["%s"]')
conf.insert_json5("scouting/multicast/enabled", "false")
with zenoh.open(conf) as s:
    n = [0]
    s.declare_subscriber("bench/edge", lambda smp: n.__setitem__(0, n[0] + 1))
    print("ready", flush=True)
    sys.stdin.read()
"""


def run(name, chunks, width, height, put, ours: bool, span_us: int, filters: bool = True):
    """Process every chunk once; returns (events, CPU s, bytes sent, windows)."""
    n_ev = 0
    sent = 0
    windows = 0
    c0 = time.process_time()
    if ours:
        dec = Evt3Decoder()
        hot = np.array([[5, 5], [width - 3, height - 7]])  # steady state: the mask was learned before
        pipe = EdgePipeline([HotPixelFilter(width, height, hot_pixels=hot),
                             BackgroundActivityFilter(width, height, 10_000)] if filters else [], 10_000)
        for ch in chunks:
            ev = dec.feed(ch)
            n_ev += ev.size
            for w in pipe.push(ev, dec.time_us):
                data = encode(w.events, t_ref_us=w.t_start_us)
                msg = EventWindow(camera="bench", seq=windows, t_start_us=w.t_start_us, t_end_us=w.t_end_us,
                                  width=width, height=height, count=int(w.events.size), codec="planes-zstd/1",
                                  data=data, filtered=w.filtered, publish_ns=time.time_ns()).encode()
                put(msg)
                sent += len(msg)
                windows += 1
    else:
        import evt3

        slicer = Slicer(10_000)
        z = zstandard.ZstdCompressor(level=3)
        rest = b""
        for ch in chunks:  # the PyPI decoder has no streaming state: decode whole word runs
            buf = rest + ch
            cut = len(buf) - len(buf) % 2
            e = evt3.decode_bytes(buf[:cut], sensor_width=width, sensor_height=height)
            rest = buf[cut:]
            ev = np.empty(len(e.x), dtype=[("x", "<u2"), ("y", "<u2"), ("p", "u1"), ("t", "<i8")])
            ev["x"], ev["y"], ev["p"], ev["t"] = e.x, e.y, e.p, e.t
            n_ev += ev.size
            for s in slicer.push(ev):
                data = z.compress(s.events.tobytes())
                msg = EventWindow(camera="bench", seq=windows, t_start_us=s.t_start_us, t_end_us=s.t_end_us,
                                  width=width, height=height, count=int(s.events.size), codec="raw-zstd",
                                  data=data, publish_ns=time.time_ns()).encode()
                put(msg)
                sent += len(msg)
                windows += 1
    return n_ev, time.process_time() - c0, sent, windows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=3.0, help="simulated seconds (default 3)")
    ap.add_argument("--port", type=int, default=7791, help="loopback port of the subscriber (default 7791)")
    args = ap.parse_args()

    from simulator.evt3 import canonical_order, encode_evt3
    from simulator.scenarios import Scenario, generate

    rec = generate(Scenario(n_robots=3, pattern="circle", duration_s=args.seconds, seed=2))
    ev = canonical_order(rec.events)
    data = encode_evt3(ev)
    span = int(ev["t"][-1] - ev["t"][0])
    datasets = [("sim 3 robots", data, rec.width, rec.height, span)]
    if SAMPLE.exists():
        raw = SAMPLE.read_bytes()
        h = parse_raw_header(raw)
        datasets.append(("real sample burst", raw[h.size:], h.width, h.height, 8_801))

    endpoint = f"tcp/127.0.0.1:{args.port}"
    sub = subprocess.Popen([sys.executable, "-c", SUB % endpoint], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                           text=True)
    try:
        assert sub.stdout.readline().strip() == "ready"
        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("connect/endpoints", f'["{endpoint}"]')
        conf.insert_json5("scouting/multicast/enabled", "false")
        with zenoh.open(conf) as s:
            pub = s.declare_publisher("bench/edge", congestion_control=zenoh.CongestionControl.DROP)
            time.sleep(0.5)
            print(f"edge pipeline, CPU time of one thread (machine: {os.cpu_count()} cores, "
                  f"load {os.getloadavg()[0]:.1f})")
            print(f"{'data':<18}{'pipeline':<34}{'M ev/s':>8}{'CPU at real time':>18}{'MB/s out':>10}"
                  f"{'ours/base speed':>16}")
            for name, body, w, h, span_us in datasets:
                chunks = [body[i:i + 16384] for i in range(0, len(body), 16384)]
                res = {}
                variants = {"ours, no filter": (True, False), "ours, hot px + denoise": (True, True),
                            "baseline evt3+zstd(array)": (False, False)}
                for label, (ours, filt) in variants.items():
                    run(name, chunks[:4], w, h, pub.put, ours, span_us, filt)  # warm caches
                    best = None
                    for _ in range(3):
                        r = run(name, chunks, w, h, pub.put, ours, span_us, filt)
                        best = r if best is None or r[1] < best[1] else best
                    res[label] = best
                base = res["baseline evt3+zstd(array)"]
                for label, (n, cpu, sent, nw) in res.items():
                    rate = n / cpu / 1e6
                    share = 100 * cpu / (span_us / 1e6)
                    mbps = sent / (span_us / 1e6) / 1e6
                    ratio = f"{rate / (base[0] / base[1] / 1e6):15.2f}x" if label.startswith("ours") else ""
                    print(f"{name:<18}{label:<34}{rate:8.1f}{share:17.1f}%{mbps:10.2f}{ratio:>16}")
            print("target: >= 10 M ev/s on one core for the whole edge")
    finally:
        sub.stdin.close()
        sub.wait(timeout=10)
    return 0


if __name__ == "__main__":
    sys.exit(main())

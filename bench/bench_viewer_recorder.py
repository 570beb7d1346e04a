"""Recorder throughput on the 4-robot demo's traffic: ours vs an all-msgpack MCAP baseline.

Ours (:class:`recorder.mcapio.RunWriter`): tracks, telemetry, ground truth and status converted
to JSON with a JSON schema per kind (Foxglove shows them) after checking that JSON converts back
to the very same msgpack bytes; event windows stored as msgpack. Baseline: the same MCAP writer
storing every payload as opaque msgpack (nothing readable in Foxglove). Also times reading the
file back as published payloads (what ``arena replay`` does) for both, and the file sizes.

Traffic per simulated second: 100 event windows of ``--events`` events (10 ms slices), 4 robots x
(100 tracks, 50 telemetry samples, 24 ground-truth poses), 8 status messages.

Examples::

    python bench/bench_viewer_recorder.py
    python bench/bench_viewer_recorder.py --seconds 5 --events 20000
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from arena import codec  # noqa: E402
from arena.events import make_events  # noqa: E402
from arena.messages import EventWindow, GroundTruthPose, Status, Telemetry, Track  # noqa: E402
from recorder.mcapio import RunWriter, read_run  # noqa: E402


def traffic(seconds: float, events: int) -> list[tuple[str, bytes, int]]:
    """(key, payload, log time ns) of ``seconds`` of demo traffic, in time order."""
    rng = np.random.default_rng(0)
    out = []
    for ms in range(int(seconds * 1000)):
        t_ns = 1_800_000_000_000_000_000 + ms * 1_000_000
        if ms % 10 == 0:  # a different window each time (identical ones would compress away)
            ev = make_events(rng.integers(0, 640, events), rng.integers(0, 480, events),
                             rng.integers(0, 2, events), np.sort(rng.integers(0, 10_000, events)) + ms * 1000)
            data = codec.encode(ev)
            out.append(("arena/events/cam0", EventWindow(camera="cam0", seq=ms // 10, t_start_us=ms * 1000,
                                                         t_end_us=ms * 1000 + 10_000, width=640, height=480,
                                                         count=events, codec=codec.DEFAULT_CODEC, data=data,
                                                         publish_ns=t_ns).encode(), t_ns))
        for r in range(4):
            name = f"zumo{r + 1}"
            a = ms / 1000 + r
            if ms % 10 == 5:
                out.append((f"arena/robots/{name}", Track(
                    track_id=r + 1, robot=name, camera="cam0", stamp_us=ms * 1000, x=0.9 + 0.4 * math.cos(a),
                    y=0.9 + 0.4 * math.sin(a), yaw=a % 3, vx=0.1, vy=0.2, u_px=320.5, v_px=240.25, n_events=900,
                    window_end_us=ms * 1000, edge_publish_ns=t_ns - 3_000_000, tracker_publish_ns=t_ns).encode(), t_ns + 1))
            if ms % 20 == 7:
                out.append((f"arena/telemetry/{name}", Telemetry(
                    robot=name, seq=ms // 20, robot_time_us=ms * 1000, host_time_ns=t_ns, enc_left=ms, enc_right=ms,
                    speed_left=0.2, speed_right=0.21, accel=(0.01, 0.0, 9.81), gyro=(0.0, 0.0, 0.5),
                    mag=(20.0, 3.0, 40.0), battery_mv=4800, power_left=200, power_right=200,
                    mission="circle", phase="run").encode(), t_ns + 2))
            if ms % 42 == 11:
                out.append((f"arena/groundtruth/{name}", GroundTruthPose(
                    robot=name, stamp_us=ms * 1000, x=0.9, y=0.9, yaw=0.3, u_px=100.0, v_px=90.0,
                    detector="aruco").encode(), t_ns + 3))
        if ms % 125 == 0:
            out.append(("arena/status/tracker/cam0", Status(
                role="tracker", name="cam0", host="vm", pid=42, time_ns=t_ns, uptime_s=ms / 1000,
                counters={"windows_in": ms // 10, "tracks_out": ms * 4 // 10},
                rates={"windows_in": 100.0, "tracks_out": 400.0}, gauges={"latency_ms": 3.5}).encode(), t_ns + 4))
    return out


def baseline_write(path: Path, msgs) -> None:
    with open(path, "wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start(profile="arena", library="baseline")
        sid = w.register_schema("arena.Raw", "", b"")
        chans: dict[str, int] = {}
        for key, payload, t in msgs:
            ch = chans.get(key)
            if ch is None:
                ch = chans[key] = w.register_channel(key, "msgpack", sid)
            w.add_message(ch, log_time=t, data=payload, publish_time=t)
        w.finish()


def baseline_read(path: Path) -> int:
    n = 0
    with open(path, "rb") as f:
        for _s, _c, m in make_reader(f).iter_messages(log_time_order=True):
            n += len(m.data)
    return n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=3.0, help="simulated seconds of traffic (default 3)")
    ap.add_argument("--events", type=int, default=10_000, help="events per 10 ms window (default 10000)")
    a = ap.parse_args()
    msgs = traffic(a.seconds, a.events)
    n, nbytes = len(msgs), sum(len(p) for _, p, _ in msgs)
    with tempfile.TemporaryDirectory() as tmp:
        ours_p, base_p = Path(tmp) / "ours.mcap", Path(tmp) / "base.mcap"
        t0 = time.perf_counter()
        with RunWriter(ours_p) as w:
            for key, payload, t in msgs:
                w.add(key, payload, t)
        t_ours = time.perf_counter() - t0
        t0 = time.perf_counter()
        baseline_write(base_p, msgs)
        t_base = time.perf_counter() - t0
        t0 = time.perf_counter()
        back = [m.payload for m in read_run(ours_p)]
        r_ours = time.perf_counter() - t0
        t0 = time.perf_counter()
        baseline_read(base_p)
        r_base = time.perf_counter() - t0
        assert back == [p for _, p, _ in msgs], "replayed payloads differ from the recorded ones"
        s_ours, s_base = ours_p.stat().st_size, base_p.stat().st_size
    print(f"{a.seconds:g} s of 4-robot demo traffic: {n} messages, {nbytes / 1e6:.1f} MB of payload "
          f"({n / a.seconds:.0f} msg/s); replayed payloads byte-identical")
    print(f"{'':<34}{'ours':>10}{'baseline':>11}{'ratio':>8}")
    print(f"{'write, messages/s':<34}{n / t_ours:>10.0f}{n / t_base:>11.0f}{t_ours / t_base:>7.2f}x")
    print(f"{'write, CPU per second of demo (%)':<34}{100 * t_ours / a.seconds:>10.1f}{100 * t_base / a.seconds:>11.1f}")
    print(f"{'read back, messages/s':<34}{n / r_ours:>10.0f}{n / r_base:>11.0f}{r_ours / r_base:>7.2f}x")
    print(f"{'file size (MB)':<34}{s_ours / 1e6:>10.2f}{s_base / 1e6:>11.2f}{s_ours / s_base:>7.2f}x")
    print("(ratio = ours / baseline time or size; the baseline's small messages are opaque in Foxglove)")


if __name__ == "__main__":
    main()

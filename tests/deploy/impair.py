"""Userspace link impairment (loss and delay jitter) between two interfaces, for kernels without the
``netem`` qdisc: every Ethernet frame received on one interface is dropped with probability
``--loss`` or sent out of the other after a delay drawn uniformly from ``--delay-ms`` +- ``--jitter-ms``
(as ``tc netem delay D J loss L``); with ``--port``, only TCP frames to or from that port are
impaired (the others are relayed at once). Runs as root in the namespace holding both interfaces; stops
after ``--duration`` seconds at the latest.

    python impair.py IF_A IF_B --loss 0.05 --delay-ms 50 --jitter-ms 50 --port 7447 --duration 60
"""

from __future__ import annotations

import argparse
import heapq
import json
import os
import random
import select
import signal
import socket
import sys
import time

ETH_P_ALL = 0x0003
PACKET_OUTGOING = 4
SOL_PACKET = 263
PACKET_VNET_HDR = 15  # frames carry a virtio_net_hdr: checksum-offload and GSO metadata survive the relay
VNET_HDR_LEN = 10


def tcp_ports(frame: bytes) -> tuple[int, int] | None:
    """(source, destination) ports of an IPv4 TCP frame (after the virtio header), else None."""
    eth = VNET_HDR_LEN
    if len(frame) < eth + 14 + 20 + 4 or frame[eth + 12:eth + 14] != b"\x08\x00" or frame[eth + 14 + 9] != 6:
        return None
    tcp = eth + 14 + (frame[eth + 14] & 0x0F) * 4
    return int.from_bytes(frame[tcp:tcp + 2], "big"), int.from_bytes(frame[tcp + 2:tcp + 4], "big")


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("if_a")
    p.add_argument("if_b")
    p.add_argument("--loss", type=float, default=0.0)
    p.add_argument("--delay-ms", type=float, default=0.0)
    p.add_argument("--jitter-ms", type=float, default=0.0)
    p.add_argument("--duration", type=float, default=60.0)
    p.add_argument("--port", type=int, default=None, help="impair only TCP frames of this port")
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args()
    try:
        os.nice(-15)  # this process is the wire: on a busy machine it must not wait for a CPU
    except OSError:
        pass
    rng = random.Random(a.seed)
    socks = {}
    for name in (a.if_a, a.if_b):
        s = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETH_P_ALL))
        s.setsockopt(SOL_PACKET, PACKET_VNET_HDR, 1)
        s.bind((name, 0))
        s.setblocking(False)
        socks[name] = s
    other = {socks[a.if_a]: socks[a.if_b], socks[a.if_b]: socks[a.if_a]}
    queue: list[tuple[float, int, socket.socket, bytes]] = []
    n = dropped = forwarded = too_big = passed = 0
    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))  # stop cleanly and report the counts
    print(json.dumps({"event": "ready"}), flush=True)
    deadline = time.monotonic() + a.duration
    while time.monotonic() < deadline and not stop:
        now = time.monotonic()
        while queue and queue[0][0] <= now:
            _, _, out, frame = heapq.heappop(queue)
            try:
                out.send(frame)
                forwarded += 1
            except OSError:
                too_big += 1
        timeout = max(0.0, min(0.05, queue[0][0] - now)) if queue else 0.05
        try:
            readable, _, _ = select.select(list(other), [], [], timeout)
        except InterruptedError:
            continue
        for s in readable:
            while True:
                try:
                    frame, addr = s.recvfrom(65536 + 64)
                except BlockingIOError:
                    break
                if addr[2] == PACKET_OUTGOING:  # our own sends, seen again
                    continue
                if a.port is not None and a.port not in (tcp_ports(frame) or ()):
                    delay = 0.0
                    passed += 1
                elif rng.random() < a.loss:
                    dropped += 1
                    continue
                else:
                    delay = max(0.0, a.delay_ms + rng.uniform(-a.jitter_ms, a.jitter_ms)) / 1e3
                n += 1
                heapq.heappush(queue, (time.monotonic() + delay, n, other[s], frame))
    print(json.dumps({"event": "done", "forwarded": forwarded, "dropped": dropped, "not_impaired": passed,
                      "send_errors": too_big}),
          flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The demo's ports: one block of consecutive free ports (router, camera, webcam, robots)."""

import random
import socket

from demo.cli import _free_ports


def test_a_block_with_a_busy_port_is_skipped(monkeypatch):
    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen()
    taken = busy.getsockname()[1]
    bases = iter([taken - 2, taken + 1])          # the first block holds the busy port
    monkeypatch.setattr(random, "randrange", lambda lo, hi: next(bases))
    try:
        base = _free_ports(5)
    finally:
        busy.close()
    assert base == taken + 1
    for port in range(base, base + 5):
        with socket.socket() as s:
            s.bind(("127.0.0.1", port))


def test_blocks_lie_below_the_ephemeral_range():
    with open("/proc/sys/net/ipv4/ip_local_port_range") as f:
        low = int(f.read().split()[0])
    for _ in range(20):
        base = _free_ports(19)
        assert 10_000 <= base and base + 19 <= low

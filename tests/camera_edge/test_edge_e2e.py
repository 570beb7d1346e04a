"""End to end over real Zenoh: the simulator's TCP camera -> `arena edge` subprocess -> a
subscriber that decodes every window; and DROP keeping the edge real time behind a slow subscriber."""

from __future__ import annotations

import os
import subprocess
import threading
import time

import numpy as np
import pytest

from arena.codec import decode as decode_events
from arena.messages import EventWindow, decode
from arena.session import open_session
from tests.conftest import arena_cmd

ENV = {**os.environ, "PYTHONUNBUFFERED": "1"}


class Windows:
    """Collects decoded EventWindows from a callback subscriber (optionally sleeping in it)."""

    def __init__(self, sleep_s: float = 0.0) -> None:
        self.items: list[tuple[EventWindow, np.ndarray]] = []
        self.lock = threading.Lock()
        self.sleep_s = sleep_s

    def __call__(self, sample) -> None:
        msg = decode(bytes(sample.payload))
        with self.lock:
            self.items.append(msg)
        if self.sleep_s:
            time.sleep(self.sleep_s)

    def decoded(self) -> list[tuple[EventWindow, np.ndarray]]:
        with self.lock:
            return [(m, decode_events(m.codec, m.data, m.count)) for m in self.items]


def _wait_alive(session, key: str, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if any(r.ok for r in session.liveliness().get(key, timeout=1.0)):
            return
        time.sleep(0.1)
    raise AssertionError(f"{key} never appeared")


def _stop(proc: subprocess.Popen) -> str:
    if proc.poll() is None:
        proc.terminate()
    try:
        _, err = proc.communicate(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate(timeout=5)
    return err


@pytest.mark.slow
def test_simulator_camera_to_subscriber_every_event_of_every_slice(router):
    from simulator.evt3 import CameraServer, canonical_order
    from simulator.scenarios import Scenario, generate

    rec = generate(Scenario(n_robots=2, pattern="circle", duration_s=1.5, seed=5))
    events = canonical_order(rec.events)
    got = Windows()
    with CameraServer(drop_when_slow=False) as cam, open_session(router.settings("client")) as s:
        s.declare_subscriber("arena/events/e2e", got)
        edge = subprocess.Popen(arena_cmd("edge", f"{cam.url}?width={rec.width}&height={rec.height}",
                                          "--camera", "e2e", *router.args), env=ENV, text=True,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        try:
            _wait_alive(s, "arena/alive/edge/e2e")
            deadline = time.monotonic() + 10
            while cam.n_clients < 1 and time.monotonic() < deadline:
                time.sleep(0.02)
            time.sleep(0.5)  # matching status reaches the edge
            t = events["t"]
            step = 10_000
            for a in range(int(t[0]) - int(t[0]) % step, int(t[-1]) + 3 * step, step):  # real time pace
                sel = events[(t >= a) & (t < a + step)]
                cam.publish(sel, until_us=a + step)
                time.sleep(step / 1e6)
            last_end = int(t[-1]) - int(t[-1]) % step + step
            deadline = time.monotonic() + 10
            while time.monotonic() < deadline:
                with got.lock:
                    if got.items and got.items[-1].t_end_us >= last_end:
                        break
                time.sleep(0.05)
        finally:
            err = _stop(edge)
    items = got.decoded()
    assert items, f"no window arrived; edge said: {err}"
    msgs = [m for m, _ in items]
    # windows are contiguous, numbered without gaps, nothing dropped, all 10 ms
    assert all(b.t_start_us == a.t_end_us for a, b in zip(msgs, msgs[1:]))
    assert [m.seq for m in msgs] == list(range(msgs[0].seq, msgs[0].seq + len(msgs)))
    assert all(m.t_end_us - m.t_start_us == 10_000 and m.dropped == 0 for m in msgs)
    assert any(m.count == 0 for m in msgs), "empty slices must be published too"
    received = np.concatenate([ev for _, ev in items])
    for m, ev in items:
        assert ev.size == m.count and (ev.size == 0 or (ev["t"].min() >= m.t_start_us and ev["t"].max() < m.t_end_us))
    start = msgs[0].t_start_us
    expected = events[(events["t"] >= start) & (events["t"] < msgs[-1].t_end_us)]
    np.testing.assert_array_equal(received, expected)
    assert expected.size > 0.9 * events.size


@pytest.mark.slow
def test_drop_keeps_the_edge_real_time_while_a_subscriber_sleeps(router, tmp_path):
    from arena.formats import write_events
    from simulator.scenarios import Scenario, generate

    rec = generate(Scenario(n_robots=2, pattern="circle", duration_s=3.0, seed=6))
    write_events(tmp_path / "rec.npz", rec.events, rec.width, rec.height)
    duration_s = (int(rec.events["t"][-1]) - int(rec.events["t"][0])) / 1e6
    slow = Windows(sleep_s=0.2)  # 5 windows/s while the edge makes 100/s
    with open_session(router.settings("client")) as s:
        s.declare_subscriber("arena/events/slow", slow)
        edge = subprocess.Popen(arena_cmd("edge", str(tmp_path / "rec.npz"), "--camera", "slow", "--speed", "1",
                                          "--codec", "raw/1", *router.args),
                                env=ENV, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        try:
            out, err = edge.communicate(timeout=duration_s + 20)
        finally:
            _stop(edge)
    assert edge.returncode == 0, err
    # the edge reports its own wall time; it finished at the sensor's pace despite the sleeper
    wall = float(err.rsplit(" in ", 1)[1].split(" s")[0])
    assert wall < duration_s + 2.0, err
    with slow.lock:
        n = len(slow.items)
    windows = int(err.split(" windows")[0].rsplit(" ", 1)[1])
    assert windows >= duration_s * 100 - 2
    assert n < windows / 2, f"the sleeping subscriber got {n} of {windows} windows: nothing was dropped?"

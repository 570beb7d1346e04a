"""`arena track --camera`: real Zenoh through a router; corrupt and late windows are skipped."""

from __future__ import annotations

import json
import os
import subprocess
import threading
import time

import pytest

from arena.codec import encode
from arena.messages import EventWindow, Status, Track, decode
from arena.session import open_session
from tests.conftest import arena_cmd

ENV = {**os.environ, "PYTHONUNBUFFERED": "1"}


def _wait_alive(session, key: str, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if any(r.ok for r in session.liveliness().get(key, timeout=1.0)):
            return
        time.sleep(0.2)
    raise AssertionError(f"{key} never appeared")


@pytest.mark.slow
def test_live_tracker_publishes_tracks_answers_get_and_survives_bad_windows(router, tmp_path):
    from simulator.scenarios import Scenario, generate

    rec = generate(Scenario(n_robots=2, pattern="circle", power=1.0, duration_s=2.0, seed=7))
    (tmp_path / "calib.json").write_text(json.dumps(rec.calibration))
    log_csv = tmp_path / "live.csv"
    tracks: list[Track] = []
    statuses: list[Status] = []
    lock = threading.Lock()

    def on_track(sample):
        with lock:
            tracks.append(decode(bytes(sample.payload)))

    def on_status(sample):
        with lock:
            statuses.append(decode(bytes(sample.payload)))

    with open_session(router.settings("client")) as s:
        s.declare_subscriber("arena/robots/*", on_track)
        s.declare_subscriber("arena/status/tracker/tracker-cam0", on_status)
        proc = subprocess.Popen(arena_cmd("track", "--camera", "cam0", "--calibration", str(tmp_path / "calib.json"),
                                          "--tracks-out", str(log_csv), "--queue", "64", "-m", "client",
                                          *router.args), env=ENV, text=True,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        try:
            _wait_alive(s, "arena/alive/tracker/tracker-cam0")
            time.sleep(0.5)
            pub = s.declare_publisher("arena/events/cam0")
            ev = rec.events
            seq = 0
            for k in range(200):
                t0, t1 = k * 10_000, (k + 1) * 10_000
                sl = ev[(ev["t"] >= t0) & (ev["t"] < t1)]
                win = EventWindow(camera="cam0", seq=seq, t_start_us=t0, t_end_us=t1, width=rec.width,
                                  height=rec.height, count=sl.size, codec="planes-zstd/1", data=encode(sl),
                                  publish_ns=time.time_ns())
                pub.put(win.encode())
                seq += 1
                if k == 100:
                    pub.put(b"\x93not a window")                                   # garbage
                    bad = EventWindow(**{**win.__dict__, "seq": seq, "data": win.data[:-7]})
                    pub.put(bad.encode())                                          # truncated payload
                    late = EventWindow(**{**win.__dict__, "seq": seq})
                    pub.put(late.encode())                                         # not newer
                time.sleep(0.004)
            time.sleep(1.5)
            replies = [r.ok for r in s.get("arena/robots/*", timeout=5.0) if r.ok is not None]
            time.sleep(1.2)  # one more status period
            assert proc.poll() is None, "the tracker died"
        finally:
            proc.terminate()
            _, err = proc.communicate(timeout=20)
    with lock:
        got = list(tracks)
        st = list(statuses)
    assert len(got) > 150, err
    late_ids = {m.track_id for m in got if m.window_end_us > 1_500_000 and m.state == "confirmed"}
    assert len(late_ids) == 2
    m = got[-1]
    assert m.camera == "cam0" and 0 < m.x < 1.83 and 0 < m.y < 1.83 and m.edge_publish_ns and m.tracker_publish_ns
    fleet = [decode(bytes(r.payload)) for r in replies]
    assert {f.track_id for f in fleet} == late_ids
    assert {str(r.key_expr) for r in replies} == {f"arena/robots/{i}" for i in late_ids}
    last = st[-1]
    assert last.counters.get("windows_bad", 0) >= 2 and last.counters.get("windows_late", 0) >= 1
    assert last.counters.get("windows_in", 0) >= 190
    assert log_csv.read_text().startswith("t_us,track_id,robot,x_m,y_m,yaw_rad")


@pytest.mark.slow
def test_simulator_camera_edge_and_tracker_end_to_end(router, tmp_path):
    """The simulator's TCP camera -> `arena edge` -> `arena track` -> a subscriber, all real."""
    import numpy as np

    from arena.formats.tables import TRACK_DTYPE, TRUTH_DTYPE
    from groundtruth.metrics import evaluate
    from simulator.evt3 import CameraServer, canonical_order
    from simulator.scenarios import Scenario, generate

    rec = generate(Scenario(n_robots=2, pattern="circle", power=1.0, duration_s=3.0, seed=9))
    (tmp_path / "calib.json").write_text(json.dumps(rec.calibration))
    events = canonical_order(rec.events)
    got: list[Track] = []
    lock = threading.Lock()

    def on_track(sample):
        with lock:
            got.append(decode(bytes(sample.payload)))

    procs = []
    with CameraServer(drop_when_slow=False) as cam, open_session(router.settings("client")) as s:
        s.declare_subscriber("arena/robots/*", on_track)
        try:
            procs.append(subprocess.Popen(arena_cmd("track", "--camera", "sim0", "--calibration",
                                                    str(tmp_path / "calib.json"), "-m", "client", *router.args),
                                          env=ENV, text=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE))
            _wait_alive(s, "arena/alive/tracker/tracker-sim0")
            procs.append(subprocess.Popen(arena_cmd("edge", f"{cam.url}?width={rec.width}&height={rec.height}",
                                                    "--camera", "sim0", *router.args),
                                          env=ENV, text=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE))
            _wait_alive(s, "arena/alive/edge/sim0")
            deadline = time.monotonic() + 20
            while cam.n_clients < 1 and time.monotonic() < deadline:
                time.sleep(0.02)
            time.sleep(0.5)
            t = events["t"]
            for a in range(0, int(t[-1]) + 30_000, 10_000):   # real time pace
                cam.publish(events[(t >= a) & (t < a + 10_000)], until_us=a + 10_000)
                time.sleep(0.01)
            time.sleep(2.0)
            assert all(p.poll() is None for p in procs), "a service died"
        finally:
            for p in procs:
                p.terminate()
            for p in procs:
                p.communicate(timeout=20)
    with lock:
        msgs = list(got)
    assert len(msgs) > 100
    tracks = np.array([(m.stamp_us, str(m.track_id), "", m.x, m.y, m.yaw if m.yaw is not None else np.nan,
                        m.vx, m.vy, m.u_px, m.v_px, m.state, m.n_events) for m in msgs], dtype=TRACK_DTYPE)
    truth = np.empty(rec.truth.size, TRUTH_DTYPE)
    for k in ("t_us", "x_m", "y_m", "yaw_rad", "vx_mps", "vy_mps"):
        truth[k] = rec.truth[k]
    truth["robot"] = np.asarray(rec.robot_names)[rec.truth["robot"]]
    scores = evaluate(tracks, truth, gate_m=0.10)
    # real time on a shared machine may drop a few slices: identities and accuracy must hold
    assert scores.id_switches == 0 and scores.precision > 0.99 and scores.mae_cm < 2.0
    assert scores.recall > 0.8


@pytest.mark.slow
def test_tracker_sigkilled_and_restarted_brings_back_its_track_ids(router, tmp_path):
    """SIGKILL the live tracker mid-run while the robots drive on; the restarted tracker
    restores its state file and publishes the same track keys, with no ID switch. (Without
    the restore, a fresh tracker numbers this seed's robots the other way round at the
    restart: the ID-switch check fails.)"""
    import signal

    import numpy as np

    from arena.formats.tables import TRACK_DTYPE, TRUTH_DTYPE
    from groundtruth.metrics import evaluate
    from simulator.evt3 import CameraServer, canonical_order
    from simulator.scenarios import Scenario, generate

    rec = generate(Scenario(n_robots=2, pattern="circle", power=1.0, duration_s=5.0, seed=4))
    (tmp_path / "calib.json").write_text(json.dumps(rec.calibration))
    events = canonical_order(rec.events)
    state = tmp_path / "tracker-state.json"
    got: list[tuple[int, Track]] = []  # (tracker run, message)
    run = [0]
    lock = threading.Lock()

    def on_track(sample):
        with lock:
            got.append((run[0], decode(bytes(sample.payload))))

    def tracker() -> subprocess.Popen:
        return subprocess.Popen(arena_cmd("-v", "track", "--camera", "sim0", "--calibration", str(tmp_path / "calib.json"),
                                          "--state", str(state), *router.args),
                                env=ENV, text=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)

    t = events["t"]

    def play(cam, a0: int, a1: int) -> None:
        for a in range(a0, a1, 10_000):   # real time pace
            cam.publish(events[(t >= a) & (t < a + 10_000)], until_us=a + 10_000)
            time.sleep(0.01)

    procs = []
    with CameraServer(drop_when_slow=False) as cam, open_session(router.settings("client")) as s:
        s.declare_subscriber("arena/robots/*", on_track)
        try:
            procs.append(tracker())
            _wait_alive(s, "arena/alive/tracker/tracker-sim0")
            procs.append(subprocess.Popen(arena_cmd("edge", f"{cam.url}?width={rec.width}&height={rec.height}",
                                                    "--camera", "sim0", *router.args),
                                          env=ENV, text=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE))
            _wait_alive(s, "arena/alive/edge/sim0")
            deadline = time.monotonic() + 20
            while cam.n_clients < 1 and time.monotonic() < deadline:
                time.sleep(0.02)
            time.sleep(0.5)
            play(cam, 0, 2_500_000)
            time.sleep(1.5)  # the state file is written every second
            assert state.exists(), "no state file written"
            procs[0].send_signal(signal.SIGKILL)
            procs[0].wait(timeout=10)
            with lock:
                run[0] = 1
            # the robots drive on for 0.6 s (~28 cm on their circles) while the tracker is down
            play(cam, 2_500_000, 3_100_000)
            procs[0] = tracker()
            _wait_alive(s, "arena/alive/tracker/tracker-sim0")
            time.sleep(0.5)
            play(cam, 3_100_000, int(t[-1]) + 30_000)
            time.sleep(2.0)
            assert all(p.poll() is None for p in procs), "a service died"
        finally:
            for p in procs:
                if p.poll() is None:
                    p.terminate()
            for p in procs:
                p.communicate(timeout=20)
    with lock:
        msgs = list(got)
    before = {str(m.track_id) for r, m in msgs if r == 0 and m.state != "tentative"}
    after = [m for r, m in msgs if r == 1]
    assert len(before) == 2, f"tracks before the kill: {before}"
    assert after and {str(m.track_id) for m in after} == before, \
        f"IDs {before} before the SIGKILL, {sorted({m.track_id for m in after})} after the restart"
    # after the restart, the restored tracks follow the robots (no ID switch over the whole run)
    msgs_after = [m for m in after if m.stamp_us >= 3_300_000]
    tracks = np.array([(m.stamp_us, str(m.track_id), "", m.x, m.y, m.yaw if m.yaw is not None else np.nan,
                        m.vx, m.vy, m.u_px, m.v_px, m.state, m.n_events) for _, m in msgs], dtype=TRACK_DTYPE)
    truth = np.empty(rec.truth.size, TRUTH_DTYPE)
    for k in ("t_us", "x_m", "y_m", "yaw_rad", "vx_mps", "vy_mps"):
        truth[k] = rec.truth[k]
    truth["robot"] = np.asarray(rec.robot_names)[rec.truth["robot"]]
    scores = evaluate(tracks, truth, gate_m=0.10)
    assert scores.id_switches == 0, scores
    assert len(msgs_after) > 50 and scores.precision > 0.97, scores

"""The live tracker's last-resort handler: a window whose processing fails for a reason no check
foresaw is counted (``windows_failed``), logged with the exception, and the loop goes on."""

from __future__ import annotations

import json
import os
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from arena.codec import encode
from arena.messages import EventWindow, Status, Track, decode
from arena.session import open_session
from tests.conftest import arena_cmd

ENV = {**os.environ, "PYTHONUNBUFFERED": "1"}


@pytest.mark.slow
@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full (a disk that is always full)")
def test_a_window_that_fails_to_process_is_counted_and_the_tracker_goes_on(router, tmp_path):
    """The codec and the pipeline refuse bad windows cleanly (fuzzed: nothing escapes), so the
    real failure used is the disk: the tracks CSV on /dev/full, where writing a window's rows
    fails with ENOSPC once the file buffer fills. Before the handler the OSError killed the
    tracker at its ~50th window; now those windows are counted and the next ones are tracked."""
    from simulator.scenarios import Scenario, generate

    rec = generate(Scenario(n_robots=2, pattern="circle", power=1.0, duration_s=3.0, seed=7))
    (tmp_path / "calib.json").write_text(json.dumps(rec.calibration))
    ev = rec.events
    n_win = 280
    cut = np.searchsorted(ev["t"], np.arange(n_win + 1) * 10_000)
    got: list[Track] = []
    statuses: list[Status] = []
    lock = threading.Lock()

    def on_track(sample):
        with lock:
            got.append(decode(bytes(sample.payload)))

    def on_status(sample):
        with lock:
            statuses.append(decode(bytes(sample.payload)))

    with open_session(router.settings("client")) as s:
        s.declare_subscriber("arena/robots/*", on_track)
        s.declare_subscriber("arena/status/tracker/tracker-cam0", on_status)
        proc = subprocess.Popen(arena_cmd("track", "--camera", "cam0", "--calibration", str(tmp_path / "calib.json"),
                                          "--tracks-out", "/dev/full", "--no-state", "-m", "client", *router.args),
                                env=ENV, text=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        try:
            deadline = time.monotonic() + 60
            while not any(r.ok for r in s.liveliness().get("arena/alive/tracker/tracker-cam0", timeout=1.0)):
                assert time.monotonic() < deadline and proc.poll() is None, "the tracker never came up"
                time.sleep(0.2)
            pub = s.declare_publisher("arena/events/cam0")
            t0 = time.monotonic()
            for k in range(n_win):
                delay = t0 + k * 0.01 - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                sl = ev[cut[k]:cut[k + 1]]
                pub.put(EventWindow(camera="cam0", seq=k, t_start_us=k * 10_000, t_end_us=(k + 1) * 10_000,
                                    width=rec.width, height=rec.height, count=sl.size, codec="planes-zstd/1",
                                    data=encode(sl), publish_ns=time.time_ns()).encode())
            deadline = time.monotonic() + 10   # until a status counts the failures and the last window
            while time.monotonic() < deadline:
                with lock:
                    c = statuses[-1].counters if statuses else {}
                if c.get("windows_failed", 0) >= 1 and c.get("windows_in", 0) >= n_win - 10:
                    break
                time.sleep(0.1)
            assert proc.poll() is None, "the tracker died"
        finally:
            if proc.poll() is None:
                proc.terminate()
            _, err = proc.communicate(timeout=20)
    with lock:
        msgs = list(got)
        c = statuses[-1].counters if statuses else {}
    assert c.get("windows_failed", 0) >= 1, (c, err)
    assert c.get("windows_in", 0) >= n_win - 10, (c, err)
    logged = [ln for ln in err.splitlines() if "window not processed" in ln]
    assert logged and "OSError" in logged[0] and "No space left" in logged[0] and "windows_failed" in logged[0], err
    # tracking went on after the failures: both robots up to the last windows
    late = {m.track_id for m in msgs if m.window_end_us > (n_win - 20) * 10_000 and m.state == "confirmed"}
    assert len(late) == 2, err

"""tracker layers (issue 21): ``tracker.service.run`` takes built objects (a session, a pipeline
factory, a CSV writer, a state path) and knows no argparse; ``tracker.cli`` builds them."""

from __future__ import annotations

import ast
import inspect
import io
import json
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np

from arena.codec import encode
from arena.keys import events_key, status_key
from arena.messages import EventWindow, Status, decode
from arena.session import open_session
from tests.tracker.synth import calibration_dict, line_pose, window
from tracker.calibration import Calibration

REPO = Path(__file__).resolve().parents[2]


def test_the_service_imports_no_cli_and_takes_no_argparse_namespace():
    tree = ast.parse((REPO / "tracker" / "service.py").read_text())
    imported = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    imported |= {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    assert not {m for m in imported if m and (m == "argparse" or m.startswith("tracker.cli"))}, imported
    code = ("import sys, json, inspect, tracker.service as s; "
            "print(json.dumps(['tracker.cli' in sys.modules, list(inspect.signature(s.run).parameters)]))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True, cwd=REPO)
    cli_loaded, params = json.loads(r.stdout.strip().splitlines()[-1])
    assert cli_loaded is False
    assert params[:4] == ["session", "make_pipeline", "camera", "stop"] and "args" not in params


def _window(ev, k: int, t0: int) -> bytes:
    a, b = t0 + k * 10_000, t0 + (k + 1) * 10_000
    sl = ev[(ev["t"] >= a) & (ev["t"] < b)]
    return EventWindow(camera="lay0", seq=k, t_start_us=a, t_end_us=b, width=640, height=480, count=sl.size,
                       codec="planes-zstd/1", data=encode(sl), publish_ns=1).encode()


def test_run_tracks_with_the_objects_it_is_given(router, tmp_path):
    from arena.formats.tables import TrackCsvWriter
    from tracker.pipeline import Pipeline
    from tracker.service import run

    cal = Calibration.from_dict(calibration_dict())
    made = []

    def make_pipeline():
        made.append(Pipeline(cal, accumulation_us=60_000))
        return made[-1]

    t0, n = 2_000_000, 30
    ev = window(np.random.default_rng(3), [line_pose(200, 200, 100.0, 0.0, t_start=t0)], t0, t0 + n * 10_000)
    csv, state = io.StringIO(), tmp_path / "state.json"
    stop, seen, err = threading.Event(), threading.Event(), []

    def on_status(sample) -> None:
        st = decode(bytes(sample.payload))
        if isinstance(st, Status) and st.counters.get("windows_in", 0) >= n:
            seen.set()

    with open_session(router.settings("client")) as session:
        sub = session.declare_subscriber(status_key("tracker", "layers"), on_status)

        def target():
            try:
                run(session, make_pipeline, "lay0", stop, name="layers", tracker="fleet", detector="default",
                    state_path=state, writer=TrackCsvWriter(csv))
            except BaseException as exc:  # pragma: no cover - reported below
                err.append(exc)

        th = threading.Thread(target=target)
        th.start()
        try:
            pub = session.declare_publisher(events_key("lay0"))
            subscribed = threading.Event()
            listener = pub.declare_matching_listener(lambda st: subscribed.set() if st.matching else None)
            if pub.matching_status.matching:
                subscribed.set()
            assert subscribed.wait(20), "the tracker did not subscribe to its camera's windows"
            listener.undeclare()
            for k in range(n):
                pub.put(_window(ev, k, t0))
            assert seen.wait(20), "the tracker did not report 30 windows in"
        finally:
            stop.set()
            th.join(timeout=20)
            sub.undeclare()
    assert not err and not th.is_alive()
    assert len(made) == 1                                     # run built its first pipeline from the factory
    rows = [line.split(",") for line in csv.getvalue().splitlines()[1:]]
    assert rows and {r[1] for r in rows} == {"1"}
    x = float(rows[-1][3])
    assert 0.6 < x < 1.0, x                                    # u = 200 + 100 px/s * ~0.3 s, 250 px/m from u = 20
    saved = json.loads(state.read_text())                      # the fleet state, written when it stopped
    assert saved["camera"] == "lay0" and [t["id"] for t in saved["fleet"]["tracks"]] == [1]


def test_run_live_stays_in_the_cli():
    import tracker.cli
    import tracker.service

    assert not hasattr(tracker.service, "run_live")
    assert "args" in inspect.signature(tracker.cli.run_live).parameters

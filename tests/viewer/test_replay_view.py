"""`arena replay` into the viewer's subscriptions: the viewer shows the recorded tracks again."""

from __future__ import annotations

import math
import subprocess

import numpy as np

from arena.messages import Track
from arena.session import ZenohSettings, open_session
from recorder.mcapio import RunWriter
from tests.conftest import arena_cmd
from tests.viewer.feed import CALIBRATION, pose, window
from viewer.service import subscribe
from viewer.state import ViewerState, arena_to_pixel_homography


def test_replayed_run_shows_the_recorded_tracks(router, tmp_path):
    rng = np.random.default_rng(0)
    run = tmp_path / "run"
    run.mkdir()
    recorded = {"zumo1": [], "zumo2": []}
    t0 = 1_800_000_000_000_000_000
    with RunWriter(run / "arena.mcap") as w:
        for seq in range(60):  # 1.2 s of a run, 20 ms apart
            t = seq * 0.02
            poses = [pose(0, t), pose(1, t)]
            w.add("arena/events/cam0", window(seq, int(t * 1e6) + 10_000, poses, rng).encode(), t0 + seq * 20_000_000)
            for i, (x, y, yaw) in enumerate(poses):
                name = f"zumo{i + 1}"
                w.add(f"arena/robots/{name}", Track(track_id=i + 1, robot=name, stamp_us=int(t * 1e6), x=x, y=y,
                                                    yaw=yaw).encode(), t0 + seq * 20_000_000 + 1)
                recorded[name].append((round(x, 4), round(y, 4)))
    state = ViewerState(H_arena_to_px=arena_to_pixel_homography(CALIBRATION))
    with open_session(ZenohSettings(mode="client", connect=[router.endpoint])) as s:
        subs = subscribe(s, state)
        r = subprocess.run(arena_cmd("replay", str(run), "--speed", "4", "-m", "client", *router.args),
                           capture_output=True, text=True, timeout=60)
        for sub in subs:
            sub.undeclare()
    assert r.returncode == 0, r.stderr
    assert "replayed 180 messages" in r.stdout
    snap = state.snapshot()
    tracks = {t["robot"]: t for t in snap["tracks"]}
    assert set(tracks) == {"zumo1", "zumo2"}
    for name, points in recorded.items():
        assert [tuple(p) for p in tracks[name]["trail_m"]] == points  # the same tracks, in order
    assert snap["counts"]["windows"] == 60 and snap["image"]["width"] == 320
    img = state.render_frame()
    x, y, _ = pose(0, 59 * 0.02)
    u, v = 40 + x * 130, 230 - y * 120  # the last events sit around the last pose
    patch = img[int(v) - 10:int(v) + 10, int(u) - 10:int(u) + 10]
    assert (patch != 255).any(axis=2).sum() > 50 and math.isfinite(u)

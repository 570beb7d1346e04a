"""The demo compiles numba kernels up front only when numba's cache lacks them."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from demo.warmup import KERNELS, kernels_cached


def test_kernels_cached_sees_the_files_numba_writes(tmp_path, monkeypatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    codec = ("arena.codec:_encode_planes", "arena.codec:_decode_planes")
    assert not kernels_cached(codec)
    assert not kernels_cached()
    code = ("import numpy as np; from arena.codec import DEFAULT_CODEC, encode, decode; "
            "from arena.events import make_events; "
            "ev = make_events(np.arange(50) % 640, np.arange(50) % 480, np.arange(50) % 2, np.arange(50) * 7); "
            "assert (decode(DEFAULT_CODEC, encode(ev, DEFAULT_CODEC), ev.size) == ev).all()")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120,
                   env={**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)})
    assert kernels_cached(codec)          # numba's own index files, found by name
    assert not kernels_cached(KERNELS)    # the simulator's and tracker's are still missing


@pytest.mark.slow
def test_arena_demo_prepare_compiles_every_kernel_once(tmp_path, monkeypatch):
    """The README's install step: ``arena demo --prepare`` fills an empty numba cache with every
    kernel the demo's services use, and a second call finds nothing to do."""
    from tests.conftest import arena_cmd

    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    assert not kernels_cached()
    first = subprocess.run(arena_cmd("demo", "--prepare"), capture_output=True, text=True, timeout=300, env=env)
    assert first.returncode == 0, first.stdout[-2000:] + first.stderr[-2000:]
    assert "kernels compiled in" in first.stdout, first.stdout
    assert kernels_cached()
    second = subprocess.run(arena_cmd("demo", "--prepare"), capture_output=True, text=True, timeout=60, env=env)
    assert second.returncode == 0 and "nothing to do" in second.stdout, second.stdout + second.stderr


def test_index_files_left_by_others_do_not_count_as_the_demo_warm_up(tmp_path, monkeypatch):
    """A test or bench that compiled the kernels (for its own argument types) leaves numba's index
    files; only the demo's warm-up, on the current sources, lets the demo skip compiling."""
    from demo import warmup

    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(warmup, "kernels_cached", lambda kernels=KERNELS: True)   # every index file there
    assert not warmup.warmed_up()
    warmup.mark_warmed_up()
    assert (tmp_path / warmup.STAMP).is_file() and warmup.warmed_up()
    # a source edited since (numba's own staleness test: size and mtime) makes the stamp stale
    fp = warmup._fingerprint()
    name = next(iter(fp["files"]))
    fp["files"][name][1] += 1
    monkeypatch.setattr(warmup, "_fingerprint", lambda: fp)
    assert not warmup.warmed_up()


_LIVE_EDGE_CASES = r'''
import sys
import numpy as np

def signatures():
    from numba.core.dispatcher import Dispatcher
    out = {}
    for name, mod in list(sys.modules.items()):
        if name.split(".")[0] in ("arena", "camera_edge", "tracker", "simulator"):
            for attr, obj in list(vars(mod).items()):
                if isinstance(obj, Dispatcher):
                    out[f"{name}:{attr}"] = {str(s) for s in obj.signatures}
    return out

from demo.warmup import compile_sim_edge, compile_tracker
compile_sim_edge()
compile_tracker()
before = signatures()

from arena.codec import CODECS, decode, encode
from arena.events import empty_events, make_events
from arena.formats.evt3 import Evt3Decoder, encode_evt3
from arena.messages import EventWindow
from camera_edge.pipeline import EdgePipeline
from simulator.camera import CeilingCamera
from simulator.evt3 import Evt3Encoder, canonical_order
from tracker.calibration import Calibration
from tracker.pipeline import Pipeline

cal = Calibration.from_dict(CeilingCamera(640, 480).calibration(), "the simulated camera")
for ev in (empty_events(0), make_events([5], [7], [1], [1234]), make_events([5, 9], [7, 7], [1, 0], [1234, 1290])):
    # the simulator's stream, the edge's decoder (a chunk of time words first), slicer and codec,
    # then the tracker's window decode and detection: as live, with zero, one and two events
    Evt3Encoder().encode(canonical_order(ev), until_us=20_000)
    dec = Evt3Decoder()
    dec.feed(np.array([0x8000, 0x6000 | 5], "<u2").tobytes())
    pipe = EdgePipeline([], slice_us=10_000)
    for w in pipe.push(dec.feed(encode_evt3(ev)), 30_000) + pipe.flush():
        for codec in CODECS:
            data = encode(w.events, codec, t_ref_us=w.t_start_us)
            msg = EventWindow(camera="cam0", seq=0, t_start_us=w.t_start_us, t_end_us=w.t_end_us, width=640,
                              height=480, codec=codec, count=w.events.size, data=data)
            win = EventWindow.decode(msg.encode())
            decode(win.codec, bytes(win.data), win.count)
    tracker = Pipeline(cal, fleet_size=4)
    tracker.push(ev, 10_000)
    tracker.push(empty_events(0), 20_000)
after = signatures()
new = {k: sorted(after[k] - before.get(k, set())) for k in after if after[k] - before.get(k, set())}
for k, v in new.items():
    print(k, v)
print("new specialisations:", len(new))
'''


def test_the_warm_up_covers_the_live_paths_empty_and_single_event_cases():
    """numba types an array of at most one element as contiguous, a specialisation of its own: the
    warm-up must compile it, or a live edge/tracker compiles it (seconds of CPU) on its first
    chunk of time words only, or empty window, while the simulator runs."""
    out = subprocess.run([sys.executable, "-c", _LIVE_EDGE_CASES], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.strip().endswith("new specialisations: 0"), out.stdout

"""The demo compiles numba kernels up front only when numba's cache lacks them."""

from __future__ import annotations

import os
import subprocess
import sys

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

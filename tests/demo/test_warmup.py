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

"""A read-only install run by a user with a read-only home (the systemd units' ProtectSystem=strict)
still imports and runs the numba kernels: arena gives numba a cache directory it can write."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import arena

ROOT = Path(arena.__file__).resolve().parents[1]   # the tree holding arena/, tracker/, ...

CODE = """
import tracker.dbscan, simulator.dvs, camera_edge.filters     # each package, imported directly
import numba, numpy as np
from arena.codec import DEFAULT_CODEC, decode, encode
from arena.events import make_events
ev = make_events(np.arange(50) % 640, np.arange(50) % 480, np.arange(50) % 2, np.arange(50) * 7)
assert (decode(DEFAULT_CODEC, encode(ev, DEFAULT_CODEC), ev.size) == ev).all()
print("cache dir", numba.config.CACHE_DIR)
"""


def _read_only(paths: list[Path], command: str) -> list[str]:
    binds = " && ".join(f"mount --bind '{p}' '{p}' && mount -o remount,ro,bind '{p}' '{p}'" for p in paths)
    return ["unshare", "-m", "sh", "-c", f"{binds} && {command}"]


def test_kernels_import_and_cache_when_neither_the_install_nor_home_is_writable(tmp_path):
    if shutil.which("unshare") is None or os.geteuid() != 0:
        pytest.skip("needs root and unshare(1) to mount the checkout read-only in a private namespace")
    home, tmp = tmp_path / "home", tmp_path / "tmp"
    home.mkdir()
    tmp.mkdir()
    probe = subprocess.run(_read_only([home], "true"), capture_output=True, text=True, timeout=30)
    if probe.returncode != 0:
        pytest.skip(f"cannot make a private mount namespace here: {probe.stderr.strip()}")
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "XDG_CACHE_HOME")}
    env.update(HOME=str(home), TMPDIR=str(tmp), PYTHONDONTWRITEBYTECODE="1")
    (tmp / "check.py").write_text(CODE)
    cmd = f"cd '{tmp}' && '{sys.executable}' check.py"
    out = subprocess.run(_read_only([ROOT, home], cmd), capture_output=True, text=True, timeout=180, env=env)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]
    fallback = tmp / f"arena-numba-{os.getuid()}"
    assert f"cache dir {fallback}" in out.stdout, out.stdout
    assert list(fallback.rglob("codec._encode_planes-*.nbi")), "the codec kernel was not cached there"


CHECK = """
import os, sys
from pathlib import Path
from numba.core.caching import UserWideCacheLocator
import tracker.dbscan as m
from demo.warmup import kernels_cached, numba_cache_dirs
ours = numba_cache_dirs(Path(m.__file__).parent)
numbas = UserWideCacheLocator.from_function(m.dbscan_grid, m.__file__).get_cache_path()
print("ours", ours, "numba", numbas)
assert ours == [Path(numbas)], (ours, numbas)
codec = ("arena.codec:_encode_planes",)
assert not kernels_cached(codec)
import numpy as np
from arena.codec import DEFAULT_CODEC, encode
from arena.events import make_events
encode(make_events(np.arange(5), np.arange(5), np.arange(5) % 2, np.arange(5)), DEFAULT_CODEC)
assert kernels_cached(codec)
print("found in the user-wide cache")
"""


def test_the_demo_finds_kernels_in_numbas_user_wide_cache_of_a_read_only_install(tmp_path):
    # install read-only, home writable (pip install as root, run as a user): numba caches in
    # ~/.cache/numba, and `arena demo` must look there too, or it compiles on every run
    if shutil.which("unshare") is None or os.geteuid() != 0:
        pytest.skip("needs root and unshare(1) to mount the checkout read-only in a private namespace")
    home = tmp_path / "home"
    home.mkdir()
    probe = subprocess.run(_read_only([home], "true"), capture_output=True, text=True, timeout=30)
    if probe.returncode != 0:
        pytest.skip(f"cannot make a private mount namespace here: {probe.stderr.strip()}")
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "XDG_CACHE_HOME")}
    env.update(HOME=str(home), PYTHONDONTWRITEBYTECODE="1")
    (tmp_path / "check.py").write_text(CHECK)
    cmd = f"cd '{tmp_path}' && '{sys.executable}' check.py"
    out = subprocess.run(_read_only([ROOT], cmd), capture_output=True, text=True, timeout=180, env=env)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]
    assert "found in the user-wide cache" in out.stdout
    assert list((home / ".cache" / "numba").rglob("codec._encode_planes-*.nbi"))

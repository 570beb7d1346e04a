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
    cmd = f"cd '{tmp}' && '{sys.executable}' -c '{CODE}'"
    out = subprocess.run(_read_only([ROOT, home], cmd), capture_output=True, text=True, timeout=180, env=env)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]
    fallback = tmp / f"arena-numba-{os.getuid()}"
    assert f"cache dir {fallback}" in out.stdout, out.stdout
    assert list(fallback.rglob("codec._encode_planes-*.nbi")), "the codec kernel was not cached there"

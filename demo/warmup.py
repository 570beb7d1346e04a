"""Compile the demo's numba kernels once, in two processes side by side, before its services start.

On the first run after installing, numba compiles every kernel (about 12 s of CPU for the
simulator's and the edge's, 12 s for the tracker's). Left to the services, that work
competes with the running simulator and with itself on a 2-core machine, and the first track
came after about a minute. Compiled here first, on both cores and with nothing else running,
the services then load the kernels from numba's on-disk cache in a fraction of a second.

``python -m demo.warmup sim-edge|tracker`` compiles one half and prints ``compiled in N s``.
:func:`kernels_cached` tells the demo whether it is needed at all (without importing numba).
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import sys
import time
from pathlib import Path

#: one kernel per module the demo compiles: "package.module:function"
KERNELS = ("simulator.dvs:_dvs_block", "simulator.world:_physics_step", "simulator.evt3:_encode",
           "arena.formats.evt3:_decode", "arena.codec:_encode_planes", "arena.codec:_decode_planes",
           "tracker.dbscan:_cores_kernel", "tracker.density:_update", "tracker.accumulate:_apply",
           "tracker.detect:_split_cluster",
           "arena.formats.csvfile:_parse_lines", "arena.formats.csvfile:_format_lines")


def numba_cache_dirs(pkg_dir: Path) -> list[Path]:
    """Where numba looks for the cached kernels of the package in ``pkg_dir``, in its own order:
    ``NUMBA_CACHE_DIR`` if set; else the package's ``__pycache__`` if numba can write there; else
    its user-wide cache (``~/.cache/numba/<package>_<sha1 of the package path>``), which numba
    uses for a read-only install."""
    from arena import numba_user_cache, numba_writes_beside   # also settles NUMBA_CACHE_DIR first

    if os.environ.get("NUMBA_CACHE_DIR"):
        return [Path(os.environ["NUMBA_CACHE_DIR"])]
    pkg_dir = Path(os.path.abspath(pkg_dir))
    if numba_writes_beside(str(pkg_dir)):
        return [pkg_dir / "__pycache__"]
    return [Path(numba_user_cache()) / f"{pkg_dir.name}_{hashlib.sha1(str(pkg_dir).encode()).hexdigest()}"]


def kernels_cached(kernels: tuple[str, ...] = KERNELS) -> bool:
    """True when numba's cache holds an index for every kernel in ``kernels`` (so the demo can
    skip compiling). Looks for the files only; a stale index just compiles as before."""
    for kernel in kernels:
        module, func = kernel.split(":")
        pkg, _, leaf = module.rpartition(".")
        spec = importlib.util.find_spec(pkg)
        if spec is None or not spec.submodule_search_locations:
            return False
        pattern = f"{leaf}.{func}-*.nbi"
        dirs = numba_cache_dirs(Path(list(spec.submodule_search_locations)[0]))
        if not any(next(d.rglob(pattern), None) is not None for d in dirs if d.is_dir()):
            return False
    return True


#: the packages whose kernels the warm-up compiles (their sources make up its fingerprint)
PACKAGES = ("arena", "camera_edge", "tracker", "simulator")
STAMP = "arena-demo-warmup.json"


def _fingerprint() -> dict:
    """What the warm-up's cache depends on: numba's and Python's versions, and the size and
    modification time of every source file of :data:`PACKAGES` (numba's own test of a stale
    cache entry, applied to all of them at once)."""
    from importlib.metadata import version

    files = {}
    for pkg in PACKAGES:
        spec = importlib.util.find_spec(pkg)
        if spec is None or not spec.submodule_search_locations:
            continue
        root = Path(list(spec.submodule_search_locations)[0])
        for f in sorted(root.rglob("*.py")):
            st = f.stat()
            files[str(f.relative_to(root.parent))] = [st.st_size, st.st_mtime_ns]
    return {"numba": version("numba"), "python": sys.version.split()[0], "files": files}


def _stamp_path() -> Path:
    return numba_cache_dirs(Path(__file__).resolve().parent)[0] / STAMP


def warmed_up() -> bool:
    """True when the demo's own warm-up (:func:`compile_all` or ``arena demo --prepare``) ran on
    the current sources and numba still holds its kernels. Index files alone do not say enough:
    a test or a bench that compiled a kernel for other argument types leaves one, and the
    demo's services then compiled the missing specialisations while the simulator ran (a 2-core
    machine fell 2.3 s behind real time)."""
    import json

    try:
        stamp = json.loads(_stamp_path().read_text())
    except (OSError, ValueError):
        return False
    return stamp == _fingerprint() and kernels_cached()


def mark_warmed_up() -> None:
    """Record that the warm-up ran on the current sources (see :func:`warmed_up`)."""
    import json

    path = _stamp_path()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(_fingerprint()))
    except OSError:   # a read-only cache: the demo warms up again next time, which is only slower
        pass


def compile_sim_edge() -> None:
    """The simulator's kernels, then the edge's (the halves take about as long: ~11 s each)."""
    from arena.codec import DEFAULT_CODEC
    from camera_edge.pipeline import warm_up as warm_edge
    from simulator.camera import CeilingCamera
    from simulator.dvs import DvsParams
    from simulator.simulation import warm_up
    from simulator.world import RobotSpec, World

    robots = [RobotSpec(f"r{i}", (25, 25, 25), start=(0.4 + 0.3 * i, 0.6, 0.0)) for i in range(2)]
    warm_up(World(robots), CeilingCamera(640, 480), DvsParams())
    warm_edge(list, 640, 480, DEFAULT_CODEC)


def compile_tracker() -> None:
    """The tracker's kernels (its grid DBSCAN alone takes ~5 s) and the CSV reader's."""
    import numpy as np

    from simulator.camera import CeilingCamera
    from tracker.calibration import Calibration
    from tracker.detect import _split_cluster
    from tracker.pipeline import Pipeline
    from tracker.pipeline import warm_up as warm_tracker

    cal = Calibration.from_dict(CeilingCamera(640, 480).calibration(), "the simulated camera")
    warm_tracker(lambda: Pipeline(cal, fleet_size=4))
    _split_cluster(np.zeros(2), np.zeros(2), np.zeros((2, 2)), 1.0, 1.0)   # robots that meet (no split in warm_tracker)
    compile_csv()


def compile_csv() -> None:
    """The CSV reader's and writer's kernels (``arena track --input X.csv``, ``arena convert``)."""
    import tempfile

    from arena.events import make_events
    from arena.formats import read_events, write_events

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "warm.csv"
        write_events(path, make_events([1], [2], [1], [3]), 640, 480)
        read_events(path, width=640, height=480)


PARTS = {"sim-edge": compile_sim_edge, "tracker": compile_tracker}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1 or argv[0] not in PARTS:
        print(f"usage: python -m demo.warmup {'|'.join(PARTS)}", file=sys.stderr)
        return 2
    t0 = time.monotonic()
    PARTS[argv[0]]()
    print(f"compiled {argv[0]} kernels in {time.monotonic() - t0:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

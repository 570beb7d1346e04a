"""Start-up (issue 22): the ``arena`` parser, built for every command, imports no heavy library;
each command imports what it needs when it runs (bench/bench_startup.py measures the rest)."""

from __future__ import annotations

import json
import subprocess
import sys

#: libraries no command's ``register`` may pull in at module level
HEAVY = ("numpy", "numba", "scipy", "cv2", "sklearn", "matplotlib", "mcap", "pandas", "PIL")


def test_building_the_arena_parser_imports_no_heavy_library():
    code = ("import sys, json; from arena.cli import build_parser; p = build_parser(); "
            "print(json.dumps(sorted(m for m in sys.modules if '.' not in m)))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    loaded = set(json.loads(r.stdout.strip().splitlines()[-1]))
    assert "recorder" in loaded and "simulator" in loaded      # every command's module was registered
    assert sorted(loaded & set(HEAVY)) == []


def test_arena_track_help_runs_without_loading_the_tracker():
    code = ("import sys; from arena.cli import main\n"
            "try:\n    main(['track', '--help'])\nexcept SystemExit:\n    pass\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('numpy', 'numba', 'scipy', 'cv2')))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert "arena track" in r.stdout or "usage" in r.stdout
    assert r.stdout.strip().splitlines()[-1] == "[]"

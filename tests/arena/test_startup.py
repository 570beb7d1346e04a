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


def test_a_service_command_loads_only_its_own_entry_point():
    # loading every service's register (simulator, recorder, demo, ...) cost ~0.1 s of CPU at
    # each start of each service; `arena track` needs only tracker.cli's
    others = ("simulator", "recorder", "demo", "viewer", "robot_bridge", "ros2", "camera_edge", "groundtruth")
    code = ("import sys, json; from arena.cli import main\n"
            "try:\n    main(['-v', 'track', '--help'])\nexcept SystemExit:\n    pass\n"
            f"print(json.dumps(['tracker.cli' in sys.modules, sorted(m for m in sys.modules if m.split('.')[0] in {others!r})]))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert "--input" in r.stdout                       # track's own help
    assert json.loads(r.stdout.strip().splitlines()[-1]) == [True, []]


def test_an_unknown_command_still_lists_every_command():
    code = "from arena.cli import main; main(['no-such-command'])"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    assert "invalid choice: 'no-such-command'" in r.stderr
    for name in ("router", "sim", "track", "replay", "ros2"):
        assert f"'{name}'" in r.stderr

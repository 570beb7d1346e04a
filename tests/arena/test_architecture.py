"""The rules of the house, enforced by import-linter with the contracts in pyproject.toml:
arena/ imports no service; services share only arena/; only launchers (demo/), tests and
benchmarks import the simulator; pure cores import no zenoh."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _lint(*args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess:
    exe = shutil.which("lint-imports", path=str(Path(sys.executable).parent)) or shutil.which("lint-imports")
    assert exe, "lint-imports (import-linter, in the test extra) is not installed"
    return subprocess.run([exe, "--no-cache", *args], cwd=cwd, capture_output=True, text=True, timeout=300)


def test_import_contracts_are_kept():
    r = _lint()
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-2000:]
    assert "5 kept, 0 broken" in r.stdout


def test_a_service_importing_another_breaks_a_contract(tmp_path):
    """The contracts can fail: a copy of the tree where a service imports another is refused."""
    copy = tmp_path / "tree"
    shutil.copytree(ROOT, copy, ignore=shutil.ignore_patterns(".git", "__pycache__", "runs", "*.egg-info",
                                                             "bench", "tests", "docs", "deploy"))
    (copy / "viewer" / "sneaky.py").write_text("from tracker import fleet  # a service reaching into another\n")
    with open(copy / "robot_bridge" / "service.py", "a") as f:   # a service reaching into its own CLI
        f.write("\nfrom robot_bridge import cli as _cli  # noqa\n")
    # `python -c` puts the working directory first on sys.path: the copy is what gets analysed
    r = subprocess.run([sys.executable, "-c", "import sys; sys.argv = ['lint-imports', '--no-cache']; "
                        "from importlinter.cli import lint_imports_command; lint_imports_command()"],
                       cwd=copy, capture_output=True, text=True, timeout=300)
    assert r.returncode != 0
    assert "viewer is not allowed to import tracker" in r.stdout and "viewer.sneaky -> tracker.fleet" in r.stdout
    assert "robot_bridge.service is not allowed to import robot_bridge.cli" in r.stdout, r.stdout[-3000:]


# --------------------------------------------------------------------------------------------
# function length (issue 21 item 7)

#: packages whose functions are held to :data:`MAX_FUNCTION_LINES`
CODE_PACKAGES = ("arena", "camera_edge", "tracker", "robot_bridge", "groundtruth", "simulator", "demo",
                 "viewer", "recorder", "ros2")
#: a function longer than this (def line to last line, docstring included) is split into
#: named steps, except a numba kernel (one compiled loop reads better whole)
MAX_FUNCTION_LINES = 80
#: "path::function" -> why it must stay longer (none today)
LONG_FUNCTIONS_ALLOWED: dict[str, str] = {}


def _long_functions(root: Path, packages=CODE_PACKAGES, limit: int = MAX_FUNCTION_LINES) -> dict[str, int]:
    """``"path::function" -> lines`` of each function under ``root/<package>`` longer than
    ``limit`` lines, numba kernels (a decorator naming ``jit``: ``njit``, ``numba.jit``, ...)
    excepted."""
    import ast

    found = {}
    for pkg in packages:
        for f in sorted((root / pkg).rglob("*.py")):
            for n in ast.walk(ast.parse(f.read_text(encoding="utf-8"), filename=str(f))):
                if (isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))
                        and n.end_lineno - n.lineno + 1 > limit
                        and not any("jit" in ast.unparse(d) for d in n.decorator_list)):
                    found[f"{f.relative_to(root).as_posix()}::{n.name}"] = n.end_lineno - n.lineno + 1
    return found


def test_no_function_outside_numba_kernels_is_over_80_lines():
    long = _long_functions(ROOT)
    over = {k: v for k, v in long.items() if k not in LONG_FUNCTIONS_ALLOWED}
    assert not over, (f"functions over {MAX_FUNCTION_LINES} lines (split them into named steps, or list "
                      f"them in LONG_FUNCTIONS_ALLOWED with the reason): {over}")
    stale = sorted(set(LONG_FUNCTIONS_ALLOWED) - set(long))
    assert not stale, f"LONG_FUNCTIONS_ALLOWED lists functions no longer over the limit: {stale}"


def test_the_length_check_finds_a_long_function_and_spares_a_kernel(tmp_path):
    """The check can fail: an 81-line function is found, an 80-line one and a long numba
    kernel are not."""
    pkg = tmp_path / "pkg"
    pkg.mkdir()

    def fn(name: str, lines: int, deco: str = "") -> str:
        return deco + f"def {name}():\n" + "    x = 1\n" * (lines - 2) + "    return x\n"

    (pkg / "m.py").write_text("import numba\n\n" + fn("too_long", 81) + "\n" + fn("just_fits", 80) + "\n"
                              + fn("kernel", 200, "@numba.njit(cache=True)\n") + "\n"
                              + "class C:\n" + "".join("    " + line + "\n"
                                                       for line in fn("method", 90).splitlines()))
    assert _long_functions(tmp_path, packages=("pkg",)) == {"pkg/m.py::too_long": 81, "pkg/m.py::method": 90}

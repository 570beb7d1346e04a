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

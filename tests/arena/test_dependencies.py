"""Every third-party module the project imports is declared in pyproject.toml.

A fresh machine installs only what ``pyproject.toml`` declares: ``pip install -e .`` for the
services, ``pip install -e '.[test]'`` for the tests. An import nobody declared works on a machine
where someone once installed the package by hand and fails everywhere else (``mcap`` did: both
README commands failed on a fresh machine while CI was green). This test reads every ``.py`` file
of the project (its AST, so imports inside functions count, and so do ``pytest.importorskip``
calls), maps each top-level module to the distributions that provide it
(``importlib.metadata.packages_distributions``) and fails on any that the right part of
``pyproject.toml`` does not declare:

- the services' code (every package but ``tests/`` and ``bench/``): ``[project] dependencies``,
  or an optional extra when the import is guarded (``try: ... except ImportError``), as the
  vendor SDKs are;
- ``tests/`` and ``bench/``: the dependencies or any extra.
"""

from __future__ import annotations

import ast
import importlib.metadata as md
import inspect
import sys
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[2]

#: Modules imported (guarded) that no package registry the project uses has: the vendor SDKs a lab
#: installs from its vendor. Each is imported inside ``try`` with an error naming how to install it.
NOT_ON_PYPI = {
    "metavision_core": "Prophesee's OpenEB Python bindings (built from source or the Metavision SDK)",
    "metavision_sdk_core": "Prophesee's Metavision SDK",
}

SKIP_DIRS = {".git", "build", "dist", "venv", ".venv", "node_modules", "__pycache__", "firmware_host"}


def _declared() -> tuple[set[str], dict[str, set[str]]]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    runtime = {canonicalize_name(Requirement(r).name) for r in project.get("dependencies", [])}
    extras = {name: {canonicalize_name(Requirement(r).name) for r in reqs}
              for name, reqs in project.get("optional-dependencies", {}).items()}
    return runtime, extras


def _local_modules() -> set[str]:
    """Top-level names that are the project's own: its packages, and modules that tests and
    benchmarks import from their own folder (``bridge_testkit``, ``netlab``, ...)."""
    names = {p.name for p in ROOT.iterdir() if (p / "__init__.py").exists()}
    names |= {p.stem for p in _py_files()}
    return names


def _py_files() -> list[Path]:
    out = []
    for path in sorted(ROOT.rglob("*.py")):
        rel = path.relative_to(ROOT)
        if any(part in SKIP_DIRS or part.startswith(".") for part in rel.parts[:-1]):
            continue
        out.append(path)
    return out


def _distributions_of_modules() -> dict[str, set[str]]:
    """Top-level module -> distributions providing it. ``packages_distributions`` of Python 3.10
    and 3.11 misnames a top-level extension module (``dv_processing.cpython-311-...so``), so the
    installed files are read here too, with ``inspect.getmodulename`` (as Python 3.12 does)."""
    out: dict[str, set[str]] = {mod: {canonicalize_name(d) for d in ds}
                                for mod, ds in md.packages_distributions().items()}
    for dist in md.distributions():
        name = canonicalize_name(dist.metadata["Name"] or "")
        for f in dist.files or ():
            if len(f.parts) == 1:
                mod = inspect.getmodulename(f.name)
                if mod and mod.isidentifier():
                    out.setdefault(mod, set()).add(name)
    return out


def _guarded_nodes(tree: ast.AST) -> set[int]:
    """ids of the nodes inside a ``try`` body whose handlers catch ImportError (or everything)."""
    guarded: set[int] = set()
    for node in ast.walk(tree):
        if not isinstance(node, ast.Try):
            continue
        names = set()
        for h in node.handlers:
            if h.type is None:
                names.add("BaseException")
            for t in (h.type.elts if isinstance(h.type, ast.Tuple) else [h.type]) if h.type else []:
                names.add(getattr(t, "id", getattr(t, "attr", "")))
        if names & {"ImportError", "ModuleNotFoundError", "Exception", "BaseException"}:
            for stmt in node.body:
                guarded.update(id(n) for n in ast.walk(stmt))
    return guarded


def imports_of(source: str) -> list[tuple[str, bool, int]]:
    """``(top-level module, guarded, line)`` of every absolute import in ``source``, including
    ``pytest.importorskip("name")`` calls (always guarded: the test skips without it)."""
    tree = ast.parse(source)
    guarded = _guarded_nodes(tree)
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name.split(".")[0], id(node) in guarded, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.append((node.module.split(".")[0], id(node) in guarded, node.lineno))
        elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
              and node.func.attr == "importorskip" and node.args
              and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)):
            out.append((node.args[0].value.split(".")[0], True, node.lineno))
    return out


def undeclared() -> list[str]:
    """One line per import that pyproject.toml does not declare where it must."""
    runtime, extras = _declared()
    any_extra = set().union(*extras.values()) if extras else set()
    local, stdlib = _local_modules(), set(sys.stdlib_module_names) | {"__future__"}
    dists_of = _distributions_of_modules()
    problems = []
    for path in _py_files():
        rel = path.relative_to(ROOT)
        test_side = rel.parts[0] in ("tests", "bench")
        for mod, guarded, line in imports_of(path.read_text(encoding="utf-8")):
            if mod in stdlib or mod in local:
                continue
            where = f"{rel}:{line}"
            if canonicalize_name(mod) in (runtime | any_extra if (test_side or guarded) else runtime):
                continue   # declared by name (tomli for Python < 3.11; the bench extra's baselines)
            dists = dists_of.get(mod)
            if not dists:
                if guarded and mod in NOT_ON_PYPI:
                    continue
                problems.append(f"{where}: imports {mod!r}, which no installed distribution provides "
                                f"(declare it in pyproject.toml, or list a vendor SDK in NOT_ON_PYPI)")
                continue
            allowed = runtime | any_extra if (test_side or guarded) else runtime
            if not dists & allowed:
                part = "the 'test' extra" if test_side else (
                    "an extra (it is imported inside try/except ImportError)" if guarded else "[project] dependencies")
                problems.append(f"{where}: imports {mod!r} (distribution {', '.join(sorted(dists))}) "
                                f"but {part} of pyproject.toml does not declare it")
    return problems


def test_every_import_is_declared():
    problems = undeclared()
    assert not problems, "undeclared imports:\n" + "\n".join(problems)


def test_the_check_finds_an_undeclared_import(tmp_path):
    """The walker sees imports inside functions, guarded imports and importorskip calls."""
    src = ("import os\n"
           "def f():\n"
           "    import mcap.reader\n"
           "try:\n"
           "    import dv_processing\n"
           "except ImportError:\n"
           "    pass\n"
           "yaml = __import__('pytest').importorskip('yaml')\n"
           "from . import sibling\n")
    got = imports_of(src)
    assert ("os", False, 1) in got and ("mcap", False, 3) in got
    assert ("dv_processing", True, 5) in got and ("yaml", True, 8) in got
    assert all(m != "sibling" for m, *_ in got)


@pytest.mark.parametrize("module", ["mcap", "yaml", "trackeval"])
def test_packages_a_fresh_machine_lacked_are_declared(module):
    """The three imports a fresh machine failed on (issue 18) map to declared distributions."""
    runtime, extras = _declared()
    dists = _distributions_of_modules().get(module, set())
    assert dists, f"{module} is not installed by pip install -e '.[test]'"
    assert dists & (runtime | extras["test"])


def test_ci_runs_the_readme_test_command_in_a_fresh_venv():
    """CI proves a fresh machine: .ci/run makes its own venv outside the checkout and runs the
    README's test command in it, verbatim."""
    import re

    readme = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```bash\n(.*?)\n```", readme, flags=re.S)
    test_cmd = next(b.strip() for b in blocks if "pytest" in b)
    ci = (ROOT / ".ci" / "run").read_text()
    lines = [ln.strip() for ln in ci.splitlines()]
    assert test_cmd in lines, f"{test_cmd!r} is not a line of .ci/run"
    assert "python3 -m venv \"$venv\"" in lines and '. "$venv/bin/activate"' in lines
    assert lines.index('. "$venv/bin/activate"') < lines.index(test_cmd)
    assert 'venv=$(mktemp -d "${TMPDIR:-/tmp}/arena-ci-venv.XXXXXX")' in lines   # outside the checkout

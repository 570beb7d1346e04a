"""Run code in a child Python under an address-space limit, so a decoder that allocates what a
hostile input claims fails with ``MemoryError`` instead of going unnoticed (a large ``malloc`` is
lazy: the resident size of the parent would not grow) or taking the machine down."""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import textwrap
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
#: address space a decoder may take on top of what the process has mapped once warmed up
LIMIT_MB = 256


def limit_address_space(extra_mb: int = LIMIT_MB) -> int:
    """Cap this process's address space at what it maps now plus ``extra_mb`` MiB; returns the cap."""
    with open("/proc/self/statm") as f:
        mapped = int(f.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
    cap = mapped + (extra_mb << 20)
    _, hard = resource.getrlimit(resource.RLIMIT_AS)
    resource.setrlimit(resource.RLIMIT_AS, (cap if hard == resource.RLIM_INFINITY else min(cap, hard), hard))
    return cap


def run_bounded(setup: str, body: str, extra_mb: int = LIMIT_MB, timeout: float = 120.0,
                args: list[str] | None = None) -> subprocess.CompletedProcess:
    """Run ``setup`` (imports, warm-up: numba loads its kernels here), then cap the address space
    at ``extra_mb`` MiB more and run ``body``, in a fresh interpreter at the repository root."""
    code = (textwrap.dedent(setup) + "\nfrom tests.fuzz.harness import limit_address_space\n"
            f"limit_address_space({int(extra_mb)})\n" + textwrap.dedent(body))
    return subprocess.run([sys.executable, "-c", code, *(args or [])], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout, env={**os.environ, "PYTHONPATH": str(REPO)})

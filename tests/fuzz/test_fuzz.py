"""The fuzz suite in CI (bounded: ~1.5 min on 2 cores): every decoder of untrusted bytes
(messages, the window codec, every file reader) fed hypothesis-mutated inputs in a child process
whose address space is capped at 256 MiB over its warmed-up baseline, one input at most 10 s.
Longer runs: ``python bench/fuzz.py --minutes N``."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.fuzz.harness import REPO, run_bounded
from tests.fuzz.targets import TARGETS

GROUPS = {
    "messages-codec": [n for n in TARGETS if not n.startswith("file-")],
    "files-camera": ["file-evt3", "file-evt2", "file-evt21", "file-dat"],
    "files-aedat4": [n for n in TARGETS if n.startswith("file-aedat4")],
    "files-text-numpy": ["file-csv", "file-npy", "file-npz"],
}


def _fuzz(targets: list[str], examples: int, seed: int, timeout: float) -> None:
    r = subprocess.run([sys.executable, "-m", "tests.fuzz.runner", "--targets", ",".join(targets),
                        "--examples", str(examples), "--seed", str(seed)],
                       cwd=REPO, capture_output=True, text=True, timeout=timeout)
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-4000:]
    assert r.stdout.count("\nok   ") == len(targets), r.stdout


def test_every_target_is_in_a_group():
    assert sorted(sum(GROUPS.values(), [])) == sorted(TARGETS)


@pytest.mark.parametrize("group", sorted(GROUPS))
def test_fuzz_decoders_raise_only_their_error_within_memory_and_time(group):
    _fuzz(GROUPS[group], examples=150, seed=0, timeout=240)


@pytest.mark.slow
def test_fuzz_longer_run_with_another_seed():
    _fuzz(list(TARGETS), examples=600, seed=12345, timeout=400)


def test_the_address_space_cap_turns_a_big_allocation_into_memory_error():
    r = run_bounded("import numpy as np", """
        try:
            a = np.ones(512 << 20, np.uint8)
            print("allocated")
        except MemoryError:
            print("MemoryError")
        """)
    assert r.returncode == 0 and r.stdout.strip() == "MemoryError", r.stdout + r.stderr

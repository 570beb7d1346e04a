"""The fuzz suite in CI (bounded: about a minute on 2 cores): every decoder of untrusted bytes
(messages, the window codec, every event file reader, the robot serial protocol, mission commands,
the tracker's state file, calibration JSON, the lab config) fed hypothesis-mutated inputs in a child process
whose address space is capped at 256 MiB over its warmed-up baseline, one input at most 10 s.
Longer runs: ``python bench/fuzz.py --minutes N`` or ``--examples-per-target N``."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from tests.fuzz.harness import REPO, run_bounded
from tests.fuzz.targets import TARGETS

GROUPS = {
    "messages-codec": ["messages"] + [n for n in TARGETS if n.startswith("codec-")],
    "files-camera": ["file-evt3", "file-evt2", "file-evt21", "file-dat"],
    "files-aedat4": [n for n in TARGETS if n.startswith("file-aedat4")],
    "files-text-numpy": ["file-csv", "file-npy", "file-npz"],
    "robot-bridge": ["robot-protocol", "mission"],
    "state-config": ["tracker-state", "calibration-json", "lab-config-toml", "lab-config-tree"],
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


#: the targets of the longer run: the byte decoders (the structured targets of the robot bridge,
#: the tracker's state and the configs run 150 inputs each above and 100 000 in ``bench/fuzz.py``)
LONG_RUN = GROUPS["messages-codec"] + GROUPS["files-camera"] + GROUPS["files-aedat4"] + GROUPS["files-text-numpy"]


@pytest.mark.slow
def test_fuzz_longer_run_with_another_seed():
    _fuzz(LONG_RUN, examples=250, seed=12345, timeout=400)


def test_the_address_space_cap_turns_a_big_allocation_into_memory_error():
    r = run_bounded("import numpy as np", """
        try:
            a = np.ones(512 << 20, np.uint8)
            print("allocated")
        except MemoryError:
            print("MemoryError")
        """)
    assert r.returncode == 0 and r.stdout.strip() == "MemoryError", r.stdout + r.stderr


def test_unwrapped_robot_counters_never_go_negative():
    """Found by the ``robot-protocol`` target: a first seq (or clock) value followed by one more
    than half the range ahead (a link silent for > 32768 frames while the robot ran on) unwrapped
    to a negative ``seq`` / ``robot_time_us``, and every telemetry the bridge published after it
    was refused by its receivers (``MessageError``)."""
    from arena.robot_protocol import Unwrapper

    u = Unwrapper(16)
    assert [u(v) for v in (10, 40_000, 65_535, 3, 40_000)] == [10, 40_000, 65_535, 65_539, 40_000]
    u = Unwrapper(32)
    assert [u(v) for v in (2**32 - 10, 5, 2**32 - 20, 100)] == [2**32 - 10, 2**32 + 5, 2**32 - 20, 2**32 + 100]


def test_a_state_file_with_a_huge_integer_is_refused_with_the_declared_error():
    """Found by the ``tracker-state`` target: ``"x": 1e400`` written as an integer (JSON ints have
    any size) made :func:`tracker.service.check_state` raise OverflowError, not ValueError."""
    from tests.fuzz.targets import _state_seed
    from tracker.service import check_state

    state = json.loads(_state_seed())
    state["fleet"]["tracks"][0]["x"] = 10**400
    with pytest.raises(ValueError, match=r"fleet.tracks\[0\].x is an integer of 401 digits"):
        check_state(state)


def test_a_start_pose_with_an_absurd_yaw_is_refused_and_a_wide_one_wrapped():
    """Found by the ``mission`` target (100 000-input run): a waypoint mission with start_pose
    yaw 7.6e11 rad was laid out with turns 5 µm longer than its own size check allowed.
    Run in a child process: the target's handle replaces the bridge's mission log with a null
    one for the whole process (it broke the bridge tests run after it in the same session)."""
    r = run_bounded("import math", """
        from arena.messages import MissionCommand
        from robot_bridge.core import CommandError
        from tests.fuzz.targets import _check_mission, _mission_handle

        pts = [[0.3, 0.3], [1.5, 0.3], [1.5, 1.5], [0.3, 0.3]]
        cmd = MissionCommand(mission="waypoints", params={"points": pts, "start_pose": [0.2, 0.2, 765620052808.0]})
        try:
            _mission_handle().start_mission(cmd)
            print("accepted")
        except CommandError as exc:
            print("refused:", exc)
        _check_mission(cmd.encode())            # the target's whole contract holds on it
        wide = MissionCommand(mission="waypoints", params={"points": pts, "start_pose": [0.2, 0.2, 6.0]})
        h = _mission_handle()
        h.start_mission(wide)
        print("yaw", repr(h.runner.mission.start[2] - (6.0 - 2 * math.pi)))
        """)
    assert r.returncode == 0, r.stdout + r.stderr
    lines = r.stdout.splitlines()
    assert lines[0].startswith("refused:") and "yaw_rad within +-2 pi" in lines[0], r.stdout
    assert abs(float(lines[1].split()[1])) < 1e-12, r.stdout

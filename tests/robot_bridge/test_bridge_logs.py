"""Mission logs: rows, gaps, rotation, and completeness after SIGKILL mid-mission."""

from __future__ import annotations

import csv
import json
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

from robot_bridge.logs import COLUMNS, MissionLog, Sample, read_log


def sample(seq: int) -> Sample:
    return Sample(1_000 + seq, 10 * seq, seq, seq, -seq, 0.1, 0.2, (0.0, 0.0, 9.8), (0.0, 0.0, 0.1),
                  (20.0, 0.0, -40.0), 5000, 100, -100, "lap 1")


def test_rows_gaps_manifest_and_rotation(tmp_path):
    with MissionLog(tmp_path, "r1", "m1", manifest={"pattern": "circle"}, max_bytes=4000) as lg:
        for seq in range(60):
            if seq == 30:
                lg.gap(5, 30, 3, "lap 1")
                continue
            lg.sample(sample(seq))
    manifest, rows = read_log(tmp_path, "r1", "m1")
    assert manifest["status"] == "finished" and manifest["pattern"] == "circle"
    assert len(manifest["files"]) >= 2 and manifest["files"][1] == "r1_m1.part002.csv"
    assert manifest["rows"] == 59 and manifest["gap_rows"] == 1 and manifest["missing"] == 3
    assert len(rows) == 60 and list(rows[0]) == list(COLUMNS)
    gap = [r for r in rows if r["event"] == "gap"][0]
    assert gap["seq"] == "30" and gap["missing"] == "3"
    assert [int(r["seq"]) for r in rows if r["event"] == "sample"] == [s for s in range(60) if s != 30]


KILLED = textwrap.dedent("""
    import sys, time
    sys.path.insert(0, sys.argv[2])
    from bridge_testkit import running_world
    from arena.messages import MissionCommand
    from robot_bridge.core import BridgeOptions, RobotHandle, RobotSetup
    from simulator.robot_emulator import RobotEmulatorServer
    with running_world() as world, RobotEmulatorServer(world, 0) as emu:
        h = RobotHandle(RobotSetup("r1", emu.url), BridgeOptions(log_dir=sys.argv[1]))
        h.start()
        h.link.wait_connected(5)
        mid = h.start_mission(MissionCommand(mission="circle", params={"radius_m": 0.2, "laps": 5}, power=0.5))
        print(mid["mission_id"], flush=True)
        time.sleep(60)
""")


def test_log_complete_after_sigkill_mid_mission(tmp_path):
    proc = subprocess.Popen([sys.executable, "-c", KILLED, str(tmp_path), str(Path(__file__).parent)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        mission_id = proc.stdout.readline().strip()
        assert mission_id, proc.stderr.read()
        csv_path = tmp_path / f"r1_{mission_id}.csv"
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and (not csv_path.exists() or csv_path.stat().st_size < 20_000):
            time.sleep(0.05)
        before = csv_path.read_bytes()   # everything flushed up to here must survive the kill
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    after = csv_path.read_bytes()
    assert after.startswith(before) and len(before) >= 20_000
    assert after.endswith(b"\r\n") or after.endswith(b"\n")   # no half-written row
    with open(csv_path, newline="") as f:
        rows = list(csv.DictReader(f))
    assert all(None not in r and all(v is not None for v in r.values()) for r in rows)
    seqs = [int(r["seq"]) for r in rows if r["event"] == "sample"]
    assert len(seqs) > 100 and seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    assert all(r["phase"].startswith("lap") for r in rows if r["event"] == "sample")
    manifest = json.loads((tmp_path / f"r1_{mission_id}.json").read_text())
    assert manifest["status"] == "running" and manifest["files"] == [csv_path.name]
    assert not any(p.name.endswith(".tmp") for p in tmp_path.iterdir())

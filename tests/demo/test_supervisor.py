"""The demo's process supervisor: readiness lines, niceness of the observers, stop order."""

from __future__ import annotations

import os
import sys

from demo.supervisor import ProcSpec, Supervisor

REPORT_NICE = "import os, time; print('nice', os.nice(0), flush=True); time.sleep(30)"


def test_child_gets_the_asked_niceness_and_is_ready_on_its_line(tmp_path):
    base = os.nice(0)
    with Supervisor(tmp_path) as sup:
        low = sup.start(ProcSpec("observer", [sys.executable, "-c", REPORT_NICE], ready="nice", nice=5))
        same = sup.start(ProcSpec("world", [sys.executable, "-c", REPORT_NICE], ready="nice"))
        assert low.alive() and same.alive()
        assert f"nice {min(base + 5, 19)}" in "".join(low.lines)
        assert f"nice {base}" in "".join(same.lines)
        codes = sup.stop_all(first=["world"])
    assert list(codes) == ["world", "observer"]              # the named ones first
    assert not low.alive() and not same.alive()
    assert (tmp_path / "observer.log").read_text().startswith("nice")



def test_the_supervisor_tells_which_children_died_early_and_which_it_had_to_kill(tmp_path):
    import signal

    ignore_term = ("import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); print('up', flush=True); "
                   "time.sleep(30)")
    with Supervisor(tmp_path) as sup:
        stubborn = sup.start(ProcSpec("stubborn", [sys.executable, "-c", ignore_term], ready="up", stop_timeout_s=0.5))
        quick = sup.start(ProcSpec("quick", [sys.executable, "-c", "raise SystemExit(3)"]))
        sup.start(ProcSpec("polite", [sys.executable, "-c", REPORT_NICE], ready="nice"))
        quick.popen.wait(timeout=20)       # it exits by itself, before anyone asks it to stop
        codes = sup.stop_all()
    assert codes == {"polite": -signal.SIGTERM, "quick": 3, "stubborn": -signal.SIGKILL}
    assert sup.killed() == ["stubborn"]
    assert sup.died() == {"quick": 3}
    # stopping again (the context manager's exit) changes nothing
    assert sup.killed() == ["stubborn"] and sup.died() == {"quick": 3}

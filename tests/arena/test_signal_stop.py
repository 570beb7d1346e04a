"""``arena.service.stop_on_signals``: once a signal began a service's stop, more signals neither
interrupt its cleanup nor kill the finished process while the interpreter finalizes (a launcher
repeating SIGTERM 10 ms apart made ``arena record`` exit 143 after it had finished its file)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

CHILD = """
import time
import numpy  # noqa: F401  (a service's imports: finalizing them takes a while)
from arena.service import stop_on_signals
from arena.session import ZenohSettings, open_session

stop = stop_on_signals()
with open_session(ZenohSettings(mode="peer", connect=[], listen=[])) as s:
    try:
        print("ready", flush=True)
        while True:
            time.sleep(0.01)
    except KeyboardInterrupt:
        pass
print("stopped", flush=True)
"""


def test_sigterm_repeated_every_millisecond_still_ends_the_service_with_exit_0():
    rcs = []
    for _ in range(2):
        p = subprocess.Popen([sys.executable, "-c", CHILD], stdout=subprocess.PIPE, text=True, cwd=REPO)
        try:
            assert p.stdout.readline().strip() == "ready"
            end = time.monotonic() + 15    # bounded: SIGTERM every ~1 ms until the process is gone
            while p.poll() is None and time.monotonic() < end:
                try:
                    os.kill(p.pid, signal.SIGTERM)
                except ProcessLookupError:
                    break
                time.sleep(0.001)
            out = p.stdout.read()
            rcs.append(p.wait(5))
        finally:
            if p.poll() is None:
                p.kill()
                p.wait()
        assert "stopped" in out
    assert rcs == [0, 0]    # without ignoring late signals: [-15, -15] (killed while finalizing)

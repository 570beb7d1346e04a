"""Send a signal to one chosen thread of another process (Linux ``tgkill``), for shutdown tests.

A launcher's SIGTERM goes to the process, and the kernel may deliver it to any of its threads
(Zenoh runs several). These helpers make that case deterministic: the signal goes to a thread
that is not the main one.
"""

from __future__ import annotations

import ctypes
import os
import platform
import signal
import time

_SYS_TGKILL = {"x86_64": 234, "aarch64": 131}


def non_main_threads(pid: int) -> list[int]:
    """Thread ids of ``pid`` other than its main thread."""
    return [int(t) for t in os.listdir(f"/proc/{pid}/task") if int(t) != pid]


def term_other_thread(pid: int, timeout_s: float = 10.0) -> int:
    """SIGTERM a non-main thread of ``pid`` (waiting up to ``timeout_s`` for one to exist);
    returns its id. Raises RuntimeError where tgkill is not available."""
    nr = _SYS_TGKILL.get(platform.machine())
    if nr is None or not os.path.isdir(f"/proc/{pid}/task"):
        raise RuntimeError(f"tgkill is not wired for {platform.machine()} here")
    deadline = time.monotonic() + timeout_s
    while not (tids := non_main_threads(pid)):
        if time.monotonic() > deadline:
            raise RuntimeError(f"process {pid} has no thread besides its main one")
        time.sleep(0.05)
    libc = ctypes.CDLL(None, use_errno=True)
    tid = tids[-1]
    if libc.syscall(nr, pid, tid, int(signal.SIGTERM)) != 0:
        raise OSError(ctypes.get_errno(), f"tgkill({pid}, {tid}) failed")
    return tid

"""Helpers every command line shares: one exit-code policy.

Exit codes of every ``arena`` command: 0 done, 1 a runtime failure (nothing answered, a service
failed, a port was taken), 2 a usage or input error (a wrong flag value, a missing or unreadable
file, a wrong lab config). Either way one line on stderr says what happened and what to do.
"""

from __future__ import annotations

import sys

USAGE = 2
RUNTIME = 1


def fail(message: str, code: int = USAGE) -> SystemExit:
    """Print ``message`` (one line, ``arena CMD: ...``) to stderr and return the SystemExit to
    raise: ``raise fail("arena track: --fleet-size must be >= 1")``. ``code`` defaults to a usage
    or input error (2); pass :data:`RUNTIME` (1) for a failure at run time."""
    print(message, file=sys.stderr, flush=True)
    return SystemExit(code)

"""Helpers every command line shares: one help layout, one exit-code policy, one way to open Zenoh.

Exit codes of every ``arena`` command: 0 done, 1 a runtime failure (nothing answered, a service
failed, a port was taken), 2 a usage or input error (a wrong flag value, a missing or unreadable
file, a wrong lab config). Either way one line on stderr says what happened and what to do.

This module is imported when the ``arena`` parser is built (every command's ``register``): it
imports nothing beyond the standard library at module level; :func:`session_or_exit` imports
:mod:`arena.session` (Zenoh) when it is called.
"""

from __future__ import annotations

import argparse
import math
import contextlib
import sys
from collections.abc import Iterator
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import zenoh

    from arena.config import LabConfig, ZenohSettings

USAGE = 2
RUNTIME = 1

__all__ = ["RUNTIME", "USAGE", "exit_on_session_error", "fail", "formatter", "number", "seconds", "session_or_exit"]


def fail(message: str, code: int = USAGE) -> SystemExit:
    """Print ``message`` (one line, ``arena CMD: ...``) to stderr and return the SystemExit to
    raise: ``raise fail("arena track: --fleet-size must be >= 1")``. ``code`` defaults to a usage
    or input error (2); pass :data:`RUNTIME` (1) for a failure at run time."""
    print(message, file=sys.stderr, flush=True)
    return SystemExit(code)


def formatter(prog: str) -> argparse.HelpFormatter:
    """The help layout of every ``arena`` command (``formatter_class=formatter``): descriptions and
    epilogs (the examples) printed as written, option help from column 32."""
    return argparse.RawDescriptionHelpFormatter(prog, max_help_position=32)


@contextlib.contextmanager
def exit_on_session_error(prog: str, code: int | None = None) -> Iterator[None]:
    """Turn an :class:`arena.session.SessionError` raised in the block into one line
    ``<prog>: <error>`` on stderr and ``SystemExit(exc.exit_code)`` (2: wrong settings, 1: nothing
    answered), or ``SystemExit(code)`` when ``code`` is given. ``prog`` is ``"arena CMD"``."""
    from arena.session import SessionError

    try:
        yield
    except SessionError as exc:
        raise fail(f"{prog}: {exc}", exc.exit_code if code is None else code) from None


@contextlib.contextmanager
def session_or_exit(settings_or_args: argparse.Namespace | ZenohSettings | None, prog: str, *,
                    lab: LabConfig | None = None, wait_s: float | None = 0.0,
                    code: int | None = None) -> Iterator[zenoh.Session]:
    """:func:`arena.session.open_session` (same arguments; closed at the end) for a command: a
    :class:`~arena.session.SessionError` while opening or in the block is one line ``<prog>:
    <error>`` on stderr and ``SystemExit`` as in :func:`exit_on_session_error`::

        with session_or_exit(args, "arena ros2", wait_s=None) as session:
            ...
    """
    from arena.session import open_session

    with exit_on_session_error(prog, code), open_session(settings_or_args, lab=lab, wait_s=wait_s) as session:
        yield session


def number(lo: float, hi: float, unit: str = "", *, integer: bool = False, lo_open: bool = False,
           hi_open: bool = False, note: str = ""):
    """An argparse ``type`` for a number in ``[lo, hi]`` (``lo_open``/``hi_open``: the bound is
    excluded) with its ``unit``: NaN, infinities, other words and absurd values are a usage error
    naming the range and unit (``note`` added after it, e.g. what 0 means). ``integer``: an int.
    ``parse.range`` keeps (lo, hi, lo_open, hi_open, integer, description), so that a value from
    elsewhere (a lab file) can be checked against the same range."""
    fmt = (lambda v: str(int(v))) if integer else (lambda v: f"{v:g}")
    rng = f"{'(' if lo_open else '['}{fmt(lo)}, {fmt(hi)}{')' if hi_open else ']'}"
    what = f"{'an integer' if integer else 'a number'} in {rng}{' ' + unit if unit else ''}{note}"

    def parse(text: str):
        try:
            v = int(text) if integer else float(text)
        except ValueError:
            v = math.nan
        if not (math.isfinite(v) and (v > lo if lo_open else v >= lo) and (v < hi if hi_open else v <= hi)):
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
        return v
    parse.range = (lo, hi, lo_open, hi_open, integer, what)
    return parse


def seconds(lo: float = 0.0, hi: float = 600.0, *, lo_open: bool = True):
    """An argparse ``type`` for a duration in seconds within ``(lo, hi]`` (``[lo, hi]`` when not
    ``lo_open``): NaN, infinities and absurd values are a usage error naming the range."""
    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            v = math.nan
        if not (math.isfinite(v) and (v > lo if lo_open else v >= lo) and v <= hi):
            raise argparse.ArgumentTypeError(f"expected seconds in {'(' if lo_open else '['}{lo:g}, {hi:g}], "
                                             f"got {text!r}")
        return v
    return parse


"""The approach's flags and consent: `trace` and `identify` bring an axis to its profile's start instead of refusing.

The move itself is planned by controllers/runtime/approach.py (one line per axis, shown first).
``--approach`` moves without asking, ``--no-approach`` refuses as before; with neither, a terminal is
asked ([y/N]) and anything else is refused with the line and the flag to use. The approach runs through
the same servo loop as the profile (limits, following error, faults, Ctrl-C).
"""

from __future__ import annotations

import sys
from typing import Any

from drivectl.controllers.runtime.cycle import LimitError


def add_approach_flags(parser: Any) -> None:
    g = parser.add_mutually_exclusive_group()
    g.add_argument("--approach", dest="approach", action="store_true", default=None,
                   help="move an axis that is not at its profile's start there first (a jerk-limited move "
                   "within [axes.NAME.motion]), without asking")
    g.add_argument("--no-approach", dest="approach", action="store_false",
                   help="refuse to run an axis that is not at its profile's start (nothing moves)")


def consent(approach: bool | None, moves: list[str], flag: str = "--approach") -> None:
    """Show the moves; LimitError (nothing moved) unless ``approach`` or a terminal says yes."""
    for line in moves:
        print(line, file=sys.stderr)
    if approach:
        return
    if approach is None and sys.stdin.isatty() and sys.stderr.isatty():
        print("move there now? [y/N] ", end="", file=sys.stderr, flush=True)
        if sys.stdin.readline().strip().lower() in ("y", "yes"):
            return
    why = "--no-approach" if approach is False else f"not confirmed (use {flag} to move there without asking)"
    raise LimitError(f"{moves[0].removeprefix('approach: ')}: not at the start, {why}; nothing moved")

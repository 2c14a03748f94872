"""The approach move: `trace` and `identify` bring an axis to its profile's start instead of refusing.

Before a run the axes are sampled once (one cycle, torque off). An axis standing farther than
``TOLERANCE_M`` from where its profile starts gets a jerk-limited point-to-point move there (ruckig,
within ``[axes.NAME.motion]``), shown first on one line per axis. ``--approach`` moves without asking,
``--no-approach`` refuses as before; with neither, a terminal is asked ([y/N]) and anything else is
refused with the line and the flag to use. The approach runs through the same servo loop as the
profile (limits, following error, faults, Ctrl-C) and ends held at the start, so the profile follows
it within one cycle (both runs are planned before the first moves).
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from typing import Any

from drivectl.controllers.runtime.motion import MotionLimits
from drivectl.controllers.runtime.servo import Channel, LimitError, RunPlan, plan_run
from drivectl.profiles.dwell import Dwell
from drivectl.profiles.ptp import PointToPoint
from drivectl.profiles.sequence import Sequence as ProfileSequence

#: an axis farther than this from its profile's start needs an approach (m)
TOLERANCE_M = 10e-6
#: the approach holds the start this long before the profile begins (s): the axis settles there
SETTLE_S = 0.2


def add_approach_flags(parser: Any) -> None:
    g = parser.add_mutually_exclusive_group()
    g.add_argument("--approach", dest="approach", action="store_true", default=None,
                   help="move an axis that is not at its profile's start there first (a jerk-limited move "
                   "within [axes.NAME.motion]), without asking")
    g.add_argument("--no-approach", dest="approach", action="store_false",
                   help="refuse to run an axis that is not at its profile's start (nothing moves)")


def where_axes_stand(channels: Sequence[Channel]) -> dict[str, float]:
    """One cycle with torque off: each axis's position (m)."""
    out = {}
    for ch in channels:
        out[ch.axis.name] = ch.axis.read().position
    for ch in channels:
        ch.axis.write(0.0)
    return out


def plan_approach(channels: Sequence[Channel], positions: dict[str, float],
                  motion: dict[str, MotionLimits]) -> tuple[RunPlan | None, list[str]]:
    """The approach run (every axis of the run: the ones already there hold) and one line per move;
    (None, []) when every axis stands at its start."""
    moves: list[str] = []
    profiles = []
    longest = 0.0
    for ch in channels:
        here, start = positions[ch.axis.name], ch.profile.start_position
        if abs(start - here) > TOLERANCE_M:
            m = motion.get(ch.axis.name) or MotionLimits()
            ptp = PointToPoint(here, start, m.max_velocity, m.max_acceleration, m.max_jerk, name="approach")
            longest = max(longest, ptp.move_time)
            profiles.append(ptp)
            moves.append(f"approach: axis {ch.axis.name} from {here * 1e3:.3f} mm to its profile's start "
                         f"{start * 1e3:.3f} mm ({abs(start - here) * 1e3:.3f} mm, {ptp.move_time:.2f} s at up to "
                         f"{m.max_velocity * 1e3:g} mm/s)")
        else:
            profiles.append(None)
    if not moves:
        return None, []
    total = longest + SETTLE_S
    approach = []
    for ch, prof in zip(channels, profiles, strict=True):
        here = positions[ch.axis.name]
        if prof is None:
            p = Dwell(here, total, name="approach")
        else:
            p = ProfileSequence([prof, Dwell(prof.target, total - prof.move_time)], name="approach")
        approach.append(Channel(ch.axis, ch.controller, p, ch.limits, {**ch.meta, "profile": "approach"}))
    return plan_run(approach), moves


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

"""The approach: the move from where an axis stands to the start of its run, planned in one place.

An axis farther than ``TOLERANCE_M`` from where its profile starts needs an approach: a jerk-limited
point-to-point move there (ruckig, within ``[axes.NAME.motion]``), described in one line per axis. A
one-shot run (`trace`, `identify`) runs the approaches of all its axes as one run of its own
(:func:`plan_approach`: the axes already there hold), ending held at the start for ``SETTLE_S``, so the
profile follows it within one cycle. The resident loop (``AxisControl.run(approach=True)``) moves there
with its own ruckig move within the same limits, then starts the run; it compares the reference's
resting target, not a measured position, hence its tighter :data:`REFERENCE_TOLERANCE_M`.

Whether to move without asking is the caller's: the CLI asks (tools/cli/approach.py), the session takes
``approach=True``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from drivectl.controllers.runtime.cycle import Channel
from drivectl.controllers.runtime.motion import MotionLimits
from drivectl.controllers.runtime.servo import RunPlan, plan_run
from drivectl.profiles.dwell import Dwell
from drivectl.profiles.ptp import PointToPoint
from drivectl.profiles.sequence import Sequence as ProfileSequence

#: a measured position farther than this from its profile's start needs an approach (m)
TOLERANCE_M = 10e-6
#: a reference's resting target farther than this from the start needs one (m): the reference is exact,
#: only rounding separates it from the start
REFERENCE_TOLERANCE_M = 1e-6
#: the approach holds the start this long before the profile begins (s): the axis settles there
SETTLE_S = 0.2


def needs_approach(here: float, start: float, tolerance: float = TOLERANCE_M) -> bool:
    """An axis at ``here`` (m) is not at ``start`` (m) within ``tolerance``."""
    return abs(start - here) > tolerance


def where_axes_stand(channels: Sequence[Channel]) -> dict[str, float]:
    """One cycle with torque off: each axis's position (m)."""
    out = {}
    for ch in channels:
        out[ch.axis.name] = ch.axis.read().position
    for ch in channels:
        ch.axis.write(0.0)
    return out


def plan_approach(channels: Sequence[Channel], positions: Mapping[str, float],
                  motion: Mapping[str, MotionLimits]) -> tuple[RunPlan | None, list[str]]:
    """The approach run (every axis of the run: the ones already there hold) and one line per move;
    (None, []) when every axis stands at its start."""
    moves: list[str] = []
    profiles: list[PointToPoint | None] = []
    longest = 0.0
    for ch in channels:
        here, start = positions[ch.axis.name], ch.profile.start_position
        if needs_approach(here, start):
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

"""Does an axis's controller hold at a servo cycle? Checked in simulation before a cycle is recommended.

A gain tuned at one cycle is not a gain at another: the loop's one-cycle transport delay takes more phase
the longer the cycle (docs/standstill.md, "The cycle": y's standstill tuned at 1 ms stood in a +-300 N
limit cycle at 2 ms while its reference rested). ``drivectl doctor`` recommends a longer cycle when the host
cannot keep the configured one; before it does, :func:`hold_at` runs each axis's configured plant and
controller at that cycle in lockstep (SimAxis: the drive's power states and one-cycle transport delay, no
bus, nothing on the machine moves): enable, a move of :data:`MOVE_M` towards the middle of the soft
limits, then :data:`HOLD_S` at rest after :data:`SETTLE_S`. The axis holds when its effort stays off the
limit (``max_effort``) at rest and the error moves by at most :data:`PEAK_TO_PEAK_M` there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

#: the move before the hold (at most a tenth of the soft limits' span), m
MOVE_M = 0.005
SETTLE_S = 0.3
HOLD_S = 1.0
#: at rest the error may move this much, peak to peak, and the axis still holds (a limit cycle is hundreds
#: of um; a loose hold a few)
PEAK_TO_PEAK_M = 10e-6


@dataclass(frozen=True)
class HoldCheck:
    axis: str
    cycle_s: float
    holds: bool | None  # None: not checked (``detail`` says why)
    peak_to_peak_m: float = math.nan
    worst_m: float = math.nan
    effort_at_limit: bool = False
    detail: str = ""

    def text(self) -> str:
        at = f"at {self.cycle_s * 1e3:g} ms"
        if self.holds is None:
            return f"not checked {at}: {self.detail}"
        if self.detail:  # the move itself faulted
            return f"does NOT hold {at} in simulation (a move faulted: {self.detail}): retune it for that cycle"
        figures = (f"at rest after a move the error stays within {self.worst_m * 1e6:.2f} um, "
                   f"{self.peak_to_peak_m * 1e6:.2f} um peak to peak")
        if self.holds:
            return f"holds {at} in simulation ({figures})"
        limit = "; the effort at its limit" if self.effort_at_limit else ""
        return f"does NOT hold {at} in simulation ({figures}{limit}): retune it for that cycle"


def hold_at(cfg: Any, name: str, cycle_s: float) -> HoldCheck:
    """Axis ``name`` of machine ``cfg`` (MachineConfig) with its configured plant and controller at ``cycle_s``."""
    import drivectl
    from drivectl.controllers.runtime.capture import CaptureError
    from drivectl.controllers.runtime.handles import MotionFault
    from drivectl.driver.axis import AxisError

    c = replace(cfg, cycle_s=cycle_s)
    limits = c.axis(name).limits
    try:
        m = drivectl.connect(c, axes=[name], sim=True, clock="lockstep", ring_s=HOLD_S + 0.5, fault_dir=None)
    except Exception as exc:  # a configuration the simulation cannot build (its error names why)
        return HoldCheck(name, cycle_s, None, detail=str(exc).splitlines()[0])
    with m:
        a = m.axes[name]
        try:
            a.enable()
            here = a.position
            step = MOVE_M
            if limits.position is not None:
                lo, hi = limits.position
                step = min(MOVE_M, 0.1 * (hi - lo))
                step = step if here <= 0.5 * (lo + hi) else -step
            a.move_by(step).wait(30)
            m.advance(SETTLE_S)
            trace = a.capture(pre=0.0, post=HOLD_S).wait(30)
        except (AxisError, MotionFault, CaptureError, TimeoutError) as exc:  # it faulted: not holding either
            return HoldCheck(name, cycle_s, False, detail=str(exc).splitlines()[0])
    pp, worst, at_limit = rest_figures(trace.error, trace.effort, limits.max_effort)
    return HoldCheck(name, cycle_s, pp <= PEAK_TO_PEAK_M and not at_limit, pp, worst, at_limit)


def rest_figures(error: np.ndarray, effort: np.ndarray, max_effort: float) -> tuple[float, float, bool]:
    """An axis at rest: the error's peak to peak and largest magnitude (m), and whether the effort reached
    its limit (a limit cycle inside the following-error window faults nothing; bench/soak.py says it too)."""
    at_limit = bool(math.isfinite(max_effort) and np.max(np.abs(effort)) >= 0.999 * max_effort)
    return float(np.ptp(error)), float(np.max(np.abs(error))), at_limit

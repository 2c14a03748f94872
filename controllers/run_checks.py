"""Did a run that completed go well? Thresholds on what the loop counted, and the encoder's plausibility.

A run can reach its last cycle and still not be what it claims: paced cycles that missed their
deadline (the drive saw a late setpoint), an effort clipped at the limit (the controller was not in
control), cycles bridged by extrapolating a lost TPDO (the controller closed its loop on a guess).
:func:`assess` holds those counts, as fractions of the run's cycles, against two thresholds each
(:class:`RunChecks`, ``[checks]`` in the machine configuration): past the first the run is
``completed with warnings`` (a line each, exit code 4), past the second it is a fault (exit 3).

:func:`position_jump` is the per-cycle plausibility check of the encoder (called from the servo
loop's ``_violation``): a CiA 402 axis cannot change its velocity by more than its acceleration
allows in one cycle, so the second difference of the position, ``p[k] - 2 p[k-1] + p[k-2]``, is at
most ``a dt^2`` (50 m/s^2, over 5 g, is 50 um at 1 ms). A larger one is a glitch, not motion:
``limits.max_jump_m`` (default 0.5 mm: 500 m/s^2 at 1 ms; the emulated axes measure at most 4 um
in normal runs, 415 um in a loop driven into an 80 Hz resonance limit cycle) bounds it; after cycles
bridged by extrapolation the bound grows with the square of the gap, as the extrapolation's own
error does.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

#: the run's counters held against the thresholds: (trace metadata key, what it is, threshold name)
_COUNTED = (
    ("missed_deadlines", "deadlines missed (paced)", "missed_deadlines"),
    ("effort_clipped_cycles", "cycles with the effort clipped at limits.max_effort", "clipped"),
    ("tpdo_lost_cycles", "cycles run on an extrapolated position (TPDO lost or malformed)", "extrapolated"),
)


@dataclass(frozen=True)
class RunChecks:
    """Fractions of a run's cycles: past ``*_warn`` a warning, past ``*_fault`` a fault."""

    missed_deadlines_warn: float = 0.005  # README: 0.07-0.28 % on an idle machine
    missed_deadlines_fault: float = 0.05
    clipped_warn: float = 0.01
    clipped_fault: float = 0.5
    extrapolated_warn: float = 0.005
    extrapolated_fault: float = 0.05

    def __post_init__(self) -> None:
        for name in ("missed_deadlines", "clipped", "extrapolated"):
            warn, fault = getattr(self, f"{name}_warn"), getattr(self, f"{name}_fault")
            for key, value in ((f"{name}_warn", warn), (f"{name}_fault", fault)):
                if not (isinstance(value, (int, float)) and 0 <= value <= 1):
                    raise ValueError(f"checks.{key}: must be a fraction of the run's cycles in [0, 1], got {value!r}")
            if fault < warn:
                raise ValueError(f"checks.{name}_fault: must be >= {name}_warn ({warn:g}), got {fault:g}")


@dataclass
class Assessment:
    """What :func:`assess` found, per axis: one line each."""

    warnings: list[str] = field(default_factory=list)
    faults: list[str] = field(default_factory=list)

    @property
    def stop(self) -> str:
        return "fault" if self.faults else "completed with warnings" if self.warnings else "completed"


def assess(traces: Mapping[str, object], checks: RunChecks) -> Assessment:
    """Hold each trace's counters (its metadata) against ``checks``; ``traces`` maps axis name to a Trace
    (anything with ``meta``) of a run that completed."""
    out = Assessment()
    for name, tr in traces.items():
        meta = tr.meta
        cycles = int(meta.get("cycles", "0") or 0)
        if cycles <= 0:
            continue
        for key, what, limit in _COUNTED:
            count = int(float(meta.get(key, "0") or 0))
            if not count:
                continue
            frac = count / cycles
            warn, fault = getattr(checks, f"{limit}_warn"), getattr(checks, f"{limit}_fault")
            line = f"axis {name}: {count} of {cycles} {what} ({frac:.1%}"
            if frac > fault:
                out.faults.append(f"{line}, more than checks.{limit}_fault {fault:.1%})")
            elif frac > warn:
                out.warnings.append(f"{line}, more than checks.{limit}_warn {warn:.1%})")
    return out


def apply(traces: Mapping[str, object], result: Assessment,
          paths: Mapping[str, str | Path] | None = None) -> None:
    """Write the verdict into each trace's metadata (``stop``, ``run_checks``, ``fault_kind``) and, for the
    traces already streamed to ``paths[axis]``, into the file's trailer."""
    if result.stop == "completed":
        return
    for name, tr in traces.items():
        updates = {"stop": result.stop}
        mine = [w for w in (*result.faults, *result.warnings) if w.startswith(f"axis {tr.meta.get('axis', name)}:")]
        if mine:
            updates["run_checks"] = "; ".join(mine)
        if result.faults:
            updates["fault_kind"] = "run check"
        tr.meta.update(updates)
        if paths and name in paths:
            from drivectl.tools.trace_stream import amend_trailer  # the trace file's own concern

            amend_trailer(paths[name], updates)


@dataclass
class JumpState:
    """The last two positions of one axis and the cycles bridged since the older real sample."""

    p1: float | None = None
    p2: float | None = None
    bridged: int = 0


def position_jump(state: JumpState, pos: float, max_jump: float, bridged_now: bool) -> float | None:
    """The implausible part of this sample's step (m), or None. ``bridged_now``: this sample is an
    extrapolation (it is taken as it is, and widens the next real sample's bound)."""
    p1, p2 = state.p1, state.p2
    state.p2, state.p1 = p1, pos
    if bridged_now:
        state.bridged += 1
        return None
    gap, state.bridged = state.bridged, 0
    if p1 is None or p2 is None or not math.isfinite(max_jump):
        return None
    second = pos - 2.0 * p1 + p2
    if abs(second) > max_jump * (1 + gap) ** 2:
        return second
    return None

"""Did a run that completed go well? Thresholds on what the loop counted, and the encoder's plausibility.

A run can reach its last cycle and still not be what it claims: paced cycles that missed their
deadline (the drive saw a late setpoint), an effort clipped at the limit (the controller was not in
control), cycles bridged by extrapolating a lost TPDO (the controller closed its loop on a guess).
:func:`assess` holds those counts, as fractions of the run's cycles, against two thresholds each
(:class:`RunChecks`, ``[checks]`` in the machine configuration): past the first the run is
``completed with warnings`` (a line each, exit code 4), past the second it is a fault (exit 3).

A fault threshold stops the run when it is crossed, not after the profile (:class:`RunGuard`, called
by the servo loop every cycle: the quick stop of any fault, its end state verified, exit 3). Mid-run a
fraction needs a base: the cycles so far, but at least ``fault_min_cycles`` (1000: one second at 1 kHz)
or the whole run if it is shorter. So a burst early in a run is judged against that many cycles (5 %
of 1000: 50 missed deadlines in the first second stop it), a long run against what it has done so far,
and a run whose final count would pass the threshold stops when it does (for the last cycle the rule
is the end-of-run one). The per-cycle part compares counters with integer limits computed before;
a limit is recomputed (it grows with the cycles) only when a counter passes it.

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
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from drivectl.driver.axis import FaultKind

#: the run's counters held against the thresholds: (trace metadata key, what it is, threshold name)
_COUNTED = (
    ("missed_deadlines", "deadlines missed (paced)", "missed_deadlines"),
    ("effort_clipped_cycles", "cycles with the effort clipped at limits.max_effort", "clipped"),
    ("tpdo_lost_cycles", "cycles run on an extrapolated position (TPDO lost or malformed)", "extrapolated"),
)


@dataclass(frozen=True)
class RunChecks:
    """Fractions of a run's cycles: past ``*_warn`` a warning, past ``*_fault`` a fault."""

    missed_deadlines_warn: float = 0.005  # docs/canopen.md (bench/loop_rate.py): 0.07-0.28 % on an idle machine
    missed_deadlines_fault: float = 0.05
    clipped_warn: float = 0.01
    clipped_fault: float = 0.5
    extrapolated_warn: float = 0.005
    extrapolated_fault: float = 0.05
    #: mid-run, a fault threshold is a fraction of the cycles so far, but of at least this many (or the run)
    fault_min_cycles: int = 1000

    def __post_init__(self) -> None:
        m = self.fault_min_cycles
        if isinstance(m, float) and m.is_integer():  # a TOML number read as float: 1000.0 is 1000 cycles
            m = int(m)
            object.__setattr__(self, "fault_min_cycles", m)
        if isinstance(m, bool) or not isinstance(m, int) or m < 1:
            raise ValueError(f"checks.fault_min_cycles: must be a whole number of cycles >= 1, got {m!r}")
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
            updates["fault_kind"] = FaultKind.RUN_CHECK.value
        tr.meta.update(updates)
        if paths and name in paths:
            from drivectl.tracefile.stream import amend_trailer  # the trace file's own concern

            amend_trailer(paths[name], updates)


class RunGuard:
    """The fault thresholds of ``checks`` held against the counters while a run of ``cycles`` cycles goes:
    :meth:`check` after every cycle. ``channels``: the run's (``clipped``; ``axis.lost_total`` where the axis
    extrapolates: CanopenAxis); ``pacer``: its ``missed`` count when the run is paced."""

    def __init__(self, checks: RunChecks, cycles: int, channels: Sequence[Any], pacer: Any = None):
        self._min = max(1, min(checks.fault_min_cycles, cycles))
        self._pacer = pacer
        self._missed_frac = checks.missed_deadlines_fault
        self._missed_lim = self._limit(self._missed_frac, 0)
        self._clip_frac = checks.clipped_fault
        self._channels = list(channels)
        self._clip_lim = [self._limit(self._clip_frac, 0) for _ in self._channels]
        self._lost_frac = checks.extrapolated_fault
        #: (channel index, axis, count at the start, limit as an absolute value of axis.lost_total)
        self._lost = [[i, ch.axis, ch.axis.lost_total, 0] for i, ch in enumerate(self._channels)
                      if ch.axis.lost_total is not None]  # None: a transport that cannot lose one
        for entry in self._lost:
            entry[3] = entry[2] + self._limit(self._lost_frac, 0)

    def _limit(self, frac: float, cycles: int) -> int:
        """The most events ``frac`` allows after ``cycles`` cycles (judged on at least the minimum)."""
        return math.floor(frac * max(cycles, self._min) + 1e-9)

    def check(self, cycles: int) -> tuple[str, str] | None:
        """After ``cycles`` cycles: None, or (axis, one line) for the first fault threshold passed."""
        pacer = self._pacer
        if pacer is not None and pacer.missed > self._missed_lim:
            lim = self._missed_lim = self._limit(self._missed_frac, cycles)
            if pacer.missed > lim:
                return self._line(0, pacer.missed, "missed_deadlines", cycles, lim)
        channels = self._channels
        for i in range(len(channels)):
            if channels[i].clipped > self._clip_lim[i]:
                lim = self._clip_lim[i] = self._limit(self._clip_frac, cycles)
                if channels[i].clipped > lim:
                    return self._line(i, channels[i].clipped, "clipped", cycles, lim)
        for entry in self._lost:
            if entry[1].lost_total > entry[3]:
                lim = self._limit(self._lost_frac, cycles)
                entry[3] = entry[2] + lim
                if entry[1].lost_total > entry[3]:
                    return self._line(entry[0], entry[1].lost_total - entry[2], "extrapolated", cycles, lim)
        return None

    def _line(self, i: int, count: int, limit: str, cycles: int, lim: int) -> tuple[str, str]:
        name = self._channels[i].axis.name
        what = next(w for _, w, key in _COUNTED if key == limit)
        frac = {"missed_deadlines": self._missed_frac, "clipped": self._clip_frac,
                "extrapolated": self._lost_frac}[limit]
        return name, (f"axis {name}: {count} {what} in the first {cycles} cycles, more than "
                      f"checks.{limit}_fault {frac:.1%} allows ({lim} of {max(cycles, self._min)} cycles)")


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

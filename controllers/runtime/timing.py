"""How late a cycle may be: each axis's deadline from its physics, the host's lateness, and the verdict.

The timing model (docs/timing.md): the drive holds the last setpoint until its deadline (the RPDO
deadline 0x1400:05), so a late cycle is a missed cycle, not a fault. The deadline is the longest
interval without a fresh setpoint the axis tolerates: the time in which the largest effort the loop may
have last commanded (``max_effort``), acting alone on the axis's mass ``m``, moves it by
:data:`WINDOW_FRACTION` of its following-error window ``e``::

    T = sqrt(2 m f e / F_max),  capped at DEADLINE_CAP_S (20 ms), whole ms (0x1400:05 counts ms)

The other part of the window is left for the loop to take the axis back once it is on time again.
The host's lateness is measured per cycle (:class:`LatencyRecord`, a histogram: constant memory and a
few operations per cycle) by the resident loop and by ``drivectl doctor``; a cycle late by ``L``
leaves ``dt + L`` between two setpoints, so an axis holds while ``L < T - dt`` (:func:`judge`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

#: the longest deadline an axis is given, whatever its physics allows (s)
DEADLINE_CAP_S = 0.020
#: the share of the following-error window the held setpoint may use up
WINDOW_FRACTION = 0.5
#: lateness as a share of the margin (T - dt) at which ``enable`` warns; at the whole margin it refuses
WARN_SHARE = 0.5


@dataclass(frozen=True)
class Deadline:
    """One axis's deadline: ``seconds`` (what the drive is given, whole ms), how it was found."""

    axis: str
    seconds: float
    source: str  # "physics", "configured" (rpdo_timeout_ms), "two cycles" (no effort bound or mass known)
    physics_s: float | None  # what the physics allows (None: unknown)
    formula: str

    @property
    def ms(self) -> int:
        """Whole ms, as 0x1400:05 holds it (0: the drive does not watch)."""
        return int(round(self.seconds * 1e3))


def physics_deadline(mass: float, max_effort: float, window: float) -> float:
    """sqrt(2 m f e / F_max) in s, uncapped; inf where the effort is unbounded (no deadline follows)."""
    if not (mass > 0 and window > 0 and max_effort > 0) or math.isinf(max_effort):
        return math.inf
    return math.sqrt(2.0 * mass * WINDOW_FRACTION * window / max_effort)


def axis_deadline(axis: str, dt: float, *, mass: float | None, max_effort: float, window: float,
                  override_ms: int | None = None) -> Deadline:
    """The deadline of one axis: ``override_ms`` (``rpdo_timeout_ms``) where configured, else its physics
    (floored to whole ms, capped at 20 ms), else two cycles (mass or effort bound unknown)."""
    phys = physics_deadline(mass, max_effort, window) if mass is not None else math.inf
    physics_s = None if math.isinf(phys) else min(phys, DEADLINE_CAP_S)
    if physics_s is not None:
        formula = (f"sqrt(2 x {mass:.4g} x {WINDOW_FRACTION:g} x {window * 1e3:g} mm / {max_effort:g}) = "
                   f"{phys * 1e3:.2f} ms" + (f", capped at {DEADLINE_CAP_S * 1e3:g} ms" if phys > DEADLINE_CAP_S
                                             else ""))
    else:
        formula = "no effort bound or mass known"
    if override_ms is not None:
        return Deadline(axis, override_ms / 1e3, "configured", physics_s, formula)
    if physics_s is None:
        return Deadline(axis, 2 * dt, "two cycles", None, formula)
    whole_ms = max(1.0, math.floor(physics_s * 1e3 + 1e-9)) / 1e3  # never longer than the physics allows
    return Deadline(axis, whole_ms, "physics", physics_s, formula)


class LatencyRecord:
    """Lateness of every cycle, as a histogram of log-spaced bins from 1 us to 10 s (constant memory).

    ``add`` is the per-cycle cost: a log and an increment. Percentiles are read at a bin's upper edge
    (an upper bound within one bin, 2.3 %), the maximum exactly."""

    BINS_PER_DECADE = 100
    LOW = 1e-6

    def __init__(self) -> None:
        self.counts = [0] * (7 * self.BINS_PER_DECADE + 1)  # 1 us .. 10 s, and one for "on time" (<= 1 us)
        self.n = 0
        self.max = 0.0
        self._scale = self.BINS_PER_DECADE / math.log(10.0)
        self._log_low = math.log(self.LOW)

    def add(self, late: float) -> None:
        self.n += 1
        if late > self.max:
            self.max = late
        if late <= self.LOW:
            self.counts[0] += 1
            return
        i = int((math.log(late) - self._log_low) * self._scale) + 1
        self.counts[i if i < len(self.counts) else -1] += 1

    def edge(self, i: int) -> float:
        """The upper edge of bin ``i`` (s)."""
        return self.LOW * 10.0 ** (i / self.BINS_PER_DECADE)

    def percentile(self, q: float) -> float:
        """The lateness (s) that ``q`` % of the cycles did not exceed (0 with no cycles)."""
        if not self.n:
            return 0.0
        want = q / 100.0 * self.n
        seen = 0
        for i, c in enumerate(self.counts):
            seen += c
            if c and seen >= want:
                return min(self.edge(i), self.max)
        return self.max

    def share_over(self, s: float) -> float:
        """The share of the cycles that started more than ``s`` late (bins whose lower edge is past it: within
        one bin, 2.3 %); 0 with no cycles."""
        if not self.n:
            return 0.0
        over = sum(c for i, c in enumerate(self.counts) if i and self.edge(i - 1) >= s)
        return over / self.n

    def percentiles_ms(self) -> dict[str, float]:
        """{"p50", "p99", "p99_9", "p99_99", "max"} in ms."""
        return {"p50": self.percentile(50) * 1e3, "p99": self.percentile(99) * 1e3,
                "p99_9": self.percentile(99.9) * 1e3, "p99_99": self.percentile(99.99) * 1e3,
                "max": self.max * 1e3}

    def clear(self) -> None:
        for i in range(len(self.counts)):
            self.counts[i] = 0
        self.n, self.max = 0, 0.0

    def merge(self, other: LatencyRecord) -> None:
        for i, c in enumerate(other.counts):
            self.counts[i] += c
        self.n += other.n
        self.max = max(self.max, other.max)


class RecentLatency:
    """The lateness of the last ``window`` to ``2 window`` cycles: what ``enable`` judges, so that one
    hiccup long ago (a program's start-up) does not refuse for the rest of the session. Two records, the
    older cleared and reused when the newer fills (nothing allocated in the cycle)."""

    def __init__(self, window: int = 30_000):
        self.window = window
        self._cur, self._prev = LatencyRecord(), LatencyRecord()

    def add(self, late: float) -> None:
        cur = self._cur
        cur.add(late)
        if cur.n >= self.window:
            self._prev.clear()
            self._cur, self._prev = self._prev, cur

    def record(self) -> LatencyRecord:
        """The two windows as one record (a copy: read from any thread)."""
        out = LatencyRecord()
        out.merge(self._prev)
        out.merge(self._cur)
        return out


def judge(deadline_s: float, dt: float, latency_ms: dict[str, float]) -> tuple[str, str]:
    """The host against one axis's deadline: ("ok" | "warn" | "refuse", why). A cycle late by ``L``
    leaves ``dt + L`` between setpoints: the axis holds while ``L < T - dt``. Refused when one cycle in
    10^4 (p99.99) would pass the deadline; a warning when the worst lateness seen would have, or came
    past half the margin."""
    if deadline_s <= 0:
        return "ok", "no deadline (rpdo_timeout_ms = 0): the drive does not watch the setpoints"
    margin_ms = (deadline_s - dt) * 1e3
    p, worst = latency_ms["p99_99"], latency_ms["max"]
    figures = (f"deadline {deadline_s * 1e3:g} ms, cycle {dt * 1e3:g} ms: the host may be {margin_ms:.2f} ms late; "
               f"measured p99.99 {p:.2f} ms, max {worst:.2f} ms")
    if margin_ms <= 0 or p >= margin_ms:
        return "refuse", figures
    if worst >= WARN_SHARE * margin_ms:
        return "warn", figures
    return "ok", figures


#: the missed fraction a host may show at the recommended cycle (issue 39: under 0.5 % of the slots)
MISSED_TARGET = 0.005
#: the share of the probe's cycles that may start over half a cycle late for the probed cycle to be recommended:
#: half MISSED_TARGET, because the probe enables no axis and lasts 10-60 s while the bands of a shared host drift
#: (docs/timing.md, "The cycle doctor recommends": across processes a probe at 0.48 % went on to miss 1.95 %)
KEEP_SHARE = MISSED_TARGET / 2
#: the share of one CPU the loop's thread may use at the recommended cycle: the rest is the slack that absorbs
#: the host's lateness and what runs beside the loop (an emulator across processes, the user's program)
CPU_SHARE_MAX = 0.5
#: the cycles a recommendation picks from (s)
STANDARD_CYCLES_S = (0.001, 0.002, 0.004, 0.005, 0.008, 0.01, 0.02)


def recommend_cycle(dt: float, cpu_share: float | None, late_share: float) -> tuple[float, str]:
    """The shortest standard cycle, at least ``dt``, that the probe at ``dt`` says the host keeps: the loop's
    CPU per cycle (``cpu_share * dt``, about the same at any cycle: the bus's frames and the laws are per
    cycle) within CPU_SHARE_MAX of it, and longer than ``dt`` when more than KEEP_SHARE of the probe's
    cycles started over half a cycle late (``late_share``, :meth:`LatencyRecord.share_over`: a burst of the
    host, which skips many slots, is one late cycle there, so a short probe is not ruled by one; a cycle the
    host cannot keep is late again and again). Returns (cycle, why)."""
    per_cycle = (cpu_share or 0.0) * dt
    longer = late_share > KEEP_SHARE
    options = sorted(c for c in {*STANDARD_CYCLES_S, dt} if c > dt + 1e-12 or (c >= dt - 1e-12 and not longer))
    c = next((c for c in options if per_cycle <= CPU_SHARE_MAX * c), options[-1] if options else 2 * dt)
    why = (f"the loop's thread used {per_cycle * 1e3:.2f} ms of CPU per cycle ({(cpu_share or 0.0) * 100:.0f} % of a "
           f"CPU at {dt * 1e3:g} ms; at most {CPU_SHARE_MAX * 100:.0f} % at the cycle recommended), "
           f"{late_share * 100:.2f} % of the cycles started over half a cycle late (at most "
           f"{KEEP_SHARE * 100:g} %: half the {MISSED_TARGET * 100:g} % of missed slots allowed, a margin for what "
           "an enabled axis adds)")
    return c, why


WAYS_OUT = "ways out: a longer cycle_s, a PREEMPT_RT kernel, fewer axes or a lighter load beside the loop"

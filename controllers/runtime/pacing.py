"""Pacing a run on the wall clock: one cycle per ``dt`` on the monotonic clock, lateness measured.

In-process, the emulated drives run on the pacer's clock meanwhile (:func:`pace_axes`), so a master
later than a drive's RPDO deadline is caught by the drive as across processes.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from drivectl.controllers.runtime.cycle import Channel


class Pacer:
    """Holds cycle k until t0 + k dt on the monotonic clock: sleep, then spin the last 300 us
    (``time.sleep`` overshoots ~70 us here). A cycle that starts later than half a period after
    its deadline counts as missed."""

    SPIN_S = 300e-6

    def __init__(self, dt: float, now: Callable[[], float] | None = None,
                 sleep: Callable[[float], None] | None = None):
        import time

        self._now = now or time.perf_counter  # injectable: tests stall a master on a simulated clock
        self._sleep = sleep or time.sleep
        self.dt = dt
        self.t0 = self._now()
        self.missed = 0
        self.worst_late = 0.0

    def wait(self, k: int) -> float:
        """Hold until cycle ``k``'s time; returns how late it starts (s)."""
        deadline = self.t0 + k * self.dt
        now = self._now()
        if deadline - now > self.SPIN_S:
            self._sleep(deadline - now - self.SPIN_S)
        while (now := self._now()) < deadline:
            pass
        late = now - deadline
        if late > self.worst_late:
            self.worst_late = late
        if late > 0.5 * self.dt:
            self.missed += 1
        return late

    def now(self) -> float:
        """The pacer's clock (the wall clock the in-process drives run on while the run is paced)."""
        return self._now()


def pace_axes(channels: Sequence[Channel], wall: Callable[[], float] | None) -> None:
    """Tell each axis that a paced run starts on ``wall`` (None: it ended); axes without drives of their
    own clock in this process (SimAxis) have no ``pace``."""
    for ch in channels:
        pace = getattr(ch.axis, "pace", None)
        if pace is not None:
            pace(wall)

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
    """Holds cycle k until t0 + k dt on the monotonic clock: sleep, then spin the last stretch. A cycle that
    starts later than half a period after its deadline counts as missed.

    The spun stretch is the sleep's own recent overshoot, learned: a decaying peak of how late ``sleep``
    woke, times SPIN_GAIN, within SPIN_MIN_S..SPIN_MAX_S. A thread in the normal class wakes ~80 us late
    here (its timer slack), the loop's SCHED_FIFO thread ~30 us (p99 60 us): a fixed 300 us spin burnt 30 %
    of a CPU at 1 kHz that the other processes beside the loop (an emulator across processes, the user's
    program) needed (docs/timing.md, "The process around the loop").
    """

    SPIN_MAX_S = 300e-6
    SPIN_MIN_S = 40e-6
    SPIN_GAIN = 1.5
    #: the learned stretch shrinks by this per cycle after a late wake-up (halved in 70 cycles)
    SPIN_DECAY = 0.99

    def __init__(self, dt: float, now: Callable[[], float] | None = None,
                 sleep: Callable[[float], None] | None = None):
        import time

        self._now = now or time.perf_counter  # injectable: tests stall a master on a simulated clock
        self._sleep = sleep or time.sleep
        self.dt = dt
        self.t0 = self._now()
        self.missed = 0
        self.worst_late = 0.0
        self.spin_s = self.SPIN_MAX_S  # from the safe end: learned down within a second

    def wait(self, k: int) -> float:
        """Hold until cycle ``k``'s time; returns how late it starts (s)."""
        deadline = self.t0 + k * self.dt
        now = self._now()
        spin = self.spin_s
        if deadline - now > spin:
            wake = deadline - spin
            self._sleep(wake - now)
            over = self._now() - wake
            self.spin_s = min(self.SPIN_MAX_S, max(self.SPIN_MIN_S, spin * self.SPIN_DECAY, self.SPIN_GAIN * over))
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


def slots_behind(since_t0: float, dt: float, k: int) -> int:
    """How many slots past slot ``k`` a time ``since_t0`` (s after the pacer's t0) lies: 0 within slot ``k``'s
    period; once a whole slot or more, the slot nearest it (what a drive samples then belongs to that one)."""
    behind = int(since_t0 / dt) - k
    if behind > 0:
        behind = max(behind, round(since_t0 / dt) - k)
    return behind


def pace_axes(channels: Sequence[Channel], wall: Callable[[], float] | None,
              slip: Callable[[float | None], int] | None = None) -> None:
    """Tell each axis that a paced run starts on ``wall`` (None: it ended), and who says, just before a cycle's
    SYNC goes out, how many slots it slipped since the cycle took its slot (``slip``: ServoLoop); an axis
    without drives of their own clock in this process (SimAxis) has nothing to do (driver/axis.py)."""
    for ch in channels:
        ch.axis.pace(wall)
        ch.axis.watch_sync(slip if wall is not None else None)

"""Handles on what the resident loop was asked to do: :class:`Move` (wait for its end), and a profile's run.

The loop's side ends a handle with :meth:`Move.finish` (its status, detail and fault, and where the
axis stood); the user's side waits on it (:meth:`Move.wait`), which raises :class:`MotionFault` when the
command ended in a fault.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from drivectl.controllers.runtime.cycle import Fault
from drivectl.driver.axis import AxisError
from drivectl.profiles.base import Reference

if TYPE_CHECKING:
    from drivectl.controllers.runtime.loop import AxisRuntime, ServoLoop
    from drivectl.controllers.runtime.servo import RunPlan


class MoveStatus(StrEnum):
    """Where a command given to the loop stands (a str: messages and traces read the value)."""

    PENDING = "pending"  # not yet taken by the loop
    MOVING = "moving"
    SETTLING = "settling"  # the reference arrived, the axis is getting into position
    DONE = "done"
    STOPPED = "stopped"  # replaced by another command, stopped, or the axis disabled
    FAULT = "fault"


class MotionFault(RuntimeError):
    """A move ended in a fault; ``fault`` says which (kind, axis, cycle, statusword, 0x603F, safe state)."""

    def __init__(self, message: str, fault: Fault | None):
        super().__init__(message)
        self.fault = fault

    def __reduce__(self) -> tuple[type, tuple[str, Fault | None]]:
        return MotionFault, (str(self), self.fault)  # across the loop's process boundary (session_process.py)


class Move:
    """A handle on a command given to the loop (move, jog, stop, home, run): ``wait()`` for its end.

    ``status``: pending (not yet taken by the loop), moving, settling (the reference arrived, the axis
    is getting into position), done, stopped (replaced by another command, stopped, or the axis
    disabled), fault. After the end: ``position`` and ``following_error`` (m) at the end, ``settled``
    (in position within the window), ``cycles`` it took, ``trace`` (a run's record)."""

    def __init__(self, loop: ServoLoop, axis: str, kind: str, target: float | None = None):
        self.loop = loop
        self.axis = axis
        self.kind = kind
        self.target = target
        self.status = MoveStatus.PENDING
        self.detail = ""
        self.fault: Fault | None = None
        self.position: float | None = None
        self.following_error: float | None = None
        self.settled = False
        self.cycles = 0
        self._run: ProfileRun | None = None  # a run's record, once it ended
        self._trace_fn: Callable[[Move], Any] | None = None
        self._run_meta: dict[str, str] = {}  # a run's own metadata (profile, offset) for its trace
        self._trace: Any = None
        self._writer: Any = None  # a streamed run's TraceWriter, closed by wait()
        self.path: Path | None = None  # where a streamed run's trace was written
        self.record_error = ""
        #: what the loop starts when this ends done (a run after its approach move)
        self._then: Callable[[], None] | None = None
        self._done = threading.Event()
        self._in_position = 0
        self._settle_cycles = 0

    @property
    def done(self) -> bool:
        return self._done.is_set()

    def finish(self, status: MoveStatus, rt: AxisRuntime | None = None, detail: str = "",
               fault: Fault | None = None) -> None:
        """The loop's side: the command ended (``status``), ``rt`` where the axis stood; once only."""
        if self._done.is_set():
            return
        self.status, self.detail, self.fault = status, detail, fault
        if rt is not None:
            self.position = rt.position
            self.following_error = rt.following_error
        self._done.set()

    @property
    def trace(self) -> Any:
        """A run's record (trace v1), once it ended; None for other commands."""
        if self._trace is None and self._run is not None and self._trace_fn is not None:
            self._trace = self._trace_fn(self)
        return self._trace

    def wait(self, timeout: float | None = None) -> Move:
        """Block until the command ended (lockstep: run the cycles, ``timeout`` in simulated s; wall:
        ``timeout`` in s of the wall clock). Raises :class:`MotionFault` when it ended in a fault,
        TimeoutError when it has not ended within ``timeout``."""
        if not self.loop.wait_until(self._done.is_set, timeout):
            if self.loop.error is not None:
                raise AxisError(f"axis {self.axis}: {self.kind}: the servo loop ended ({self.loop.error!r}); the "
                                "drives' own watchdogs stop the axes")
            within = f"within {timeout:g} s" if timeout is not None else "while waiting"
            raise TimeoutError(f"axis {self.axis}: {self.kind} not done {within} (status {self.status})")
        self.close_record()
        if self.status == MoveStatus.FAULT:
            raise MotionFault(f"axis {self.axis}: {self.kind} ended in a fault: {self.detail}", self.fault)
        return self

    def close_record(self) -> None:
        """A streamed run's file: closed (trailer, rename) on the waiting side, never in the cycle."""
        writer, self._writer = self._writer, None
        if writer is None:
            return
        trailer = {"stop": self.status, "cycles": str(self._run.k if self._run else 0)}
        if self.detail:
            trailer["stop_detail"] = self.detail
        if self.fault is not None:
            trailer.update(self.fault.meta())
        try:
            self.path = writer.close(trailer)
        except Exception as exc:  # noqa: BLE001 - the run's end is reported all the same
            self.record_error = str(exc)

    def __repr__(self) -> str:
        where = f" at {self.position * 1e3:.6f} mm" if self.position is not None else ""
        return f"<Move {self.kind} axis {self.axis}: {self.status}{where}>"


@dataclass
class ProfileRun:
    """A profile being run on one axis by the resident loop: the cursor ``k`` through a
    :class:`~drivectl.controllers.runtime.servo.RunPlan` of one channel (checked and sampled whole by
    ``plan_run`` outside the cycle: the one record of a run's references), and what the axis did,
    recorded into ``rec`` (and ``append``-ed where it streams)."""

    plan: RunPlan
    k: int = 0
    rec: np.ndarray = field(default_factory=lambda: np.zeros((3, 0)))  # pos, vel, effort
    #: TraceWriter.append of a streamed record (time, ref, pos, effort, vel), or None
    append: Callable[..., None] | None = None

    def __post_init__(self) -> None:
        self.refs = self.plan.refs[0]  # r, r', r'', r''' per cycle (offset applied)
        self.n = self.plan.n
        self.rows = [self.rec[j] for j in range(len(self.rec))]  # row views: element writes in the cycle
        self.skipped = np.zeros(self.rec.shape[1], dtype=bool)  # rows a late wake-up skipped (no sample)

    def skip(self, cycles: int) -> None:
        """A late wake-up skipped ``cycles`` slots: the reference is a function of time, as a move's is
        (Trajectory.skip), so the cursor moves on with the slots; their rows are marked skipped (no sample
        was taken: the run's trace has no row there, its time jumps over them as the streamed record's does)."""
        end = min(self.k + cycles, self.n)
        if end > self.k:
            self.skipped[self.k:end] = True
            self.k = end

    def next(self) -> Reference:
        k = self.k if self.k < self.n else self.n - 1
        pr, vr, ar, jr = self.refs
        if self.k >= self.n:
            return Reference(pr[k])
        return Reference(pr[k], vr[k], ar[k], jr[k])

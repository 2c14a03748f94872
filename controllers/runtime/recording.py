"""A run's record: every cycle's reference, position, velocity and effort per axis, turned into traces.

:class:`Recording` preallocates the arrays (``keep``) and/or streams rows through
:class:`~drivectl.tracefile.stream.TraceWriter` (an append per cycle: no I/O in the cycle);
:meth:`Recording.result` makes the :class:`RunResult` (one trace per axis, how the run ended).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from drivectl.controllers.base import Controller
from drivectl.controllers.runtime.cycle import Fault, StopReason, settle_cycles
from drivectl.driver.axis import Axis, Feedback
from drivectl.tracefile.format import Trace, format_value

if TYPE_CHECKING:
    from drivectl.controllers.runtime.pacing import Pacer
    from drivectl.controllers.runtime.servo import RunOutcome, RunPlan


def trace_header(axis: Axis, dt: float, controller: Controller | None = None, meta: Mapping[str, object] | None = None,
                 *, paced: bool = False) -> dict[str, str]:
    """The metadata a trace v1 starts with (docs/trace-format.md), the same lines in the same order for
    every trace drivectl writes (a run, a session's run, a capture, a fault's ring): the axis, its effort
    unit, the cycle time, the controller's settings (``describe()``), what the caller knows (the machine's
    part: plant, model, profile, bus, configuration, effects, injected faults, from
    machine/build.py ``machine_meta``; a session run's profile and offset), and the clock."""
    head = {"axis": axis.name, "effort_unit": axis.effort_unit, "dt_s": format_value(dt)}
    if controller is not None:
        head.update((k, format_value(v)) for k, v in controller.describe().items())
    head.update((k, format_value(v)) for k, v in (meta or {}).items())
    head["clock"] = "wall clock, paced" if paced else "lockstep"
    return head


@dataclass
class RunResult:
    """One trace per axis and why the run ended."""

    traces: dict[str, Trace]
    stop: StopReason = StopReason.COMPLETED
    detail: str = ""
    cycles: int = 0
    clipped: dict[str, int] = field(default_factory=dict)
    fault: Fault | None = None
    #: False when the run ended before any axis was asked to enable (nothing moved)
    enabled: bool = True
    #: the files the run streamed its traces to (``stream=``), per axis
    paths: dict[str, Path] = field(default_factory=dict)
    #: why a streamed trace could not be written whole (the run itself went on), per axis
    stream_errors: dict[str, str] = field(default_factory=dict)

    @property
    def trace(self) -> Trace:
        """The trace of a single-axis run."""
        return next(iter(self.traces.values()))

    @property
    def ok(self) -> bool:
        return self.stop is StopReason.COMPLETED


class Recording:
    """Position, velocity and effort of every cycle of a run, preallocated; turned into one
    :class:`~drivectl.tracefile.format.Trace` per axis at the end, and (``stream``) written as the run goes
    through :class:`~drivectl.tracefile.stream.TraceWriter` (an append per cycle: no I/O in the cycle)."""

    COLUMNS = ("time_s", "ref_m", "pos_m", "effort", "vel_m_s")

    def __init__(self, plan: RunPlan, stream: str | Path | None = None, paced: bool = False):
        self.plan = plan
        self.dt = plan.dt
        if not plan.keep and stream is None:
            raise ValueError("run: a plan made with keep=False records only by streaming: give stream=")
        n = plan.cycles if plan.keep else 0
        self._cols = [{k: np.zeros(n) for k in ("ref_m", "pos_m", "effort", "vel_m_s")} for _ in plan.channels]
        self._rows = [(c["ref_m"], c["pos_m"], c["vel_m_s"], c["effort"]) for c in self._cols] if plan.keep else None
        self._counters0 = [dict(ch.axis.counters) for ch in plan.channels]
        self._head = [trace_header(ch.axis, plan.dt, ch.controller, ch.meta, paced=paced) for ch in plan.channels]
        self.writers: list = []
        if stream is not None:
            from drivectl.tracefile.stream import TraceWriter

            # in lockstep (nothing runs on a wall clock beside the loop) the loop writes its own full blocks:
            # no writer thread taking the GIL mid-cycle. Paced, or with drives in another process (their
            # RPDO deadline is on the wall clock), the thread formats them and the loop never waits.
            inline = not paced and all(ch.axis.lockstep for ch in plan.channels)
            try:
                for ch, head in zip(plan.channels, self._head, strict=True):
                    self.writers.append(TraceWriter(stream, ch.axis.name, columns=self.COLUMNS, meta=head,
                                                    inline=inline).start())
            except BaseException:
                self.abandon()
                raise
        self._append = [w.append for w in self.writers] if self.writers else None

    def record(self, i: int, k: int, fb: Feedback, u: float, ref: float) -> None:
        if self._rows is not None:
            r, pos, vel, eff = self._rows[i]
            r[k] = ref
            pos[k] = fb.position
            vel[k] = fb.velocity
            eff[k] = u
        if self._append is not None:
            self._append[i](k * self.dt, ref, fb.position, u, fb.velocity)

    def abandon(self) -> None:
        for w in self.writers:
            try:
                w.abandon()
            except Exception:  # noqa: BLE001 - the others must still be closed
                pass
        self._append = None

    def result(self, out: RunOutcome, pacer: Pacer | None) -> RunResult:
        plan, n = self.plan, out.cycles
        pacing = {}
        if pacer is not None and n:
            pacing = {"paced": "wall clock", "missed_deadlines": str(pacer.missed),
                      "missed_fraction": format_value(pacer.missed / n),
                      "worst_late_ms": format_value(pacer.worst_late * 1e3)}
        traces = {}
        paths: dict[str, Path] = {}
        errors: dict[str, str] = {}
        t = plan.t[:n] if plan.keep else None
        for i, ch in enumerate(plan.channels):
            head = self._head[i]
            meta = {
                **head,
                "cycles": str(n),
                "stop": out.stop.value,
                **pacing,
            }
            if out.detail:
                meta["stop_detail"] = out.detail
            if ch.clipped:
                meta["effort_clipped_cycles"] = str(ch.clipped)
            if ch.settle_max_error is not None:  # held after enabling, before the first row (servo.py _settle)
                meta["settle_s"] = format_value(settle_cycles(plan.channels, plan.dt) * plan.dt)
                meta["settle_max_error_m"] = format_value(ch.settle_max_error)
            for key, value in ch.axis.counters.items():
                meta[key] = str(value - self._counters0[i].get(key, 0))
            if out.fault is not None:
                meta.update(out.fault.meta())
                name = ch.axis.name
                meta["safe_state"] = out.fault.safe_state.get(name, "unknown")
                after = out.fault.safe_after.get(name)
                meta["safe_after_cycles"] = "unknown" if after is None else str(after)
            if plan.keep:
                cols = {"time_s": t, **{k: v[:n] for k, v in self._cols[i].items()}}
                traces[ch.axis.name] = Trace({k: cols[k] for k in self.COLUMNS}, meta)
            if self.writers:
                w = self.writers[i]
                try:
                    paths[ch.axis.name] = w.close({k: v for k, v in meta.items() if k not in head})
                except Exception as exc:  # noqa: BLE001 - a write error must not lose the run's result
                    errors[ch.axis.name] = str(exc)
                if not plan.keep:  # the record is the file: read back (the rows it has, if it failed)
                    try:
                        tr = traces[ch.axis.name] = Trace.read(paths.get(ch.axis.name) or w.partial)
                        if ch.axis.name in errors:  # cut short by the disk, not by the run: say how the run ended
                            tr.meta.update({k: v for k, v in meta.items() if k != "cycles"})
                    except Exception as exc:  # noqa: BLE001
                        errors.setdefault(ch.axis.name, str(exc))
        return RunResult(traces, out.stop, out.detail, n, {ch.axis.name: ch.clipped for ch in plan.channels},
                         out.fault, out.started, paths, errors)

"""The servo cycle: profile -> controller -> axis, once per cycle, recorded as a trace.

Lockstep: each ``axis.read()`` lets the axis advance exactly one cycle (a plant step in SimAxis, a
SYNC on the bus), so the run takes as little wall time as the CPU allows and is deterministic.

Safety is part of the loop, not an option: before anything moves the profile is checked against the
soft limits and the axis must sit where the profile starts; every cycle the command is clipped to the
effort limit, and a position outside the soft limits or a following error outside its window for
longer than its time ends the run in quick stop, with the trace kept and the reason recorded. Ctrl-C
and SIGTERM end the same way, at the next cycle boundary (:mod:`~drivectl.controllers.runtime.interrupt`).
So does every fault: the drive leaving Operation Enabled (a drive fault: statusword bit 3), an
implausible position step (faster than ``max_speed``), and what the axis itself detects
(:class:`~drivectl.driver.axis.AxisError` with its kind: lost TPDOs, a lost heartbeat, an unexpected
boot-up, a bus error). The quick stop goes out in the very cycle of the detection; the cycles until
each drive reports a safe state (Switch On Disabled, Quick Stop Active, or Fault: torque off in all
three) are counted, and the fault (kind, cycle, statusword, 0x603F text) goes into the trace metadata.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping, Sequence
from contextlib import nullcontext
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import ClassVar

import numpy as np

from drivectl.controllers.base import Controller, Settings, SettingsError, param
from drivectl.controllers.runtime.interrupt import StopRequest, stop_on_signals
from drivectl.controllers.runtime.run_checks import JumpState, RunChecks, RunGuard, position_jump
from drivectl.driver.axis import Axis, AxisError, FaultKind, Feedback
from drivectl.driver.cia402 import PowerState, error_text
from drivectl.errors import InputError
from drivectl.profiles.base import Profile, ProfileError, Reference, check_limits, profile_name
from drivectl.tracefile.format import Trace, format_value


class StopReason(Enum):
    COMPLETED = "completed"
    FOLLOWING_ERROR = "following error"
    SOFT_LIMIT = "soft position limit"
    INTERRUPTED = "interrupted"
    FAULT = "fault"
    AXIS_ERROR = "axis error"


class LimitError(InputError):
    """A run was refused before anything moved (profile outside limits, axis not at the start)."""


#: the most cycles a run records in memory (``keep=True``: 32 bytes per cycle and axis), one hour at 1 kHz
MAX_RUN_CYCLES = 3_600_000
#: the most cycles of a run that records only as it streams (constant memory; the limit is the file's:
#: about 24 days at 1 kHz, some 60 GB per axis)
MAX_STREAMED_CYCLES = 2**31 - 1


def check_run_length(duration: float, dt: float, what: str = "run: duration", *, streamed: bool = False) -> int:
    """The number of cycles of a run of ``duration`` s; LimitError (naming ``what``) unless it is > 0 and
    at most MAX_RUN_CYCLES (MAX_STREAMED_CYCLES for a run that records only by streaming)."""
    if not (math.isfinite(duration) and duration > 0):
        raise LimitError(f"{what}: must be a number of seconds > 0, got {duration!r}")
    n = int(round(duration / dt)) + 1
    cap, how = (MAX_STREAMED_CYCLES, "a streamed run records") if streamed else (MAX_RUN_CYCLES, "a run records")
    if n > cap:
        raise LimitError(f"{what}: {duration:g} s is {n} cycles of {dt * 1e3:g} ms, more than {how} "
                         f"({cap} cycles, {cap * dt:g} s); split it into shorter runs")
    return n


@dataclass(frozen=True)
class Limits(Settings):
    """What an axis may do. Defaults allow everything but a following error beyond 5 mm."""

    where: ClassVar[str] = "limits"

    position: tuple[float, float] | None = None  # soft limits, m (0x607D)
    max_effort: float = param(math.inf, lo=0.0, lo_open=True, finite=False,
                              doc="the command is clipped to +-max_effort (inf: not limited)")
    following_error: float = param(5e-3, lo=0.0, lo_open=True, unit="m", doc="window (0x6065)")
    following_time: float = param(0.0, lo=0.0, unit="s", doc="the error may stay outside the window this long (0x6066)")
    max_speed: float = param(2.0, lo=0.0, lo_open=True, unit="m/s",
                             doc="a position step faster than this between two samples is implausible")
    max_jump: float = param(5e-4, lo=0.0, lo_open=True, unit="m", doc="a second difference of the position beyond "
                            "this is an encoder glitch (controllers/runtime/run_checks.py)")
    #: where the soft limits come from (a configuration key, a drive object), named when a profile leaves them
    position_source: str | None = field(default=None, compare=False)

    def validate(self, source: str = "limits", prefix: str = "") -> None:
        if self.position is not None and not self.position[0] < self.position[1]:
            raise SettingsError(f"{source}: {prefix}position: lower limit must be below upper, got {self.position}")
        super().validate(source, prefix)


#: power states with the torque off: where a stop must end
SAFE_STATES = (PowerState.SWITCH_ON_DISABLED, PowerState.QUICK_STOP_ACTIVE, PowerState.FAULT,
               PowerState.FAULT_REACTION_ACTIVE)


@dataclass
class Fault:
    """What ended a run other than completion, and how the axes came to rest."""

    kind: str  # a FaultKind value, or "interrupted"
    axis: str
    cycle: int  # trace row of the detection
    detail: str
    statusword: int | None = None  # of the faulted axis, after the stop
    error_code: int | None = None  # its 0x603F, after the stop (None: could not be read)
    safe_after: dict[str, int | None] = field(default_factory=dict)  # cycles to a safe state (None: unknown)
    safe_state: dict[str, str] = field(default_factory=dict)

    def meta(self) -> dict[str, str]:
        out = {"fault_kind": self.kind, "fault_axis": self.axis, "fault_cycle": str(self.cycle)}
        if self.statusword is not None:
            stale = self.safe_after.get(self.axis) is None  # the drive confirmed nothing after the stop
            out["fault_statusword"] = f"0x{self.statusword:04X}" + (" (the last received)" if stale else "")
        out["fault_error"] = (f"0x{self.error_code:04X}: {error_text(self.error_code)}" if self.error_code is not None
                              else "unknown (0x603F could not be read)")
        return out


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


@dataclass
class Channel:
    """One axis of a run: what it follows and what closes its loop."""

    axis: Axis
    controller: Controller
    profile: Profile
    limits: Limits = field(default_factory=Limits)
    meta: Mapping[str, object] = field(default_factory=dict)
    #: first cycle of the current excursion outside the following-error window
    following_since: int | None = field(default=None, init=False, repr=False)
    last_position: float | None = field(default=None, init=False, repr=False)
    #: cycles whose command was clipped to max_effort (since the run or the enable began)
    clipped: int = field(default=0, init=False, repr=False)
    #: the encoder plausibility check's memory (renewed with last_position: a run, a move of the loop)
    jump: JumpState = field(default_factory=JumpState, init=False, repr=False)


def run(
    axis: Axis,
    controller: Controller,
    profile: Profile,
    *,
    duration: float | None = None,
    limits: Limits | None = None,
    meta: Mapping[str, object] | None = None,
    progress: bool = False,
) -> RunResult:
    """Run one axis through ``profile`` under ``controller``; see :func:`run_channels`."""
    channel = Channel(axis, controller, profile, limits or Limits(), meta or {})
    return run_channels([channel], duration=duration, progress=progress)


def run_preview(controller: Controller, profile: Profile, times: np.ndarray, offset: float = 0.0) -> object:
    """The controller's reference preview for a run of ``profile`` at the run's cycle times ``times``
    (controllers/base.py ``preview``), the profile's positions shifted by ``offset`` (a relative run of
    the resident loop). A one-shot run prepares the controller with the same profile and times
    (:func:`run_channels`); the resident loop computes this outside its cycle (``Controller.preview``
    only reads) and installs it with ``use_preview`` in the cycle the run takes the axis."""
    return controller.preview(_Offset(profile, offset) if offset else profile, np.asarray(times, dtype=float))


class _Offset:
    """``profile`` with its positions shifted by ``offset`` m (a relative run)."""

    def __init__(self, profile: Profile, offset: float):
        self._p, self._offset = profile, offset
        self.duration = profile.duration

    def sample(self, t: np.ndarray):
        r, *rest = self._p.sample(t)
        return (np.asarray(r) + self._offset, *rest)


#: cycles of reference sampled at a time: a run holds one chunk of its references, whatever its length
REF_CHUNK = 8192


@dataclass
class RunPlan:
    """A run checked before anything moves: the channels, the cycle count and, chunk by chunk, every
    channel's reference (r, r', r'', r''' as Python lists: the cycle indexes them, no maths; the next
    :data:`REF_CHUNK` cycles are sampled when the cycle reaches them, so the memory does not grow with
    the run's length). ``keep``: the run's record is also held in memory (see :class:`Recording`)."""

    channels: Sequence[Channel]
    dt: float
    n: int
    refs: list[list[list[float]]] = field(default_factory=list)  # the chunk that starts at cycle ``base``
    base: int = 0
    keep: bool = True

    @property
    def cycles(self) -> int:
        return self.n

    @property
    def t(self) -> np.ndarray:
        """Every cycle's time (made when asked: a controller's preview, the in-memory record)."""
        return np.arange(self.n) * self.dt

    def load(self, k0: int) -> None:
        """Sample the chunk of references that starts at cycle ``k0``."""
        t = np.arange(k0, min(k0 + REF_CHUNK, self.n)) * self.dt
        self.refs = [[a.tolist() for a in ch.profile.sample(t)] for ch in self.channels]
        self.base = k0


def plan_run(channels: Sequence[Channel], duration: float | None = None, *, keep: bool = True) -> RunPlan:
    """Check the channels and their profiles against the limits and sample the first references
    (LimitError or ValueError, nothing moved). Planning a second run before the first ends (an approach
    move, then the profile) lets the second follow the first within one cycle. ``keep=False``: the run
    is recorded only where it streams (``run_channels(stream=...)``), at constant memory."""
    if not channels:
        raise ValueError("run: no axes given")
    dt = channels[0].axis.dt
    for ch in channels:
        if abs(ch.axis.dt - dt) > 1e-12 or abs(ch.controller.dt - dt) > 1e-12:
            raise ValueError(f"run: axis {ch.axis.name}: cycle times differ ({ch.axis.dt}, {ch.controller.dt})")
    if duration is not None:
        total, what = duration, "run: duration"
    else:
        longest = max(channels, key=lambda ch: ch.profile.duration).profile
        total = longest.duration
        source = getattr(longest, "source", None)
        what = f"profile {profile_name(longest)}{f' ({source})' if source else ''}: duration"
    n = check_run_length(total, dt, what, streamed=not keep)
    for ch in channels:
        _check_profile(ch, (n - 1) * dt)
    plan = RunPlan(channels, dt, n, keep=keep)
    plan.load(0)
    return plan


def run_channels(
    channels: Sequence[Channel] | RunPlan,
    *,
    duration: float | None = None,
    progress: bool = False,
    disable_at_end: bool = True,
    on_start: Callable[[int], None] | None = None,
    pace: bool | Pacer = False,
    stop_request: StopRequest | None = None,
    stream: str | Path | None = None,
    checks: RunChecks | None = None,
) -> RunResult:
    """Run several axes in lockstep, one cycle each per step, and record a trace per axis.

    Read top-down: :func:`plan_run` (checks, references; nothing moves), :func:`_bring_up` (enable),
    :func:`_run_cycles` (the cycle: :func:`sample_axis` -> :func:`control` -> record ->
    :func:`check_and_write` per axis), then the ending (:func:`_safe_stop` on a fault or an interrupt,
    :func:`_disable_all` on completion) and :class:`Recording` turning the arrays into traces.

    ``channels`` may be a :class:`RunPlan` already made (``duration`` is then ignored).
    ``on_start(cycles)`` is called once the axes are enabled and the first cycle is recorded (an
    interrupt ends in quick stop with the trace kept at any time). ``pace=True`` runs the cycles on the
    wall clock (one per ``dt``, as with a real drive) instead of lockstep; missed deadlines and the
    worst lateness are measured and written into the trace metadata, never hidden; in-process the
    emulated drives run on the same wall clock meanwhile (their RPDO deadline catches a master that runs
    late, as across processes: :meth:`Pacer.now`, ``axis.pace``). ``pace`` may be a :class:`Pacer` (its
    clock injected: tests).
    ``disable_at_end=False`` leaves the axes enabled (zero effort until the next run takes them).
    ``stream``: a folder the traces are written to as the run goes (tracefile/stream.py: a
    ``.partial`` file flushed every 100 ms, renamed when the run ends, a new name per run and
    ``AXIS.csv`` the latest; ``RunResult.paths``); the files are opened before anything moves, so an
    output that cannot be written stops the run before it starts (TraceWriteError).
    ``checks``: the ``[checks]`` fault thresholds stop the run the cycle they are passed (a fault of kind
    "run check": controllers/run_checks.RunGuard); the warnings are judged after the run (``assess``).

    SIGINT and SIGTERM end the run at the next cycle boundary in quick stop, the trace kept: through
    ``stop_request`` when the caller routes the signals (:func:`stop_on_signals`, e.g. for a whole
    command), otherwise the run routes them itself while it lasts (from the main thread).
    """
    plan = channels if isinstance(channels, RunPlan) else plan_run(channels, duration)
    channels = plan.channels
    rec = Recording(plan, stream, pace)
    try:
        for ch in channels:
            ch.controller.reset()
            prepare = getattr(ch.controller, "prepare", None)  # reference preview (controllers/base.py)
            if prepare is not None:
                prepare(ch.profile, plan.t)
            ch.clipped = 0
        pacer = pace if isinstance(pace, Pacer) else Pacer(plan.dt) if pace else None
        if pacer is not None:
            _pace_axes(channels, pacer.now)  # in-process, the drives' clocks are the wall clock too
        guard = RunGuard(checks, plan.cycles, channels, pacer) if checks is not None else None
        signals = nullcontext(stop_request) if stop_request is not None else stop_on_signals()
        with signals as request:
            outcome = _run_cycles(plan, rec, request, pacer, on_start, progress, guard)
        if outcome.stop is StopReason.COMPLETED and disable_at_end:
            _disable_all(channels)
    except BaseException:
        rec.abandon()  # what was streamed stays, as a .partial file
        raise
    finally:
        if pace:
            _pace_axes(channels, None)
    return rec.result(outcome, pacer)


@dataclass
class _Outcome:
    """How the cycles ended (filled by :func:`_run_cycles`)."""

    stop: StopReason = StopReason.COMPLETED
    detail: str = ""
    fault: Fault | None = None
    cycles: int = 0  # cycles recorded
    started: bool = False  # the axes were asked to enable


def _run_cycles(plan: RunPlan, rec: Recording, request: StopRequest, pacer: Pacer | None,
                on_start: Callable[[int], None] | None, progress: bool, guard: RunGuard | None = None) -> _Outcome:
    """Bring the axes up and run the cycles; every way out ends here with the axes stopped."""
    channels, dt, n = plan.channels, plan.dt, plan.cycles
    if plan.base:
        plan.load(0)  # a plan run a second time
    refs, base = plan.refs, 0
    out = _Outcome()
    bar = None
    k = 0
    try:
        if request.signum:
            raise _Interrupted  # before anything is enabled: nothing moves
        out.started = True
        _bring_up(channels)
        bar = _progress(n, progress)
        for k in range(n):
            if request.signum:
                raise _Interrupted  # at a cycle boundary: no frame is half-handled
            j = k - base
            if j == REF_CHUNK:  # the next chunk of references (bounded memory), before the deadline wait
                plan.load(k)
                refs, base, j = plan.refs, k, 0
            if pacer is not None:
                pacer.wait(k)
            for i, ch in enumerate(channels):
                fb = sample_axis(ch, k)
                pr, vr, ar, jr = refs[i]
                r = pr[j]
                u = control(ch, Reference(r, vr[j], ar[j], jr[j]), fb)
                rec.record(i, k, fb, u, r)
                check_and_write(ch, k, dt, fb.position, r, u)
            out.cycles = k + 1
            if guard is not None and (over := guard.check(k + 1)) is not None:
                raise CycleFault(StopReason.FAULT, Fault(FaultKind.RUN_CHECK.value, over[0], k, over[1]), True)
            if k == 0 and on_start is not None:
                on_start(n)
            if bar is not None and k % 250 == 0:
                bar.update(min(250, n - bar.n))
    except CycleFault as exc:
        out.stop, out.fault = exc.stop, exc.fault
        if exc.recorded:
            out.cycles = k + 1
        _safe_stop(channels, out.fault)
        out.detail = out.fault.detail  # with the drive's own reason, read after the stop
    except (_Interrupted, KeyboardInterrupt):
        out.stop = StopReason.INTERRUPTED
        out.detail = f"interrupted ({request.name or 'KeyboardInterrupt'})"
        out.fault = Fault("interrupted", channels[0].axis.name, k, out.detail)
        if out.started:
            _safe_stop(channels, out.fault)
        else:
            out.detail += " before the axes were enabled"
            for ch in channels:
                out.fault.safe_after[ch.axis.name] = 0
                out.fault.safe_state[ch.axis.name] = ch.axis.power.value
    except AxisError as exc:  # raised by the bring-up or by a write
        out.stop, out.detail = (StopReason.FAULT if exc.kind else StopReason.AXIS_ERROR), str(exc)
        out.fault = Fault(exc.kind.value if exc.kind else "axis error", _axis_of(exc, channels), k, out.detail)
        _safe_stop(channels, out.fault)
    finally:
        if bar is not None:
            bar.close()
    return out


# -- one axis, one cycle (shared by run_channels and the resident loop, controllers/runtime/loop.py) ------------
class CycleFault(Exception):
    """A cycle found a reason to stop: a fault or a limit (``fault``), before or after the sample was
    recorded (``recorded``)."""

    def __init__(self, stop: StopReason, fault: Fault, recorded: bool):
        super().__init__(fault.detail)
        self.stop = stop
        self.fault = fault
        self.recorded = recorded


def sample_axis(ch: Channel, k: int) -> Feedback:
    """This cycle's sample of an axis that must be in Operation Enabled (else CycleFault)."""
    try:
        fb = ch.axis.read()
    except AxisError as exc:
        raise CycleFault(StopReason.FAULT if exc.kind else StopReason.AXIS_ERROR,
                         Fault(exc.kind.value if exc.kind else "axis error", ch.axis.name, k, str(exc)),
                         False) from None
    if ch.axis.power is not PowerState.OPERATION_ENABLED:
        raise CycleFault(StopReason.FAULT, _left_operation(ch, k), False)
    return fb


def control(ch: Channel, ref: Reference, fb: Feedback) -> float:
    """The control law, clipped to the effort limit (clipped cycles counted)."""
    u = ch.controller.step(ref, fb)
    lim = ch.limits.max_effort
    if u > lim or u < -lim:
        ch.clipped += 1
        return lim if u > 0 else -lim
    return u


def check_and_write(ch: Channel, k: int, dt: float, pos: float, ref: float, u: float) -> None:
    """The limits (:func:`_violation`), then the setpoint out; CycleFault (recorded) on a violation."""
    reason = _violation(ch, k, dt, pos, ref)
    if reason is not None:
        stop, kind, detail = reason
        raise CycleFault(stop, Fault(kind.value, ch.axis.name, k, detail), True)
    ch.axis.write(u)


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
        self._counters0 = [dict(getattr(ch.axis, "counters", {})) for ch in plan.channels]
        self._head = [self._head_meta(ch, paced) for ch in plan.channels]
        self.writers: list = []
        if stream is not None:
            from drivectl.tracefile.stream import TraceWriter

            try:
                for ch, head in zip(plan.channels, self._head, strict=True):
                    self.writers.append(TraceWriter(stream, ch.axis.name, columns=self.COLUMNS, meta=head).start())
            except BaseException:
                self.abandon()
                raise
        self._append = [w.append for w in self.writers] if self.writers else None

    def _head_meta(self, ch: Channel, paced: bool) -> dict[str, str]:
        """What is known before the run: the header of a streamed trace."""
        return {
            "axis": ch.axis.name,
            "effort_unit": ch.axis.effort_unit,
            "dt_s": format_value(self.plan.dt),
            **{k: format_value(v) for k, v in ch.controller.describe().items()},
            **{k: format_value(v) for k, v in ch.meta.items()},
            "clock": "wall clock, paced" if paced else "lockstep",
        }

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

    def result(self, out: _Outcome, pacer: Pacer | None) -> RunResult:
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
            for key, value in getattr(ch.axis, "counters", {}).items():
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


def _disable_all(channels: Sequence[Channel]) -> None:
    """The end of a completed run: every axis to Switch On Disabled through the cycle."""
    for ch in channels:
        ch.axis.disable()
    _cycle_until(channels, lambda ax: ax.power is not PowerState.OPERATION_ENABLED)


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

    def wait(self, k: int) -> None:
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


    def now(self) -> float:
        """The pacer's clock (the wall clock the in-process drives run on while the run is paced)."""
        return self._now()


def _pace_axes(channels: Sequence[Channel], wall: Callable[[], float] | None) -> None:
    """Tell each axis that a paced run starts on ``wall`` (None: it ended); axes without drives of their
    own clock in this process (SimAxis) have no ``pace``."""
    for ch in channels:
        pace = getattr(ch.axis, "pace", None)
        if pace is not None:
            pace(wall)


class _Interrupted(Exception):
    """Internal: SIGINT/SIGTERM seen at a cycle boundary."""


def _check_profile(ch: Channel, until: float) -> None:
    """Refuse a profile that leaves the soft limits anywhere in the run (before anything moves)."""
    lim = ch.limits
    if lim.position is not None:
        try:
            t0 = 0.0
            while True:  # a window at a time: the check's memory does not grow with the run's length
                span = min(until - t0, CHECK_WINDOW_S)
                profile = ch.profile if t0 == 0.0 else _Shifted(ch.profile, t0)
                try:
                    check_limits(profile, position=lim.position, until=span)
                except ProfileError as exc:
                    raise ProfileError(re.sub(r"at t=([0-9.]+) s", lambda m, t0=t0: f"at t={float(m[1]) + t0:.3f} s",
                                              str(exc), count=1)) from None
                t0 += span
                if t0 >= until:
                    break
        except ProfileError as exc:
            origin = f" ({lim.position_source})" if lim.position_source else ""
            raise LimitError(f"axis {ch.axis.name}: {exc}{origin}; nothing moved") from None
    ch.following_since = None
    ch.last_position = None


#: the soft-limit check of a run samples this much of the profile at a time (s)
CHECK_WINDOW_S = 600.0


class _Shifted:
    """``profile`` seen from ``t0`` on (its name and file kept for the messages)."""

    def __init__(self, profile: Profile, t0: float):
        self._p, self._t0 = profile, t0
        self.name = getattr(profile, "name", None) or profile_name(profile)
        self.source = getattr(profile, "source", None)
        self.duration = max(profile.duration - t0, 0.0)

    def sample(self, t: np.ndarray):
        return self._p.sample(np.asarray(t) + self._t0)


def _left_operation(ch: Channel, k: int) -> Fault:
    """The drive is no longer in Operation Enabled though the master keeps asking for it."""
    axis = ch.axis
    power = axis.power
    if power in (PowerState.FAULT, PowerState.FAULT_REACTION_ACTIVE):
        emcy = getattr(axis, "last_emcy", None)
        code = f"; EMCY 0x{emcy[0]:04X}: {error_text(emcy[0])}" if emcy else ""
        return Fault(FaultKind.DRIVE_FAULT.value, axis.name, k, f"axis {axis.name}: drive fault ({power.value}, "
                     f"statusword 0x{getattr(axis, 'statusword', 0):04X}{code})")
    return Fault(FaultKind.DRIVE_STOPPED.value, axis.name, k,
                 f"axis {axis.name}: the drive left Operation Enabled by itself (now {power.value})")


def _axis_of(exc: AxisError, channels: Sequence[Channel]) -> str:
    text = str(exc)
    return next((ch.axis.name for ch in channels if text.startswith(f"axis {ch.axis.name}:")), channels[0].axis.name)


def _violation(ch: Channel, k: int, dt: float, pos: float, ref: float) -> tuple[StopReason, FaultKind, str] | None:
    lim = ch.limits
    name = ch.axis.name
    last, ch.last_position = ch.last_position, pos
    if last is not None and k and abs(pos - last) > lim.max_speed * dt:
        return StopReason.FAULT, FaultKind.IMPLAUSIBLE_POSITION, (
            f"axis {name}: position jumped {(pos - last) * 1e3:+.3f} mm in one cycle at t={k * dt:.3f} s "
            f"(faster than max_speed {lim.max_speed:g} m/s: encoder?)")
    if last is None:
        ch.jump = JumpState()  # anew with last_position (a run, a move of the resident loop)
    jump = position_jump(ch.jump, pos, lim.max_jump, getattr(ch.axis, "lost_cycles", 0) > 0)
    if jump is not None:
        return StopReason.FAULT, FaultKind.IMPLAUSIBLE_POSITION, (
            f"axis {name}: position jumped {jump * 1e3:+.3f} mm beyond its motion at t={k * dt:.3f} s "
            f"(a second difference beyond limits.max_jump_m {lim.max_jump * 1e3:g} mm: an encoder glitch, or a "
            "violent oscillation)")
    if lim.position is not None and not (lim.position[0] <= pos <= lim.position[1]):
        return StopReason.SOFT_LIMIT, FaultKind.SOFT_LIMIT, (
            f"axis {name}: position {pos:.6f} m outside soft limits at t={k * dt:.3f} s")
    err = ref - pos
    if err > lim.following_error or err < -lim.following_error:
        since = ch.following_since
        if since is None:
            since = ch.following_since = k
        if k == 0:
            return StopReason.FOLLOWING_ERROR, FaultKind.FOLLOWING_ERROR, (
                f"axis {name}: at {pos:.6f} m but the profile starts at {ref:.6f} m; nothing moved"
            )
        if (k - since) * dt >= lim.following_time:
            return StopReason.FOLLOWING_ERROR, FaultKind.FOLLOWING_ERROR, (
                f"axis {name}: following error {err * 1e6:.1f} um beyond the {lim.following_error * 1e6:.0f} um "
                f"window at t={k * dt:.3f} s"
            )
    else:
        ch.following_since = None
    return None


#: cycles a drive may take to reach a commanded power state (CiA 402: two or three)
STATE_CHANGE_CYCLES = 20


def _cycle_until(channels: Sequence[Channel], done: Callable[[Axis], bool]) -> bool:
    """Run zero-effort cycles until every axis satisfies ``done`` (state changes happen at SYNC)."""
    for _ in range(STATE_CHANGE_CYCLES):
        if all(done(ch.axis) for ch in channels):
            return True
        for ch in channels:
            ch.axis.read()
            ch.axis.write(0.0)
    return all(done(ch.axis) for ch in channels)


def _bring_up(channels: Sequence[Channel]) -> None:
    """Enable every axis through the cycle (zero effort, halt set) before the profile starts."""
    for ch in channels:
        ch.axis.enable()
    if not _cycle_until(channels, lambda ax: ax.power is PowerState.OPERATION_ENABLED):
        late = [f"{ch.axis.name} ({ch.axis.power.value})" for ch in channels
                if ch.axis.power is not PowerState.OPERATION_ENABLED]
        raise AxisError(f"axis {', '.join(late)}: not Operation Enabled after {STATE_CHANGE_CYCLES} cycles")


def _safe_stop(channels: Sequence[Channel], fault: Fault | None = None) -> None:
    """Quick stop now (the command goes out in this very cycle), verified by what each drive reports
    after it and escalated where it does not confirm (controllers/runtime/safe_stop.py); the cycles to a
    confirmed safe state and the state (or "may still be powered" and what was tried) go into ``fault``."""
    from drivectl.controllers.runtime.safe_stop import stop_axes

    axes = [ch.axis for ch in channels]
    stops = stop_axes(axes, fault.kind if fault else None, fault.axis if fault else None)
    if fault is not None:
        for ax in axes:
            st = stops[ax.name]
            fault.safe_after[ax.name] = st.confirmed_after
            fault.safe_state[ax.name] = st.safe_state(ax)
        faulted = next((ax for ax in axes if ax.name == fault.axis), None)
        if faulted is not None:
            fault.statusword = getattr(faulted, "statusword", None)
            code = _quietly(faulted.read_error_code) if hasattr(faulted, "read_error_code") else None
            if code is None and getattr(faulted, "last_emcy", None):
                code = faulted.last_emcy[0]
            fault.error_code = code
            if code and fault.kind == FaultKind.DRIVE_STOPPED.value:  # why the drive stopped, in its own words
                fault.detail += f" (its 0x603F: 0x{code:04X}: {error_text(code)})"


def _quietly(fn: Callable[..., object], *args: object) -> object:
    try:
        return fn(*args)
    except Exception:  # noqa: BLE001 - stopping goes on whatever one call raises
        return None


def _progress(n: int, enabled: bool):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=n, unit="cycle", unit_scale=True, leave=False, desc="trace")

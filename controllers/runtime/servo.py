"""A run: profile -> controller -> axis, once per cycle, recorded as a trace (one axis's cycle: cycle.py).

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
from collections.abc import Callable, Mapping, Sequence
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from drivectl.controllers.base import Controller
from drivectl.controllers.runtime.cycle import (
    BRAKE_WAIT_S,
    SAFE_STATES,
    Channel,
    CycleFault,
    Fault,
    LimitError,
    Limits,
    StopReason,
    bridge,
    check_and_write,
    control,
    sample_axis,
    settle_cycles,
)
from drivectl.controllers.runtime.interrupt import StopRequest, stop_on_signals
from drivectl.controllers.runtime.pacing import Pacer, pace_axes
from drivectl.controllers.runtime.recording import Recording, RunResult, trace_header
from drivectl.controllers.runtime.run_checks import RunChecks, RunGuard
from drivectl.controllers.runtime.safe_stop import stop_channels
from drivectl.driver.axis import Axis, AxisError, FaultKind
from drivectl.driver.cia402 import PowerState
from drivectl.profiles.base import Profile, Reference, profile_label, profile_name

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


def offset_profile(profile: Profile, offset: float) -> Profile:
    """``profile`` shifted by ``offset`` m (a relative run of the resident loop); itself when 0."""
    return _Offset(profile, offset) if offset else profile  # type: ignore[return-value]


def run_preview(controller: Controller, profile: Profile, times: np.ndarray, offset: float = 0.0) -> object:
    """The controller's reference preview for a run of ``profile`` at the run's cycle times ``times``
    (controllers/base.py ``preview``), the profile's positions shifted by ``offset`` (a relative run of
    the resident loop). A one-shot run prepares the controller with the same profile and times
    (:func:`run_channels`); the resident loop computes this outside its cycle (``Controller.preview``
    only reads) and installs it with ``use_preview`` in the cycle the run takes the axis."""
    return controller.preview(offset_profile(profile, offset), np.asarray(times, dtype=float))


class _Offset:
    """``profile`` with its positions shifted by ``offset`` m (a relative run; its name and file kept for
    the messages)."""

    def __init__(self, profile: Profile, offset: float):
        self._p, self._offset = profile, offset
        self.duration = profile.duration
        self.name = profile_name(profile)
        self.source = getattr(profile, "source", None)

    def sample(self, t: np.ndarray):
        r, *rest = self._p.sample(t)
        return (np.asarray(r) + self._offset, *rest)


#: cycles of reference sampled at a time: a run holds one chunk of its references, whatever its length
REF_CHUNK = 8192


@dataclass
class RunPlan:
    """A run checked before anything moves: the channels, the cycle count and, chunk by chunk, every
    channel's reference (r, r', r'', r''' as Python lists: the cycle indexes them, no maths; the next
    ``chunk`` cycles are sampled when the cycle reaches them, so the memory does not grow with the run's
    length). ``keep``: the run's record is also held in memory (see :class:`Recording`).

    The one record of a run's references for both runners: a one-shot run (:func:`run_channels`) and
    the resident loop's profile run (controllers/runtime/handles.py ``ProfileRun``, a cursor through a
    plan of one channel, all of it loaded: nothing is sampled in the loop's cycle)."""

    channels: Sequence[Channel]
    dt: float
    n: int
    refs: list[list[list[float]]] = field(default_factory=list)  # the chunk that starts at cycle ``base``
    base: int = 0
    keep: bool = True
    chunk: int = REF_CHUNK

    @property
    def cycles(self) -> int:
        return self.n

    @property
    def t(self) -> np.ndarray:
        """Every cycle's time (made when asked: a controller's preview, the in-memory record)."""
        return np.arange(self.n) * self.dt

    def load(self, k0: int) -> None:
        """Sample the chunk of references that starts at cycle ``k0``."""
        t = np.arange(k0, min(k0 + self.chunk, self.n)) * self.dt
        self.refs = [[a.tolist() for a in ch.profile.sample(t)] for ch in self.channels]
        self.base = k0


def plan_run(channels: Sequence[Channel], duration: float | None = None, *, keep: bool = True,
             chunk: int | None = REF_CHUNK) -> RunPlan:
    """Check the channels and their profiles against the limits and sample the first references
    (LimitError or ValueError, nothing moved). Planning a second run before the first ends (an approach
    move, then the profile) lets the second follow the first within one cycle. ``keep=False``: the run
    is recorded only where it streams (``run_channels(stream=...)``), at constant memory. ``chunk``:
    cycles of reference sampled at a time (None: all of them now)."""
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
        what = f"profile {profile_label(longest)}: duration"
    n = check_run_length(total, dt, what, streamed=not keep)
    for ch in channels:
        _check_profile(ch, (n - 1) * dt)
    plan = RunPlan(channels, dt, n, keep=keep, chunk=chunk or n)
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
    :func:`_settle` (an axis with ``enable_settle_s`` held at the start before the first reference sample),
    :func:`_run_cycles` (the cycle, controllers/runtime/cycle.py: :func:`sample_axis` -> :func:`control` ->
    record -> :func:`check_and_write` per axis), then the ending (:func:`stop_channels` on a fault or an
    interrupt, :func:`_disable_all` on completion) and :class:`Recording` turning the arrays into traces.

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
        settle = settle_cycles(channels, plan.dt)
        for ch in channels:
            ch.controller.reset()
            ch.settle_max_error = None
            if settle:
                # the preview is computed now and installed after the settle (the law's cycle 0 is the run's),
                # where the run would prepare one (a wrapper without ``prepare`` gets none, as without a settle)
                law = control_law(ch.controller)
                prepares = getattr(ch.controller, "prepare", None) is not None
                ch.settle_preview = (law, law.preview(ch.profile, plan.t) if prepares else None, prepares)
            else:
                prepare = getattr(ch.controller, "prepare", None)  # reference preview (controllers/base.py)
                if prepare is not None:
                    prepare(ch.profile, plan.t)
            ch.clipped = 0
        pacer = pace if isinstance(pace, Pacer) else Pacer(plan.dt) if pace else None
        if pacer is not None:
            pace_axes(channels, pacer.now)  # in-process, the drives' clocks are the wall clock too
        guard = RunGuard(checks, plan.cycles, channels, pacer) if checks is not None else None
        signals = nullcontext(stop_request) if stop_request is not None else stop_on_signals()
        with signals as request, one_blas_thread():
            outcome = _run_cycles(plan, rec, request, pacer, on_start, progress, guard)
        if outcome.stop is StopReason.COMPLETED and disable_at_end:
            _disable_all(channels)
    except BaseException:
        rec.abandon()  # what was streamed stays, as a .partial file
        raise
    finally:
        if pace:
            pace_axes(channels, None)
    return rec.result(outcome, pacer)


def one_blas_thread() -> AbstractContextManager[object]:
    """A context in which BLAS (OpenBLAS under numpy) runs on the calling thread only: the cycle's
    products are a few elements, and a BLAS worker left spinning after each burned about 10 us of CPU
    per cycle on the other core. Process-wide while it lasts (threadpoolctl), restored after.

    threadpoolctl finds the BLAS libraries by walking every library the process has loaded (some ms,
    and a tenth of a 3 s lockstep run's wall time when done per run): they are looked up once, at the
    first run, and the same controller limits every later run (numpy's and scipy's are loaded by then:
    the controllers import them)."""
    global _blas
    if _blas is None:
        from threadpoolctl import ThreadpoolController

        _blas = ThreadpoolController()
    return _blas.limit(limits=1, user_api="blas")


_blas = None  # the process's ThreadpoolController, made at the first run (one_blas_thread)


@dataclass
class RunOutcome:
    """How the cycles ended (filled by :func:`_run_cycles`)."""

    stop: StopReason = StopReason.COMPLETED
    detail: str = ""
    fault: Fault | None = None
    cycles: int = 0  # cycles recorded
    started: bool = False  # the axes were asked to enable


def _run_cycles(plan: RunPlan, rec: Recording, request: StopRequest, pacer: Pacer | None,
                on_start: Callable[[int], None] | None, progress: bool, guard: RunGuard | None = None) -> RunOutcome:
    """Bring the axes up and run the cycles; every way out ends here with the axes stopped."""
    channels, dt, n = plan.channels, plan.dt, plan.cycles
    if plan.base:
        plan.load(0)  # a plan run a second time
    refs, base = plan.refs, 0
    out = RunOutcome()
    bar = None
    k = 0
    try:
        if request.signum:
            raise _Interrupted  # before anything is enabled: nothing moves
        out.started = True
        _bring_up(channels)
        if (settle := settle_cycles(channels, dt)):
            _settle(plan, settle, pacer, request)
        bar = _progress(n, progress)
        for k in range(n):
            if request.signum:
                raise _Interrupted  # at a cycle boundary: no frame is half-handled
            j = k - base
            if j == plan.chunk:  # the next chunk of references (bounded memory), before the deadline wait
                plan.load(k)
                refs, base, j = plan.refs, k, 0
            if pacer is not None:
                pacer.wait(k)
            for i, ch in enumerate(channels):
                fb = sample_axis(ch, k)
                pr, vr, ar, jr = refs[i]
                r = pr[j]
                ref = Reference(r, vr[j], ar[j], jr[j])
                fb = bridge(ch, ref, fb, k)
                u = control(ch, ref, fb)
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
        stop_channels(channels, out.fault)
        out.detail = out.fault.detail  # with the drive's own reason, read after the stop
    except (_Interrupted, KeyboardInterrupt):
        out.stop = StopReason.INTERRUPTED
        out.detail = f"interrupted ({request.name or 'KeyboardInterrupt'})"
        out.fault = Fault(FaultKind.INTERRUPTED, channels[0].axis.name, k, out.detail)
        if out.started:
            stop_channels(channels, out.fault)
        else:
            out.detail += " before the axes were enabled"
            for ch in channels:
                out.fault.safe_after[ch.axis.name] = 0
                out.fault.safe_state[ch.axis.name] = ch.axis.power.value
    except AxisError as exc:  # raised by the bring-up or by a write
        out.stop, out.detail = (StopReason.FAULT if exc.kind else StopReason.AXIS_ERROR), str(exc)
        out.fault = Fault(exc.kind or FaultKind.AXIS_ERROR, _axis_of(exc, channels), k, out.detail)
        stop_channels(channels, out.fault)
    finally:
        if bar is not None:
            bar.close()
    return out


def control_law(controller: Controller) -> Controller:
    """The law inside wrappers that add to it per run cycle (a learned correction, an excitation): what
    holds an axis before the run."""
    while (inner := getattr(controller, "inner", None)) is not None:
        controller = inner
    return controller


def _settle(plan: RunPlan, cycles: int, pacer: Pacer | None, request: StopRequest) -> None:
    """Hold every axis at its profile's start under its own law for ``cycles`` cycles, then install the
    run's preview (the law's next step is the run's cycle 0). An axis with a holding brake is free from the
    cycle its drive reports Operation Enabled: whatever load the brake held (z: the table's load-side
    disturbance on the coupling's spring) the law takes over here, at rest, not in the run's first cycles
    of motion. The largest error of the hold goes into the trace (``settle_max_error_m``): the transient
    a part would see at rest before the motion. Faults are a run's (cycle 0: nothing recorded yet)."""
    channels, dt = plan.channels, plan.dt
    holds = [Reference(plan.refs[i][0][0], 0.0, 0.0, 0.0) for i in range(len(channels))]
    worst = [0.0] * len(channels)
    if pacer is not None:
        pacer.t0 = pacer.now()  # paced from the settle's first cycle (the bring-up waited on the drives)
    for s in range(cycles):
        if request.signum:
            raise _Interrupted
        if pacer is not None:
            pacer.wait(s)
        for i, ch in enumerate(channels):
            law = ch.settle_preview[0]
            fb = sample_axis(ch, 0)
            u = law.step(holds[i], fb)
            lim = ch.limits.max_effort
            if u > lim or u < -lim:
                u = lim if u > 0 else -lim
                law.note_applied(u)
            worst[i] = max(worst[i], abs(holds[i].position - fb.position))
            try:
                check_and_write(ch, s, dt, fb.position, holds[i].position, u)
            except CycleFault as exc:
                raise CycleFault(exc.stop, exc.fault, False) from None  # no trace row yet
    if pacer is not None:
        pacer.t0 += cycles * dt  # the run's cycle 0 is the slot after the settle's last
    for i, ch in enumerate(channels):
        law, preview, prepares = ch.settle_preview
        if prepares:
            law.use_preview(preview)
        ch.settle_max_error = worst[i]
        ch.following_since = None
        ch.settle_preview = None


def _disable_all(channels: Sequence[Channel]) -> None:
    """The end of a completed run: every axis to Switch On Disabled through the cycle."""
    for ch in channels:
        ch.axis.disable()
    _cycle_until(channels, lambda ax: ax.power is not PowerState.OPERATION_ENABLED)


class _Interrupted(Exception):
    """Internal: SIGINT/SIGTERM seen at a cycle boundary."""


def _check_profile(ch: Channel, until: float) -> None:
    """Refuse a profile that leaves the soft limits anywhere in the run (before anything moves), sampled
    at :data:`CHECK_RATE_HZ` a window at a time: the check's memory does not grow with the run's length."""
    lim = ch.limits
    if lim.position is not None:
        who = f"axis {ch.axis.name}: profile {profile_label(ch.profile)}"
        t0 = 0.0
        while True:
            span = min(until - t0, CHECK_WINDOW_S)
            t = np.linspace(0.0, span, max(2, math.ceil(span * CHECK_RATE_HZ) + 1)) + t0
            lim.refuse_outside(who, ch.profile.sample(t)[0], t)
            t0 += span
            if t0 >= until:
                break
    ch.following_since = None
    ch.last_position = None


#: the soft-limit check of a run samples this much of the profile at a time (s), at this rate (Hz)
CHECK_WINDOW_S = 600.0
CHECK_RATE_HZ = 2000.0


def _axis_of(exc: AxisError, channels: Sequence[Channel]) -> str:
    text = str(exc)
    return next((ch.axis.name for ch in channels if text.startswith(f"axis {ch.axis.name}:")), channels[0].axis.name)


#: cycles a drive may take to reach a commanded power state (CiA 402: two or three)
STATE_CHANGE_CYCLES = 20


def _cycle_until(channels: Sequence[Channel], done: Callable[[Axis], bool],
                 cycles: int = STATE_CHANGE_CYCLES) -> bool:
    """Run zero-effort cycles until every axis satisfies ``done`` (state changes happen at SYNC)."""
    for _ in range(cycles):
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
    # a drive with a holding brake reports Operation Enabled once the brake has released (tens to
    # hundreds of ms): wait BRAKE_WAIT_S, not just the few cycles of the state machine itself
    cycles = max(STATE_CHANGE_CYCLES, *(math.ceil(BRAKE_WAIT_S / ch.axis.dt) for ch in channels))
    if not _cycle_until(channels, lambda ax: ax.power is PowerState.OPERATION_ENABLED, cycles):
        # the drive's own reason where it gives one (driver/enable_check.py), not just "timed out"
        late = [f"{ch.axis.name} ({ch.axis.power.value}" + (f": {why}" if (why := ch.axis.enable_blocker()) else "")
                + ")" for ch in channels if ch.axis.power is not PowerState.OPERATION_ENABLED]
        raise AxisError(f"axis {', '.join(late)}: not Operation Enabled after {cycles} cycles")


def _progress(n: int, enabled: bool):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=n, unit="cycle", unit_scale=True, leave=False, desc="trace")


#: the run's vocabulary, importable from here as from its own modules (cycle, pacing, recording)
__all__ = ["CHECK_WINDOW_S", "MAX_RUN_CYCLES", "MAX_STREAMED_CYCLES", "REF_CHUNK", "SAFE_STATES", "STATE_CHANGE_CYCLES",
           "Channel", "CycleFault", "Fault", "LimitError", "Limits", "Pacer", "Recording", "RunOutcome", "RunPlan",
           "RunResult", "StopReason", "check_and_write", "check_run_length", "control", "offset_profile", "plan_run",
           "run", "run_channels", "run_preview", "sample_axis", "trace_header"]

"""The servo cycle: profile -> controller -> axis, once per cycle, recorded as a trace.

Lockstep: each ``axis.read()`` lets the axis advance exactly one cycle (a plant step in SimAxis, a
SYNC on the bus), so the run takes as little wall time as the CPU allows and is deterministic.

Safety is part of the loop, not an option: before anything moves the profile is checked against the
soft limits and the axis must sit where the profile starts; every cycle the command is clipped to the
effort limit, and a position outside the soft limits or a following error outside its window for
longer than its time ends the run in quick stop, with the trace kept and the reason recorded. Ctrl-C
(KeyboardInterrupt) ends the same way.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from enum import Enum

import numpy as np

from drivectl.controllers.base import Controller
from drivectl.driver.axis import Axis, AxisError
from drivectl.driver.cia402 import PowerState
from drivectl.profiles.base import Profile, ProfileError, Reference, check_limits
from drivectl.tools.trace import Trace, format_value


class StopReason(Enum):
    COMPLETED = "completed"
    FOLLOWING_ERROR = "following error"
    SOFT_LIMIT = "soft position limit"
    INTERRUPTED = "interrupted"
    AXIS_ERROR = "axis error"


class LimitError(ValueError):
    """A run was refused before anything moved (profile outside limits, axis not at the start)."""


@dataclass(frozen=True)
class Limits:
    """What an axis may do. Defaults allow everything but a following error beyond 5 mm."""

    position: tuple[float, float] | None = None  # soft limits, m (0x607D)
    max_effort: float = math.inf  # the command is clipped to +-max_effort
    following_error: float = 5e-3  # window, m (0x6065)
    following_time: float = 0.0  # s the error may stay outside the window (0x6066)

    def __post_init__(self) -> None:
        if self.position is not None and not self.position[0] < self.position[1]:
            raise ValueError(f"limits: position: lower limit must be below upper, got {self.position}")
        if not self.max_effort > 0:
            raise ValueError(f"limits: max_effort: must be > 0, got {self.max_effort}")
        if not self.following_error > 0:
            raise ValueError(f"limits: following_error: must be > 0, got {self.following_error}")
        if not self.following_time >= 0:
            raise ValueError(f"limits: following_time: must be >= 0, got {self.following_time}")


@dataclass
class RunResult:
    """One trace per axis and why the run ended."""

    traces: dict[str, Trace]
    stop: StopReason = StopReason.COMPLETED
    detail: str = ""
    cycles: int = 0
    clipped: dict[str, int] = field(default_factory=dict)

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


def run_channels(
    channels: Sequence[Channel],
    *,
    duration: float | None = None,
    progress: bool = False,
    disable_at_end: bool = True,
    on_start: Callable[[int], None] | None = None,
    pace: bool = False,
) -> RunResult:
    """Run several axes in lockstep, one cycle each per step, and record a trace per axis.

    ``on_start(cycles)`` is called once the axes are enabled and the first cycle is recorded (an
    interrupt ends in quick stop with the trace kept at any time). ``pace=True`` runs the cycles on the
    wall clock (one per ``dt``, as with a real drive) instead of lockstep; missed deadlines and the
    worst lateness are measured and written into the trace metadata, never hidden.
    """
    if not channels:
        raise ValueError("run: no axes given")
    dt = channels[0].axis.dt
    for ch in channels:
        if abs(ch.axis.dt - dt) > 1e-12 or abs(ch.controller.dt - dt) > 1e-12:
            raise ValueError(f"run: axis {ch.axis.name}: cycle times differ ({ch.axis.dt}, {ch.controller.dt})")
    total = duration if duration is not None else max(ch.profile.duration for ch in channels)
    if not total > 0:
        raise ValueError(f"run: duration: must be > 0, got {total}")
    n = int(round(total / dt)) + 1
    t = np.arange(n) * dt

    refs = []
    for ch in channels:
        _check_profile(ch, float(t[-1]))
        refs.append([a.tolist() for a in ch.profile.sample(t)])
    rec = [{k: np.zeros(n) for k in ("pos_m", "effort", "vel_m_s")} for _ in channels]
    clipped = [0] * len(channels)
    stop, detail, k_done = StopReason.COMPLETED, "", 0

    for ch in channels:
        ch.controller.reset()
    bar = None
    k = 0
    try:
        _bring_up(channels)
        bar = _progress(n, progress)
        pacer = Pacer(dt) if pace else None
        for k in range(n):
            if pacer is not None:
                pacer.wait(k)
            for i, ch in enumerate(channels):
                fb = ch.axis.read()
                pr, vr, ar, jr = refs[i]
                pos = fb.position
                ref = Reference(pr[k], vr[k], ar[k], jr[k])
                u = ch.controller.step(ref, fb)
                lim = ch.limits
                if u > lim.max_effort or u < -lim.max_effort:
                    u = lim.max_effort if u > 0 else -lim.max_effort
                    clipped[i] += 1
                r = rec[i]
                r["pos_m"][k] = pos
                r["vel_m_s"][k] = fb.velocity
                r["effort"][k] = u
                reason = _violation(ch, k, dt, pos, pr[k])
                if reason is not None:
                    stop, detail = reason
                    raise _Stop
                ch.axis.write(u)
            k_done = k + 1
            if k == 0 and on_start is not None:
                on_start(n)
            if bar is not None and k % 250 == 0:
                bar.update(min(250, n - bar.n))
    except _Stop:
        k_done = k + 1
        _safe_stop(channels)
    except KeyboardInterrupt:
        stop, detail = StopReason.INTERRUPTED, "interrupted (KeyboardInterrupt: Ctrl-C or a signal)"
        _safe_stop(channels)
    except AxisError as exc:
        stop, detail = StopReason.AXIS_ERROR, str(exc)
        _safe_stop(channels)
    finally:
        if bar is not None:
            bar.close()
    if stop is StopReason.COMPLETED and disable_at_end:
        for ch in channels:
            ch.axis.disable()
        _cycle_until(channels, lambda ax: ax.power is not PowerState.OPERATION_ENABLED)

    traces = {}
    pacing = {}
    if pace and k_done:
        pacing = {"paced": "wall clock", "missed_deadlines": str(pacer.missed),
                  "missed_fraction": format_value(pacer.missed / k_done),
                  "worst_late_ms": format_value(pacer.worst_late * 1e3)}
    for i, ch in enumerate(channels):
        cols = {
            "time_s": t[:k_done],
            "ref_m": np.asarray(refs[i][0][:k_done]),
            "pos_m": rec[i]["pos_m"][:k_done],
            "effort": rec[i]["effort"][:k_done],
            "vel_m_s": rec[i]["vel_m_s"][:k_done],
        }
        meta = {
            "axis": ch.axis.name,
            "effort_unit": ch.axis.effort_unit,
            "dt_s": format_value(dt),
            **{k: format_value(v) for k, v in ch.controller.describe().items()},
            **{k: format_value(v) for k, v in ch.meta.items()},
            "cycles": str(k_done),
            "stop": stop.value,
            **pacing,
        }
        if detail:
            meta["stop_detail"] = detail
        if clipped[i]:
            meta["effort_clipped_cycles"] = str(clipped[i])
        traces[ch.axis.name] = Trace(cols, meta)
    return RunResult(traces, stop, detail, k_done, {ch.axis.name: c for ch, c in zip(channels, clipped, strict=True)})


class Pacer:
    """Holds cycle k until t0 + k dt on the monotonic clock: sleep, then spin the last 300 us
    (``time.sleep`` overshoots ~70 us here). A cycle that starts later than half a period after
    its deadline counts as missed."""

    SPIN_S = 300e-6

    def __init__(self, dt: float):
        import time

        self._now = time.perf_counter
        self._sleep = time.sleep
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


class _Stop(Exception):
    """Internal: a limit ended the run."""


def _check_profile(ch: Channel, until: float) -> None:
    """Refuse a profile that leaves the soft limits anywhere in the run (before anything moves)."""
    lim = ch.limits
    if lim.position is not None:
        try:
            check_limits(ch.profile, position=lim.position, until=until)
        except ProfileError as exc:
            raise LimitError(f"axis {ch.axis.name}: {exc}; nothing moved") from None
    ch.following_since = None


def _violation(ch: Channel, k: int, dt: float, pos: float, ref: float) -> tuple[StopReason, str] | None:
    lim = ch.limits
    name = ch.axis.name
    if lim.position is not None and not (lim.position[0] <= pos <= lim.position[1]):
        return StopReason.SOFT_LIMIT, f"axis {name}: position {pos:.6f} m outside soft limits at t={k * dt:.3f} s"
    err = ref - pos
    if err > lim.following_error or err < -lim.following_error:
        since = ch.following_since
        if since is None:
            since = ch.following_since = k
        if k == 0:
            return StopReason.FOLLOWING_ERROR, (
                f"axis {name}: at {pos:.6f} m but the profile starts at {ref:.6f} m; nothing moved"
            )
        if (k - since) * dt >= lim.following_time:
            return StopReason.FOLLOWING_ERROR, (
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


def _safe_stop(channels: Sequence[Channel]) -> None:
    """Quick stop, then disable, every axis, cycling until the drives report it; keep going if one
    of them fails (the others must still be stopped)."""
    safe = (PowerState.SWITCH_ON_DISABLED, PowerState.QUICK_STOP_ACTIVE, PowerState.FAULT)
    for action, done in ((lambda ax: ax.quick_stop(), lambda ax: ax.power in safe),
                         (lambda ax: ax.disable(), lambda ax: ax.power is not PowerState.OPERATION_ENABLED
                          and ax.power is not PowerState.QUICK_STOP_ACTIVE)):
        for ch in channels:
            try:
                action(ch.axis)
            except Exception:  # noqa: BLE001 - the other axes must still be stopped
                pass
        try:
            _cycle_until(channels, done)
        except Exception:  # noqa: BLE001 - a dead transport cannot be cycled; nothing more to do here
            pass


def _progress(n: int, enabled: bool):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=n, unit="cycle", unit_scale=True, leave=False, desc="trace")

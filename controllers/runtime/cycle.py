"""One axis, one cycle: sample -> control -> check and write, and the types that cycle speaks.

Both a one-shot run (controllers/runtime/servo.py) and the resident loop (controllers/runtime/loop.py)
close an axis's loop with the same three calls: :func:`sample_axis` (a fault if the drive left Operation
Enabled), :func:`control` (the law, clipped to the effort limit) and :func:`check_and_write` (soft limits,
following error, encoder plausibility, then the setpoint out). A reason to stop is raised as
:class:`CycleFault` carrying a :class:`Fault`; the caller stops the axes (controllers/runtime/safe_stop.py).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from enum import Enum
from typing import Any, ClassVar

from drivectl.controllers.base import Controller, Settings, SettingsError, param
from drivectl.controllers.runtime.run_checks import JumpState, position_jump
from drivectl.driver.axis import Axis, AxisError, FaultKind, Feedback
from drivectl.driver.cia402 import POWER_OPERATION_ENABLED, PowerState, error_text
from drivectl.errors import InputError
from drivectl.profiles.base import Profile, Reference, outside_soft_limits, soft_limit_text


class StopReason(Enum):
    COMPLETED = "completed"
    FOLLOWING_ERROR = "following error"
    SOFT_LIMIT = "soft position limit"
    INTERRUPTED = "interrupted"
    FAULT = "fault"
    AXIS_ERROR = "axis error"



class LimitError(InputError):
    """A run or a move was refused before anything moved (outside the limits, the axis not at the start)."""


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

    def inside(self, position: float) -> bool:
        """``position`` (m) lies within the soft limits (always, without them)."""
        return self.position is None or outside_soft_limits(self.position, position) is None

    def refuse_outside(self, who: str, positions: object, times: object = None) -> None:
        """The soft-limit refusal, for every caller (a move's target, a run, a profile): LimitError, one line
        naming ``who`` ("axis x: move_to"), the first of ``positions`` (m; at ``times`` s) outside the soft
        limits, and where the limits come from; nothing has moved. Nothing without soft limits."""
        if self.position is None:
            return
        outside = outside_soft_limits(self.position, positions, times)
        if outside is not None:
            origin = f" ({self.position_source})" if self.position_source else ""
            raise LimitError(f"{who}: {outside}{origin}; nothing moved")

    def validate(self, source: str = "limits", prefix: str = "") -> None:
        if self.position is not None and not self.position[0] < self.position[1]:
            raise SettingsError(f"{source}: {prefix}position: lower limit must be below upper, got {self.position}")
        super().validate(source, prefix)



#: the longest a power-state change may take: a drive with a holding brake reports Operation Enabled once
#: the brake has released, and leaves it once the brake has engaged (tens to hundreds of ms), s
BRAKE_WAIT_S = 0.5

#: power states with the torque off: where a stop must end
SAFE_STATES = (PowerState.SWITCH_ON_DISABLED, PowerState.QUICK_STOP_ACTIVE, PowerState.FAULT,
               PowerState.FAULT_REACTION_ACTIVE)


@dataclass
class Fault:
    """What ended a run other than completion, and how the axes came to rest."""

    kind: FaultKind
    axis: str
    cycle: int  # trace row of the detection
    detail: str
    statusword: int | None = None  # of the faulted axis, after the stop
    error_code: int | None = None  # its 0x603F, after the stop (None: could not be read)
    safe_after: dict[str, int | None] = field(default_factory=dict)  # cycles to a safe state (None: unknown)
    safe_state: dict[str, str] = field(default_factory=dict)
    at: float | None = None  # on the wall clock: when it was detected (time.monotonic), for the record

    def meta(self) -> dict[str, str]:
        out = {"fault_kind": str(self.kind), "fault_axis": self.axis, "fault_cycle": str(self.cycle)}
        if self.statusword is not None:
            stale = self.safe_after.get(self.axis) is None  # the drive confirmed nothing after the stop
            out["fault_statusword"] = f"0x{self.statusword:04X}" + (" (the last received)" if stale else "")
        out["fault_error"] = (f"0x{self.error_code:04X}: {error_text(self.error_code)}" if self.error_code is not None
                              else "unknown (0x603F could not be read)")
        return out



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
    #: taken up outside the soft limits: the innermost position since (m), None: inside, or not taken so
    outside_mark: float | None = field(default=None, init=False, repr=False)
    #: cycles whose command was clipped to max_effort (since the run or the enable began)
    clipped: int = field(default=0, init=False, repr=False)
    #: a run's settle (servo.py ``_settle``): the law holding the axis, the run's preview it installs after and
    #: whether it does; the largest error of the hold (m), None: no settle
    settle_preview: tuple[Any, Any, bool] | None = field(default=None, init=False, repr=False)
    settle_max_error: float | None = field(default=None, init=False, repr=False)
    #: the encoder plausibility check's memory (renewed with last_position: a run, a move of the loop)
    jump: JumpState = field(default_factory=JumpState, init=False, repr=False)
    #: the tracking error (m, m/s) of the last real sample, which a bridged cycle holds (:func:`bridge`);
    #: None: no real sample yet
    held_error: float | None = field(default=None, init=False, repr=False)
    held_velocity_error: float = field(default=0.0, init=False, repr=False)
    #: the position the last cycle bridged with (m); None: the last cycle had a real sample
    bridged_at: float | None = field(default=None, init=False, repr=False)
    #: real samples judged one SYNC old in a row (:func:`bridge`); each fresh frame resets the axis's own count
    stale_run: int = field(default=0, init=False, repr=False)


class CycleFault(Exception):
    """A cycle found a reason to stop: a fault or a limit (``fault``), before or after the sample was
    recorded (``recorded``)."""

    def __init__(self, stop: StopReason, fault: Fault, recorded: bool):
        super().__init__(fault.detail)
        self.stop = stop
        self.fault = fault
        self.recorded = recorded


def settle_cycles(channels: Sequence[Channel], dt: float) -> int:
    """The cycles a run holds its axes after they are enabled, before its first reference sample: the
    longest ``enable_settle_s`` of its axes (all start together: a contour's axes move as one)."""
    return max(math.ceil(ch.axis.enable_settle_s / dt - 1e-9) for ch in channels)


def sample_axis(ch: Channel, k: int) -> Feedback:
    """This cycle's sample of an axis that must be in Operation Enabled (else CycleFault)."""
    try:
        fb = ch.axis.read()
    except AxisError as exc:
        raise CycleFault(StopReason.FAULT if exc.kind else StopReason.AXIS_ERROR,
                         Fault(exc.kind or FaultKind.AXIS_ERROR, ch.axis.name, k, str(exc)),
                         False) from None
    if ch.axis.power is not POWER_OPERATION_ENABLED:  # a module constant: read every cycle
        raise CycleFault(StopReason.FAULT, _left_operation(ch, k), False)
    return fb


#: a first sample after bridged cycles that lies nearer the last bridged cycle's position than this one's, the
#: two this far apart (m), answered the SYNC before: beyond an encoder's and a tracking error's noise, below
#: what a sample that old costs (at 74 mm/s one slot is 74 um; across a late wake-up 8-10 slots, 0.6-0.7 mm)
STALE_M = 50e-6
#: real samples in a row judged one SYNC old before the cycle faults: each verdict bridges the cycle on a guess,
#: and the axis's count of bridged cycles restarts with every frame that came, so a chain of verdicts had no
#: bound: an axis that fell behind its guess stayed nearer the last one, and the law drove it open-loop at its
#: effort limit (z ran 18 mm away in 0.1 s in an in-process soak, docs/timing.md)
STALE_RUN_MAX = 3


def bridge(ch: Channel, ref: Reference, fb: Feedback, k: int) -> Feedback:
    """A bridged cycle's sample (the drive's TPDOs lost or late: ``axis.lost_cycles``) as the axis following its
    reference with the tracking error of its last real sample; a real sample is returned as it is and its error
    kept. The axis itself can only extrapolate at its last velocity, which knows nothing of the reference: on a
    decelerating move bridged for tens of ms the law then saw the axis ahead of a reference it was following
    and braked it hard on a guess (x 1.3 mm behind after three lost answers at 2 ms; docs/timing.md). Held, the
    error is what was measured last: the law adds no correction on a guess, its feedforward goes on.

    The first real sample after bridged cycles is judged by which cycle's position it fits: nearer the last
    bridged one's (more than :data:`STALE_M` from this one's), it answered the SYNC before, a drive late past
    the budget twice running (docs/timing.md), and this cycle is bridged too (``axis.stale()``; CycleFault past
    the axis's limit of bridged cycles)."""
    axis = ch.axis
    held = ch.held_error
    if axis.lost_cycles:
        if held is None:
            return fb
        pos = ch.bridged_at = ref.position - held
        return Feedback(fb.time, pos, ref.velocity - ch.held_velocity_error)
    before = ch.bridged_at
    if before is not None:
        ch.bridged_at = None
        now = ref.position - held
        if (now - before > STALE_M or before - now > STALE_M) and abs(fb.position - before) < abs(fb.position - now):
            ch.stale_run += 1
            if ch.stale_run > STALE_RUN_MAX:
                raise CycleFault(StopReason.FAULT, Fault(FaultKind.IMPLAUSIBLE_POSITION, axis.name, k, (
                    f"axis {axis.name}: {ch.stale_run} samples in a row behind the position bridged for them (each "
                    f"nearer the cycle before's): the axis is not where the bridge assumes")), False)
            try:
                axis.stale()
            except AxisError as exc:
                raise CycleFault(StopReason.FAULT, Fault(exc.kind or FaultKind.AXIS_ERROR, axis.name, k, str(exc)),
                                 False) from None
            ch.bridged_at = now
            return Feedback(fb.time, now, ref.velocity - ch.held_velocity_error)
    ch.stale_run = 0
    ch.held_error = ref.position - fb.position
    ch.held_velocity_error = ref.velocity - fb.velocity
    return fb


def control(ch: Channel, ref: Reference, fb: Feedback) -> float:
    """The control law, clipped to the effort limit (clipped cycles counted). A clipped cycle tells the law
    what was applied: an observer that took its own unclipped command for what acted would read the
    difference as a disturbance and wind up against the limit (the anti-windup of an observer)."""
    u = ch.controller.step(ref, fb)
    lim = ch.limits.max_effort
    if u > lim or u < -lim:
        ch.clipped += 1
        u = lim if u > 0 else -lim
        ch.controller.note_applied(u)
    return u


def check_and_write(ch: Channel, k: int, dt: float, pos: float, ref: float, u: float) -> None:
    """The limits (:func:`_violation`), then the setpoint out; CycleFault (recorded) on a violation."""
    reason = _violation(ch, k, dt, pos, ref)
    if reason is not None:
        stop, kind, detail = reason
        raise CycleFault(stop, Fault(kind.value, ch.axis.name, k, detail), True)
    ch.axis.write(u)


def _left_operation(ch: Channel, k: int) -> Fault:
    """The drive is no longer in Operation Enabled though the master keeps asking for it."""
    axis = ch.axis
    power = axis.power
    if power in (PowerState.FAULT, PowerState.FAULT_REACTION_ACTIVE):
        emcy = axis.last_emcy
        code = f"; EMCY 0x{emcy[0]:04X}: {error_text(emcy[0])}" if emcy else ""
        return Fault(FaultKind.DRIVE_FAULT, axis.name, k, f"axis {axis.name}: drive fault ({power.value}, "
                     f"statusword 0x{axis.statusword:04X}{code})")
    return Fault(FaultKind.DRIVE_STOPPED, axis.name, k,
                 f"axis {axis.name}: the drive left Operation Enabled by itself (now {power.value})")


#: how much further out than the innermost point it reached an axis taken up outside its soft limits may
#: stand before that is a soft-limit fault (m): a held axis stands within microns, a runaway passes this in ms
OUTSIDE_SLACK_M = 50e-6


def _further_out(ch: Channel, pos: float, limits: tuple[float, float], taken: bool) -> bool:
    """Whether ``pos``, outside the soft limits, is a soft-limit fault. An axis that leaves its limits while
    checked is one at once. One taken up outside them (an enable, a move started there: ``taken``) is held
    where it stands and may go back in, as a machine's soft limits allow: a fault only once it is
    :data:`OUTSIDE_SLACK_M` further out than the innermost point it has reached (``ch.outside_mark``)."""
    mark = pos if taken else ch.outside_mark
    if mark is None:
        return True
    below = pos < limits[0]
    if (pos < mark - OUTSIDE_SLACK_M) if below else (pos > mark + OUTSIDE_SLACK_M):
        return True
    ch.outside_mark = max(mark, pos) if below else min(mark, pos)  # a ratchet toward the inside
    return False


def _violation(ch: Channel, k: int, dt: float, pos: float, ref: float) -> tuple[StopReason, FaultKind, str] | None:
    lim = ch.limits
    last, ch.last_position = ch.last_position, pos
    if last is not None and k and abs(pos - last) > lim.max_speed * dt:
        return StopReason.FAULT, FaultKind.IMPLAUSIBLE_POSITION, (
            f"axis {ch.axis.name}: position jumped {(pos - last) * 1e3:+.3f} mm in one cycle at t={k * dt:.3f} s "
            f"(faster than max_speed {lim.max_speed:g} m/s: encoder?)")
    if last is None:
        ch.jump = JumpState()  # anew with last_position (a run, a move of the resident loop)
    jump = position_jump(ch.jump, pos, lim.max_jump, ch.axis.lost_cycles > 0)
    if jump is not None:
        return StopReason.FAULT, FaultKind.IMPLAUSIBLE_POSITION, (
            f"axis {ch.axis.name}: position jumped {jump * 1e3:+.3f} mm beyond its motion at t={k * dt:.3f} s "
            f"(a second difference beyond limits.max_jump_m {lim.max_jump * 1e3:g} mm: an encoder glitch, or a "
            "violent oscillation)")
    if lim.position is not None and not (lim.position[0] <= pos <= lim.position[1]):  # inline: every cycle
        if _further_out(ch, pos, lim.position, taken=last is None):
            return StopReason.SOFT_LIMIT, FaultKind.SOFT_LIMIT, (
                f"axis {ch.axis.name}: {soft_limit_text(pos, lim.position, f' at t={k * dt:.3f} s')}")
    elif ch.outside_mark is not None:
        ch.outside_mark = None  # back inside: the soft limits hold again as they always do
    err = ref - pos
    if err > lim.following_error or err < -lim.following_error:
        since = ch.following_since
        if since is None:
            since = ch.following_since = k
        if k == 0:
            return StopReason.FOLLOWING_ERROR, FaultKind.FOLLOWING_ERROR, (
                f"axis {ch.axis.name}: at {pos:.6f} m but the profile starts at {ref:.6f} m; nothing moved"
            )
        if (k - since) * dt >= lim.following_time:
            return StopReason.FOLLOWING_ERROR, FaultKind.FOLLOWING_ERROR, (
                f"axis {ch.axis.name}: following error {err * 1e6:.1f} um beyond the "
                f"{lim.following_error * 1e6:.0f} um window at t={k * dt:.3f} s"
            )
    else:
        ch.following_since = None
    return None

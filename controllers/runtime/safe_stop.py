"""Stopping every axis of a run, verified by the drives' own reports, escalated when they do not confirm.

What the master believes about a drive is not evidence: every statement about an axis's end state
(the CLI's line, the exit code, the trace's ``safe_state``) comes from a statusword the drive sent
after the stop — by TPDO in that cycle, or by SDO when the TPDOs are gone
(:attr:`CanopenAxis.state_fresh`). A drive that does not report a safe state (Switch On Disabled,
Quick Stop Active, Fault: torque off in all three) within :data:`CONFIRM_CYCLES` cycles of a step is
taken to the next one:

1. quick stop by RPDO, in the very cycle of the detection;
2. quick stop by SDO (0x6040): reaches a drive outside NMT Operational, which ignores RPDOs;
3. NMT Stop, if the drive's 0x6007 says losing the connection stops it (1 fault, 2 disable
   voltage, 3 quick stop; sent too when 0x6007 cannot be read); the state is then read by SDO,
   after NMT Pre-operational if a Stopped drive does not answer;
4. the last resort the configuration names (``last_resort``, default NMT Reset Node).

Where the master already knows that RPDOs do not reach or do not hold — a second RPDO producer
overrides them (steps 2 and 3 together, at once: only a drive that no longer takes PDOs stops
listening to the rogue), a foreign NMT command took the drive out of Operational (step 2 at once) —
it does not wait for step 1. An axis that still does not confirm is reported, on one line and in
the trace, as "may still be powered", with what was tried.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from drivectl.controllers.runtime.cycle import BRAKE_WAIT_S, SAFE_STATES, Channel, Fault
from drivectl.driver.axis import Axis, AxisError, FaultKind, Feedback
from drivectl.driver.cia402 import PowerState, error_text

#: cycles a drive has to report a safe state after each step before the next one (a CiA 402 drive in
#: cyclic synchronous torque takes a quick stop at the next SYNC)
CONFIRM_CYCLES = 2
#: cycles the disable that follows a confirmed quick stop may take (at least BRAKE_WAIT_S: a holding
#: brake engages before the power stage switches off)
SETTLE_CYCLES = 20

_STILL_CHANGING = (PowerState.OPERATION_ENABLED, PowerState.QUICK_STOP_ACTIVE, PowerState.FAULT_REACTION_ACTIVE)

#: the words of ``safe_state`` for an axis whose stop was not confirmed
MAY_BE_POWERED = "may still be powered"


@dataclass
class AxisStop:
    """How one axis's stop went."""

    name: str
    confirmed_after: int | None = None  # cycles from the detection to a confirmed safe state
    tried: list[str] = field(default_factory=list)
    source: str = ""  # "TPDO", "SDO", "" (the master's model: SimAxis has no transport)

    def safe_state(self, axis: Axis) -> str:
        """The trace's ``safe_state`` value: the confirmed state, or the honest "may still be powered"."""
        steps = f" after {', '.join(self.tried)}" if len(self.tried) > 1 else ""
        if self.confirmed_after is not None:
            by = f" (reported by {self.source}{steps})" if self.source and steps else ""
            return f"{axis.power.value}{by}"
        # a report names its transport (TPDO, SDO); an axis without one (SimAxis) confirmed nothing to report
        last = (f"it last reported {axis.power.value} by {axis.state_source}"
                if axis.state_fresh and axis.state_source else "no confirmed report from the drive")
        return f"{MAY_BE_POWERED}: {last}; tried {', '.join(self.tried)}"


def confirmed(axis: Axis) -> bool:
    """The drive itself reported a safe state (SimAxis: its model is the plant, always current)."""
    return axis.power in SAFE_STATES and axis.state_fresh


def stop_axes(axes: Sequence[Axis], fault_kind: str | None = None, fault_axis: str | None = None,
              on_cycle: Callable[[dict[str, Feedback | None]], None] | None = None) -> dict[str, AxisStop]:
    """Quick stop every axis now and verify; escalate per axis until each confirms or nothing is left.
    Then disable the confirmed ones (a drive in Fault stays there: its reset is the operator's).
    ``on_cycle``: given every axis's sample (None: none came) after each of the stop's cycles."""
    stops = {ax.name: AxisStop(ax.name) for ax in axes}
    for ax in axes:
        _attempt(stops[ax.name], "quick stop by RPDO", ax.quick_stop)
        quietly(ax.write, 0.0)
    cycle = 0

    def done(ax: Axis) -> bool:
        return stops[ax.name].confirmed_after is not None

    def mark(cycles: int) -> None:
        for ax in axes:
            st = stops[ax.name]
            if st.confirmed_after is None and confirmed(ax):
                st.confirmed_after = cycles
                st.source = ax.state_source

    mark(0)
    # what the master knows does not reach the drive by RPDO: escalate these at once
    for ax in axes:
        kind = ax.foreign_kind
        if kind is None and ax.name == fault_axis and fault_kind in (FaultKind.ROGUE_RPDO.value,
                                                                     FaultKind.FOREIGN_NMT.value):
            kind = FaultKind(fault_kind)
        if done(ax) or kind not in (FaultKind.ROGUE_RPDO, FaultKind.FOREIGN_NMT):
            continue
        _sdo_quick_stop(stops[ax.name], ax)
        if kind is FaultKind.ROGUE_RPDO:
            _nmt_stop(stops[ax.name], ax, always=True)
    steps: list[Callable[[AxisStop, Axis], None]] = [_sdo_quick_stop, _nmt_stop, _last_resort]
    while True:
        for _ in range(CONFIRM_CYCLES):
            if all(done(ax) for ax in axes):
                break
            cycle += 1
            if not _stop_cycle(axes, on_cycle):
                break  # nothing answers at all: the next step may still get through (or fail and say so)
            mark(cycle)
        pending = [ax for ax in axes if not done(ax)]
        if not pending or not steps:
            break
        step = steps.pop(0)
        for ax in pending:
            step(stops[ax.name], ax)
        mark(cycle)
    for ax in axes:
        if done(ax) and ax.power is not PowerState.FAULT:
            quietly(ax.disable)
    for _ in range(max(SETTLE_CYCLES, *(math.ceil(BRAKE_WAIT_S / ax.dt) for ax in axes))):
        if all(ax.power not in _STILL_CHANGING for ax in axes if done(ax)):
            break
        if not _stop_cycle(axes, on_cycle):
            break
    return stops


def _sdo_quick_stop(st: AxisStop, ax: Axis) -> None:
    if "quick stop by SDO" not in st.tried:
        _attempt(st, "quick stop by SDO", ax.sdo_quick_stop)


def _nmt_stop(st: AxisStop, ax: Axis, always: bool = False) -> None:
    if any(t.startswith("NMT Stop") for t in st.tried):
        return
    try:
        option = ax.abort_connection_option() if not always else quietly(ax.abort_connection_option)
    except NotImplementedError:
        return  # no NMT on this transport
    if not always and option not in (1, 2, 3, None):
        st.tried.append(f"no NMT Stop (0x6007 = {option}: the drive would not stop on it)")
        return
    what = "NMT Stop" + (f" (0x6007 = {option})" if option is not None else " (0x6007 unreadable)")
    if _attempt(st, what, ax.nmt_stop):
        quietly(ax.refresh_state_outside_operational)


def _last_resort(st: AxisStop, ax: Axis) -> None:
    action = ax.last_resort_action
    if action is None:  # the transport has no last resort
        return
    if action == "none":
        st.tried.append("no last resort configured (last_resort = \"none\")")
        return
    _attempt(st, {"nmt-reset": "NMT Reset Node"}.get(action, action), ax.last_resort)


def _attempt(st: AxisStop, what: str, fn: Callable[[], object]) -> bool:
    try:
        fn()
    except NotImplementedError:
        return False  # the transport has no such step (driver/axis.py): nothing was tried
    except Exception as exc:  # noqa: BLE001 - stopping goes on whatever one call raises
        reason = str(exc).split(": ")[-1] or type(exc).__name__
        st.tried.append(f"{what} (failed: {reason})")
        return False
    st.tried.append(what)
    return True


def _stop_cycle(axes: Sequence[Axis], on_cycle: Callable[[dict[str, Feedback | None]], None] | None = None) -> bool:
    """One zero-effort cycle of every axis during a stop, the statusword asked by SDO where no TPDO
    brought it; False when no axis could be cycled or asked."""
    alive = False
    samples: dict[str, Feedback | None] = {}
    for axis in axes:
        samples[axis.name] = None
        try:
            samples[axis.name] = axis.read()
            alive = True
        except AxisError:
            pass  # no sample (TPDOs gone): asked by SDO below
        except Exception:  # noqa: BLE001 - a dead transport: the others must still be stopped
            pass
        if not axis.state_fresh:
            if quietly(axis.refresh_state) is not None:
                alive = True
        quietly(axis.write, 0.0)
    if on_cycle is not None:
        quietly(on_cycle, samples)
    return alive


def drive_error_code(axis: Axis) -> int | None:
    """The drive's 0x603F: read where the axis can (by SDO on a bus), else its last EMCY's; None: unknown."""
    code = quietly(axis.read_error_code)
    if code is None and axis.last_emcy:
        code = axis.last_emcy[0]
    return code  # type: ignore[return-value]


def quietly(fn: Callable[..., object], *args: object) -> object:
    """``fn(*args)``, or None where it raised: a stop goes on whatever one call raises."""
    try:
        return fn(*args)
    except Exception:  # noqa: BLE001 - stopping goes on whatever one call raises
        return None


def stop_channels(channels: Sequence[Channel], fault: Fault | None = None,
                  on_cycle: Callable[[dict[str, Feedback | None]], None] | None = None) -> None:
    """Quick stop now (the command goes out in this very cycle), verified by what each drive reports
    after it and escalated where it does not confirm (:func:`stop_axes`); the cycles to a confirmed safe
    state and the state (or "may still be powered" and what was tried) go into ``fault``."""
    axes = [ch.axis for ch in channels]
    stops = stop_axes(axes, fault.kind if fault else None, fault.axis if fault else None, on_cycle)
    if fault is not None:
        for ax in axes:
            st = stops[ax.name]
            fault.safe_after[ax.name] = st.confirmed_after
            fault.safe_state[ax.name] = st.safe_state(ax)
        faulted = next((ax for ax in axes if ax.name == fault.axis), None)
        if faulted is not None:
            fault.statusword = faulted.statusword
            code = drive_error_code(faulted)
            fault.error_code = code
            if code and fault.kind is FaultKind.DRIVE_STOPPED:  # why the drive stopped, in its own words
                fault.detail += f" (its 0x603F: 0x{code:04X}: {error_text(code)})"


def end_state_line(safe_state: dict[str, str], safe_after: dict[str, int | None]) -> str:
    """The CLI's words for how the axes ended, from what the drives reported (never a fixed sentence)."""
    parts = []
    for name, state in safe_state.items():
        after = safe_after.get(name)
        if after is not None:
            parts.append(f"{name} {state} after {after} cycle(s)")
        else:
            parts.append(f"{name} {state.replace(MAY_BE_POWERED, MAY_BE_POWERED.upper(), 1)}")
    return ", ".join(parts)


def all_confirmed(safe_after: dict[str, int | None]) -> bool:
    return all(v is not None for v in safe_after.values())

"""The drive section of ``drivectl doctor --axis NAME``: what the drive is and what drivectl does with it.

On a connected :class:`~drivectl.driver.canopen_axis.CanopenAxis` (booted and configured): the identity
(0x1018, 0x1000) and 0x6502 as the device reports them; the mode, the PDO mapping and the watchdogs it
uses (its heartbeat, the master heartbeat it consumes, the RPDO deadline, 0x6007); what it lacks and
what drivectl does instead; then an enable attempt at zero torque (halt set until enabled, disabled at
once after, each state confirmed by the drive): either it enabled, or the reason it did not
(driver/enable_check.py) instead of "transition timed out".
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from drivectl.driver import cia402
from drivectl.driver.axis import AxisError
from drivectl.driver.capabilities import MODE_NAMES
from drivectl.driver.cia402 import PowerState

if TYPE_CHECKING:
    from drivectl.driver.canopen_axis import CanopenAxis

#: cycles an enable (or the disable after it) may take (CiA 402: two or three; controllers/runtime/servo.py)
ENABLE_CYCLES = 20


def _read(axis: CanopenAxis, index: int, sub: int | None = None) -> int | None:
    if index not in axis.od:
        return None
    try:
        return axis._sdo(index, sub)
    except (AxisError, KeyError):
        return None


def drive_lines(axis: CanopenAxis) -> list[tuple[str, str]]:
    """(what, value) of the drive section, before the enable attempt."""
    out: list[tuple[str, str]] = []
    ident = [_read(axis, cia402.IDENTITY, s) for s in (1, 2, 3, 4)]
    names = ("vendor", "product", "revision", "serial")
    answered = ", ".join(f"{n} 0x{v:08X}" for n, v in zip(names, ident, strict=True) if v is not None)
    out.append(("identity answered", answered or "0x1018 not readable"))
    out.append(("identity expected", axis.identity.lines()
                + (f" ({axis.identity.source})" if getattr(axis.identity, "source", None) else "")))
    dtype = _read(axis, cia402.DEVICE_TYPE)
    if dtype is not None:
        out.append(("device type", f"0x{dtype:08X} (profile {dtype & 0xFFFF})"))
    modes = _read(axis, cia402.SUPPORTED_DRIVE_MODES)
    out.append(("0x6502", f"0x{modes:08X} (read from the device)" if modes is not None else
                f"not readable; {axis.capabilities.modes_source}: 0x{axis.capabilities.modes:08X}"))
    mode = axis.mode if axis.mode is not None else 0
    out.append(("mode", MODE_NAMES.get(mode, str(mode))))
    for line in axis.pdo_plan.lines():
        out.append(("mapping", line))
    hb = _read(axis, cia402.PRODUCER_HEARTBEAT_TIME)
    out.append(("heartbeat", f"the drive sends one every {hb} ms; the master allows 3 periods" if hb else
                "the drive sends none (0x1017 absent or 0): the master watches its TPDOs only"))
    consumer = _read(axis, cia402.CONSUMER_HEARTBEAT_TIME, 1)
    if consumer:
        out.append(("master watched", f"0x1016:1: node {(consumer >> 16) & 0x7F} within {consumer & 0xFFFF} ms"))
    for p in axis.pdo_plan.rx:
        if p.slot.event_timer and p.trans_type <= 240:
            deadline = _read(axis, p.slot.comm, 5)
            out.append(("RPDO deadline", f"0x{p.slot.comm:04X}:05 = {deadline} ms on {p.slot.name}"))
    option = _read(axis, cia402.ABORT_CONNECTION_OPTION)
    if option is not None:
        said = {0: "no action", 1: "fault", 2: "disable voltage", 3: "quick stop"}.get(option, "manufacturer's")
        out.append(("on a lost master", f"0x6007 = {option} ({said})"))
    for note in axis.capabilities.fallback_lines():
        out.append(("fallback", note))
    return out


def enable_attempt(axis: CanopenAxis) -> tuple[bool, str]:
    """Enable at zero torque, then disable; (enabled?, what the drive said). The axis ends disabled, confirmed by
    the drive, or the text says it may still be powered."""
    axis.read()
    axis.write(0.0)
    if axis.power in (PowerState.FAULT, PowerState.FAULT_REACTION_ACTIVE):
        return False, axis.enable_blocker()  # drivectl never resets a fault on its own
    axis.enable()
    for _ in range(ENABLE_CYCLES):
        if axis.power is PowerState.OPERATION_ENABLED:
            break
        axis.read()
        axis.write(0.0)
    enabled = axis.power is PowerState.OPERATION_ENABLED
    reason = "" if enabled else axis.enable_blocker()
    axis.disable()
    for _ in range(ENABLE_CYCLES):
        if axis.power in (PowerState.SWITCH_ON_DISABLED, PowerState.FAULT):
            break
        axis.read()
        axis.write(0.0)
    after = axis.refresh_state()
    if after not in (PowerState.SWITCH_ON_DISABLED, PowerState.FAULT, PowerState.READY_TO_SWITCH_ON,
                     PowerState.NOT_READY_TO_SWITCH_ON):
        return enabled, (reason + "; " if reason else "") + f"after the attempt the drive reports {after.value}: it " \
            "may still be powered"
    if enabled:
        return True, f"enabled at zero torque, then disabled (the drive reports {after.value})"
    return False, reason


def standing_blocker(axis: CanopenAxis) -> str:
    """What would stop the drive enabling, from what it reports now, without enabling it (a fault and its
    code, no DC link voltage); "none seen" when its state allows an enable (STO or a mode refused show only
    in an attempt: :func:`enable_attempt`)."""
    state = axis.refresh_state()
    if state in (PowerState.FAULT, PowerState.FAULT_REACTION_ACTIVE):
        return axis.enable_blocker()
    if state in (PowerState.READY_TO_SWITCH_ON, PowerState.SWITCHED_ON) and not axis.statusword & 0x0010:
        return axis.enable_blocker()
    return f"none seen ({state.value}, statusword 0x{axis.statusword:04X}; not tried: nothing is enabled here)"

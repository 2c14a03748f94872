"""What a drive offers drivectl's torque loop, read from its EDS (and at boot from the device itself).

To close a torque loop drivectl needs (docs/drives.md): the controlword 0x6040 and statusword 0x6041 and
modes of operation 0x6060; a torque setpoint 0x6071 it can map into an RPDO; the position 0x6064 it can
map into a TPDO; a torque mode: cyclic synchronous torque (10) preferred, profile torque (4) with
synchronous RPDOs where cst is absent. A drive without one of these is refused before anything moves, in
one line naming the file and the object or mode (:class:`DriveRefused`).

Everything else is optional: :data:`FALLBACKS` says what drivectl does instead, and the boot says it.
0x6502 (supported modes) is read from the device at boot; an EDS often gives it no value, and then the
modes its objects allow stand in for it offline (:func:`supported_modes`).
"""

from __future__ import annotations

from dataclasses import dataclass

from canopen import objectdictionary as odt

from drivectl.driver import cia402
from drivectl.driver.axis import AxisConfigError

#: the essentials, in the order they are checked, with what the refusal says
ESSENTIALS: tuple[tuple[int, str], ...] = (
    (cia402.CONTROLWORD, "controlword 0x6040"),
    (cia402.STATUSWORD, "statusword 0x6041"),
    (cia402.MODES_OF_OPERATION, "modes of operation 0x6060"),
    (cia402.TARGET_TORQUE, "torque setpoint 0x6071: drivectl closes the loop in torque"),
    (cia402.POSITION_ACTUAL, "position actual value 0x6064: drivectl closes the loop on the drive's position"),
)

#: optional objects: what drivectl does when the drive lacks one (said at boot, in docs/drives.md)
FALLBACKS: tuple[tuple[int, str], ...] = (
    (cia402.RATED_TORQUE, "rated_effort comes from the configuration"),
    (cia402.COB_ID_SYNC, "the SYNC COB-ID is not written (the drive's own, 0x80, is used)"),
    (cia402.COMM_CYCLE_PERIOD, "the SYNC period is not written"),
    (cia402.MAX_TORQUE, "drivectl's own clip only"),
    (cia402.ABORT_CONNECTION_OPTION, "the drive's reaction to a lost master is unknown"),
    (cia402.CONSUMER_HEARTBEAT_TIME, "the RPDO deadline (0x14xx:05), where the drive has one, watches the master "
                                     "instead of the heartbeat"),
    (cia402.ERROR_CODE, "the EMCY code tells the fault"),
    (cia402.FOLLOWING_ERROR_WINDOW, "drivectl's own following-error check only"),
    (cia402.FOLLOWING_ERROR_TIMEOUT, "drivectl's own following-error check only"),
    (cia402.VELOCITY_ACTUAL, "velocity derived on the host"),
    (cia402.TORQUE_ACTUAL, "no torque actual in traces"),
    (cia402.QUICK_STOP_OPTION, "the drive's quick-stop reaction is its own default"),
    (cia402.SOFTWARE_POSITION_LIMIT, "drivectl's own position limits only"),
)

CST = int(cia402.Mode.CYCLIC_SYNC_TORQUE)
TQ = int(cia402.Mode.PROFILE_TORQUE)
#: mode -> what it is called in a message
MODE_NAMES = {CST: "cyclic synchronous torque (10)", TQ: "profile torque (4)"}
#: the modes a set of objects allows, where the EDS gives 0x6502 no value (CiA 402: the mode's setpoint)
_MODES_BY_OBJECT = ((0x6071, (TQ, CST)), (0x607A, (1, 8)), (0x60FF, (3, 9)), (0x6098, (6,)), (0x6042, (2,)))


class DriveRefused(AxisConfigError):
    """The drive lacks an essential: one line naming the file (or node) and the object or mode."""


def _has(od: odt.ObjectDictionary, index: int) -> bool:
    return index in od


def _var(od: odt.ObjectDictionary, index: int) -> odt.ODVariable | None:
    if index not in od:
        return None
    obj = od[index]
    return obj if isinstance(obj, odt.ODVariable) else None


def object_value(var: odt.ODVariable | None) -> int | None:
    """What the EDS (or DCF) says the object holds: ParameterValue first, then DefaultValue."""
    if var is None:
        return None
    for value in (var.value, var.default):
        if isinstance(value, int):
            return value
    return None


def supported_modes(od: odt.ObjectDictionary) -> tuple[int, str]:
    """(0x6502 bits, where they come from): the EDS's value, else the modes its objects allow."""
    value = object_value(_var(od, cia402.SUPPORTED_DRIVE_MODES))
    if value is not None:
        return value, "0x6502 in the EDS"
    bits = 0
    for index, modes in _MODES_BY_OBJECT:
        if index in od:
            for m in modes:
                bits |= 1 << (m - 1)
    return bits, "no 0x6502 value in the EDS: the modes its objects allow"


def choose_mode(modes: int) -> int | None:
    """The torque mode drivectl runs: cst where offered, else profile torque, else None."""
    if modes & (1 << (CST - 1)):
        return CST
    if modes & (1 << (TQ - 1)):
        return TQ
    return None


@dataclass(frozen=True)
class Capabilities:
    mode: int  # the torque mode drivectl commands (10 or 4)
    modes: int  # 0x6502 as used
    modes_source: str
    missing: tuple[int, ...]  # optional objects the drive lacks (FALLBACKS order)
    rated_effort_from_drive: bool  # 0x6076 present: the drive holds the rated effort

    def fallback_lines(self) -> list[str]:
        said = dict(FALLBACKS)
        return [f"0x{i:04X} absent: {said[i]}" for i in self.missing]


def refuse_mode(where: str, modes: int, source: str) -> DriveRefused:
    return DriveRefused(f"{where}: drive offers no torque mode (0x6502 = 0x{modes:08X}, {source}: neither cyclic "
                        "synchronous torque 10 nor profile torque 4): drivectl closes the loop in torque")


def assess(od: odt.ObjectDictionary, where: str, modes: int | None = None) -> Capabilities:
    """What this drive offers, or :class:`DriveRefused` naming the first essential it lacks. ``modes``: 0x6502
    as the device reported it (None: from the EDS)."""
    for index, what in ESSENTIALS:
        if index not in od:
            raise DriveRefused(f"{where}: drive has no {what}")
    for index, rx, what in ((cia402.TARGET_TORQUE, True, "torque setpoint 0x6071 cannot be mapped into an RPDO"),
                            (cia402.CONTROLWORD, True, "controlword 0x6040 cannot be mapped into an RPDO"),
                            (cia402.POSITION_ACTUAL, False, "position 0x6064 cannot be mapped into a TPDO"),
                            (cia402.STATUSWORD, False, "statusword 0x6041 cannot be mapped into a TPDO")):
        var = _var(od, index)
        if var is None or not var.pdo_mappable or not (var.writable if rx else var.readable):
            raise DriveRefused(f"{where}: {what}: drivectl closes the loop by PDO")
    if modes is None:
        modes, source = supported_modes(od)
    else:
        source = "0x6502 read from the device"
    mode = choose_mode(modes)
    if mode is None:
        raise refuse_mode(where, modes, source)
    missing = tuple(i for i, _ in FALLBACKS if not _has(od, i))
    return Capabilities(mode, modes, source, missing, _has(od, cia402.RATED_TORQUE))

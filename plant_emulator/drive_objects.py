"""The emulated drive's object dictionary hooks: the drive's own rules on SDO writes (beyond the EDS limits
sdo_server.py checks), what a stored value changes, and the live objects it reads (a mixin of
node402.EmulatedDrive)."""

from __future__ import annotations

import canopen
from canopen import objectdictionary as odt

from drivectl.driver import cia402
from drivectl.driver.cia301 import HEARTBEAT_BASE, SDO_ABORT_VALUE_RANGE
from drivectl.driver.emulator_clock import CLOCK_NAMES, CLOCK_OWN, CLOCK_SUB, EMULATOR_MARK, EMULATOR_OBJECT, MARK_SUB
from drivectl.driver.enable_check import VOLTAGE_ENABLED
from drivectl.driver.units import EffortScale
from drivectl.plant_emulator.drive_constants import DIGITAL_INPUTS, FAULTED
from drivectl.plant_emulator.faults import SDO_ABORT_GENERAL

#: the modes in which the emulated drive puts the setpoint on the plant
TORQUE_MODES = (int(cia402.Mode.CYCLIC_SYNC_TORQUE), int(cia402.Mode.PROFILE_TORQUE))


def add_emulator_object(od: canopen.ObjectDictionary) -> None:
    """0x5FFF, the object by which a master tells drivectl's emulated drive its clock (driver/emulator_clock.py),
    added to whatever EDS the drive impersonates (unless that EDS has an object there of its own)."""
    if EMULATOR_OBJECT in od:
        return
    rec = odt.ODRecord("drivectl emulated drive", EMULATOR_OBJECT)
    for sub, name, dtype, access, default, high in (
            (0, "Highest sub-index supported", odt.UNSIGNED8, "const", CLOCK_SUB, None),
            (MARK_SUB, "drivectl emulator", odt.UNSIGNED32, "ro", EMULATOR_MARK, None),
            (CLOCK_SUB, "Master clock", odt.UNSIGNED8, "rw", CLOCK_OWN, max(CLOCK_NAMES))):
        var = odt.ODVariable(name, EMULATOR_OBJECT, sub)
        var.data_type, var.access_type, var.default, var.min, var.max = dtype, access, default, None, high
        if high is not None:
            var.min = 0
        rec.add_member(var)
    od.add_object(rec)


class DriveObjects:
    def _on_write(self, index: int, subindex: int, od, data: bytes) -> None:
        """Called before canopen stores ``data``: the drive's own rules (beyond the EDS limits that the
        SDO server checked); an abort leaves the value unchanged."""
        if self.faults is not None and self.faults.sdo_abort_index == index:
            raise canopen.SdoAbortedError(SDO_ABORT_GENERAL)
        if 0x1400 <= index <= 0x1BFF:
            self.rules.check(index, subindex, data)
        elif index == cia402.COB_ID_SYNC:
            value = od.decode_raw(data)  # (as the EDS types it: an impersonated drive's types are its own)
            if value & 0x60000000 or value & 0x1FFFF800:  # bit 30: this drive cannot produce SYNC; 29: 29-bit
                raise canopen.SdoAbortedError(SDO_ABORT_VALUE_RANGE)
        elif index == cia402.COMM_CYCLE_PERIOD:
            value = od.decode_raw(data)
            # the drive's control cycle is its plant's: it can follow a SYNC of that period (or none)
            if value not in (0, round(self.cycle_ms * 1000)):
                raise canopen.SdoAbortedError(SDO_ABORT_VALUE_RANGE)
        elif index == cia402.MODES_OF_OPERATION:
            if not self._mode_supported(od.decode_raw(data)):
                raise canopen.SdoAbortedError(SDO_ABORT_VALUE_RANGE)
        elif index == cia402.RATED_TORQUE and od.decode_raw(data) == 0:
            raise canopen.SdoAbortedError(SDO_ABORT_VALUE_RANGE)

    def _after_write(self, index: int, sub: int) -> None:
        """A value is stored: the drive takes it at once."""
        value = self._value(index, sub)
        if 0x1400 <= index <= 0x1BFF:
            self._load_mapping()  # a new mapping is effective the moment it is made valid
            if cia402.RPDO_COMM <= index < cia402.RPDO_MAP and sub == 5:
                self._rpdo_timeout_ms, self._deadline_comm = value, index
                self._ms_since_rpdo = None  # CiA 301: monitoring starts at the next RPDO
        elif index == cia402.CONTROLWORD:
            self.controlword = value
        elif index == cia402.TARGET_TORQUE:
            self.setpoint = value
        elif index == cia402.MODES_OF_OPERATION:
            self._set_mode(value)
        elif index == cia402.MAX_TORQUE:
            self.max_torque = value
        elif index == cia402.RATED_TORQUE:
            self.scale = EffortScale(value / 1000.0)  # 0x6076 holds the rated effort in thousandths
        elif index == cia402.QUICK_STOP_OPTION:
            self.drive.quick_stop_option = value
        elif index == cia402.CONSUMER_HEARTBEAT_TIME and sub == 1:
            if self._consumer is not None:
                self.network.unsubscribe(HEARTBEAT_BASE + self._consumer[0], self._on_master_heartbeat)
            node, ms = (value >> 16) & 0x7F, value & 0xFFFF
            self._consumer, self._ms_since_master, self.master_lost = None, None, False
            if node and ms:
                self._consumer = (node, ms)
                self.network.subscribe(HEARTBEAT_BASE + node, self._on_master_heartbeat)
        elif index == cia402.ABORT_CONNECTION_OPTION:
            self._abort_option = value
        elif index == cia402.PRODUCER_HEARTBEAT_TIME:
            self._heartbeat_ms = value
            self._heartbeat_cycles = 0  # restart the count with the new period
        elif index == cia402.COB_ID_SYNC:
            self._set_sync_cob(value & 0x7FF)
        elif index == EMULATOR_OBJECT and sub == CLOCK_SUB:
            self._set_master_clock(value)

    def _mode_supported(self, mode: int) -> bool:
        if mode == 0:
            return True  # no mode: allowed, the drive then gives no torque
        return 0 < mode <= 32 and bool(self.supported_modes & (1 << (mode - 1)))

    def _set_mode(self, mode: int) -> None:
        self.mode = mode
        # the plant is driven in torque: cyclic synchronous torque, or profile torque (the setpoint taken at the
        # SYNC as in cst, no torque slope 0x6087); any other mode (0 included) gives no torque
        self.drive.mode_ok = mode in TORQUE_MODES

    @property
    def error_register(self) -> int:
        """0x1001: bit 4 communication error, bit 0 whenever any error is active (CiA 301)."""
        reg = 0x10 if self._errors else 0
        if self.drive.power in FAULTED or reg:
            reg |= 0x01
        return reg

    def _on_read(self, index: int, subindex: int, od):
        d = self.drive
        if index == cia402.STATUSWORD:
            return self.statusword()
        if index == cia402.POSITION_ACTUAL:
            return self.encoder.to_counts(self.reported_position)
        if index == cia402.VELOCITY_ACTUAL:
            return self.encoder.to_counts(d.velocity)
        if index == cia402.TORQUE_ACTUAL:
            return self.scale.to_permille(d.applied)
        if index == cia402.ERROR_CODE:
            return d.error_code
        if index == cia402.MODES_OF_OPERATION_DISPLAY:
            return self.mode
        if index == cia402.ERROR_REGISTER:
            return self.error_register
        if index == DIGITAL_INPUTS:  # switches (session homing: controllers/runtime/homing.py)
            return d.digital_inputs()
        return None

    def statusword(self) -> int:
        sw = cia402.encode_statusword(self.drive.power, follows=self.drive.following,
                                      internal_limit=self.internal_limit)
        return sw if self.drive.voltage else sw & ~VOLTAGE_ENABLED

    @property
    def reported_position(self) -> float:
        """What the encoder says (the plant's position, unless an injected glitch offsets it)."""
        return self.drive.position + (self.faults.position_offset if self.faults is not None else 0.0)

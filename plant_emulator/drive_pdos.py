"""The emulated drive's PDO engine: the mapping the object dictionary defines now, RPDOs received (length
checked, values stored), remote frames answered (a mixin of node402.EmulatedDrive; the rules are
pdo_rules.py)."""

from __future__ import annotations

from drivectl.driver import cia402
from drivectl.driver.cia301 import NMT_OPERATIONAL, NmtState
from drivectl.plant_emulator.drive_constants import (
    DIGITAL_INPUTS,
    RPDO_LONG_ERROR,
    RPDO_SHORT_ERROR,
    RPDO_TIMEOUT_ERROR,
)
from drivectl.plant_emulator.pdo_rules import Rpdo
from drivectl.plant_emulator.remote import subscribe_remote, unsubscribe_remote

_CONTROLWORD, _TARGET_TORQUE, _MODES_OF_OPERATION = cia402.CONTROLWORD, cia402.TARGET_TORQUE, cia402.MODES_OF_OPERATION


class DrivePdos:
    _rpdos: dict[int, Rpdo]

    def _load_mapping(self) -> None:
        """The PDOs as the object dictionary defines them now."""
        for cob in self._rpdos:
            self.network.unsubscribe(cob, self._on_rpdo)
            unsubscribe_remote(self.network, cob, self._on_remote)
        for tp in self._tpdos:
            unsubscribe_remote(self.network, tp.cob, self._on_remote)
        self._rpdos = {rp.cob: rp for rp in self.rules.rpdos()}
        for cob in self._rpdos:
            self.network.subscribe(cob, self._on_rpdo)
            subscribe_remote(self.network, cob, self._on_remote)
        self._tpdos = self.rules.tpdos(self._getter)
        for tp in self._tpdos:
            subscribe_remote(self.network, tp.cob, self._on_remote)

    def _getter(self, index: int, sub: int):
        """How a TPDO reads one mapped object each time it is sent."""
        d = self.drive
        live = {
            cia402.STATUSWORD: self.statusword,
            cia402.POSITION_ACTUAL: lambda: self.encoder.to_counts(self.reported_position),
            cia402.VELOCITY_ACTUAL: lambda: self.encoder.to_counts(d.velocity),
            cia402.TORQUE_ACTUAL: lambda: self.scale.to_permille(d.applied),
            cia402.ERROR_CODE: lambda: d.error_code,
            cia402.MODES_OF_OPERATION_DISPLAY: lambda: self.mode,
            cia402.ERROR_REGISTER: lambda: self.error_register,
            DIGITAL_INPUTS: d.digital_inputs,
        }
        if index in live:
            return live[index]
        return lambda: self._value(index, sub)

    def _on_rpdo(self, can_id: int, data: bytes, timestamp: float) -> None:
        if self.nmt is not NMT_OPERATIONAL:
            return
        rp = self._rpdos.get(can_id)
        if rp is None:
            return
        size = rp.layout.codec.size
        errors = self._errors  # the live set: an error to clear only when one is active (not per cycle)
        if len(data) < size:
            self.frames.reject("short-rpdo", can_id, data, f"RPDO of {len(data)} bytes, mapping needs {size}")
            if RPDO_SHORT_ERROR not in errors:
                errors.add(RPDO_SHORT_ERROR)
                self._emcy(RPDO_SHORT_ERROR)
            return  # not processed: for the deadline it is a lost frame
        if errors:
            self._clear_error(RPDO_SHORT_ERROR)
        if len(data) > size:
            self.frames.reject("long-rpdo", can_id, data, f"RPDO of {len(data)} bytes, mapping has {size}: "
                               "the mapped bytes used")
            if RPDO_LONG_ERROR not in errors:
                errors.add(RPDO_LONG_ERROR)
                self._emcy(RPDO_LONG_ERROR)
        elif errors:
            self._clear_error(RPDO_LONG_ERROR)
        store = self.node.data_store
        frame = bytes(data)
        values = rp.layout.codec.unpack_from(frame)
        for (index, sub, offset, width), value in zip(rp.slots, values, strict=True):
            if index < 0x1000:
                continue  # a dummy entry: bytes meant for another drive
            if index == _CONTROLWORD:
                self.controlword = value
            elif index == _TARGET_TORQUE:
                self.setpoint = value
            elif index == _MODES_OF_OPERATION:
                if not self._mode_supported(value):
                    self.frames.reject("rpdo-mode", can_id, data, f"mode {value} not supported: mode kept")
                    continue
                self._set_mode(value)
            entries = store.get(index)
            if entries is None:
                entries = store[index] = {}
            entries[sub] = frame[offset:offset + width]
        if rp.comm != self._deadline_comm:
            return  # another RPDO (an event-driven controlword, type 255): the deadline watches the one it was set on
        if self._rpdo_timeout_ms:
            self._ms_since_rpdo = 0.0
            self._syncs_since_rpdo = self._skipped_since_rpdo = 0
        if errors:
            self._clear_error(RPDO_TIMEOUT_ERROR)
        if self.faults is not None and self.faults.held:
            self._send_held()  # a late TPDO: after the master's deadline, with its RPDO

    def _on_remote(self, can_id: int) -> None:
        """A remote frame: answered on a TPDO's COB-ID (unless 0x18xx:1 bit 30 forbids it), counted and
        dropped anywhere else."""
        for tp in self._tpdos:
            if tp.cob == can_id and self.nmt is NmtState.OPERATIONAL:
                if not tp.rtr_allowed:
                    self.frames.reject("remote", can_id, b"", "RTR not allowed on this TPDO (COB-ID bit 30)")
                elif tp.answers_rtr_now:
                    self._send_tpdo(tp)
                else:
                    tp.rtr_pending = True  # synchronous: sampled and sent at the next SYNC
                return
        if any(tp.cob == can_id for tp in self._tpdos):
            return  # a TPDO outside Operational: silent
        self.frames.reject("remote", can_id, b"", "remote frame on a COB-ID that carries data")

"""The emulated drive: a CiA 402 slave on a CAN bus, stepping its plant once per SYNC.

Built on canopen's LocalNode (object dictionary from the EDS, SDO server) and adding what that
toolbox lacks (see ../shared/DESIGN.md, "Known traps"):

* NMT done here: boot-up message (0x700 + id, [00]) at start and after every reset, NMT state
  respected (PDOs only in Operational), heartbeat produced in simulated time (every 0x1017 ms of
  SYNCs, not by a timer thread, so the frame order stays deterministic);
* the PDO mapping read back from the object dictionary whenever the master remaps by SDO;
* RPDO data written into the object dictionary (an SDO upload of 0x6040/0x6071 shows them);
* on each SYNC: the drive (plant_emulator/drive.py, shared with SimAxis) steps the plant one cycle
  with the setpoint latched at the previous SYNC (clipped to the drive's max torque, 0x6072, as a
  real drive does), takes the controlword and setpoint received since, and the TPDOs go out
  (position actual in counts, statusword, velocity and torque actual);
* EMCY on a fault (canopen's EmcyProducer), the master's heartbeat consumed (0x1016) and the RPDO
  deadline monitored (0x1400:05, CiA 301): a lost master is answered per 0x6007 on the drive's own;
* faults injected on cue (plant_emulator/faults.py).

Time is simulated: the plant advances exactly one cycle per SYNC, never by wall clock. When nothing
reaches the drive any more (the master died, the bus is off), :meth:`EmulatedDrive.idle` lets its
own clock run a cycle: the plant moves on and the deadline monitoring counts.
"""

from __future__ import annotations

import struct
import time
from pathlib import Path

import canopen

from drivectl.driver import cia402
from drivectl.driver.cia301 import (
    HEARTBEAT_BASE,
    NMT_COB_ID,
    NMT_TRANSITIONS,
    SDO_ABORT_VALUE_RANGE,
    SYNC_COB_ID,
    NmtCommand,
    NmtState,
)
from drivectl.driver.pdo import PdoLayout
from drivectl.driver.units import DEFAULT_RESOLUTION_M, EffortScale, Encoder
from drivectl.plant_emulator.drive import DriveModel
from drivectl.plant_emulator.faults import SDO_ABORT_GENERAL, FaultInjector
from drivectl.plant_emulator.models import Plant

#: CiA 402 digital inputs (bit 0 negative limit, 1 positive limit, 2 home switch)
DIGITAL_INPUTS = 0x60FD

#: EMCY / 0x603F code of a missed RPDO deadline (CiA 301: RPDO timeout)
RPDO_TIMEOUT_ERROR = 0x8250

EMULATED_DRIVE_EDS = Path(__file__).resolve().parent.parent / "driver" / "eds" / "drivectl-emulated-drive.eds"


class EmulatedDrive:
    """One CiA 402 drive (one node) on ``network``; several may share a network and its SYNC."""

    def __init__(
        self,
        network: canopen.Network,
        node_id: int,
        plant: Plant,
        *,
        rated_effort: float,
        eds: str | Path = EMULATED_DRIVE_EDS,
        resolution: float = DEFAULT_RESOLUTION_M,
        force_noise: float = 0.0,
        seed: int = 0,
        initial_position: float = 0.0,
        faults: FaultInjector | None = None,
        io: object = None,
    ):
        if not 1 <= node_id <= 127:
            raise ValueError(f"emulated drive: node id must be 1..127, got {node_id}")
        self.network = network
        self.node_id = node_id
        self.od = canopen.import_od(str(eds), node_id)
        self.node = canopen.LocalNode(node_id, self.od)
        network.add_node(self.node)
        # canopen's NmtSlave runs heartbeats on a timer thread and stays INITIALISING after a reset:
        # replace it by the simulated-time NMT below
        network.unsubscribe(NMT_COB_ID, self.node.nmt.on_command)
        self.node._write_callbacks.remove(self.node.nmt.on_write)
        network.subscribe(NMT_COB_ID, self._on_nmt)
        self.node.add_write_callback(self._on_write)
        self.node.add_read_callback(self._on_read)

        self.encoder = Encoder(resolution)
        self.scale = EffortScale(rated_effort)
        self.drive = DriveModel(plant, force_noise=force_noise, seed=seed, initial_position=initial_position,
                                quick_stop_option=self._od_default(cia402.QUICK_STOP_OPTION), io=io)
        self.node.data_store.setdefault(cia402.RATED_TORQUE, {})[0] = struct.pack("<I", self.scale.rated_thousandths)
        # one serial number per emulated drive (the EDS default would make every drive look alike)
        self.node.data_store.setdefault(cia402.IDENTITY, {})[4] = struct.pack("<I", node_id)
        self.nmt = NmtState.INITIALISING
        self.controlword = 0
        self.setpoint = 0  # per mille of the rated effort, as received
        # the drive's own torque limit (0x6072, per mille of rated): a setpoint beyond it is clipped
        self.max_torque = self._od_default(cia402.MAX_TORQUE)
        self.mode = 0
        self._sync_cob = SYNC_COB_ID
        self._heartbeat_cycles = 0
        self._heartbeat_ms = self._od_default(cia402.PRODUCER_HEARTBEAT_TIME)
        self._consumer: tuple[int, int] | None = None  # master node id, timeout ms (0x1016 sub 1)
        self._abort_option = self._od_default(cia402.ABORT_CONNECTION_OPTION)
        self._master_seen: float | None = None
        self.master_lost = False
        self._rpdos: list[tuple[int, PdoLayout, tuple[tuple[int, int, int], ...]]] = []
        self._tpdos: list[tuple[int, PdoLayout]] = []
        self._mapping_dirty = True
        self.faults = faults
        self.internal_limit = False  # statusword bit 11 (a limit switch tripped)
        self._rpdo_timeout_ms = 0  # 0x1400:05; 0 = no deadline monitoring
        self._ms_since_rpdo: float | None = None  # None until the first RPDO after configuration
        network.subscribe(self._sync_cob, self._on_sync)

    # -- object dictionary helpers -----------------------------------------------------------------
    def _od_default(self, index: int, sub: int = 0) -> int:
        obj = self.od[index]
        if not isinstance(obj, canopen.objectdictionary.ODVariable):
            obj = obj[sub]
        return obj.default

    def _value(self, index: int, sub: int = 0) -> int:
        return self.node.sdo[index][sub].raw if sub or not isinstance(
            self.od[index], canopen.objectdictionary.ODVariable) else self.node.sdo[index].raw

    # -- NMT -----------------------------------------------------------------------------------------
    def boot(self) -> None:
        """Power on: boot-up message, then Pre-operational."""
        self.nmt = NmtState.INITIALISING
        self.network.send_message(HEARTBEAT_BASE + self.node_id, bytes([NmtState.INITIALISING]))
        self.nmt = NmtState.PRE_OPERATIONAL

    def reset(self, application: bool = True, spontaneous: bool = False) -> None:
        """NMT reset (node: parameters back to the EDS defaults, power stage restarted; communication:
        only the CANopen side), then boot-up. ``spontaneous``: the drive did it by itself (a watchdog,
        a brown-out), which the master must notice from the boot-up message."""
        if application or spontaneous:
            self.node.data_store.clear()
            self.node.data_store.setdefault(cia402.RATED_TORQUE, {})[0] = struct.pack(
                "<I", self.scale.rated_thousandths)
            self.node.data_store.setdefault(cia402.IDENTITY, {})[4] = struct.pack("<I", self.node_id)
            self._heartbeat_ms = self._od_default(cia402.PRODUCER_HEARTBEAT_TIME)
            self._abort_option = self._od_default(cia402.ABORT_CONNECTION_OPTION)
            self.max_torque = self._od_default(cia402.MAX_TORQUE)
            self.drive.quick_stop_option = self._od_default(cia402.QUICK_STOP_OPTION)
            self.mode = 0
            d = self.drive
            d.power, d.applied, d.error_code = cia402.PowerState.SWITCH_ON_DISABLED, 0.0, 0
            self.internal_limit = False
        self._rpdo_timeout_ms, self._ms_since_rpdo = 0, None
        self._mapping_dirty = True
        self.boot()

    def _on_nmt(self, can_id: int, data: bytes, timestamp: float) -> None:
        if len(data) < 2:
            return
        cmd, target = data[0], data[1]
        if target not in (0, self.node_id):
            return
        if cmd in (NmtCommand.RESET_NODE, NmtCommand.RESET_COMMUNICATION):
            self.reset(application=cmd == NmtCommand.RESET_NODE)
        elif cmd in NMT_TRANSITIONS:
            self.nmt = NMT_TRANSITIONS[NmtCommand(cmd)]
            if self.nmt is NmtState.OPERATIONAL:
                self._load_mapping()

    # -- SDO hooks -----------------------------------------------------------------------------------
    def _on_write(self, index: int, subindex: int, od, data: bytes) -> None:
        if self.faults is not None and self.faults.sdo_abort_index == index:
            raise canopen.SdoAbortedError(SDO_ABORT_GENERAL)
        if cia402.RPDO_COMM <= index <= cia402.TPDO_MAP + 0x1FF:
            self._mapping_dirty = True  # LocalNode stores the value after this callback
            if index == cia402.RPDO_COMM and subindex == 5:
                self._rpdo_timeout_ms = struct.unpack("<H", data)[0]
                self._ms_since_rpdo = None  # CiA 301: monitoring starts at the next RPDO
        elif index == cia402.CONTROLWORD:
            self.controlword = struct.unpack("<H", data)[0]
        elif index == cia402.TARGET_TORQUE:
            self.setpoint = struct.unpack("<h", data)[0]
        elif index == cia402.MODES_OF_OPERATION:
            mode = struct.unpack("<b", data)[0]
            supported = self._od_default(cia402.SUPPORTED_DRIVE_MODES)
            if mode <= 0 or not supported & cia402.supported_mode_bit(cia402.Mode(mode)):
                raise canopen.SdoAbortedError(SDO_ABORT_VALUE_RANGE)
            self.mode = mode
        elif index == cia402.MAX_TORQUE:
            self.max_torque = struct.unpack("<H", data)[0]
        elif index == cia402.QUICK_STOP_OPTION:
            self.drive.quick_stop_option = struct.unpack("<h", data)[0]
        elif index == cia402.CONSUMER_HEARTBEAT_TIME and subindex == 1:
            value = struct.unpack("<I", data)[0]
            self._consumer = ((value >> 16) & 0x7F, value & 0xFFFF)  # (master node id, timeout ms)
            self.network.subscribe(HEARTBEAT_BASE + self._consumer[0], self._on_master_heartbeat)
        elif index == cia402.ABORT_CONNECTION_OPTION:
            self._abort_option = struct.unpack("<h", data)[0]
        elif index == cia402.PRODUCER_HEARTBEAT_TIME:
            self._heartbeat_ms = struct.unpack("<H", data)[0]
            self._heartbeat_cycles = 0  # restart the count with the new period

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
        if index == DIGITAL_INPUTS:  # switches (session homing: controllers/homing.py)
            return d.digital_inputs()
        return None

    def statusword(self) -> int:
        power = self.drive.power
        return cia402.encode_statusword(power, follows=power is cia402.PowerState.OPERATION_ENABLED,
                                        internal_limit=self.internal_limit)

    @property
    def reported_position(self) -> float:
        """What the encoder says (the plant's position, unless an injected glitch offsets it)."""
        return self.drive.position + (self.faults.position_offset if self.faults is not None else 0.0)

    # -- faults and their reactions ------------------------------------------------------------------
    def fault(self, code: int, *, internal_limit: bool = False) -> None:
        """The drive's own fault: Fault Reaction Active (zero torque now), 0x603F = code, EMCY out."""
        self.drive.fault(code)
        self.internal_limit = internal_limit
        self.node.emcy.send(code, 0x01)  # error register bit 0: generic error

    def _communication_lost(self, code: int) -> None:
        """The master is gone (heartbeat or RPDO deadline): react per 0x6007 (1 fault, 2 disable
        voltage, 3 quick stop; in torque mode both end at zero torque at once)."""
        d = self.drive
        if self._abort_option == 1:
            self.fault(code)
        elif self._abort_option in (2, 3) and d.power in (cia402.PowerState.OPERATION_ENABLED,
                                                          cia402.PowerState.QUICK_STOP_ACTIVE):
            d.power = cia402.PowerState.SWITCH_ON_DISABLED
            d.applied = 0.0
            d.error_code = code
            self.node.emcy.send(code, 0x10)  # error register bit 4: communication error

    # -- PDOs ----------------------------------------------------------------------------------------
    def _load_mapping(self) -> None:
        """Read the PDO mapping the master wrote (LocalNode keeps it in its data store)."""
        for cob, _layout, _slots in self._rpdos:
            self.network.unsubscribe(cob, self._on_rpdo)
        self._rpdos, self._tpdos = [], []
        for cob, layout in self._enabled_pdos(cia402.RPDO_COMM, cia402.RPDO_MAP):
            offsets, offset = [], 0
            for (index, sub), code in zip(layout.entries, layout.codec.format[1:], strict=True):
                size = struct.calcsize("<" + code)
                offsets.append((index, sub, offset, size))
                offset += size
            self._rpdos.append((cob, layout, tuple(offsets)))
            self.network.subscribe(cob, self._on_rpdo)
        self._tpdos = self._enabled_pdos(cia402.TPDO_COMM, cia402.TPDO_MAP)
        self._mapping_dirty = False

    def _enabled_pdos(self, comm_base: int, map_base: int) -> list[tuple[int, PdoLayout]]:
        """(COB-ID, layout) of every valid PDO of one direction, from the object dictionary."""
        out = []
        for n in range(4):
            comm, mapping = comm_base + n, map_base + n
            if comm not in self.od:
                continue
            cob = self._value(comm, 1)
            count = self._value(mapping, 0)
            if cob & 0x80000000 or count == 0:  # bit 31: PDO not valid
                continue
            words = [self._value(mapping, i + 1) for i in range(count)]
            out.append((cob & 0x7FF, PdoLayout.from_mapping_words(self.od, words)))
        return out

    def _on_rpdo(self, can_id: int, data: bytes, timestamp: float) -> None:
        if self.nmt is not NmtState.OPERATIONAL:
            return
        store = self.node.data_store
        for cob, layout, slots in self._rpdos:
            if cob != can_id:
                continue
            values = layout.codec.unpack_from(data)
            for (index, sub, offset, size), value in zip(slots, values, strict=True):
                store.setdefault(index, {})[sub] = bytes(data[offset:offset + size])
                if index == cia402.CONTROLWORD:
                    self.controlword = value
                elif index == cia402.TARGET_TORQUE:
                    self.setpoint = value
        if self._rpdo_timeout_ms:
            self._ms_since_rpdo = 0.0
        if self.faults is not None and self.faults.held:
            self._send_held()  # a late TPDO: after the master's deadline, with its RPDO

    def _on_master_heartbeat(self, can_id: int, data: bytes, timestamp: float) -> None:
        self._master_seen = time.monotonic()
        self.master_lost = False

    def check_master(self, now: float | None = None) -> bool:
        """Heartbeat consumer on the wall clock, called by the emulator's receive loop: when the
        master's heartbeat stops (a dead master sends no SYNC either, so simulated time would stand
        still), react per 0x6007: 1 fault, 2 disable voltage, 3 quick stop (zero torque both ways).
        Returns True when that stopped the drive now (False too when it was not running)."""
        if self._consumer is None or self._master_seen is None or self.master_lost or not self._consumer[1]:
            return False
        now = time.monotonic() if now is None else now
        if (now - self._master_seen) * 1000.0 <= self._consumer[1]:
            return False
        self.master_lost = True
        running = self.drive.power in (cia402.PowerState.OPERATION_ENABLED, cia402.PowerState.QUICK_STOP_ACTIVE)
        self._communication_lost(cia402.HEARTBEAT_LOST_ERROR)
        return running

    def _on_sync(self, can_id: int, data: bytes, timestamp: float) -> None:
        d = self.drive
        faults = self.faults
        if faults is not None and faults.held:
            self._send_held()  # late frames that no RPDO flushed go out before this cycle's
        sp, limit = self.setpoint, self.max_torque
        d.sync(self.controlword, self.scale.from_permille(limit if sp > limit else -limit if sp < -limit else sp))
        if self.internal_limit and d.power is not cia402.PowerState.FAULT and \
                d.power is not cia402.PowerState.FAULT_REACTION_ACTIVE:
            self.internal_limit = False  # the fault was reset
        self._watch_deadline()
        if faults is not None and faults.pending:
            faults.on_sync(self, d.syncs, d.plant.dt)
        if self._heartbeat_ms and not (faults is not None and faults.heartbeat_stopped):
            self._heartbeat_cycles += 1
            if self._heartbeat_cycles * self.plant_dt_ms >= self._heartbeat_ms:
                self._heartbeat_cycles = 0
                self.network.send_message(HEARTBEAT_BASE + self.node_id, bytes([self.nmt]))
        if self.nmt is not NmtState.OPERATIONAL:
            return
        if self._mapping_dirty:
            self._load_mapping()
        values = {
            cia402.STATUSWORD: self.statusword(),
            cia402.POSITION_ACTUAL: self.encoder.to_counts(self.reported_position),
            cia402.VELOCITY_ACTUAL: self.encoder.to_counts(d.velocity),
            cia402.TORQUE_ACTUAL: self.scale.to_permille(d.applied),
            cia402.ERROR_CODE: d.error_code,
            cia402.MODES_OF_OPERATION_DISPLAY: self.mode,
        }
        send = self.network.send_message
        if faults is None:
            for cob, layout in self._tpdos:
                send(cob, layout.codec.pack(*[values[index] for index, _ in layout.entries]))
            return
        for n, (cob, layout) in enumerate(self._tpdos):
            action = faults.tpdo_action(n)
            frame = layout.codec.pack(*[values[index] for index, _ in layout.entries])
            if action == "send":
                send(cob, frame)
            elif action == "hold":
                faults.held.append((cob, frame))
        faults.end_cycle()

    def _send_held(self) -> None:
        send = self.network.send_message
        for cob, frame in self.faults.release():
            send(cob, frame)

    def _watch_deadline(self) -> None:
        """RPDO deadline monitoring (0x1400:05), one drive cycle at a time."""
        if self._ms_since_rpdo is None or not self._rpdo_timeout_ms or self.nmt is not NmtState.OPERATIONAL:
            return
        self._ms_since_rpdo += self.plant_dt_ms
        if self._ms_since_rpdo > self._rpdo_timeout_ms:
            self._ms_since_rpdo = None  # one reaction; monitoring restarts with the next RPDO
            self._communication_lost(RPDO_TIMEOUT_ERROR)

    def idle(self) -> None:
        """One cycle of the drive's own clock with no SYNC received (the master is silent): the plant
        moves on under the effort last applied, the deadline monitoring counts."""
        d = self.drive
        if d.syncs:
            d.plant.step(d.state, d.applied)
        self._watch_deadline()

    @property
    def plant_dt_ms(self) -> float:
        return self.drive.plant.dt * 1000.0

    def close(self) -> None:
        self.network.unsubscribe(self._sync_cob, self._on_sync)
        self.network.unsubscribe(NMT_COB_ID, self._on_nmt)
        for cob, _layout, _slots in self._rpdos:
            self.network.unsubscribe(cob, self._on_rpdo)

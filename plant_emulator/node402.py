"""The emulated drive: a CiA 402 slave on a CAN bus, with the plant as its power stage.

Built on canopen's LocalNode (object dictionary from the EDS) and adding what that toolbox lacks (see
../shared/DESIGN.md, "Known traps"), each part as CiA 301/402 and real drives have it:

* NMT (nmt_slave.py rules): boot-up message a configurable delay after power-on or a reset command
  (default 50 ms of drive time: real drives take tens to hundreds of ms, and canopen's documented
  ``send_command(0x81)`` then ``wait_for_bootup()`` needs the boot-up to come after the command has
  returned); in Stopped only NMT and heartbeat (no SDO, no PDO, no EMCY); reset communication restores
  0x1000-0x1FFF, reset node everything; leaving Operational while enabled is answered per 0x6007
  with EMCY 0x8100 (communication error), as a real drive whose PDOs stop;
* SDO (sdo_server.py): sub-indices, EDS limits, reserved values and PDO mapping checked with the
  abort code CiA 301 gives (pdo_rules.py);
* PDOs (pdo_rules.py for the rules, here the engine): transmission types 0, 1..240 (every n-th SYNC),
  252/253 (on RTR), 254/255 (on change, inhibit time 0x1800:3, event timer 0x1800:5); a new mapping
  takes effect the moment it is made valid; an RPDO shorter than its mapping is dropped with EMCY
  0x8210, a longer one used with EMCY 0x8220 (CANopenNode does the same); an RPDO's values are stored on
  reception, whatever its type (an event-driven one, 255, as drivectl's minimal mapping sends the
  controlword, is thus taken at once), and the drive acts on them at its next cycle; the RPDO deadline
  (0x1400:05) watches RPDO1;
* EMCY: 0x1001 live (bit 0 any error, bit 4 communication), an error-reset EMCY (0x0000) when the last
  error clears;
* CiA 402: the drive (plant_emulator/drive.py, shared with SimAxis) steps the plant once per cycle
  with the setpoint latched at the previous SYNC, clipped to 0x6072, scaled by 0x6076; no mode
  (0x6060 = 0) gives no torque; halt clears statusword bit 12;
* the master's heartbeat consumed (0x1016) and the RPDO deadline monitored (0x1400:05): a lost master
  is answered per 0x6007 on the drive's own.

The drive's clock (issue 19): drive time advances one cycle per SYNC, so a lockstep run is
deterministic and a merely slow master is never taken for a dead one (its heartbeat, sent every n
SYNCs, and the drive's consumer count the same time). When nothing brings SYNCs, the drive runs on
its own: in-process through :meth:`EmulatedDrive.advance` (the lockstep network lets time pass while
the master waits, :meth:`idle` runs one cycle); across processes, and in-process while a run is paced
on the wall clock (``trace --paced``: :meth:`EmulatedDrive.wall_clock`, called by the lockstep network
around every frame it delivers), through :meth:`EmulatedDrive.serve` with the wall clock: SYNC-locked
while SYNCs come, free-running (the whole gap counted, so the RPDO deadline fires 2 cycles of drive
time after the last RPDO) once no SYNC came for ``sync_loss_ms``. Its default is the master-heartbeat
consumer time (0x1016, 300 ms as drivectl configures it; 300 ms without a consumer): a lockstep
master on a loaded machine leaves gaps of some ms and, now and then, over 100 ms (measured on the
2-core CI VM), which must not count as a dead master, while a master silent for longer than its own
heartbeat period allows is dead by CiA 301's own rule. A master paced in real time wants about two
cycles (:data:`PACED_SYNC_LOSS_CYCLES`, what a paced in-process run uses: a master later than its RPDO
deadline allows is caught by the drive, as across processes). Heartbeat, event-driven TPDOs, the RPDO
deadline and the 0x1016 consumer all run on that one clock, so a silent master is always caught.
"""

from __future__ import annotations

import struct
import time
from pathlib import Path

import can
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
from drivectl.driver.network import deliver_remote
from drivectl.driver.units import DEFAULT_RESOLUTION_M, EffortScale, Encoder
from drivectl.plant_emulator.drive import DriveModel
from drivectl.plant_emulator.faults import SDO_ABORT_GENERAL, FaultInjector
from drivectl.plant_emulator.frames import FrameGuard, log
from drivectl.plant_emulator.models import Plant
from drivectl.plant_emulator.pdo_rules import PdoRules, Rpdo, Tpdo
from drivectl.plant_emulator.sdo_server import DriveSdoServer

#: CiA 402 digital inputs (bit 0 negative limit, 1 positive limit, 2 home switch)
DIGITAL_INPUTS = 0x60FD

#: EMCY / 0x603F codes (CiA 301 table 21)
RPDO_TIMEOUT_ERROR = 0x8250
RPDO_SHORT_ERROR = 0x8210  # PDO not processed due to length error
RPDO_LONG_ERROR = 0x8220  # PDO length exceeded
SYNC_LENGTH_ERROR = 0x8240  # unexpected SYNC data length
COMMUNICATION_ERROR = 0x8100  # communication, generic: NMT took the drive out of Operational while enabled
ERROR_RESET = 0x0000

#: default boot-up delay (ms of drive time); SYNC-loss window of a served drive (ms of wall time) when
#: no master heartbeat is consumed (else the consumer's time, 0x1016)
BOOT_DELAY_MS = 50.0
SYNC_LOSS_MS = 300.0
#: the SYNC-loss window of an in-process drive while the master's run is paced on the wall clock (cycles):
#: a master paced in real time leaves about one cycle between SYNCs, so a longer gap is the master running late
PACED_SYNC_LOSS_CYCLES = 2

EMULATED_DRIVE_EDS = Path(__file__).resolve().parent.parent / "driver" / "eds" / "drivectl-emulated-drive.eds"

_RUNNING = (cia402.PowerState.OPERATION_ENABLED, cia402.PowerState.QUICK_STOP_ACTIVE)
_FAULTED = (cia402.PowerState.FAULT, cia402.PowerState.FAULT_REACTION_ACTIVE)


def subscribe_remote(network: canopen.Network, can_id: int, callback) -> None:
    """Remote frames (RTR) go to ``network.remote_subscribers`` (canopen's notify() carries no RTR bit:
    a remote frame would look like an empty data frame); the receive loops route them there."""
    subs = network.__dict__.setdefault("remote_subscribers", {})
    if callback not in subs.setdefault(can_id, []):
        subs[can_id].append(callback)


def unsubscribe_remote(network: canopen.Network, can_id: int, callback) -> None:
    subs = network.__dict__.get("remote_subscribers", {})
    if callback in subs.get(can_id, ()):
        subs[can_id].remove(callback)


_handler_errors: set[str] = set()


def deliver(network: canopen.Network, msg: can.Message) -> None:
    """One received frame to the emulated drives on ``network`` (the receive loop of a served emulator):
    a remote frame to the RTR handlers, a data frame to canopen's notify, 29-bit and error frames
    nowhere (not CANopen). A handler that still raises is a bug: logged once per exception type, never
    the end of the emulator."""
    if msg.is_error_frame or msg.is_extended_id:
        return
    try:
        if msg.is_remote_frame:
            deliver_remote(network, msg.arbitration_id)
        else:
            network.notify(msg.arbitration_id, msg.data, msg.timestamp)
    except Exception as exc:  # noqa: BLE001 - the emulator outlives any one frame
        kind = type(exc).__name__
        if kind not in _handler_errors:
            _handler_errors.add(kind)
            log.exception("frame 0x%03X [%s]: handler raised %s (further ones of this type not logged)",
                          msg.arbitration_id, bytes(msg.data).hex(" "), kind)


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
        boot_delay_ms: float = BOOT_DELAY_MS,
        sync_loss_ms: float | None = None,
        io: object = None,
    ):
        if not 1 <= node_id <= 127:
            raise ValueError(f"emulated drive: node id must be 1..127, got {node_id}")
        if not boot_delay_ms >= 0:
            raise ValueError(f"emulated drive: boot_delay_ms must be >= 0, got {boot_delay_ms!r}")
        if sync_loss_ms is not None and not sync_loss_ms >= 0:
            raise ValueError(f"emulated drive: sync_loss_ms must be >= 0, got {sync_loss_ms!r}")
        self.network = network
        self.node_id = node_id
        self.od = canopen.import_od(str(eds), node_id)
        self.node = canopen.LocalNode(node_id, self.od)
        self.frames = FrameGuard(node_id)
        network.add_node(self.node)
        # canopen's NmtSlave runs heartbeats on a timer thread and stays INITIALISING after a reset, its
        # SdoServer answers in every NMT state: both replaced (NMT here, SDO in sdo_server.py)
        network.unsubscribe(NMT_COB_ID, self.node.nmt.on_command)
        self.node._write_callbacks.remove(self.node.nmt.on_write)
        network.unsubscribe(self.node.sdo.rx_cobid, self.node.sdo.on_request)
        self.sdo = DriveSdoServer(self.node, self.frames, self._sdo_allowed, self._after_write)
        self.sdo.network = network
        network.subscribe(self.sdo.rx_cobid, self.sdo.on_request)
        subscribe_remote(network, self.sdo.rx_cobid, self._on_remote)
        network.subscribe(NMT_COB_ID, self._on_nmt)
        subscribe_remote(network, NMT_COB_ID, self._on_remote)
        self.node.add_write_callback(self._on_write)
        self.node.add_read_callback(self._on_read)
        self.rules = PdoRules(self.od, self._value)

        self.encoder = Encoder(resolution)
        self.scale = EffortScale(rated_effort)
        self._rated_effort = rated_effort
        self.drive = DriveModel(plant, force_noise=force_noise, seed=seed, initial_position=initial_position,
                                quick_stop_option=self._od_default(cia402.QUICK_STOP_OPTION), io=io)
        self.cycle_ms = plant.dt * 1000.0
        self.boot_delay_ms = float(boot_delay_ms)
        self.sync_loss_ms = sync_loss_ms
        self.faults = faults
        self.nmt = NmtState.INITIALISING
        self.time_ms = 0.0  # the drive's own clock
        self._boot_due: float | None = None  # drive time of the pending boot-up message
        self._served = False
        self._synced = False  # a SYNC came since the last serve()
        self._anchor = 0.0  # wall time (s) matching the drive's clock when served
        self._last_serve = 0.0  # wall time (s) of the last serve(): a long absence is this process's own
        self._free_running = True  # served and not SYNC-locked (no SYNC since power-on or reset)
        self._window_ms: float | None = None  # the SYNC-loss window of a paced in-process run (wall_clock)
        self._heartbeat_cycles = 0
        self._consumer: tuple[int, int] | None = None  # master node id, timeout ms (0x1016 sub 1)
        self._ms_since_master: float | None = None  # None until the first heartbeat of the master
        self.master_lost = False
        self._reaction = 0  # EMCY code of a watchdog that stopped the running drive (reported by check_master())
        self._rpdos: dict[int, Rpdo] = {}
        self._tpdos: list[Tpdo] = []
        self.internal_limit = False  # statusword bit 11 (a limit switch tripped)
        self._errors: set[int] = set()  # active communication errors (EMCY codes) besides a Fault
        self._fault_reported = False
        self._sync_cob = SYNC_COB_ID
        self._restore(application=True)
        network.subscribe(self._sync_cob, self._on_sync)
        subscribe_remote(network, self._sync_cob, self._on_remote)
        if getattr(network, "frame_guard", None) is not None:
            # the master's frame checks (driver/frame_guard.py) would drop what a drive must see and answer
            # itself (a SYNC of the wrong length is EMCY 0x8240, an RTR on a TPDO is answered)
            network.frame_guard = None
        lockstep = getattr(network, "lockstep", None)
        if lockstep is not None and hasattr(lockstep, "clocks"):
            lockstep.clocks.append(self.advance)  # the drive's clock runs while the master waits
            lockstep.wall_clocks.append(self.wall_clock)  # ... and on the wall clock while a run is paced

    # -- object dictionary helpers -----------------------------------------------------------------
    def _od_default(self, index: int, sub: int = 0) -> int:
        obj = self.od[index]
        if not isinstance(obj, canopen.objectdictionary.ODVariable):
            obj = obj[sub]
        return obj.default

    def _value(self, index: int, sub: int = 0) -> int:
        """The value the drive holds (written, live or the EDS default)."""
        obj = self.od[index]
        if not isinstance(obj, canopen.objectdictionary.ODVariable):
            obj = obj.subindices[sub]
        return obj.decode_raw(self.node.get_data(index, sub))

    def _restore(self, application: bool) -> None:
        """The values of power-on: 0x1000-0x1FFF (communication) and, for ``application``, the rest."""
        store = self.node.data_store
        for index in list(store):
            if application or 0x1000 <= index <= 0x1FFF:
                del store[index]
        # one serial number per emulated drive (the EDS default would make every drive look alike)
        store.setdefault(cia402.IDENTITY, {})[4] = struct.pack("<I", self.node_id)
        self._heartbeat_ms = self._od_default(cia402.PRODUCER_HEARTBEAT_TIME)
        self._heartbeat_cycles = 0
        if self._consumer is not None:
            self.network.unsubscribe(HEARTBEAT_BASE + self._consumer[0], self._on_master_heartbeat)
        self._consumer, self._ms_since_master, self.master_lost = None, None, False
        self._rpdo_timeout_ms, self._ms_since_rpdo = 0, None
        self._set_sync_cob(self._od_default(cia402.COB_ID_SYNC) & 0x7FF)
        self._errors.clear()
        if application:
            store.setdefault(cia402.RATED_TORQUE, {})[0] = struct.pack("<I", round(self._rated_effort * 1000))
            self.scale = EffortScale(self._rated_effort)
            self._abort_option = self._od_default(cia402.ABORT_CONNECTION_OPTION)
            self.max_torque = self._od_default(cia402.MAX_TORQUE)
            self.drive.quick_stop_option = self._od_default(cia402.QUICK_STOP_OPTION)
            self._set_mode(self._od_default(cia402.MODES_OF_OPERATION))
            self.controlword = 0
            self.setpoint = 0  # per mille of the rated effort, as received
            d = self.drive
            d.power, d.applied, d.error_code = cia402.PowerState.SWITCH_ON_DISABLED, 0.0, 0
            self.internal_limit = False
            self._fault_reported = False
        self._load_mapping()

    def _set_sync_cob(self, cob: int) -> None:
        if getattr(self, "_sync_cob", None) == cob:
            return
        self.network.unsubscribe(self._sync_cob, self._on_sync)
        unsubscribe_remote(self.network, self._sync_cob, self._on_remote)
        self._sync_cob = cob
        self.network.subscribe(cob, self._on_sync)
        subscribe_remote(self.network, cob, self._on_remote)

    # -- NMT -----------------------------------------------------------------------------------------
    def boot(self) -> None:
        """Power on (or the end of a reset): the boot-up message after ``boot_delay_ms`` of drive time,
        then Pre-operational."""
        self.nmt = NmtState.INITIALISING
        self._free_running = True  # no SYNC lock until the next SYNC
        if self.boot_delay_ms <= 0:
            self._boot_done()
        else:
            self._boot_due = self.time_ms + self.boot_delay_ms

    def _boot_done(self) -> None:
        self._boot_due = None
        self.network.send_message(HEARTBEAT_BASE + self.node_id, bytes([NmtState.INITIALISING]))
        self.nmt = NmtState.PRE_OPERATIONAL

    def reset(self, application: bool = True, spontaneous: bool = False) -> None:
        """NMT reset (node: parameters back to the EDS defaults, power stage restarted; communication:
        0x1000-0x1FFF only), then boot-up. ``spontaneous``: the drive did it by itself (an injected
        watchdog reset, a brown-out), which the master must notice from the boot-up message: that one
        comes at once (the fault matrix counts on the master seeing the boot-up, not a TPDO gap)."""
        self._restore(application or spontaneous)
        if spontaneous:
            self.nmt = NmtState.INITIALISING
            self._boot_done()
        else:
            self.boot()

    def _on_nmt(self, can_id: int, data: bytes, timestamp: float) -> None:
        if len(data) != 2:
            self.frames.reject("nmt-length", can_id, data, f"NMT command of {len(data)} bytes (CiA 301: 2)")
            return
        cmd, target = data[0], data[1]
        if target not in (0, self.node_id):
            return
        if cmd in (NmtCommand.RESET_NODE, NmtCommand.RESET_COMMUNICATION):
            self._leave_operational()
            self.reset(application=cmd == NmtCommand.RESET_NODE)
        elif cmd in NMT_TRANSITIONS:
            if self._boot_due is not None:
                return  # still initialising: only a reset acts
            new = NMT_TRANSITIONS[NmtCommand(cmd)]
            if new is not NmtState.OPERATIONAL:
                self._leave_operational()
            self.nmt = new
        else:
            self.frames.reject("nmt-command", can_id, data, f"unknown NMT command 0x{cmd:02X}")

    def _leave_operational(self) -> None:
        """NMT takes the drive out of Operational: its PDOs stop, so an enabled drive must not hold the
        last torque. Reaction per 0x6007 (CiA 402 lists NMT stop and resets among its causes; a change
        to Pre-operational stops the PDOs just the same), EMCY 0x8100 sent before the state changes
        (once Stopped, the drive may send no EMCY)."""
        if self.nmt is NmtState.OPERATIONAL and self.drive.power in _RUNNING:
            self._communication_lost(COMMUNICATION_ERROR, only_running=True)

    def _sdo_allowed(self) -> bool:
        return self.nmt in (NmtState.PRE_OPERATIONAL, NmtState.OPERATIONAL)

    # -- SDO hooks -----------------------------------------------------------------------------------
    def _on_write(self, index: int, subindex: int, od, data: bytes) -> None:
        """Called before canopen stores ``data``: the drive's own rules (beyond the EDS limits that the
        SDO server checked); an abort leaves the value unchanged."""
        if self.faults is not None and self.faults.sdo_abort_index == index:
            raise canopen.SdoAbortedError(SDO_ABORT_GENERAL)
        if 0x1400 <= index <= 0x1BFF:
            self.rules.check(index, subindex, data)
        elif index == cia402.COB_ID_SYNC:
            value = struct.unpack("<I", data)[0]
            if value & 0x60000000 or value & 0x1FFFF800:  # bit 30: this drive cannot produce SYNC; 29: 29-bit
                raise canopen.SdoAbortedError(SDO_ABORT_VALUE_RANGE)
        elif index == cia402.COMM_CYCLE_PERIOD:
            value = struct.unpack("<I", data)[0]
            # the drive's control cycle is its plant's: it can follow a SYNC of that period (or none)
            if value not in (0, round(self.cycle_ms * 1000)):
                raise canopen.SdoAbortedError(SDO_ABORT_VALUE_RANGE)
        elif index == cia402.MODES_OF_OPERATION:
            if not self._mode_supported(struct.unpack("<b", data)[0]):
                raise canopen.SdoAbortedError(SDO_ABORT_VALUE_RANGE)
        elif index == cia402.RATED_TORQUE and struct.unpack("<I", data)[0] == 0:
            raise canopen.SdoAbortedError(SDO_ABORT_VALUE_RANGE)

    def _after_write(self, index: int, sub: int) -> None:
        """A value is stored: the drive takes it at once."""
        value = self._value(index, sub)
        if 0x1400 <= index <= 0x1BFF:
            self._load_mapping()  # a new mapping is effective the moment it is made valid
            if index == cia402.RPDO_COMM and sub == 5:
                self._rpdo_timeout_ms = value
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

    def _mode_supported(self, mode: int) -> bool:
        if mode == 0:
            return True  # no mode: allowed, the drive then gives no torque
        supported = self._od_default(cia402.SUPPORTED_DRIVE_MODES)
        return 0 < mode <= 32 and bool(supported & (1 << (mode - 1)))

    def _set_mode(self, mode: int) -> None:
        self.mode = mode
        # this drive runs cyclic synchronous torque only: any other mode (0 included) gives no torque
        self.drive.mode_ok = mode == cia402.Mode.CYCLIC_SYNC_TORQUE

    @property
    def error_register(self) -> int:
        """0x1001: bit 4 communication error, bit 0 whenever any error is active (CiA 301)."""
        reg = 0x10 if self._errors else 0
        if self.drive.power in _FAULTED or reg:
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
        return cia402.encode_statusword(self.drive.power, follows=self.drive.following,
                                        internal_limit=self.internal_limit)

    @property
    def reported_position(self) -> float:
        """What the encoder says (the plant's position, unless an injected glitch offsets it)."""
        return self.drive.position + (self.faults.position_offset if self.faults is not None else 0.0)

    # -- EMCY, faults and their reactions -----------------------------------------------------------------
    def _emcy(self, code: int) -> None:
        """EMCY with the live error register; none outside Pre-operational and Operational (CiA 301)."""
        if self.nmt in (NmtState.PRE_OPERATIONAL, NmtState.OPERATIONAL):
            self.node.emcy.send(code, self.error_register)

    def _clear_error(self, code: int) -> None:
        if code in self._errors:
            self._errors.discard(code)
            if not self._errors and self.drive.power not in _FAULTED:
                self._emcy(ERROR_RESET)

    def fault(self, code: int, *, internal_limit: bool = False) -> None:
        """The drive's own fault: Fault Reaction Active (zero torque now), 0x603F = code, EMCY out."""
        self.drive.fault(code)
        self.internal_limit = internal_limit
        self._fault_reported = True
        self._emcy(code)

    def _communication_lost(self, code: int, only_running: bool = False) -> None:
        """The master is gone (heartbeat, RPDO deadline, NMT out of Operational): react per 0x6007
        (1 fault, 2 disable voltage, 3 quick stop; in torque mode both end at zero torque at once)."""
        d = self.drive
        running = d.power in _RUNNING
        if only_running and not running:
            return
        if running and not self._reaction:
            self._reaction = code
        if self._abort_option == 1:
            self._errors.add(code)
            self.fault(code)
        elif self._abort_option in (2, 3) and running:
            d.power = cia402.PowerState.SWITCH_ON_DISABLED
            d.applied = 0.0
            d.error_code = code
            self._errors.add(code)
            self._emcy(code)

    # -- PDOs ----------------------------------------------------------------------------------------
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
        if self.nmt is not NmtState.OPERATIONAL:
            return
        rp = self._rpdos.get(can_id)
        if rp is None:
            return
        size = rp.layout.codec.size
        if len(data) < size:
            self.frames.reject("short-rpdo", can_id, data, f"RPDO of {len(data)} bytes, mapping needs {size}")
            if RPDO_SHORT_ERROR not in self._errors:
                self._errors.add(RPDO_SHORT_ERROR)
                self._emcy(RPDO_SHORT_ERROR)
            return  # not processed: for the deadline it is a lost frame
        self._clear_error(RPDO_SHORT_ERROR)
        if len(data) > size:
            self.frames.reject("long-rpdo", can_id, data, f"RPDO of {len(data)} bytes, mapping has {size}: "
                               "the mapped bytes used")
            if RPDO_LONG_ERROR not in self._errors:
                self._errors.add(RPDO_LONG_ERROR)
                self._emcy(RPDO_LONG_ERROR)
        else:
            self._clear_error(RPDO_LONG_ERROR)
        store = self.node.data_store
        values = rp.layout.codec.unpack_from(data)
        for (index, sub, offset, width), value in zip(rp.slots, values, strict=True):
            if index < 0x1000:
                continue  # a dummy entry: bytes meant for another drive
            if index == cia402.CONTROLWORD:
                self.controlword = value
            elif index == cia402.TARGET_TORQUE:
                self.setpoint = value
            elif index == cia402.MODES_OF_OPERATION:
                if not self._mode_supported(value):
                    self.frames.reject("rpdo-mode", can_id, data, f"mode {value} not supported: mode kept")
                    continue
                self._set_mode(value)
            store.setdefault(index, {})[sub] = bytes(data[offset:offset + width])
        if rp.comm != cia402.RPDO_COMM:
            return  # another RPDO (an event-driven controlword, type 255): the deadline watches RPDO1 only
        if self._rpdo_timeout_ms:
            self._ms_since_rpdo = 0.0
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

    def _on_master_heartbeat(self, can_id: int, data: bytes, timestamp: float) -> None:
        if len(data) != 1:
            self.frames.reject("heartbeat-length", can_id, data, f"heartbeat of {len(data)} bytes (CiA 301: 1)")
            return
        self._ms_since_master = 0.0
        self.master_lost = False
        self._clear_error(cia402.HEARTBEAT_LOST_ERROR)

    # -- the drive's clock -------------------------------------------------------------------------------
    def _on_sync(self, can_id: int, data: bytes, timestamp: float) -> None:
        if len(data) > 1:  # CiA 301: no data, or the 1-byte SYNC counter
            self.frames.reject("sync-length", can_id, data, f"SYNC of {len(data)} bytes")
            if SYNC_LENGTH_ERROR not in self._errors and self.nmt in (NmtState.PRE_OPERATIONAL,
                                                                      NmtState.OPERATIONAL):
                self._errors.add(SYNC_LENGTH_ERROR)  # (in Stopped: no EMCY, and nothing kept to report)
                self._emcy(SYNC_LENGTH_ERROR)
            return
        if SYNC_LENGTH_ERROR in self._errors:
            self._clear_error(SYNC_LENGTH_ERROR)
        self._synced = True  # serve() re-anchors the wall clock here
        self._cycle(sync=True)

    def _cycle(self, sync: bool) -> None:
        """One cycle of the drive: at a SYNC (``sync``) or on its own clock."""
        self.time_ms += self.cycle_ms
        if self._boot_due is not None:
            if self.time_ms >= self._boot_due - 1e-9:
                self._boot_done()
            return  # initialising: the application does not run yet
        d = self.drive
        faults = self.faults
        if sync and faults is not None and faults.held:
            self._send_held()  # late frames that no RPDO flushed go out before this cycle's
        sp, limit = self.setpoint, self.max_torque
        effort = self.scale.from_permille(limit if sp > limit else -limit if sp < -limit else sp)
        if sync:
            d.sync(self.controlword, effort)
        else:
            d.free_cycle(self.controlword, effort)
        if self.internal_limit and d.power not in _FAULTED:
            self.internal_limit = False  # the fault was reset
        if self._fault_reported and d.power not in _FAULTED:
            self._fault_reported = False  # fault reset: the error-reset EMCY tells the master (CiA 301)
            self._errors.clear()
            self._emcy(ERROR_RESET)
        self._watch_deadline()
        self._watch_master()
        if sync and faults is not None and faults.pending:
            faults.on_sync(self, d.syncs, d.plant.dt)
        if self._heartbeat_ms and not (faults is not None and faults.heartbeat_stopped):
            self._heartbeat_cycles += 1
            if self._heartbeat_cycles * self.cycle_ms >= self._heartbeat_ms:
                self._heartbeat_cycles = 0
                self.network.send_message(HEARTBEAT_BASE + self.node_id, bytes([self.nmt]))
        if self.nmt is not NmtState.OPERATIONAL:
            return
        now = self.time_ms
        send = self.network.send_message
        if not sync:
            for tp in self._tpdos:
                frame = tp.on_tick(now)
                if frame is not None:
                    send(tp.cob, frame)
            return
        if faults is None:
            for tp in self._tpdos:
                frame = tp.on_sync(now)
                if frame is None:
                    frame = tp.on_tick(now)
                if frame is not None:
                    send(tp.cob, frame)
            return
        for n, tp in enumerate(self._tpdos):
            frame = tp.on_sync(now)
            if frame is None:
                frame = tp.on_tick(now)
            if frame is None:
                continue
            action = faults.tpdo_action(n)
            if action == "send":
                send(tp.cob, frame)
            elif action == "hold":
                faults.held.append((tp.cob, frame))
        faults.end_cycle()

    def _send_tpdo(self, tp: Tpdo) -> None:
        frame = tp.pack()
        tp.sent(frame, self.time_ms)
        self.network.send_message(tp.cob, frame)

    def _send_held(self) -> None:
        send = self.network.send_message
        for cob, frame in self.faults.release():
            send(cob, frame)

    def _watch_deadline(self) -> None:
        """RPDO deadline monitoring (0x1400:05), one drive cycle at a time."""
        if self._ms_since_rpdo is None or not self._rpdo_timeout_ms or self.nmt is not NmtState.OPERATIONAL:
            return
        self._ms_since_rpdo += self.cycle_ms
        if self._ms_since_rpdo > self._rpdo_timeout_ms:
            self._ms_since_rpdo = None  # one reaction; monitoring restarts with the next RPDO
            self._communication_lost(RPDO_TIMEOUT_ERROR)

    def _watch_master(self) -> None:
        """Heartbeat consumer (0x1016) on the drive's clock, from the master's first heartbeat on."""
        if self._consumer is None or self._ms_since_master is None or self.master_lost:
            return
        self._ms_since_master += self.cycle_ms
        if self._ms_since_master > self._consumer[1]:
            self.master_lost = True
            self._communication_lost(cia402.HEARTBEAT_LOST_ERROR)

    def idle(self) -> None:
        """One cycle of the drive's own clock with no SYNC received (the master is silent)."""
        self._cycle(sync=False)

    def advance(self, seconds: float) -> None:
        """Let the drive's own clock run ``seconds`` (in-process: the lockstep network lets time pass
        while the master waits, e.g. for the boot-up); whole cycles only."""
        for _ in range(round(seconds * 1000.0 / self.cycle_ms)):
            self._cycle(sync=False)

    def serve(self, now: float | None = None) -> None:
        """The wall clock of a drive served across processes (call it whenever the receive loop wakes):
        SYNC-locked while SYNCs come; once none came for ``sync_loss_ms`` (or before the first SYNC
        after power-on or a reset), the drive runs on its own and counts the whole gap."""
        now = time.monotonic() if now is None else now
        if not self._served:
            self._served, self._anchor, self._last_serve = True, now, now
            return
        away, self._last_serve = now - self._last_serve, now
        if self._synced:
            # SYNC-locked: the drive's time is the SYNCs' (a slow master is not a dead one)
            self._synced, self._anchor, self._free_running = False, now, False
            return
        gap_ms = (now - self._anchor) * 1000.0
        if not self._free_running:
            window = self.sync_loss_ms if self._window_ms is None else self._window_ms
            if window is None:
                window = self._consumer[1] if self._consumer is not None else SYNC_LOSS_MS
            if gap_ms <= window:
                return
            if self._window_ms is None and away * 1000.0 > 0.5 * window:
                # this process itself was not running (a starved host or VM): the silence it saw may be its
                # own, not the master's; it judges again from now (in-process, _window_ms, it never is away)
                self._anchor = now
                return
            self._free_running = True
        n = int(gap_ms // self.cycle_ms)
        for _ in range(n):
            self._cycle(sync=False)
        self._anchor += n * self.cycle_ms / 1000.0

    def wall_clock(self, now: float | None) -> None:
        """In-process, while the master's run is paced on the wall clock (driver/network.Lockstep.pace): the
        wall time ``now``, given before and after every frame the lockstep network delivers, served as
        across processes (:meth:`serve`: the drive's clock is the wall clock, SYNC-locked within
        :data:`PACED_SYNC_LOSS_CYCLES`; a longer gap runs its cycles, so the RPDO deadline and the heartbeat
        consumer count the time the master was late). ``now=None``: the paced run ended; time is the SYNCs'
        again (lockstep). The first call of a paced run anchors the clock: the lockstep SYNCs came until then."""
        if now is None:
            self._served, self._window_ms = False, None
            return
        if not self._served:
            self._served, self._anchor, self._synced, self._free_running = True, now, False, False
            self._window_ms = PACED_SYNC_LOSS_CYCLES * self.cycle_ms
            return
        self.serve(now)

    def check_master(self, now: float | None = None) -> int:
        """:meth:`serve`, then the code (0x603F) of the watchdog that stopped the running drive since the
        last call (RPDO deadline 0x8250, master heartbeat 0x8130, NMT 0x8100), 0 if none did."""
        self.serve(now)
        code, self._reaction = self._reaction, 0
        return code

    @property
    def plant_dt_ms(self) -> float:
        return self.cycle_ms

    def close(self) -> None:
        self.network.unsubscribe(self._sync_cob, self._on_sync)
        self.network.unsubscribe(NMT_COB_ID, self._on_nmt)
        self.network.unsubscribe(self.sdo.rx_cobid, self.sdo.on_request)
        for cob in self._rpdos:
            self.network.unsubscribe(cob, self._on_rpdo)
        if self._consumer is not None:
            self.network.unsubscribe(HEARTBEAT_BASE + self._consumer[0], self._on_master_heartbeat)
        remote = self.network.__dict__.get("remote_subscribers", {})
        for subs in remote.values():
            if self._on_remote in subs:
                subs.remove(self._on_remote)
        lockstep = getattr(self.network, "lockstep", None)
        if lockstep is not None and self.advance in getattr(lockstep, "clocks", ()):
            lockstep.clocks.remove(self.advance)
        if lockstep is not None and self.wall_clock in getattr(lockstep, "wall_clocks", ()):
            lockstep.wall_clocks.remove(self.wall_clock)

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

The drive's clock is plant_emulator/drive_clock.py; its SDO hooks plant_emulator/drive_objects.py; its
PDO engine plant_emulator/drive_pdos.py; frame routing plant_emulator/remote.py.
"""

from __future__ import annotations

import struct
from pathlib import Path

import canopen
from canopen.objectdictionary import NUMBER_TYPES

from drivectl.driver import cia402
from drivectl.driver.capabilities import object_value, supported_modes
from drivectl.driver.cia301 import (
    HEARTBEAT_BASE,
    NMT_COB_ID,
    NMT_TRANSITIONS,
    SYNC_COB_ID,
    NmtCommand,
    NmtState,
)
from drivectl.driver.emulator_clock import CLOCK_OWN
from drivectl.driver.units import DEFAULT_RESOLUTION_M, EffortScale, Encoder
from drivectl.plant_emulator.drive import DriveModel
from drivectl.plant_emulator.drive_clock import DriveClock
from drivectl.plant_emulator.drive_constants import (  # noqa: F401 - re-exported: the drive's public constants
    BOOT_DELAY_MS,
    COMMUNICATION_ERROR,
    DIGITAL_INPUTS,
    EMULATED_DRIVE_EDS,
    ERROR_RESET,
    FAULTED,
    PACED_SYNC_LOSS_CYCLES,
    RPDO_LONG_ERROR,
    RPDO_SHORT_ERROR,
    RPDO_TIMEOUT_ERROR,
    RUNNING,
    SYNC_LENGTH_ERROR,
    SYNC_LOSS_MS,
)
from drivectl.plant_emulator.drive_objects import DriveObjects, add_emulator_object
from drivectl.plant_emulator.drive_pdos import DrivePdos
from drivectl.plant_emulator.faults import FaultInjector
from drivectl.plant_emulator.frames import FrameGuard
from drivectl.plant_emulator.models import Plant
from drivectl.plant_emulator.pdo_rules import PdoRules, Rpdo, Tpdo
from drivectl.plant_emulator.remote import deliver, subscribe_remote, unsubscribe_remote  # noqa: F401 - re-exported
from drivectl.plant_emulator.sdo_server import DriveSdoServer

#: 0x6072 where the drive has none: no clip of its own; 0x605A where it has none: CiA 402's default (quick stop
#: ramp, then Switch On Disabled)
NO_TORQUE_LIMIT = 0x7FFF
QUICK_STOP_DEFAULT = 2


def _variables(od: canopen.ObjectDictionary):
    for index in od.indices:
        obj = od[index]
        if isinstance(obj, canopen.objectdictionary.ODVariable):
            yield obj
        else:
            yield from obj.subindices.values()


class EmulatedDrive(DriveObjects, DrivePdos, DriveClock):
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
        add_emulator_object(self.od)  # whatever EDS it impersonates, a master can tell it is drivectl's emulator
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
                                quick_stop_option=self._od_default(cia402.QUICK_STOP_OPTION,
                                                                   absent=QUICK_STOP_DEFAULT), io=io)
        self.cycle_ms = plant.dt * 1000.0
        self.boot_delay_ms = float(boot_delay_ms)
        self.sync_loss_ms = sync_loss_ms
        #: the last RPDO deadline's account of the time without a setpoint (whose it was); "" if none fired
        self.deadline_why = ""
        self.faults = faults
        self.nmt = NmtState.INITIALISING
        self.time_ms = 0.0  # the drive's own clock
        self._boot_due: float | None = None  # drive time of the pending boot-up message
        self._served = False
        self._synced = False  # a SYNC came since the last serve()
        self._anchor = 0.0  # wall time (s) matching the drive's clock when served
        self._last_serve = 0.0  # wall time (s) of the last serve(): a long absence is this process's own
        self._sync_at = 0.0  # the last serve() before the last SYNC's delivery (in-process and paced: its arrival)
        self._free_running = True  # served and not SYNC-locked (no SYNC since power-on or reset)
        self._window_ms: float | None = None  # the SYNC-loss window of a paced in-process run (wall_clock)
        self.master_clock = CLOCK_OWN  # what the master said its clock is (0x5FFF:2, driver/emulator_clock.py)
        self._slot: int | None = None  # the last SYNC's counter (the master's slot count, CLOCK_SLOTS)
        #: cycles the drive's own clock ran since the last SYNC, and those it ran ahead of the counter (_catch_up)
        self._own_cycles = self._ahead = 0
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
        # what the EDS leaves open, fixed once: the numeric variables with no value (read as 0), the modes
        # (0x6502, else the modes its objects allow), whether 0x1018 has a serial number
        self._unset = {(v.index, v.subindex): len(v) // 8 for v in _variables(self.od)
                       if v.data_type in NUMBER_TYPES and object_value(v) is None and v.readable}
        self.supported_modes, _ = supported_modes(self.od)
        self._modes_unset = cia402.SUPPORTED_DRIVE_MODES in self.od and object_value(
            self.od[cia402.SUPPORTED_DRIVE_MODES]) is None
        self._unset.pop((cia402.SUPPORTED_DRIVE_MODES, 0), None)
        ident = self.od[cia402.IDENTITY] if cia402.IDENTITY in self.od else None
        self._has_serial = ident is not None and not isinstance(ident, canopen.objectdictionary.ODVariable) \
            and 4 in ident.subindices
        # 0x1018:1-3 without a usable default (absent or 0) answer what [DeviceInfo] declares, as the real
        # drive answers its own identity (docs/drives.md)
        info = self.od.device_information
        declared = {1: info.vendor_number, 2: info.product_number, 3: info.revision_number}
        self._identity = {sub: struct.pack("<I", value & 0xFFFFFFFF) for sub, value in declared.items()
                          if value and ident is not None and not isinstance(ident, canopen.objectdictionary.ODVariable)
                          and sub in ident.subindices and not object_value(ident.subindices[sub])}
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
    def _od_default(self, index: int, sub: int = 0, absent: int | None = None) -> int | None:
        """What the EDS says index:sub holds at power-on (ParameterValue, else DefaultValue); ``absent`` where
        the drive has no such object (an impersonated EDS without it: docs/drives.md says what then)."""
        if index not in self.od:
            return absent
        obj = self.od[index]
        if not isinstance(obj, canopen.objectdictionary.ODVariable):
            obj = obj.subindices.get(sub)
            if obj is None:
                return absent
        value = object_value(obj)
        return absent if value is None else value

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
        # a value the EDS leaves open reads 0 (a device always answers with something)
        for index, sub in self._unset:
            store.setdefault(index, {}).setdefault(sub, bytes(self._unset[index, sub]))
        if self._modes_unset:  # the EDS states no 0x6502: the modes its objects allow
            store.setdefault(cia402.SUPPORTED_DRIVE_MODES, {})[0] = struct.pack("<I", self.supported_modes)
        # one serial number per emulated drive (the EDS default would make every drive look alike)
        if self._has_serial:
            store.setdefault(cia402.IDENTITY, {})[4] = struct.pack("<I", self.node_id)
        for sub, raw in self._identity.items():
            store.setdefault(cia402.IDENTITY, {})[sub] = raw
        self._heartbeat_ms = self._od_default(cia402.PRODUCER_HEARTBEAT_TIME, absent=0)
        self._heartbeat_cycles = 0
        if self._consumer is not None:
            self.network.unsubscribe(HEARTBEAT_BASE + self._consumer[0], self._on_master_heartbeat)
        self._consumer, self._ms_since_master, self.master_lost = None, None, False
        self._rpdo_timeout_ms, self._ms_since_rpdo = 0, None
        self._syncs_since_rpdo = self._skipped_since_rpdo = 0  # what the deadline counted since the last RPDO
        self._deadline_comm = cia402.RPDO_COMM  # the RPDO whose event timer (0x14xx:05) was written last
        self._set_sync_cob(self._od_default(cia402.COB_ID_SYNC, absent=SYNC_COB_ID) & 0x7FF)
        self._errors.clear()
        if application:
            if self.master_clock != CLOCK_OWN:  # 0x5FFF:2 back to its power-on value
                self._set_master_clock(CLOCK_OWN)
            if cia402.RATED_TORQUE in self.od:
                store.setdefault(cia402.RATED_TORQUE, {})[0] = struct.pack("<I", round(self._rated_effort * 1000))
            self.scale = EffortScale(self._rated_effort)
            # without 0x6007 a lost master faults the drive (the reaction of most drives without the object)
            self._abort_option = self._od_default(cia402.ABORT_CONNECTION_OPTION, absent=1)
            self.max_torque = self._od_default(cia402.MAX_TORQUE, absent=NO_TORQUE_LIMIT)
            self.drive.quick_stop_option = self._od_default(cia402.QUICK_STOP_OPTION, absent=QUICK_STOP_DEFAULT)
            self._set_mode(self._od_default(cia402.MODES_OF_OPERATION, absent=0))
            self.controlword = 0
            self.setpoint = 0  # per mille of the rated effort, as received
            self.drive.restart()
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
        if self.nmt is NmtState.OPERATIONAL and self.drive.power in RUNNING:
            self._communication_lost(COMMUNICATION_ERROR, only_running=True)

    def _sdo_allowed(self) -> bool:
        return self.nmt in (NmtState.PRE_OPERATIONAL, NmtState.OPERATIONAL)


    # -- EMCY, faults and their reactions -----------------------------------------------------------------
    def _emcy(self, code: int) -> None:
        """EMCY with the live error register; none outside Pre-operational and Operational (CiA 301)."""
        if self.nmt in (NmtState.PRE_OPERATIONAL, NmtState.OPERATIONAL):
            self.node.emcy.send(code, self.error_register)

    def _clear_error(self, code: int) -> None:
        if code in self._errors:
            self._errors.discard(code)
            if not self._errors and self.drive.power not in FAULTED:
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
        running = d.power in RUNNING
        if only_running and not running:
            return
        if running and not self._reaction:
            self._reaction = code
        if self._abort_option == 1:
            self._errors.add(code)
            self.fault(code)
        elif self._abort_option in (2, 3) and running:
            d.disable_voltage(code)
            self._errors.add(code)
            self._emcy(code)


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

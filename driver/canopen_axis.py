"""CanopenAxis: the Axis protocol over a CiA 402 drive in cyclic synchronous torque mode.

Boot (NMT reset, boot-up awaited), identity 0x1018 checked against the configuration, configuration by
SDO (mode 10 = CST, PDO mapping through canopen's PdoMap, SYNC period, heartbeat), then once per cycle:
SYNC -> TPDOs in (statusword, position, velocity, torque) -> the controller -> RPDO out (controlword,
target torque in per mille of the rated effort; with the minimal mapping the controlword goes in an
event-driven RPDO2, sent when it changes, again each cycle while the drive has not reached the state
it asks for, and every 100 cycles). The CiA 402 state machine is stepped inside the
cycle from the tables of driver/cia402.py (never canopen's blocking BaseNode402 setters): enabling
takes two cycles, a fault reset is a rising edge of bit 7 verified by the next statusword.

Several axes on one bus share one :class:`SyncClock`: the first axis to read in a new cycle sends
the SYNC, the others read what it brought.

Faults it detects (each raised once as :class:`AxisError` with its :class:`FaultKind`): more than
``max_lost_cycles`` cycles in a row without the TPDOs (one lost or late cycle is bridged by
extrapolating the last sample, and counted); the drive's heartbeat silent for three periods; a
boot-up message from the drive while connected (it reset by itself); python-can raising on send or
receive (bus error, bus-off); frames it did not send on its own COB-IDs: an RPDO on this drive's
RPDO COB-ID (a second producer overrides the master's commands), a SYNC (the master is the bus's only
SYNC producer: another one changes the drive's rate), an NMT command, or a heartbeat saying the drive
left Operational (a second NMT master). A drive fault arrives as the statusword (and EMCY, kept in
``last_emcy``); the servo loop reacts to the power state.

Every received frame is checked before use (driver/frame_guard.py): a TPDO whose length is not the
mapping's is counted (``malformed_frames``) and its cycle bridged as a lost one.

When a stop is not confirmed by the drive (driver/safe_stop.py), the axis escalates through
:meth:`sdo_quick_stop`, :meth:`nmt_stop` and :meth:`last_resort`; :attr:`state_fresh` says whether
:attr:`power` is what the drive reported in this cycle (TPDO) or since (SDO), not a stale belief.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from pathlib import Path

import can
import canopen

from drivectl.driver import cia402
from drivectl.driver.axis import LAST_RESORTS, Axis, AxisConfigError, AxisError, FaultKind, Feedback
from drivectl.driver.axis_boot import AxisBoot, Identity
from drivectl.driver.axis_stop import AxisStop
from drivectl.driver.cia301 import (
    HEARTBEAT_BASE,
    NMT_COB_ID,
    RPDO_BASE,
    SYNC_COB_ID,
    TPDO_BASE,
    NmtCommand,
    NmtState,
)
from drivectl.driver.cia402 import MasterStateMachine, PowerState
from drivectl.driver.frame_guard import FrameGuard
from drivectl.driver.network import LockstepNetwork
from drivectl.driver.pdo import PdoLayout
from drivectl.driver.pdo_mappings import (  # noqa: F401 - re-exported: the mappings the master knows
    COMPACT_TPDO_ENTRIES,
    CW_REFRESH_CYCLES,
    CW_RESEND_CYCLES,
    MAPPINGS,
    MINIMAL_RPDO_ENTRIES,
    MINIMAL_TPDO_ENTRIES,
    RPDO_ENTRIES,
    TPDO_ENTRIES,
)
from drivectl.driver.sync_clock import SyncClock
from drivectl.driver.units import EffortScale, Encoder

__all__ = ["CanopenAxis", "Identity", "SyncClock"]

#: the states a heartbeat may report (CiA 301): boot-up, Stopped, Operational, Pre-operational
_HEARTBEAT_STATES = frozenset(int(s) for s in NmtState)

#: EMCY messages kept in canopen's consumer log (the newest; last_emcy is what the loop reads)
EMCY_KEPT = 32


class CanopenAxis(AxisBoot, AxisStop, Axis):
    """One CiA 402 drive behind the Axis protocol."""

    def __init__(
        self,
        network: canopen.Network,
        node_id: int,
        *,
        name: str,
        dt: float,
        effort_unit: str,
        eds: str | Path,
        encoder: Encoder,
        effort_scale: EffortScale,
        clock: SyncClock | None = None,
        identity: Identity | None = None,
        heartbeat_ms: int = 100,
        timeout: float = 2.0,
        tpdo_timeout: float = 0.1,
        max_lost_cycles: int = 3,
        rpdo_timeout_ms: int | None = None,
        max_effort: float = math.inf,
        last_resort: str = "nmt-reset",
        mapping: str = "full",
    ):
        self.name = name
        self.dt = dt
        self.effort_unit = effort_unit
        self.node_id = node_id
        self.network = network
        self.encoder = encoder
        self.scale = effort_scale
        self.clock = clock or SyncClock(network)
        self.timeout = timeout  # boot-up and SDO answers
        self.tpdo_timeout = tpdo_timeout  # a cycle's TPDOs, across processes (in lockstep they are there at once)
        self.heartbeat_ms = heartbeat_ms
        if max_lost_cycles < 0:
            raise ValueError(f"axis {name}: max_lost_cycles: must be >= 0, got {max_lost_cycles}")
        self.max_lost_cycles = max_lost_cycles
        if last_resort not in LAST_RESORTS:
            raise ValueError(f"axis {name}: last_resort: expected one of {', '.join(LAST_RESORTS)}, "
                             f"got {last_resort!r}")
        self.last_resort_action = last_resort
        if not max_effort > 0:
            raise ValueError(f"axis {name}: max_effort: must be > 0, got {max_effort}")
        # the drive clips the torque to 0x6072 on its own: the configured limit holds even if a
        # setpoint ever passed the master's clip (unlimited: the drive keeps its own setting)
        self.max_torque_permille = None if math.isinf(max_effort) else max(1, effort_scale.to_permille(max_effort))
        # the drive's RPDO deadline (0x1400:05): two cycles unless configured
        self.rpdo_timeout_ms = round(2 * dt * 1000) if rpdo_timeout_ms is None else rpdo_timeout_ms
        self.lockstep = isinstance(network, LockstepNetwork)
        try:
            od = canopen.import_od(str(eds), node_id)
        except Exception as exc:  # canopen raises many types for a bad file
            # configparser's messages run over several lines (a line per offending line): keep the first
            reason = (str(exc).strip().splitlines() or [type(exc).__name__])[0].rstrip(":")
            raise AxisConfigError(f"axis {name}: EDS {eds}: cannot be read: {reason}") from None
        missing = [f"0x{i:04X}" for i in cia402.REQUIRED_OBJECTS if i not in od]
        if missing:
            raise AxisConfigError(f"axis {name}: EDS {eds}: missing required object(s) {', '.join(missing)}")
        self.od = od
        self.identity = identity if identity is not None else Identity(
            od.device_information.vendor_number, od.device_information.product_number)
        self.node = canopen.RemoteNode(node_id, od)
        network.add_node(self.node)
        self.node.emcy.add_callback(self._on_emcy)
        self.master = MasterStateMachine(PowerState.SWITCH_ON_DISABLED)
        self.power = PowerState.NOT_READY_TO_SWITCH_ON
        self.statusword = 0
        self.error_code = 0
        self.lost_cycles = 0
        self.lost_total = 0
        self.late_total = 0
        self.last_emcy: tuple[int, int] | None = None  # (error code, cycle)
        self._rebooted = False
        self._last = Feedback(0.0, 0.0, 0.0)
        self._cycle = self.clock.cycle
        self._consumed = self.clock.cycle  # the cycle whose TPDOs the last read() used
        self._controlword = 0
        self._rpdo_cob = RPDO_BASE[0] + node_id
        if mapping not in MAPPINGS:
            raise ValueError(f"axis {name}: mapping: expected {', '.join(MAPPINGS)}, got {mapping!r}")
        self.mapping = mapping
        self._rpdo_entries = MINIMAL_RPDO_ENTRIES if mapping == "minimal" else (RPDO_ENTRIES,)
        self._rpdo = PdoLayout.from_entries(od, self._rpdo_entries[0])
        # minimal: the controlword's event-driven RPDO2, and the controlword it last carried (None: none yet,
        # so the first cycle after connect() sends it)
        self._cw_rpdo = PdoLayout.from_entries(od, self._rpdo_entries[1]) if mapping == "minimal" else None
        self._cw_cob = RPDO_BASE[1] + node_id
        self._cw_sent: int | None = None
        self._cw_age = 0  # cycles since the last RPDO2
        self._cw_resends = 0  # resends left while the drive has not reached the state the controlword asks for
        self._tpdo_entries = {"compact": COMPACT_TPDO_ENTRIES, "minimal": MINIMAL_TPDO_ENTRIES}.get(mapping,
                                                                                                  TPDO_ENTRIES)
        self._tpdo = [PdoLayout.from_entries(od, e) for e in self._tpdo_entries]
        self._tpdo_cob = [TPDO_BASE[i] + node_id for i in range(len(self._tpdo_entries))]
        self._fresh = [False] * len(self._tpdo_entries)
        self._raw = [tuple(0 for _ in e) for e in self._tpdo_entries]
        self._prev_counts: tuple[int, int] | None = None  # compact, minimal: (counts, cycle) of the last sample
        # made once: canopen's subscribe() skips a callback it holds, so reconnecting after a drive
        # reset does not stack a second handler per TPDO (each would count a late frame again)
        self._tpdo_handlers = [self._tpdo_callback(i) for i in range(len(self._tpdo_entries))]
        self._arrived = threading.Event()
        self._last_heartbeat = 0
        self.heartbeat_state: int | None = None
        self._booted = threading.Event()
        self._connected = False
        # frames checked before use (the network's guard when it has one: it also counts what it dropped)
        guard = getattr(network, "frame_guard", None)
        if guard is None:
            guard = network.frame_guard = FrameGuard()
        self.frame_guard: FrameGuard = guard
        #: frames nobody but the master may send, seen from someone else: (kind, what) of the first
        self._foreign: tuple[FaultKind, str] | None = None
        self._foreign_seen = False  # raised once per connection
        self._nmt_own = False  # the master itself took the drive out of Operational (a stop escalation)
        self._seen_operational = False  # the drive's heartbeat has said Operational since connect()
        #: :attr:`power` is the drive's own report of this cycle (TPDO) or of an SDO read since
        self.state_fresh = False
        self.state_source = ""  # "TPDO" or "SDO": where the last confirmed statusword came from

    # -- the cycle ---------------------------------------------------------------------------------
    def _tpdo_callback(self, i: int):
        codec = self._tpdo[i].codec
        size = codec.size
        fresh = self._fresh
        raw = self._raw

        def on_tpdo(can_id: int, data: bytes, timestamp: float) -> None:
            if len(data) != size:  # not the mapping's length: unusable, the cycle is bridged as lost
                self.frame_guard.reject(can_id, f"{len(data)} data bytes, the mapping has {size}", "tpdo-length")
                return
            if self._consumed == self.clock.cycle:
                self.late_total += 1  # for a cycle already used: too late, dropped
                return
            raw[i] = codec.unpack_from(data)
            fresh[i] = True
            if all(fresh):
                self._arrived.set()

        return on_tpdo

    def _on_heartbeat(self, can_id: int, data: bytes, timestamp: float) -> None:
        if len(data) != 1:  # the guard drops these on our networks; a bare canopen Network may not
            self.frame_guard.reject(can_id, f"{len(data)} data bytes, CiA 301 says 1")
            return
        state = data[0]
        if state not in _HEARTBEAT_STATES:  # not a state CiA 301 knows: a garbled frame, not a report
            self.frame_guard.reject(can_id, f"heartbeat state 0x{state:02X} is no NMT state", "heartbeat-state")
            return
        self._last_heartbeat = self.clock.cycle
        self.heartbeat_state = state
        if not self._connected:
            return
        if state == 0:
            self._awaiting_boot = False
            self._rebooted = True  # a boot-up while we run the drive: it reset by itself
        elif state == NmtState.OPERATIONAL:
            self._seen_operational = True
        elif self._seen_operational and not self._nmt_own and self._foreign is None:
            # the drive left Operational and the master did not ask it to: another NMT master did
            # (its command may not have reached us; the heartbeat always does)
            names = {int(s): s.name.replace("_", "-").lower() for s in NmtState}
            self._foreign = (FaultKind.FOREIGN_NMT, f"the drive's heartbeat says {names.get(state, hex(state))} "
                             "(the master did not command it: a second NMT master?)")

    @property
    def foreign_kind(self) -> FaultKind | None:
        """The rogue producer or foreign NMT seen since connect() (None: none)."""
        return self._foreign[0] if self._foreign is not None else None

    @property
    def _watched_cobs(self) -> tuple[int, ...]:
        if self._cw_rpdo is not None:
            return (self._rpdo_cob, self._cw_cob, SYNC_COB_ID, NMT_COB_ID)
        return (self._rpdo_cob, SYNC_COB_ID, NMT_COB_ID)

    def _on_foreign(self, can_id: int, data: bytes, timestamp: float) -> None:
        """A frame on a COB-ID only the master sends (it never receives its own): someone else sent it."""
        if not self._connected or self._foreign is not None:
            return
        if can_id == self._rpdo_cob or (can_id == self._cw_cob and self._cw_rpdo is not None):
            self._foreign = (FaultKind.ROGUE_RPDO, f"an RPDO on 0x{can_id:03X} that the master did not send "
                             "(a second producer: the drive takes whichever came last)")
        elif can_id == SYNC_COB_ID:
            self._foreign = (FaultKind.ROGUE_SYNC, "a SYNC that the master did not send (a second SYNC producer: "
                             "the drive steps at the wrong rate)")
        elif len(data) == 2 and data[1] in (0, self.node_id):
            names = {int(c): c.name.replace("_", " ").lower() for c in NmtCommand}
            self._foreign = (FaultKind.FOREIGN_NMT, f"NMT {names.get(data[0], f'0x{data[0]:02X}')} to "
                             f"{'all nodes' if data[1] == 0 else f'node {data[1]}'} from another master")
            if data[0] == NmtCommand.STOP:
                self.heartbeat_state = int(NmtState.STOPPED)  # it will not answer SDO (see _sdo)
            elif data[0] in (NmtCommand.RESET_NODE, NmtCommand.RESET_COMMUNICATION):
                self._awaiting_boot = True  # it answers no SDO until its boot-up (see _sdo)

    def _on_emcy(self, entry: canopen.emcy.EmcyError) -> None:
        self.last_emcy = (entry.code, self.clock.cycle)
        # canopen keeps every EMCY in log (and active, until an error reset) for ever: bound both, so a
        # drive that repeats its EMCY for hours does not grow the master's memory
        emcy = self.node.emcy
        with emcy.emcy_received:
            del emcy.log[:-EMCY_KEPT]
            del emcy.active[:-EMCY_KEPT]

    def read(self) -> Feedback:
        """Next cycle: SYNC (unless another axis of this bus sent it), then this drive's TPDOs."""
        if not self._connected:
            raise AxisError(f"axis {self.name}: not connected")
        if self._cycle == self.clock.cycle:
            self._fresh[:] = [False] * len(self._fresh)
            self._arrived.clear()
            try:
                self.clock.tick()
            except can.CanError as exc:
                raise AxisError(f"axis {self.name}: SYNC not sent: {exc}", FaultKind.BUS_ERROR) from None
        self._cycle = cycle = self.clock.cycle
        self.state_fresh = False
        if not all(self._fresh) and not self.lockstep:
            self._arrived.wait(self.tpdo_timeout)
        self._consumed = cycle
        if self._foreign is not None and not self._foreign_seen:
            self._foreign_seen = True  # raised once; the stop that follows must still cycle
            kind, what = self._foreign
            raise AxisError(f"axis {self.name}: node {self.node_id}: {what}", kind)
        if self._rebooted:
            self._rebooted = False
            raise AxisError(f"axis {self.name}: node {self.node_id}: unexpected boot-up (the drive reset by itself; "
                            "its configuration is lost)", FaultKind.UNEXPECTED_BOOT)
        silent_ms = (cycle - self._last_heartbeat) * self.dt * 1000.0
        if self.heartbeat_ms and silent_ms > 3 * self.heartbeat_ms:
            self._last_heartbeat = cycle  # raised once; the stop that follows must still cycle
            raise AxisError(f"axis {self.name}: node {self.node_id}: heartbeat lost ({silent_ms:.0f} ms without one, "
                            f"period {self.heartbeat_ms} ms)", FaultKind.HEARTBEAT_LOST)
        fresh = self._fresh
        if all(fresh):
            self.lost_cycles = 0
            for i in range(len(fresh)):
                fresh[i] = False
            enc = self.encoder
            if self._prev_counts is None:
                (sw, counts), (vel_counts, _torque) = self._raw
                velocity = enc.from_counts(vel_counts)
            else:  # compact, minimal: the velocity from this position and the last one (as SimAxis derives it)
                sw, counts = self._raw[0][:2]
                velocity = enc.velocity(counts, self._prev_counts[0], (cycle - self._prev_counts[1]) * self.dt)
                self._prev_counts = (counts, cycle)
            self.statusword = sw
            self.power = cia402.decode_statusword(sw)
            self.state_fresh, self.state_source = True, "TPDO"
            self._controlword = self.master.controlword(self.power)
            fb = self._last = Feedback((cycle - 1) * self.dt, enc.from_counts(counts), velocity)
            return fb
        # no (complete) sample: bridge the cycle by extrapolating the last one; too many in a row is a fault
        self.lost_cycles += 1
        self.lost_total += 1
        for i in range(len(fresh)):
            fresh[i] = False
        if self.lost_cycles > self.max_lost_cycles:
            raise AxisError(f"axis {self.name}: node {self.node_id}: no TPDO for {self.lost_cycles} cycles "
                            f"(limit {self.max_lost_cycles})", FaultKind.TPDO_TIMEOUT)
        last = self._last
        fb = self._last = Feedback((cycle - 1) * self.dt, last.position + last.velocity * self.dt, last.velocity)
        return fb

    @property
    def torque_actual(self) -> float:
        """0x6077 of the latest TPDOs, in the effort unit (NaN when the mapping does not carry it)."""
        if self.mapping == "minimal":
            return math.nan
        try:
            return self.scale.from_permille(self._raw[0][2] if self.mapping == "compact" else self._raw[1][1])
        except (IndexError, TypeError):
            return math.nan

    def refresh_state(self) -> PowerState:
        """The power state by SDO (0x6041), when the TPDOs do not bring it."""
        self.statusword = self._sdo(cia402.STATUSWORD)
        self.power = cia402.decode_statusword(self.statusword)
        self.state_fresh, self.state_source = True, "SDO"
        self._controlword = self.master.controlword(self.power)
        return self.power

    @property
    def counters(self) -> dict[str, int]:
        """Cycles bridged for lack of TPDOs, TPDO frames that came too late, and the frames the master
        dropped as malformed (wrong length, remote; this drive's and the broadcast NMT/SYNC; cumulative)."""
        return {"tpdo_lost_cycles": self.lost_total, "tpdo_late_frames": self.late_total,
                "malformed_frames": self.frame_guard.count(self.node_id) + self.frame_guard.count(0)}


    def write(self, effort: float) -> None:
        try:
            if self._cw_rpdo is None:
                self.network.send_message(self._rpdo_cob, self._rpdo.codec.pack(self._controlword,
                                                                                   self.scale.to_permille(effort)))
                return
            cw = self._controlword
            self._cw_age += 1
            # minimal: the controlword when it changes (in the same cycle); then again each cycle while the drive
            # has not reached the state it asks for (a lost frame must not stall a transition: CW_RESEND_CYCLES,
            # the cycles a master waits for one), and every CW_REFRESH_CYCLES whatever (a lost halt or reset edge)
            if cw != self._cw_sent:
                self._cw_resends = CW_RESEND_CYCLES
                self._send_cw(cw)
            elif self._cw_age >= CW_REFRESH_CYCLES:
                self._send_cw(cw)
            elif self._cw_resends and self.power is not self.master.target:
                self._cw_resends -= 1
                self._send_cw(cw)
            self.network.send_message(self._rpdo_cob, self._rpdo.codec.pack(self.scale.to_permille(effort)))
        except can.CanError as exc:
            raise AxisError(f"axis {self.name}: RPDO not sent: {exc}", FaultKind.BUS_ERROR) from None

    def _send_cw(self, cw: int) -> None:
        self.network.send_message(self._cw_cob, self._cw_rpdo.codec.pack(cw))
        self._cw_sent, self._cw_age = cw, 0

    # -- power state targets (reached through the following cycles) ----------------------------------
    def enable(self) -> None:
        if self.power is PowerState.FAULT:
            raise AxisError(f"axis {self.name}: node {self.node_id}: in Fault "
                            f"({cia402.error_text(self.read_error_code())}), fault-reset first")
        self._target(PowerState.OPERATION_ENABLED)

    def disable(self) -> None:
        self._target(PowerState.SWITCH_ON_DISABLED)

    def quick_stop(self) -> None:
        self._target(PowerState.QUICK_STOP_ACTIVE)

    def fault_reset(self) -> None:
        self.master.request_fault_reset()
        self._target(PowerState.SWITCH_ON_DISABLED)

    def _target(self, target: PowerState) -> None:
        self.master.target = target
        self._controlword = self.master.controlword(self.power)

    def pace(self, wall: Callable[[], float] | None) -> None:
        """A run paced on the wall clock ``wall`` starts (None: it ended). In-process (lockstep) the emulated
        drives on this bus then run on that clock, as they do across processes (driver/network.Lockstep.pace);
        across processes a drive has its own clock and nothing changes."""
        if self.lockstep:
            self.network.lockstep.pace(wall)

    def read_digital_inputs(self) -> int:
        """0x60FD by SDO (the drive's switches; homing reads them)."""
        return int(self.node.sdo[cia402.DIGITAL_INPUTS].raw)

    def read_error_code(self) -> int:
        """0x603F by SDO."""
        self.error_code = self._sdo(cia402.ERROR_CODE)
        return self.error_code

    def close(self) -> None:
        subs = self.network.subscribers
        for cob, handler in [*zip(self._tpdo_cob, self._tpdo_handlers, strict=True),
                             (HEARTBEAT_BASE + self.node_id, self._on_heartbeat),
                             *((c, self._on_foreign) for c in self._watched_cobs)]:
            if handler in subs.get(cob, ()):  # only ours: another listener on the COB-ID stays
                self.network.unsubscribe(cob, handler)
        if self._connected:
            try:
                self.network.send_message(NMT_COB_ID, bytes([NmtCommand.ENTER_PRE_OPERATIONAL, self.node_id]))
            except Exception:  # noqa: BLE001 - the bus may already be gone
                pass
        self._connected = False

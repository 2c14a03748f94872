"""CanopenAxis: the Axis protocol over a CiA 402 drive in a torque mode.

What the drive offers decides the bring-up (driver/capabilities.py: the essentials, else one line before
anything moves; cyclic synchronous torque, else profile torque with synchronous RPDOs; the fallback for
each optional object said at boot) and the PDOs it carries (driver/pdo_plan.py, within the drive's
limits). Boot (axis_boot.py: NMT reset, boot-up awaited), identity 0x1018 checked against the
configuration, configuration by SDO (the mode, the ``sdo_init`` writes, the PDO plan, SYNC period and
heartbeat where the drive has them), then once per cycle:
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
from collections.abc import Callable, Sequence
from pathlib import Path

import can
import canopen

from drivectl.driver import cia402
from drivectl.driver.axis import LAST_RESORTS, Axis, AxisConfigError, AxisError, FaultKind, Feedback
from drivectl.driver.axis_boot import AxisBoot, Identity, IdentityCheck
from drivectl.driver.axis_stop import AxisStop
from drivectl.driver.capabilities import DriveRefused, assess
from drivectl.driver.cia301 import (
    HEARTBEAT_BASE,
    NMT_COB_ID,
    SYNC_COB_ID,
    NmtCommand,
    NmtState,
)
from drivectl.driver.cia402 import MasterStateMachine, PowerState
from drivectl.driver.emulator_clock import CLOCK_OWN, CLOCK_SLOTS
from drivectl.driver.enable_check import enable_blocker
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
from drivectl.driver.pdo_plan import PdoPlan
from drivectl.driver.pdo_plan import plan as plan_pdos
from drivectl.driver.running_time import RunningTimeSdoClient, wait_running
from drivectl.driver.sync_clock import SyncClock
from drivectl.driver.units import EffortScale, Encoder

__all__ = ["CanopenAxis", "Identity", "IdentityCheck", "SyncClock"]

#: the states a heartbeat may report (CiA 301): boot-up, Stopped, Operational, Pre-operational
_HEARTBEAT_STATES = frozenset(int(s) for s in NmtState)

#: what a cyclic RPDO's entry carries: the controlword, the target torque, or zero (a dummy, or an object a
#: fixed mapping adds)
_RX_CW, _RX_TT, _RX_ZERO = 0, 1, 2
_RX_KIND = {cia402.CONTROLWORD: _RX_CW, cia402.TARGET_TORQUE: _RX_TT}

#: EMCY messages kept in canopen's consumer log (the newest; last_emcy is what the loop reads)
EMCY_KEPT = 32
#: lockstep across processes: how long a cycle waits for its TPDOs (s of this process's running time) before it is
#: one error (a host 60 times slower than this one answers a SYNC in some 50 ms)
LOCKSTEP_WAIT_S = 10.0


class _Node(canopen.RemoteNode):
    """canopen's remote node whose SDO answers are waited for in this process's running time
    (driver/running_time.py): a stalled host is not a silent drive."""

    def add_sdo(self, rx_cobid: int, tx_cobid: int) -> RunningTimeSdoClient:
        client = RunningTimeSdoClient(rx_cobid, tx_cobid, self.object_dictionary)
        self.sdo_channels.append(client)
        if self.has_network():
            self.network.subscribe(client.tx_cobid, client.on_response)
        return client


def _no_wall() -> float:
    return 0.0


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
        identity: Identity | IdentityCheck | None = None,
        heartbeat_ms: int = 100,
        timeout: float = 2.0,
        tpdo_timeout: float = 0.1,
        max_lost_cycles: int = 3,
        rpdo_timeout_ms: int | None = None,
        max_effort: float = math.inf,
        last_resort: str = "nmt-reset",
        mapping: str = "full",
        rated_effort_source: str | None = "the configuration",
        sdo_init: Sequence[tuple[int, int, int]] = (),
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
        # the floors of the timeouts adapted to the drive's measured answer time at connect() (_adapt_to_peer)
        self._tpdo_timeout = tpdo_timeout
        self._unpaced_wait = tpdo_timeout
        self._unpaced_wall: float | None = None  # the drive's SYNC tolerance bounds it (_adapt_to_peer)
        self._paced = False  # a run paced on the wall clock is under way (pace())
        self._wall: Callable[[], float] = _no_wall
        self._tpdo_budget = tpdo_timeout  # a paced cycle's wait for its TPDOs after its SYNC (pace())
        self.peer_rtt: float | None = None
        self.heartbeat_ms = heartbeat_ms
        if max_lost_cycles < 0:
            raise ValueError(f"axis {name}: max_lost_cycles: must be >= 0, got {max_lost_cycles}")
        self.max_lost_cycles = max_lost_cycles
        self._lost_limit = max_lost_cycles  # what read() faults past: max_lost_cycles, or from the deadline (pace())
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
        self.lockstep = self.in_process = isinstance(network, LockstepNetwork)
        #: lockstep across processes (set before connect(): open_machine(lockstep=True)): every SYNC's TPDOs are
        #: waited for, up to ``lockstep_wait`` s of this process's running time, then one error (never bridged);
        #: the emulated drive is told so (0x5FFF:2) and a real drive is refused at connect()
        self.lockstep_peer = False
        self.lockstep_wait = LOCKSTEP_WAIT_S
        self._lockstep_gone = False  # its wait ran out once: the stop that follows bridges as usual
        self._emulator: bool | None = None  # is the node drivectl's emulated drive (is_emulator)
        try:
            od = canopen.import_od(str(eds), node_id)
        except Exception as exc:  # canopen raises many types for a bad file
            # configparser's messages run over several lines (a line per offending line): keep the first
            reason = (str(exc).strip().splitlines() or [type(exc).__name__])[0].rstrip(":")
            raise AxisConfigError(f"axis {name}: EDS {eds}: cannot be read: {reason}") from None
        where = f"axis {name}: EDS {eds}"
        if mapping not in MAPPINGS:
            raise ValueError(f"axis {name}: mapping: expected {', '.join(MAPPINGS)}, got {mapping!r}")
        # what the drive offers (the essentials, else one line and nothing moves) and the PDOs it can carry
        self.capabilities = assess(od, where)
        self.pdo_plan = plan_pdos(od, mapping, node_id, where)
        if not self.capabilities.rated_effort_from_drive and rated_effort_source is None:
            raise DriveRefused(f"{where}: drive has no rated torque 0x6076: set axes.{name}.rated_effort (the effort "
                               "of 1000 per mille of 0x6071, from the motor's data) in the configuration")
        self.rated_effort_source = rated_effort_source
        self.sdo_init = tuple(sdo_init)
        self.boot_notes: list[str] = []  # what the boot chose and what the drive lacks (said at boot)
        self.mode: int | None = None  # the mode of operation the boot chose (driver/axis_boot.py)
        self._awaiting_boot = False  # a reset another master sent: SDO waits for the boot-up
        self._sent_stop = False  # our NMT Stop is out: the state is asked after Pre-operational
        self.od = od
        # what 0x1018 must say: given, else the configuration's check against the EDS's [DeviceInfo]
        self.identity = identity if isinstance(identity, Identity) else (identity or IdentityCheck()).against(
            od.device_information)
        self.identity_answered: tuple[int | None, ...] | None = None  # 0x1018:1-3 as read at boot
        self.node = _Node(node_id, od)
        self._sdo_timeout = self.node.sdo.RESPONSE_TIMEOUT  # canopen's default (0.3 s)
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
        self._last_cycle = 1  # the cycle of the last sample (a bridged one extrapolates from it)
        self._cycle = self.clock.cycle
        self._consumed = self.clock.cycle  # the cycle whose TPDOs the last read() used
        self._controlword = 0
        self.mapping = mapping
        self._setup_pdos(self.pdo_plan)
        # made once: canopen's subscribe() skips a callback it holds, so reconnecting after a drive
        # reset does not stack a second handler per TPDO (each would count a late frame again)
        self._arrived = threading.Event()
        self._tpdo_handlers = [self._tpdo_callback(i) for i in range(len(self._tpdo))]
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

    def _setup_pdos(self, plan: PdoPlan) -> None:
        """The per-cycle structures of the PDO plan: what each cyclic RPDO carries, where the statusword,
        position, velocity and torque actual sit in the TPDOs."""
        od = self.od
        self._cyclic_rx: list[tuple[int, object, tuple[int, ...]]] = []
        self._cw_rpdo = None  # minimal: the controlword's event-driven RPDO (None: it rides a cyclic one)
        self._cw_cob = 0
        for p in plan.rx:
            layout = PdoLayout.from_entries(od, p.entries)
            if p.trans_type > 240:
                self._cw_rpdo, self._cw_cob = layout, p.cob_id
                continue
            kinds = tuple(_RX_KIND.get(e[0], _RX_ZERO) for e in p.entries)
            self._cyclic_rx.append((p.cob_id, layout.codec, kinds))
        self._rx_cobs = tuple(p.cob_id for p in plan.rx)
        # the controlword the event-driven RPDO last carried (None: none yet, so the first cycle after connect()
        # sends it)
        self._cw_sent: int | None = None
        self._cw_age = 0  # cycles since the last controlword RPDO
        self._cw_resends = 0  # resends left while the drive has not reached the state the controlword asks for
        self._tpdo = [PdoLayout.from_entries(od, p.entries) for p in plan.tx]
        self._tpdo_cob = [p.cob_id for p in plan.tx]
        self._fresh = [False] * len(self._tpdo)
        self._none_fresh = tuple(self._fresh)
        # across processes, per TPDO: the SYNC (SyncClock.syncs) its last frame answered, the SYNC up to which the
        # loop wrote answers off as lost, the SYNC at which a frame was taken for an earlier SYNC's (on_tpdo)
        self._answered = [0] * len(self._tpdo)
        self._written_off = [0] * len(self._tpdo)
        self._owed_at = [-1] * len(self._tpdo)
        self._raw = [tuple(0 for _ in layout.entries) for layout in self._tpdo]
        at = {e: (i, j) for i, p in enumerate(plan.tx) for j, e in enumerate(p.entries)}
        self._at_sw = at[(cia402.STATUSWORD, 0)]
        self._at_pos = at[(cia402.POSITION_ACTUAL, 0)]
        self._at_vel = at.get((cia402.VELOCITY_ACTUAL, 0))
        self._at_tq = at.get((cia402.TORQUE_ACTUAL, 0))
        self._prev_counts: tuple[int, int] | None = None  # velocity derived: (counts, cycle) of the last sample

    # -- the cycle ---------------------------------------------------------------------------------
    def _tpdo_callback(self, i: int):
        codec = self._tpdo[i].codec
        size = codec.size
        fresh = self._fresh
        raw = self._raw

        unpack = codec.unpack_from
        clock = self.clock
        # in lockstep the frames arrive on the reading thread, before read() looks: no event to wake it
        arrived = None if self.lockstep else self._arrived

        answered, written_off, owed_at = self._answered, self._written_off, self._owed_at

        def on_tpdo(can_id: int, data: bytes, timestamp: float) -> None:
            if len(data) != size:  # not the mapping's length: unusable, the cycle is bridged as lost
                self.frame_guard.reject(can_id, f"{len(data)} data bytes, the mapping has {size}", "tpdo-length")
                return
            if arrived is not None:
                # across processes a drive answers its SYNCs in order, and an answer may come after the master's
                # next SYNC. Right after a late wake-up (clock.late_sync) the answers of the SYNCs since this TPDO's
                # last one are still owed: this frame is the oldest of them, not this cycle's sample (taken as it
                # was, the loop ran a cycle behind on a position slots old). Otherwise a missing answer was lost.
                s = clock.bus_syncs()
                a = answered[i]
                if a < written_off[i]:
                    a = written_off[i]
                if a < s - 1 and clock.late_sync == s:
                    answered[i] = a + 1
                    owed_at[i] = s
                    self.late_total += 1
                    return
                answered[i] = s
            if self._consumed == clock.cycle:
                self.late_total += 1  # for a cycle already used: too late, dropped
                return
            raw[i] = unpack(data)
            fresh[i] = True
            if arrived is not None and all(fresh):
                arrived.set()

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
        return (*self._rx_cobs, SYNC_COB_ID, NMT_COB_ID)

    def _on_foreign(self, can_id: int, data: bytes, timestamp: float) -> None:
        """A frame on a COB-ID only the master sends (it never receives its own): someone else sent it."""
        if not self._connected or self._foreign is not None:
            return
        if can_id in self._rx_cobs:
            self._foreign = (FaultKind.ROGUE_RPDO, f"an RPDO on 0x{can_id:03X} that the master did not send "
                             "(a second producer: the drive takes whichever came last)")
        elif can_id == SYNC_COB_ID:
            if self.clock.periodic is not None:
                return  # the transport's own SYNC; a second producer shows as a doubled rate (read())
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
        clock = self.clock
        if self._cycle == clock.cycle:
            self._fresh[:] = self._none_fresh
            if not self.lockstep:  # in lockstep nobody waits on it (on_tpdo)
                self._arrived.clear()
            try:
                clock.tick()
            except can.CanError as exc:
                raise AxisError(f"axis {self.name}: SYNC not sent: {exc}", FaultKind.BUS_ERROR) from None
            if self._paced:  # the cycle's TPDO waits, every axis's, end at one time after this SYNC
                clock.ticked_at = self._wall()
        self._cycle = cycle = clock.cycle
        if clock.periodic is not None and clock.periodic.rogue and self._foreign is None:
            self._foreign = (FaultKind.ROGUE_SYNC, "SYNCs closer than half a period apart (a second SYNC producer "
                             "beside the transport's periodic one: the drive steps at the wrong rate)")
        self.state_fresh = False
        if not all(self._fresh) and not self.lockstep:
            # only the axis that sends the SYNC clears the event at its tick: the others clear it here, then
            # look again (a TPDO marks itself fresh before it sets the event, so none is missed between)
            self._arrived.clear()
            if all(self._fresh):
                pass
            elif self._paced:  # a deadline on the wall clock: a late drive is waited for (the loop is then late
                # and resynchronises) until the cycle's TPDO budget after its SYNC, shared by the bus's axes;
                # then the cycle is bridged, and the next RPDO still reaches the drive in time (docs/timing.md)
                left = clock.ticked_at + self._tpdo_budget - self._wall()
                if left > 0:
                    self._arrived.wait(left)
            elif self.lockstep_peer and not self._lockstep_gone:  # lockstep across processes: every SYNC's TPDOs
                # (the drive's time is the SYNC count: it does not miss us however long we wait)
                if not wait_running(self._arrived, self.lockstep_wait) and not all(self._fresh):
                    self._lockstep_gone = True
                    self._consumed = cycle
                    raise AxisError(f"axis {self.name}: node {self.node_id}: no TPDO for SYNC {clock.syncs} within "
                                    f"{self.lockstep_wait:g} s (clock lockstep across processes: the drive or its "
                                    "link is gone)", FaultKind.TPDO_TIMEOUT)
            else:  # no deadline: the drive gets the wait in this process's running time (a stall is not its)
                wait_running(self._arrived, self._unpaced_wait, wall_limit=self._unpaced_wall)
            syncs = clock.syncs
            for n, at in enumerate(self._owed_at):
                if at == syncs and not self._fresh[n]:
                    # a frame came that was taken for an earlier SYNC's, and none after it: that one may as well
                    # have been this SYNC's, the earlier lost. The count starts again from here (the cycle is
                    # bridged), so one lost frame never makes every later answer look owed
                    self._written_off[n] = syncs
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
            fresh[:] = self._none_fresh
            enc = self.encoder
            raw = self._raw
            (si, sj), (pi, pj) = self._at_sw, self._at_pos
            sw, counts = raw[si][sj], raw[pi][pj]
            if self._at_vel is not None:
                vi, vj = self._at_vel
                velocity = enc.from_counts(raw[vi][vj])
            else:  # velocity derived from this position and the last one (as SimAxis derives it)
                velocity = enc.velocity(counts, self._prev_counts[0], (cycle - self._prev_counts[1]) * self.dt)
                self._prev_counts = (counts, cycle)
            self.statusword = sw
            self.power = cia402.decode_statusword(sw)
            self.state_fresh, self.state_source = True, "TPDO"
            self._controlword = self.master.controlword(self.power)
            fb = self._last = Feedback((cycle - 1) * self.dt, enc.from_counts(counts), velocity)
            self._last_cycle = cycle
            return fb
        # no (complete) sample: bridge the cycle by extrapolating the last one; too many in a row is a fault
        self.lost_cycles += 1
        self.lost_total += 1
        fresh[:] = self._none_fresh
        if self.lost_cycles > self._lost_limit:
            raise AxisError(f"axis {self.name}: node {self.node_id}: no TPDO for {self.lost_cycles} cycles "
                            f"(limit {self._lost_limit})", FaultKind.TPDO_TIMEOUT)
        last = self._last
        # over every slot since the last sample: a late wake-up's skipped ones included
        since, self._last_cycle = (cycle - self._last_cycle) * self.dt, cycle
        fb = self._last = Feedback((cycle - 1) * self.dt, last.position + last.velocity * since, last.velocity)
        return fb

    def stale(self) -> None:
        """The frame taken for this cycle's sample answered the SYNC before (the cycle found it by the position:
        controllers/runtime/cycle.py ``bridge``): a drive late past the budget twice running, which the count
        cannot tell from one lost answer. Counted as a late frame and a bridged cycle, with the same limit."""
        self.late_total += 1
        self.lost_total += 1
        self.lost_cycles += 1
        if self.lost_cycles > self._lost_limit:
            raise AxisError(f"axis {self.name}: node {self.node_id}: no TPDO for {self.lost_cycles} cycles "
                            f"(limit {self._lost_limit})", FaultKind.TPDO_TIMEOUT)

    @property
    def torque_actual(self) -> float:
        """0x6077 of the latest TPDOs, in the effort unit (NaN when the mapping does not carry it)."""
        if self._at_tq is None:
            return math.nan
        i, j = self._at_tq
        try:
            return self.scale.from_permille(self._raw[i][j])
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
            cw = self._controlword
            if self._cw_rpdo is not None:
                self._cw_age += 1
                # the controlword when it changes (in the same cycle); then again each cycle while the drive has not
                # reached the state it asks for (a lost frame must not stall a transition: CW_RESEND_CYCLES, the
                # cycles a master waits for one), and every CW_REFRESH_CYCLES whatever (a lost halt or reset edge)
                if cw != self._cw_sent:
                    self._cw_resends = CW_RESEND_CYCLES
                    self._send_cw(cw)
                elif self._cw_age >= CW_REFRESH_CYCLES:
                    self._send_cw(cw)
                elif self._cw_resends and self.power is not self.master.target:
                    self._cw_resends -= 1
                    self._send_cw(cw)
            pick = (cw, self.scale.to_permille(effort), 0).__getitem__
            send = self.network.send_message
            for cob, codec, kinds in self._cyclic_rx:
                send(cob, codec.pack(*map(pick, kinds)))
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
        elif wall is not None:
            self.clock.start_periodic(self.dt)  # where the transport can: the SYNC off the Python thread
        else:
            self.clock.stop_periodic()
        if not self.in_process and not self.lockstep_peer:
            self._tell_slots(wall is not None)
        self._paced = wall is not None
        self._wall = wall or _no_wall
        self._lost_limit, self._tpdo_budget = self.max_lost_cycles, self.tpdo_timeout
        if wall is not None and not self.lockstep and self.rpdo_timeout_ms > 0:
            # across processes on the wall clock a cycle bridged for want of its TPDOs is mostly a late drive or
            # host: the axis's deadline bounds it, as it bounds a late setpoint (docs/timing.md), never less
            # than the configured count; in lockstep the frames come at once, and a missing one is lost
            deadline = self.rpdo_timeout_ms * 1e-3
            self._lost_limit = max(self.max_lost_cycles, int(deadline / self.dt + 1e-9) - 1)
            self._tpdo_budget = min(self.tpdo_timeout, 0.5 * deadline)

    def _tell_slots(self, on: bool) -> None:
        """A paced run across processes: drivectl's emulated drive steps by the master's slots, which the SYNC's
        counter byte carries, a late wake-up's skipped ones included (driver/emulator_clock.py CLOCK_SLOTS), so
        its plant moves on while the master is late as a real drive's does. Only while every drive on this clock
        answered drivectl's mark (a real drive sees no counter); unanswered, the drive stays SYNC-locked."""
        clock = self.clock
        if not on:
            clock.slot_counter = False
            clock.slot_vetoed = False
        elif not self.is_emulator():
            clock.slot_counter, clock.slot_vetoed = False, True
        try:
            self.tell_clock(CLOCK_SLOTS if on and not clock.slot_vetoed else CLOCK_OWN)
        except (canopen.SdoAbortedError, canopen.SdoCommunicationError, can.CanError):
            return  # the drive may be gone: its own watchdogs stop it
        if on and not clock.slot_vetoed:
            clock.slot_counter = True

    def watch_sync(self, slip: Callable[[float | None], int] | None) -> None:
        self.clock.slip = slip  # the bus's axes share the clock, each says the same

    def skip(self, slots: int) -> None:
        self.clock.skip(slots)  # the bus's axes share the clock, each says the same: set, not added

    def enable_blocker(self) -> str:
        """Why the drive is not Operation Enabled, from what it reports now by SDO (statusword, 0x603F or the last
        EMCY, 0x6061): driver/enable_check.py."""
        def read(index: int) -> int | None:
            if index not in self.od:
                return None
            try:
                return self._sdo(index)
            except AxisError:
                return None

        sw = read(cia402.STATUSWORD)
        if sw is None:
            return f"node {self.node_id}: no statusword by SDO (the drive does not answer)"
        return enable_blocker(sw, error_code=read(cia402.ERROR_CODE),
                              emcy_code=self.last_emcy[0] if self.last_emcy else None,
                              mode_display=read(cia402.MODES_OF_OPERATION_DISPLAY), mode=self.mode)

    def read_digital_inputs(self) -> int:
        """0x60FD by SDO (the drive's switches; homing reads them)."""
        return int(self.node.sdo[cia402.DIGITAL_INPUTS].raw)

    def read_error_code(self) -> int:
        """0x603F by SDO."""
        self.error_code = self._sdo(cia402.ERROR_CODE)
        return self.error_code

    def close(self) -> None:
        self.clock.stop_periodic()
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

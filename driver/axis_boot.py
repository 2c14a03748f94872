"""The CiA 402 master's boot and configuration of one drive, before the cycle runs (a mixin of
canopen_axis.CanopenAxis): NMT reset and boot-up, identity 0x1018, mode and PDO mapping by SDO, NMT start."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

import can
import canopen
from canopen import objectdictionary as odt

from drivectl.driver import cia402
from drivectl.driver.axis import AxisConfigError, AxisError, FaultKind, Feedback
from drivectl.driver.capabilities import MODE_NAMES, choose_mode, refuse_mode
from drivectl.driver.cia301 import (
    HEARTBEAT_BASE,
    MASTER_NODE_ID,
    NMT_COB_ID,
    NmtCommand,
    NmtState,
)
from drivectl.driver.emulator_clock import CLOCK_LOCKSTEP, CLOCK_SUB, EMULATOR_MARK, EMULATOR_OBJECT, MARK_SUB
from drivectl.driver.pdo_plan import entry_bits
from drivectl.driver.running_time import wait_running

#: timeouts across processes are this many times the drive's measured SDO round trip (at least the defaults)
PEER_RTT_FACTOR = 10.0


@dataclass(frozen=True)
class Identity:
    """What 0x1018 must say (None: not checked); ``source`` names the configuration it comes from (the file
    whose line to change on a mismatch), None where no file states it."""

    vendor_id: int | None = None
    product_code: int | None = None
    revision: int | None = None
    source: str | None = None

    def lines(self) -> str:
        """The expectation as said: ``vendor 0x.. product 0x..`` or ``nothing (identity = "off")``."""
        said = ", ".join(f"{n} 0x{v:08X}" for n, v in zip(_ID_NAMES, self._values(), strict=False) if v is not None)
        return said or "nothing (no identity check)"

    def _values(self) -> tuple[int | None, int | None, int | None]:
        return self.vendor_id, self.product_code, self.revision


_ID_NAMES = ("vendor", "product", "revision")
#: [axes.NAME] identity: what the boot compares of 0x1018 (docs/drives.md); revision: vendor, product and revision
IDENTITY_CHECKS = ("vendor+product", "vendor", "revision", "off")


@dataclass(frozen=True)
class IdentityCheck:
    """The configuration's identity check: which fields (``check``, one of :data:`IDENTITY_CHECKS`) and their
    values where the file states them (None: the EDS's [DeviceInfo]; 0 or absent there: not checked)."""

    check: str = "vendor+product"
    vendor_id: int | None = None
    product_code: int | None = None
    revision: int | None = None
    source: str | None = field(default=None, compare=False)  # the file (for the line to change on a mismatch)

    def against(self, info: odt.DeviceInformation) -> Identity:
        """The :class:`Identity` the boot compares, the values the file leaves out taken from ``info``."""
        def stated(mine: int | None, eds: int | None) -> int | None:
            return mine if mine is not None else (eds or None)  # an EDS's 0 states nothing

        if self.check == "off":
            return Identity(source=self.source)
        vendor = stated(self.vendor_id, info.vendor_number)
        product = stated(self.product_code, info.product_number) if self.check != "vendor" else None
        revision = stated(self.revision, info.revision_number) if self.check == "revision" else None
        return Identity(vendor, product, revision, self.source)


class AxisBoot:
    # -- boot and configuration (before the cycle runs) ------------------------------------------
    def connect(self) -> None:
        """NMT reset and boot-up, identity check, CST and PDO configuration by SDO, NMT start."""
        self._emulator = None  # asked again (is_emulator): another node may answer on this id now
        self._lockstep_gone = False
        self._boot()
        # the first SDO after a boot-up: a boot-up still buffered in an adapter from the drive's power-on
        # can arrive after our reset command, while the drive is still booting (tens of ms, no SDO): more
        # retries of canopen's client (0.3 s each) for this one exchange
        sdo = self.node.sdo
        retries = sdo.MAX_RETRIES
        sdo.MAX_RETRIES = max(retries, 3)
        if not self.lockstep:
            # the first answers may take as long as the boot-up could: nothing says yet how fast this drive is
            sdo.RESPONSE_TIMEOUT = max(self._sdo_timeout, self.timeout)
        t0 = time.perf_counter()
        try:
            self._check_identity()
        finally:
            sdo.MAX_RETRIES = retries
        if not self.lockstep:
            self._adapt_to_peer((time.perf_counter() - t0) / 2)
        if self.lockstep_peer:  # before anything is configured or moves: only the emulator is driven in lockstep
            self._lockstep_peer()
        self._configure()
        for cob, handler in zip(self._tpdo_cob, self._tpdo_handlers, strict=True):
            self.network.subscribe(cob, handler)
        # heartbeat consumer on the master's side: the drive's heartbeat counts in bus cycles
        self._last_heartbeat = self.clock.cycle
        self.network.subscribe(HEARTBEAT_BASE + self.node_id, self._on_heartbeat)
        # frames only the master sends: seen from someone else they are a fault of their own
        for cob in self._watched_cobs:
            self.network.subscribe(cob, self._on_foreign)
        # in lockstep the START below is taken at once; across processes a heartbeat already under way may
        # still say Pre-operational, so a change counts only after the drive has said Operational
        self._foreign, self._foreign_seen, self._nmt_own = None, False, False
        self._seen_operational = self.lockstep
        # the state before the first SYNC, so that the first cycle already sends the right command
        self.statusword = self._sdo(cia402.STATUSWORD)
        self.power = cia402.decode_statusword(self.statusword)
        self.state_fresh, self.state_source = True, "SDO"
        self._controlword = self.master.controlword(self.power)
        counts = self._sdo(cia402.POSITION_ACTUAL)
        self._last = Feedback((self.clock.cycle - 1) * self.dt, self.encoder.from_counts(counts), 0.0)
        self._last_cycle = self.clock.cycle
        if self._at_vel is None:
            self._prev_counts = (counts, self.clock.cycle)
        self._cw_sent = None  # the drive's 0x6040 after a (re)boot is not what we last sent
        self.lost_cycles = 0
        self._rebooted = False
        self._consumed = self.clock.cycle
        syncs = self.clock.syncs  # no answer is owed from before this connection (CanopenAxis.on_tpdo)
        self._answered[:] = self._written_off[:] = [syncs] * len(self._answered)
        self.network.send_message(NMT_COB_ID, bytes([NmtCommand.START, self.node_id]))
        self._connected = True

    def is_emulator(self) -> bool:
        """Is this node drivectl's emulated drive? 0x5FFF:1 read (never written) once per connection: a real drive
        aborts the read of an object it lacks, or answers something else (driver/emulator_clock.py)."""
        if self._emulator is None:
            try:
                self._emulator = self.node.sdo.upload(EMULATOR_OBJECT, MARK_SUB) == EMULATOR_MARK.to_bytes(4, "little")
            except (canopen.SdoAbortedError, canopen.SdoCommunicationError, can.CanError):
                self._emulator = False
        return self._emulator

    def tell_clock(self, mode: int) -> None:
        """Tell drivectl's emulated drive the master's clock (0x5FFF:2); nothing to a real drive (it has its own)."""
        if not self.in_process and self.is_emulator():  # (in-process the lockstep network paces its drives)
            self.node.sdo.download(EMULATOR_OBJECT, CLOCK_SUB, bytes([mode]))

    def _lockstep_peer(self) -> None:
        """Lockstep across processes: the master waits for every SYNC's TPDOs and the drive's time is the SYNC
        count. Only drivectl's emulated drive can be driven so; a real drive runs on its own clock and is refused,
        one line, before anything is configured."""
        if not self.is_emulator():
            raise AxisConfigError(
                f"axis {self.name}: node {self.node_id}: clock lockstep: the node is not drivectl's emulated drive "
                f"(0x{EMULATOR_OBJECT:04X}:{MARK_SUB} is not 0x{EMULATOR_MARK:08X}), and a real drive runs on its own "
                "clock: run it on the wall clock (drivectl trace --paced, connect(clock=\"wall\"))")
        self.tell_clock(CLOCK_LOCKSTEP)

    def _adapt_to_peer(self, rtt: float) -> None:
        """Timeouts from what this drive on this bus takes to answer (``rtt``: the slowest SDO round trip
        measured so far, at connect() and by every SDO exchange after it): SDO answers and a cycle's TPDOs
        get PEER_RTT_FACTOR times that, never less than the defaults. A drive behind a slow host or a
        loaded VM answers late by a factor the defaults cannot know. The waits count this process's
        running time only (driver/running_time.py): a stall of our own host is not the drive's."""
        self.peer_rtt = rtt
        # at most the boot-up's wait: one outlier (a stall of seconds) must not make every later silence,
        # a real one included, take minutes to be noticed
        cap = max(self._sdo_timeout, self.timeout)
        self.node.sdo.RESPONSE_TIMEOUT = min(cap, max(self._sdo_timeout, PEER_RTT_FACTOR * rtt))
        self.tpdo_timeout = min(cap, max(self._tpdo_timeout, PEER_RTT_FACTOR * rtt))
        # a run not paced on the wall clock (a trace as fast as it goes) waits for a cycle's TPDOs up to half
        # the time the drive waits for our SYNC and heartbeat (the consumer time we give it, 0x1016), on the
        # wall clock too (read()): a slow drive is waited for, and a master that gives up still sends its next
        # SYNC within the drive's window, however slow the drive's SDO answers were
        tolerance = 1.5 * self.clock.heartbeat_cycles * self.dt
        self._unpaced_wait = max(self.tpdo_timeout, tolerance)
        self._unpaced_wall = tolerance or None

    def _wait(self, event: threading.Event, what: str) -> None:
        # in lockstep simulated time passes, one cycle at a time, until the answer (a drive's boot-up
        # comes some tens of ms after the reset); otherwise wait for the notifier
        if self.lockstep:
            for _ in range(round(self.timeout / self.dt)):
                if event.is_set():
                    break
                self.network.lockstep.advance(self.dt)
        if not (event.is_set() or (not self.lockstep and wait_running(event, self.timeout))):
            raise AxisError(f"axis {self.name}: node {self.node_id}: no {what} within {self.timeout:g} s")

    def _boot(self) -> None:
        self._booted.clear()

        def on_heartbeat(can_id: int, data: bytes, timestamp: float) -> None:
            if data[:1] == b"\x00":
                self._booted.set()

        cob = HEARTBEAT_BASE + self.node_id
        self.network.subscribe(cob, on_heartbeat)
        try:
            self.network.send_message(NMT_COB_ID, bytes([NmtCommand.RESET_NODE, self.node_id]))
            self._wait(self._booted, "boot-up message after NMT reset (is the drive powered, the node id right?)")
        finally:
            self.network.unsubscribe(cob, on_heartbeat)

    def _sdo(self, index: int, sub: int | None = None, value: int | None = None) -> int:
        what = f"0x{index:04X}" + (f":{sub}" if sub is not None else "")
        if self._awaiting_boot:
            # a reset we saw another master send: the drive answers once it has booted (tens of ms)
            for _ in range(round(self.timeout / self.dt)):
                if not self._awaiting_boot:
                    break
                if self.lockstep:
                    self.network.lockstep.advance(self.dt)
                else:
                    time.sleep(self.dt)
            self._awaiting_boot = False
        if self._connected and self.heartbeat_state == NmtState.STOPPED:
            # a Stopped drive answers no SDO (CiA 301): Pre-operational first (no PDO there either)
            self._nmt_own = True
            self._sent_stop = False
            self.heartbeat_state = int(NmtState.PRE_OPERATIONAL)
            self.network.send_message(NMT_COB_ID, bytes([NmtCommand.ENTER_PRE_OPERATIONAL, self.node_id]))
        t0 = time.perf_counter()
        try:
            var = self.node.sdo[index]
            if sub is not None and not isinstance(self.od[index], odt.ODVariable):
                var = var[sub]  # (a plain variable is its own sub-index 0)
            if value is None:
                value = var.raw
            else:
                var.raw = value
            if self.peer_rtt is not None and time.perf_counter() - t0 > self.peer_rtt:
                # the drive (or its host) answered slower than measured so far: every timeout follows
                self._adapt_to_peer(time.perf_counter() - t0)
            return value
        except canopen.SdoAbortedError as exc:
            raise AxisConfigError(f"axis {self.name}: node {self.node_id}: SDO {what} aborted: {exc}") from None
        except canopen.SdoCommunicationError as exc:
            raise AxisError(f"axis {self.name}: node {self.node_id}: SDO {what}: {exc}") from None
        except KeyError:
            raise AxisConfigError(f"axis {self.name}: node {self.node_id}: object {what} is not in the EDS") from None
        except can.CanError as exc:
            raise AxisError(f"axis {self.name}: node {self.node_id}: SDO {what}: {exc}", FaultKind.BUS_ERROR) from None

    def _check_identity(self) -> None:
        if not self._has(cia402.IDENTITY, 1, writable=False):
            self.identity = Identity()  # no 0x1018 in the EDS: nothing to check against
            return
        want = self.identity
        got = tuple(self._sdo(cia402.IDENTITY, sub) if self._has(cia402.IDENTITY, sub, writable=False) else None
                    for sub in (1, 2, 3))
        self.identity_answered = got
        wrong = [n for n, w, g in zip(_ID_NAMES, want._values(), got, strict=True) if w is not None and g is not None
                 and w != g]
        if not wrong:
            return
        answered = ", ".join(f"{n} 0x{v:08X}" for n, v in zip(_ID_NAMES, got, strict=True) if v is not None)
        # the one line that lets this drive boot: a looser check (a wrong vendor is most likely the wrong EDS)
        loose = {"revision": "vendor+product", "product": "vendor", "vendor": "off"}[wrong[0]]
        where = (f'set identity = "{loose}" under [axes.{self.name}] in {want.source}' if want.source else
                 f'pass identity=Identity() or configure identity = "{loose}" under [axes.{self.name}]')
        extra = " (or name this drive's own EDS in eds)" if wrong[0] == "vendor" else ""
        raise AxisConfigError(
            f"axis {self.name}: node {self.node_id}: identity: the device answered {answered}, the configuration "
            f"expects {want.lines()} ({' and '.join(wrong)} differ{'s' if len(wrong) == 1 else ''}): {where}{extra}"
        )

    def _has(self, index: int, sub: int = 0, writable: bool = True) -> bool:
        """The EDS has index:sub (and lets it be written)."""
        if index not in self.od:
            return False
        obj = self.od[index]
        if not isinstance(obj, odt.ODVariable):
            obj = obj.subindices.get(sub)
        return obj is not None and (obj.writable or not writable)

    def _configure(self) -> None:
        """The mode, the configured ``sdo_init`` writes (read back), the PDO plan and the optional objects the
        drive has (SYNC period, heartbeat, torque limit, watchdogs); what it lacks is said in :attr:`boot_notes`."""
        where = f"axis {self.name}: node {self.node_id}"
        notes: list[str] = []
        caps = self.capabilities
        if self._has(cia402.SUPPORTED_DRIVE_MODES, writable=False):
            supported, source = self._sdo(cia402.SUPPORTED_DRIVE_MODES), "0x6502 read from the device"
        else:
            supported, source = caps.modes, caps.modes_source
        mode = choose_mode(supported)
        if mode is None:
            raise refuse_mode(where, supported, source)
        self.mode = mode
        notes.append(f"mode {MODE_NAMES[mode]} ({source}: 0x{supported:08X})")
        notes.extend(caps.fallback_lines())
        for index, sub, value in self.sdo_init:
            self._sdo(index, sub, value=value)
            back = self._sdo(index, sub)
            if back != value:
                raise AxisConfigError(f"{where}: sdo_init 0x{index:04X}:{sub} written {value}, read back {back}")
        if self.sdo_init:
            notes.append(f"sdo_init: {len(self.sdo_init)} value(s) written and read back")
        self._sdo(cia402.MODES_OF_OPERATION, value=mode)
        if self._has(cia402.COMM_CYCLE_PERIOD):
            self._sdo(cia402.COMM_CYCLE_PERIOD, value=round(self.dt * 1e6))
        if self._has(cia402.PRODUCER_HEARTBEAT_TIME):
            self._sdo(cia402.PRODUCER_HEARTBEAT_TIME, value=self.heartbeat_ms)
        else:
            self.heartbeat_ms = 0  # the master cannot watch a drive that sends none
            notes.append("0x1017 absent: the drive sends no heartbeat; the master watches its TPDOs only")
        if self.max_torque_permille is not None and self._has(cia402.MAX_TORQUE):
            limit = self.od[cia402.MAX_TORQUE]
            permille = self.max_torque_permille
            if limit.max is not None and permille > limit.max:
                # the drive's own clip cannot go as high as limits.max_effort: it clips lower (safe), and says so
                permille = limit.max
                notes.append(f"0x6072 tops out at {limit.max} per mille ({self.scale.from_permille(limit.max):g} "
                             f"{self.effort_unit}): the drive clips there, below limits.max_effort")
            if limit.min is not None and permille < limit.min:
                raise AxisConfigError(f"{where}: limits.max_effort is {permille} per mille of the rated effort, below "
                                      f"the drive's lowest 0x6072 ({limit.min}): raise max_effort or lower "
                                      "rated_effort")
            self._sdo(cia402.MAX_TORQUE, value=permille)
        # the drive watches the master's heartbeat (0x1016) and reacts per 0x6007 when it stops;
        # allow three periods of the master's heartbeat before it counts as lost
        master_ms = round(self.clock.heartbeat_cycles * self.dt * 1000)
        if master_ms and self._has(cia402.CONSUMER_HEARTBEAT_TIME, 1):
            self._sdo(cia402.CONSUMER_HEARTBEAT_TIME, 1, value=(MASTER_NODE_ID << 16) | min(3 * master_ms, 0xFFFF))
        deadline = any(p.slot.event_timer for p in self.pdo_plan.rx if p.trans_type <= 240)
        if not self._has(cia402.CONSUMER_HEARTBEAT_TIME, 1) and not deadline:
            notes.append("no heartbeat consumer (0x1016) and no RPDO deadline (0x14xx:05): the drive will not notice "
                         "a lost master by itself (node guarding 0x100C/0x100D is not run by drivectl)")
        try:
            self._map_pdos()
        except canopen.SdoAbortedError as exc:
            raise AxisConfigError(f"{where}: PDO mapping aborted: {exc}") from None
        notes.extend(self.pdo_plan.lines())
        if self._has(cia402.MODES_OF_OPERATION_DISPLAY, writable=False):
            shown = self._sdo(cia402.MODES_OF_OPERATION_DISPLAY)
            if shown != mode:
                raise AxisConfigError(f"{where}: mode not accepted: 0x6061 = {shown} after 0x6060 = {mode} "
                                      f"({MODE_NAMES[mode]})")
        self.boot_notes = notes

    def _map_pdos(self) -> None:
        """The PDO plan written by SDO (CiA 301 7.5.2.36: invalidate, sub 0 = 0, entries, sub 0 = n, validate;
        a fixed mapping left as it is, a read-only COB-ID or transmission type used as the drive has it); every
        other PDO disabled, or its mapping emptied where its COB-ID is read-only."""
        used = [(p.slot, p) for p in (*self.pdo_plan.rx, *self.pdo_plan.tx)]
        for slot, p in [*used, *((s, None) for s in self.pdo_plan.unused)]:
            comm, mapping = slot.comm, slot.comm + 0x200
            current = self._sdo(comm, 1)
            keep = current & 0x40000000  # the RTR bit as the drive has it
            if slot.cob_writable:
                cob = p.cob_id if p is not None else current & 0x7FF
                self._sdo(comm, 1, value=cob | 0x80000000 | keep)
            if p is None:
                if slot.fixed is None:
                    self._sdo(mapping, 0, value=0)
                continue
            if slot.type_writable:
                self._sdo(comm, 2, value=p.trans_type)
            if slot.rx and p.trans_type <= 240 and slot.event_timer:
                self._sdo(comm, 5, value=self.rpdo_timeout_ms)  # the drive's deadline on our cyclic RPDO
            if slot.fixed is None:
                self._sdo(mapping, 0, value=0)
                for k, entry in enumerate(p.entries):
                    self._sdo(mapping, k + 1, value=entry[0] << 16 | entry[1] << 8 | entry_bits(self.od, entry))
                self._sdo(mapping, 0, value=len(p.entries))
            if slot.cob_writable:
                self._sdo(comm, 1, value=p.cob_id | keep)

    def read_back_mapping(self) -> dict[str, list[int]]:
        """The mapping entries the drive holds now, read by SDO (a commissioning check)."""
        out = {}
        for p in (*self.pdo_plan.rx, *self.pdo_plan.tx):
            mapping = p.slot.comm + 0x200
            count = self._sdo(mapping, 0)
            out[p.slot.name.lower()] = [self._sdo(mapping, s + 1) for s in range(count)]
        return out

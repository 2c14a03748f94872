"""The CiA 402 master's boot and configuration of one drive, before the cycle runs (a mixin of
canopen_axis.CanopenAxis): NMT reset and boot-up, identity 0x1018, mode and PDO mapping by SDO, NMT start."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import can
import canopen

from drivectl.driver import cia402
from drivectl.driver.axis import AxisConfigError, AxisError, FaultKind, Feedback
from drivectl.driver.cia301 import (
    HEARTBEAT_BASE,
    MASTER_NODE_ID,
    NMT_COB_ID,
    RPDO_BASE,
    TPDO_BASE,
    NmtCommand,
    NmtState,
)


@dataclass(frozen=True)
class Identity:
    """What 0x1018 must say (None: not checked)."""

    vendor_id: int | None = None
    product_code: int | None = None


class AxisBoot:
    # -- boot and configuration (before the cycle runs) ------------------------------------------
    def connect(self) -> None:
        """NMT reset and boot-up, identity check, CST and PDO configuration by SDO, NMT start."""
        self._boot()
        # the first SDO after a boot-up: a boot-up still buffered in an adapter from the drive's power-on
        # can arrive after our reset command, while the drive is still booting (tens of ms, no SDO): more
        # retries of canopen's client (0.3 s each) for this one exchange
        sdo = self.node.sdo
        retries = sdo.MAX_RETRIES
        sdo.MAX_RETRIES = max(retries, 3)
        try:
            self._check_identity()
        finally:
            sdo.MAX_RETRIES = retries
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
        if self.mapping != "full":
            self._prev_counts = (counts, self.clock.cycle)
        self._cw_sent = None  # the drive's 0x6040 after a (re)boot is not what we last sent
        self.lost_cycles = 0
        self._rebooted = False
        self._consumed = self.clock.cycle
        self.network.send_message(NMT_COB_ID, bytes([NmtCommand.START, self.node_id]))
        self._connected = True

    def _wait(self, event: threading.Event, what: str) -> None:
        # in lockstep simulated time passes, one cycle at a time, until the answer (a drive's boot-up
        # comes some tens of ms after the reset); otherwise wait for the notifier
        if self.lockstep:
            for _ in range(round(self.timeout / self.dt)):
                if event.is_set():
                    break
                self.network.lockstep.advance(self.dt)
        if not (event.is_set() or (not self.lockstep and event.wait(self.timeout))):
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
        if getattr(self, "_awaiting_boot", False):
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
        try:
            var = self.node.sdo[index] if sub is None else self.node.sdo[index][sub]
            if value is None:
                return var.raw
            var.raw = value
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
        vendor = self._sdo(cia402.IDENTITY, 1)
        product = self._sdo(cia402.IDENTITY, 2)
        want = self.identity
        if (want.vendor_id is not None and vendor != want.vendor_id) or (
            want.product_code is not None and product != want.product_code
        ):
            raise AxisConfigError(
                f"axis {self.name}: node {self.node_id}: identity vendor 0x{vendor:08X} product 0x{product:08X}, "
                f"the configuration expects vendor 0x{want.vendor_id or 0:08X} product 0x{want.product_code or 0:08X}"
            )

    def _configure(self) -> None:
        supported = self._sdo(cia402.SUPPORTED_DRIVE_MODES)
        if not supported & cia402.supported_mode_bit(cia402.Mode.CYCLIC_SYNC_TORQUE):
            raise AxisConfigError(f"axis {self.name}: node {self.node_id}: drive does not support cyclic synchronous "
                            f"torque (0x6502 = 0x{supported:08X})")
        self._sdo(cia402.MODES_OF_OPERATION, value=int(cia402.Mode.CYCLIC_SYNC_TORQUE))
        self._sdo(cia402.COMM_CYCLE_PERIOD, value=round(self.dt * 1e6))
        self._sdo(cia402.PRODUCER_HEARTBEAT_TIME, value=self.heartbeat_ms)
        if self.max_torque_permille is not None:
            self._sdo(cia402.MAX_TORQUE, value=self.max_torque_permille)
        # the drive watches the master's heartbeat (0x1016) and reacts per 0x6007 when it stops;
        # allow three periods of the master's heartbeat before it counts as lost
        master_ms = round(self.clock.heartbeat_cycles * self.dt * 1000)
        if master_ms:
            self._sdo(cia402.CONSUMER_HEARTBEAT_TIME, 1, value=(MASTER_NODE_ID << 16) | min(3 * master_ms, 0xFFFF))
        try:
            self._map_pdos()
        except canopen.SdoAbortedError as exc:
            raise AxisConfigError(f"axis {self.name}: node {self.node_id}: PDO mapping aborted: {exc}") from None
        mode = self._sdo(cia402.MODES_OF_OPERATION_DISPLAY)
        if mode != cia402.Mode.CYCLIC_SYNC_TORQUE:
            raise AxisConfigError(f"axis {self.name}: node {self.node_id}: mode display 0x6061 = {mode}, "
                                  "expected 10 (CST)")

    def _map_pdos(self) -> None:
        """The RPDOs and TPDOs of the mapping, every other PDO off (canopen's PdoMap writes)."""
        node = self.node
        node.rpdo.read()
        node.tpdo.read()
        for maps, wanted, base in ((node.rpdo, self._rpdo_entries, RPDO_BASE),
                                   (node.tpdo, self._tpdo_entries, TPDO_BASE)):
            for n, pdo in maps.map.items():
                pdo.clear()
                if n <= len(wanted):
                    for index, sub in wanted[n - 1]:
                        pdo.add_variable(index, sub)
                    pdo.cob_id = base[n - 1] + self.node_id
                    pdo.enabled = True
                    if maps is node.rpdo and n == 2:
                        pdo.trans_type = 255  # minimal's controlword: event-driven, taken on reception
                    else:
                        pdo.trans_type = 1  # synchronous, every SYNC
                        if maps is node.rpdo and 5 in pdo.com_record.od:
                            pdo.event_timer = self.rpdo_timeout_ms  # the drive's deadline on our cyclic RPDO
                else:
                    pdo.enabled = False
                pdo.save()
                if maps is node.tpdo and pdo.enabled:
                    # save() subscribed canopen's own decoder (a lock and notify_all per frame); the
                    # cycle decodes the TPDOs itself (_tpdo_callback): keep the per-cycle path one call
                    if pdo.on_message in self.network.subscribers.get(pdo.cob_id, ()):
                        self.network.unsubscribe(pdo.cob_id, pdo.on_message)

    def read_back_mapping(self) -> dict[str, list[int]]:
        """The mapping entries the drive holds now, read by SDO (a commissioning check)."""
        out = {}
        for name, base, n in (("rpdo", cia402.RPDO_MAP, len(self._rpdo_entries)), ("tpdo", cia402.TPDO_MAP, 2)):
            for i in range(n):
                count = self._sdo(base + i, 0)
                out[f"{name}{i + 1}"] = [self._sdo(base + i, s + 1) for s in range(count)]
        return out

"""The stop escalation of the CiA 402 master (a mixin of canopen_axis.CanopenAxis; controllers/runtime/safe_stop.py
decides when): quick stop by SDO, NMT Stop, the state read outside Operational, the configured last resort."""

from __future__ import annotations

from drivectl.driver import cia402
from drivectl.driver.axis import AxisError
from drivectl.driver.cia301 import HEARTBEAT_BASE, NMT_COB_ID, NmtCommand
from drivectl.driver.cia402 import PowerState


class AxisStop:
    # -- stop escalation (driver/safe_stop.py decides when) ----------------------------------------
    def sdo_quick_stop(self) -> None:
        """Quick stop by SDO (0x6040 = Quick Stop), for a drive that does not take it by RPDO (outside
        Operational, or a second RPDO producer overriding the master's). The RPDO says the same from now on."""
        self._target(PowerState.QUICK_STOP_ACTIVE)
        self._sdo(cia402.CONTROLWORD, value=int(cia402.Command.QUICK_STOP))
        self._cw_sent = None  # the drive's 0x6040 is the SDO's now: the next cycle sends ours again

    def abort_connection_option(self) -> int | None:
        """0x6007 by SDO (None: not readable): 1 fault, 2 disable voltage, 3 quick stop on a lost connection."""
        try:
            return self._sdo(cia402.ABORT_CONNECTION_OPTION)
        except AxisError:
            return None

    def nmt_stop(self) -> None:
        """NMT Stop to this drive: it no longer takes any PDO (a rogue producer's neither) and, per its
        0x6007, stops its power stage. The drive's reply comes by SDO after NMT Pre-operational
        (:meth:`refresh_state_outside_operational`); a Stopped node need not answer SDO."""
        self._nmt_own = True
        self._sent_stop = True
        self.network.send_message(NMT_COB_ID, bytes([NmtCommand.STOP, self.node_id]))

    def refresh_state_outside_operational(self) -> PowerState:
        """The statusword by SDO; if the drive is NMT Stopped and does not answer, NMT Pre-operational
        first (SDO works there, PDOs still do not). Known Stopped (by our NMT Stop or its heartbeat): Pre-operational
        at once (a conforming drive answers no SDO in Stopped, CiA 301; waiting for the SDO timeout costs 0.6 s)."""
        if self._sent_stop:
            self._sent_stop = False
            self._nmt_own = True
            self.network.send_message(NMT_COB_ID, bytes([NmtCommand.ENTER_PRE_OPERATIONAL, self.node_id]))
            return self.refresh_state()
        try:
            return self.refresh_state()
        except AxisError:
            self._nmt_own = True
            self.network.send_message(NMT_COB_ID, bytes([NmtCommand.ENTER_PRE_OPERATIONAL, self.node_id]))
            return self.refresh_state()

    def last_resort(self) -> str | None:
        """The configured last resort (``last_resort``); returns what was done, None for "none"."""
        if self.last_resort_action == "none":
            return None
        # NMT Reset Node: the drive restarts with its power stage off (and its configuration lost: connect()
        # again before the next run); wait for its boot-up, then read the state it came back in
        self._nmt_own = True
        self._connected = False  # the boot-up that follows is ours, not a spontaneous reset
        self._booted.clear()

        def on_boot(can_id: int, data: bytes, timestamp: float) -> None:
            if data[:1] == b"\x00":
                self._booted.set()

        cob = HEARTBEAT_BASE + self.node_id
        self.network.subscribe(cob, on_boot)
        try:
            self.network.send_message(NMT_COB_ID, bytes([NmtCommand.RESET_NODE, self.node_id]))
            self._wait(self._booted, "boot-up message after NMT reset")
        finally:
            self.network.unsubscribe(cob, on_boot)
        self.refresh_state()
        return "NMT Reset Node"

    def drive_limits(self) -> dict[str, object]:
        """The limits the drive holds (0x6065/0x6066 following error, 0x607D software position limits),
        in SI; a window of 0xFFFFFFFF, and position limits that are equal or span all of int32, mean "none"."""
        enc = self.encoder
        out: dict[str, object] = {}
        window = self._sdo(cia402.FOLLOWING_ERROR_WINDOW)
        if window != 0xFFFFFFFF:
            out["following_error"] = enc.from_counts(window)
            out["following_time"] = self._sdo(cia402.FOLLOWING_ERROR_TIMEOUT) / 1000.0
        lo, hi = self._sdo(cia402.SOFTWARE_POSITION_LIMIT, 1), self._sdo(cia402.SOFTWARE_POSITION_LIMIT, 2)
        if lo < hi and (lo, hi) != (-0x80000000, 0x7FFFFFFF):  # the whole int32 range: no limits set
            out["position"] = (enc.from_counts(lo), enc.from_counts(hi))
            out["position_source"] = f"node {self.node_id}: 0x607D software position limit"
        return out

"""The SYNC producer of one bus, shared by its axes (and the master's heartbeat producer): the loop, or the
transport's periodic transmit while a wall-clock run lasts (driver/sync_source.py)."""

from __future__ import annotations

from collections.abc import Callable

import can
import canopen

from drivectl.driver.cia301 import HEARTBEAT_BASE, MASTER_NODE_ID, SYNC_COB_ID, NmtState
from drivectl.driver.emulator_clock import SLOT_COUNTER_SPAN
from drivectl.driver.sync_source import SYNC_WAIT_PERIODS, PeriodicSync, start_periodic_sync


class SyncClock:
    """The SYNC producer of one bus, shared by its axes; also the master's heartbeat producer
    (node ``MASTER_NODE_ID``, every ``heartbeat_cycles`` SYNCs), which the drives consume (0x1016)."""

    def __init__(self, network: canopen.Network, cob_id: int = SYNC_COB_ID, heartbeat_cycles: int = 100):
        self.network = network
        self.cob_id = cob_id
        self.cycle = 0
        self.heartbeat_cycles = heartbeat_cycles
        #: the transport's periodic SYNC while a paced run lasts (driver/sync_source.py); None: the loop sends it
        self.periodic: PeriodicSync | None = None
        self._periodic_base = 0
        #: who sends the SYNC now, and why the loop does where it does
        self.sync_source, self.sync_note = "loop", ""
        self.allow_periodic = True  # False: the loop always sends it (bus.sync = "loop")
        #: when the cycle's SYNC went (the pacer's clock; paced runs across processes): the TPDO waits end from it
        self.ticked_at = 0.0
        self._skipped = 0  # slots the loop skipped before this tick (it woke late): the cycle counts them
        #: a paced run's loop: the slots it slipped since its cycle took its slot, at the wall time given (None: now),
        #: asked just before the SYNC goes out, in-process at its delivery (the host may stop the loop between the
        #: two; the drive samples at the SYNC, docs/timing.md "A SYNC later than its slot")
        self.slip: Callable[[float | None], int] | None = None
        self._slip_hook = self._slipped_at  # bound once: handed to the lockstep network every paced tick
        #: SYNCs on the bus since the clock began, up to this cycle's (a skipped slot sends none: ``cycle`` counts
        #: slots, this counts frames); an axis counts its answers against it (CanopenAxis, docs/timing.md)
        self.syncs = 0
        #: ``syncs`` of the last SYNC that came after a late wake-up (slots skipped, or periodic SYNCs the loop
        #: did not wait for): only across one may an answer to an earlier SYNC still be on its way
        self.late_sync = -1
        self._periodic_syncs = 0  # ``syncs`` when the periodic transmit started
        #: the SYNC carries the slot count as its counter byte (only to drivectl's emulated drives: CanopenAxis.pace)
        self.slot_counter = False
        self.slot_vetoed = False  # a drive of the bus is not drivectl's emulator: no counter this run

    def skip(self, slots: int) -> None:
        """The next tick's SYNC is ``slots`` slots after the last one plus one: its cycle counts them, so what the
        drive sampled there is stamped with the time it was sampled (a transport's periodic SYNC counts itself)."""
        self._skipped = slots

    def tick(self) -> None:
        prev, skipped, self._skipped = self.cycle, self._skipped, 0
        if self.periodic is None:
            self.cycle += 1 + skipped  # first: what answers this SYNC belongs to the new cycle
            self.syncs += 1
            if skipped:
                self.late_sync = self.syncs
            lockstep = None
            if self.slip is not None:
                lockstep = getattr(self.network, "lockstep", None)
                if lockstep is not None and lockstep.paced:
                    # in-process the drives sample at the wall time the lockstep network gives them just before the
                    # delivery: the slip is judged at that time, so a stop inside the send is counted too (no counter
                    # byte in-process: the frame does not depend on it)
                    lockstep.at_delivery = self._slip_hook
                else:
                    lockstep = None
                    self._slipped_at(None)
            try:
                self.network.send_message(self.cob_id, bytes((self.cycle % SLOT_COUNTER_SPAN + 1,))
                                          if self.slot_counter else b"")
            finally:
                if lockstep is not None and lockstep.at_delivery is not None:  # not delivered here (a callback's send)
                    lockstep.at_delivery = None
                    self._slipped_at(None)
        else:  # the transport sends it: wait for the next one (a late loop takes the latest: no burst)
            seen = self.periodic.wait_beyond(self.cycle - self._periodic_base)
            if self._periodic_base + seen == prev:
                raise can.CanOperationError(f"no SYNC from the periodic transmit for "
                                            f"{SYNC_WAIT_PERIODS * self.periodic.dt * 1000:g} ms")
            self.cycle = self._periodic_base + seen
            syncs, self.syncs = self.syncs, self._periodic_syncs + seen
            if self.syncs - syncs > 1:
                self.late_sync = self.syncs
        # from the first SYNC on: a drive starts watching at the first heartbeat (CiA 301), so a master
        # that died before its first one would leave the drive unwatched
        hb = self.heartbeat_cycles
        if hb and (self.cycle - 1) // hb > (prev - 1) // hb:
            self.network.send_message(HEARTBEAT_BASE + MASTER_NODE_ID, bytes([NmtState.OPERATIONAL]))

    def _slipped_at(self, now: float | None) -> None:
        """The loop's slip at ``now`` (None: now), counted into this cycle's slots (the one place it is applied)."""
        extra = self.slip(now)
        if extra:
            self.cycle += extra
            self.late_sync = self.syncs

    def start_periodic(self, dt: float) -> None:
        """The transport sends the SYNC from now on, where it can off the Python thread (else the loop
        goes on sending it; :attr:`sync_note` says why)."""
        if self.periodic is not None or self.network.bus is None:
            return
        if not self.allow_periodic:
            self.sync_note = "bus.sync = \"loop\""
            return
        periodic, why = start_periodic_sync(self.network.bus, self.cob_id, dt)
        if periodic is None:
            self.sync_source, self.sync_note = "loop", why
            return
        self._periodic_base, self._periodic_syncs = self.cycle, self.syncs
        self.network.subscribe(self.cob_id, periodic.on_sync)
        self.periodic = periodic
        self.sync_source, self.sync_note = "transport", ""

    def bus_syncs(self) -> int:
        """The SYNCs the bus has seen so far: this cycle's count, or, while the transport sends them, every one
        the master's receiver has seen (a frame received after one of them answers it or an earlier one)."""
        periodic = self.periodic
        return self.syncs if periodic is None else self._periodic_syncs + periodic.seen

    def stop_periodic(self) -> None:
        """The loop sends the SYNC again (the paced run ended)."""
        periodic, self.periodic = self.periodic, None
        if periodic is not None:
            periodic.stop()
            self.network.unsubscribe(self.cob_id, periodic.on_sync)
            self.sync_source = "loop"

"""The emulated drive's clock, its watchdogs and its cycle (a mixin of node402.EmulatedDrive).

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

import math
import time

from drivectl.driver import cia402
from drivectl.driver.cia301 import HEARTBEAT_BASE, NMT_OPERATIONAL, NmtState
from drivectl.driver.emulator_clock import CLOCK_LOCKSTEP, CLOCK_SLOTS, SLOT_COUNTER_SPAN
from drivectl.plant_emulator.drive_constants import (
    ERROR_RESET,
    FAULTED,
    PACED_SYNC_LOSS_CYCLES,
    RPDO_TIMEOUT_ERROR,
    SYNC_LENGTH_ERROR,
    SYNC_LOSS_MS,
)
from drivectl.plant_emulator.pdo_rules import Tpdo


class DriveClock:
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
        if self.master_clock == CLOCK_SLOTS and data:
            self._catch_up(data[0])
        self._syncs_since_rpdo += 1
        self._synced = True  # serve() re-anchors the wall clock here
        self._sync_at = self._last_serve  # in-process and paced: the wall time just before this delivery
        self._cycle(sync=True)

    def _catch_up(self, counter: int) -> None:
        """The master's slot count in the SYNC counter (0x5FFF:2 = slots): the slots since the last SYNC but this
        one's run first on the drive's own clock, the setpoint held (a late master skipped them; a real drive's
        plant moves on meanwhile, and its RPDO deadline counts them). Each cycle of wall time runs once.

        Cycles the drive's own clock ran just before this SYNC (:meth:`serve`, a gap past the paced window) stand
        for the skipped slots of that gap. More of them than the counter skipped: the SYNC came late after its
        slot was taken (a master held off between the two); the drive ran that time, and the next SYNC's counter
        says the master skipped those slots: they are not run again. After its own clock ran longer than the
        counter can tell (half its span) the counter only sets the count again."""
        last, self._slot = self._slot, counter
        own, self._own_cycles = self._own_cycles, 0
        ahead, self._ahead = self._ahead, 0  # what an earlier SYNC ran beyond its counter (used once)
        if last is None or own >= SLOT_COUNTER_SPAN // 2:
            return
        skipped = (counter - last - 1) % SLOT_COUNTER_SPAN
        if own > skipped:
            self._ahead = own - skipped  # a late SYNC: the gap it ended is ahead of the counter
            return
        run = skipped - own
        run -= min(ahead, run)
        self._skipped_since_rpdo += run
        for _ in range(run):
            self._cycle(sync=False)

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
        if self.internal_limit and d.power not in FAULTED:
            self.internal_limit = False  # the fault was reset
        if self._fault_reported and d.power not in FAULTED:
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
        if self.nmt is not NMT_OPERATIONAL:
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
        if self._ms_since_rpdo is None or not self._rpdo_timeout_ms or self.nmt is not NMT_OPERATIONAL:
            return
        self._ms_since_rpdo += self.cycle_ms
        if self._ms_since_rpdo > self._rpdo_timeout_ms:
            self.deadline_why = self._deadline_account()
            self._ms_since_rpdo = None  # one reaction; monitoring restarts with the next RPDO
            self._communication_lost(RPDO_TIMEOUT_ERROR)

    def _deadline_account(self) -> str:
        """Whose the drive time without a setpoint was: SYNCs that came without one (frames lost or late),
        slots the master's counter said it skipped (a late master), or the drive's own clock (no SYNC)."""
        cycles = round(self._ms_since_rpdo / self.cycle_ms)
        syncs, skipped = self._syncs_since_rpdo, self._skipped_since_rpdo
        # (the cycle that fired may be a SYNC's still to be counted, or one of a catch-up not yet run)
        own = max(0, cycles - syncs - skipped)
        return (f"{self._ms_since_rpdo:g} ms of drive time without the RPDO (deadline {self._rpdo_timeout_ms:g} ms); "
                f"since the last one: {syncs} SYNC(s), {skipped} slot(s) the master skipped (its SYNC counter), "
                f"{own} cycle(s) on the drive's own clock (no SYNC)")

    def _watch_master(self) -> None:
        """Heartbeat consumer (0x1016) on the drive's clock, from the master's first heartbeat on."""
        if self._consumer is None or self._ms_since_master is None or self.master_lost:
            return
        self._ms_since_master += self.cycle_ms
        if self._ms_since_master > self._consumer[1]:
            self.master_lost = True
            self._communication_lost(cia402.HEARTBEAT_LOST_ERROR)

    def _set_master_clock(self, mode: int) -> None:
        """The master's clock (0x5FFF:2, driver/emulator_clock.py): lockstep, the drive's time is the SYNC count and
        nothing else (never its own clock: a slow master is never late, a silent one stops time); slots, a SYNC
        first runs the slots its counter says the master skipped (_catch_up); own, as at power-on."""
        self.master_clock, self._slot = mode, None
        self._own_cycles = self._ahead = 0
        if mode == CLOCK_LOCKSTEP:
            self._window_ms, self._free_running = math.inf, False
        else:
            if self._window_ms == math.inf:
                self._window_ms = None
            if mode == CLOCK_SLOTS:
                self._free_running = False  # the master's SYNCs are the clock from here (serve() judges their loss)

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
            self._synced, self._free_running = False, False
            if self._window_ms is None or self._window_ms == math.inf:
                self._anchor = now
                return
            # in-process and paced (wall_clock: served just before each delivery too), the lock holds from the
            # SYNC's arrival: a host that stopped this process inside the delivery, after the SYNC's cycle ran,
            # let that time pass on a real drive too, so the gap below runs it (else the plant stood still and the
            # RPDO deadline never saw it: docs/timing.md, "A host stop inside a SYNC's delivery")
            self._anchor = self._sync_at
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
        # the cycles that passed, but the last half one: a SYNC that ends the gap runs that cycle itself, so a
        # gap of 5.3 cycles runs 5 of them (not 5 and then the SYNC's: the plant 0.7 cycle ahead of the time)
        n = int((gap_ms - 0.5 * self.cycle_ms) // self.cycle_ms)
        for _ in range(n):
            self._cycle(sync=False)
        self._own_cycles += n
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

"""Issue 19 point 1: the emulated drive's own clock (SYNC-locked, free-running when served and no SYNC
comes), its boot-up delay, what reset communication restores, 0x6076 scaling and a long RPDO. The
served drive is driven here with a simulated wall clock (``serve(now)``), so nothing waits."""

from __future__ import annotations

import struct

import can
import canopen
import pytest
from helpers import SimWallClock, enabled_wall_loop

from drivectl.driver import cia402
from drivectl.driver.cia301 import NmtState
from drivectl.driver.network import open_bus, unique_virtual_channel
from drivectl.plant_emulator.models import load_plant
from drivectl.plant_emulator.node402 import EmulatedDrive, deliver


class Served:
    """A drive served as `drivectl emulate` serves it (frames, then the clock), its time simulated."""

    def __init__(self, **kw) -> None:
        channel = unique_virtual_channel("clock")
        self.bus = open_bus("virtual", channel)
        self.master = open_bus("virtual", channel)
        self.net = canopen.Network(self.bus)
        self.drive = EmulatedDrive(self.net, 1, load_plant("rigid-x").build(0.001), rated_effort=100.0, **kw)
        self.now = 0.0
        self.reactions: list[int] = []
        self.drive.boot()
        self.serve(0.0)

    def serve(self, dt: float) -> list[can.Message]:
        """``dt`` s of wall time pass; the frames the master sent are delivered first. Returns what the
        drive sent."""
        while (msg := self.bus.recv(0)) is not None:
            deliver(self.net, msg)
        self.now += dt
        code = self.drive.check_master(self.now)
        if code:
            self.reactions.append(code)
        out = []
        while (msg := self.master.recv(0)) is not None:
            out.append(msg)
        return out

    def send(self, can_id: int, data: bytes) -> None:
        self.master.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))

    def sdo_write(self, index: int, sub: int, value: int, size: int) -> bytes:
        cmd = {1: 0x2F, 2: 0x2B, 4: 0x23}[size]
        self.send(0x601, bytes([cmd, index & 0xFF, index >> 8, sub]) + value.to_bytes(size, "little",
                                                                                     signed=value < 0).ljust(4, b"\0"))
        answers = [m for m in self.serve(0.0) if m.arbitration_id == 0x581]
        return bytes(answers[0].data)

    def enable(self) -> None:
        self.sdo_write(cia402.MODES_OF_OPERATION, 0, 10, 1)
        self.send(0x000, b"\x01\x01")
        for cw in (0x06, 0x0F, 0x0F):
            self.send(0x201, struct.pack("<Hh", cw, 0))
            self.send(0x080, b"")
            self.serve(0.001)
        assert self.drive.drive.power is cia402.PowerState.OPERATION_ENABLED

    def close(self) -> None:
        self.drive.close()
        self.bus.shutdown()
        self.master.shutdown()


@pytest.fixture
def served():
    s = Served()
    s.serve(0.06)  # booted
    yield s
    s.close()


def test_a_slow_master_is_not_taken_for_a_dead_one_and_a_silent_one_is_caught(served):
    s = served
    s.sdo_write(cia402.CONSUMER_HEARTBEAT_TIME, 1, (0x7F << 16) | 300, 4)
    s.sdo_write(0x1400, 5, 2, 2)  # RPDO deadline 2 ms of drive time
    s.enable()
    # 1500 cycles at 90 cycles/s (11 ms of wall time each, some stalls of 150 ms): heartbeat every 100 SYNCs
    for k in range(1500):
        s.send(0x201, struct.pack("<Hh", 0x0F, 0))
        s.send(0x080, b"")
        if k % 100 == 0:
            s.send(0x77F, b"\x05")
        s.serve(0.150 if k % 400 == 399 else 0.011)
    assert s.reactions == [] and s.drive.drive.power is cia402.PowerState.OPERATION_ENABLED
    # the master dies: no SYNC, no RPDO, no heartbeat. The drive's clock runs on after the consumer time
    # (300 ms) and counts the whole gap: the RPDO deadline fires 2 ms of drive time after the last RPDO
    t_dead = s.now
    while not s.reactions and s.now - t_dead < 1.0:
        s.serve(0.010)
    assert s.reactions == [0x8250] and 0.29 <= s.now - t_dead <= 0.32
    assert s.drive.drive.power is cia402.PowerState.SWITCH_ON_DISABLED


def test_heartbeat_and_sdo_controlword_without_any_sync(served):
    """No SYNC at all (scan, an SDO-only master): the heartbeat comes on the drive's own clock, and a
    controlword written by SDO moves the power state."""
    s = served
    s.sdo_write(cia402.PRODUCER_HEARTBEAT_TIME, 0, 100, 2)
    beats = [m for _ in range(100) for m in s.serve(0.01) if m.arbitration_id == 0x701]
    assert len(beats) in (9, 10) and all(bytes(m.data) == bytes([NmtState.PRE_OPERATIONAL]) for m in beats)
    s.sdo_write(cia402.CONTROLWORD, 0, 0x06, 2)
    s.serve(0.01)
    assert s.drive.drive.power is cia402.PowerState.READY_TO_SWITCH_ON


def test_boot_up_delay_is_drive_time_and_zero_on_request():
    s = Served(boot_delay_ms=0)
    try:
        assert s.drive.nmt is NmtState.PRE_OPERATIONAL  # at once
        s.send(0x000, b"\x81\x01")
        assert [m.arbitration_id for m in s.serve(0.0)] == [0x701]
    finally:
        s.close()
    s = Served(boot_delay_ms=80)
    try:
        s.serve(0.070)
        assert s.drive.nmt is NmtState.INITIALISING
        assert [m.arbitration_id for m in s.serve(0.011)] == [0x701]
    finally:
        s.close()


def test_reset_communication_restores_the_communication_area_only(served):
    s = served
    for index, sub, value, size in ((cia402.PRODUCER_HEARTBEAT_TIME, 0, 250, 2), (0x1800, 2, 5, 1),
                                    (cia402.COMM_CYCLE_PERIOD, 0, 0, 4), (cia402.ABORT_CONNECTION_OPTION, 0, 1, 2)):
        assert s.sdo_write(index, sub, value, size)[0] == 0x60
    s.send(0x000, b"\x82\x01")
    s.serve(0.06)
    d = s.drive
    assert (d._value(0x1017), d._value(0x1800, 2), d._value(0x1006)) == (0, 1, 1000)  # the EDS defaults
    assert d._value(cia402.ABORT_CONNECTION_OPTION) == 1  # application area kept


def test_rated_torque_written_scales_the_torque_and_a_long_rpdo_is_used_with_emcy_0x8220(served):
    s = served
    s.sdo_write(cia402.RATED_TORQUE, 0, 50_000, 4)  # 50 N rated instead of 100
    s.enable()
    s.send(0x201, struct.pack("<Hh", 0x0F, 100) + b"\x00\x00")  # 6 bytes for a 4-byte mapping
    s.send(0x080, b"")
    sent = s.serve(0.001)
    assert s.drive.drive.applied == pytest.approx(5.0)  # 100 per mille of 50 N
    emcy = [struct.unpack_from("<H", m.data)[0] for m in sent if m.arbitration_id == 0x81]
    assert emcy == [0x8220] and s.drive.frames.counts["long-rpdo"] == 1


def test_in_process_the_heartbeat_consumer_runs_on_the_drive_clock():
    """Lockstep: the master stops (no SYNC, no heartbeat); the drive's own clock (Machine.let_drives_run)
    counts the consumer time, 300 ms as drivectl configures it, and the drive stops with 0x8130."""
    from drivectl.machine.build import open_machine
    from drivectl.machine.config import load_config

    cfg = load_config(None)
    ac = cfg.axis("x")
    object.__setattr__(ac, "rpdo_timeout_ms", 0)  # no RPDO deadline: the heartbeat consumer alone
    with open_machine(cfg, ["x"], faults=[]) as m:
        ax, drive = m.axes["x"], m.drives["x"]
        ax.enable()
        for _ in range(5):
            ax.read()
            ax.write(0.0)
        assert drive.drive.power is cia402.PowerState.OPERATION_ENABLED
        safe = m.let_drives_run(1000, until_safe=True)["x"]
        assert drive.drive.error_code == cia402.HEARTBEAT_LOST_ERROR
        assert 295 <= safe <= 305  # 300 ms after the master's last heartbeat (sent at its first SYNC)



class _LateMaster:
    """The controller of the run, stalling the master ``stall_s`` of wall time in its ``at``-th step (between
    the cycle's SYNC and its RPDO: the master runs late)."""

    def __init__(self, inner, clock: SimWallClock, at: int, stall_s: float) -> None:
        self.inner, self.clock, self.at, self.stall_s, self.steps = inner, clock, at, stall_s, 0
        self.dt = inner.dt

    def reset(self) -> None:
        self.inner.reset()

    def describe(self):
        return self.inner.describe()

    def step(self, ref, fb):
        self.steps += 1
        if self.steps == self.at:
            self.clock.t += self.stall_s
        return self.inner.step(ref, fb)


def _paced_run(stall_s: float, *, paced: bool = True, rpdo_timeout_ms: int | None = None):
    from drivectl.controllers.registry import make_controller
    from drivectl.controllers.runtime.servo import Channel, Pacer, run_channels
    from drivectl.machine.build import open_machine
    from drivectl.machine.config import load_config

    cfg = load_config(None)
    ac = cfg.axis("x")
    if rpdo_timeout_ms is not None:
        object.__setattr__(ac, "rpdo_timeout_ms", rpdo_timeout_ms)
    from drivectl.profiles.library import load_profile

    prof = load_profile(ac.profile)
    clock = SimWallClock(100.0)
    m = open_machine(cfg, ["x"], start={"x": prof.start_position})
    ctrl = make_controller(ac.controller, cfg.cycle_s, ac.controller_settings, plant=m.specs["x"], axis="x")
    late = _LateMaster(ctrl, clock, at=200, stall_s=stall_s)
    pacer = Pacer(cfg.cycle_s, now=clock.now, sleep=clock.sleep) if paced else False
    try:
        res = run_channels([Channel(m.axes["x"], late, prof, ac.limits)], duration=0.4, pace=pacer)
        return res, m.drives["x"], m
    finally:
        m.close()


def test_paced_in_process_a_late_master_is_caught_by_the_drive_deadline():
    """--paced in-process: the drive's RPDO deadline (0x1400:05, 17 ms from x's physics: docs/timing.md) runs
    on the wall clock, as across processes. A master 25 ms late is caught by the drive (0x8250, reaction per
    0x6007); the master sees the drive leave Operation Enabled in its next sample and stops, the end state
    reported by the drive."""
    from drivectl.controllers.runtime.servo import StopReason

    res, drive, _ = _paced_run(0.025)
    assert drive._rpdo_timeout_ms == 17
    assert res.stop is StopReason.FAULT
    f = res.fault
    assert f.kind in ("drive left Operation Enabled", "drive fault") and f.cycle == 200, f
    assert drive.drive.error_code == 0x8250  # the drive's own reaction: RPDO deadline
    assert f.safe_state["x"].split(" (")[0] in ("Switch On Disabled", "Fault") and f.safe_after["x"] is not None
    assert res.trace.meta["fault_kind"] == f.kind and res.trace.meta["paced"] == "wall clock"
    assert res.detail.endswith("(its 0x603F: 0x8250: RPDO timeout (the master's setpoint came too late))")
    assert res.trace.meta["stop_detail"] == res.detail


def test_paced_in_process_a_master_within_the_deadline_is_not_caught():
    """The same stall within the RPDO deadline (20 ms configured), and a master on time: the run completes;
    so does the 5 ms stall in lockstep (simulated time: no wall clock)."""
    for stall, timeout, paced in ((0.005, 20, True), (0.0, None, True), (0.005, None, False)):
        res, drive, _ = _paced_run(stall, paced=paced, rpdo_timeout_ms=timeout)
        assert res.ok, (stall, timeout, paced, res.detail)
        assert drive.drive.error_code == 0


def test_after_a_paced_run_the_drive_is_back_on_lockstep_time():
    """Once the paced run ended the drive's clock is the SYNCs' again: a lockstep pause of any length between
    frames is not a late master."""
    from drivectl.driver.network import Lockstep

    res, drive, m = _paced_run(0.0)
    assert res.ok
    lockstep = drive.network.lockstep
    assert isinstance(lockstep, Lockstep) and lockstep._wall is None and not drive._served


def test_the_resident_wall_clock_loop_is_caught_by_the_drive_deadline_too(tmp_path):
    """The session's loop on the wall clock (controllers/runtime/loop.py) paces the in-process drives as
    ``trace --paced`` does: a loop 200 ms late (a jump injected through its clock, so the outcome does not
    depend on how busy the machine is; below its own stall bound) is caught by the drive's RPDO deadline
    (50 ms here, so that real scheduling hiccups of a loaded test machine do not count)."""

    from drivectl.controllers.registry import make_controller
    from drivectl.controllers.runtime.servo import Channel
    from drivectl.machine.build import open_machine
    from drivectl.machine.config import load_config

    cfg = load_config(None)
    ac = cfg.axis("x")
    object.__setattr__(ac, "rpdo_timeout_ms", 50)
    m = open_machine(cfg, ["x"])
    axis, drive = m.axes["x"], m.drives["x"]
    ch = Channel(axis, make_controller("pid-dob", cfg.cycle_s, {}, plant=m.specs["x"], axis="x"), None, ac.limits)
    loop, jump = enabled_wall_loop(ch, stall_s=5.0, fault_dir=tmp_path)
    try:
        assert drive.drive.error_code == 0
        jump["s"] = 0.2
        assert loop.run_until(lambda: loop.faults, 10.0)
        assert drive.drive.error_code == 0x8250  # the drive's own reaction: RPDO deadline, on the loop's clock
        assert "0x8250" in loop.faults[0].detail and loop.status()["stalls"] == 0
    finally:
        loop.close()
        m.close()
    assert axis.power is not cia402.PowerState.OPERATION_ENABLED
    assert drive.network.lockstep._wall is None  # the loop ended: the drive is back on SYNC time


def test_the_drives_own_absence_is_not_the_masters_silence(served):
    """A starved host or VM stops the emulator's process too: a gap it slept through itself is no evidence
    against the master (it judges again from its return); silence it watched is."""
    s = served
    s.sdo_write(cia402.CONSUMER_HEARTBEAT_TIME, 1, (0x7F << 16) | 300, 4)
    s.sdo_write(0x1400, 5, 2, 2)
    s.enable()
    s.send(0x201, struct.pack("<Hh", 0x0F, 0))
    s.serve(0.400)  # the emulator itself was away 400 ms (> the 300 ms window): an RPDO was waiting, no SYNC
    assert s.reactions == [] and s.drive.drive.power is cia402.PowerState.OPERATION_ENABLED
    t = s.now
    while not s.reactions and s.now - t < 1.0:  # then the master is silent while the emulator watches
        s.serve(0.010)
    assert s.reactions == [0x8250] and 0.29 <= s.now - t <= 0.32


def test_told_the_master_is_in_lockstep_the_drive_s_time_is_the_sync_count_only(served):
    """Issue 39 point 5: in lockstep across processes (0x5FFF:2 = 1) the drive never runs on its own clock: a master
    silent for seconds (a slow host's lockstep wait, a user idle in the shell) stops its time, nothing is missed
    and nothing moves; its RPDO deadline and heartbeat consumer count SYNCs. An NMT reset puts it back."""
    from drivectl.driver.emulator_clock import CLOCK_LOCKSTEP, CLOCK_OWN, CLOCK_SUB, EMULATOR_OBJECT

    s = served
    s.sdo_write(cia402.CONSUMER_HEARTBEAT_TIME, 1, (0x7F << 16) | 300, 4)
    s.sdo_write(0x1400, 5, 2, 2)  # RPDO deadline 2 ms (2 SYNCs)
    s.enable()
    s.sdo_write(EMULATOR_OBJECT, CLOCK_SUB, CLOCK_LOCKSTEP, 1)
    d = s.drive
    steps = d.drive.free_steps
    for _ in range(50):
        s.serve(0.1)  # 5 s of wall time, no SYNC
    assert s.reactions == [] and d.drive.free_steps == steps and d.drive.power is cia402.PowerState.OPERATION_ENABLED
    for _ in range(3):  # SYNCs without a setpoint: the deadline counts them (2 ms = 2 SYNCs)
        s.send(0x080, b"")
        s.serve(0.5)
    assert s.reactions == [0x8250] and d.drive.free_steps == steps
    s.send(0x000, b"\x81\x01")  # NMT reset node: the clock is the drive's own again
    s.serve(0.0)
    assert d.master_clock == CLOCK_OWN


def test_told_the_master_s_slots_a_sync_whose_counter_jumped_first_runs_the_gap(served):
    """Issue 39 point 2: a paced master tells drivectl's emulated drive to step by its slots (0x5FFF:2 = 2) and
    sends its slot count as the SYNC counter byte: a SYNC whose counter jumped by n (the master woke late and
    skipped n - 1 slots) first runs n - 1 cycles on the drive's own clock, the setpoint held; the RPDO deadline
    counts them (a late master is caught by the drive, as by a real one)."""
    from drivectl.driver.emulator_clock import CLOCK_SLOTS, CLOCK_SUB, EMULATOR_OBJECT

    s = served
    s.sdo_write(0x1400, 5, 17, 2)  # RPDO deadline 17 ms
    s.enable()
    assert s.sdo_write(EMULATOR_OBJECT, CLOCK_SUB, CLOCK_SLOTS, 1)[0] == 0x60
    d = s.drive.drive
    before = d.syncs + d.free_steps
    for counter in (239, 240, 1, 6, 7):  # (the counter wraps from 240 to 1)  slots: -, 1, 1, 5, 1
        s.send(0x201, struct.pack("<Hh", 0x0F, 0))
        s.send(0x080, bytes([counter]))
        s.serve(0.001)
    assert d.syncs + d.free_steps - before == 1 + 1 + 1 + 5 + 1 and d.free_steps == 4
    assert s.reactions == [] and d.power is cia402.PowerState.OPERATION_ENABLED
    assert s.drive.deadline_why == ""
    s.send(0x080, bytes([7 + 18]))  # 18 slots without a setpoint: past the 17 ms deadline, caught in the gap
    s.serve(0.001)
    assert d.power is cia402.PowerState.SWITCH_ON_DISABLED and d.error_code == 0x8250
    # the drive says whose the time was: the master's skipped slots, not lost frames nor its own clock
    why = s.drive.deadline_why
    assert why.startswith("18 ms of drive time") and "1 SYNC(s), 17 slot(s) the master skipped" in why
    assert "0 cycle(s) on the drive's own clock" in why


def test_a_sync_sent_late_after_its_slot_is_not_run_twice_when_the_next_counter_skips(served):
    """A drive told the master's slots (0x5FFF:2) whose SYNC-loss window is short enough for a gap to run on its
    own clock (2 cycles here, as a paced in-process drive's). A master held off between taking its slot and
    sending the SYNC sends it 9.5 ms late: the drive ran that gap; the next SYNC's counter then says the master
    skipped those slots. The same wall time runs once, not twice (the plant 9 cycles ahead of the master)."""
    from drivectl.driver.emulator_clock import CLOCK_SLOTS, CLOCK_SUB, EMULATOR_OBJECT

    s = served
    s.sdo_write(0x1400, 5, 17, 2)  # RPDO deadline 17 ms
    s.enable()
    s.sdo_write(EMULATOR_OBJECT, CLOCK_SUB, CLOCK_SLOTS, 1)
    d = s.drive.drive
    s.drive.wall_clock(None)
    s.drive.wall_clock(s.now)  # paced in-process: the SYNC-loss window is 2 cycles

    def sync(counter: int, wait_s: float) -> None:
        s.send(0x201, struct.pack("<Hh", 0x0F, 0))
        s.send(0x080, bytes([counter]))
        s.serve(wait_s)

    for counter in (10, 11):
        sync(counter, 0.001)
    before, t = d.syncs + d.free_steps, s.now
    s.serve(0.0095)  # slot 12 taken on time, its SYNC sent 9.5 ms late: the drive runs the gap on its own clock
    sync(12, 0.0005)
    sync(22, 0.001)  # the master woke late: slots 13..21 skipped (the same wall time)
    cycles = d.syncs + d.free_steps - before
    # 11 slots by the counter (11 to 22), 11 ms of wall time: 11 cycles (the gap run twice before: 19, the plant
    # 9 cycles ahead of the master's time)
    assert round((s.now - t) * 1000) == 11 and cycles == 11, cycles
    assert s.reactions == [] and d.power is cia402.PowerState.OPERATION_ENABLED
    for counter in (23, 24):  # back on the SYNCs: one cycle each, nothing carried over
        sync(counter, 0.001)
    assert d.syncs + d.free_steps - before == cycles + 2

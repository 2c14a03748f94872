"""The drive over CANopen, with real frames on python-can's virtual bus (one unique channel per test)."""

from __future__ import annotations

import logging

import canopen
import numpy as np
import pytest

from drivectl.controllers.registry import make_controller
from drivectl.controllers.runtime.servo import run
from drivectl.driver import cia402
from drivectl.driver.axis import AxisError, FaultKind
from drivectl.driver.canopen_axis import CanopenAxis, Identity, SyncClock
from drivectl.driver.capabilities import assess
from drivectl.driver.cia301 import HEARTBEAT_BASE, NMT_COB_ID, NmtCommand, NmtState
from drivectl.driver.cia402 import Command, PowerState
from drivectl.driver.network import Lockstep, LockstepNetwork, open_bus, unique_virtual_channel
from drivectl.driver.units import EffortScale, Encoder
from drivectl.machine.build import open_machine
from drivectl.machine.config import load_config
from drivectl.plant_emulator.models import load_plant
from drivectl.plant_emulator.node402 import EMULATED_DRIVE_EDS, EmulatedDrive
from drivectl.profiles.library import load_profile
from drivectl.profiles.ptp import PointToPoint

DT = 0.001


class Bench:
    """An emulator network and a master network on one fresh virtual channel, in lockstep."""

    def __init__(self) -> None:
        self.lockstep = Lockstep()
        self.channel = unique_virtual_channel("test")
        self.emu = LockstepNetwork(open_bus("virtual", self.channel), self.lockstep)
        self.master = LockstepNetwork(open_bus("virtual", self.channel), self.lockstep)
        self.clock = SyncClock(self.master)
        self.drives: dict[int, EmulatedDrive] = {}

    def drive(self, node_id: int = 1, plant: str = "rigid-x", **kw) -> EmulatedDrive:
        d = EmulatedDrive(self.emu, node_id, load_plant(plant).build(DT), rated_effort=100.0, **kw)
        d.boot()
        self.drives[node_id] = d
        return d

    def axis(self, node_id: int = 1, connect: bool = True, **kw) -> CanopenAxis:
        ax = CanopenAxis(self.master, node_id, name=f"n{node_id}", dt=DT, effort_unit="N", eds=EMULATED_DRIVE_EDS,
                         encoder=Encoder(), effort_scale=EffortScale(100.0), clock=self.clock, **kw)
        if connect:
            ax.connect()
        return ax

    def close(self) -> None:
        self.master.disconnect()
        self.emu.disconnect()


@pytest.fixture
def bench():
    b = Bench()
    yield b
    b.close()


def test_eds_reads_and_has_every_cst_object():
    od = canopen.import_od(str(EMULATED_DRIVE_EDS), 1)
    assert assess(od, "x").missing == ()  # every optional object drivectl uses (driver/capabilities.py)
    assert od[cia402.SUPPORTED_DRIVE_MODES].default & cia402.supported_mode_bit(cia402.Mode.CYCLIC_SYNC_TORQUE)
    assert od[cia402.DEVICE_TYPE].default == cia402.DEVICE_TYPE_SERVO


def test_eds_missing_a_required_object_is_refused(bench, tmp_path):
    text = EMULATED_DRIVE_EDS.read_text()
    start = text.index("[6071]")
    end = text.index("[", start + 1)
    broken = tmp_path / "broken.eds"
    broken.write_text(text[:start] + text[end:])
    with pytest.raises(AxisError, match=r"broken.eds: drive has no torque setpoint 0x6071: drivectl closes the loop"):
        CanopenAxis(bench.master, 1, name="x", dt=DT, effort_unit="N", eds=broken, encoder=Encoder(),
                    effort_scale=EffortScale(100.0), clock=bench.clock)


def test_boot_configures_cst_and_the_pdo_mapping_reads_back(bench):
    drive = bench.drive(1)
    ax = bench.axis(1)
    assert drive.nmt is NmtState.OPERATIONAL and drive.mode == cia402.Mode.CYCLIC_SYNC_TORQUE
    assert ax.read_back_mapping() == {
        "rpdo1": [0x60400010, 0x60710010],
        "tpdo1": [0x60410010, 0x60640020],
        "tpdo2": [0x606C0020, 0x60770010],
    }
    assert ax.node.sdo[cia402.COMM_CYCLE_PERIOD].raw == 1000
    assert ax.node.sdo[cia402.PRODUCER_HEARTBEAT_TIME].raw == 100


def test_wrong_identity_is_refused(bench):
    bench.drive(1)
    ax = bench.axis(1, connect=False, identity=Identity(vendor_id=0x12345678))
    with pytest.raises(AxisError, match=r"answered vendor 0x00D71C70.*expects vendor 0x12345678.*vendor differs"):
        ax.connect()


def test_no_drive_at_the_node_id_times_out_with_a_clear_error(bench):
    bench.drive(1)
    ax = bench.axis(9, connect=False)
    with pytest.raises(AxisError, match="node 9: no boot-up message"):
        ax.connect()


def test_sdo_abort_is_reported_with_node_and_object(bench, caplog):
    bench.drive(1)
    ax = bench.axis(1)
    with pytest.raises(AxisError, match=r"node 1: SDO 0x6060 aborted"):
        ax._sdo(cia402.MODES_OF_OPERATION, value=int(cia402.Mode.PROFILE_POSITION))  # not supported: abort
    with pytest.raises(canopen.SdoAbortedError, match="0x06020000"):
        ax.node.sdo.upload(0x2000, 0)  # the drive itself answers: object does not exist
    with pytest.raises(AxisError, match=r"node 1: object 0x2000 is not in the EDS"):
        ax._sdo(0x2000)


@pytest.mark.parametrize(("state", "command", "expected"),
                         [(s, c, e) for (s, c), e in cia402.DRIVE_TRANSITIONS.items()])
def test_each_cia402_transition_with_real_frames(bench, state, command, expected):
    drive = bench.drive(1)
    ax = bench.axis(1)
    drive.drive.power = state
    drive.drive.quick_stop_option = 6  # stay in Quick Stop Active (else it completes to Switch On Disabled)
    drive.controlword = int(cia402._HOLD[state])  # the command that keeps the state for the first SYNC
    ax.read()  # SYNC: the TPDO reports the state we set
    assert ax.power is state
    ax._controlword = int(command)  # what the master sends in its RPDO, bypassing its own path
    ax.write(0.0)
    ax.read()
    assert ax.power is expected, (state, command, ax.power)
    assert cia402.decode_statusword(ax.statusword) is expected


def test_every_statusword_decodes_as_the_cia402_table_says():
    # CiA 402 (table of the statusword's state bits), written out here, not read from cia402's own patterns:
    # the decoder reads a table made from those once, so a wrong table must show on some statusword
    spec = [(0x4F, 0x00, PowerState.NOT_READY_TO_SWITCH_ON), (0x4F, 0x40, PowerState.SWITCH_ON_DISABLED),
            (0x6F, 0x21, PowerState.READY_TO_SWITCH_ON), (0x6F, 0x23, PowerState.SWITCHED_ON),
            (0x6F, 0x27, PowerState.OPERATION_ENABLED), (0x6F, 0x07, PowerState.QUICK_STOP_ACTIVE),
            (0x4F, 0x0F, PowerState.FAULT_REACTION_ACTIVE), (0x4F, 0x08, PowerState.FAULT)]
    for sw in range(0x10000):
        want = next((state for mask, value, state in spec if sw & mask == value), PowerState.NOT_READY_TO_SWITCH_ON)
        assert cia402.decode_statusword(sw) is want, f"0x{sw:04X}"


def test_enable_quick_stop_and_fault_reset_through_the_cycle(bench):
    drive = bench.drive(1)
    ax = bench.axis(1)
    ax.enable()
    seen = []
    for _ in range(3):
        ax.read()
        ax.write(0.0)
        seen.append(ax.power)
    assert seen[-1] is PowerState.OPERATION_ENABLED
    drive.drive.fault(0x7305)
    ax.read()
    ax.write(0.0)
    ax.read()
    assert ax.power is PowerState.FAULT and ax.read_error_code() == 0x7305
    with pytest.raises(AxisError, match="incremental sensor"):
        ax.enable()
    ax.fault_reset()
    edges = []
    for _ in range(4):
        ax.write(0.0)
        edges.append(drive.controlword & Command.FAULT_RESET)
        ax.read()
    assert ax.power is PowerState.SWITCH_ON_DISABLED  # verified by the statusword
    assert 0x80 in edges


def test_nmt_reset_gives_boot_up_and_stops_the_tpdos(bench):
    drive = bench.drive(1)
    ax = bench.axis(1)
    seen = []
    bench.master.subscribe(HEARTBEAT_BASE + 1, lambda cob, data, ts: seen.append(bytes(data)))
    bench.master.send_message(NMT_COB_ID, bytes([NmtCommand.RESET_NODE, 1]))
    assert seen == [] and drive.nmt is NmtState.INITIALISING  # a drive boots for a while (50 ms default)
    bench.lockstep.advance(0.049)
    assert seen == []
    bench.lockstep.advance(0.001)
    assert seen == [b"\x00"] and drive.nmt is NmtState.PRE_OPERATIONAL
    with pytest.raises(AxisError, match="unexpected boot-up") as info:
        ax.read()  # the boot-up of a drive the master runs is a fault of its own, raised once
    assert info.value.kind is FaultKind.UNEXPECTED_BOOT
    ax.read()  # then bridged once (no TPDO in Pre-operational) ...
    for _ in range(ax.max_lost_cycles - 1):
        ax.read()
    with pytest.raises(AxisError, match="no TPDO for 4 cycles") as info:
        ax.read()  # ... and then a fault
    assert info.value.kind is FaultKind.TPDO_TIMEOUT


def test_heartbeat_in_simulated_time(bench):
    bench.drive(1)
    ax = bench.axis(1)
    beats = []
    bench.master.subscribe(HEARTBEAT_BASE + 1, lambda cob, data, ts: beats.append(bytes(data)))
    for _ in range(350):
        ax.read()
        ax.write(0.0)
    assert beats == [bytes([NmtState.OPERATIONAL])] * 3  # every 100 ms of SYNCs


def test_two_nodes_on_one_bus_share_one_sync(bench):
    dx = bench.drive(1, "rigid-x")
    dy = bench.drive(2, "rigid-y")
    ax, ay = bench.axis(1), bench.axis(2)
    syncs = []
    bench.emu.subscribe(0x80, lambda cob, data, ts: syncs.append(1))
    for a in (ax, ay):
        a.enable()
    for _ in range(200):
        for a, u in ((ax, 200.0), (ay, -250.0)):
            a.read()
            a.write(u)
    assert len(syncs) == 200
    assert dx.drive.syncs == dy.drive.syncs == 200 + 2 * 0  # both stepped by the same SYNCs
    assert dx.drive.position > 0 > dy.drive.position


def test_rpdo_data_lands_in_the_object_dictionary(bench):
    bench.drive(1)
    ax = bench.axis(1)
    ax.read()
    ax.write(12.3)  # 123 per mille of 100 N
    assert ax.node.sdo[cia402.TARGET_TORQUE].raw == 123
    assert ax.node.sdo[cia402.CONTROLWORD].raw == ax._controlword


def _applied_after(ax: CanopenAxis, drive: EmulatedDrive, effort: float) -> float:
    """Command ``effort`` straight to the drive (past any master-side clip) and read what it applied."""
    for _ in range(3):
        ax.read()
        ax.write(effort)
    ax.read()
    return drive.drive.applied


def test_the_drive_clips_the_torque_to_the_configured_max_torque(bench):
    """limits.max_effort goes to the drive as 0x6072: a second limit, in the drive, on its own."""
    drive = bench.drive(1)
    ax = bench.axis(1, max_effort=25.0)  # 250 per mille of 100 N
    assert ax.node.sdo[cia402.MAX_TORQUE].raw == 250 and drive.max_torque == 250
    ax.enable()
    assert _applied_after(ax, drive, 12.3) == pytest.approx(12.3)  # inside: as commanded
    assert _applied_after(ax, drive, 80.0) == pytest.approx(25.0)  # beyond: the drive's limit
    assert _applied_after(ax, drive, -80.0) == pytest.approx(-25.0)
    assert ax.node.sdo[cia402.TORQUE_ACTUAL].raw == -250  # and reports it so (0x6077)
    # an NMT reset brings back the EDS default (32767: no limit inside 0x6071's range) until connect()
    ax.disable()
    drive.reset()
    assert drive.max_torque == 32767
    ax.connect()
    assert drive.max_torque == 250


def test_reconnecting_after_a_reset_keeps_one_handler_per_tpdo(bench):
    """A drive reset and connect() again, many times: a late TPDO still counts once, nothing piles up."""
    drive = bench.drive(1)
    ax = bench.axis(1)
    for _ in range(5):
        drive.reset(spontaneous=True)
        ax.connect()
    cob = ax._tpdo_cob[0]
    ax.read()  # this cycle's TPDOs used: one arriving now is late
    before = ax.late_total
    bench.master.notify(cob, bytes(6), 0.0)
    assert ax.late_total == before + 1
    # one handler per TPDO, ours (canopen's PdoMap decoder, subscribed by its save(), is taken off)
    assert bench.master.subscribers[cob] == [ax._tpdo_handlers[0]]
    bench.master.subscribe(cob, seen := [].append)  # someone else listening on the same COB-ID
    ax.close()
    assert seen in bench.master.subscribers[cob] and ax._tpdo_handlers[0] not in bench.master.subscribers[cob]
    assert HEARTBEAT_BASE + 1 not in bench.master.subscribers or \
        ax._on_heartbeat not in bench.master.subscribers[HEARTBEAT_BASE + 1]


def test_a_node_reset_restores_every_parameter_the_master_wrote(bench):
    """NMT reset node: the application parameters go back to the EDS defaults, as on a real drive."""
    drive = bench.drive(1)
    ax = bench.axis(1, max_effort=25.0)
    defaults = {i: drive._od_default(i) for i in (cia402.QUICK_STOP_OPTION, cia402.MAX_TORQUE,
                                                  cia402.PRODUCER_HEARTBEAT_TIME)}
    ax.node.sdo[cia402.QUICK_STOP_OPTION].raw = 6
    ax.node.sdo[cia402.PRODUCER_HEARTBEAT_TIME].raw = 250
    assert (drive.drive.quick_stop_option, drive.max_torque, drive._heartbeat_ms) == (6, 250, 250)
    drive.reset()
    bench.lockstep.advance(0.05)  # booted again (no SDO while it initialises)
    assert drive.drive.quick_stop_option == defaults[cia402.QUICK_STOP_OPTION] != 6
    assert drive.max_torque == defaults[cia402.MAX_TORQUE] != 250
    assert drive._heartbeat_ms == defaults[cia402.PRODUCER_HEARTBEAT_TIME] != 250
    assert ax.node.sdo[cia402.QUICK_STOP_OPTION].raw == defaults[cia402.QUICK_STOP_OPTION]


def test_the_machine_writes_each_axis_limit_to_its_drive():
    cfg = load_config(None)
    machine = open_machine(cfg, ["x", "z"], faults=[])
    try:
        for n in ("x", "z"):
            want = round(cfg.axis(n).limits.max_effort * 1000 / cfg.axis(n).rated_effort)
            assert machine.drives[n].max_torque == want == machine.axes[n].max_torque_permille
        assert machine.drives["x"].max_torque == 3000 and machine.drives["z"].max_torque == 5000
    finally:
        machine.close()


def test_unlimited_max_effort_leaves_the_drives_own_limit(bench):
    drive = bench.drive(1)
    ax = bench.axis(1)  # max_effort unlimited: 0x6072 not written, the drive's own value holds
    assert ax.max_torque_permille is None and drive.max_torque == 32767
    ax.enable()
    assert _applied_after(ax, drive, 150.0) == pytest.approx(150.0)
    ax.node.sdo[cia402.MAX_TORQUE].raw = 1000  # set on the drive by its own tool: rated
    assert _applied_after(ax, drive, 150.0) == pytest.approx(100.0)
    with pytest.raises(ValueError, match="max_effort: must be > 0"):
        bench.axis(2, connect=False, max_effort=0.0)


@pytest.mark.parametrize(
    ("controller", "plant", "settings"),
    [
        ("smc", "two-mass", {}),
        ("vprl", "two-mass", {}),
        ("pid-nftsm", "two-mass", {"m_tilde": 0.15, "accel_filter_hz": 150.0}),
        ("asmc", "rigid-x", {"law": 14}),
        ("pid", "rigid-x", {}),
        ("pid-dob", "rigid-x", {}),
    ],
)
def test_same_trace_over_the_bus_as_in_simulation_bit_for_bit(controller, plant, settings):
    cfg = load_config()
    name = "z" if plant == "two-mass" else "x"
    profile = (load_profile("seed-000", axis=name) if name == "z"
               else PointToPoint(0.0, 0.02, 0.05, 0.5, 20.0, hold_until=0.6))
    traces = []
    for sim in (True, False):
        with open_machine(cfg, [name], sim=sim, plant=plant, noise=0.5 if name == "x" else 0.0, seed=3) as m:
            ctrl = make_controller(controller, DT, settings, plant=m.specs[name], axis="x")
            res = run(m.axes[name], ctrl, profile, duration=0.6)
            assert res.ok, res.detail
            traces.append(res.trace)
    sim_tr, bus_tr = traces
    assert np.array_equal(sim_tr.pos, bus_tr.pos)
    assert np.array_equal(sim_tr.effort, bus_tr.effort)
    assert np.abs(bus_tr.pos).max() > 1e-3  # it moved


def test_canopen_error_logs_fail_tests(fail_on_canopen_errors):
    # the autouse fixture's handler sees what canopen logs at ERROR from a swallowed callback error
    net = canopen.Network()

    def boom(can_id, data, ts):
        raise RuntimeError("callback failed")

    net.subscribe(0x123, boom)
    import can
    from canopen.network import MessageListener
    MessageListener(net).on_message_received(can.Message(arbitration_id=0x123, data=b""))
    assert any("callback failed" in r.getMessage() for r in fail_on_canopen_errors.records)
    fail_on_canopen_errors.records.clear()  # expected here; anywhere else it fails the test
    logging.getLogger("canopen").debug("ok")


@pytest.mark.parametrize("suffix", [".asc", ".blf", ".log"])
def test_bus_log_reads_back_with_the_sync_pdo_sequence(tmp_path, suffix, capsys):
    import can

    from drivectl.tools.cli.main import main

    log = tmp_path / f"bus{suffix}"
    rc = main(["trace", "--axis", "x", "--duration", "0.02", "--out", str(tmp_path), "--no-plot", "--quiet",
               "--bus-log", str(log)])
    assert rc == 0
    ids = [m.arbitration_id for m in can.LogReader(str(log))]
    # the master's NMT reset (the drive is still booting from power-on), then the drive's boot-up
    assert ids[:2] == [NMT_COB_ID, HEARTBEAT_BASE + 1]
    assert NMT_COB_ID in ids and 0x601 in ids and 0x581 in ids  # NMT, SDO configuration
    assert HEARTBEAT_BASE + 0x7F in ids  # the master's own heartbeat, from the first SYNC
    first_sync = ids.index(0x80)
    cyclic = [i for i in ids[first_sync:] if not HEARTBEAT_BASE <= i < HEARTBEAT_BASE + 0x80][:4 * 21]
    # every cycle: SYNC, then the drive's two TPDOs, then the master's RPDO
    assert cyclic == [0x80, 0x181, 0x281, 0x201] * 21


def test_bus_log_with_an_unknown_suffix_is_bad_input(tmp_path, capsys):
    from drivectl.tools.cli.main import main

    rc = main(["trace", "--axis", "x", "--duration", "0.01", "--out", str(tmp_path), "--bus-log",
               str(tmp_path / "bus.xyz")])
    err = capsys.readouterr().err
    assert rc == 2 and "bus.xyz: unknown log format" in err


def test_master_notices_a_lost_heartbeat(bench):
    drive = bench.drive(1)
    ax = bench.axis(1)
    for _ in range(250):
        ax.read()
        ax.write(0.0)
    drive._heartbeat_ms = 0  # the drive stops producing (TPDOs still come)
    with pytest.raises(AxisError, match="heartbeat lost"):
        for _ in range(400):
            ax.read()
            ax.write(0.0)


def test_master_heartbeat_is_configured_on_the_drive_and_produced(bench):
    bench.drive(1)
    ax = bench.axis(1)
    assert ax.node.sdo[cia402.CONSUMER_HEARTBEAT_TIME][1].raw == (0x7F << 16) | 300
    beats = []
    bench.emu.subscribe(HEARTBEAT_BASE + 0x7F, lambda cob, data, ts: beats.append(bytes(data)))
    for _ in range(250):
        ax.read()
        ax.write(0.0)
    assert beats == [bytes([NmtState.OPERATIONAL])] * 3  # SYNC 1, 101, 201

"""Issue 19 point 4: the minimal mapping (TPDO1 statusword + position, RPDO1 target torque, the controlword in an
event-driven RPDO2 sent only when it changes) fits four axes on one 1 Mbit/s bus at 1 kHz under 70 %; the
drive's state machine sees the same controlword sequence as with the cyclic mappings."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import reset_fault

from drivectl.controllers.registry import make_controller
from drivectl.controllers.runtime.servo import Channel, StopReason, run_channels
from drivectl.driver import cia402
from drivectl.driver.canopen_axis import CanopenAxis, SyncClock
from drivectl.driver.cia301 import RPDO_BASE
from drivectl.driver.cia402 import Command, PowerState
from drivectl.driver.network import Lockstep, LockstepNetwork, open_bus, unique_virtual_channel
from drivectl.driver.units import EffortScale, Encoder
from drivectl.machine.build import open_machine
from drivectl.machine.bus_budget import axes_per_bus, bus_load
from drivectl.machine.config import DEFAULT_CONFIG_TOML, load_config
from drivectl.plant_emulator.faults import parse_fault
from drivectl.plant_emulator.models import load_plant
from drivectl.plant_emulator.node402 import EMULATED_DRIVE_EDS, EmulatedDrive
from drivectl.profiles.library import load_profile
from drivectl.tools.cli.main import main
from drivectl.tracefile.format import Trace

DT = 0.001

#: (nominal bits, nominal %, bound %) per cycle at 1 kHz on 1 Mbit/s, for 1..5 axes
FIGURES = {
    "full": [(316, 31.6, 38.0), (585, 58.5, 70.5), (854, 85.4, 103.0), (1123, 112.3, 135.5), (1392, 139.2, 168.0)],
    "compact": [(237, 23.7, 28.5), (427, 42.7, 51.5), (617, 61.7, 74.5), (807, 80.7, 97.5), (997, 99.7, 120.5)],
    "minimal": [(205, 20.5, 24.5), (363, 36.3, 43.5), (521, 52.1, 62.5), (679, 67.9, 81.5), (837, 83.7, 100.5)],
}


@pytest.mark.parametrize("mapping", FIGURES)
def test_bus_load_for_one_to_five_axes(mapping):
    for axes, (bits, pct, bound) in enumerate(FIGURES[mapping], 1):
        load = bus_load(axes, 0.001, 1_000_000, mapping)
        assert (load.bits_nominal, round(load.nominal_pct, 1), round(load.bound_pct, 1)) == (bits, pct, bound)
    assert axes_per_bus(0.001, 1_000_000, mapping=mapping) == {"full": 2, "compact": 3, "minimal": 4}[mapping]


class _Bus:
    def __init__(self, mapping: str = "minimal") -> None:
        lockstep = Lockstep()
        channel = unique_virtual_channel("minimal")
        self.emu = LockstepNetwork(open_bus("virtual", channel), lockstep)
        self.master = LockstepNetwork(open_bus("virtual", channel), lockstep)
        self.drive = EmulatedDrive(self.emu, 1, load_plant("rigid-x").build(DT), rated_effort=100.0)
        self.drive.boot()
        self.cw_frames: list[tuple[int, int]] = []  # (drive cycle, controlword) of every RPDO2
        self.emu.subscribe(RPDO_BASE[1] + 1, lambda cob, data, ts: self.cw_frames.append(
            (self.drive.drive.syncs, int.from_bytes(data[:2], "little"))))
        self.axis = CanopenAxis(self.master, 1, name="x", dt=DT, effort_unit="N", eds=EMULATED_DRIVE_EDS,
                                encoder=Encoder(), effort_scale=EffortScale(100.0), clock=SyncClock(self.master),
                                mapping=mapping)
        self.axis.connect()

    def cycle(self, n: int = 1) -> None:
        for _ in range(n):
            self.axis.read()
            self.axis.write(0.0)

    def close(self) -> None:
        self.axis.close()
        self.drive.close()
        self.master.disconnect()
        self.emu.disconnect()


@pytest.fixture
def bus():
    b = _Bus()
    yield b
    b.close()


def test_the_drive_accepts_the_minimal_remap(bus):
    ax = bus.axis
    assert ax.read_back_mapping() == {"rpdo1": [0x60710010], "rpdo2": [0x60400010], "tpdo1": [0x60410010, 0x60640020]}
    assert ax.node.sdo[cia402.TPDO_COMM + 1][1].raw & 0x80000000  # TPDO2 unused: disabled
    assert ax.node.sdo[cia402.RPDO_COMM + 1][2].raw == 255  # RPDO2 event-driven
    assert ax.node.sdo[cia402.RPDO_COMM][2].raw == 1 and ax.node.sdo[cia402.RPDO_COMM][5].raw == 2  # deadline
    assert np.isnan(ax.torque_actual)


def test_rpdo2_only_when_the_controlword_changes_enable_quick_stop_fault_reset(bus):
    ax, drive = bus.axis, bus.drive
    bus.cycle()
    assert [cw for _, cw in bus.cw_frames] == [ax.master.controlword(ax.power)]  # the first one after connect
    ax.enable()
    bus.cycle(5)
    assert ax.power is PowerState.OPERATION_ENABLED and drive.drive.power is PowerState.OPERATION_ENABLED
    sent = len(bus.cw_frames)
    bus.cycle(50)
    assert len(bus.cw_frames) == sent  # steady state: no controlword frame (but one every 100 cycles)
    cws = [cw for _, cw in bus.cw_frames]
    assert all(a != b for a, b in zip(cws, cws[1:], strict=False))  # each frame a change
    assert cws[-1] == int(Command.ENABLE_OPERATION)
    ax.quick_stop()
    bus.cycle(5)
    assert drive.drive.power in (PowerState.QUICK_STOP_ACTIVE, PowerState.SWITCH_ON_DISABLED)
    assert ax.power is drive.drive.power  # what the drive reported
    ax.disable()
    bus.cycle(3)
    assert ax.power is PowerState.SWITCH_ON_DISABLED
    drive.drive.fault(0x7305)
    bus.cycle(2)
    assert ax.power is PowerState.FAULT
    start = len(bus.cw_frames)
    ax.fault_reset()
    for _ in range(4):
        ax.write(0.0)
        ax.read()
    assert ax.power is PowerState.SWITCH_ON_DISABLED and drive.drive.power is PowerState.SWITCH_ON_DISABLED
    edge = [cw & Command.FAULT_RESET for _, cw in bus.cw_frames[start - 1:]]
    assert edge[:2] == [0, 0x80]  # the rising edge: bit 7 low in the frame before, then high


def test_the_rpdo_deadline_watches_the_cyclic_rpdo1_not_the_controlword(bus):
    ax, drive = bus.axis, bus.drive
    ax.enable()
    bus.cycle(5)
    assert drive.drive.power is PowerState.OPERATION_ENABLED
    for _ in range(5):  # RPDO1 (the torque) stops; only controlword frames keep coming
        ax.read()
        bus.master.send_message(RPDO_BASE[1] + 1, int(Command.ENABLE_OPERATION).to_bytes(2, "little"))
    assert drive.drive.power is not PowerState.OPERATION_ENABLED and drive.drive.error_code == 0x8250
    assert ax.power is not PowerState.OPERATION_ENABLED  # reported back by the TPDO


def _script(b: _Bus) -> list[int]:
    """Enable, quick stop, disable, fault, fault reset: the controlword the drive holds at each SYNC."""
    seen = []
    ax = b.axis

    def cycles(n: int) -> None:
        for _ in range(n):
            ax.read()
            ax.write(0.0)
            seen.append(b.drive.controlword)

    cycles(2)
    ax.enable()
    cycles(6)
    ax.quick_stop()
    cycles(4)
    ax.disable()
    cycles(3)
    b.drive.drive.fault(0x7305)
    cycles(2)
    ax.fault_reset()
    cycles(5)
    ax.enable()
    cycles(5)
    return seen


def test_the_drive_sees_the_same_controlword_sequence_as_with_the_cyclic_mapping():
    runs = {}
    for mapping in ("full", "minimal"):
        b = _Bus(mapping)
        try:
            runs[mapping] = (_script(b), b.drive.drive.power, len(b.cw_frames))
        finally:
            b.close()
    assert runs["minimal"][0] == runs["full"][0]
    assert runs["minimal"][1] is runs["full"][1] is PowerState.OPERATION_ENABLED
    assert any(cw & Command.FAULT_RESET for cw in runs["minimal"][0])
    # RPDO2 on changes, and resent while a transition is pending (the quick stop ends in Switch On Disabled,
    # not the Quick Stop Active asked for): fewer frames than cycles
    assert runs["full"][2] == 0 and 0 < runs["minimal"][2] < 27


def _config(tmp_path, mapping: str = "minimal"):
    text = DEFAULT_CONFIG_TOML.replace("bitrate = 1000000\n", f'bitrate = 1000000\npdo_mapping = "{mapping}"\n', 1)
    p = tmp_path / "m.toml"
    p.write_text(text)
    return load_config(p)


def test_minimal_quick_stop_by_a_limit_and_fault_reset_through_the_loop(tmp_path):
    cfg = _config(tmp_path)
    prof = load_profile("short-move")
    m = open_machine(cfg, ["x"], faults=[parse_fault("emcy-fault@0.1")], start={"x": prof.start_position})
    with m:
        axis, drive = m.axes["x"], m.drives["x"]
        assert axis.mapping == "minimal"
        ac = cfg.axis("x")
        ctrl = make_controller(ac.controller, cfg.cycle_s, ac.controller_settings, plant=m.specs["x"], axis="x")
        res = run_channels([Channel(axis, ctrl, prof, ac.limits)])
        assert res.stop is StopReason.FAULT and drive.drive.power is PowerState.FAULT
        reset_fault(axis)
        assert axis.power is PowerState.SWITCH_ON_DISABLED and drive.drive.error_code == 0
        # a feeble effort limit against a tight window: the following-error limit stops it by quick stop
        limits = type(ac.limits)(following_error=50e-6, following_time=0.005, max_effort=20.0)
        home = load_profile("short-move")
        from drivectl.profiles.ptp import PointToPoint

        move = PointToPoint(drive.drive.position, home.start_position, 0.05, 0.5, 20.0, hold_until=0.6)
        res = run_channels([Channel(axis, ctrl, move, limits)])
        assert res.stop is StopReason.FOLLOWING_ERROR
        assert drive.drive.power in (PowerState.QUICK_STOP_ACTIVE, PowerState.SWITCH_ON_DISABLED)


def _four_axes(tmp_path, mapping: str = "auto"):
    text = ["cycle_s = 0.001", "[bus]", 'interface = "virtual"', f'pdo_mapping = "{mapping}"']
    for i, name in enumerate("wxyz", 1):
        text += [f"[axes.{name}]", f"node_id = {i}", "rated_effort = 100.0", 'plant = "rigid-x"',
                 'controller = "pid"', 'profile = "short-move"']
    p = tmp_path / "m.toml"
    p.write_text("\n".join(text) + "\n")
    return p


def test_four_axes_fit_with_auto_and_the_bus_equals_sim_bit_for_bit(tmp_path, capsys):
    p = _four_axes(tmp_path)
    argv = ["--config", str(p), "trace", "--axis", "w,x,y,z", "--duration", "0.05", "--out", str(tmp_path / "out"),
            "--quiet", "--no-plot"]
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert "bus load 67.9 % of 1 Mbit/s (81.5 % with worst-case stuffing): 4 axes, minimal mapping" in err
    bus = {n: Trace.read(tmp_path / "out" / f"{n}.csv") for n in "wxyz"}
    assert main([*argv, "--sim"]) == 0
    sim = {n: Trace.read(tmp_path / "out" / f"{n}.csv") for n in "wxyz"}
    for name in bus:
        assert len(bus[name].columns["pos_m"]) == 51
        for col in ("pos_m", "effort", "vel_m_s"):
            assert np.array_equal(bus[name].columns[col], sim[name].columns[col]), (name, col)
    assert np.ptp(bus["w"].columns["pos_m"]) > 0  # it moved


def test_a_lost_controlword_frame_does_not_stall_a_transition_and_steady_state_is_refreshed(bus):
    """The minimal mapping's RPDO2 is event-driven: a lost frame must not leave the drive where it was until
    the next change. Resent each cycle while the drive has not reached the state asked for; every 100
    cycles in steady state."""
    ax, drive, net = bus.axis, bus.drive, bus.master
    bus.cycle(2)
    send, dropped = net.send_message, []

    def lossy(can_id, data, remote=False):
        if can_id == RPDO_BASE[1] + 1 and len(dropped) < 2:
            dropped.append(bytes(data))  # the first two controlword frames after enable() are lost
            return
        send(can_id, data, remote)

    net.send_message = lossy
    ax.enable()
    bus.cycle(6)
    assert len(dropped) == 2 and ax.power is PowerState.OPERATION_ENABLED
    assert drive.drive.power is PowerState.OPERATION_ENABLED
    n = len(bus.cw_frames)
    bus.cycle(250)
    refresh = bus.cw_frames[n:]
    assert len(refresh) == 2 and all(cw == int(Command.ENABLE_OPERATION) for _, cw in refresh)
    assert refresh[1][0] - refresh[0][0] == 100

"""Issue 7: faults injected into the emulated drive and its bus, detected by the master, every axis
brought to a safe state within two cycles, the trace kept whole with the fault in its metadata."""

from __future__ import annotations

import pytest
from helpers import reset_fault

from drivectl.controllers.registry import make_controller
from drivectl.controllers.runtime.servo import Channel, LimitError, StopReason, run_channels
from drivectl.driver import cia402
from drivectl.driver.cia402 import PowerState
from drivectl.machine.build import open_machine
from drivectl.machine.config import DEFAULT_CONFIG_TOML, load_config
from drivectl.plant_emulator.faults import KINDS, FaultInjector, FaultSpec, FaultSpecError, parse_fault
from drivectl.profiles.library import load_profile
from drivectl.tools.cli.main import main
from drivectl.tools.conformance.fault_matrix import CASES, SAFE_BOUND_CYCLES, run_case
from drivectl.tracefile.format import Trace


def test_the_matrix_covers_every_kind():
    assert {case.split(":")[0] for case in CASES} == set(KINDS)


@pytest.mark.parametrize("case", list(CASES))
def test_fault_matrix(case, tmp_path):
    expect_stop, expect_kind = CASES[case]
    o = run_case(case, out_dir=tmp_path)
    assert o.detected, o
    assert o.safe_within_cycles is not None and o.safe_within_cycles <= o.bound_cycles, o
    assert o.bound_cycles == SAFE_BOUND_CYCLES or case in ("bus-off", "master-dead"), o
    if expect_stop is None:  # tolerated by design: bridged, counted, the run completes
        assert o.kind.startswith("tolerated"), o
        assert o.trace_complete and o.meta["stop"] == "completed"
        assert sum(int(o.meta[k]) for k in ("tpdo_lost_cycles", "tpdo_late_frames", "malformed_frames")) >= 1
        assert "fault_kind" not in o.meta
    elif expect_stop == "fault":
        assert o.kind == expect_kind, o
        assert o.trace_complete, o
        m = o.meta
        assert m["stop"] == "fault" and m["fault_kind"] == expect_kind and m["fault_axis"] == "x"
        assert int(m["fault_cycle"]) == o.detect_cycle and o.rows in (o.detect_cycle, o.detect_cycle + 1)
        assert m["fault_statusword"].startswith("0x")
        if case == "bus-off":  # nothing answers any more: what the master knows is marked as such
            assert m["fault_error"].startswith("unknown") and m["fault_statusword"].endswith("(the last received)")
        else:
            assert ":" in m["fault_error"]
        if case == "bus-off":  # never claimed: the drive confirmed nothing, and what was tried is said
            assert m["safe_state"].startswith("may still be powered: no confirmed report") and "NMT" in m["safe_state"]
            assert m["safe_after_cycles"] == "unknown"
        else:
            # the state the drive reported (by TPDO, or by SDO after the escalation it says)
            assert m["safe_state"].split(" (")[0] in ("Switch On Disabled", "Quick Stop Active", "Fault"), m
            assert m["safe_after_cycles"] != "unknown"
        assert m["injected"].startswith(case.split(":")[0])
        assert o.exit_reason.startswith("axis x")
    elif expect_stop == "refused":  # configuration refused by the drive: nothing moved, nothing written
        assert "SDO 0x6060 aborted" in o.exit_reason and o.trace_complete
        assert not list(tmp_path.iterdir())
    else:  # the master is dead: the drive stops on its own; what the master streamed stays, marked incomplete
        assert "0x8250" in o.kind and o.safe_state == "Switch On Disabled"
        assert o.trace_complete and o.rows >= o.inject_cycle and o.meta["trace_complete"] == "false"


def test_drive_fault_details_reach_the_trace(tmp_path):
    o = run_case("emcy-fault:code=0x4310", out_dir=tmp_path)
    assert o.meta["fault_error"] == "0x4310: drive temperature too high"
    assert o.meta["fault_statusword"] == "0x0208"  # Fault, remote
    assert o.meta["safe_state"] == "Fault" and o.meta["safe_after_cycles"] == "0"
    limit = run_case("limit-switch", out_dir=tmp_path)
    assert limit.meta["fault_error"] == "0x5441: limit switch (positive)"
    assert int(limit.meta["fault_statusword"], 16) & cia402.SW_INTERNAL_LIMIT


def test_limit_switch_at_a_position_trips_when_the_axis_gets_there(tmp_path):
    o = run_case("limit-switch:position=0.005", at=0.0, out_dir=tmp_path)
    assert o.kind == "drive fault"
    tr = Trace.read(next(tmp_path.glob("*/x.csv")))
    assert tr.pos[-1] == pytest.approx(0.005, abs=2e-4)  # short-move passes 5 mm on its way to 10 mm


def _config(tmp_path, old: str, new: str):
    assert old in DEFAULT_CONFIG_TOML
    path = tmp_path / "machine.toml"
    path.write_text(DEFAULT_CONFIG_TOML.replace(old, new, 1))
    return str(path)


@pytest.mark.parametrize(("limit", "lost", "stops"), [(3, 3, False), (3, 4, True), (1, 1, False), (1, 2, True),
                                                     (0, 1, True)])
def test_consecutive_tpdo_losses_are_bridged_up_to_the_configured_limit(tmp_path, limit, lost, stops):
    cfg = _config(tmp_path, "max_lost_cycles = 3", f"max_lost_cycles = {limit}")
    o = run_case(f"tpdo-lost:cycles={lost}", config=cfg, out_dir=tmp_path)
    if stops:
        assert o.kind == "tpdo timeout" and f"(limit {limit})" in o.exit_reason
    else:
        assert o.meta["stop"] == "completed" and o.meta["tpdo_lost_cycles"] == str(lost)


def test_cli_fault_one_line_and_exit_3(tmp_path, capsys):
    rc = main(["trace", "--axis", "x", "--duration", "0.4", "--fault", "emcy-fault@0.1", "--out", str(tmp_path),
               "--no-plot", "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 3
    assert err[-1].startswith("drivectl: fault: drive fault at cycle ") and "trace kept" in err[-1]
    tr = Trace.read(tmp_path / "x.csv")
    assert tr.meta["fault_kind"] == "drive fault" and tr.meta["injected"] == "emcy-fault@0.1"


def test_cli_tolerated_loss_is_reported_and_exits_0(tmp_path, capsys):
    rc = main(["trace", "--axis", "x", "--duration", "0.4", "--fault", "tpdo-lost@0.1", "--out", str(tmp_path),
               "--no-plot", "--quiet"])
    assert rc == 0
    assert "1 cycle(s) without TPDOs bridged" in capsys.readouterr().out
    assert Trace.read(tmp_path / "x.csv").meta["tpdo_lost_cycles"] == "1"


@pytest.mark.parametrize(("text", "message"), [
    ("bogus@1", "unknown kind 'bogus'"),
    ("tpdo-lost:cycle=2@1", "cycle: unknown parameter"),
    ("tpdo-lost:cycles=two@1", "cycles: expected a number"),
    ("tpdo-lost:cycles=0@1", "cycles: must be >= 1"),
    ("emcy-fault@-1", "time: must be >= 0"),
    ("emcy-fault@soon", "time: expected seconds"),
    ("heartbeat-stop:x=1", "it takes none"),
    ("/emcy-fault@1", "axis: empty"),
    ("emcy-fault:code@1", "expected key=value"),
])
def test_fault_spec_errors_name_the_field(text, message):
    with pytest.raises(FaultSpecError, match=message):
        parse_fault(text)


def test_fault_spec_round_trip():
    spec = parse_fault("y/emcy-fault:code=0x4310@2.5")
    assert spec == FaultSpec("emcy-fault", 2.5, {"code": 0x4310}, "y")
    assert parse_fault(str(spec)) == spec
    assert parse_fault("node-reset").at == 0.0


def test_bus_faults_need_the_masters_bus():
    with pytest.raises(FaultSpecError, match="master's bus"):
        FaultInjector([parse_fault("bus-off@1")])


@pytest.mark.parametrize("argv", [
    ["trace", "--sim", "--fault", "emcy-fault@1"],
    ["trace", "--fault", "master-dead@1"],
    ["trace", "--fault", "y/emcy-fault@1"],
    ["emulate", "--slcan", "--fault", "bus-off@1"],
])
def test_cli_refuses_faults_it_cannot_inject(argv, tmp_path, capsys):
    assert main([*argv[:1], "--out", str(tmp_path)] + argv[1:] if argv[0] == "trace" else argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("drivectl: --fault")
    assert not list(tmp_path.iterdir())


def _machine(cfg, faults=()):
    prof = load_profile("short-move")
    m = open_machine(cfg, ["x"], faults=list(faults), start={"x": prof.start_position})
    ac = cfg.axis("x")
    ctrl = make_controller(ac.controller, cfg.cycle_s, ac.controller_settings, plant=m.specs["x"], axis="x")
    return m, ctrl, prof


def test_following_error_window_and_soft_limits_from_the_drive_objects(tmp_path):
    """Point 4: limits the configuration leaves out come from 0x6065/0x6066 and 0x607D."""
    text = DEFAULT_CONFIG_TOML
    for line in ("position_m = [-0.1, 0.1]        # soft limits\n", "following_error_m = 0.001       # window\n",
                 "following_time_s = 0.01\n",
                 "max_effort = 300.0              # N (3x rated), clipped here and by the drive (0x6072)\n"):
        assert line in text
        text = text.replace(line, "", 1)
    path = tmp_path / "m.toml"
    path.write_text(text)
    cfg = load_config(path)
    ac = cfg.axis("x")
    assert ac.limits_from_drive == {"position", "following_error", "following_time"}
    m, ctrl, prof = _machine(cfg)
    with m:
        axis = m.axes["x"]
        assert axis.drive_limits() == {}  # the EDS defaults: no window, no soft limits
        axis._sdo(cia402.FOLLOWING_ERROR_WINDOW, value=axis.encoder.to_counts(50e-6))
        axis._sdo(cia402.FOLLOWING_ERROR_TIMEOUT, value=5)
        limits = ac.limits_with(axis.drive_limits())
        assert limits.following_error == pytest.approx(50e-6, rel=1e-3) and limits.following_time == 0.005
        assert limits.position is None
        # a feeble effort limit: the axis cannot follow the move, and the drive's window stops it
        weak = type(limits)(following_error=limits.following_error, following_time=limits.following_time,
                            max_effort=20.0)
        res = run_channels([Channel(axis, ctrl, prof, weak)])
        assert res.stop is StopReason.FOLLOWING_ERROR and "beyond the 50 um window" in res.detail
        assert res.trace.meta["fault_kind"] == "following error"
        # soft limits held by the drive: a 10 mm move against +-5 mm is refused before anything moves
        axis._sdo(cia402.SOFTWARE_POSITION_LIMIT, 1, value=axis.encoder.to_counts(-5e-3))
        axis._sdo(cia402.SOFTWARE_POSITION_LIMIT, 2, value=axis.encoder.to_counts(5e-3))
        limits = ac.limits_with(axis.drive_limits())
        assert limits.position == pytest.approx((-5e-3, 5e-3), rel=1e-3)
        syncs = m.drives["x"].drive.syncs
        with pytest.raises(LimitError, match="nothing moved"):
            run_channels([Channel(axis, ctrl, prof, limits)])
        assert m.drives["x"].drive.syncs == syncs  # not a single cycle ran


def test_fault_reset_then_enable_then_trace_again():
    """Point 6 after injected faults: a drive fault is reset with a verified edge, a reset drive is
    reconnected; both axes run again."""
    cfg = load_config(None)
    m, ctrl, prof = _machine(cfg, [parse_fault("emcy-fault@0.1")])
    with m:
        axis, drive = m.axes["x"], m.drives["x"]
        ac = cfg.axis("x")
        res = run_channels([Channel(axis, ctrl, prof, ac.limits)])
        assert res.stop is StopReason.FAULT and drive.drive.power is PowerState.FAULT
        reset_fault(axis)
        assert axis.power is PowerState.SWITCH_ON_DISABLED and drive.drive.error_code == 0
        back = load_profile("short-move")
        from drivectl.profiles.ptp import PointToPoint

        home = PointToPoint(drive.drive.position, back.start_position, 0.05, 0.5, 20.0, hold_until=0.6)
        res = run_channels([Channel(axis, ctrl, home, ac.limits)])
        assert res.ok, res.detail
        m.injectors["x"].arm(parse_fault("node-reset@0.05"))
        res = run_channels([Channel(axis, ctrl, prof, ac.limits)])
        assert res.fault.kind == "unexpected boot-up"
        axis.connect()  # configuration again (it was lost with the reset)
        res = run_channels([Channel(axis, ctrl, PointToPoint(drive.drive.position, 0.0, 0.05, 0.5, 20.0,
                                                             hold_until=0.6), ac.limits)])
        assert res.ok, res.detail


def test_a_drive_repeating_its_emcy_does_not_grow_the_masters_memory():
    """canopen's consumer keeps every EMCY; the axis keeps the newest EMCY_KEPT and the last one."""
    from drivectl.driver.canopen_axis import EMCY_KEPT

    cfg = load_config(None)
    m, _ctrl, _prof = _machine(cfg)
    with m:
        axis, drive = m.axes["x"], m.drives["x"]
        for i in range(3 * EMCY_KEPT):
            drive.node.emcy.send(0x4310 + (i % 2), 0x01)
            axis.read()
            axis.write(0.0)
        assert axis.last_emcy[0] == 0x4310 + (3 * EMCY_KEPT - 1) % 2
        assert len(axis.node.emcy.log) == EMCY_KEPT and len(axis.node.emcy.active) == EMCY_KEPT

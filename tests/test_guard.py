"""Issue 18, points 1, 3 (master side) and 6: what drivectl says about an axis comes from the drive; a
rogue producer or a foreign NMT master is a fault of its own; a malformed frame is counted, not fatal;
a run that went badly says so."""

from __future__ import annotations

import logging
import math
import time

import can
import canopen
import pytest

from drivectl.controllers.registry import make_controller
from drivectl.controllers.runtime.run_checks import Assessment, JumpState, RunChecks, assess, position_jump
from drivectl.controllers.runtime.safe_stop import MAY_BE_POWERED, stop_axes
from drivectl.controllers.runtime.servo import SAFE_STATES, Channel, run_channels
from drivectl.driver.axis import Axis
from drivectl.driver.cia301 import SYNC_COB_ID
from drivectl.driver.cia402 import PowerState
from drivectl.driver.network import close_threaded, open_bus, threaded_network, unique_virtual_channel
from drivectl.machine.build import open_machine
from drivectl.machine.config import DEFAULT_CONFIG_TOML, load_config
from drivectl.plant_emulator.faults import FaultSpecError, parse_fault
from drivectl.profiles.library import load_profile
from drivectl.tools.cli.main import main
from drivectl.tools.conformance.fault_matrix import SAFE_BOUND_CYCLES, run_case
from drivectl.tracefile.format import Trace


def _run(cfg, spec: str, duration: float = 0.5):
    """One lockstep run of x with ``spec`` injected; returns (result, emulated drive, drive-side history of
    (drive SYNC count, power, applied effort))."""
    prof = load_profile("short-move")
    ac = cfg.axis("x")
    m = open_machine(cfg, ["x"], faults=[parse_fault(spec)], start={"x": prof.start_position})
    drive = m.drives["x"]
    history = []
    drive.network.subscribe(SYNC_COB_ID, lambda *a: history.append((drive.drive.syncs, drive.drive.power,
                                                                   drive.drive.applied)))
    ctrl = make_controller(ac.controller, cfg.cycle_s, ac.controller_settings, plant=m.specs["x"], axis="x")
    with m:
        res = run_channels([Channel(m.axes["x"], ctrl, prof, ac.limits)], duration=duration)
    return res, drive, history


@pytest.mark.parametrize("spec", ["rogue-rpdo:effort=30@0.1", "foreign-nmt@0.1", "foreign-nmt:command=0x80@0.1",
                                  "foreign-nmt:command=0x82@0.1", "rogue-sync@0.1"])
def test_rogue_producers_and_foreign_nmt_end_in_a_state_the_drive_reported(spec):
    res, drive, history = _run(load_config(None), spec)
    f = res.fault
    assert f is not None and f.kind in ("rogue rpdo", "foreign nmt", "rogue sync"), res.detail
    # the claim: a safe state, confirmed, within the bound
    assert f.safe_after["x"] is not None and f.safe_after["x"] <= SAFE_BOUND_CYCLES
    assert f.safe_state["x"].split(" (")[0] in ("Switch On Disabled", "Quick Stop Active")
    # the truth (the emulator's own state): it matches the claim, torque off
    assert drive.drive.power in SAFE_STATES and drive.drive.applied == 0.0
    assert history[-1][1] in SAFE_STATES and history[-1][2] == 0.0
    if spec.startswith("rogue-rpdo"):  # RPDO and SDO quick stops are overridden by the rogue: NMT Stop ends it
        assert "quick stop by SDO" in f.safe_state["x"] and "NMT Stop" in f.safe_state["x"]


def test_a_rogue_rpdo_is_stopped_before_the_drive_applies_it_for_long():
    res, drive, history = _run(load_config(None), "rogue-rpdo:effort=300@0.1")
    # the rogue's first frame is seen by the master at once: the drive applies its 300 N at most until
    # the NMT Stop (never, here: the SDO quick stop and NMT Stop go out before the next SYNC)
    rogue_cycles = sum(1 for _s, _p, applied in history if applied == pytest.approx(300.0, abs=0.1))
    assert rogue_cycles <= SAFE_BOUND_CYCLES
    assert res.fault.cycle == 99 and res.fault.kind == "rogue rpdo"  # the row it fired at (as emcy-fault@0.1)


def test_a_drive_taken_out_of_operational_unseen_is_stopped_by_sdo(tmp_path):
    """Issue 18 (b): the TPDOs stop, the master's RPDO quick stop is ignored by a drive outside Operational;
    its SDO answer says Operation Enabled, so the quick stop goes by SDO, and the state is what SDO says."""
    o = run_case("foreign-nmt:command=0x80,hidden=1", out_dir=tmp_path)
    assert o.kind == "tpdo timeout" and o.safe_within_cycles is not None
    assert o.safe_within_cycles <= SAFE_BOUND_CYCLES + 1  # the RPDO's bound, then the SDO quick stop
    # the drive reacts to leaving Operational by itself, per its 0x6007 (issue 18 point 2): the master finds it
    # already in Switch On Disabled (before that, its SDO quick stop did the job)
    assert o.meta["safe_state"].startswith("Switch On Disabled"), o.meta["safe_state"]


def test_foreign_nmt_seen_only_in_the_drives_heartbeat_is_a_fault():
    """A command the master's bus did not carry (another segment, a gateway): the drive's heartbeat says it
    left Operational, which the master did not ask for."""
    from drivectl.driver.axis import AxisError, FaultKind

    prof = load_profile("short-move")
    with open_machine(load_config(None), ["x"], start={"x": prof.start_position}) as m:
        axis, drive = m.axes["x"], m.drives["x"]
        for _ in range(3):
            axis.read()
            axis.write(0.0)
        drive.network.send_message(0x700 + drive.node_id, bytes([0x7F]))  # "I am Pre-operational"
        with pytest.raises(AxisError, match="heartbeat says pre-operational") as exc:
            axis.read()
        assert exc.value.kind is FaultKind.FOREIGN_NMT
        axis.write(0.0)
        axis.read()  # raised once: the stop that follows can still cycle


class _Stubborn(Axis):
    """An axis that reports, by fresh TPDOs, Operation Enabled whatever it is told (a drive a rogue
    controls and no NMT reaches)."""

    name, dt, effort_unit = "x", 0.001, "N"
    power = PowerState.OPERATION_ENABLED
    state_fresh, state_source, last_resort_action = True, "TPDO", "nmt-reset"

    def __init__(self):
        self.calls = []

    def read(self):
        self.calls.append("read")

    def write(self, effort):
        pass

    def quick_stop(self):
        self.calls.append("quick_stop")

    def disable(self):
        self.calls.append("disable")

    def sdo_quick_stop(self):
        self.calls.append("sdo_quick_stop")

    def abort_connection_option(self):
        return 3

    def nmt_stop(self):
        self.calls.append("nmt_stop")

    def refresh_state_outside_operational(self):
        return self.power

    def last_resort(self):
        self.calls.append("last_resort")
        return "NMT Reset Node"


def test_an_unconfirmed_stop_escalates_and_says_the_axis_may_still_be_powered():
    ax = _Stubborn()
    st = stop_axes([ax], "following error", "x")["x"]
    assert st.confirmed_after is None
    assert [c for c in ax.calls if c != "read"] == ["quick_stop", "sdo_quick_stop", "nmt_stop", "last_resort"]
    text = st.safe_state(ax)
    assert text == (f"{MAY_BE_POWERED}: it last reported Operation Enabled by TPDO; tried quick stop by RPDO, "
                    "quick stop by SDO, NMT Stop (0x6007 = 3), NMT Reset Node")
    assert "disable" not in ax.calls  # nothing is claimed, nothing more is assumed


def test_cli_says_may_still_be_powered_when_nothing_answers(tmp_path, capsys):
    rc = main(["trace", "--axis", "x", "--duration", "0.4", "--fault", "bus-off@0.1", "--out", str(tmp_path),
               "--no-plot", "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 3
    assert "x MAY STILL BE POWERED: no confirmed report from the drive; tried quick stop by RPDO" in err[-1]
    tr = Trace.read(tmp_path / "x.csv")
    assert tr.meta["safe_state"].startswith("may still be powered") and tr.meta["safe_after_cycles"] == "unknown"


def test_cli_rogue_rpdo_one_line_with_what_the_drive_reported(tmp_path, capsys):
    rc = main(["trace", "--axis", "x", "--duration", "0.4", "--fault", "rogue-rpdo@0.1", "--out", str(tmp_path),
               "--no-plot", "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 3
    assert err[-1].startswith("drivectl: fault: rogue rpdo at cycle ")
    assert "x Switch On Disabled (reported by SDO after quick stop by RPDO, quick stop by SDO, NMT Stop" in err[-1]
    assert "quick-stopped and disabled" not in err[-1]  # no fixed sentence


# -- malformed frames at the master -------------------------------------------------------------------
@pytest.mark.parametrize("case", ["malformed-frame:cycles=3", "malformed-frame:function=0x280,length=8",
                                  "malformed-frame:function=0x80,length=2,cycles=4",
                                  "malformed-frame:function=0x580,length=0", "malformed-frame:function=0x700,length=2",
                                  "malformed-frame:function=0,length=3",
                                  "malformed-frame:function=0x80,broadcast=1,length=5",
                                  "malformed-frame:rtr=1,cycles=3", "malformed-frame:function=0x700,rtr=1"])
def test_malformed_frames_are_counted_logged_once_and_survived(case, tmp_path, caplog):
    caplog.set_level(logging.WARNING, logger="drivectl.frames")
    o = run_case(case, out_dir=tmp_path)
    assert o.meta["stop"] == "completed" and o.trace_complete, o
    spec = parse_fault(case)
    cycles = int(spec.param("cycles"))
    assert int(o.meta["malformed_frames"]) == cycles
    lines = [r for r in caplog.records if r.name == "drivectl.frames"]
    assert len(lines) == 1 and "malformed frame dropped" in lines[0].getMessage()  # once per kind
    if spec.param("function") in (0x180, 0x280) and not spec.param("broadcast"):  # a control frame: a lost cycle
        assert int(o.meta["tpdo_lost_cycles"]) == cycles


def test_malformed_tpdos_past_the_limit_are_a_tpdo_timeout(tmp_path):
    o = run_case("malformed-frame:cycles=10", out_dir=tmp_path)
    assert o.kind == "tpdo timeout" and o.safe_within_cycles is not None and o.safe_within_cycles <= SAFE_BOUND_CYCLES


def test_threaded_network_guards_canopen_handlers():
    """Across processes canopen's own handlers (EMCY, SDO) sit behind the same checks."""
    channel = unique_virtual_channel("guard")
    net = threaded_network(open_bus("virtual", channel))
    other = open_bus("virtual", channel)
    node = canopen.RemoteNode(5, canopen.ObjectDictionary())
    net.add_node(node)
    seen = []
    net.subscribe(0x185, lambda cob, data, ts: seen.append(bytes(data)))
    try:
        for msg in (can.Message(arbitration_id=0x85, data=b"\x10"),  # short EMCY: canopen's unpack would raise
                    can.Message(arbitration_id=0x705, data=b""),
                    can.Message(arbitration_id=0x185, is_remote_frame=True, dlc=6),
                    can.Message(arbitration_id=0x185, data=b"\x01\x02"),
                    can.Message(arbitration_id=0x85, data=bytes([0x10, 0x23, 1, 0, 0, 0, 0, 0]))):
            other.send(msg)
        # the notifier thread delivers in order: the valid EMCY last, so once it is there all were seen
        deadline = time.monotonic() + 5.0
        while not node.emcy.log and time.monotonic() < deadline:
            time.sleep(0.002)
        assert [e.code for e in node.emcy.log] == [0x2310]
        assert seen == [b"\x01\x02"]  # PDO lengths are the axis's business; the RTR was dropped
        assert net.frame_guard.count() == 3
    finally:
        other.shutdown()
        close_threaded(net)


# -- runs that went badly say so ----------------------------------------------------------------------
class _Tr:
    def __init__(self, **meta):
        self.meta = {"axis": "x", **{k: str(v) for k, v in meta.items()}}


@pytest.mark.parametrize(("meta", "stop"), [
    ({"cycles": 1000}, "completed"),
    ({"cycles": 1000, "missed_deadlines": 5}, "completed"),
    ({"cycles": 1000, "missed_deadlines": 6}, "completed with warnings"),
    ({"cycles": 1000, "missed_deadlines": 51}, "fault"),
    ({"cycles": 2501, "effort_clipped_cycles": 2479}, "fault"),
    ({"cycles": 1000, "effort_clipped_cycles": 11}, "completed with warnings"),
    ({"cycles": 1000, "tpdo_lost_cycles": 6}, "completed with warnings"),
    ({"cycles": 1000, "tpdo_lost_cycles": 422}, "fault"),
])
def test_assessment_thresholds(meta, stop):
    a = assess({"x": _Tr(**meta)}, RunChecks())
    assert a.stop == stop
    assert len(a.warnings) + len(a.faults) == (0 if stop == "completed" else 1)


def test_assessment_refuses_inverted_thresholds():
    with pytest.raises(ValueError, match="clipped_fault: must be >= clipped_warn"):
        RunChecks(clipped_warn=0.2, clipped_fault=0.1)
    assert Assessment().stop == "completed"


def test_cli_completed_with_warnings_exits_4(tmp_path, capsys):
    rc = main(["trace", "--axis", "x", "--duration", "0.4", "--fault", "tpdo-lost:cycles=3@0.1", "--out",
               str(tmp_path), "--no-plot", "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 4, err
    assert err[-2] == ("drivectl: warning: axis x: 3 of 401 cycles run on an extrapolated position (TPDO lost or "
                       "malformed) (0.7%, more than checks.extrapolated_warn 0.5%)")
    assert err[-1] == "drivectl: completed with warnings"
    tr = Trace.read(tmp_path / "x.csv")
    assert tr.meta["stop"] == "completed with warnings" and "extrapolated" in tr.meta["run_checks"]


def test_cli_checks_from_the_configuration(tmp_path, capsys):
    path = tmp_path / "machine.toml"
    path.write_text(DEFAULT_CONFIG_TOML.replace("extrapolated_fault = 0.05", "extrapolated_fault = 0.006"))
    rc = main(["--config", str(path), "trace", "--axis", "x", "--duration", "0.4", "--fault",
               "tpdo-lost:cycles=3@0.1", "--out", str(tmp_path), "--no-plot", "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    # the fault threshold stops the run when it is passed (the third lost cycle: 0.6 % of the run's 401
    # cycles allows 2), not after the profile (controllers/run_checks.RunGuard)
    assert rc == 3 and err[-1].startswith("drivectl: fault: run check at cycle 101: axis x: 3 cycles run on an "
                                          "extrapolated position"), err
    assert "checks.extrapolated_fault 0.6% allows (2 of 401 cycles); stopped (x Switch On Disabled" in err[-1]
    tr = Trace.read(tmp_path / "x.csv")
    assert tr.meta["stop"] == "fault" and tr.meta["fault_kind"] == "run check" and len(tr) == 102


@pytest.mark.parametrize(("old", "new", "message"), [
    ("clipped_warn = 0.01 ", "clipped_warn = 2 ", "checks.clipped_warn: must be a fraction"),
    ("clipped_fault = 0.5", "clipped_fault = 0.001", "checks.clipped_fault: must be >= clipped_warn"),
    ("[checks]", "[checks]\nbogus = 1", "checks.bogus: unknown key"),
    ("clipped_warn = 0.01 ", "clipped_warn = \"x\" ", "checks.clipped_warn"),
    ('last_resort = "nmt-reset"', 'last_resort = "explode"', "axes.x.last_resort: expected one of"),
    ("max_jump_m = 0.0005", "max_jump_m = -1", "axes.x.limits.max_jump_m"),
])
def test_bad_checks_and_guard_keys_exit_2_with_one_line(tmp_path, capsys, old, new, message):
    assert old in DEFAULT_CONFIG_TOML
    path = tmp_path / "machine.toml"
    path.write_text(DEFAULT_CONFIG_TOML.replace(old, new, 1))
    rc = main(["--config", str(path), "trace", "--axis", "x", "--out", str(tmp_path / "out"), "--no-plot"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and message in err[0] and str(path) in err[0], err


def test_paced_run_says_paced(tmp_path, capsys):
    main(["trace", "--axis", "x", "--duration", "0.05", "--paced", "--out", str(tmp_path), "--no-plot", "--quiet"])
    err = capsys.readouterr().err.splitlines()
    assert "paced on the wall clock" in err[0] and "lockstep" not in err[0]
    assert "paced" in Trace.read(tmp_path / "x.csv").meta["bus"]


# -- the encoder's plausibility -----------------------------------------------------------------------
def test_a_1_mm_encoder_glitch_is_a_fault(tmp_path):
    o = run_case("encoder-glitch:jump=0.001", out_dir=tmp_path)
    assert o.kind == "implausible position" and o.detect_after == 0, o
    assert "limits.max_jump_m" in o.exit_reason


def test_position_jump_bound_grows_over_bridged_cycles():
    st = JumpState()
    for p in (0.0, 1e-5, 2e-5):
        assert position_jump(st, p, 5e-4, False) is None
    assert position_jump(st, 3e-5 + 6e-4, 5e-4, False) == pytest.approx(6e-4)
    st = JumpState()
    for p in (0.0, 1e-5, 2e-5, 3e-5, 4e-5):  # the last two extrapolated
        position_jump(st, p, 5e-4, p >= 3e-5)
    assert position_jump(st, 5e-5 + 6e-4, 5e-4, False) is None  # within (1 + 2)^2 x the bound
    assert position_jump(JumpState(), 1.0, math.inf, False) is None


def test_fault_kinds_parameters_are_checked():
    with pytest.raises(FaultSpecError, match="command: expected an NMT command"):
        parse_fault("foreign-nmt:command=7@1")
    with pytest.raises(FaultSpecError, match="length: must be 0..8"):
        parse_fault("malformed-frame:length=9@1")
    with pytest.raises(FaultSpecError, match="function: expected a CANopen function code"):
        parse_fault("malformed-frame:function=0x181@1")

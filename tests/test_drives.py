"""Real drives: capability-driven bring-up, PDO plans within a drive's limits, the emulated drive impersonating
an EDS, config init from an EDS, the drive's configuration as a file, why a drive does not enable (issue 27).

Drives other than drivectl's own are made here by editing its object dictionary in memory (canopen) and
exporting it as an EDS: objects removed, mappings fixed, PDOs renumbered, transmission types read-only.
Every EDS in shared/eds (skipped where that folder is absent) is brought up and traced, or refused in one line.
"""

from __future__ import annotations

import sys
from pathlib import Path

import canopen
import pytest

from drivectl.driver import cia402
from drivectl.driver.capabilities import DriveRefused, assess
from drivectl.driver.pdo_plan import plan
from drivectl.machine.build import open_machine
from drivectl.machine.config import ConfigError, load_config
from drivectl.plant_emulator.node402 import EMULATED_DRIVE_EDS
from drivectl.tools.cli.main import main

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from drives import eds_dir, try_drive  # noqa: E402

OWN = str(EMULATED_DRIVE_EDS)


def _od(path: str | Path = OWN) -> canopen.ObjectDictionary:
    return canopen.import_od(str(path), 1)


def _export(od: canopen.ObjectDictionary, path: Path) -> Path:
    canopen.export_od(od, str(path), doc_type="eds")
    return path


def _without(path: Path, *indices: int) -> Path:
    od = _od()
    for i in indices:
        del od.indices[i]
        od.names = {k: v for k, v in od.names.items() if v.index != i}
    return _export(od, path)


def _set(var: canopen.objectdictionary.ODVariable, value: int) -> None:
    var.default, var.default_raw = value, None  # (the exporter writes default_raw where it has one)


def _config(tmp_path: Path, eds: Path, extra: str = "", rated: bool = True) -> Path:
    text = (
        'cycle_s = 0.001\n[bus]\ninterface = "virtual"\nchannel = "drives"\n[axes.x]\nnode_id = 1\n'
        f'eds = "{eds}"\nplant = "rigid-x"\ncontroller = "mbc"\nprofile = "short-move"\n'
        + ("rated_effort = 100.0\n" if rated else "") + extra
        + "[axes.x.limits]\nposition_m = [-0.1, 0.1]\nmax_effort = 2000.0\nfollowing_error_m = 0.001\n"
        "following_time_s = 0.01\n"
    )
    p = tmp_path / "machine.toml"
    p.write_text(text)
    return p


# -- point 1: capabilities ------------------------------------------------------------------------------------
def test_own_drive_offers_everything():
    caps = assess(_od(), "x")
    assert caps.mode == 10 and caps.missing == () and caps.rated_effort_from_drive


def test_a_missing_optional_object_is_a_fallback_not_a_refusal(tmp_path):
    od = _od(_without(tmp_path / "d.eds", 0x6077, 0x6007, 0x1016))
    caps = assess(od, "x")
    assert caps.fallback_lines() == [
        "0x6007 absent: the drive's reaction to a lost master is unknown",
        "0x1016 absent: the RPDO deadline (0x14xx:05), where the drive has one, watches the master instead of the "
        "heartbeat",
        "0x6077 absent: no torque actual in traces",
    ]


def test_no_torque_setpoint_is_refused_in_one_line(tmp_path):
    eds = _without(tmp_path / "d.eds", 0x6071)
    with pytest.raises(DriveRefused) as exc:
        assess(_od(eds), f"axis x: EDS {eds}")
    assert str(exc.value) == f"axis x: EDS {eds}: drive has no torque setpoint 0x6071: drivectl closes the loop in " \
        "torque"


def test_profile_torque_when_cst_is_absent_and_no_torque_mode_refused(tmp_path):
    od = _od()
    od[cia402.SUPPORTED_DRIVE_MODES].default = 0x0D  # pp, pv, tq
    assert assess(od, "x").mode == 4
    od[cia402.SUPPORTED_DRIVE_MODES].default = 0x05  # pp, pv
    with pytest.raises(DriveRefused, match=r"x: drive offers no torque mode \(0x6502 = 0x00000005"):
        assess(od, "x")


def test_trace_on_a_drive_without_the_rated_torque_needs_it_configured(tmp_path, capsys):
    eds = _without(tmp_path / "d.eds", cia402.RATED_TORQUE)
    cfg = _config(tmp_path, eds, rated=False)
    assert main(["--config", str(cfg), "trace", "--axis", "x", "--out", str(tmp_path), "--no-plot"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(eds) in err[0]
    assert "drive has no rated torque 0x6076: set axes.x.rated_effort" in err[0]


# -- point 2: PDO plans -----------------------------------------------------------------------------------------
def test_own_drive_gets_the_mapping_it_always_had():
    p = plan(_od(), "full", 1, "x")
    assert [(q.slot.name, q.entries, q.cob_id, q.trans_type) for q in (*p.rx, *p.tx)] == [
        ("RPDO1", ((0x6040, 0), (0x6071, 0)), 0x201, 1),
        ("TPDO1", ((0x6041, 0), (0x6064, 0)), 0x181, 1),
        ("TPDO2", ((0x606C, 0), (0x6077, 0)), 0x281, 1),
    ]


def _fix(od: canopen.ObjectDictionary, index: int, entries: list[int]) -> None:
    rec = od[index]
    rec[0].default = len(entries)
    rec[0].access_type = "ro"
    for s, word in enumerate(entries, start=1):
        rec[s].default = word
        rec[s].access_type = "ro"
    for s in range(len(entries) + 1, len(rec.subindices)):
        if s in rec.subindices:
            rec[s].access_type = "ro"


def test_fixed_mappings_are_used_as_they_are_and_one_entry_pdos_split_a_group():
    od = _od()
    _fix(od, 0x1600, [0x60400010, 0x60710010])  # RPDO1 fixed: controlword + target torque
    _fix(od, 0x1A00, [0x60410010, 0x60640020, 0x60610008])  # TPDO1 fixed, one more object
    od[0x1A01][0].max = 1  # one entry in TPDO2
    p = plan(od, "full", 1, "x")
    assert [(q.slot.name, q.entries) for q in (*p.rx, *p.tx)] == [
        ("RPDO1", ((0x6040, 0), (0x6071, 0))),
        ("TPDO1", ((0x6041, 0), (0x6064, 0), (0x6061, 0))),
        ("TPDO2", ((0x606C, 0),)),
    ]
    assert [f[1] for f in p.frames()] == [7, 4, 4]
    assert not p.torque_mapped and "torque actual 0x6077: no PDO left for it, not traced" in p.lines()
    # the group that cannot be split further: a one-entry RPDO takes the controlword, the next the torque
    od = _od()
    od[0x1600][0].max = 1
    p = plan(od, "full", 1, "x")
    assert [(q.slot.name, q.entries) for q in p.rx] == [("RPDO1", ((0x6040, 0),)), ("RPDO2", ((0x6071, 0),))]


def test_asynchronous_only_pdos_are_refused_in_one_line():
    od = _od()
    for k in range(2):
        od[0x1400 + k][2].access_type = "ro"
        od[0x1400 + k][2].default = 255
    with pytest.raises(DriveRefused, match=r"^x: drive's RPDOs are not synchronous \(transmission types 255, "
                       r"read-only\): drivectl's loop runs on SYNC$"):
        plan(od, "full", 1, "x")


# -- point 4: the emulated drive impersonates an EDS -------------------------------------------------------------
def test_impersonated_drive_answers_with_its_objects_and_refuses_what_it_lacks(tmp_path):
    od = _od()
    # a drive with a gap in its RPDO numbering (no RPDO2), no 0x6077, profile torque only, its own identity
    for i in (0x1401, 0x1601, cia402.TORQUE_ACTUAL):
        del od.indices[i]
    _set(od[0x1A01][0], 1)  # its default TPDO2 without the torque actual
    od.names = {k: v for k, v in od.names.items() if v.index in od.indices}
    _set(od[cia402.SUPPORTED_DRIVE_MODES], 0x0D)
    _set(od[cia402.IDENTITY][1], 0xABCD)
    od.device_information.vendor_number = 0xABCD
    eds = _export(od, tmp_path / "other.eds")
    with open_machine(load_config(_config(tmp_path, eds)), ["x"]) as m:
        ax = m.axes["x"]
        assert ax.mode == 4 and ax.mapping == "full"
        assert "0x6077 absent: no torque actual in traces" in ax.boot_notes
        assert ax.read_back_mapping() == {"rpdo1": [0x60400010, 0x60710010], "tpdo1": [0x60410010, 0x60640020],
                                          "tpdo2": [0x606C0020]}
        sdo = ax.node.sdo
        assert sdo[cia402.IDENTITY][1].raw == 0xABCD
        with pytest.raises(canopen.SdoAbortedError) as exc:
            sdo.upload(cia402.TORQUE_ACTUAL, 0)
        assert exc.value.code == 0x06020000  # object does not exist
        with pytest.raises(canopen.SdoAbortedError) as exc:
            sdo.download(cia402.MODES_OF_OPERATION, 0, bytes([10]))  # cst: a mode it lacks
        assert exc.value.code == 0x06090030
        with pytest.raises(canopen.SdoAbortedError):
            sdo.download(0x1A01, 0, bytes([9]))  # more entries than the mapping has
        assert m.drives["x"].mode == 4


# -- point 3: config init ---------------------------------------------------------------------------------------
def test_config_init_from_an_eds_writes_a_commented_file_that_loads(tmp_path, capsys):
    eds = _without(tmp_path / "d.eds", cia402.RATED_TORQUE, cia402.VELOCITY_ACTUAL)
    out = tmp_path / "m.toml"
    assert main(["config", "init", str(out), "--eds", str(eds), "--axis", "y"]) == 0
    text = out.read_text()
    assert "# mode: cyclic synchronous torque (10)" in text
    assert "#   0x6076 absent: rated_effort comes from the configuration" in text
    assert "#   0x606C absent: velocity derived on the host" in text
    assert "bus budget" in text and "RPDO1 (COB-ID 0x201, every SYNC, mapped): controlword + target torque" in text
    cfg = load_config(out)
    assert cfg.axes["y"].eds == str(eds.resolve()) and cfg.axes["y"].rated_effort_source is not None


def test_config_init_refuses_a_drive_without_an_essential_and_writes_nothing(tmp_path, capsys):
    eds = _without(tmp_path / "d.eds", cia402.POSITION_ACTUAL)
    out = tmp_path / "m.toml"
    assert main(["config", "init", str(out), "--eds", str(eds)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"drivectl: --eds {eds}: drive has no position actual value 0x6064: drivectl closes the loop on "
                   "the drive's position"]
    assert not out.exists()


# -- sdo_init ------------------------------------------------------------------------------------------------
def test_sdo_init_is_written_and_read_back(tmp_path):
    cfg = load_config(_config(tmp_path, EMULATED_DRIVE_EDS, extra="sdo_init = [[0x605A, 0, 6]]\n"))
    with open_machine(cfg, ["x"]) as m:
        assert m.axes["x"].node.sdo[cia402.QUICK_STOP_OPTION].raw == 6
        assert "sdo_init: 1 value(s) written and read back" in m.axes["x"].boot_notes


def test_sdo_init_bad_entry_is_one_line(tmp_path):
    p = _config(tmp_path, EMULATED_DRIVE_EDS, extra='sdo_init = [[0x605A, 0]]\n')
    with pytest.raises(ConfigError, match=r"machine.toml: axes.x.sdo_init\[0\]: expected \[index, sub, value\]"):
        load_config(p)


# -- point 6: drive save / restore / get / set --------------------------------------------------------------------
def test_drive_get_set_save_restore(tmp_path, capsys):
    cfg = str(_config(tmp_path, EMULATED_DRIVE_EDS))
    assert main(["--config", cfg, "drive", "get", "--axis", "x", "0x6072:0"]) == 0
    assert capsys.readouterr().out.startswith("0x6072:0 ")
    assert main(["--config", cfg, "drive", "set", "--axis", "x", "0x605A", "5"]) == 0
    assert "= 5 (0x5) (written, read back)" in capsys.readouterr().out
    # beyond the object's type (0x6072 is UNSIGNED16): one line, exit 2, nothing written
    assert main(["--config", cfg, "drive", "set", "--axis", "x", "0x6072", "70000"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "0x6072:0" in err[0] and "nothing written" in err[0]
    assert main(["--config", cfg, "drive", "get", "--axis", "x", "0x7777"]) == 2
    assert "object 0x7777 is not in the EDS" in capsys.readouterr().err
    dcf = tmp_path / "x.dcf"
    assert main(["--config", cfg, "drive", "save", "--axis", "x", str(dcf)]) == 0
    assert "ParameterValue" in dcf.read_text()
    capsys.readouterr()
    text = dcf.read_text()
    at = text.index("ParameterValue=", text.index("[605A]"))
    dcf.write_text(text[:at] + "ParameterValue=6\n" + text[text.index("\n", at) + 1:])
    assert main(["--config", cfg, "drive", "restore", "--axis", "x", str(dcf)]) == 0
    assert "1 objects written and read back" in capsys.readouterr().out


# -- point 5: why a drive does not enable ---------------------------------------------------------------------
@pytest.mark.parametrize("how, says", [
    ("sto", "safe torque off (STO)"),
    ("voltage", "voltage not enabled"),
    ("fault", "in Fault: 0x603F = 0x2310 (continuous over-current)"),
])
def test_enable_attempt_says_why_the_drive_does_not_enable(tmp_path, how, says):
    from drivectl.driver.drive_report import drive_lines, enable_attempt

    with open_machine(load_config(_config(tmp_path, EMULATED_DRIVE_EDS)), ["x"]) as m:
        ax, drive = m.axes["x"], m.drives["x"]
        lines = dict(drive_lines(ax))
        assert lines["mode"] == "cyclic synchronous torque (10)" and "vendor 0x" in lines["identity answered"]
        assert "vendor 0x" in lines["identity expected"]
        if how == "sto":
            drive.drive.sto = True
        elif how == "voltage":
            drive.drive.voltage = False
        else:
            drive.fault(0x2310)
        ok, why = enable_attempt(ax)
        assert not ok and says in why


def test_enable_attempt_on_a_healthy_drive_enables_then_disables(tmp_path):
    from drivectl.driver.drive_report import enable_attempt

    with open_machine(load_config(_config(tmp_path, EMULATED_DRIVE_EDS)), ["x"]) as m:
        ok, what = enable_attempt(m.axes["x"])
        assert ok and "Switch On Disabled" in what
        assert m.drives["x"].drive.power is cia402.PowerState.SWITCH_ON_DISABLED


# -- point 7: every real drive's EDS ------------------------------------------------------------------------
EDS = eds_dir()


@pytest.mark.skipif(EDS is None, reason="no shared/eds folder")
@pytest.mark.parametrize("name", sorted(p.name for p in EDS.glob("*.eds")) if EDS is not None else [])
def test_every_real_eds_is_brought_up_and_traced_or_refused_in_one_line(tmp_path, name):
    outcome = try_drive(EDS / name, tmp_path)
    assert outcome.verdict in ("brought_up", "refused"), outcome.detail
    if outcome.verdict == "refused":
        assert str(EDS / name) in outcome.detail and "\n" not in outcome.detail
    else:
        assert outcome.max_um <= 2.0


def test_doctor_drive_section(tmp_path, capsys):
    from drivectl.tools.cli.doctor import drive_sections

    with open_machine(load_config(_config(tmp_path, EMULATED_DRIVE_EDS)), ["x"]) as m:
        sec = drive_sections(m, ["x"], try_enable=True)["x"]
    text = "\n".join(f"{k}: {v}" for k, v in sec.items())
    assert "0x6502" in text and "cyclic synchronous torque (10)" in text and "RPDO deadline" in text
    assert "enabled at zero torque, then disabled" in text
    eds = _without(tmp_path / "d.eds", cia402.TARGET_TORQUE)
    assert main(["--config", str(_config(tmp_path, eds)), "doctor", "--axis", "x", "--seconds", "0.1"]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        f"drivectl: axis x: EDS {eds}: drive has no torque setpoint 0x6071: drivectl closes the loop in torque"]


def test_emulate_eds_is_checked_before_the_bus_opens(capsys, tmp_path):
    assert main(["emulate", "--axis", "x", "--slcan", "--eds", str(tmp_path / "none.eds")]) == 2
    assert capsys.readouterr().err.splitlines() == [f"drivectl: emulate: --eds {tmp_path / 'none.eds'}: no such file"]


def test_the_bus_budget_counts_the_mapping_the_drive_gets(tmp_path):
    from drivectl.machine.bus_budget import machine_load

    od = _od()
    _fix(od, 0x1A00, [0x60410010, 0x60640020, 0x60610008])  # a fixed TPDO1 of 7 bytes
    for s in range(4):
        if s in od[0x1A00].subindices:
            od[0x1A00][s].default_raw = None
    eds = _export(od, tmp_path / "fixed.eds")
    load = machine_load(load_config(_config(tmp_path, eds)), ["x"])
    # SYNC, TPDO1 7 bytes, TPDO2 6, RPDO1 4 (47 + 8 n bits each)
    assert load.bits_nominal == 47 + (47 + 56) + (47 + 48) + (47 + 32)


def test_drive_get_by_the_eds_name(tmp_path, capsys):
    cfg = str(_config(tmp_path, EMULATED_DRIVE_EDS))
    assert main(["--config", cfg, "drive", "get", "--axis", "x", "Identity object.Vendor-ID"]) == 0
    assert capsys.readouterr().out.startswith("0x1018:1 Vendor-ID = ")
    assert main(["--config", cfg, "drive", "get", "--axis", "x", "Max torque"]) == 0
    assert capsys.readouterr().out.startswith("0x6072:0 Max torque = ")


def test_a_mode_the_drive_does_not_take_is_said(tmp_path, monkeypatch):
    from drivectl.driver.axis import AxisConfigError
    from drivectl.plant_emulator.node402 import EmulatedDrive

    # a drive that acknowledges 0x6060 but keeps showing no mode in 0x6061
    monkeypatch.setattr(EmulatedDrive, "_set_mode", lambda self, mode: setattr(self, "mode", 0))
    with pytest.raises(AxisConfigError, match=r"node 1: mode not accepted: 0x6061 = 0 after 0x6060 = 10"):
        open_machine(load_config(_config(tmp_path, EMULATED_DRIVE_EDS)), ["x"])


def test_standing_blocker_reads_a_fault_without_enabling(tmp_path):
    from drivectl.driver.drive_report import standing_blocker

    with open_machine(load_config(_config(tmp_path, EMULATED_DRIVE_EDS)), ["x"]) as m:
        assert standing_blocker(m.axes["x"]).startswith("none seen (Switch On Disabled")
        m.drives["x"].fault(0x4310)
        m.axes["x"].read()
        assert "0x603F = 0x4310 (drive temperature too high)" in standing_blocker(m.axes["x"])


def test_doctor_command_says_the_drive(tmp_path):
    from drivectl.tools.cli.doctor import drive_sections

    with open_machine(load_config(_config(tmp_path, EMULATED_DRIVE_EDS)), ["x"]) as m:
        sec = drive_sections(m, ["x"])["x"]
        assert "0x6502" in sec and sec["enable"].startswith("none seen")
        assert m.axes["x"].power.value == sec["power"] != "operation enabled"  # nothing was enabled

"""The drive section of ``drivectl doctor --axis NAME`` (driver/drive_report.py on a live bus).

The axis is connected as ``trace`` connects it (booted, configured: the drive's own refusal is the section's
one line), its identity, 0x6502, mode, mapping and watchdogs listed, then an enable attempt at zero torque
says whether it enables or why not (the statusword and 0x603F: voltage not enabled, STO, a fault code, a mode
not accepted), and the axis is left disabled, as the drive confirms.
"""

from __future__ import annotations

from typing import Any

from drivectl.driver.axis import AxisConfigError, AxisError


def drive_section(cfg: Any, name: str) -> tuple[bool, list[str]]:
    """(the drive enables?, the section's lines) for axis ``name`` of ``cfg``."""
    from drivectl.driver.drive_report import drive_lines, enable_attempt
    from drivectl.machine.build import open_machine

    cfg.axis(name)
    try:
        machine = open_machine(cfg, [name])
    except AxisConfigError as exc:
        return False, [f"drive: refused: {exc}"]
    except AxisError as exc:
        return False, [f"drive: does not answer: {exc}"]
    with machine:
        axis = machine.axes[name]
        lines = [f"drive ({machine.bus})"]
        lines += [f"  {what:<17} {value}" for what, value in drive_lines(axis)]
        try:
            ok, said = enable_attempt(axis)
        except AxisError as exc:
            return False, [*lines, f"  {'enable':<17} failed: {exc}"]
        lines.append(f"  {'enable':<17} {said if ok else 'does not enable: ' + said}")
        return ok, lines


def add_doctor_parser(sub: Any) -> None:
    """``drivectl doctor --axis NAME`` with the drive section only: registered only where no fuller ``doctor``
    (the host's preflight) is (tools/cli/main.py), so the two never clash."""
    if "doctor" in getattr(sub, "choices", {}):
        return
    d = sub.add_parser("doctor", help="the drive: identity, 0x6502, mode, mapping, watchdogs, and whether it "
                       "enables (at zero torque, disabled after) or why not")
    d.add_argument("--axis", default="x")
    d.set_defaults(doctor_drive=True)


def cmd_doctor_drive(args: Any) -> int:
    """The drive section alone (``drivectl doctor --axis NAME`` where no fuller doctor is installed)."""
    from drivectl.machine.config import load_config

    cfg = load_config(args.config)
    ok, lines = drive_section(cfg, args.axis)
    print("\n".join(lines))
    return 0 if ok else 1

"""``drivectl drive save|restore|get|set --axis NAME``: a drive's configuration as a file (driver/drive_file.py).

The drive is reached on the configured bus as ``status`` reaches it (on the virtual bus: the emulated drive,
impersonating the axis's EDS). Bad input (an unknown object, a value outside the object's limits or type, a
bad DCF) is one line and exit 2 with nothing written; a drive that refuses or does not answer, exit 3.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

import canopen

from drivectl.driver.axis import AxisConfigError, AxisError
from drivectl.machine.config import load_config


def add_drive_parser(sub: Any) -> None:
    d = sub.add_parser("drive", help="a drive's configuration: save it to a DCF, restore it, get or set one object")
    dsub = d.add_subparsers(dest="drive_command", metavar="save|restore|get|set")
    dsub.required = True
    s = dsub.add_parser("save", help="read every readable object of the EDS by SDO into a DCF")
    s.add_argument("file", metavar="FILE.dcf")
    r = dsub.add_parser("restore", help="write a DCF's writable values back, each read back")
    r.add_argument("file", metavar="FILE.dcf")
    g = dsub.add_parser("get", help="read one object (index:sub, e.g. 0x6071:0, or the EDS's name)")
    g.add_argument("object")
    st = dsub.add_parser("set", help="write one object (checked against its limits first) and read it back")
    st.add_argument("object")
    st.add_argument("value")
    for p in (s, r, g, st):
        p.add_argument("--axis", default="x")


def cmd_drive(args: argparse.Namespace) -> int:
    from drivectl.driver import drive_file
    from drivectl.machine.build import open_bus_session

    cfg = load_config(args.config)
    ac = cfg.axis(args.axis)
    where = f"axis {args.axis}: node {ac.node_id}"
    try:
        od = canopen.import_od(ac.eds, ac.node_id)
    except Exception as exc:  # canopen raises many types for a bad file
        reason = (str(exc).strip().splitlines() or [type(exc).__name__])[0].rstrip(":")
        raise AxisConfigError(f"axis {args.axis}: EDS {ac.eds}: cannot be read: {reason}") from None
    # everything the command line says is checked before the bus opens: nothing is written on bad input
    var = value = None
    if args.drive_command in ("get", "set"):
        var = drive_file.find(od, args.object, where)
        if args.drive_command == "set":
            if not var.writable:
                raise drive_file.DriveFileError(f"{where}: {drive_file.label(var)} ({var.name}) is "
                                                f"{var.access_type}: nothing written")
            value = drive_file.parse_value(var, args.value, where)
    with open_bus_session(cfg) as session:
        node = canopen.RemoteNode(ac.node_id, od)
        session.network.add_node(node)
        try:
            if args.drive_command == "save":
                n, refused = drive_file.save(node, od, args.file, where)
                print(f"wrote {args.file}: {n} objects read" + (f", {refused} the drive would not give" if refused
                                                               else ""))
            elif args.drive_command == "restore":
                written, equal = drive_file.restore(node, args.file, ac.node_id, where)
                print(f"{args.file}: {written} objects written and read back, {equal} already equal")
            elif args.drive_command == "get":
                print(f"{drive_file.label(var)} {var.name} = {_show(drive_file.read(node, var, where))}")
            else:
                back = drive_file.write(node, var, value, where)
                print(f"{drive_file.label(var)} {var.name} = {_show(back)} (written, read back)")
        except AxisError as exc:
            print(f"drivectl: {exc}", file=sys.stderr)
            return 3
    return 0


def _show(value: object) -> str:
    if isinstance(value, int) and not isinstance(value, bool):
        return f"{value} (0x{value & 0xFFFFFFFFFFFFFFFF:X})" if value >= 0 else str(value)
    return str(value)

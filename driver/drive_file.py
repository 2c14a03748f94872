"""A drive's configuration as a file, through canopen's object dictionary and SDO client.

``save``: every readable object of the EDS read by SDO into a DCF (canopen's exporter: the values go in
ParameterValue). ``restore``: the DCF's values of writable objects checked against the EDS's limits first
(a value out of them: one line, nothing written), then each one that differs from what the drive holds
written and read back. ``get``/``set``: one object by index[:sub] or by the EDS's name ("Name" or
"Name.Sub name"), a value checked against the object's limits and type before anything is written.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import canopen
from canopen import objectdictionary as odt

from drivectl.driver.axis import AxisConfigError, AxisError

#: the integer range of each CANopen integer type (CiA 301 table 44)
_INT_RANGE = {
    odt.BOOLEAN: (0, 1), odt.INTEGER8: (-2**7, 2**7 - 1), odt.INTEGER16: (-2**15, 2**15 - 1),
    odt.INTEGER32: (-2**31, 2**31 - 1), odt.INTEGER64: (-2**63, 2**63 - 1), odt.UNSIGNED8: (0, 2**8 - 1),
    odt.UNSIGNED16: (0, 2**16 - 1), odt.UNSIGNED32: (0, 2**32 - 1), odt.UNSIGNED64: (0, 2**64 - 1),
}


class DriveFileError(AxisConfigError):
    """Bad input for a drive command (an unknown object, a value out of limits, a bad file): exit 2."""


def variables(od: odt.ObjectDictionary) -> Iterator[odt.ODVariable]:
    """Every variable of the dictionary, sub-index 0 of records and arrays included, in index order."""
    for index in sorted(od.indices):
        obj = od[index]
        if isinstance(obj, odt.ODVariable):
            yield obj
        else:
            yield from (obj.subindices[s] for s in sorted(obj.subindices))


def find(od: odt.ObjectDictionary, what: str, where: str) -> odt.ODVariable:
    """The variable ``what`` names: 0xIIII[:S] / IIII[:S] (hex), or the EDS's name, "Name" or "Name.Sub name"."""
    text = what.strip()
    try:
        head, _, sub = text.partition(":")
        index = int(head, 16)
        subindex = int(sub, 0) if sub else 0
    except ValueError:
        index = None
    if index is not None:
        if index not in od:
            raise DriveFileError(f"{where}: object 0x{index:04X} is not in the EDS")
        obj = od[index]
        if isinstance(obj, odt.ODVariable):
            if subindex:
                raise DriveFileError(f"{where}: object 0x{index:04X} has no sub-index {subindex}")
            return obj
        if subindex not in obj.subindices:
            raise DriveFileError(f"{where}: object 0x{index:04X} has no sub-index {subindex}")
        return obj.subindices[subindex]
    name, _, subname = text.partition(".")
    for candidate in ((text, ""), (name, subname)):
        try:
            obj = od[candidate[0]]
        except KeyError:
            continue
        if isinstance(obj, odt.ODVariable) and not candidate[1]:
            return obj
        if not isinstance(obj, odt.ODVariable):
            if not candidate[1]:
                raise DriveFileError(f"{where}: {text!r} is a record: name a sub-index (\"{text}.<name>\" or "
                                     f"0x{obj.index:04X}:N)")
            try:
                return obj[candidate[1]]
            except KeyError:
                pass
    raise DriveFileError(f"{where}: no object named {text!r} in the EDS (use index:sub, e.g. 0x6071:0)")


def label(var: odt.ODVariable) -> str:
    return f"0x{var.index:04X}:{var.subindex}"


def parse_value(var: odt.ODVariable, text: str, where: str) -> int | float | str:
    """``text`` as a value of ``var``: its type's range and the EDS's LowLimit/HighLimit checked."""
    if var.data_type in odt.INTEGER_TYPES or var.data_type == odt.BOOLEAN:
        try:
            value: int | float | str = int(text, 0)
        except ValueError:
            raise DriveFileError(f"{where}: {label(var)} ({var.name}): {text!r} is not an integer") from None
        lo, hi = _INT_RANGE.get(var.data_type, (None, None))
        if lo is not None and not lo <= value <= hi:
            raise DriveFileError(f"{where}: {label(var)} ({var.name}): {value} is outside its type's range "
                                 f"{lo}..{hi}: nothing written")
    elif var.data_type in odt.FLOAT_TYPES:
        try:
            value = float(text)
        except ValueError:
            raise DriveFileError(f"{where}: {label(var)} ({var.name}): {text!r} is not a number") from None
    else:
        value = text
    check_limits(var, value, where)
    return value


def check_limits(var: odt.ODVariable, value: object, where: str) -> None:
    if not isinstance(value, int | float):
        return
    if var.min is not None and value < var.min:
        raise DriveFileError(f"{where}: {label(var)} ({var.name}): {value} is below its limit {var.min}: "
                             "nothing written")
    if var.max is not None and value > var.max:
        raise DriveFileError(f"{where}: {label(var)} ({var.name}): {value} is above its limit {var.max}: "
                             "nothing written")


def _sdo_var(node: canopen.RemoteNode, var: odt.ODVariable):
    obj = node.sdo[var.index]
    return obj if isinstance(var.parent, odt.ObjectDictionary) else obj[var.subindex]


def read(node: canopen.RemoteNode, var: odt.ODVariable, where: str) -> int | float | str:
    try:
        return _sdo_var(node, var).raw
    except canopen.SdoAbortedError as exc:
        raise AxisError(f"{where}: SDO read of {label(var)} aborted: {exc}") from None
    except canopen.SdoCommunicationError as exc:
        raise AxisError(f"{where}: SDO read of {label(var)}: {exc}") from None


def write(node: canopen.RemoteNode, var: odt.ODVariable, value: object, where: str) -> object:
    """Write ``value`` and read it back; the value the drive then holds."""
    if not var.writable:
        raise DriveFileError(f"{where}: {label(var)} ({var.name}) is {var.access_type}: nothing written")
    sdo = _sdo_var(node, var)
    try:
        sdo.raw = value
    except canopen.SdoAbortedError as exc:
        raise AxisError(f"{where}: SDO write of {label(var)} = {value} aborted by the drive: {exc}") from None
    except canopen.SdoCommunicationError as exc:
        raise AxisError(f"{where}: SDO write of {label(var)}: {exc}") from None
    back = read(node, var, where) if var.readable else value
    if back != value:
        raise AxisError(f"{where}: {label(var)} written {value}, read back {back}")
    return back


def save(node: canopen.RemoteNode, od: odt.ObjectDictionary, path: str | Path, where: str) -> tuple[int, int]:
    """Every readable object into a DCF at ``path``; (objects read, objects the drive refused to read)."""
    read_n = refused = 0
    for var in variables(od):
        var.value = None
        if not var.readable or var.data_type == odt.DOMAIN:
            continue
        try:
            var.value = _sdo_var(node, var).raw
            read_n += 1
        except canopen.SdoAbortedError:
            refused += 1  # kept out of the file: the drive does not give it
        except canopen.SdoCommunicationError as exc:
            raise AxisError(f"{where}: SDO read of {label(var)}: {exc}") from None
    import io

    from drivectl.tracefile.format import atomic_write_text

    buf = io.StringIO()
    canopen.export_od(od, buf, doc_type="dcf")
    atomic_write_text(Path(path), buf.getvalue())
    return read_n, refused


def restore(node: canopen.RemoteNode, path: str | Path, node_id: int, where: str) -> tuple[int, int]:
    """The DCF's writable values back into the drive, each read back; (written, already equal). Every value is
    checked against its limits before the first write."""
    try:
        dcf = canopen.import_od(str(path), node_id)
    except Exception as exc:  # canopen raises many types for a bad file
        reason = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise DriveFileError(f"{path}: cannot be read as a DCF: {reason}") from None
    todo = [v for v in variables(dcf) if v.writable and v.value is not None]
    for var in todo:
        check_limits(var, var.value, f"{path}")
    written = equal = 0
    for var in todo:
        if var.readable and read(node, var, where) == var.value:
            equal += 1
            continue
        write(node, var, var.value, where)
        written += 1
    return written, equal

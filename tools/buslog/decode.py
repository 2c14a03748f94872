"""``drivectl decode LOG``: a CANopen / CiA 402 reading of a bus log, one line per event (docs/guide/buslog.md).

NMT commands, boot-ups and heartbeat state changes, expedited SDO requests and answers with the object's name
from the EDS (canopen's object dictionary), aborts by name, CiA 402 power-state transitions from the statusword
in the node's TPDO (driver/cia402.py), and the SYNC period's statistics at the end. Segmented SDO transfers are
named, not joined; PDOs are not printed frame by frame.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import canopen
import numpy as np
from canopen.sdo.exceptions import SdoAbortedError

from drivectl.driver import cia402
from drivectl.driver.cia301 import (
    HEARTBEAT_BASE,
    NMT_COB_ID,
    SDO_RX_BASE,
    SDO_TX_BASE,
    SYNC_COB_ID,
    NmtCommand,
    NmtState,
)
from drivectl.driver.pdo import PdoLayout
from drivectl.driver.pdo_plan import plan as plan_pdos
from drivectl.tools.buslog.convert import BusLogError, check_log


def _name(od: canopen.ObjectDictionary, index: int, sub: int) -> str:
    try:
        obj = od[index]
    except KeyError:
        return "(not in the EDS)"
    if isinstance(obj, canopen.objectdictionary.ODVariable):
        return obj.name
    var = obj.subindices.get(sub)
    return f"{obj.name}" + (f" / {var.name}" if var is not None and var.name != obj.name else "")


def _nmt(code: int) -> str:
    try:
        return NmtCommand(code).name.lower().replace("_", " ")
    except ValueError:
        return f"command 0x{code:02X}"


def _state(code: int) -> str:
    try:
        return NmtState(code).name.lower().replace("_", "-")
    except ValueError:
        return f"state 0x{code:02X}"


def decode_lines(log: Path, *, node: int, eds: str, mapping: str) -> Iterator[str]:
    """The events of ``log`` for ``node`` as lines (see the module docstring)."""
    log = check_log(log)
    try:
        od = canopen.import_od(eds, node)
    except Exception as exc:  # canopen raises many types for a bad file
        raise BusLogError(f"{log}: EDS {eds}: cannot be read: {str(exc).splitlines()[0] if str(exc) else exc}") \
            from None
    sw_pdo: tuple[int, PdoLayout, int] | None = None
    for p in plan_pdos(od, mapping, node, f"{log}: EDS {eds}").tx:
        if (cia402.STATUSWORD, 0) in p.entries:
            sw_pdo = (p.cob_id, PdoLayout.from_entries(od, p.entries), p.entries.index((cia402.STATUSWORD, 0)))
    syncs: list[float] = []
    heartbeat: dict[int, int] = {}
    power: cia402.PowerState | None = None
    frames = 0
    t0: float | None = None
    try:
        with can.LogReader(str(log)) as reader:
            for msg in reader:
                frames += 1
                if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
                    continue
                t0 = msg.timestamp if t0 is None else t0
                t = f"{msg.timestamp - t0:12.6f}"
                cob, data = msg.arbitration_id, bytes(msg.data)
                if cob == SYNC_COB_ID:
                    syncs.append(msg.timestamp)
                elif cob == NMT_COB_ID and len(data) == 2:
                    yield f"{t} NMT {_nmt(data[0])} -> {'all nodes' if data[1] == 0 else f'node {data[1]}'}"
                elif HEARTBEAT_BASE < cob <= HEARTBEAT_BASE + 127 and len(data) == 1:
                    who = cob - HEARTBEAT_BASE
                    if data[0] == 0:
                        yield f"{t} node {who}: boot-up"
                    elif heartbeat.get(who) != data[0]:
                        yield f"{t} node {who}: heartbeat {_state(data[0])}"
                    heartbeat[who] = data[0]
                elif cob in (SDO_RX_BASE + node, SDO_TX_BASE + node) and len(data) == 8:
                    yield from _sdo(t, od, cob == SDO_RX_BASE + node, data)
                elif sw_pdo is not None and cob == sw_pdo[0] and len(data) == sw_pdo[1].codec.size:
                    sw = sw_pdo[1].codec.unpack(data)[sw_pdo[2]]
                    state = cia402.decode_statusword(sw)
                    if state is not power:
                        yield f"{t} node {node}: CiA 402 {power.value if power else '(start)'} -> {state.value} " \
                              f"(statusword 0x{sw:04X})"
                        power = state
    except Exception as exc:  # python-can's readers raise their parsers' own errors on garbage
        if not frames:
            raise BusLogError(f"{log}: not a readable {log.suffix} CAN log: {exc}") from None
        yield f"{log}: unreadable after frame {frames} (a truncated log?): {exc}"
    if not frames:
        raise BusLogError(f"{log}: no CAN frames in it (not a {log.suffix} log, or an empty one)")
    if len(syncs) > 1:
        d = np.diff(np.asarray(syncs)) * 1e3
        yield (f"SYNC: {len(syncs)} frames, period median {np.median(d):.3f} ms, min {d.min():.3f}, max {d.max():.3f}, "
               f"std {d.std():.3f} ms (the log's own timestamps)")
    else:
        yield f"SYNC: {len(syncs)} frame(s)"
    yield f"{frames} frames read"


def _sdo(t: str, od: Any, request: bool, data: bytes) -> Iterator[str]:
    cmd = data[0]
    ccs = cmd >> 5
    index, sub = struct.unpack_from("<HB", data, 1)
    where = f"0x{index:04X}:{sub:02X} {_name(od, index, sub)}"
    size = 4 - ((cmd >> 2) & 3) if cmd & 0x03 == 0x03 else 4
    raw = int.from_bytes(data[4 : 4 + size], "little")
    value = f"{raw} (0x{raw:X})" if raw > 9 else str(raw)
    if cmd == 0x80:
        code = struct.unpack_from("<I", data, 4)[0]
        reason = SdoAbortedError.CODES.get(code, "unknown abort code")
        yield f"{t} SDO abort {where}: 0x{code:08X} {reason}"
    elif request and ccs == 1:
        yield f"{t} SDO write {where} = {value}" if cmd & 0x02 else f"{t} SDO write {where} (segmented)"
    elif request and ccs == 2:
        yield f"{t} SDO read {where}"
    elif not request and ccs == 2:
        yield f"{t} SDO read {where} -> {value}" if cmd & 0x02 else f"{t} SDO read {where} -> (segmented)"
    elif not request and ccs == 3:
        yield f"{t} SDO write {where} done"


def add_decode_parser(sub: Any) -> None:
    d = sub.add_parser("decode", help="read a CAN log as CANopen / CiA 402: NMT, SDO, SYNC, state transitions",
                       description="One line per event of a recorded CAN log (.asc .blf .log .trc .csv .mf4): NMT, "
                       "boot-up and heartbeat changes, SDO requests and answers named from the EDS, aborts by name, "
                       "CiA 402 state transitions from the statusword, and the SYNC period's statistics "
                       "(docs/guide/buslog.md).")
    d.add_argument("log", metavar="LOG")
    d.add_argument("--axis", default="x", help="the axis whose node, EDS and mapping are used (default x)")
    d.add_argument("--node", type=int, metavar="N", help="the drive's node-ID (default: the axis's)")
    d.add_argument("--eds", metavar="FILE", help="the drive's EDS (default: the axis's)")


def cmd_decode(args: Any) -> int:
    from drivectl.machine.bus_budget import resolve_mapping
    from drivectl.machine.config import load_config

    cfg = load_config(args.config)
    ac = cfg.axis(args.axis)
    node = ac.node_id if args.node is None else args.node
    if not 1 <= node <= 127:
        raise BusLogError(f"--node {node}: expected 1..127")
    for line in decode_lines(Path(args.log), node=node, eds=args.eds or ac.eds, mapping=resolve_mapping(cfg, 1)):
        print(line)
    return 0

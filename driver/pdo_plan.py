"""The PDO mapping drivectl asks of one drive, planned within that drive's limits (read from its EDS).

A drive says in its EDS how many RPDOs and TPDOs it has (numbering may have gaps), how many entries each
mapping takes (sub-index 0's HighLimit, or the entries it lists), which mappings are fixed (read-only or
const: used as they are when they carry what the loop needs), which COB-IDs it lets a master change,
and which transmission types it allows (a read-only type is the only one). The plan puts each wanted
group of objects (driver/pdo_mappings.py: full, compact, minimal) into the first PDOs that can carry
it: a fixed mapping that carries a whole group is used as it is, the others are mapped entry by entry
(at most 64 bits and the drive's entry count per PDO, a group split across PDOs where it must). The
loop runs on SYNC: a cyclic PDO needs transmission type 1 (every SYNC); a drive whose PDOs cannot be
synchronous is refused in one line. PDOs the plan leaves unused are disabled where the drive lets the
COB-ID be written, else their mapping emptied, else said (and counted in the bus budget).
"""

from __future__ import annotations

from dataclasses import dataclass

from canopen import objectdictionary as odt

from drivectl.driver import cia402
from drivectl.driver.capabilities import DriveRefused, assess, object_value
from drivectl.driver.cia301 import RPDO_BASE, TPDO_BASE
from drivectl.driver.pdo_mappings import (
    COMPACT_TPDO_ENTRIES,
    MINIMAL_RPDO_ENTRIES,
    MINIMAL_TPDO_ENTRIES,
    RPDO_ENTRIES,
    TPDO_ENTRIES,
)

Entry = tuple[int, int]
SYNC_EVERY = 1  # transmission type: every SYNC
EVENT = 255  # event-driven (device profile)
_STANDARD_RX = frozenset([*range(0, 241), 254, 255])
_STANDARD_TX = frozenset([*range(0, 241), 252, 253, 254, 255])


@dataclass(frozen=True)
class PdoSlot:
    """One PDO of the drive as its EDS describes it."""

    rx: bool
    n: int  # 1-based PDO number (0x1400 + n - 1)
    cob_id: int  # the EDS's value (with $NODEID resolved)
    cob_writable: bool
    types: frozenset[int]  # transmission types the drive allows
    type_writable: bool
    max_entries: int
    fixed: tuple[Entry, ...] | None  # the mapping, when the drive does not let it be changed
    event_timer: bool  # sub-index 5 present and writable (the RPDO deadline, or a TPDO's event timer)

    @property
    def comm(self) -> int:
        return (cia402.RPDO_COMM if self.rx else cia402.TPDO_COMM) + self.n - 1

    @property
    def name(self) -> str:
        return f"{'RPDO' if self.rx else 'TPDO'}{self.n}"


@dataclass(frozen=True)
class PlannedPdo:
    slot: PdoSlot
    entries: tuple[Entry, ...]
    trans_type: int
    cob_id: int  # 11-bit COB-ID it will use
    data_bytes: int


@dataclass(frozen=True)
class PdoPlan:
    rx: tuple[PlannedPdo, ...]  # cyclic first; an event-driven one (minimal's controlword) last
    tx: tuple[PlannedPdo, ...]
    unused: tuple[PdoSlot, ...]
    mapping: str
    dropped: tuple[Entry, ...] = ()  # optional objects no PDO was left for

    @property
    def derived_velocity(self) -> bool:
        return not any((cia402.VELOCITY_ACTUAL, 0) in p.entries for p in self.tx)

    @property
    def torque_mapped(self) -> bool:
        return any((cia402.TORQUE_ACTUAL, 0) in p.entries for p in self.tx)

    def frames(self) -> list[tuple[str, int, bool]]:
        """(what, data bytes, cyclic) of each frame this mapping puts on the bus per cycle."""
        out = []
        for p in (*self.tx, *self.rx):
            names = " + ".join(OBJECT_NAMES.get(i, f"0x{i:04X}") for i, _ in p.entries)
            out.append((f"{p.slot.name} {names}", p.data_bytes, p.trans_type <= 240))
        return out

    def lines(self) -> list[str]:
        out = []
        for p in (*self.rx, *self.tx):
            names = " + ".join(OBJECT_NAMES.get(i, f"0x{i:04X}") for i, _ in p.entries)
            how = "fixed mapping, used as it is" if p.slot.fixed is not None else "mapped"
            kind = "every SYNC" if p.trans_type == SYNC_EVERY else f"transmission type {p.trans_type}"
            out.append(f"{p.slot.name} (COB-ID 0x{p.cob_id:03X}, {kind}, {how}): {names}")
        for i, _ in self.dropped:
            out.append(f"{OBJECT_NAMES.get(i, hex(i))} 0x{i:04X}: no PDO left for it, "
                       + ("derived on the host" if i == cia402.VELOCITY_ACTUAL else "not traced"))
        for s in self.unused:
            if s.cob_writable:
                continue
            if s.fixed is None:
                out.append(f"{s.name}: COB-ID read-only: its mapping is emptied")
            else:
                out.append(f"{s.name}: COB-ID and mapping read-only: it stays as the drive has it")
        return out


#: what a mapping may leave out when the drive has no PDO left for it
OPTIONAL = ((cia402.VELOCITY_ACTUAL, 0), (cia402.TORQUE_ACTUAL, 0))

OBJECT_NAMES = {
    cia402.CONTROLWORD: "controlword", cia402.TARGET_TORQUE: "target torque", cia402.STATUSWORD: "statusword",
    cia402.POSITION_ACTUAL: "position", cia402.VELOCITY_ACTUAL: "velocity", cia402.TORQUE_ACTUAL: "torque actual",
}


def entry_bits(od: odt.ObjectDictionary, entry: Entry) -> int:
    index, sub = entry
    if index < 0x1000:  # a dummy entry: the data type's length (CiA 301 7.4.7.1)
        return {1: 1, 2: 8, 3: 16, 4: 32, 5: 8, 6: 16, 7: 32}.get(index, 8)
    obj = od[index]
    if not isinstance(obj, odt.ODVariable):
        obj = obj[sub]
    return len(obj)


def _sub(od: odt.ObjectDictionary, index: int, sub: int) -> odt.ODVariable | None:
    if index not in od:
        return None
    obj = od[index]
    if isinstance(obj, odt.ODVariable):
        return obj if sub == 0 else None
    return obj.subindices.get(sub)


def _types(var: odt.ODVariable | None, rx: bool) -> tuple[frozenset[int], bool]:
    standard = _STANDARD_RX if rx else _STANDARD_TX
    if var is None:
        return frozenset(), False
    if not var.writable:
        value = object_value(var)
        return frozenset([value] if value is not None else []), False
    lo = var.min if var.min is not None else 0
    hi = var.max if var.max is not None else 255
    return frozenset(t for t in standard if lo <= t <= hi), True


def slots(od: odt.ObjectDictionary, rx: bool) -> list[PdoSlot]:
    """The drive's RPDOs (``rx``) or TPDOs as its EDS describes them (gaps in the numbering skipped)."""
    comm_base = cia402.RPDO_COMM if rx else cia402.TPDO_COMM
    out = []
    for k in range(512):
        comm, mapping = comm_base + k, comm_base + 0x200 + k
        if comm not in od or mapping not in od:
            continue
        cob = _sub(od, comm, 1)
        if cob is None or (not cob.writable and (object_value(cob) or 0) & 0x80000000):
            continue  # no COB-ID, or one fixed as invalid: a PDO the drive never sends or takes
        types, type_writable = _types(_sub(od, comm, 2), rx)
        count = _sub(od, mapping, 0)
        entries = [s for s in od[mapping].subindices if s] if not isinstance(od[mapping], odt.ODVariable) else []
        max_entries = len(entries)
        if count is not None and count.max is not None:
            max_entries = min(max_entries, count.max) if max_entries else count.max
        fixed = None
        if count is None or not count.writable or not all(_sub(od, mapping, s).writable for s in entries):
            n = object_value(count) or 0
            words = [object_value(_sub(od, mapping, s)) or 0 for s in range(1, n + 1)]
            fixed = tuple(((w >> 16) & 0xFFFF, (w >> 8) & 0xFF) for w in words)
        timer = _sub(od, comm, 5)
        out.append(PdoSlot(rx, k + 1, object_value(cob) or 0, cob.writable, types, type_writable, max_entries,
                           fixed, timer is not None and timer.writable))
    return out


def wanted(od: odt.ObjectDictionary, mapping: str) -> tuple[list[tuple[Entry, ...]], list[tuple[Entry, ...]]]:
    """(RPDO groups, TPDO groups) the mapping asks for, without the optional objects the drive lacks or cannot
    map (velocity and torque actual: derived on the host, or not traced)."""

    def ok(entry: Entry) -> bool:
        var = _sub(od, *entry)
        return var is not None and var.pdo_mappable

    if mapping == "minimal":
        rx, tx = list(MINIMAL_RPDO_ENTRIES), list(MINIMAL_TPDO_ENTRIES)
    else:
        rx = [RPDO_ENTRIES]
        tx = list(COMPACT_TPDO_ENTRIES if mapping == "compact" else TPDO_ENTRIES)
    tx = [g for g in (tuple(e for e in group if ok(e)) for group in tx) if g]
    return rx, tx


def _cob(slot: PdoSlot, k: int, node_id: int) -> int:
    """The COB-ID a planned PDO uses: the drive's own when it is read-only; else the predefined connection set's
    for the k-th PDO of its direction (0x180/0x200 + 0x100 k + node), beyond four the EDS's value."""
    if not slot.cob_writable:
        return slot.cob_id & 0x7FF
    base = RPDO_BASE if slot.rx else TPDO_BASE
    if k < len(base):
        return base[k] + node_id
    return slot.cob_id & 0x7FF


def plan(od: odt.ObjectDictionary, mapping: str, node_id: int, where: str) -> PdoPlan:
    """The PDOs drivectl configures on this drive for ``mapping``, or :class:`DriveRefused` (one line) when the
    drive's PDOs cannot carry the loop."""
    assess(od, where)  # the essentials first: a drive without one is refused for that, not for its PDOs
    rx_groups, tx_groups = wanted(od, mapping)
    planned: dict[bool, list[PlannedPdo]] = {True: [], False: []}
    unused: list[PdoSlot] = []
    dropped: list[Entry] = []
    for rx, groups in ((True, rx_groups), (False, tx_groups)):
        free = slots(od, rx)
        kind = "RPDO" if rx else "TPDO"
        if not free:
            raise DriveRefused(f"{where}: drive has no {kind}: drivectl closes the loop by PDO")
        if not any(SYNC_EVERY in s.types for s in free):
            types = sorted({t for s in free for t in s.types})
            raise DriveRefused(f"{where}: drive's {kind}s are not synchronous (transmission types "
                               f"{', '.join(map(str, types)) or 'none'}{'' if free[0].type_writable else ', read-only'}"
                               "): drivectl's loop runs on SYNC")
        for g, group in enumerate(groups):
            event = rx and mapping == "minimal" and g == 1  # the controlword, event-driven
            group_left = list(group)
            # a fixed mapping that carries the whole group (an RPDO: nothing else but dummies) is used as it is
            for slot in free:
                if slot.fixed is None or not slot.fixed:
                    continue
                if not set(group) <= set(slot.fixed):
                    continue
                if rx and any(e not in group and e[0] >= 0x1000 for e in slot.fixed):
                    continue
                ttype = _type_for(slot, event)
                if ttype is None:
                    continue
                free.remove(slot)
                planned[rx].append(_planned(od, slot, slot.fixed, ttype, len(planned[rx]), node_id))
                group_left = []
                break
            while group_left:
                slot = next((s for s in free if s.fixed is None and s.max_entries > 0
                             and _type_for(s, event) is not None), None)
                if slot is None and all(e in OPTIONAL for e in group_left):
                    dropped.extend(group_left)  # velocity derived on the host, torque actual not traced
                    break
                if slot is None:
                    names = ", ".join(f"0x{i:04X}" for i, _ in group_left)
                    raise DriveRefused(f"{where}: no {kind} left that can carry {names} (the drive's {kind}s: "
                                       f"{len(slots(od, rx))}, fixed or full): drivectl closes the loop by PDO")
                free.remove(slot)
                taken, bits = [], 0
                for e in group_left:
                    b = entry_bits(od, e)
                    if len(taken) >= slot.max_entries or bits + b > 64:
                        break
                    taken.append(e)
                    bits += b
                group_left = group_left[len(taken):]
                planned[rx].append(_planned(od, slot, tuple(taken), _type_for(slot, event), len(planned[rx]),
                                            node_id))
        unused.extend(free)
    return PdoPlan(tuple(planned[True]), tuple(planned[False]), tuple(unused), mapping, tuple(dropped))


def _type_for(slot: PdoSlot, event: bool) -> int | None:
    if event and EVENT in slot.types:
        return EVENT
    return SYNC_EVERY if SYNC_EVERY in slot.types else None


def _planned(od: odt.ObjectDictionary, slot: PdoSlot, entries: tuple[Entry, ...], ttype: int, k: int,
             node_id: int) -> PlannedPdo:
    nbytes = (sum(entry_bits(od, e) for e in entries) + 7) // 8
    return PlannedPdo(slot, entries, ttype, _cob(slot, k, node_id), nbytes)

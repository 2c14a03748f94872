"""The PDO mapping of one node as a log shows it: replayed from the log's own PDO configuration SDO writes.

A log that covers the bring-up carries the master's writes to 0x1400.. (RPDO communication: COB-ID, transmission
type), 0x1600.. (RPDO mapping), 0x1800.. and 0x1A00.. (the TPDOs'). :class:`NodeMapping` starts from a base
(the mapping drivectl plans for the drive from the machine configuration, driver/pdo_plan.py, or the EDS's own
default values) and replays every write the drive confirmed (tools/buslog/sdo.py) on top of it, so a PDO the
log configured decodes as the log configured it, and one it did not as the base says. :attr:`NodeMapping.source`
says which. The layouts are the driver's own (driver/pdo.py :class:`PdoLayout`); :func:`numpy_dtype` is that
layout's struct as a numpy record, so a column of frames unpacks exactly as the master unpacks one.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from canopen import objectdictionary as odt

from drivectl.driver import cia402
from drivectl.driver.capabilities import object_value
from drivectl.driver.pdo import PdoLayout
from drivectl.driver.pdo_plan import entry_bits, slots
from drivectl.driver.pdo_plan import plan as plan_pdos

_INVALID = 0x80000000
_NP = {"b": "<i1", "h": "<i2", "i": "<i4", "B": "<u1", "H": "<u2", "I": "<u4"}


def numpy_dtype(layout: PdoLayout) -> np.dtype:
    """The layout's packed struct as a numpy record (one field per mapped object, in order)."""
    codes = layout.codec.format.lstrip("<")
    return np.dtype([(f"f{k}", _NP[c]) for k, c in enumerate(codes)])


@dataclass
class PdoConfig:
    """One PDO of the node as configured: COB-ID (bit 31: not valid), transmission type, mapping words."""

    rx: bool
    n: int  # 1-based PDO number
    cob_id: int
    trans_type: int
    count: int
    words: dict[int, int] = field(default_factory=dict)  # sub-index -> index << 16 | sub << 8 | bits
    source: str = "configuration"  # where the mapping words came from: "log", "configuration" or "EDS defaults"
    comm_source: str = "configuration"  # where the COB-ID and transmission type came from

    @property
    def name(self) -> str:
        return f"{'RPDO' if self.rx else 'TPDO'}{self.n}"

    @property
    def valid(self) -> bool:
        return not self.cob_id & _INVALID and self.count > 0

    @property
    def cyclic(self) -> bool:
        """Sent at every SYNC (transmission type 1): expected in every SYNC's window."""
        return self.trans_type == 1

    def entries(self) -> tuple[tuple[int, int], ...]:
        return tuple(((w >> 16) & 0xFFFF, (w >> 8) & 0xFF) for w in
                     (self.words.get(s, 0) for s in range(1, self.count + 1)) if w)


@dataclass(frozen=True)
class ActivePdo:
    """A PDO the node uses now, ready to decode."""

    config: PdoConfig
    cob: int  # 11-bit
    layout: PdoLayout
    dtype: np.dtype


class NodeMapping:
    """The PDOs of ``node`` (see the module docstring). ``base``: "configuration" (the plan for ``mapping`` on
    the EDS, as drivectl would configure the drive) or "eds" (the EDS's default values)."""

    def __init__(self, od: odt.ObjectDictionary, node: int, mapping: str, where: str, base: str = "configuration"):
        self.od, self.node = od, node
        self.pdos: dict[tuple[bool, int], PdoConfig] = {}
        self.version = 0
        self.errors: list[str] = []
        self.base = base
        if base == "configuration":
            try:
                self._from_plan(plan_pdos(od, mapping, node, where), mapping, where)
            except Exception as exc:  # a drive drivectl itself would refuse: its EDS's defaults then
                self.errors.append(f"no {mapping} mapping planned ({str(exc).splitlines()[0]}): EDS defaults used")
                self.base = "eds"
        if self.base == "eds":
            self._from_eds()
        self._base_label = (f"the configuration ({mapping} mapping planned on {where})" if self.base == "configuration"
                            else f"the EDS's default values ({where})")
        self._active: list[ActivePdo] | None = None

    # -- the base ------------------------------------------------------------------------------------------
    def _from_plan(self, plan, mapping: str, where: str) -> None:
        for s in slots(self.od, True) + slots(self.od, False):
            self.pdos[(s.rx, s.n)] = PdoConfig(s.rx, s.n, _INVALID | (s.cob_id & 0x7FF), 255, 0)
        for p in (*plan.rx, *plan.tx):
            words = {k: e[0] << 16 | e[1] << 8 | entry_bits(self.od, e) for k, e in enumerate(p.entries, 1)}
            self.pdos[(p.slot.rx, p.slot.n)] = PdoConfig(p.slot.rx, p.slot.n, p.cob_id, p.trans_type, len(words),
                                                         words)

    def _from_eds(self) -> None:
        for s in slots(self.od, True) + slots(self.od, False):
            comm = self.od[s.comm]
            ttype = object_value(comm.subindices.get(2)) if 2 in comm.subindices else None
            mp = self.od[s.comm + 0x200]
            count = object_value(mp.subindices.get(0)) or 0
            words = {k: object_value(mp.subindices.get(k)) or 0 for k in range(1, count + 1)}
            self.pdos[(s.rx, s.n)] = PdoConfig(s.rx, s.n, s.cob_id, 255 if ttype is None else ttype, count, words,
                                               "EDS defaults", "EDS defaults")

    # -- the log's writes ----------------------------------------------------------------------------------
    def write(self, index: int, sub: int, value: bytes) -> bool:
        """Replay a write the drive confirmed; True when it changed a PDO's configuration."""
        found = next(((b, rx, m) for b, rx, m in ((cia402.RPDO_COMM, True, False), (cia402.RPDO_MAP, True, True),
                                                  (cia402.TPDO_COMM, False, False), (cia402.TPDO_MAP, False, True))
                      if b <= index < b + 0x200), None)
        if found is None:
            return False
        base, rx, is_map = found
        n = index - base + 1
        v = int.from_bytes(value[:4], "little")
        pdo = self.pdos.get((rx, n))
        if pdo is None:
            pdo = self.pdos[(rx, n)] = PdoConfig(rx, n, _INVALID, 255, 0)
        if is_map:
            if sub == 0:
                pdo.count = v
            else:
                pdo.words[sub] = v
            pdo.source = "log"
        elif sub in (1, 2):
            if sub == 1:
                pdo.cob_id = v
            else:
                pdo.trans_type = v
            pdo.comm_source = "log"
        else:
            return False
        self.version += 1
        self._active = None
        return True

    # -- what to decode ------------------------------------------------------------------------------------
    def active(self) -> list[ActivePdo]:
        """The valid PDOs now, each with its layout (one whose objects cannot be unpacked is left out and said)."""
        if self._active is None:
            out = []
            for pdo in sorted(self.pdos.values(), key=lambda p: (p.rx, p.n)):
                if not pdo.valid:
                    continue
                try:
                    layout = PdoLayout.from_entries(self.od, pdo.entries())
                except (KeyError, ValueError) as exc:
                    msg = f"{pdo.name}: mapping {[hex(w) for w in pdo.words.values()]} not decoded: {exc}"
                    if msg not in self.errors:
                        self.errors.append(msg)
                    continue
                out.append(ActivePdo(pdo, pdo.cob_id & 0x7FF, layout, numpy_dtype(layout)))
            self._active = out
        return self._active

    @property
    def source(self) -> str:
        """Where the mapping in use came from, in words."""
        used = self.active()
        from_log = [a.config.name for a in used if a.config.source == "log"]
        rest = [a.config.name for a in used if a.config.source != "log"]
        if from_log and not rest:
            return f"the log's own PDO configuration SDO writes ({', '.join(from_log)})"
        if from_log:
            return (f"the log's own PDO configuration SDO writes ({', '.join(from_log)}); the mapping of "
                    f"{', '.join(rest)} from {self._base_label}")
        return f"{self._base_label}: the log carries no PDO configuration writes for node {self.node}"

    def describe(self) -> list[str]:
        names = {cia402.CONTROLWORD: "controlword", cia402.STATUSWORD: "statusword"}
        out = []
        for a in self.active():
            objs = " + ".join(f"0x{i:04X}" + (f" {names[i]}" if i in names else "") for i, _ in a.layout.entries)
            c = a.config
            where = c.source if c.source == c.comm_source else f"mapping: {c.source}, COB-ID and type: {c.comm_source}"
            out.append(f"{c.name} COB-ID 0x{a.cob:03X} type {c.trans_type} ({where}): {objs}")
        return out

"""PDOs of the emulated drive: what CiA 301 lets a master write, and the PDOs that result.

Rules checked on every SDO write to 0x1400-0x1BFF (abort codes as CiA 301 lists them; where the
standard leaves the code open, CANopenNode's choice, as a master written against real drives expects):

* communication parameter: 29-bit COB-IDs (bit 29) and the restricted COB-IDs refused (0x06090030);
  a valid PDO's COB-ID, inhibit time and SYNC start value change only while it is invalid (bit 31 set,
  0x06090030); reserved transmission types refused (RPDO 241..253, TPDO 241..251: 0x06090030);
* mapping: no change while the PDO is valid, and entries only while sub-index 0 is 0 (0x06010000,
  the procedure of CiA 301 7.5.2.36: invalidate, sub 0 = 0, entries, sub 0 = n, validate); each
  entry must name an existing object (0x06020000 / 0x06090011) that may be mapped in that direction,
  with its true length (0x06040041); n entries of more than 64 bits in all: 0x06040042.

A PDO is valid when its COB-ID has bit 31 clear and its mapping is not empty; a TPDO answers an RTR
unless bit 30 is set.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from operator import call

import canopen
from canopen import objectdictionary as odt

from drivectl.driver.pdo import PdoLayout
from drivectl.plant_emulator.sdo_server import find_object

ABORT_UNSUPPORTED = 0x06010000
ABORT_RANGE = 0x06090030
ABORT_NOT_MAPPABLE = 0x06040041
ABORT_TOO_LONG = 0x06040042

#: COB-IDs no PDO may use (CiA 301 table 41: NMT, SYNC/EMCY, TIME, SDO, NMT error control, LSS)
_RESTRICTED = (range(0x000, 0x001), range(0x001, 0x080), range(0x080, 0x081), range(0x100, 0x101),
               range(0x101, 0x181), range(0x581, 0x600), range(0x601, 0x680), range(0x6E0, 0x700),
               range(0x701, 0x780), range(0x780, 0x800))
RPDO_TYPES = frozenset([*range(0, 241), 254, 255])
TPDO_TYPES = frozenset([*range(0, 241), 252, 253, 254, 255])


def _restricted(cob: int) -> bool:
    return any(cob in r for r in _RESTRICTED)


@dataclass
class Rpdo:
    cob: int
    layout: PdoLayout
    slots: tuple[tuple[int, int, int, int], ...]  # (index, sub, byte offset, byte width) per entry
    trans_type: int
    comm: int = 0x1400  # its communication parameter (0x1400:05, RPDO1's event timer, is the drive's deadline)


@dataclass
class Tpdo:
    """One valid TPDO and its transmission state (times in ms of the drive's clock)."""

    cob: int
    layout: PdoLayout
    getters: tuple[Callable[[], int], ...]
    trans_type: int
    inhibit_ms: float
    event_ms: float
    rtr_allowed: bool
    rtr_pending: bool = False
    count: int = 0
    last_frame: bytes | None = None
    last_ms: float = field(default=-math.inf)

    def pack(self) -> bytes:
        return self.layout.codec.pack(*map(call, self.getters))  # each getter called, in order (no list frame)

    @property
    def answers_rtr_now(self) -> bool:
        return self.trans_type >= 253  # event-driven and RTR-only: at once; synchronous ones at the next SYNC

    def on_sync(self, now: float) -> bytes | None:
        """The frame this TPDO sends at a SYNC, or None."""
        t = self.trans_type
        if t == 1:
            frame = self.pack()
        elif 2 <= t <= 240:  # every t-th SYNC
            self.count += 1
            if self.count < t and not self.rtr_pending:
                return None
            self.count = 0 if self.count >= t else self.count
            frame = self.pack()
        elif t == 0:  # acyclic synchronous: at the SYNC after a change
            frame = self.pack()
            if frame == self.last_frame and not self.rtr_pending:
                return None
        elif t == 252:  # synchronous, on RTR only
            if not self.rtr_pending:
                return None
            frame = self.pack()
        else:
            return None
        self.rtr_pending = False
        self.last_frame, self.last_ms = frame, now
        return frame

    def on_tick(self, now: float) -> bytes | None:
        """Event-driven (254/255): on a change once the inhibit time (0x18xx:3) has passed since the last
        frame, and when the event timer (0x18xx:5) runs out."""
        if self.trans_type < 254 or now - self.last_ms < self.inhibit_ms:
            return None
        frame = self.pack()
        if frame != self.last_frame or (self.event_ms and now - self.last_ms >= self.event_ms - 1e-9):
            self.last_frame, self.last_ms = frame, now
            return frame
        return None

    def sent(self, frame: bytes, now: float) -> None:
        self.last_frame, self.last_ms = frame, now


class PdoRules:
    """The PDO rules of one drive; ``value(index, sub)`` reads what the drive holds."""

    def __init__(self, od: odt.ObjectDictionary, value: Callable[[int, int], int]):
        self.od = od
        self.value = value

    @staticmethod
    def _parts(index: int) -> tuple[bool, int, int]:
        """(receive?, communication index, mapping index) of a PDO parameter index."""
        rx = index < 0x1800
        n = (index - (0x1400 if rx else 0x1800)) & 0x1FF
        comm = (0x1400 if rx else 0x1800) + n
        return rx, comm, comm + 0x200

    def _valid(self, comm: int) -> bool:
        return not self.value(comm, 1) & 0x80000000

    def _cob_writable(self, comm: int) -> bool:
        rec = self.od[comm]
        return isinstance(rec, odt.ODVariable) or 1 not in rec.subindices or rec.subindices[1].writable

    def check(self, index: int, sub: int, data: bytes) -> None:
        rx, comm, mapping = self._parts(index)
        if comm not in self.od:
            return
        valid = self._valid(comm)
        if index == comm:
            if sub == 1:
                new = struct.unpack("<I", data)[0]
                old = self.value(comm, 1)
                if new & 0x20000000 or new & 0x1FFFF800:
                    raise canopen.SdoAbortedError(ABORT_RANGE)  # 29-bit identifiers: not supported
                if not new & 0x80000000:
                    if valid and (new & 0x7FF) != (old & 0x7FF):
                        raise canopen.SdoAbortedError(ABORT_RANGE)
                    if _restricted(new & 0x7FF):
                        raise canopen.SdoAbortedError(ABORT_RANGE)
            elif sub == 2:
                if data[0] not in (RPDO_TYPES if rx else TPDO_TYPES):
                    raise canopen.SdoAbortedError(ABORT_RANGE)
            elif sub in (3, 6) and not rx:
                if valid:
                    raise canopen.SdoAbortedError(ABORT_RANGE)
                if sub == 6 and data[0] > 240:
                    raise canopen.SdoAbortedError(ABORT_RANGE)
            return
        if index != mapping:
            return
        if valid and self._cob_writable(comm):
            # invalidate first (CiA 301 7.5.2.36); a drive whose COB-ID is read-only takes sub 0 = 0 as the step
            raise canopen.SdoAbortedError(ABORT_UNSUPPORTED)
        if sub == 0:
            count = data[0]
            entries = [s for s in self.od[mapping].subindices if s]
            if count > len(entries):
                raise canopen.SdoAbortedError(ABORT_TOO_LONG)
            bits = sum(self._entry(self.value(mapping, s), rx) for s in range(1, count + 1))
            if bits > 64:
                raise canopen.SdoAbortedError(ABORT_TOO_LONG)
            return
        if self.value(mapping, 0) != 0:
            raise canopen.SdoAbortedError(ABORT_UNSUPPORTED)
        word = struct.unpack("<I", data)[0]
        if word:
            self._entry(word, rx)

    def _entry(self, word: int, rx: bool) -> int:
        """The length in bits of one mapping entry, or the abort that refuses it."""
        index, sub, bits = (word >> 16) & 0xFFFF, (word >> 8) & 0xFF, word & 0xFF
        if word == 0:
            raise canopen.SdoAbortedError(ABORT_NOT_MAPPABLE)  # an empty entry among the n mapped
        obj = find_object(self.od, index, sub)
        if index < 0x1000:  # a dummy entry (DummyUsage): receive only
            ok = rx
        else:
            ok = obj.pdo_mappable and (obj.writable if rx else obj.readable)
        try:
            PdoLayout.from_entries(self.od, ((index, sub),))
        except ValueError:
            ok = False
        if not ok or bits != len(obj):
            raise canopen.SdoAbortedError(ABORT_NOT_MAPPABLE)
        return bits

    # -- the PDOs that result ---------------------------------------------------------------------------
    def _mapped(self, comm: int) -> tuple[int, PdoLayout] | None:
        cob = self.value(comm, 1)
        count = self.value(comm + 0x200, 0)
        if cob & 0x80000000 or count == 0:
            return None
        words = [self.value(comm + 0x200, i + 1) for i in range(count)]
        try:
            return cob, PdoLayout.from_mapping_words(self.od, words)
        except (KeyError, ValueError):
            return None  # a default mapping naming an object the drive lacks: no PDO until it is remapped

    def rpdos(self) -> list[Rpdo]:
        out = []
        for comm in range(0x1400, 0x1600):
            if comm not in self.od or comm + 0x200 not in self.od:
                continue  # a gap in the drive's PDO numbering
            got = self._mapped(comm)
            if got is None:
                continue
            cob, layout = got
            slots, offset = [], 0
            for (index, sub), code in zip(layout.entries, layout.codec.format[1:], strict=True):
                width = struct.calcsize("<" + code)
                slots.append((index, sub, offset, width))
                offset += width
            out.append(Rpdo(cob & 0x7FF, layout, tuple(slots), self.value(comm, 2), comm))
        return out

    def tpdos(self, getter: Callable[[int, int], Callable[[], int]]) -> list[Tpdo]:
        out = []
        for comm in range(0x1800, 0x1A00):
            if comm not in self.od or comm + 0x200 not in self.od:
                continue  # a gap in the drive's PDO numbering
            got = self._mapped(comm)
            if got is None:
                continue
            cob, layout = got
            rec = self.od[comm]
            inhibit = self.value(comm, 3) / 10.0 if 3 in rec.subindices else 0.0  # 100 us units
            event = float(self.value(comm, 5)) if 5 in rec.subindices else 0.0
            out.append(Tpdo(cob & 0x7FF, layout, tuple(getter(i, s) for i, s in layout.entries),
                            self.value(comm, 2), inhibit, event, not cob & 0x40000000))
        return out

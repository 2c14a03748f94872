"""PDO layouts: which objects a PDO carries, packed and unpacked with one precompiled struct.

The master configures the mapping by SDO (canopen's PdoMap does the writing); both sides then use a
:class:`PdoLayout` for the per-cycle frames, so the cyclic path does no object-dictionary lookups.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from canopen import objectdictionary as odt

_FORMATS = {
    odt.INTEGER8: "b", odt.INTEGER16: "h", odt.INTEGER32: "i",
    odt.UNSIGNED8: "B", odt.UNSIGNED16: "H", odt.UNSIGNED32: "I",
}


@dataclass(frozen=True)
class PdoLayout:
    """The objects of one PDO in order, as (index, subindex) pairs, and their packed form."""

    entries: tuple[tuple[int, int], ...]
    codec: struct.Struct

    @classmethod
    def from_entries(cls, od: odt.ObjectDictionary, entries: tuple[tuple[int, int], ...]) -> PdoLayout:
        fmt = "<"
        for index, sub in entries:
            obj = od[index]
            if not isinstance(obj, odt.ODVariable):
                obj = obj[sub]
            if obj.data_type not in _FORMATS:
                raise ValueError(f"PDO: object 0x{index:04X}:{sub} has a type that cannot be mapped")
            fmt += _FORMATS[obj.data_type]
        codec = struct.Struct(fmt)
        if codec.size > 8:
            raise ValueError(f"PDO: {len(entries)} objects need {codec.size} bytes, a CAN frame holds 8")
        return cls(tuple(entries), codec)

    @classmethod
    def from_mapping_words(cls, od: odt.ObjectDictionary, words: list[int]) -> PdoLayout:
        """From the 32-bit mapping entries of 0x16xx/0x1Axx (index << 16 | sub << 8 | bits)."""
        return cls.from_entries(od, tuple(((w >> 16) & 0xFFFF, (w >> 8) & 0xFF) for w in words if w))

    def mapping_words(self, od: odt.ObjectDictionary) -> list[int]:
        words = []
        for (index, sub), code in zip(self.entries, self.codec.format[1:], strict=True):
            words.append(index << 16 | sub << 8 | struct.calcsize("<" + code) * 8)
        return words

"""Malformed frames at the emulated drive: counted per kind, logged once per kind (then every 1000th).

Every receive path of the emulated drive (NMT, SYNC, SDO, RPDO, heartbeat consumer, RTR) checks length,
RTR and data before use and hands what it cannot use to :meth:`FrameGuard.reject`: the frame is dropped
(an RPDO that does not fit its mapping is also answered with EMCY 0x8210/0x8220 by the caller, CiA 301),
the drive goes on. Nothing a bus sends makes the emulator raise.
"""

from __future__ import annotations

import logging
from collections import Counter

log = logging.getLogger("drivectl.emulator")

#: after the first report of a kind, one more every LOG_EVERY occurrences (a flood stays a few lines)
LOG_EVERY = 1000


class FrameGuard:
    """Counts the frames one drive refused, by kind (``short-rpdo``, ``sdo-length``, ``remote-sdo``...)."""

    def __init__(self, node_id: int):
        self.node_id = node_id
        self.counts: Counter[str] = Counter()

    def reject(self, kind: str, can_id: int, data: bytes | bytearray, why: str) -> None:
        self.counts[kind] += 1
        n = self.counts[kind]
        if n == 1 or n % LOG_EVERY == 0:
            log.warning("node %d: malformed frame 0x%03X [%s] dropped (%s): %s (%d of this kind so far)",
                        self.node_id, can_id, bytes(data).hex(" "), kind, why, n)

    @property
    def total(self) -> int:
        return sum(self.counts.values())

"""What the master accepts from the bus: every received frame is checked before canopen's dispatch.

CANopen fixes the length of most of its frames (CiA 301): an NMT command is 2 bytes, an EMCY 8, an
SDO response 8, a heartbeat 1, a SYNC 0 or 1 (the counter). canopen's own handlers unpack them
without looking (``struct.unpack`` on a short EMCY raises inside the dispatch; in lockstep that
would end the master with a traceback in the middle of a cycle, before its quick stop). The master
answers no remote frame (no node guarding, no RTR-requested PDO), so a remote frame is dropped too.

A frame that fails its check is not delivered: it is counted (per kind, per node), logged once per
kind and then at most every ``LOG_INTERVAL_S`` with the count since, and — where it belongs to the
control exchange (a TPDO) — the cycle that lacked it is bridged as a lost one by the axis. The
PDO lengths are the axes' business (only they know the mapping): :class:`CanopenAxis` checks its
TPDOs itself and counts them here through :meth:`FrameGuard.reject`.
"""

from __future__ import annotations

import logging
import time
from collections import Counter

from drivectl.driver.cia301 import (
    EMCY_BASE,
    HEARTBEAT_BASE,
    NMT_COB_ID,
    SDO_TX_BASE,
    SYNC_COB_ID,
)

log = logging.getLogger("drivectl.frames")

#: a kind's log line is repeated at most this often (with the count since the last one)
LOG_INTERVAL_S = 10.0


def expected_length(can_id: int) -> tuple[int, int] | None:
    """(shortest, longest) data length CiA 301 allows on ``can_id``; None where it depends on a
    mapping (PDOs) or the COB-ID is not a CiA 301 service the master consumes."""
    if can_id == NMT_COB_ID:
        return 2, 2
    if can_id == SYNC_COB_ID:
        return 0, 1  # with or without the SYNC counter
    if EMCY_BASE < can_id <= EMCY_BASE + 0x7F:
        return 8, 8
    if SDO_TX_BASE < can_id <= SDO_TX_BASE + 0x7F:
        return 8, 8
    if HEARTBEAT_BASE < can_id <= HEARTBEAT_BASE + 0x7F:
        return 1, 1
    return None


def frame_kind(can_id: int) -> str:
    """The CiA 301 service a COB-ID belongs to (predefined connection set), for counts and logs."""
    if can_id == NMT_COB_ID:
        return "nmt"
    if can_id == SYNC_COB_ID:
        return "sync"
    function = can_id & 0x780
    return {0x080: "emcy", 0x180: "tpdo", 0x280: "tpdo", 0x380: "tpdo", 0x480: "tpdo", 0x200: "rpdo",
            0x300: "rpdo", 0x400: "rpdo", 0x500: "rpdo", 0x580: "sdo", 0x600: "sdo", 0x700: "heartbeat"
            }.get(function, "other")


class FrameGuard:
    """The checks and counts of one master network."""

    def __init__(self) -> None:
        #: rejected frames by (kind, node id); node 0 for NMT and SYNC
        self.rejected: Counter[tuple[str, int]] = Counter()
        self._bounds: dict[int, tuple[int, int] | None] = {}  # per COB-ID, computed once
        self._logged: dict[str, tuple[float, int]] = {}  # kind -> (last log time, total then)
        self._kind_total: Counter[str] = Counter()

    def accept(self, can_id: int, data: bytes, remote: bool = False) -> bool:
        """True if the frame may be dispatched; otherwise it is counted and logged (rate-limited)."""
        if remote:
            self.reject(can_id, f"remote frame (RTR, {len(data)} bytes requested)", "rtr")
            return False
        try:
            bounds = self._bounds[can_id]
        except KeyError:
            bounds = self._bounds[can_id] = expected_length(can_id)
        if bounds is not None and not bounds[0] <= len(data) <= bounds[1]:
            want = f"{bounds[0]}" if bounds[0] == bounds[1] else f"{bounds[0]}-{bounds[1]}"
            self.reject(can_id, f"{len(data)} data bytes, CiA 301 says {want}")
            return False
        return True

    def reject(self, can_id: int, why: str, kind: str | None = None) -> None:
        """Count a frame the master did not use and log it (first of its kind, then rate-limited)."""
        kind = kind or f"short-{frame_kind(can_id)}"
        node = can_id & 0x7F if can_id not in (NMT_COB_ID, SYNC_COB_ID) else 0
        self.rejected[(kind, node)] += 1
        self._kind_total[kind] += 1
        total = self._kind_total[kind]
        now = time.monotonic()
        last = self._logged.get(kind)
        if last is None or now - last[0] >= LOG_INTERVAL_S:
            since = "" if last is None else f" ({total - last[1]} more of this kind since the last report)"
            log.warning("malformed frame dropped: 0x%03X (%s): %s%s", can_id, kind, why, since)
            self._logged[kind] = (now, total)

    def count(self, node_id: int | None = None) -> int:
        """Frames rejected in total, or those of one node (its EMCY, TPDOs, SDO answers, heartbeat)."""
        if node_id is None:
            return sum(self.rejected.values())
        return sum(n for (_kind, node), n in self.rejected.items() if node == node_id)

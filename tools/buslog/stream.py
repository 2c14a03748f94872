"""One pass over a log for one node: chunks of frames, the rare frames in order, the PDOs by the mapping in force.

The cyclic frames (SYNC, PDOs) are the bulk of a log and are left to numpy; the rare ones (NMT, heartbeat,
EMCY, the node's SDO) are walked one by one in log order, and the node's confirmed SDO writes are replayed into
its :class:`~drivectl.tools.buslog.mapping.NodeMapping`. Each chunk comes back cut into segments between the
writes that changed the mapping, each segment with the PDOs in force over it, so a frame is decoded by the
mapping the drive had when it was sent.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivectl.driver import cia402
from drivectl.driver.cia301 import HEARTBEAT_BASE, NMT_COB_ID, SDO_RX_BASE, SDO_TX_BASE, SYNC_COB_ID
from drivectl.tools.buslog.frames import Frames, Reading, read_frames
from drivectl.tools.buslog.mapping import ActivePdo, NodeMapping
from drivectl.tools.buslog.sdo import SdoTracker, Transfer

#: what a rare frame is: (time, COB-ID, data, the SDO transfer it completed or None)
Event = tuple[float, int, bytes, Transfer | None]


@dataclass
class Walk:
    """The state one pass keeps: the mapping, the cycle period the log wrote, the rare frames' handler."""

    node: int
    mapping: NodeMapping
    on_event: Callable[[float, int, bytes, Transfer | None], None] | None = None
    period_us: int | None = None  # 0x1006 as the log wrote it (confirmed)

    def __post_init__(self) -> None:
        self.sdo = SdoTracker()

    def chunks(self, log: Path, reading: Reading, *, fast: bool | None = None, progress: bool = False,
               ) -> Iterator[tuple[Frames, list[tuple[int, int, list[ActivePdo]]]]]:
        node = self.node
        rx_cob, tx_cob = SDO_RX_BASE + node, SDO_TX_BASE + node
        for fr in read_frames(log, reading, fast=fast, progress=progress):
            cob = fr.cob
            rare = (cob == NMT_COB_ID) | ((cob > SYNC_COB_ID) & (cob <= SYNC_COB_ID + 127)) | (cob == rx_cob) | \
                (cob == tx_cob) | ((cob >= HEARTBEAT_BASE) & (cob <= HEARTBEAT_BASE + 127))
            cuts = [0]
            pdos = [self.mapping.active()]
            for i in np.flatnonzero(rare).tolist():
                c = int(cob[i])
                data = fr.data[i, : fr.dlc[i]].tobytes()
                done = None
                if c in (rx_cob, tx_cob):
                    done = self.sdo.feed(float(fr.t[i]), c == rx_cob, fr.data[i].tobytes() if fr.dlc[i] == 8 else data)
                    if done is not None and done.kind == "write":
                        if done.index == cia402.COMM_CYCLE_PERIOD and done.sub == 0:
                            self.period_us = int.from_bytes(done.value[:4], "little")
                        if self.mapping.write(done.index, done.sub, done.value):
                            cuts.append(i + 1)
                            pdos.append(self.mapping.active())
                if self.on_event is not None:
                    self.on_event(float(fr.t[i]), c, data, done)
            cuts.append(len(fr))
            yield fr, [(cuts[k], cuts[k + 1], pdos[k]) for k in range(len(pdos)) if cuts[k + 1] > cuts[k]]


class Jitter:
    """Streaming statistics of the SYNC intervals against the nominal period (bounded memory: sums and a
    histogram of the deviation in microseconds)."""

    BINS_US = np.concatenate([[0], np.logspace(-1, 6, 141)])

    def __init__(self) -> None:
        self.n = 0
        self.sum = self.sumsq = 0.0
        self.min, self.max = math.inf, -math.inf
        self.hist = np.zeros(len(self.BINS_US), np.int64)
        self.last: float | None = None
        self.nominal = 0.0
        self._intervals: list[np.ndarray] = []

    def add(self, stamps: np.ndarray, nominal: float) -> None:
        """The SYNC stamps of one chunk; ``nominal``: the period in force (the histogram's reference)."""
        self.nominal = nominal
        if not len(stamps):
            return
        s = stamps if self.last is None else np.concatenate([[self.last], stamps])
        self.last = float(stamps[-1])
        d = np.diff(s)
        if not len(d):
            return
        self.n += len(d)
        self.sum += float(d.sum())
        self.sumsq += float((d * d).sum())
        self.min, self.max = min(self.min, float(d.min())), max(self.max, float(d.max()))
        self._intervals.append(d)
        if sum(len(x) for x in self._intervals) > 1 << 16:
            self._flush()

    def _flush(self, nominal: float | None = None) -> None:
        if not self._intervals:
            return
        d = np.concatenate(self._intervals)
        self._intervals = []
        ref = self.nominal if nominal is None else nominal
        dev = np.abs(d - ref) * 1e6
        self.hist += np.bincount(np.searchsorted(self.BINS_US, dev), minlength=len(self.BINS_US) + 1)[
            : len(self.BINS_US)]

    def report(self, nominal: float) -> dict[str, float]:
        """mean/std/min/max of the interval, and the largest and 99th-percentile deviation from ``nominal``
        (the percentile to the histogram's bin, rounded up)."""
        self._flush(nominal)
        if not self.n:
            return {}
        mean = self.sum / self.n
        std = math.sqrt(max(self.sumsq / self.n - mean * mean, 0.0))
        cum = np.cumsum(self.hist)
        k = int(np.searchsorted(cum, 0.99 * cum[-1]))
        p99 = float(self.BINS_US[min(k, len(self.BINS_US) - 1)]) * 1e-6
        dev = max(abs(self.max - nominal), abs(self.min - nominal))
        return {"sync_intervals": self.n, "sync_period_mean_s": mean, "sync_period_std_s": std,
                "sync_period_min_s": self.min, "sync_period_max_s": self.max, "frame_jitter_max_s": dev,
                "frame_jitter_p99_s": p99}

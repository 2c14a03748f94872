"""The scope's live data: read out of the loop's ring buffers on the console's side, never in the cycle.

The loop already pushes every cycle's sample of every channel into its axis's ring
(controllers/runtime/capture.py). A :class:`ScopeFeed` remembers the last loop cycle it sent and, each
time the page is updated, copies only the samples that came since, without a lock: it reads the write
index once and stays clear of the sample being written (the newest one is left for the next poll).
The page keeps its window and decimates it per pixel column (min and max: no peak is lost).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from drivectl.controllers.runtime.capture import CHANNELS, COLUMNS

#: samples kept away from the write index and from the wrap (the loop may be writing there)
GUARD = 8


def read_since(ring: Any, last_cycle: int, most: int) -> tuple[np.ndarray, np.ndarray]:
    """The ring's samples after loop cycle ``last_cycle`` (at most ``most``, newest last, the newest
    sample left out): (data rows, cycles)."""
    nxt, count, size = ring.next, ring.count, ring.size
    n = min(count - 1, size - GUARD, most)
    if n <= 0:
        return np.empty((len(CHANNELS), 0)), np.empty(0, dtype=np.int64)
    idx = np.arange(nxt - 1 - n, nxt - 1) % size
    data, cycles = ring.data[:, idx].copy(), ring.slot[idx].copy()
    keep = cycles > last_cycle
    if keep.any():
        first = int(keep.argmax())
        data, cycles = data[:, first:], cycles[first:]
        ok = np.concatenate(([True], np.diff(cycles) > 0))  # a sample overwritten while copying: dropped
        if not ok.all():
            data, cycles = data[:, ok], cycles[ok]
        return data, cycles
    return data[:, :0], cycles[:0]


class ScopeFeed:
    """One page's live scope: which axis and channels, and how far it has been sent."""

    def __init__(self, machine: Any):
        self.m = machine
        self.axis: str | None = None
        self.channels: list[str] = []
        self.window_s = 5.0
        self.last_cycle = -1

    def subscribe(self, axis: str, channels: list[str], window_s: float) -> None:
        if axis not in self.m.loop.axes:
            raise ValueError(f"scope: axis {axis!r}: not on this machine (axes: {', '.join(self.m.loop.axes)})")
        bad = [c for c in channels if c not in CHANNELS]
        if bad:
            raise ValueError(f"scope: channel {bad[0]!r}: expected one of {', '.join(CHANNELS)}")
        ring = self.m.loop.axes[axis].ring
        longest = (ring.size - GUARD) * self.m.loop.dt
        if not 0 < window_s < 1e6:
            raise ValueError(f"scope: window must be > 0 s, got {window_s:g}")
        window_s = min(window_s, longest)  # the ring holds no more (connect(ring_s=...))
        self.axis, self.channels, self.window_s = axis, channels, window_s
        self.last_cycle = -1  # the whole window once, then what comes

    def poll(self) -> dict[str, Any] | None:
        if self.axis is None:
            return None
        loop = self.m.loop
        ring = loop.axes[self.axis].ring
        most = int(round(self.window_s / loop.dt))
        data, cycles = read_since(ring, self.last_cycle, most)
        if not len(cycles):
            return None
        reset = self.last_cycle < 0
        self.last_cycle = int(cycles[-1])
        return {"type": "scope", "axis": self.axis, "reset": reset, "window_s": self.window_s,
                "t": (cycles * loop.dt).tolist(),
                "channels": {c: data[CHANNELS.index(c)].tolist() for c in self.channels}}


def capture_payload(cap: Any) -> dict[str, Any]:
    """A completed capture as the page plots it: time from the trigger, the chosen channels."""
    tr = cap.result()
    cols = {c: np.asarray(tr.columns[COLUMNS[c]]).tolist() for c in cap.channels if COLUMNS[c] in tr.columns}
    from drivectl.tools.ui.console import trigger_text

    return {"type": "capture", "axis": cap.axis, "trigger": trigger_text(cap), "detail": cap.detail,
            "effort_unit": tr.meta.get("effort_unit", ""),
            "t": np.asarray(tr.time).tolist(), "channels": cols}

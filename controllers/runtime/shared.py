"""The loop's state in shared memory: what the user's process reads of a loop that runs in its own process.

One ``multiprocessing.shared_memory`` segment holds, per machine, a status block (the loop's counters and
each axis's state of the last cycle) and every axis's capture ring (capture.Ring's arrays, in place). The
loop's process writes the block at the end of every cycle (:meth:`SharedState.publish`: element writes, no
allocation) under a sequence count; the user's process reads it without a call to the loop's process
(:meth:`SharedView.read`: a copy taken between two equal, even counts). The rings are the loop's own arrays:
a capture still completes in the loop's process, and the scope reads the ring where it is.
"""

from __future__ import annotations

from collections.abc import Sequence
from multiprocessing import resource_tracker, shared_memory
from typing import Any

import numpy as np

from drivectl.controllers.runtime.capture import CHANNELS, Ring
from drivectl.driver.cia402 import PowerState

#: the loop's counters, then per axis its fields (float64 each; codes are indices into the tuples below)
LOOP_FIELDS = ("seq", "cycle", "slot", "slots", "missed", "worst_late", "stalls", "skipped", "gc_runs", "gc_worst",
               "faults", "command_errors")
AXIS_FIELDS = ("state", "power", "position", "velocity", "reference", "following_error", "effort", "clipped",
               "offset", "move", "arrived", "ring_next", "ring_count", "faulted", "moving")
STATES = ("off", "enabling", "servo")
POWERS = tuple(PowerState)
#: the kinds of command a handle names (Move.kind); another kind reads as "command"
KINDS = ("move", "jog", "stop", "run", "home (here)", "home (switch)", "home (hard-stop)")
_L = {f: i for i, f in enumerate(LOOP_FIELDS)}
_A = {f: i for i, f in enumerate(AXIS_FIELDS)}


def layout(names: Sequence[str], ring_size: int) -> dict[str, Any]:
    """Byte offsets of the block and of each axis's ring in the segment (both sides compute the same)."""
    nl, na, nc = len(LOOP_FIELDS), len(AXIS_FIELDS), len(CHANNELS)
    block = 8 * (nl + na * len(names))
    rings = {}
    at = block
    for n in names:
        rings[n] = (at, at + 8 * nc * ring_size)  # data (channels x size float64), then slot (size int64)
        at += 8 * (nc + 1) * ring_size
    return {"names": list(names), "ring_size": ring_size, "block": block, "rings": rings, "size": at}


class _Segment:
    def __init__(self, shm: shared_memory.SharedMemory, lay: dict[str, Any]):
        self.shm = shm
        self.layout = lay
        names = lay["names"]
        n = len(LOOP_FIELDS) + len(AXIS_FIELDS) * len(names)
        self.block = np.ndarray((n,), dtype=np.float64, buffer=shm.buf, offset=0)
        size = lay["ring_size"]
        self.ring_arrays = {}
        for name in names:
            d, s = lay["rings"][name]
            self.ring_arrays[name] = (np.ndarray((len(CHANNELS), size), dtype=np.float64, buffer=shm.buf, offset=d),
                                      np.ndarray((size,), dtype=np.int64, buffer=shm.buf, offset=s))

    def close(self) -> None:
        self.block = self.block.copy()  # the last state stays readable (an axis's power after close, as in-process)
        self.ring_arrays = {}
        try:
            self.shm.close()
        except BufferError:  # a view still held by a reader: the mapping goes with the process
            pass


class SharedState(_Segment):
    """The loop's side: creates the segment, gives the loop its rings, publishes the block every cycle."""

    def __init__(self, names: Sequence[str], ring_size: int):
        lay = layout(names, ring_size)
        super().__init__(shared_memory.SharedMemory(create=True, size=lay["size"]), lay)
        self.block[:] = 0.0
        for data, slot in self.ring_arrays.values():
            data[:] = np.nan
            slot[:] = 0
        self.name = self.shm.name
        self._loop: Any = None
        self._rows: list[tuple[Any, int]] = []

    def ring(self, name: str, size: int) -> Ring:
        """``ServoLoop(ring=...)``: the axis's ring over the segment's arrays."""
        data, slot = self.ring_arrays[name]
        return Ring(size, data, slot)

    def attach(self, loop: Any) -> None:
        """Publish ``loop`` (a ServoLoop built with :meth:`ring`) from now on."""
        nl, na = len(LOOP_FIELDS), len(AXIS_FIELDS)
        self._rows = [(rt, nl + na * i) for i, rt in enumerate(loop.axes[n] for n in self.layout["names"])]
        self._loop = loop
        self._states = {s: STATES.index(s.value) for s in type(loop._rts[0].state)}
        self._powers = {p: i for i, p in enumerate(POWERS)}
        self._kinds = {k: i for i, k in enumerate(KINDS)}
        self.publish()

    def publish(self) -> None:
        """The block, as of this cycle (the per-cycle path: element writes under the sequence count)."""
        loop, b = self._loop, self.block
        if loop is None:
            return
        seq = b[0] + 1.0
        b[0] = seq  # odd: being written
        b[1] = loop.cycle
        b[2] = loop.slot
        b[3] = loop.slots
        b[4] = loop.missed
        b[5] = loop.worst_late
        b[6] = loop.stalls
        b[7] = loop.skipped
        b[8] = loop.gc_runs
        b[9] = loop.gc_worst
        b[10] = len(loop.faults)
        b[11] = len(loop.command_errors)
        states, powers, kinds = self._states, self._powers, self._kinds
        for rt, i in self._rows:
            ax = rt.ch.axis
            b[i] = states[rt.state]
            b[i + 1] = powers.get(ax.power, -1)
            b[i + 2] = rt.position
            b[i + 3] = rt.velocity
            b[i + 4] = rt.reference
            b[i + 5] = rt.following_error
            b[i + 6] = rt.effort
            b[i + 7] = rt.ch.clipped
            b[i + 8] = rt.offset
            h = rt.handle
            b[i + 9] = -1 if h is None else kinds.get(h.kind, len(KINDS))
            b[i + 10] = rt.traj.arrived
            b[i + 11] = rt.ring.next
            b[i + 12] = rt.ring.count
            b[i + 13] = rt.fault is not None
            b[i + 14] = rt.run is not None or rt.traj._moving
        b[0] = seq + 1.0  # even: complete

    def unlink(self) -> None:
        self._loop = None
        try:
            self.shm.unlink()
        except FileNotFoundError:
            pass
        self.close()


class SharedView(_Segment):
    """The user's side: the segment attached by name, read without calling the loop's process."""

    def __init__(self, name: str, lay: dict[str, Any]):
        shm = shared_memory.SharedMemory(name=name)
        # Python 3.11 registers an attached segment with this process's resource tracker too, which would
        # unlink it when this process ends (and warn): the loop's process owns it
        try:
            resource_tracker.unregister(shm._name, "shared_memory")  # type: ignore[attr-defined]
        except Exception:  # noqa: BLE001 - no tracker running: nothing to undo
            pass
        super().__init__(shm, lay)
        self.names = lay["names"]

    def read(self) -> np.ndarray:
        """A consistent copy of the block (the loop never holds it odd for longer than its writes)."""
        b = self.block
        for _ in range(10_000):
            s0 = b[0]
            out = b.copy()
            if s0 == b[0] and int(s0) % 2 == 0:
                return out
        return out  # the loop's process is stopped mid-write (SIGSTOP): the last copy, as it stands

    def loop_field(self, blk: np.ndarray, name: str) -> float:
        return float(blk[_L[name]])

    def axis_row(self, blk: np.ndarray, name: str) -> dict[str, float]:
        i = len(LOOP_FIELDS) + len(AXIS_FIELDS) * self.names.index(name)
        return dict(zip(AXIS_FIELDS, blk[i:i + len(AXIS_FIELDS)].tolist(), strict=True))

    def axis_value(self, name: str, field: str) -> float:
        blk = self.read()
        return float(blk[len(LOOP_FIELDS) + len(AXIS_FIELDS) * self.names.index(name) + _A[field]])


def decode_axis(row: dict[str, float]) -> dict[str, Any]:
    """An axis's row as ``ServoLoop.status()`` names it (the fields that live in the block)."""
    move = int(row["move"])
    power = int(row["power"])
    return {"state": STATES[int(row["state"])], "power": POWERS[power].value if power >= 0 else "unknown",
            "position_m": row["position"], "velocity_m_s": row["velocity"], "reference_m": row["reference"],
            "following_error_m": row["following_error"], "effort": row["effort"],
            "clipped_cycles": int(row["clipped"]), "home_offset_m": row["offset"],
            "move": None if move < 0 else (KINDS[move] if move < len(KINDS) else "command")}

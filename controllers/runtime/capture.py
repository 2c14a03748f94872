"""Capture, as a scope does it: an always-running ring buffer per axis and triggered windows out of it.

The resident loop pushes one sample of every channel into its axis's :class:`Ring` every cycle
(preallocated numpy rows written element by element: nothing is allocated in the cycle). A
:class:`Capture` is armed with a :class:`Trigger` and a number of pre- and post-trigger samples; the
loop checks the trigger each cycle and, once the post-trigger samples are in, copies the window out
of the ring (the one allocation, at completion). The result is a trace v1 (tracefile/format.py; the
required columns plus the chosen channels) and its plot.

Channels: ``reference`` (m), ``position`` (m), ``following_error`` (m, reference - position),
``effort`` (the command, effort unit), ``velocity`` (m/s, 0x606C), ``torque`` (actual, 0x6077, effort
unit) and ``statusword`` (0x6041).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivectl.errors import InputError
from drivectl.tracefile.format import Trace

CHANNELS = ("reference", "position", "following_error", "effort", "velocity", "torque", "statusword")
#: channel -> trace column
COLUMNS = {"reference": "ref_m", "position": "pos_m", "following_error": "following_error_m", "effort": "effort",
           "velocity": "vel_m_s", "torque": "torque_actual", "statusword": "statusword"}
TRIGGERS = ("now", "move", "fault", "level")


class CaptureError(InputError):
    """A capture was asked for something it cannot do; one line naming the argument."""


@dataclass(frozen=True)
class Trigger:
    """What starts the post-trigger part of a capture.

    ``now``: at once; ``move``: the next move's first cycle on this axis (move, jog, home, run);
    ``fault``: a fault on any axis (time 0 is the last sample before the detection; the post-trigger
    samples are the stop's own cycles and what followed); ``level``: ``channel`` crossing ``level`` in
    ``direction`` (rising, falling, either)."""

    kind: str = "now"
    channel: str = "position"
    level: float = 0.0
    direction: str = "rising"

    def __post_init__(self) -> None:
        if self.kind not in TRIGGERS:
            raise CaptureError(f"capture: trigger: expected one of {', '.join(TRIGGERS)}, got {self.kind!r}")
        if self.channel not in CHANNELS:
            raise CaptureError(f"capture: trigger channel: expected one of {', '.join(CHANNELS)}, got "
                               f"{self.channel!r}")
        if self.direction not in ("rising", "falling", "either"):
            raise CaptureError(f"capture: trigger direction: expected rising, falling or either, got "
                               f"{self.direction!r}")
        if not math.isfinite(self.level):
            raise CaptureError(f"capture: trigger level: expected a finite number, got {self.level!r}")

    @classmethod
    def parse(cls, spec: str | Trigger | None) -> Trigger:
        """``"now"``, ``"move"``, ``"fault"`` or ``"CHANNEL>LEVEL"`` / ``"CHANNEL<LEVEL"`` (rising / falling)."""
        if spec is None:
            return cls()
        if isinstance(spec, Trigger):
            return spec
        text = spec.strip()
        for op, direction in ((">", "rising"), ("<", "falling")):
            if op in text:
                channel, _, level = text.partition(op)
                try:
                    value = float(level)
                except ValueError:
                    raise CaptureError(f"capture: trigger {spec!r}: level {level!r} is not a number") from None
                return cls("level", channel.strip(), value, direction)
        return cls(text)


class Ring:
    """The last ``size`` samples of every channel, and the loop slot each stands for.

    A slot is a cycle period of the loop's clock (ServoLoop.slot): on the wall clock a late wake-up skips
    slots, so consecutive samples may be more than one slot apart, and a capture's time, taken from the
    slots, is strictly increasing with the skipped slots as a gap (docs/trace-format.md), never the
    count of cycles run (which lost the skipped time and, after a stop, repeated a number)."""

    def __init__(self, size: int, data: np.ndarray | None = None, slot: np.ndarray | None = None):
        if size < 2:
            raise ValueError(f"capture ring: size must be >= 2, got {size}")
        self.size = size
        # ``data``/``slot``: arrays the ring fills in place (the loop's own process: shared memory, read by
        # the user's process without a copy through a pipe); else its own
        self.data = data if data is not None else np.full((len(CHANNELS), size), np.nan)
        self.slot = slot if slot is not None else np.zeros(size, dtype=np.int64)
        self.rows = [self.data[j] for j in range(len(CHANNELS))]
        self.next = 0  # index the next sample goes to
        self.count = 0  # samples pushed, in all

    def push(self, slot: int, ref: float, pos: float, u: float, vel: float, torque: float, sw: int) -> None:
        """One cycle's sample (the per-cycle path: element writes only)."""
        i = self.next
        r = self.rows
        r[0][i] = ref
        r[1][i] = pos
        r[2][i] = ref - pos
        r[3][i] = u
        r[4][i] = vel
        r[5][i] = torque
        r[6][i] = sw
        self.slot[i] = slot
        self.next = i + 1 if i + 1 < self.size else 0
        self.count += 1

    def latest(self, channel: int) -> float:
        return self.rows[channel][self.next - 1]

    def window(self, samples: int) -> tuple[np.ndarray, np.ndarray]:
        """A copy of the last ``samples`` samples (fewer if fewer were pushed), oldest first, and their slots."""
        n = min(samples, self.count, self.size)
        idx = (np.arange(self.next - n, self.next)) % self.size
        return self.data[:, idx].copy(), self.slot[idx].copy()


class Capture:
    """A capture armed on one axis; ``wait()`` gives its trace once it has triggered and filled."""

    def __init__(self, axis: str, channels: tuple[str, ...], trigger: Trigger, pre: int, post: int,
                 dt: float, meta: dict[str, str]):
        self.axis = axis
        self.channels = channels
        self.trigger = trigger
        self.pre = pre
        self.post = post
        self.dt = dt
        self.meta = meta
        self.state = "armed"  # armed -> triggered -> done (or cancelled)
        self.trigger_slot: int | None = None
        self._prev: float | None = None
        self._done = threading.Event()
        self._data: np.ndarray | None = None
        self._slots: np.ndarray | None = None
        self.trace: Trace | None = None
        self.detail = ""
        #: how waiting lets time pass (the machine's run_until: lockstep runs cycles); None: an Event wait
        self.run_until: Callable[[Callable[[], bool], float | None], bool] | None = None
        #: draw the PNG in a child process (set when a wall-clock loop runs in this process)
        self.plot_apart = False

    @property
    def done(self) -> bool:
        return self._done.is_set()

    # -- called by the loop, in the cycle ------------------------------------------------------------
    def on_cycle(self, ring: Ring, slot: int, move_started: bool) -> bool:
        """After this cycle's sample (at ``slot``) is in the ring; True when the capture completed now."""
        if self.state == "armed":
            t = self.trigger
            kind = t.kind
            hit = False
            if kind == "now" or (kind == "move" and move_started):
                hit = True
            elif kind == "level":
                value = ring.latest(CHANNELS.index(t.channel))
                prev, self._prev = self._prev, value
                if prev is not None:
                    if t.direction != "falling" and prev < t.level <= value:
                        hit = True
                    elif t.direction != "rising" and prev > t.level >= value:
                        hit = True
            if not hit:
                return False
            self.state = "triggered"
            self.trigger_slot = slot
        elif self.state != "triggered":
            return False
        if slot < self.trigger_slot + self.post:  # by slot (time): after a fault the stop's cycles count too
            return False
        self.complete(ring, slot)
        return True

    def fire(self, slot: int, detail: str) -> None:
        """Triggered from outside (a fault) at ``slot``: the post-trigger samples follow in the cycles to come."""
        self.state, self.trigger_slot, self.detail = "triggered", slot, detail

    def complete(self, ring: Ring, slot: int, detail: str = "") -> None:
        """Copy the window out of the ring: the samples of the slots ``pre`` before the trigger to ``slot``
        (pre + 1 + post of them, fewer where a late wake-up skipped slots)."""
        if self.trigger_slot is None:
            self.trigger_slot = slot
        data, slots = ring.window(self.pre + 1 + self.post)
        keep = slots >= self.trigger_slot - self.pre  # by slot: time (a fault's detecting cycle may have no sample)
        self._data, self._slots = data[:, keep], slots[keep]
        self.detail = detail or self.detail
        self.state = "done"
        self._done.set()

    def cancel(self, detail: str) -> None:
        self.detail = detail
        self.state = "cancelled"
        self._done.set()

    # -- the user's side --------------------------------------------------------------------------------
    def wait(self, timeout: float | None = None) -> Trace:
        """The captured trace; TimeoutError when it did not trigger and fill within ``timeout`` s
        (CaptureError when it was cancelled: the machine closed)."""
        waited = self.run_until(self._done.is_set, timeout) if self.run_until else self._done.wait(timeout)
        if not waited:
            what = "filled" if self.state == "triggered" else "triggered"
            within = f"within {timeout:g} s" if timeout is not None else "while waiting"
            raise TimeoutError(f"capture on axis {self.axis}: not {what} {within}")
        return self.result()

    def result(self) -> Trace:
        if self.state == "cancelled":
            raise CaptureError(f"capture on axis {self.axis}: {self.detail}")
        if self.trace is None:
            assert self._data is not None and self._slots is not None
            data, slots = self._data, self._slots
            t = (slots - self.trigger_slot) * self.dt  # skipped slots: a gap in time, as in a run's trace
            cols = {"time_s": t, "ref_m": data[0], "pos_m": data[1], "effort": data[3]}
            for name in self.channels:
                cols.setdefault(COLUMNS[name], data[CHANNELS.index(name)])
            meta = {**self.meta, "capture_trigger": self._trigger_text(), "capture_pre_samples": str(self.pre),
                    "capture_post_samples": str(self.post), "cycles": str(len(t))}
            if self.detail:
                meta["capture_detail"] = self.detail
            self.trace = Trace(cols, meta, source=f"capture {self.axis}")
        return self.trace

    def _trigger_text(self) -> str:
        t = self.trigger
        if t.kind == "level":
            return f"{t.channel} {t.direction} through {t.level:g}"
        return t.kind

    def write(self, path: str | Path, plot: bool = True) -> list[Path]:
        """The trace (format v1) at ``path`` and, with ``plot``, its PNG beside it."""
        from drivectl.tracefile.plot import plot_files_apart, plot_traces

        tr = self.result()
        path = Path(path)
        written = [tr.write(path)]
        if plot and len(tr) > 1:
            title = f"drivectl capture: {self.axis}, trigger {self._trigger_text()}"
            png = path.with_suffix(".png")
            # beside a wall-clock loop the drawing goes to a child process (tracefile/plot.py says why)
            written.append(plot_files_apart({self.axis: written[0]}, png, title) if self.plot_apart
                           else plot_traces({self.axis: tr}, png, title=title))
        return written

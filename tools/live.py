"""The shell's live view: position and following error of every axis while the session runs.

Where a display exists, a matplotlib window in a child process (its drawing never takes the GIL from
the servo loop's thread), fed every 50 ms by a sampler thread; where none does, a status line that
refreshes in place while a command waits; when the output is not a terminal, nothing (a script's
output stays one line per result).
"""

from __future__ import annotations

import math
import multiprocessing as mp
import os
import queue
import threading
from collections import deque
from typing import Any, TextIO

#: samples per second sent to the window; points kept on screen
SAMPLE_HZ = 20
WINDOW_POINTS = 20 * 30


def has_display() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


class QuietView:
    kind = "off (output is not a terminal)"

    def refresh(self) -> None:
        pass

    def close(self) -> None:
        pass


class StatusLine:
    """A line rewritten in place (carriage return) while a command waits."""

    kind = "status line"

    def __init__(self, machine: Any, out: TextIO):
        self.m = machine
        self.out = out
        self._shown = False

    def refresh(self) -> None:
        from drivectl.tools.shell import positions_line

        self.out.write("\r\x1b[2K" + positions_line(self.m))
        self.out.flush()
        self._shown = True

    def clear(self) -> None:
        if self._shown:
            self.out.write("\r\x1b[2K")
            self.out.flush()
            self._shown = False

    def close(self) -> None:
        self.clear()


class WindowView:
    """A matplotlib window in a child process, fed by a sampler thread here."""

    kind = "window"

    def __init__(self, machine: Any):
        self.m = machine
        ctx = mp.get_context("spawn")
        self.q: Any = ctx.Queue(maxsize=1000)
        self.proc = ctx.Process(target=window_main, args=(self.q, list(machine.axes)), daemon=True)
        self.proc.start()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, name="drivectl-live", daemon=True)
        self._thread.start()

    def _sample(self) -> None:
        while not self._stop.wait(1.0 / SAMPLE_HZ):
            if not self.proc.is_alive():
                return  # the window was closed
            t = self.m.loop.cycle * self.m.loop.dt
            row = [(ax.position, ax.following_error) for ax in self.m.axes.values()]
            try:
                self.q.put_nowait((t, row))
            except queue.Full:  # the window is behind: drop, never block the session
                pass

    def refresh(self) -> None:
        pass  # the sampler feeds the window on its own

    def close(self) -> None:
        self._stop.set()
        try:
            self.q.put_nowait(None)
        except queue.Full:
            pass
        self.proc.join(timeout=2.0)
        if self.proc.is_alive():
            self.proc.terminate()


def window_main(q: Any, names: list[str], *, max_frames: int | None = None) -> None:
    """The child: draw what arrives on ``q`` until None arrives or the window is closed."""
    import matplotlib.pyplot as plt

    fig, (ax_pos, ax_err) = plt.subplots(2, 1, sharex=True, figsize=(8, 5))
    fig.canvas.manager.set_window_title("drivectl live") if fig.canvas.manager else None
    t: deque[float] = deque(maxlen=WINDOW_POINTS)
    pos = {n: deque(maxlen=WINDOW_POINTS) for n in names}
    err = {n: deque(maxlen=WINDOW_POINTS) for n in names}
    lp = {n: ax_pos.plot([], [], label=n)[0] for n in names}
    le = {n: ax_err.plot([], [], label=n)[0] for n in names}
    ax_pos.set_ylabel("position, mm")
    ax_err.set_ylabel("following error, um")
    ax_err.set_xlabel("time, s")
    ax_pos.legend(loc="upper left")
    frames = 0
    while plt.fignum_exists(fig.number):
        end = False
        while True:
            try:
                item = q.get_nowait()
            except queue.Empty:
                break
            if item is None:
                end = True
                break
            ts, row = item
            t.append(ts)
            for n, (p, e) in zip(names, row, strict=True):
                pos[n].append(p * 1e3 if math.isfinite(p) else math.nan)
                err[n].append(e * 1e6)
        for n in names:
            lp[n].set_data(t, pos[n])
            le[n].set_data(t, err[n])
        for a in (ax_pos, ax_err):
            a.relim()
            a.autoscale_view()
        plt.pause(0.05)
        frames += 1
        if end or (max_frames is not None and frames >= max_frames):
            break
    plt.close(fig)


def open_live_view(machine: Any, out: TextIO) -> Any:
    """A window where a display exists, a status line on a terminal, else nothing."""
    if has_display():
        try:
            return WindowView(machine)
        except Exception:  # noqa: BLE001 - no GUI backend: fall back to the text line
            pass
    return StatusLine(machine, out) if out.isatty() else QuietView()

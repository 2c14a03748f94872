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
import shutil
import threading
from collections import deque
from typing import Any, TextIO

#: samples per second sent to the window; points kept on screen
SAMPLE_HZ = 20
WINDOW_POINTS = 20 * 30

#: what the live view can show: channel -> (the loop runtime's attribute, scale, unit)
LIVE_CHANNELS = {"position": ("position", 1e3, "mm"), "reference": ("reference", 1e3, "mm"),
                 "following_error": ("following_error", 1e6, "um"), "velocity": ("velocity", 1e3, "mm/s"),
                 "effort": ("effort", 1.0, "effort unit")}
DEFAULT_LIVE = ("position", "following_error")


def parse_channels(text: str | None) -> tuple[str, ...]:
    """``position,effort`` -> the channels; ValueError naming the one not known."""
    if not text:
        return DEFAULT_LIVE
    names = tuple(c for c in text.split(",") if c)
    for c in names:
        if c not in LIVE_CHANNELS:
            raise ValueError(f"live: channel {c!r}: expected one of {', '.join(LIVE_CHANNELS)}")
    return names or DEFAULT_LIVE


def sample(machine: Any, channels: tuple[str, ...]) -> list[list[float]]:
    """Per axis, the chosen channels' values of the last cycle, scaled for display."""
    rows = []
    for rt in machine.loop.axes.values():
        rows.append([getattr(rt, LIVE_CHANNELS[c][0]) * LIVE_CHANNELS[c][1] for c in channels])
    return rows


def has_display() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


class QuietView:
    kind = "none (output is not a terminal)"

    def refresh(self) -> None:
        pass

    def clear(self) -> None:
        pass

    def close(self) -> None:
        pass


class StatusLine:
    """A line rewritten in place (carriage return) while a command waits."""

    kind = "status line"

    def __init__(self, machine: Any, out: TextIO, channels: tuple[str, ...] = DEFAULT_LIVE):
        self.m = machine
        self.out = out
        self.channels = channels
        self._shown = False

    def refresh(self) -> None:
        parts = []
        for name, row in zip(self.m.loop.axes, sample(self.m, self.channels), strict=True):
            vals = " ".join(f"{c} {v:.4g} {LIVE_CHANNELS[c][2]}" for c, v in zip(self.channels, row, strict=True))
            parts.append(f"{name}: {vals}")
        loop = self.m.loop
        if loop.clock == "wall" and loop.latency.n:
            lat = loop.latency
            parts.append(f"late p99.9 {lat.percentile(99.9) * 1e3:.2f} max {lat.max * 1e3:.2f} ms")
        # one row only: a line wider than the terminal wraps, and the carriage return then rewrites only its
        # last row, leaving a trail of old ones (read each time: the window may have been resized)
        width = shutil.get_terminal_size((80, 24)).columns
        text = "  |  ".join(parts)
        if len(text) > width - 1:
            text = text[:max(width - 2, 0)] + "~"
        self.out.write("\r\x1b[2K" + text)
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

    def __init__(self, machine: Any, channels: tuple[str, ...] = DEFAULT_LIVE):
        self.m = machine
        self.channels = channels
        ctx = mp.get_context("spawn")
        self.q: Any = ctx.Queue(maxsize=1000)
        self.proc = ctx.Process(target=window_main, args=(self.q, list(machine.axes), channels), daemon=True)
        self.proc.start()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, name="drivectl-live", daemon=True)
        self._thread.start()

    def _sample(self) -> None:
        while not self._stop.wait(1.0 / SAMPLE_HZ):
            if not self.proc.is_alive():
                return  # the window was closed
            t = self.m.loop.cycle * self.m.loop.dt
            try:
                self.q.put_nowait((t, sample(self.m, self.channels)))
            except queue.Full:  # the window is behind: drop, never block the session
                pass

    def refresh(self) -> None:
        pass  # the sampler feeds the window on its own

    def clear(self) -> None:
        pass  # nothing of it is in the terminal

    def close(self) -> None:
        self._stop.set()
        try:
            self.q.put_nowait(None)
        except queue.Full:
            pass
        self.proc.join(timeout=2.0)
        if self.proc.is_alive():
            self.proc.terminate()


def window_main(q: Any, names: list[str], channels: tuple[str, ...] = DEFAULT_LIVE, *,
                max_frames: int | None = None) -> None:
    """The child: one panel per channel, a line per axis; draw what arrives on ``q`` until None arrives
    or the window is closed."""
    import matplotlib.pyplot as plt

    fig, panels = plt.subplots(len(channels), 1, sharex=True, figsize=(8, 2.5 * len(channels)), squeeze=False)
    panels = [p[0] for p in panels]
    if fig.canvas.manager is not None:
        fig.canvas.manager.set_window_title("drivectl live")
    t: deque[float] = deque(maxlen=WINDOW_POINTS)
    data = {(n, c): deque(maxlen=WINDOW_POINTS) for n in names for c in channels}
    lines = {(n, c): panels[j].plot([], [], label=n)[0] for n in names for j, c in enumerate(channels)}
    for j, c in enumerate(channels):
        panels[j].set_ylabel(f"{c}, {LIVE_CHANNELS[c][2]}")
    panels[-1].set_xlabel("time, s")
    panels[0].legend(loc="upper left")
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
            ts, rows = item
            t.append(ts)
            for n, row in zip(names, rows, strict=True):
                for c, v in zip(channels, row, strict=True):
                    data[(n, c)].append(v if math.isfinite(v) else math.nan)
        for key, line in lines.items():
            line.set_data(t, data[key])
        for p in panels:
            p.relim()
            p.autoscale_view()
        plt.pause(0.05)
        frames += 1
        if end or (max_frames is not None and frames >= max_frames):
            break
    plt.close(fig)


def open_live_view(machine: Any, out: TextIO, channels: tuple[str, ...] = DEFAULT_LIVE) -> Any:
    """A window where a display exists, a status line on a terminal, else nothing."""
    if has_display():
        try:
            return WindowView(machine, channels)
        except Exception:  # noqa: BLE001 - no GUI backend: fall back to the text line
            pass
    return StatusLine(machine, out, channels) if out.isatty() else QuietView()

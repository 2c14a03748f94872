"""The console's side of the session: one :class:`Conductor` thread gives the machine its commands, in
order, and (lockstep clock) lets simulated time pass at the wall clock's pace; :class:`Console` turns
the browser's requests into session calls, validated as the shell validates them.

There is one control path: the web requests end in the same ``AxisControl`` calls as the shell's and
the API's, on the same ``Machine`` and resident loop (session.py). Stop and Stop-all do not queue
behind other commands: ``AxisControl.stop`` only submits to the loop, from any thread, so they are
given at once. Jogs are renewed by the browser while a button is held; the loop's own dead man
(``jog_deadman_s``) stops an axis whose renewals stop coming (a lost connection, a hidden tab), and a
release, a disconnect or a hidden tab also stop it at once (docs/ui.md).
"""

from __future__ import annotations

import collections
import math
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from drivectl.controllers.runtime.capture import CHANNELS, Capture, CaptureError, Trigger
from drivectl.controllers.runtime.homing import HomingError
from drivectl.controllers.runtime.loop import MotionFault
from drivectl.controllers.runtime.servo import LimitError
from drivectl.driver.axis import AxisError
from drivectl.driver.cia402 import PowerState
from drivectl.tools.cli.quantity import QuantityError, parse_quantity

#: the errors that become one visible line in the browser (nothing moved); anything else is a bug
USER_ERRORS = (QuantityError, LimitError, AxisError, MotionFault, CaptureError, HomingError, ValueError,
               TimeoutError)
#: the unit a trigger level is typed in, per channel (the shell's quantities; others plain numbers)
LEVEL_KIND = {"reference": "position", "position": "position", "following_error": "position",
              "velocity": "velocity"}


class Conductor:
    """The one thread that runs the console's commands on the machine, one after another. On the
    lockstep clock it also runs the cycles between commands, paced so that simulated time keeps up
    with the wall clock but never races ahead of it (under load simulated time slows down: nothing is
    late in lockstep, and a jog renewed by the browser's wall-clock timer still arrives in time)."""

    def __init__(self, machine: Any, tick_s: float = 0.01, clock: Callable[[], float] = time.monotonic):
        self.m = machine
        self._clock = clock  # the wall clock simulated time keeps pace with (a test gives its own)
        self.lockstep = machine.clock == "lockstep"
        self.tick_cycles = max(1, int(round(tick_s / machine.loop.dt)))
        self._queue: collections.deque[tuple[Callable[[], Any], Future]] = collections.deque()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._main, name="drivectl-ui-conductor", daemon=True)

    def start(self) -> Conductor:
        self._thread.start()
        return self

    def call(self, fn: Callable[[], Any]) -> Future:
        """Run ``fn`` on the conductor's thread; the future carries its result or its exception."""
        fut: Future = Future()
        self._queue.append((fn, fut))
        self._wake.set()
        return fut

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(timeout)
        while self._queue:
            _fn, fut = self._queue.popleft()
            fut.cancel()

    def _main(self) -> None:
        loop = self.m.loop
        base_t, base_c = self._clock(), loop.cycle
        while not self._stop.is_set():
            while self._queue and not self._stop.is_set():
                fn, fut = self._queue.popleft()
                if fut.set_running_or_notify_cancel():
                    try:
                        fut.set_result(fn())
                    except BaseException as exc:  # noqa: BLE001 - the caller gets it through the future
                        fut.set_exception(exc)
            if not self.lockstep:
                self._wake.wait(0.05)
                self._wake.clear()
                continue
            ahead = (loop.cycle - base_c) * loop.dt - (self._clock() - base_t)
            if ahead > 0:
                self._wake.wait(min(ahead, 0.05))  # bounded: a clock that jumps is seen soon
                self._wake.clear()
                continue
            if ahead < -0.25:  # fell behind (load, a long command): go on from now, never rush to catch up
                base_t, base_c = self._clock(), loop.cycle
            loop.step(self.tick_cycles)


@dataclass
class JogHold:
    """A jog held from one browser: who holds it, its velocity, when it was last renewed."""

    client: str
    velocity: float
    handle: Any
    last_renewal_cycle: int
    press: int | None = None  # the page's number of the button press (None: a client that sends none)


class Console:
    """The browser's view of one connected machine: commands (validated), jogs with a dead man, the
    scope's captures, and a log of how every jog ended (for the person, and for the tests)."""

    def __init__(self, machine: Any, out: Path, *, tick_s: float = 0.01, health_store: Path | None = None):
        from drivectl.tools.health.fingerprint import default_machine_name
        from drivectl.tools.health.store import default_store
        from drivectl.tools.ui.health import HealthPanel

        self.m = machine
        self.out = Path(out)
        self.conductor = Conductor(machine, tick_s)
        #: the Health page: --store, else [health] store, else the user's data folder (docs/health.md)
        store = health_store or (Path(machine.config.health_store) if machine.config.health_store else default_store())
        self.health = HealthPanel(self, store, default_machine_name(machine.config))
        self.jogs: dict[str, JogHold] = {}
        self.stopping: list[dict[str, Any]] = []  # jogs that ended and whose standstill is not yet seen
        self.jog_log: list[dict[str, Any]] = []
        #: (client, axis) -> the last press whose jog ended (a page numbers its presses 1, 2, ...): a renewal
        #: of an ended press (sent before the release, or by a timer that fired late) is ignored, never a
        #: new jog (docs/ui.md)
        self.ended_press: dict[tuple[str, str], int] = {}
        self.capture: Capture | None = None
        self.capture_seq = 0
        self.saved: list[Path] = []
        self.drive_errors: dict[str, str] = {}
        self._reading_error: set[str] = set()
        self._lock = threading.Lock()

    def start(self) -> Console:
        self.conductor.start()
        return self

    def close(self) -> dict[str, str]:
        """Stop the conductor, then disable every axis (verified from the drives) and close the bus."""
        self.conductor.stop()
        return self.m.close()

    # -- validation, as the shell does it -------------------------------------------------------------------
    def axis(self, name: Any) -> Any:
        try:
            return self.m.axes[str(name)]
        except KeyError:
            raise ValueError(f"axis {name!r}: not on this machine (axes: {', '.join(self.m.axes)})") from None

    def speed(self, ax: Any, text: Any, what: str = "speed") -> float | None:
        """An optional speed field: empty means the axis's max_velocity_m_s; else > 0 and within it."""
        if text is None or not str(text).strip():
            return None
        v = parse_quantity(str(text), "velocity", what=what)
        vmax = ax.motion_limits.max_velocity
        if not 0 < v <= vmax:
            raise LimitError(f"axis {ax.name}: {what}: {v * 1e3:g} mm/s is not within (0, {vmax * 1e3:g}] mm/s "
                             f"(max_velocity_m_s of [axes.{ax.name}.motion]); nothing moved")
        return v

    # -- commands ---------------------------------------------------------------------------------------------
    def command(self, client: str, msg: dict[str, Any]) -> str:
        """One request from the browser; returns the line to show. Raises USER_ERRORS for bad input (the
        caller shows it; nothing moved)."""
        op = msg.get("op")
        if op == "stop_all":
            return self.stop_all(client)
        if op == "stop":
            ax = self.axis(msg.get("axis"))
            self._end_jog(ax.name, "stop")
            ax.stop("stopped (console)")
            return f"{ax.name}: stop"
        if op == "jog_release":
            return self.jog_release(client, str(msg.get("axis")), str(msg.get("why") or "release"), msg.get("press"))
        if op == "jog":
            return self.jog(client, msg)
        handler = {"enable": self._enable, "disable": self._disable, "fault_reset": self._fault_reset,
                   "move_to": self._move, "move_by": self._move, "home": self._home,
                   "capture": self._capture, "health_run": self.health.start_run}.get(str(op))
        if handler is None:
            raise ValueError(f"unknown request {op!r}")
        return self.conductor.call(lambda: handler(msg)).result()

    def stop_all(self, client: str = "") -> str:
        """Every axis: a controlled stop, given at once (not queued behind other commands)."""
        for name in list(self.jogs):
            self._end_jog(name, "stop-all")
        stops = self.m.stop_all("Stop-all (console)")
        return f"Stop-all: {len(stops)} enabled ax{'is' if len(stops) == 1 else 'es'} stopping"

    def _enable(self, msg: dict[str, Any]) -> str:
        ax = self.axis(msg.get("axis"))
        ax.enable()
        return f"{ax.name}: {ax.power.value} (the drive reports it), holding {ax.position * 1e3:.4f} mm"

    def _disable(self, msg: dict[str, Any]) -> str:
        ax = self.axis(msg.get("axis"))
        self._end_jog(ax.name, "disable")
        ax.disable()
        return f"{ax.name}: {ax.power.value} (the drive reports it)"

    def _fault_reset(self, msg: dict[str, Any]) -> str:
        ax = self.axis(msg.get("axis"))
        ax.fault_reset()
        self.drive_errors.pop(ax.name, None)
        return f"{ax.name}: {ax.power.value} (fault reset, verified)"

    def _move(self, msg: dict[str, Any]) -> str:
        ax = self.axis(msg.get("axis"))
        by = msg.get("op") == "move_by"
        kind = "distance" if by else "position"
        value = parse_quantity(str(msg.get(kind, "")), "position", what=kind)
        speed = self.speed(ax, msg.get("speed"))
        self._end_jog(ax.name, "move")
        if by:
            ax.move_by(value, speed=speed)
            return f"{ax.name}: move by {value * 1e3:.4f} mm started"
        ax.move_to(value, speed=speed)
        return f"{ax.name}: move to {value * 1e3:.4f} mm started"

    def _home(self, msg: dict[str, Any]) -> str:
        ax = self.axis(msg.get("axis"))
        self._end_jog(ax.name, "home")
        h = ax.home()
        if h.done:  # lockstep: the homing ran to its end here
            h.wait(0)
            return f"{ax.name}: home {h.status}: {h.detail}"
        return f"{ax.name}: homing started"

    # -- jog with a dead man ----------------------------------------------------------------------------------
    def jog(self, client: str, msg: dict[str, Any]) -> str:
        """Start or renew a jog: the browser sends this every JOG_RENEW_MS while the button is held."""
        ax = self.axis(msg.get("axis"))
        direction = msg.get("direction")
        if direction not in (1, -1):
            raise ValueError(f"jog: direction must be 1 or -1, got {direction!r}")
        speed = self.speed(ax, msg.get("speed"), "jog speed")
        v = direction * (speed if speed is not None else ax.motion_limits.max_velocity * 0.1)
        press = press_id(msg.get("press"))
        if press is not None and press <= self.ended_press.get((client, ax.name), 0):
            return ""  # a renewal of a jog that ended (released, stopped): it must not start it again
        held = self.jogs.get(ax.name)
        if held is not None and (held.velocity != v or held.client != client or held.press != press):
            self._end_jog(ax.name, "replaced")
            held = None
        handle = ax.jog(v)  # same v as the jog under way: a renewal (session.py)
        cycle = self.m.loop.slot  # the ring records slots (capture.Ring): the standstill is read there
        if held is None or held.handle is not handle:
            self.jogs[ax.name] = JogHold(client, v, handle, cycle, press)
            return f"{ax.name}: jog {v * 1e3:+g} mm/s (held)"
        held.last_renewal_cycle = cycle
        return ""

    def _press_ended(self, client: str, axis: str, press: int) -> None:
        key = (client, axis)
        self.ended_press[key] = max(press, self.ended_press.get(key, 0))

    def jog_release(self, client: str, axis: str, why: str = "release", press: Any = None) -> str:
        press = press_id(press)
        if press is not None:  # whatever is held: renewals of this press that come later are ignored
            self._press_ended(client, axis, press)
        held = self.jogs.get(axis)
        if held is None or held.client != client:
            return ""
        self._end_jog(axis, why)
        return f"{axis}: jog ended ({why})"

    def client_gone(self, client: str) -> None:
        """A browser's connection closed: its jogs stop now (the loop's dead man would, a moment later)."""
        for name, held in list(self.jogs.items()):
            if held.client == client:
                self._end_jog(name, "connection lost")
        for key in [k for k in self.ended_press if k[0] == client]:
            del self.ended_press[key]

    def _end_jog(self, axis: str, why: str) -> None:
        held = self.jogs.pop(axis, None)
        if held is None:
            return
        if held.press is not None:
            self._press_ended(held.client, axis, held.press)
        ax = self.m.axes[axis]
        stopped_cycle = self.m.loop.cycle
        if not held.handle.done and ax.enabled:
            ax.stop(f"jog ended ({why})")
        self.stopping.append({"axis": axis, "why": why, "velocity_m_s": held.velocity,
                              "last_renewal_cycle": held.last_renewal_cycle, "stop_cycle": stopped_cycle})

    def watch(self) -> None:
        """Called by the status stream (not in the cycle): a jog whose renewals stopped is ended by the
        loop's dead man; a jog that ended is logged with the cycle its reference came to rest."""
        for name, held in list(self.jogs.items()):
            if held.handle.done:
                self.jogs.pop(name, None)
                self.stopping.append({"axis": name, "why": "dead man (renewals stopped)",
                                      "velocity_m_s": held.velocity, "last_renewal_cycle": held.last_renewal_cycle,
                                      "stop_cycle": None})
        loop = self.m.loop
        for ev in list(self.stopping):
            rt = loop.axes[ev["axis"]]
            if rt.handle is not None and rt.handle.kind == "jog" and not rt.handle.done:
                continue
            if not (rt.traj.arrived or rt.state.value != "servo"):
                continue
            self.stopping.remove(ev)
            rest = standstill_cycle(rt.ring, ev["last_renewal_cycle"])
            dt = loop.dt
            ev["standstill_cycle"] = rest
            ev["standstill_after_renewal_s"] = None if rest is None else (rest - ev["last_renewal_cycle"]) * dt
            stop = ev["stop_cycle"]  # an explicit end (release, stop, ...): how far and long its stop took
            after = None if rest is None or stop is None else travel_between(rt.ring, stop, rest)
            ev["standstill_after_stop_s"] = None if after is None else (rest - stop) * dt
            ev["travel_after_stop_m"] = after
            ev["deadman_s"] = rt.motion.jog_deadman
            self.jog_log.append(ev)
        self.health.watch()
        for name, ax in self.m.axes.items():  # a drive in Fault: its 0x603F, read once per fault
            if ax.power in (PowerState.FAULT, PowerState.FAULT_REACTION_ACTIVE):
                if name not in self.drive_errors and name not in self._reading_error:
                    self._reading_error.add(name)
                    self.conductor.call(lambda ax=ax: self._read_error(ax))
            else:
                self.drive_errors.pop(name, None)

    def _read_error(self, ax: Any) -> None:
        try:
            err = ax.error
            self.drive_errors[ax.name] = f"0x{err[0]:04X}: {err[1]}" if err else "no error code"
        finally:
            self._reading_error.discard(ax.name)

    # -- scope captures -------------------------------------------------------------------------------------------
    def _capture(self, msg: dict[str, Any]) -> str:
        ax = self.axis(msg.get("axis"))
        channels = [str(c) for c in msg.get("channels") or ()]
        if not channels:
            raise CaptureError("capture: choose at least one channel")
        kind = str(msg.get("trigger") or "now")
        if kind not in ("now", "move", "fault", "level"):  # a level comes with its unit, never as "position>0.002"
            raise CaptureError(f"capture: trigger {kind!r}: expected now, move, fault or level")
        pre = parse_quantity(str(msg.get("pre") or "0s"), "time", what="pre")
        post = parse_quantity(str(msg.get("post") or "0s"), "time", what="post")
        if kind == "level":
            channel = str(msg.get("level_channel") or "position")
            if channel not in CHANNELS:
                raise CaptureError(f"capture: trigger channel {channel!r}: expected one of {', '.join(CHANNELS)}")
            text = str(msg.get("level") or "")
            if channel in LEVEL_KIND:
                level = parse_quantity(text, LEVEL_KIND[channel], what="trigger level")
            else:
                try:
                    level = float(text)
                except ValueError:
                    raise CaptureError(f"trigger level: {text!r} is not a number") from None
            direction = str(msg.get("direction") or "rising")
            trigger: str | Trigger = Trigger("level", channel, level, direction)
        else:
            trigger = kind
        if self.capture is not None and not self.capture.done:
            self.capture.cancel("replaced by a new capture")
        self.capture = ax.capture(channels, trigger, pre=pre, post=post)
        self.capture_seq += 1
        return f"{ax.name}: capture armed (trigger {trigger_text(self.capture)}, pre {pre:g} s, post {post:g} s)"

    def save_capture(self) -> list[Path]:
        """The last completed capture as trace v1 + PNG in the output folder."""
        cap = self.capture
        if cap is None or not cap.done:
            raise CaptureError("save: no completed capture (freeze or capture first)")
        stamp = time.strftime("%Y%m%d-%H%M%S")
        with self._lock:
            path = self.out / f"{cap.axis}-scope-{stamp}-{self.capture_seq:02d}.csv"
            written = cap.write(path)
        self.saved.extend(written)
        return written


def travel_between(ring: Any, first: int, last: int) -> float | None:
    """How far the reference went from loop cycle ``first`` to ``last`` (m, signed), read from the ring;
    None when the ring no longer holds both."""
    data, cycles = ring.window(ring.size - 1)
    a, b = data[0][cycles == first], data[0][cycles == last]
    if not len(a) or not len(b):
        return None
    return float(b[0] - a[0])


def press_id(value: Any) -> int | None:
    """A jog's press number as the page sends it (a positive integer), or None when there is none."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"jog: press must be a positive integer, got {value!r}")
    return value


def standstill_cycle(ring: Any, since: int) -> int | None:
    """The first loop cycle at or after ``since`` from which the axis's reference stays where it is
    (the jog's stop complete), read from the ring; None when the ring no longer holds it."""
    data, cycles = ring.window(ring.size - 1)
    keep = cycles >= since
    ref, cyc = data[0][keep], cycles[keep]
    if len(ref) < 2:
        return None
    moving = abs(ref[1:] - ref[:-1]) > 1e-12
    if not moving.any():
        return int(cyc[0])
    last = int(len(moving) - 1 - moving[::-1].argmax())  # the last step at which the reference changed
    return int(cyc[last + 1])


def trigger_text(cap: Capture) -> str:
    """A capture's trigger as the person typed it: a level in its channel's display unit (2 mm, not 0.002)."""
    t = cap.trigger
    if t.kind != "level":
        return t.kind
    kind = LEVEL_KIND.get(t.channel)
    if kind == "position":
        level = f"{t.level * 1e3:g} mm"
    elif kind == "velocity":
        level = f"{t.level * 1e3:g} mm/s"
    elif t.channel in ("effort", "torque"):
        level = f"{t.level:g} {cap.meta.get('effort_unit', '')}".rstrip()
    else:
        level = f"{t.level:g}"
    return f"{t.channel} {t.direction} through {level}"


def finite(value: Any) -> Any:
    """JSON has no NaN or infinity: None in their place, through dicts and lists."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [finite(v) for v in value]
    return value

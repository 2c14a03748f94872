"""Homing: where the axis's coordinates come from, by the method ``[axes.NAME.homing]`` names.

* ``here``: the axis stands at ``position_m`` now ("set here");
* ``switch``: search toward ``direction`` at ``speed_m_s`` until the switch (``switch``: home,
  negative-limit or positive-limit; CiA 402 digital inputs 0x60FD bits 2, 0, 1) is active, then creep
  back at ``creep_m_s`` until it releases: that edge is ``position_m``;
* ``hard-stop``: push toward ``direction`` at ``speed_m_s`` with the effort limited to
  ``hard_stop_effort`` until the following error exceeds ``hard_stop_error_m`` (the axis stopped, the
  reference went on): where it stands is ``position_m``; then back off by ``backoff_m``.

Before homing the soft limits mean nothing (the coordinates are not known yet), so the searches are
bounded by ``max_travel_m`` instead; every move is still a ruckig move of the resident loop, the
following-error window stays armed (widened for the hard stop to twice its detection threshold), and
every fault ends the homing in quick stop like any move. The offset is kept by the session (the
drive's 0x6064 is not changed): it is lost when the machine is closed.

``[axes.NAME.emulator]`` places the emulated drive's switches and mechanical stops (tests, demos).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, replace
from typing import Any

from drivectl.errors import DrivectlError
from drivectl.plant_emulator.brake import BrakeSpec

METHODS = ("here", "switch", "hard-stop")
#: 0x60FD bits (CiA 402): negative limit switch, positive limit switch, home switch
INPUT_BITS = {"negative-limit": 0, "positive-limit": 1, "home": 2}
DIGITAL_INPUTS = 0x60FD


class HomingError(DrivectlError, RuntimeError):
    """Homing could not find its reference (switch not found within max_travel_m, ...)."""


@dataclass(frozen=True)
class HomingConfig:
    method: str = "here"
    position: float = 0.0  # m: the coordinate of the reference point (the switch edge, the stop, here)
    direction: int = -1  # search direction
    speed: float = 0.01  # m/s
    creep: float = 0.001  # m/s, off the switch
    switch: str = "home"
    max_travel: float = 0.5  # m the search may go
    hard_stop_error: float = 0.0005  # m
    hard_stop_effort: float = math.inf  # effort limit while pushing against the stop
    backoff: float = 0.001  # m away from the stop after it was found


HOMING_KEYS = {"method": "method", "position_m": "position", "direction": "direction", "speed_m_s": "speed",
               "creep_m_s": "creep", "switch": "switch", "max_travel_m": "max_travel",
               "hard_stop_error_m": "hard_stop_error", "hard_stop_effort": "hard_stop_effort",
               "backoff_m": "backoff"}


def _positive(src: str, key: str, v: Any, zero: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or v < 0 or (v == 0 and not zero):
        raise ValueError(f"{src}: {key}: expected a number {'>=' if zero else '>'} 0, got {v!r}")
    return float(v)


def parse_homing(src: str, key: str, raw: Any) -> HomingConfig:
    if raw is None:
        return HomingConfig()
    if not isinstance(raw, dict):
        raise ValueError(f"{src}: {key}: expected a table")
    extra = set(raw) - set(HOMING_KEYS)
    if extra:
        raise ValueError(f"{src}: {key}.{sorted(extra)[0]}: unknown key (known: {', '.join(HOMING_KEYS)})")
    out: dict[str, Any] = {}
    for k, v in raw.items():
        field = HOMING_KEYS[k]
        if k == "method":
            if v not in METHODS:
                raise ValueError(f"{src}: {key}.method: expected one of {', '.join(METHODS)}, got {v!r}")
            out[field] = v
        elif k == "direction":
            if v not in ("negative", "positive"):
                raise ValueError(f"{src}: {key}.direction: expected negative or positive, got {v!r}")
            out[field] = -1 if v == "negative" else 1
        elif k == "switch":
            if v not in INPUT_BITS:
                raise ValueError(f"{src}: {key}.switch: expected one of {', '.join(INPUT_BITS)}, got {v!r}")
            out[field] = v
        elif k == "position_m":
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise ValueError(f"{src}: {key}.position_m: expected a number of m, got {v!r}")
            out[field] = float(v)
        else:
            out[field] = _positive(src, f"{key}.{k}", v, zero=k == "backoff_m")
    return HomingConfig(**out)


@dataclass(frozen=True)
class EmulatorIO:
    """Switches and mechanical stops of an emulated drive, in the drive's position (m).

    The home switch is active at and below ``home_switch`` (a cam from there to the negative end);
    the limit switches at and beyond their positions; the hard stops are where the carriage stops."""

    home_switch: float | None = None
    limit_switches: tuple[float, float] | None = None
    hard_stops: tuple[float, float] | None = None
    #: a holding brake (plant_emulator/brake.py), None: the axis has none
    brake: BrakeSpec | None = None

    @property
    def brake_release_ms(self) -> float | None:
        return None if self.brake is None else self.brake.release_ms

    @property
    def brake_engage_ms(self) -> float | None:
        return None if self.brake is None else self.brake.engage_ms

    def inputs(self, position: float) -> int:
        """0x60FD at ``position``: bit 0 negative limit, bit 1 positive limit, bit 2 home."""
        bits = 0
        if self.limit_switches is not None:
            if position <= self.limit_switches[0]:
                bits |= 1
            if position >= self.limit_switches[1]:
                bits |= 2
        if self.home_switch is not None and position <= self.home_switch:
            bits |= 4
        return bits


def parse_emulator_io(src: str, key: str, raw: Any) -> EmulatorIO | None:
    if raw is None:
        return None
    if not isinstance(raw, dict):
        raise ValueError(f"{src}: {key}: expected a table")
    extra = set(raw) - {"home_switch_m", "limit_switches_m", "hard_stops_m", "brake_release_ms", "brake_engage_ms"}
    if extra:
        raise ValueError(f"{src}: {key}.{sorted(extra)[0]}: unknown key (known: home_switch_m, limit_switches_m, "
                         "hard_stops_m, brake_release_ms, brake_engage_ms)")
    out: dict[str, Any] = {}
    home = raw.get("home_switch_m")
    if home is not None:
        if isinstance(home, bool) or not isinstance(home, int | float) or not math.isfinite(home):
            raise ValueError(f"{src}: {key}.home_switch_m: expected a number of m, got {home!r}")
        out["home_switch"] = float(home)
    for k, field in (("limit_switches_m", "limit_switches"), ("hard_stops_m", "hard_stops")):
        v = raw.get(k)
        if v is None:
            continue
        numbers = isinstance(v, list) and len(v) == 2 and all(
            isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x) for x in v)
        if not (numbers and v[0] < v[1]):
            raise ValueError(f"{src}: {key}.{k}: expected [lower, upper] in m (lower < upper), got {v!r}")
        out[field] = (float(v[0]), float(v[1]))
    delays = {k: raw.get(k) for k in ("brake_release_ms", "brake_engage_ms")}
    if any(v is not None for v in delays.values()):
        for k, v in delays.items():
            if isinstance(v, bool) or not isinstance(v, int | float) or not (0 <= v <= 10_000):
                raise ValueError(f"{src}: {key}.{k}: expected a delay in ms (0..10000; a brake needs both delays), "
                                 f"got {v!r}")
        out["brake"] = BrakeSpec(float(delays["brake_release_ms"]), float(delays["brake_engage_ms"]))
    return EmulatorIO(**out)


# -- the procedures ------------------------------------------------------------------------------------------
def read_inputs(machine: Any, axis: Any) -> int:
    """0x60FD of the drive: from the emulated drive model without a bus, else by SDO."""
    return machine._bus(axis._rt.ch.axis.read_digital_inputs)


def home(machine: Any, axis: Any) -> Any:
    """Home ``axis`` (an AxisControl) by its configuration; returns the finished homing's Move handle
    (lockstep: at once; wall clock: the homing runs in a helper thread, the handle ends when it does)."""
    from drivectl.controllers.runtime.handles import Move, MoveStatus

    cfg = machine.config.axis(axis.name).homing or HomingConfig()
    axis._require_enabled("home")
    handle = Move(machine.loop, axis.name, f"home ({cfg.method})", cfg.position)
    handle.status = MoveStatus.MOVING

    def procedure() -> None:
        rt = axis._rt
        try:
            if cfg.method == "here":
                axis.set_position(cfg.position)
                machine.run_until(lambda: True, None)
            elif cfg.method == "switch":
                _home_switch(machine, axis, cfg)
            else:
                _home_hard_stop(machine, axis, cfg)
            handle.settled = True
            handle.finish(MoveStatus.DONE, rt, f"homed by {cfg.method}: offset {rt.offset * 1e3:+.6f} mm")
        except Exception as exc:  # noqa: BLE001 - the handle carries it to whoever waits
            from drivectl.controllers.runtime.handles import MotionFault

            fault = getattr(exc, "fault", None)
            handle.finish(MoveStatus.FAULT, rt, str(exc), fault if fault is not None else None)
            handle.error = exc  # type: ignore[attr-defined]
            if not isinstance(exc, MotionFault | HomingError):
                raise

    if machine.loop.clock == "lockstep":
        procedure()
    else:
        threading.Thread(target=procedure, name=f"drivectl-home-{axis.name}", daemon=True).start()
    return handle


def _with_limits(machine: Any, axis: Any, **changes: Any) -> Any:
    """Swap the axis's limits for the search (restored by the caller); returns the old ones."""
    rt = axis._rt
    old = rt.ch.limits
    done = threading.Event()

    def go() -> None:
        rt.ch.limits = replace(old, **changes)
        done.set()

    machine.loop.submit(go)
    machine.run_until(done.is_set, 5.0)
    return old


def _restore(machine: Any, axis: Any, limits: Any) -> None:
    def go() -> None:
        axis._rt.ch.limits = limits

    machine.loop.submit(go)


def _search(machine: Any, axis: Any, velocity: float, found: Any, travel: float, what: str) -> float:
    """Jog at ``velocity`` (renewed) until ``found()``; returns the position at that cycle."""
    from drivectl.controllers.runtime.handles import MoveStatus

    loop = machine.loop
    start = axis.position
    rt = axis._rt
    # the jog's own target: max_travel away (no soft limits while the coordinates are unknown)
    jog = axis.jog(velocity)

    def retarget() -> None:
        if rt.handle is jog:
            rt.traj.move_to(rt.traj.position + math.copysign(travel, velocity), abs(velocity))

    loop.submit(retarget)
    machine.run_until(lambda: jog.status != MoveStatus.PENDING or jog.done, 5.0)  # taken by the loop (wall clock)
    while True:
        if found():
            pos = axis.position
            return pos
        if jog.done or rt.state.value != "servo":
            if rt.fault is not None:
                from drivectl.controllers.runtime.handles import MotionFault

                raise MotionFault(f"axis {axis.name}: homing: {rt.fault.detail}", rt.fault)
            raise HomingError(f"axis {axis.name}: homing: {what} not found within {travel * 1e3:g} mm of "
                              f"{start * 1e3:.3f} mm")
        axis.jog(velocity)
        if loop.clock == "lockstep":
            loop.step(1)
        else:
            machine.run_until(lambda: False, loop.dt)


def _home_switch(machine: Any, axis: Any, cfg: HomingConfig) -> None:
    bit = 1 << INPUT_BITS[cfg.switch]
    old = _with_limits(machine, axis, position=None)
    try:
        if not read_inputs(machine, axis) & bit:
            _search(machine, axis, cfg.direction * cfg.speed, lambda: read_inputs(machine, axis) & bit,
                    cfg.max_travel, f"the {cfg.switch} switch")
            axis.stop().wait(5)
        edge = _search(machine, axis, -cfg.direction * cfg.creep, lambda: not read_inputs(machine, axis) & bit,
                       cfg.max_travel, f"the {cfg.switch} switch's edge")
        axis.stop().wait(5)
        axis.set_position(cfg.position + (axis.position - edge))
        machine.run_until(lambda: True, None)
    finally:
        _restore(machine, axis, old)
    axis.move_to(cfg.position).wait(10) if axis.limits.inside(cfg.position) else None


def _home_hard_stop(machine: Any, axis: Any, cfg: HomingConfig) -> None:
    from drivectl.controllers.runtime.handles import MoveStatus

    lim = axis._rt.ch.limits
    window = max(lim.following_error, 2 * cfg.hard_stop_error)
    old = _with_limits(machine, axis, position=None, following_error=window,
                       max_effort=min(lim.max_effort, cfg.hard_stop_effort))
    rt = axis._rt
    try:
        _search(machine, axis, cfg.direction * cfg.speed,
                lambda: abs(rt.following_error) > cfg.hard_stop_error, cfg.max_travel, "the hard stop")
        held = threading.Event()

        def hold() -> None:  # the reference back to where the axis stands: the push ends
            if rt.handle is not None:
                h, rt.handle = rt.handle, None
                h.finish(MoveStatus.STOPPED, rt, "hard stop found")
            rt.jog_until = 0
            rt.traj.hold(rt.position)
            rt.ch.controller.reset()
            held.set()

        machine.loop.submit(hold)
        machine.run_until(held.is_set, 5.0)
        machine.run_until(lambda: False, 0.05)  # let it settle against the stop
        axis.set_position(cfg.position)  # where it stands against the stop
        machine.run_until(lambda: True, None)
    finally:
        _restore(machine, axis, old)
    axis.move_to(cfg.position - cfg.direction * cfg.backoff).wait(10)



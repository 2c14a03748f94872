"""Moves generated on line, one cycle at a time, by ruckig: hold, move to, jog, controlled stop.

The resident loop (:mod:`~drivectl.controllers.runtime.loop`) asks a :class:`Trajectory` for the next
reference every cycle of an enabled axis. Every command starts from the reference's current state
(position, velocity, acceleration), so a move may replace a jog or another move at any cycle without
a step in the reference; ruckig keeps |v|, |a|, |j| within the axis's :class:`MotionLimits` all the way.

* ``hold(p)``: at rest at p (what an enabled axis with nothing to do follows);
* ``move_to(p)``: jerk-limited, time-optimal, to rest at p (position interface);
* ``jog(v, toward)``: a move toward ``toward`` (the soft limit in the jog's direction, less a margin)
  at speed |v|: a jog can never run through a soft limit, it stops in front of it;
* ``stop()``: to rest as fast as the limits allow (velocity interface, target 0).

ruckig recomputes only when its input changes; a steady cycle costs under a microsecond.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import ruckig

from drivectl.controllers.base import Settings, param
from drivectl.profiles.base import Reference


@dataclass(frozen=True)
class MotionLimits(Settings):
    """How an axis may move when drivectl generates the move (``[axes.NAME.motion]``)."""

    where: ClassVar[str] = "motion"

    max_velocity: float = param(0.1, lo=0.0, lo_open=True, unit="m/s")
    max_acceleration: float = param(1.0, lo=0.0, lo_open=True, unit="m/s^2")
    max_jerk: float = param(50.0, lo=0.0, lo_open=True, unit="m/s^3")
    jog_deadman: float = param(0.2, lo=0.0, lo_open=True, unit="s", doc="a jog not renewed within this stops by itself")
    in_position: float = param(1e-6, lo=0.0, lo_open=True, unit="m",
                               doc="a move has settled when |target - position| stays within this ...")
    in_position_time: float = param(0.01, lo=0.0, unit="s", doc="... for this long")
    settle_timeout: float = param(1.0, lo=0.0, unit="s",
                                  doc="after the reference arrived: the move ends unsettled (reported so)")


#: configuration keys of [axes.NAME.motion] -> MotionLimits fields
MOTION_KEYS = {"max_velocity_m_s": "max_velocity", "max_acceleration_m_s2": "max_acceleration",
               "max_jerk_m_s3": "max_jerk", "jog_deadman_s": "jog_deadman", "in_position_m": "in_position",
               "in_position_s": "in_position_time", "settle_timeout_s": "settle_timeout"}


def parse_motion(src: str, key: str, raw: Any) -> MotionLimits:
    """``[axes.NAME.motion]`` of a configuration file; ValueError naming the file and key."""
    if raw is None:
        return MotionLimits()
    if not isinstance(raw, dict):
        raise ValueError(f"{src}: {key}: expected a table")
    extra = set(raw) - set(MOTION_KEYS)
    if extra:
        raise ValueError(f"{src}: {key}.{sorted(extra)[0]}: unknown key (known: {', '.join(MOTION_KEYS)})")
    values = {}
    for k, v in raw.items():
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or v < 0 or (
                v == 0 and MOTION_KEYS[k] not in ("in_position_time", "settle_timeout")):
            raise ValueError(f"{src}: {key}.{k}: expected a number > 0, got {v!r}")
        values[MOTION_KEYS[k]] = float(v)
    return MotionLimits(**values)


class Trajectory:
    """The reference of one axis, generated on line by ruckig at the cycle time ``dt``."""

    def __init__(self, dt: float, limits: MotionLimits):
        self.dt = dt
        self.limits = limits
        self._otg = ruckig.Ruckig(1, dt)
        self._in = ruckig.InputParameter(1)
        self._out = ruckig.OutputParameter(1)
        self._set_limits(limits.max_velocity)
        self.position = 0.0
        self.velocity = 0.0
        self.acceleration = 0.0
        self.target = 0.0
        #: True once the reference is at rest at its target (a hold, or a move or stop that ended)
        self.arrived = True
        self._moving = False

    def _set_limits(self, vmax: float) -> None:
        inp, lim = self._in, self.limits
        inp.max_velocity = [vmax]
        inp.max_acceleration = [lim.max_acceleration]
        inp.max_jerk = [lim.max_jerk]

    def _from_here(self) -> None:
        inp = self._in
        inp.current_position = [self.position]
        inp.current_velocity = [self.velocity]
        inp.current_acceleration = [self.acceleration]

    # -- commands (between two cycles) ----------------------------------------------------------------
    def hold(self, position: float) -> None:
        """At rest at ``position`` (the axis was just enabled there)."""
        self.position, self.velocity, self.acceleration = position, 0.0, 0.0
        self.target = position
        self.arrived = True
        self._moving = False

    def move_to(self, target: float, vmax: float | None = None) -> None:
        """To rest at ``target`` from wherever the reference is now."""
        inp = self._in
        self._from_here()
        inp.control_interface = ruckig.ControlInterface.Position
        inp.target_position = [target]
        inp.target_velocity = [0.0]
        inp.target_acceleration = [0.0]
        self._set_limits(min(vmax, self.limits.max_velocity) if vmax else self.limits.max_velocity)
        self.target = target
        self.arrived = False
        self._moving = True

    def stop(self) -> None:
        """To rest as fast as the limits allow (where it comes to rest is where it then holds)."""
        if not self._moving:
            return
        inp = self._in
        self._from_here()
        inp.control_interface = ruckig.ControlInterface.Velocity
        inp.target_velocity = [0.0]
        inp.target_acceleration = [0.0]
        self.arrived = False

    def release(self) -> None:
        """Drop the ruckig objects (the loop closed); the reference then holds where it is."""
        self._moving = False
        self.arrived = True
        self._otg = self._in = self._out = None

    @property
    def stopping(self) -> bool:
        """A controlled stop is under way."""
        return self._moving and self._in.control_interface == ruckig.ControlInterface.Velocity

    def skip(self, cycles: int) -> None:
        """Advance over ``cycles`` cycles that got none of their own (the wall-clock loop woke late): the
        reference stays on the time the axis lives on, where the drive held the last command meanwhile. A
        reference left behind would find the axis ahead of it by the skipped motion, and the law would brake
        it hard (a soak's following-error fault, docs/timing.md)."""
        for _ in range(cycles):
            if not self._moving:
                return
            self.next()

    # -- one cycle ---------------------------------------------------------------------------------------
    def next(self) -> Reference:
        """The reference of the next cycle."""
        if not self._moving:
            return Reference(self.position)
        out = self._out
        result = self._otg.update(self._in, out)
        if result == ruckig.Result.Working or result == ruckig.Result.Finished:
            a0 = self.acceleration
            self.position = out.new_position[0]
            self.velocity = out.new_velocity[0]
            self.acceleration = out.new_acceleration[0]
            out.pass_to_input(self._in)
            jerk = (self.acceleration - a0) / self.dt
            if result == ruckig.Result.Finished:
                self._moving = False
                self.arrived = True
                if self._in.control_interface == ruckig.ControlInterface.Velocity:
                    self.target = self.position
                self.velocity = self.acceleration = 0.0
                return Reference(self.position)
            return Reference(self.position, self.velocity, self.acceleration, jerk)
        # ruckig refused the input (cannot happen with validated limits): hold where the reference is
        self.hold(self.position)
        return Reference(self.position)


#: the longest move previewed, s (a jog runs toward the soft limit; its dead man stops it long before)
PREVIEW_S = 5.0


class PlannedMove:
    """A move from rest to rest, planned whole by ruckig's offline calculation, as a profile (``sample``
    at any times, holding its ends outside [0, duration]). Bit for bit what the loop's :class:`Trajectory`
    outputs cycle by cycle for the same input (tests/test_standstill.py), so a controller's preview of it
    (controllers/base.py ``preview``) is computed outside the cycle when the command is given, as a run's
    is, and the move runs on the table instead of an extrapolation."""

    def __init__(self, start: float, target: float, limits: MotionLimits, vmax: float | None = None):
        inp = ruckig.InputParameter(1)
        inp.current_position = [start]
        inp.target_position = [target]
        inp.max_velocity = [min(vmax, limits.max_velocity) if vmax else limits.max_velocity]
        inp.max_acceleration = [limits.max_acceleration]
        inp.max_jerk = [limits.max_jerk]
        self.start, self.target = start, target
        self._traj = ruckig.Trajectory(1)
        result = ruckig.Ruckig(1).calculate(inp, self._traj)
        prof = self._traj.profiles[0][0]
        if result not in (ruckig.Result.Working, ruckig.Result.Finished) or prof.brake.duration or prof.accel.duration:
            raise ValueError("ruckig: no single-phase profile for this move")
        self.duration = float(self._traj.duration)
        # the seven phases of constant jerk: their start times and the state at each start, integrated as
        # ruckig integrates them (p0 + t (v0 + t (a0/2 + t j/6))), so a sample is one numpy expression
        self._edges = np.concatenate([[0.0], np.cumsum(prof.t)])
        self._p, self._v, self._a = np.asarray(prof.p), np.asarray(prof.v), np.asarray(prof.a)
        self._j = np.asarray(prof.j)

    def sample(self, t: Any) -> tuple[Any, Any, Any, Any]:
        t = np.clip(np.asarray(t, dtype=float), 0.0, self.duration)
        i = np.clip(np.searchsorted(self._edges, t, side="right") - 1, 0, 6)
        tau = t - self._edges[i]
        j = self._j[i]
        a0, v0 = self._a[i], self._v[i]
        p = self._p[i] + tau * (v0 + tau * (a0 / 2 + tau * j / 6))
        v = v0 + tau * (a0 + tau * j / 2)
        a = a0 + tau * j
        rest = t >= self.duration
        p = np.where(rest, self.target, p)
        zero = np.where(rest, 0.0, 1.0)
        return p, v * zero, a * zero, j * zero * (t > 0.0)

"""Jerk-limited point-to-point move (time-optimal, planned offline by ruckig).

The move starts at rest at ``start`` at time ``t0`` and ends at rest at ``target``; before ``t0`` it
holds ``start``, after the move ``target``. ruckig plans a 7-phase profile (constant jerk in each
phase); we keep each phase's start time and start state (p, v, a) and its jerk, so that ``sample`` is
a vectorised piecewise-cubic evaluation with no per-sample calls into ruckig.
"""

from __future__ import annotations

import math

import numpy as np
import ruckig

from drivectl.profiles.base import ProfileBase, ProfileError, Samples, as_times, require


class PointToPoint(ProfileBase):
    """Rest-to-rest move ``start`` -> ``target`` with |v| <= vmax, |a| <= amax, |j| <= jmax.

    ``duration`` = max(t0 + move time, hold_until): ``hold_until`` (s, absolute) keeps the profile
    holding ``target`` until then, e.g. to give the controller time to settle.
    """

    def __init__(
        self,
        start: float,
        target: float,
        vmax: float,
        amax: float,
        jmax: float,
        t0: float = 0.0,
        hold_until: float | None = None,
        *,
        name: str = "ptp",
    ) -> None:
        self.name = name
        self.start = require(name, "start", start)
        self.target = require(name, "target", target)
        self.vmax = require(name, "vmax", vmax, gt=0)
        self.amax = require(name, "amax", amax, gt=0)
        self.jmax = require(name, "jmax", jmax, gt=0)
        self.t0 = require(name, "t0", t0, ge=0)
        self.hold_until = None if hold_until is None else require(name, "hold_until", hold_until, ge=0)

        traj = _plan(name, self.start, self.target, self.vmax, self.amax, self.jmax)
        prof = traj.profiles[0][0]
        # Starting at rest inside the limits, ruckig needs no brake pre-phase; if it ever did, the
        # 7 phases below would not start at t0 and the evaluation would be wrong.
        if prof.brake.duration != 0.0:
            raise RuntimeError(f"profile {name}: ruckig planned a brake phase from rest; not supported")
        durations = np.asarray(prof.t, dtype=np.float64)
        self.move_time = float(traj.duration)
        self._t_start = np.concatenate(([0.0], np.cumsum(durations)[:-1]))  # phase starts, relative to t0
        self._p = np.asarray(prof.p[:7], dtype=np.float64)
        self._v = np.asarray(prof.v[:7], dtype=np.float64)
        self._a = np.asarray(prof.a[:7], dtype=np.float64)
        self._j = np.asarray(prof.j, dtype=np.float64)
        end = self.t0 + self.move_time
        self.duration = end if self.hold_until is None else max(end, self.hold_until)
        self._verify(traj)

    @property
    def phase_times(self) -> np.ndarray:
        """Absolute start times of the 7 constant-jerk phases, followed by the end of the move."""
        return np.concatenate((self._t_start, [self.move_time])) + self.t0

    def sample(self, t: np.ndarray) -> Samples:
        tau = as_times(t) - self.t0
        # Phase index: the last phase starting at or before tau (side="right" skips zero-length phases).
        k = np.clip(np.searchsorted(self._t_start, tau, side="right") - 1, 0, 6)
        dt = tau - self._t_start[k]
        p0, v0, a0, j = self._p[k], self._v[k], self._a[k], self._j[k]
        pos = p0 + dt * (v0 + dt * (a0 / 2.0 + dt * j / 6.0))
        vel = v0 + dt * (a0 + dt * j / 2.0)
        acc = a0 + dt * j
        jerk = j.copy()
        before = tau < 0.0
        after = tau >= self.move_time
        for arr in (vel, acc, jerk):
            arr[before | after] = 0.0
        pos[before] = self.start
        pos[after] = self.target  # exactly the target, not ruckig's end state (off by an ulp or so)
        return pos, vel, acc, jerk

    def _verify(self, traj: ruckig.Trajectory) -> None:
        # Guard against a change in ruckig's profile representation: our piecewise evaluation must
        # reproduce Trajectory.at_time at every phase midpoint and at the end.
        tau = np.concatenate((self._t_start + np.diff(self.phase_times) / 2.0, [self.move_time]))
        pos, vel, acc, _ = self.sample(tau + self.t0)
        scale = max(abs(self.target - self.start), self.vmax, self.amax, 1.0)
        for i, ti in enumerate(tau):
            rp, rv, ra = (x[0] for x in traj.at_time(float(ti)))
            err = max(abs(pos[i] - rp), abs(vel[i] - rv), abs(acc[i] - ra))
            if err > 1e-9 * scale:
                raise RuntimeError(f"profile {self.name}: evaluation disagrees with ruckig at t={ti:.6f} s")


def _plan(name: str, start: float, target: float, vmax: float, amax: float, jmax: float) -> ruckig.Trajectory:
    otg = ruckig.Ruckig(1)
    inp = ruckig.InputParameter(1)
    inp.current_position = [start]
    inp.current_velocity = [0.0]
    inp.current_acceleration = [0.0]
    inp.target_position = [target]
    inp.target_velocity = [0.0]
    inp.target_acceleration = [0.0]
    inp.max_velocity = [vmax]
    inp.max_acceleration = [amax]
    inp.max_jerk = [jmax]
    traj = ruckig.Trajectory(1)
    try:
        result = otg.calculate(inp, traj)
    except ruckig.RuckigError as exc:  # input it refuses (we validate first, so this is rare)
        reason = str(exc).strip().splitlines()[0].strip().removesuffix(" input:")  # then ruckig dumps its whole input
        raise ProfileError(f"profile {name}: vmax, amax, jmax: ruckig cannot plan {start:g} -> {target:g} m with "
                           f"{vmax:g} m/s, {amax:g} m/s^2, {jmax:g} m/s^3 ({reason})") from exc
    if result != ruckig.Result.Working or not math.isfinite(traj.duration):
        raise ProfileError(f"profile {name}: ruckig could not plan the move ({result})")
    return traj

"""Disturbance observer (DOB) of paper 004 eq (3): velocity observer plus a constant-disturbance state.

The paper prints (garbled)::

    g^ = k_ed (v^ - r')
    v^ = (1/m) (f - g^) + k_ev (v^ - r')

Read as a Luenberger observer of the rigid axis m q'' = f - g with the friction g as an augmented,
slowly varying state (the form of its reference [21], Li et al. 2012), the consistent version is::

    v^' = (f - g^) / m + L1 (q' - v^)        L1 = the paper's k_ev, 1/s
    g^' = L2 (v^ - q')                        L2 = the paper's k_ed, N/m

Choices, each needed to make (3) an observer at all:

* both left-hand sides are rates (the printed ``v^ = ...`` has v^ on both sides; ``g^ = k_ed (...)``
  as an algebraic law would be a proportional term with no memory, unable to hold a constant g);
* the velocity is the measured one, q' (the drive's velocity actual). With the reference r' the
  observer would estimate "force needed to move at r'", which mixes the tracking error into g^;
* the innovation sign of the v^ equation is q' - v^ (the printed v^ - r' makes the estimation error
  grow). With these signs the error dynamics (e_v = q' - v^, e_g = g - g^, g constant) are
  ``e_v' = -L1 e_v - e_g / m``, ``e_g' = L2 e_v``: characteristic ``s^2 + L1 s + L2 / m``, stable for
  any L1, L2 > 0 and independent of the controller (separation);
* the gains. Table 1's values (k_ev = 0.1 "Hz", k_ed = 0.001 N/mm = 1 N/m) have the right units for
  L1 and L2 but put the poles at 0.05 +- 0.09j rad/s on the X axis: a time constant of ~20 s, longer
  than any constant-velocity stroke of the +-0.1 m travel. They cannot be the gains the experiment
  ran. We parametrise the observer by its natural frequency ``w0`` and damping ``zeta``:
  ``L1 = 2 zeta w0``, ``L2 = m w0^2`` (Table 1's values are ``w0 = 0.107 rad/s, zeta = 0.47``);
* the effort. On a cyclic-synchronous-torque drive the setpoint computed at sample k acts from
  t(k+1) to t(k+2) (DESIGN.md, transport rule), so the force that moved the axis between samples
  k-1 and k is the one computed ``delay_cycles + 1`` steps ago. The observer propagates with that
  one; ignoring the delay would break the separation above and bias g^ during accelerations.

Discretisation: a predictor-corrector at the cycle dt (Euler prediction with the acting force, then
the correction by the measured velocity). With ``w0 dt`` below ~0.3 it is indistinguishable from the
continuous observer.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any


class DisturbanceObserver:
    """Estimates the friction g of ``m q'' = f - g`` from the effort and the measured velocity.

    ``step(effort, velocity)`` is called once per cycle, after the sample at ``velocity`` was taken
    and before the new effort is known: ``effort`` is the command computed in the previous cycle
    (the observer itself keeps the transport delay line). Works on floats or numpy arrays.
    """

    def __init__(self, dt: float, mass: Any, w0: Any, zeta: Any = 1.0, delay_cycles: int = 1):
        if not dt > 0:
            raise ValueError(f"DisturbanceObserver: dt: must be > 0, got {dt!r}")
        if delay_cycles < 0 or int(delay_cycles) != delay_cycles:
            msg = f"must be an integer >= 0, got {delay_cycles!r}"
            raise ValueError(f"DisturbanceObserver: delay_cycles: {msg}")
        self.dt = float(dt)
        self.mass = mass
        self.l1 = 2.0 * zeta * w0  # the paper's k_ev, 1/s
        self.l2 = mass * w0 * w0  # the paper's k_ed, N/m
        self.delay_cycles = int(delay_cycles)
        self.reset()

    @classmethod
    def from_gains(cls, dt: float, mass: float, k_ev: float, k_ed: float, delay_cycles: int = 1):
        """The observer with the paper's raw gains L1 = k_ev (1/s) and L2 = k_ed (N/m)."""
        w0 = math.sqrt(k_ed / mass)
        return cls(dt, mass, w0, k_ev / (2.0 * w0), delay_cycles)

    def reset(self, velocity: Any = 0.0, estimate: Any = 0.0) -> None:
        self.v_hat = velocity
        #: the friction estimate g^, in the effort unit (N)
        self.g_hat = estimate
        self._started = False
        # commands of past cycles, newest last; the oldest is the one acting now
        self._pending: deque = deque([0.0] * self.delay_cycles, maxlen=self.delay_cycles + 1)

    def step(self, effort: Any, velocity: Any) -> Any:
        """Advance one cycle; ``effort`` = the command of the previous cycle. Returns g^."""
        pend = self._pending
        pend.append(effort)  # maxlen drops the command that has finished acting
        acting = pend[0]
        if not self._started:
            # the first sample: nothing has acted yet; start the velocity estimate where the axis is
            self._started = True
            self.v_hat = velocity
            return self.g_hat
        dt = self.dt
        v_pred = self.v_hat + dt * (acting - self.g_hat) / self.mass
        innov = velocity - v_pred
        self.v_hat = v_pred + dt * self.l1 * innov
        self.g_hat = self.g_hat - dt * self.l2 * innov
        return self.g_hat

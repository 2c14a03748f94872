"""Time-delay estimation (TDE), paper 000 eqs (3), (4), (18), (19), (21), (22): what SMC, VPRL and
PID-NFTSM share.

The axis is written as ``m~ x2'' + h = u`` (eq 3) with ``h`` everything else (eq 4). TDE takes ``h``
from one cycle ago: ``h^ = u(t - dt) - m~ x2''(t - dt)`` (eq 19), so the law is
``u = m~ u_c + u(t - dt) - m~ x2''(t - dt)`` (eq 22) and uses no model parameter.

Choices the paper leaves open or gets wrong, made here once for all three controllers:

* Eq (21) prints the second difference of ``u``; what eq (19) needs is ``x2''(t - dt)``, so it is the
  second difference of the measured table position: ``(x(t) - 2 x(t - dt) + x(t - 2 dt)) / dt^2``
  (central, hence an estimate at exactly ``t - dt``). ``accel_source = "velocity"`` offers the first
  difference of the measured velocity instead (an estimate at ``t - dt/2``, one half-cycle fresher,
  and on a real drive 0x606C is often better filtered than twice-differenced counts).
* Start-up: eq (21) sets the estimate to 0 for ``t <= T`` with ``T >= 2 dt``; we take ``T = 2 dt``
  and count ``t`` in cycles since ``reset()`` (not from ``feedback.time``, which on a bus does not
  start at 0), so the estimate is 0 on cycles 0, 1 and 2 and the difference is used from cycle 3.
* ``m~`` (``m_tilde``, V s^2/m, the effort is a voltage) is not given in the paper. Its range is
  capped by the 89.2 Hz axial mode of the two-mass plant; each controller's default is the value
  bench/reproduce_000.py justifies.
* The paper mentions "a smaller m~ or an extra low-pass filter" against the noise of eq (21) without
  giving one. ``accel_filter_hz`` is a first-order low-pass on the ``x2''`` estimate only (not on
  ``u(t - dt)``), discretised with the exact pole ``exp(-2 pi f dt)``; 0 switches it off.
* ``u(t - dt)`` is this controller's own previous output (what it commanded, before any clipping by
  the servo loop; the loop's clip is a safety limit, not part of the law), 0 before the first cycle.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from drivectl.controllers.base import SCALAR_OPS, Controller, Settings, choice, param
from drivectl.driver.axis import Feedback
from drivectl.profiles.base import Reference


@dataclass
class TdeSettings(Settings):
    """The TDE part of the settings; controllers inherit and add their gains."""

    m_tilde: Any = param(
        0.06, lo=0.0, lo_open=True, unit="V s^2/m", doc="constant mass estimate m~ of eq (3) (unstated)"
    )
    accel_filter_hz: Any = param(
        0.0, lo=0.0, unit="Hz", doc="first-order low-pass on the x2'' estimate, 0 = off (unstated)"
    )
    accel_source: str = choice(
        "position",
        ("position", "velocity"),
        doc="x2'' from the 2nd difference of position (eq 21 corrected) or the 1st of velocity",
    )


class TdeController(Controller):
    """A controller whose law is ``u = m~ (u_c - x2''(t - dt)) + u(t - dt)`` (eq 22).

    Subclasses compute ``u_c`` in ``step`` and call :meth:`_accel` first and :meth:`_tde` last.
    """

    def reset(self) -> None:
        self._tde_reset()

    def _tde_reset(self) -> None:
        s = self.settings
        if self.ops is SCALAR_OPS:
            # numpy scalars (np.float64, 0-d arrays) would turn the float path into numpy scalar
            # maths: slower, and ScalarOps.sign cannot subtract numpy bools. Same values, as floats.
            for f in dataclasses.fields(s):
                v = getattr(s, f.name)
                if isinstance(v, np.generic | np.ndarray) and np.ndim(v) == 0 and np.issubdtype(
                    np.asarray(v).dtype, np.number
                ):
                    setattr(s, f.name, float(v))
        self._cycle = 0  # cycles since reset: eq (21)'s t in units of dt
        self._u1 = 0.0  # u(t - dt)
        self._x1 = 0.0  # x2(t - dt)
        self._x2 = 0.0  # x2(t - 2 dt)
        self._v1 = 0.0  # x2'(t - dt)
        self._acc = 0.0  # filtered x2''(t - dt) estimate
        self._by_velocity = s.accel_source == "velocity"
        self._inv_dt = 1.0 / self.dt
        self._inv_dt2 = 1.0 / (self.dt * self.dt)
        f = s.accel_filter_hz
        if isinstance(f, np.ndarray):
            self._alpha = np.where(f > 0.0, -np.expm1(-2.0 * math.pi * f * self.dt), 1.0)
        else:
            self._alpha = -math.expm1(-2.0 * math.pi * f * self.dt) if f > 0.0 else 1.0
        self._m = s.m_tilde
        # a batch's feedback arrays may be buffers the caller reuses: keep copies in the history
        self._copy_history = self.ops is not SCALAR_OPS

    def _accel(self, x: Any, v: Any) -> Any:
        """The (filtered) estimate of x2''(t - dt) from this cycle's sample; advances the history."""
        if self._cycle > 2:  # eq (21): 0 for t <= T = 2 dt
            if self._by_velocity:
                raw = (v - self._v1) * self._inv_dt
            else:
                raw = (x - 2.0 * self._x1 + self._x2) * self._inv_dt2
        else:
            raw = 0.0
        self._cycle += 1
        if self._copy_history:
            x = np.array(x, dtype=float)
            v = np.array(v, dtype=float)
        self._x2 = self._x1
        self._x1 = x
        self._v1 = v
        acc = self._acc + self._alpha * (raw - self._acc)
        self._acc = acc
        return acc

    def note_applied(self, effort: Any) -> None:
        # eq (18)'s u(t - dt) is the effort that acted, a learned feedforward included (controllers/base.py);
        # not while eq (21) holds the acceleration at 0 (the first cycles): with no acceleration to balance
        # it, h^ would integrate the addition cycle after cycle
        if self._cycle > 3:
            self._u1 = effort

    def _tde(self, u_c: Any, acc: Any) -> Any:
        """Eq (22): u = m~ u_c + h^, h^ = u(t - dt) - m~ x2''(t - dt) (eqs 18, 19)."""
        u = self._m * (u_c - acc) + self._u1
        self._u1 = u
        return u


class LinearSurfaceTde(TdeController):
    """TDE with the linear surface s = c e + e' (eq 5, e = x_d - x), so that
    ``u_c = x_d'' + c e' + R(s)`` for the reaching law R of the subclass (SMC eq 12, VPRL eq 13):
    the two baselines differ only there."""

    def step(self, reference: Reference, feedback: Feedback) -> Any:
        x = feedback.position
        v = feedback.velocity
        acc = self._accel(x, v)
        c = self.settings.c
        ed = reference.velocity - v
        s = c * (reference.position - x) + ed
        return self._tde(reference.acceleration + c * ed + self._reaching(s), acc)

    def _reaching(self, s: Any) -> Any:
        """-s' of the reaching law: what drives s to 0."""
        raise NotImplementedError

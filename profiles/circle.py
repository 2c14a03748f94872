"""One axis of a circle, paper 004 eq (25): x = 40 cos(pi t / 5) mm, y = 40 sin(pi t / 5) mm.

Radius 0.040 m, angular rate 2 pi / period = pi/5 rad/s (period 10 s), feed R * omega = 25.1 mm/s.
The x axis starts at center + radius (+40 mm), not at 0: the axis must be brought to ``start_position``
before the run. Derivatives are analytic.

The circle is periodic, so after ``duration`` (= revolutions * period) it does NOT hold: it continues
its formula (as it does for t < 0), which is what a servo run longer than the nominal duration wants.

``run_in`` > 0 (s): the path speed is brought from rest to the feed along the same circle by the
cycloidal motion law (angular acceleration w/T (1 - cos(2 pi t/T)): continuous, zero at both ends,
finite jerk), instead of eq (25)'s step to the full feed at t = 0, which no drive follows (y needs
2.46 N s of momentum at once: at a 300 N peak that is ~150 um of following error whatever the law,
docs/precision.md). The ramp covers half its time's worth of angle, so the duration is
``revolutions * period + run_in / 2``; the circle ends at the feed as eq (25) does, and continues its
formula after ``duration`` (it holds its start before 0). ``run_in = 0`` is eq (25) exactly
(bench/reproduce_004.py).
"""

from __future__ import annotations

import math

import numpy as np

from drivectl.profiles.base import ProfileBase, ProfileError, Samples, as_times, require


class Circle(ProfileBase):
    """x = center + R cos(w t + phase) or y = center + R sin(w t + phase), w = 2 pi / period."""

    def __init__(
        self,
        axis: str = "x",
        radius: float = 0.04,
        period: float = 10.0,
        revolutions: float = 1.0,
        center: float = 0.0,
        phase: float = 0.0,
        *,
        run_in: float = 0.0,
        name: str = "circle",
    ) -> None:
        self.name = name
        if axis not in ("x", "y"):
            raise ProfileError(f"profile {name}: axis: a circle needs axis 'x' or 'y', got {axis!r}")
        self.axis = axis
        self.radius = require(name, "radius", radius, gt=0)
        self.period = require(name, "period", period, gt=0)
        self.revolutions = require(name, "revolutions", revolutions, gt=0)
        self.center = require(name, "center", center)
        self.phase = require(name, "phase", phase)
        self.omega = 2.0 * math.pi / self.period
        self.run_in = require(name, "run_in", run_in, ge=0)
        self.duration = self.revolutions * self.period + 0.5 * self.run_in

    def sample(self, t: np.ndarray) -> Samples:
        if self.run_in:
            return self._sample_run_in(as_times(t))
        th = self.omega * as_times(t) + self.phase
        r, w = self.radius, self.omega
        c, s = np.cos(th), np.sin(th)
        if self.axis == "x":
            return self.center + r * c, -r * w * s, -r * w**2 * c, r * w**3 * s
        return self.center + r * s, r * w * c, -r * w**2 * s, -r * w**3 * c

    def _sample_run_in(self, t: np.ndarray) -> Samples:
        """The circle at the angle w g(t) + phase, g the time on the circle (g' from 0 to 1 over ``run_in``)."""
        big_t = self.run_in
        g, g1, g2, g3 = _ramp(np.clip(t, 0.0, big_t), big_t)
        after = t >= big_t
        g = np.where(after, t - 0.5 * big_t, g)
        g1, g2, g3 = np.where(after, 1.0, g1), np.where(after, 0.0, g2), np.where(after, 0.0, g3)
        w, r = self.omega, self.radius
        th = w * g + self.phase
        th1, th2, th3 = w * g1, w * g2, w * g3
        c, s = np.cos(th), np.sin(th)
        if self.axis == "x":
            return (self.center + r * c, -r * s * th1, -r * (s * th2 + c * th1**2),
                    -r * (s * th3 + 3.0 * c * th1 * th2 - s * th1**3))
        return (self.center + r * s, r * c * th1, r * (c * th2 - s * th1**2),
                r * (c * th3 - 3.0 * s * th1 * th2 - c * th1**3))


def _ramp(t: np.ndarray, big_t: float) -> tuple[np.ndarray, ...]:
    """The cycloidal ramp of the time on the circle over [0, T]: g' rises from 0 to 1 with
    g'' = (1 - cos(2 pi t / T)) / T, zero at both ends; g(T) = T / 2. Returns g and its three derivatives."""
    a = 2.0 * math.pi / big_t
    g = t * t / (2.0 * big_t) - (1.0 - np.cos(a * t)) / (a * a * big_t)
    g1 = t / big_t - np.sin(a * t) / (a * big_t)
    g2 = (1.0 - np.cos(a * t)) / big_t
    g3 = a * np.sin(a * t) / big_t
    return g, g1, g2, g3

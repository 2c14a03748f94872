"""One axis of a circle, paper 004 eq (25): x = 40 cos(pi t / 5) mm, y = 40 sin(pi t / 5) mm.

Radius 0.040 m, angular rate 2 pi / period = pi/5 rad/s (period 10 s), feed R * omega = 25.1 mm/s.
The x axis starts at center + radius (+40 mm), not at 0: the axis must be brought to ``start_position``
before the run. Derivatives are analytic.

The circle is periodic, so after ``duration`` (= revolutions * period) it does NOT hold: it continues
its formula (as it does for t < 0), which is what a servo run longer than the nominal duration wants.
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
        self.duration = self.revolutions * self.period

    def sample(self, t: np.ndarray) -> Samples:
        th = self.omega * as_times(t) + self.phase
        r, w = self.radius, self.omega
        c, s = np.cos(th), np.sin(th)
        if self.axis == "x":
            return self.center + r * c, -r * w * s, -r * w**2 * c, r * w**3 * s
        return self.center + r * s, r * w * c, -r * w**2 * s, -r * w**3 * c

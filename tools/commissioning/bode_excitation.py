"""What `drivectl bode` adds to a holding axis: a flat-spectrum multisine on the controller's effort
(:class:`ExcitedController`) and the reference the axis follows meanwhile (:class:`Hold` on a
frictionless model, :class:`BiasRamp` where Coulomb friction would make a hold stick; the why is in
tools/commissioning/bode.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from drivectl.controllers.base import Controller
from drivectl.driver.axis import Feedback
from drivectl.profiles.base import Reference
from drivectl.tools.commissioning.frf import BodeError

#: ... ramped up (and down after the last period) over this long, inside the first, discarded period
BIAS_RAMP_S = 0.5


# --------------------------------------------------------------------------------------------------
# Excitation
# --------------------------------------------------------------------------------------------------


def multisine(n: int, dt: float, fmin: float, fmax: float, amplitude: float) -> tuple[np.ndarray, np.ndarray]:
    """One period (``n`` samples) of a flat-spectrum multisine on every bin in [fmin, fmax], scaled
    to a peak of ``amplitude``; returns (signal, excited frequencies). Schroeder phases keep the
    crest factor low (~1.5-2), so most of the effort budget goes into the lines, not into peaks."""
    df = 1.0 / (n * dt)
    lines = np.arange(math.ceil(fmin / df - 1e-9), math.floor(fmax / df + 1e-9) + 1)
    lines = lines[lines > 0]
    if len(lines) < 3:
        raise BodeError(f"bode: band {fmin:g}-{fmax:g} Hz holds fewer than 3 lines of {df:g} Hz")
    k = np.arange(1, len(lines) + 1)
    phases = -math.pi * k * (k - 1) / len(lines)
    t = np.arange(n) * dt
    x = np.zeros(n)
    for line, ph in zip(lines, phases, strict=True):
        x += np.cos(2 * math.pi * line * df * t + ph)
    x *= amplitude / np.max(np.abs(x))
    return x, lines * df


class ExcitedController(Controller):
    """The axis's controller plus a known signal added to its effort, sample by sample.

    The inner controller does not see the excitation as its own output (TDE controllers take it for a
    disturbance and partly cancel it below their bandwidth); that is what a closed-loop measurement
    is, and why the FRF is estimated against the excitation, not against the effort alone.
    """

    name = "excited"
    SettingsClass = None  # type: ignore[assignment] - a wrapper, it has no settings of its own

    def __init__(self, inner: Controller, excitation: np.ndarray):  # no Controller.__init__: no settings
        self.inner = inner
        self.dt = inner.dt
        self.excitation = np.asarray(excitation, dtype=float)
        self._k = 0

    def reset(self) -> None:
        self.inner.reset()
        self._k = 0

    def prepare(self, profile: Any, times: np.ndarray) -> None:
        self.inner.prepare(profile, times)  # the inner controller's reference preview

    def step(self, reference: Reference, feedback: Feedback) -> float:
        k = self._k
        self._k += 1
        e = float(self.excitation[k]) if k < len(self.excitation) else 0.0
        return self.inner.step(reference, feedback) + e

    def describe(self) -> dict[str, Any]:
        return {**self.inner.describe(), "excitation": "multisine on the effort"}


@dataclass(frozen=True)
class Hold:
    """A profile that holds one position for ``duration`` s (the servo loop's Profile protocol)."""

    position: float
    duration: float
    name: str = "hold"

    @property
    def start_position(self) -> float:
        return self.position

    def at(self, t: float) -> Reference:
        return Reference(self.position)

    def sample(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        t = np.asarray(t, dtype=float)
        z = np.zeros_like(t)
        return z + self.position, z, z.copy(), z.copy()


@dataclass(frozen=True)
class BiasRamp:
    """A constant-velocity reference (the servo loop's Profile protocol): from ``start`` the velocity
    rises to ``velocity`` over ``ramp`` s (raised cosine: finite jerk), stays there until
    ``duration - ramp`` and falls back to 0 at ``duration``; it holds its last position afterwards."""

    start: float
    velocity: float
    duration: float
    ramp: float = BIAS_RAMP_S
    name: str = "constant-velocity bias + multisine"

    @property
    def start_position(self) -> float:
        return self.start

    @property
    def travel(self) -> float:
        """Distance covered, m (signed): the ramps are symmetric, each loses half its time."""
        return self.velocity * (self.duration - self.ramp)

    def at(self, t: float) -> Reference:
        p, v, a, j = self.sample(np.array([float(t)]))
        return Reference(float(p[0]), float(v[0]), float(a[0]), float(j[0]))

    def sample(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        t = np.clip(np.asarray(t, dtype=float), 0.0, self.duration)
        vb, ta, w = self.velocity, self.ramp, math.pi / self.ramp
        td = self.duration - ta  # the deceleration starts here
        up, down = t < ta, t > td
        pos = self.start + vb * (t - 0.5 * ta)  # the cruise: each ramp lags a full-speed start by ta / 2
        vel = np.full_like(t, vb)
        acc = np.zeros_like(t)
        jerk = np.zeros_like(t)
        tu = t[up]
        pos[up] = self.start + vb * (0.5 * tu - np.sin(w * tu) / (2 * w))
        vel[up] = vb * 0.5 * (1 - np.cos(w * tu))
        acc[up] = vb * 0.5 * w * np.sin(w * tu)
        jerk[up] = vb * 0.5 * w * w * np.cos(w * tu)
        s = t[down] - td  # mirror image of the ramp up
        pos[down] = self.start + vb * (td - 0.5 * ta) + vb * (0.5 * s + np.sin(w * s) / (2 * w))
        vel[down] = vb * 0.5 * (1 + np.cos(w * s))
        acc[down] = -vb * 0.5 * w * np.sin(w * s)
        jerk[down] = -vb * 0.5 * w * w * np.cos(w * s)
        return pos, vel, acc, jerk

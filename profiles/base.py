"""The reference an axis should follow: r, r', r'', r''' at any time."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np


@dataclass(slots=True, frozen=True)
class Reference:
    """Desired motion at one instant (SI: m, m/s, m/s^2, m/s^3)."""

    position: float
    velocity: float = 0.0
    acceleration: float = 0.0
    jerk: float = 0.0


@runtime_checkable
class Profile(Protocol):
    """A reference trajectory for one axis.

    ``duration`` is the time the profile covers (it holds its last position afterwards);
    ``sample`` evaluates r, r', r'', r''' at many times at once (the servo loop samples the whole
    run up front so that the per-cycle path does no trajectory maths).
    """

    duration: float

    def at(self, t: float) -> Reference: ...

    def sample(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]: ...

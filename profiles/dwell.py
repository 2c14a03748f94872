"""Stand still at one position for a while (a pause between moves, or a settle time)."""

from __future__ import annotations

import numpy as np

from drivectl.profiles.base import ProfileBase, Samples, as_times, require


class Dwell(ProfileBase):
    """r = position, r' = r'' = r''' = 0, for ``duration`` s (and, like every hold, before and after)."""

    def __init__(self, position: float, duration: float, *, name: str = "dwell") -> None:
        self.name = name
        self.position = require(name, "position", position)
        self.duration = require(name, "duration", duration, ge=0)

    def sample(self, t: np.ndarray) -> Samples:
        tt = as_times(t)
        return np.full(tt.shape, self.position), np.zeros(tt.shape), np.zeros(tt.shape), np.zeros(tt.shape)

"""A learned feedforward added to any controller's effort (iterative learning control).

:class:`LearnedFeedforward` wraps a :class:`~drivectl.controllers.base.Controller` and adds, at cycle k
of a run, the k-th sample of a correction sequence (effort unit) to the inner controller's effort. The
inner controller's ``step`` stays what it was: pure, unaware of the correction (a time-delay estimator
sees the correction as part of the disturbance it estimates; the learning accounts for that because it
learns through the closed loop, see tools/commissioning/learn.py). Past the end of the sequence the correction is 0.

The wrapper keeps the contract of every controller: explicit state (the cycle index), ``reset()``
back to cycle 0, fixed ``dt``, ``describe()`` for the trace metadata (the inner controller's keys plus
``learned``: the correction's origin and size).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from drivectl.controllers.base import Controller
from drivectl.driver.axis import Feedback
from drivectl.profiles.base import Reference


class LearnedFeedforward(Controller):
    """``inner.step(reference, feedback) + correction[k]`` at cycle k (0 past the end)."""

    SettingsClass = None  # type: ignore[assignment] - a wrapper, it has no settings of its own

    def __init__(self, inner: Controller, correction: np.ndarray, *, origin: str = ""):  # no settings to parse
        self.inner = inner
        self.name = inner.name  # type: ignore[misc] - the trace names the controller that closes the loop
        self.dt = inner.dt
        self.correction = [float(c) for c in np.asarray(correction, dtype=float)]  # floats: the scalar path
        self.origin = origin
        self._n = len(self.correction)
        self._k = 0

    def reset(self) -> None:
        self.inner.reset()
        self._k = 0

    def prepare(self, profile: Any, times: np.ndarray) -> None:
        self.inner.prepare(profile, times)  # the inner controller's reference preview (controllers/base.py)

    def preview(self, profile: Any, times: np.ndarray) -> Any:
        return self.inner.preview(profile, times)

    def use_preview(self, preview: Any) -> None:
        self.inner.use_preview(preview)

    def skipped(self, cycles: int) -> None:
        self.inner.skipped(cycles)

    def step(self, reference: Reference, feedback: Feedback) -> float:
        k = self._k
        self._k = k + 1
        u = self.inner.step(reference, feedback)
        if k < self._n:
            u += self.correction[k]
            self.inner.note_applied(u)  # an observer inside must not cancel the correction as a disturbance
        return u

    def describe(self) -> dict[str, Any]:
        c = np.asarray(self.correction)
        size = float(np.sqrt(np.mean(c * c))) if self._n else 0.0
        text = f"{self.origin + ', ' if self.origin else ''}{self._n} samples, rms {size:.4g}"
        return {**self.inner.describe(), "learned": text}

    def __getattr__(self, item: str) -> Any:
        # attributes of the inner controller (a disturbance estimate, the model) stay reachable
        if item == "inner":
            raise AttributeError(item)
        return getattr(self.inner, item)

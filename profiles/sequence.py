"""Profiles played one after another, and the commissioning back-and-forth built from them.

Each segment runs on its own clock (its t = 0 is where it begins in the sequence). Segments must join:
each starts where the previous one ended (within 1e-9 m), otherwise the reference would step and the
axis would be asked for an infinite velocity. Velocity steps are allowed (e.g. a circle starting on
the y axis from a dwell), since paper 004 runs the circle from rest that way.

Before t = 0 the sequence holds its first segment's start; after its ``duration`` the last segment
decides (a point-to-point move or dwell holds, a circle continues).
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from drivectl.profiles.base import (
    Profile,
    ProfileBase,
    ProfileError,
    Samples,
    as_times,
    profile_name,
    require,
)
from drivectl.profiles.dwell import Dwell
from drivectl.profiles.ptp import PointToPoint

CONTINUITY_TOLERANCE = 1e-9  # m


def _position(profile: Profile, t: float) -> float:
    return float(profile.sample(np.array([t]))[0][0])


class Sequence(ProfileBase):
    """``segments`` back to back; ``duration`` is the sum of theirs."""

    def __init__(self, segments: Iterable[Profile], *, name: str = "sequence") -> None:
        self.name = name
        self.segments: tuple[Profile, ...] = tuple(segments)
        if not self.segments:
            raise ProfileError(f"profile {name}: segments: need at least one segment")
        for i, seg in enumerate(self.segments):
            if not isinstance(seg, Profile):
                raise ProfileError(f"profile {name}: segments[{i}]: not a profile, got {type(seg).__name__}")
            require(name, f"segments[{i}].duration", seg.duration, ge=0)
        for i in range(1, len(self.segments)):
            prev, seg = self.segments[i - 1], self.segments[i]
            end, start = _position(prev, prev.duration), _position(seg, 0.0)
            if abs(start - end) > CONTINUITY_TOLERANCE:
                raise ProfileError(
                    f"profile {name}: segments[{i}] ({profile_name(seg)}) starts at {start:.9g} m but "
                    f"segments[{i - 1}] ({profile_name(prev)}) ends at {end:.9g} m"
                )
        durations = np.array([seg.duration for seg in self.segments], dtype=np.float64)
        self.offsets = np.concatenate(([0.0], np.cumsum(durations)[:-1]))  # segment start times
        self.duration = float(durations.sum())

    def sample(self, t: np.ndarray) -> Samples:
        tt = as_times(t)
        flat = tt.ravel()
        # Segment index: the last one starting at or before t (side="right" skips zero-length ones);
        # t < 0 goes to the first segment, t >= duration to the last, so each applies its own hold.
        k = np.clip(np.searchsorted(self.offsets, flat, side="right") - 1, 0, len(self.segments) - 1)
        out = [np.empty_like(flat) for _ in range(4)]
        for i in np.unique(k):
            m = k == i
            parts = self.segments[i].sample(flat[m] - self.offsets[i])
            for o, part in zip(out, parts, strict=True):
                o[m] = part
        pos, vel, acc, jerk = (o.reshape(tt.shape) for o in out)
        return pos, vel, acc, jerk


def back_and_forth(
    start: float = 0.0,
    distance: float = 0.05,
    speeds: Iterable[float] = (0.02, 0.05, 0.1),
    amax: float = 0.5,
    jmax: float = 20.0,
    dwell: float = 0.3,
    repeats: int = 1,
    *,
    name: str = "back-and-forth",
) -> Sequence:
    """Commissioning run: for each speed, a jerk-limited move out by ``distance``, dwell, back, dwell.

    The whole pattern is played ``repeats`` times. With the defaults (50 mm at 20, 50, 100 mm/s,
    0.5 m/s^2, 20 m/s^3, 0.3 s dwells) it takes about 10.6 s and exercises both directions, three
    velocities, and a standstill (friction) after every reversal.
    """
    start = require(name, "start", start)
    distance = require(name, "distance", distance)
    if distance == 0.0:
        raise ProfileError(f"profile {name}: distance: must be non-zero, got {distance!r}")
    speed_list = list(speeds)
    if not speed_list:
        raise ProfileError(f"profile {name}: speeds: need at least one speed")
    for i, v in enumerate(speed_list):
        require(name, f"speeds[{i}]", v, gt=0)
    amax = require(name, "amax", amax, gt=0)
    jmax = require(name, "jmax", jmax, gt=0)
    dwell = require(name, "dwell", dwell, ge=0)
    if isinstance(repeats, bool) or not isinstance(repeats, int) or repeats < 1:
        raise ProfileError(f"profile {name}: repeats: must be an integer >= 1, got {repeats!r}")
    far = start + distance
    segments: list[Profile] = []
    for r in range(repeats):
        for i, v in enumerate(speed_list):
            tag = f"{name}[{r}.{i}]"
            segments += [
                PointToPoint(start, far, v, amax, jmax, name=f"{tag} out"),
                Dwell(far, dwell, name=f"{tag} dwell out"),
                PointToPoint(far, start, v, amax, jmax, name=f"{tag} back"),
                Dwell(start, dwell, name=f"{tag} dwell back"),
            ]
    return Sequence(segments, name=name)

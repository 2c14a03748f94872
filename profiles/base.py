"""The reference an axis should follow: r, r', r'', r''' at any time.

Every profile has a ``duration`` and a ``start_position`` (r at t = 0; the axis must sit there before
anything moves) and can be evaluated at one instant (``at``) or, vectorised, at many (``sample``).
Outside ``[0, duration]`` a profile holds: before t = 0 it holds its start, after ``duration`` its last
position with velocity, acceleration and jerk 0. Periodic profiles (:class:`~drivectl.profiles.circle.Circle`)
are the exception: they just continue their formula, which is what a servo run longer than one
revolution wants.

:func:`check_limits` samples a profile densely and refuses it if it leaves the soft limits or exceeds a
velocity/acceleration bound; it is meant to run before anything moves.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from drivectl.errors import InputError


class ProfileError(InputError):
    """A profile is invalid or violates a limit; the message is one line naming the profile/file and field."""


@dataclass(slots=True, frozen=True)
class Reference:
    """Desired motion at one instant (SI: m, m/s, m/s^2, m/s^3)."""

    position: float
    velocity: float = 0.0
    acceleration: float = 0.0
    jerk: float = 0.0

    def __init__(self, position: float, velocity: float = 0.0, acceleration: float = 0.0, jerk: float = 0.0) -> None:
        # made every cycle: the slots are set through their descriptors, not by name through
        # object.__setattr__ as the generated frozen __init__ does (0.46 us against 0.78)
        _set_position(self, position)
        _set_velocity(self, velocity)
        _set_acceleration(self, acceleration)
        _set_jerk(self, jerk)


_set_position, _set_velocity, _set_acceleration, _set_jerk = (
    Reference.__dict__[k].__set__ for k in ("position", "velocity", "acceleration", "jerk"))


Samples = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


@runtime_checkable
class Profile(Protocol):
    """A reference trajectory for one axis.

    ``duration`` is the time the profile covers (it holds its last position afterwards, except periodic
    profiles, which continue); ``start_position`` is r(0); ``sample`` evaluates r, r', r'', r''' at many
    times at once (the servo loop samples the whole run up front so that the per-cycle path does no
    trajectory maths).
    """

    duration: float

    @property
    def start_position(self) -> float: ...

    def at(self, t: float) -> Reference: ...

    def sample(self, t: np.ndarray) -> Samples: ...


class ProfileBase:
    """Shared plumbing for the built-in profiles: subclasses set ``name``, ``duration``; implement ``sample``.

    ``sample`` accepts any array-like of times (also 0-d) and returns four float arrays of its shape.
    """

    name: str
    duration: float
    #: the file it was loaded from (set by ``load_profile``), named with ``name`` in limit errors
    source: str | None = None

    def sample(self, t: np.ndarray) -> Samples:  # pragma: no cover - abstract
        raise NotImplementedError

    def at(self, t: float) -> Reference:
        p, v, a, j = self.sample(np.array([float(t)]))
        return Reference(float(p[0]), float(v[0]), float(a[0]), float(j[0]))

    @property
    def start_position(self) -> float:
        return self.at(0.0).position

    @property
    def end_position(self) -> float:
        """r(duration): where the profile ends (and holds, unless periodic)."""
        return self.at(self.duration).position

    def __repr__(self) -> str:
        kind = type(self).__name__
        return f"<{kind} {self.name!r}: {self.duration:.6g} s from {self.start_position:.6g} m>"


def as_times(t: np.ndarray | float) -> np.ndarray:
    """Times as a float64 array (a copy is not needed: callers never write into it)."""
    return np.asarray(t, dtype=np.float64)


def require(
    name: str, field: str, value: object, *, gt: float | None = None, ge: float | None = None
) -> float:
    """Check a constructor argument: a finite real number, optionally > gt / >= ge; returns it as float.

    Raises ProfileError("profile NAME: FIELD: must be > 0, got -1") so that a bad argument is named.
    """
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise ProfileError(f"profile {name}: {field}: must be a number, got {value!r}")
    x = float(value)
    if not math.isfinite(x):
        raise ProfileError(f"profile {name}: {field}: must be finite, got {value!r}")
    if gt is not None and not x > gt:
        raise ProfileError(f"profile {name}: {field}: must be > {gt:g}, got {value!r}")
    if ge is not None and not x >= ge:
        raise ProfileError(f"profile {name}: {field}: must be >= {ge:g}, got {value!r}")
    return x


def profile_name(profile: Profile) -> str:
    """The name used in messages; profiles not built here may lack one."""
    return str(getattr(profile, "name", type(profile).__name__))


def profile_label(profile: Profile) -> str:
    """How a message names a profile: its name and, for one read from a file, the file."""
    source = getattr(profile, "source", None)
    return f"{profile_name(profile)} ({source})" if source else profile_name(profile)


# Slack on every limit: profile maths rounds (ruckig's cruise velocity is vmax -+ 1 ulp), and a move
# planned right at a limit must pass.
LIMIT_TOLERANCE = 1e-9


def outside_soft_limits(position: tuple[float, float], values: object, times: object = None) -> str | None:
    """The soft-limit test of every refusal (a profile, a run, a move's target) and its one line.

    ``values``: positions (m; one or many), sampled at ``times`` (s) when given. None when every value
    lies within ``position`` = (lower, upper) give or take :data:`LIMIT_TOLERANCE`; else the first one
    outside, e.g. "position 0.040000 m at t=0.000 s is outside the soft limits [-0.03, 0.03] m" (the
    caller says whose and prefixes it: controllers/runtime/cycle.py ``Limits.refuse_outside``)."""
    p = np.atleast_1d(np.asarray(values, dtype=float))
    i = first_outside(position, p)
    if i is None:
        return None
    at = "" if times is None else f" at t={float(np.atleast_1d(times)[i]):.3f} s"
    return soft_limit_text(float(p[i]), position, at)


def first_outside(position: tuple[float, float], values: np.ndarray) -> int | None:
    """The index of the first of ``values`` outside ``position`` (beyond :data:`LIMIT_TOLERANCE`), or None."""
    bad = (values < position[0] - LIMIT_TOLERANCE) | (values > position[1] + LIMIT_TOLERANCE)
    return int(np.argmax(bad)) if bad.any() else None


def soft_limit_text(value: float, position: tuple[float, float], at: str = "") -> str:
    """The words of a position outside the soft limits (a refusal's, and the cycle's when it stops a run)."""
    return f"position {value:.6f} m{at} is outside the soft limits [{position[0]:g}, {position[1]:g}] m"


def check_limits(
    profile: Profile,
    *,
    position: tuple[float, float] | None = None,
    vmax: float | None = None,
    amax: float | None = None,
    until: float | None = None,
    rate: float = 2000.0,
) -> None:
    """Refuse ``profile`` if it leaves the soft limits or exceeds |v| <= vmax or |a| <= amax.

    The profile is sampled at ``rate`` Hz (at least 1 kHz) from t = 0 to ``until`` (default its
    ``duration``; pass the run length when the servo runs longer, e.g. a circle continuing), endpoints
    included. Raises ProfileError naming the earliest violation and its time, e.g.
    "profile circle: position 0.040000 m at t=0.000 s is outside the soft limits [-0.03, 0.03] m".
    A tolerance of 1e-9 (in the SI unit of each quantity) absorbs rounding.
    """
    name = profile_name(profile)
    shown = profile_label(profile)
    if position is not None:
        if len(position) != 2:
            raise ProfileError(f"profile {name}: position limits: expected (lower, upper), got {position!r}")
        lo, hi = (require(name, "position limits", x) for x in position)
        if not lo < hi:
            raise ProfileError(f"profile {name}: position limits: lower must be below upper, got {position}")
    if vmax is not None:
        require(name, "vmax limit", vmax, gt=0)
    if amax is not None:
        require(name, "amax limit", amax, gt=0)
    require(name, "rate", rate, ge=1000.0)
    span = profile.duration if until is None else require(name, "until", until, ge=0)
    n = max(2, math.ceil(span * rate) + 1)
    t = np.linspace(0.0, span, n)
    pos, vel, acc, _ = profile.sample(t)
    tol = LIMIT_TOLERANCE

    # (index of first violation, message builder); the earliest in time wins, position first on a tie.
    found: list[tuple[int, str]] = []
    if position is not None and (i := first_outside(position, pos)) is not None:
        found.append((i, soft_limit_text(float(pos[i]), position, f" at t={t[i]:.3f} s")))
    if vmax is not None:
        bad = np.abs(vel) > vmax + tol
        if bad.any():
            i = int(np.argmax(bad))
            found.append((i, f"velocity {vel[i]:.4f} m/s at t={t[i]:.3f} s exceeds the limit {vmax:g} m/s"))
    if amax is not None:
        bad = np.abs(acc) > amax + tol
        if bad.any():
            i = int(np.argmax(bad))
            where = f"at t={t[i]:.3f} s exceeds the limit {amax:g} m/s^2"
            found.append((i, f"acceleration {acc[i]:.4f} m/s^2 {where}"))
    if found:
        _, msg = min(found, key=lambda f: f[0])  # stable: position before velocity before acceleration
        raise ProfileError(f"profile {shown}: {msg}")

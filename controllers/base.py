"""What every controller shares: the step contract, validated settings, scalar/array maths.

A controller is a pure function of its explicit state: ``step(reference, feedback) -> effort`` at a
fixed ``dt``, no I/O, ``reset()`` back to the initial state. Settings are dataclasses whose fields
declare their ranges; a bad value raises :class:`SettingsError` with one line naming the source and
the field.

Gains may be numpy arrays of shape (N,) (a batch of N gain sets simulated together, see
``plant_emulator.batch``); controllers then receive array feedback and pick the array maths of
:data:`ARRAY_OPS` instead of the scalar maths of :data:`SCALAR_OPS`, so one implementation of each
control law serves the single run and the batch.
"""

from __future__ import annotations

import dataclasses
import math
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import field
from typing import Any, ClassVar

import numpy as np

from drivectl.driver.axis import Feedback
from drivectl.errors import InputError
from drivectl.profiles.base import Reference


class SettingsError(InputError):
    """A setting is missing, of the wrong type or out of range. The message is one line."""


def param(
    default: Any = dataclasses.MISSING,
    *,
    lo: float | None = None,
    hi: float | None = None,
    lo_open: bool = False,
    hi_open: bool = False,
    unit: str = "",
    doc: str = "",
    finite: bool = True,
) -> Any:
    """A numeric settings field with its admissible range ``lo .. hi`` (open or closed ends); ``finite=False``
    admits +-inf (a limit that is not set), never NaN."""
    meta = {"lo": lo, "hi": hi, "lo_open": lo_open, "hi_open": hi_open, "unit": unit, "doc": doc, "finite": finite}
    return field(default=default, metadata=meta)


def choice(default: Any, options: tuple, *, doc: str = "") -> Any:
    """A settings field that takes one of ``options``."""
    return field(default=default, metadata={"options": options, "doc": doc})


def _range_text(meta: Mapping[str, Any]) -> str:
    lo, hi = meta.get("lo"), meta.get("hi")
    if lo is not None and hi is not None:
        left = "(" if meta["lo_open"] else "["
        right = ")" if meta["hi_open"] else "]"
        return f"in {left}{lo:g}, {hi:g}{right}"
    if lo is not None:
        return f"{'>' if meta['lo_open'] else '>='} {lo:g}"
    if hi is not None:
        return f"{'<' if meta['hi_open'] else '<='} {hi:g}"
    return "a finite number"


class Settings:
    """Base of validated settings (every controller's, the axis's limits): subclasses are dataclasses,
    frozen or not, whose fields declare their ranges; each field is checked against its range."""

    #: the name a bad value is reported under when no source is given
    where: ClassVar[str] = "settings"

    def __post_init__(self) -> None:
        self.validate(self.where)

    def validate(self, source: str = "settings", prefix: str = "") -> None:
        """Raise SettingsError naming ``source`` and ``prefix + field`` for the first bad field."""
        for f in dataclasses.fields(self):
            name = prefix + f.name
            meta = f.metadata
            value = getattr(self, f.name)
            if "options" in meta:
                if value not in meta["options"]:
                    opts = ", ".join(repr(o) for o in meta["options"])
                    raise SettingsError(f"{source}: {name}: must be one of {opts}, got {value!r}")
                continue
            if "lo" not in meta:
                continue
            arr = np.asarray(value) if not isinstance(value, list | tuple | dict) else None  # arrays: numpy only
            if arr is None or arr.dtype == bool or not np.issubdtype(arr.dtype, np.number):
                raise SettingsError(f"{source}: {name}: expected a number, got {value!r}")
            if not np.all(np.isfinite(arr)) and (meta.get("finite", True) or np.any(np.isnan(arr))):
                raise SettingsError(f"{source}: {name}: expected a finite number, got {value!r}")
            lo, hi = meta["lo"], meta["hi"]
            bad = False
            if lo is not None:
                bad |= bool(np.any(arr <= lo) if meta["lo_open"] else np.any(arr < lo))
            if hi is not None:
                bad |= bool(np.any(arr >= hi) if meta["hi_open"] else np.any(arr > hi))
            if bad:
                shown = value if arr.ndim == 0 else f"array with min {arr.min():g}, max {arr.max():g}"
                raise SettingsError(f"{source}: {name}: must be {_range_text(meta)}, got {shown}")

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any], source: str = "settings", prefix: str = "") -> Settings:
        """Build from a TOML table or keyword arguments; unknown keys and bad values are errors."""
        names = {f.name for f in dataclasses.fields(cls)}
        for key in values:
            if key not in names:
                known = ", ".join(sorted(names))
                raise SettingsError(f"{source}: {prefix}{key}: unknown setting (known: {known})")
        obj = cls.__new__(cls)
        for f in dataclasses.fields(cls):
            if f.name in values:
                value = values[f.name]
                if isinstance(value, int) and not isinstance(value, bool) and "lo" in f.metadata:
                    value = float(value)
            elif f.default is not dataclasses.MISSING:
                value = f.default
            elif f.default_factory is not dataclasses.MISSING:
                value = f.default_factory()
            else:
                raise SettingsError(f"{source}: {prefix}{f.name}: missing (required)")
            object.__setattr__(obj, f.name, value)  # frozen subclasses too
        obj.validate(source, prefix)
        return obj

    def as_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


class ScalarOps:
    """Branch and sign maths on Python floats (the single-run path; fast, no numpy scalars)."""

    abs = staticmethod(abs)
    sqrt = staticmethod(math.sqrt)
    exp = staticmethod(math.exp)
    asinh = staticmethod(math.asinh)

    @staticmethod
    def sign(x: float) -> float:
        return float(x > 0.0) - float(x < 0.0)  # float(): numpy scalars (np.bool_) do not subtract

    @staticmethod
    def where(cond: bool, a: float, b: float) -> float:
        return a if cond else b

    @staticmethod
    def clip(x: float, lo: float, hi: float) -> float:
        return lo if x < lo else hi if x > hi else x

    @staticmethod
    def sig(x: float, p: float) -> float:
        """|x|^p sgn(x)."""
        if x > 0.0:
            return x**p
        if x < 0.0:
            return -((-x) ** p)
        return 0.0


class ArrayOps:
    """The same maths on numpy arrays (a batch of gain sets)."""

    abs = staticmethod(np.abs)
    sqrt = staticmethod(np.sqrt)
    exp = staticmethod(np.exp)
    asinh = staticmethod(np.arcsinh)
    sign = staticmethod(np.sign)
    where = staticmethod(np.where)
    clip = staticmethod(np.clip)

    @staticmethod
    def sig(x: np.ndarray, p: Any) -> np.ndarray:
        return np.abs(x) ** p * np.sign(x)


SCALAR_OPS = ScalarOps()
ARRAY_OPS = ArrayOps()


def outside_band(e: float, band: float) -> float:
    """The part of error ``e`` outside the band +-``band`` (0 inside): what a standstill's integral and
    stiffness act on, the error inside being left to the stiction (docs/standstill.md)."""
    return e - band if e > band else e + band if e < -band else 0.0


def ops_for(settings: Settings) -> ScalarOps | ArrayOps:
    """Array maths when any gain is an array (a batch), scalar maths otherwise."""
    for value in settings.as_dict().values():
        if isinstance(value, np.ndarray) and value.ndim > 0:
            return ARRAY_OPS
    return SCALAR_OPS


class Controller(ABC):
    """A position controller closing the loop once per cycle.

    Subclasses set ``name``, ``effort_unit_hint`` and ``SettingsClass``; they keep every piece of
    evolving state in attributes that ``reset()`` restores.
    """

    name: ClassVar[str]
    SettingsClass: ClassVar[type[Settings]]
    #: paper the law comes from, shown in traces and reports
    origin: ClassVar[str] = ""

    def __init__(self, dt: float, settings: Settings | Mapping[str, Any] | None = None, **kwargs: Any):
        if not (isinstance(dt, int | float) and dt > 0 and math.isfinite(dt)):
            raise SettingsError(f"controller {self.name}: dt: must be > 0, got {dt!r}")
        if settings is None:
            settings = self.SettingsClass.from_mapping(kwargs, source=f"controller {self.name}")
        elif isinstance(settings, Mapping):
            settings = self.SettingsClass.from_mapping(
                {**settings, **kwargs}, source=f"controller {self.name}"
            )
        elif kwargs:
            raise SettingsError(f"controller {self.name}: pass settings or keyword arguments, not both")
        self.dt = float(dt)
        self.settings = settings
        self.ops = ops_for(settings)
        self.reset()

    @abstractmethod
    def reset(self) -> None:
        """Return to the initial state (integrators, adaptive gains, delayed samples)."""

    @abstractmethod
    def step(self, reference: Reference, feedback: Feedback) -> float:
        """The effort for this cycle from the reference and the sampled feedback."""

    def prepare(self, profile: Any, times: np.ndarray) -> None:
        """Reference preview: called once before a run, after :meth:`reset`, with the profile and the
        run's cycle times (step k follows ``times[k]``). A controller that plans ahead (a feed-forward
        through a model with a transport delay needs the reference a few cycles early) computes it here;
        the default needs nothing. Callers that cannot give a profile skip it: the controller then works
        from each cycle's Reference alone. It is :meth:`use_preview` of :meth:`preview`: the resident loop
        (session.py) computes the preview outside its cycle and installs it in the cycle the run starts,
        the controller continuing from its hold (controllers/runtime/servo.py ``run_preview``)."""
        self.use_preview(self.preview(profile, times))

    def preview(self, profile: Any, times: np.ndarray) -> Any:
        """What :meth:`prepare` installs, computed from the profile and the run's cycle times alone: it may
        run in another thread while the controller steps (it must not change the controller's state).
        Default: nothing to plan."""
        return None

    def use_preview(self, preview: Any) -> None:  # noqa: B027 - optional hook, no-op by default
        """Install a :meth:`preview`: the next ``step`` is the run's cycle 0. Default: nothing."""

    def linear_form(self) -> Any:
        """The law's linear form about a held reference (controllers/linear_form.py ``LinearForm``: a state
        space from [position, velocity] to the effort), or None: a nonlinear law (sliding mode, time-delay
        estimation) has none, and its measured margins are describing-function estimates. Default: None."""
        return None

    def note_applied(self, effort: Any) -> None:
        """Told, after ``step``, the effort actually applied this cycle when something outside the law added
        to it (a learned feedforward, controllers/learning.py). A law that remembers its own last effort
        (time-delay estimation, a disturbance observer) overrides this to remember the applied one, so
        that it does not take the addition for a disturbance and cancel it. Default: nothing."""
        return None

    def shift(self, delta: float) -> None:  # noqa: B027 - optional hook, no-op by default
        """The axis's coordinates moved: every position reads ``delta`` less from the next cycle on (a home
        offset, session.py ``set_position``). A law that keeps absolute positions in its state (an
        observer's estimate) moves them, or it would see a step of ``delta``. Default: nothing kept."""

    def skipped(self, cycles: int) -> None:  # noqa: B027 - optional hook, no-op by default
        """Told, before ``step``, that ``cycles`` cycles passed since the last step without one (the
        wall-clock loop woke late and resynchronised; the drive held the last command meanwhile:
        docs/timing.md). A law with a model propagates its estimate over them. Default: nothing (an
        integrator integrates one step per call: a skipped cycle winds nothing up)."""

    def describe(self) -> dict[str, Any]:
        """Name and settings, for trace metadata."""
        return {"controller": self.name, **{k: _plain(v) for k, v in self.settings.as_dict().items()}}


def _plain(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    return value

"""Quantities with units as a person types them (``20mm``, ``-5 mm/s``, ``0.5s``), parsed to SI.

A motion command with a bare number is refused: ``move x 20`` could mean 20 mm or 20 m, and on an
axis the difference is a crash. Position, velocity and time each accept only their own units.
"""

from __future__ import annotations

import math
import re

from drivectl.errors import InputError

#: unit -> factor to SI, per kind of quantity
UNITS: dict[str, dict[str, float]] = {
    "position": {"m": 1.0, "mm": 1e-3, "um": 1e-6, "µm": 1e-6, "nm": 1e-9},
    "velocity": {"m/s": 1.0, "mm/s": 1e-3, "um/s": 1e-6, "µm/s": 1e-6},
    "time": {"s": 1.0, "ms": 1e-3},
}

#: the unit suggested when a number comes without one
EXAMPLE = {"position": "mm", "velocity": "mm/s", "time": "s"}

_NUMBER_UNIT = re.compile(r"^\s*([+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)\s*([^\s\d.+-][^\s]*)?\s*$")


class QuantityError(InputError):
    """A value that is not a number with one of its kind's units."""


def parse_quantity(text: str, kind: str, *, what: str | None = None) -> float:
    """``text`` (e.g. ``"-5mm/s"``) in SI units of ``kind`` (position, velocity or time).

    QuantityError names ``what`` (default: the kind) and the units it takes."""
    units = UNITS[kind]
    name = what or kind
    m = _NUMBER_UNIT.match(text)
    if m is None:
        raise QuantityError(f"{name}: {text!r} is not a number with a unit ({', '.join(units)})")
    value, unit = float(m.group(1)), m.group(2)
    if unit is None:
        raise QuantityError(f"{name}: {text!r} needs a unit ({', '.join(units)}), e.g. {m.group(1)}{EXAMPLE[kind]}")
    if unit not in units:
        raise QuantityError(f"{name}: unit {unit!r} is not one of {', '.join(units)}")
    if not math.isfinite(value):
        raise QuantityError(f"{name}: {text!r} is not finite")
    return value * units[unit]


def format_position(metres: float) -> str:
    """A position as a person reads it: mm with micrometre digits."""
    return f"{metres * 1e3:.4f} mm"


def format_velocity(m_s: float) -> str:
    return f"{m_s * 1e3:.3f} mm/s"

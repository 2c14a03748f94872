"""The configuration's health keys (docs/health.md), parsed here for machine/config.py:

```toml
[health]
store = "health"
[health.limits]                  # every axis (each key: EFFECT.PARAM = a number in SI units, or a quantity)
backlash.width = "20um"
viscous.scale = 1.5

[axes.x.health]
profile = "fingerprint"          # the fingerprint run's profile (library name or TOML file)
[axes.x.health.limits]           # this axis only, over [health.limits]
backlash.width = "15um"
```

A limit is where a parameter's trend stops being acceptable: `drivectl health report` says when the
trend will cross it. No heavy import here: the configuration loads it on every command.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from drivectl.errors import InputError

#: the fingerprint run's profile when the configuration names none (profiles/library/fingerprint.toml)
DEFAULT_PROFILE = "fingerprint"

#: documented defaults (docs/health.md): backlash past 20 um costs parts on a hardening feed axis (a
#: quarter of the typical 80 um tolerance band); friction 1.5 times the commissioning model's viscous
#: part is a screw out of lubrication. Parameters in effort units have no default: their scale is the
#: plant's (N, V), so a limit on them is the machine builder's to set.
DEFAULT_LIMITS: dict[str, float] = {
    "backlash.width": 20e-6,
    "viscous.scale": 1.5,
    "viscous.scale_neg": 1.5,
    "delay.delay": 2e-3,
}

#: a parameter's unit (plant_emulator/effects.py ParamDef.unit) -> the kind of quantity a string takes
_KIND = {"m": "position", "m/s": "velocity", "s": "time"}


@dataclass(frozen=True)
class AxisHealth:
    """``[axes.NAME.health]``: the fingerprint profile, the axis's own limits (over ``[health.limits]``)."""

    profile: str = DEFAULT_PROFILE
    #: "effect.param" -> SI value, only the keys this axis's table set
    limits: dict[str, float] = field(default_factory=dict)
    #: where the profile came from, for messages ("FILE: axes.x.health.profile", or the default)
    profile_source: str = field(default="the default fingerprint profile", compare=False)


def parse_limits(src: str, key: str, raw: Any) -> dict[str, float]:
    """``[... .limits]``: EFFECT.PARAM = value (TOML dotted keys: a table per effect)."""
    from drivectl.plant_emulator.effects import EFFECTS
    from drivectl.tools.cli.quantity import QuantityError, parse_quantity

    if raw is None:
        return {}
    if not isinstance(raw, Mapping):
        raise InputError(f"{src}: {key}: expected a table (backlash.width = \"20um\")")
    out: dict[str, float] = {}
    for effect, params in raw.items():
        if effect not in EFFECTS:
            raise InputError(f"{src}: {key}.{effect}: unknown effect (known: {', '.join(EFFECTS)})")
        if not isinstance(params, Mapping):
            raise InputError(f"{src}: {key}.{effect}: expected EFFECT.PARAM = value, e.g. {effect}."
                             f"{EFFECTS[effect].params[0].name} = ...")
        defs = {p.name: p for p in EFFECTS[effect].params}
        for pname, value in params.items():
            where = f"{src}: {key}.{effect}.{pname}"
            if pname not in defs:
                raise InputError(f"{where}: not a parameter of {effect} (parameters: {', '.join(defs)})")
            unit = defs[pname].unit
            if isinstance(value, str) and unit in _KIND:
                try:
                    v = parse_quantity(value, _KIND[unit], what=f"{key}.{effect}.{pname}")
                except QuantityError as exc:
                    raise InputError(f"{src}: {exc}") from None
            elif isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value):
                v = float(value)
            else:
                hint = f"a number in {unit}" + (f" or a quantity such as \"20{'um' if unit == 'm' else unit}\""
                                                 if unit in _KIND else "")
                raise InputError(f"{where}: expected {hint}, got {value!r}")
            out[f"{effect}.{pname}"] = v
    return out


def parse_axis_health(src: str, key: str, raw: Any) -> AxisHealth:
    """``[axes.NAME.health]`` (``key`` is ``axes.NAME.health``)."""
    if raw is None:
        return AxisHealth()
    if not isinstance(raw, Mapping):
        raise InputError(f"{src}: {key}: expected a table")
    extra = set(raw) - {"profile", "limits"}
    if extra:
        raise InputError(f"{src}: {key}.{sorted(extra)[0]}: unknown key (known: profile, limits)")
    profile = raw.get("profile", DEFAULT_PROFILE)
    if not isinstance(profile, str) or not profile:
        raise InputError(f"{src}: {key}.profile: expected a profile name or TOML file, got {profile!r}")
    source = f"{src}: {key}.profile" if "profile" in raw else AxisHealth.profile_source
    return AxisHealth(profile, parse_limits(src, f"{key}.limits", raw.get("limits")), source)


def axis_limits(machine_limits: Mapping[str, float], axis: AxisHealth | None) -> dict[str, float]:
    """The limits of one axis: the defaults, then ``[health.limits]``, then ``[axes.NAME.health.limits]``."""
    return {**DEFAULT_LIMITS, **machine_limits, **(axis.limits if axis is not None else {})}

"""Controllers by name: what configuration files and the CLI refer to."""

from __future__ import annotations

from collections.abc import Mapping
from importlib import import_module
from typing import Any

from drivectl.controllers.base import Controller, SettingsError

#: name -> (module, class); imported on first use so the CLI starts fast
CONTROLLERS: dict[str, tuple[str, str]] = {
    "smc": ("drivectl.controllers.tde_smc", "TdeSmc"),
    "vprl": ("drivectl.controllers.vprl", "TdeVprl"),
    "pid-nftsm": ("drivectl.controllers.pid_nftsm", "TdePidNftsm"),
    "asmc": ("drivectl.controllers.asmc", "Asmc"),
    "pid": ("drivectl.controllers.pid", "Pid"),
    "pid-dob": ("drivectl.controllers.pid", "PidDob"),
    "mbc": ("drivectl.controllers.mbc", "Mbc"),
}

#: controllers whose law uses the plant's nominal model (mass, friction) and take it at construction
MODEL_BASED = ("asmc", "pid-dob", "mbc")


def controller_class(name: str) -> type[Controller]:
    if name not in CONTROLLERS:
        raise SettingsError(f"controller: {name!r}: unknown (known: {', '.join(CONTROLLERS)})")
    module, cls = CONTROLLERS[name]
    return getattr(import_module(module), cls)


def make_controller(
    name: str,
    dt: float,
    settings: Mapping[str, Any] | None = None,
    *,
    plant: Any = None,
    axis: str = "x",
    source: str | None = None,
) -> Controller:
    """Build controller ``name`` at cycle ``dt`` from a settings table.

    Model-based controllers take the nominal model from ``plant`` (a PlantSpec) and the paper's
    column for ``axis`` (x or y) where the paper gives one per axis.
    """
    cls = controller_class(name)
    settings = dict(settings or {})
    try:
        if name in MODEL_BASED and plant is not None and hasattr(cls, "for_plant"):
            return cls.for_plant(dt, plant, axis=axis, **settings)
        return cls(dt, settings)
    except SettingsError as exc:
        if source:
            raise SettingsError(f"{source}: {exc}") from None
        raise

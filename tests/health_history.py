"""Histories for the health tests: fingerprint runs of an emulated axis, one a shift, each with its own
noise seed and the temperature of its day, and wear hidden from a given run on (the plant's effects,
plant_emulator/effects.py). Each run goes through ``drivectl.connect`` and ``run_fingerprint``: the
resident loop, the trace's header, the store."""

from __future__ import annotations

import math
from collections.abc import Callable
from datetime import UTC, datetime, timedelta
from pathlib import Path

SHORT_PROFILE = Path(__file__).with_name("data") / "health-short.toml"
START = datetime(2026, 11, 2, 6, 0, tzinfo=UTC)
SHIFT = timedelta(hours=8)

#: wear(run) -> the effects the plant plays on that run, beyond the day's temperature
Wear = Callable[[int], list[tuple[str, dict[str, float]]]]


def clean(run: int) -> list[tuple[str, dict[str, float]]]:  # noqa: ARG001 - every run alike
    return []


def viscous_from(onset: int, per_run: float) -> Wear:
    """Viscous friction growing by ``per_run`` of the model's a run from run ``onset`` on."""
    return lambda run: [] if run < onset else [("viscous", {"scale": 1.0 + per_run * (run - onset + 1)})]


def backlash_from(onset: int, per_run: float) -> Wear:
    """Backlash opening by ``per_run`` m a run from run ``onset`` on (none before)."""
    return lambda run: [] if run < onset else [("backlash", {"width": per_run * (run - onset + 1)})]


def temperature(run: int, swing: float = 0.03) -> float:
    """The day's temperature as a viscous factor: three shifts a day, warm in the afternoon (+-swing)."""
    return 1.0 + swing * math.sin(2 * math.pi * (run % 3) / 3)


def make_history(store: Path, out: Path, wear: Wear, runs: int, *, machine: str = "m1", axis: str = "x",
                 noise: float = 0.5, seed: int = 0, swing: float = 0.03) -> list[Path]:
    """``runs`` fingerprint runs of ``axis`` (the short test profile) kept in ``store``; the traces'
    paths in run order."""
    import drivectl
    from drivectl.profiles.library import load_profile
    from drivectl.tools.health.fingerprint import run_fingerprint

    profile = load_profile(SHORT_PROFILE)
    paths = []
    for run in range(runs):
        effects = wear(run)
        named = {e for e, _ in effects}
        if "viscous" in named:  # the day's temperature on top of the wear
            effects = [(e, {**p, "scale": p["scale"] * temperature(run, swing)} if e == "viscous" else p)
                       for e, p in effects]
        else:
            effects = [*effects, ("viscous", {"scale": temperature(run, swing)})]
        with drivectl.connect(axes=[axis], sim=True, effects=effects, noise=noise, seed=seed * 1000 + run,
                              fault_dir=None) as m:
            m.axes[axis].enable()
            r = run_fingerprint(m, axis, machine_name=machine, out=out, store=store, profile=profile,
                                started=START + run * SHIFT)
        assert r.status == "done" and r.ingest is not None and r.ingest.status == "added", r.line
        paths.append(r.trace)
    return paths

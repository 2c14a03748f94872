"""The test set of `drivectl explain`: traces through SimAxis with one hidden effect each, and clean ones.

Every trace is made exactly as the issue prescribes, so hidden traces look like these::

    spec = load_plant(plant).with_effect(name, **params)        # the machine
    axis = SimAxis(spec.build(0.001), resolution=76.29e-9, force_noise=..., seed=...)
    controller = make_controller(ctrl, 0.001, settings, plant=load_plant(plant))   # knows the NOMINAL plant
    profile = back_and_forth(start, distance, speeds, amax, jmax, dwell)        # 8-12 s, 2-3 speeds
    trace = run(axis, controller, profile, limits=Limits(following_error=...)).trace

Cases are drawn from a seeded generator (``cases(n_per_effect, seed)``): each effect at magnitudes
spread over the issue's ranges, alternating rigid-x / rigid-y, controllers and profiles. Nothing in
`explain` reads this module: it only makes data.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass, field
from typing import Any

from drivectl.controllers.registry import make_controller
from drivectl.controllers.servo import Limits, run
from drivectl.plant_emulator.models import load_plant
from drivectl.plant_emulator.sim_axis import SimAxis
from drivectl.profiles.sequence import back_and_forth
from drivectl.tools.trace import Trace

DT = 0.001
RESOLUTION = 76.29e-9
MIN_TRACE_S = 3.0

#: controllers and settings that close a stable loop on the rigid plants (the TDE laws were tuned
#: for the two-mass plant in V; on the rigid axes in N their m_tilde must be ~10-20 kg)
CONTROLLERS: list[tuple[str, dict[str, Any]]] = [
    ("pid", {}),
    ("pid", {"d_filter_hz": 200.0, "ff_mass": 80.0, "i_limit": 200.0}),  # a plain PID with filters
    ("pid-dob", {}),
    ("asmc", {}),
    ("asmc", {"law": 12}),
    ("pid-nftsm", {"m_tilde": 20.0, "accel_filter_hz": 0.0}),
    ("smc", {"m_tilde": 10.0, "accel_filter_hz": 0.0}),
]

#: softer loops a commissioning engineer falls back to when a low resonance makes the stiff ones
#: unstable (tried in this order when a run does not complete)
SOFT_CONTROLLERS: list[tuple[str, dict[str, Any]]] = [
    ("pid", {"kp": 5.0e5, "kd": 2.0e3, "ki": 2.0e4, "d_filter_hz": 30.0, "ff_mass": 88.0}),
    ("pid", {"kp": 3.0e5, "kd": 3.0e3, "ki": 2.0e4, "d_filter_hz": 50.0, "ff_mass": 88.0}),
    ("pid", {"kp": 1.0e5, "kd": 1.0e3, "ki": 5.0e3, "d_filter_hz": 20.0, "ff_mass": 88.0}),
]

EFFECT_NAMES = ("stribeck", "backlash", "periodic", "mass", "viscous", "delay", "offset", "spring", "resonance",
                "saturation")


@dataclass
class Case:
    """One trace to make: the hidden effect (or none) and everything around it."""

    effect: str
    params: dict[str, float]
    plant: str
    controller: str
    settings: dict[str, Any]
    profile: dict[str, Any]
    noise: float
    seed: int
    extra: dict[str, float] = field(default_factory=dict)  # e.g. the periodic phase

    @property
    def label(self) -> str:
        p = ",".join(f"{k}={v:.4g}" for k, v in self.params.items())
        return f"{self.effect}[{p}] {self.plant} {self.controller} seed={self.seed}"


def _log_uniform(rng: random.Random, lo: float, hi: float) -> float:
    return math.exp(rng.uniform(math.log(lo), math.log(hi)))


def draw_profile(rng: random.Random) -> dict[str, Any]:
    """A commissioning back-and-forth of 8-12 s: 2-3 speeds, dwells, reversals."""
    while True:
        n_speeds = rng.choice((2, 3))
        speeds = sorted(rng.uniform(0.01, 0.12) for _ in range(n_speeds))
        prof = {
            "start": rng.choice((0.0, rng.uniform(-0.05, 0.05))),
            "distance": rng.choice((1, -1)) * rng.uniform(0.02, 0.08),
            "speeds": speeds,
            "amax": rng.uniform(0.3, 1.0),
            "jmax": rng.uniform(10.0, 40.0),
            "dwell": rng.uniform(0.2, 0.5),
        }
        seq = back_and_forth(**prof)
        repeats = max(1, round(10.0 / seq.duration))
        prof["repeats"] = repeats
        if 8.0 <= seq.duration * repeats <= 12.0:
            return prof


def draw_params(effect: str, rng: random.Random, plant: str) -> tuple[dict[str, float], dict[str, float]]:
    """Physically sensible, visible magnitudes (the issue's ranges); second dict: extras (phase)."""
    nominal = load_plant(plant)
    sign = rng.choice((1.0, -1.0))
    if effect == "stribeck":
        return {"excess_force": rng.uniform(5.0, 30.0), "velocity": _log_uniform(rng, 5e-4, 5e-3)}, {}
    if effect == "backlash":
        return {"width": _log_uniform(rng, 5e-6, 50e-6)}, {}
    if effect == "periodic":
        return ({"amplitude": rng.uniform(3.0, 30.0), "period": _log_uniform(rng, 2e-3, 20e-3)},
                {"phase": rng.uniform(0, 2 * math.pi)})
    if effect == "mass":
        return {"mass": nominal.params["mass"] * (1.0 + sign * rng.uniform(0.10, 0.40))}, {}
    if effect == "viscous":
        return {"scale": rng.uniform(0.5, 0.8) if sign < 0 else rng.uniform(1.3, 2.0)}, {}
    if effect == "delay":
        return {"delay": rng.uniform(0.5e-3, 5e-3)}, {}
    if effect == "offset":
        return {"force": sign * rng.uniform(5.0, 40.0)}, {}
    if effect == "spring":
        return {"stiffness": _log_uniform(rng, 2e3, 5e4)}, {}
    if effect == "resonance":
        return {"frequency": _log_uniform(rng, 20.0, 150.0), "damping": _log_uniform(rng, 0.02, 0.2)}, {}
    if effect == "saturation":
        return {"limit": rng.uniform(0.4, 0.8)}, {}  # fraction of the clean run's peak effort, resolved later
    raise ValueError(effect)


def cases(n_per_effect: int = 4, n_clean: int = 8, seed: int = 1) -> list[Case]:
    """The test set: ``n_per_effect`` traces per effect and ``n_clean`` clean ones."""
    rng = random.Random(seed)
    out: list[Case] = []
    plans = [("none", i) for i in range(n_clean)] + [(e, i) for e in EFFECT_NAMES for i in range(n_per_effect)]
    for k, (effect, i) in enumerate(plans):
        plant = ("rigid-x", "rigid-y")[i % 2]
        cname, settings = CONTROLLERS[(i + k) % len(CONTROLLERS)]
        params, extra = ({}, {}) if effect == "none" else draw_params(effect, rng, plant)
        out.append(Case(effect, params, plant, cname, dict(settings), draw_profile(rng),
                        noise=rng.uniform(0.5, 2.0), seed=rng.randrange(1 << 30), extra=extra))
    return out


def simulate(case: Case, effects: list[tuple[str, dict[str, float]]] | None = None) -> Trace:
    """Run one case; ``effects`` overrides the case's (used to resolve a saturation limit)."""
    nominal = load_plant(case.plant)
    spec = nominal
    if effects is None:
        effects = [] if case.effect == "none" else [(case.effect, {**case.params, **case.extra})]
    for name, params in effects:
        spec = spec.with_effect(name, **params)
    axis_name = case.plant.split("-")[-1]
    axis = SimAxis(spec.build(DT), resolution=RESOLUTION, force_noise=case.noise, seed=case.seed,
                   initial_position=case.profile["start"], name=axis_name)
    settings = dict(case.settings)
    controller = make_controller(case.controller, DT, settings, plant=nominal, axis=axis_name)
    profile = back_and_forth(**case.profile)
    res = run(axis, controller, profile, limits=Limits(following_error=0.02),
              meta={"plant": case.plant, "truth": case.label})
    return res.trace


def _completed(case: Case, effects: list[tuple[str, dict[str, float]]] | None) -> Trace | None:
    try:
        tr = simulate(case, effects)
    except (ArithmeticError, ValueError):
        return None  # a loop driven unstable (asmc's exp overflows): not a trace anyone records
    # a run stopped by a limit still leaves a trace (the machine recorded it); keep it when it holds
    # enough to decide (MIN_TRACE_S), as a user would hand it to explain
    return tr if tr.meta.get("stop") == "completed" or float(tr.time[-1]) >= MIN_TRACE_S else None


def make_trace(case: Case) -> tuple[Trace, dict[str, float]]:
    """The trace of a case and the true parameters (saturation: the limit in N, from the clean run).

    A loop that the hidden effect drives unstable (a low resonance under stiff gains) ends in a
    following-error stop after a few cycles; as on a real machine, the run is repeated with softer
    gains (SOFT_CONTROLLERS). A run stopped by a limit after MIN_TRACE_S is kept. Raises RuntimeError
    when no controller gets that far.
    """
    truth = dict(case.params)
    effects = None
    if case.effect == "saturation":
        if "limit_n" not in case.extra:
            clean = simulate(case, effects=[])
            case.extra["limit_n"] = case.params["limit"] * float(max(abs(clean.effort)))
        truth = {"limit": case.extra["limit_n"]}
        effects = [("saturation", truth)]
    tr = _completed(case, effects)
    for cname, settings in SOFT_CONTROLLERS:
        if tr is not None:
            break
        case.controller, case.settings = cname, dict(settings)
        tr = _completed(case, effects)
    if tr is None:
        raise RuntimeError(f"{case.label}: no controller completes the run")
    return tr, truth

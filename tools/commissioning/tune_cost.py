"""Scoring one candidate gain set for `drivectl tune`: run it on the axis's model, reduce the run to
the cost J, and score a whole sample at once (numpy batch on linear plants, else a process pool).

The cost:

    J = max|e| [um] + w * du_rms / (rated_effort / 1000)        [um]

``max|e|`` the largest tracking error of the run, ``du_rms`` the RMS of the effort's first difference
per cycle (tracefile/metrics.py ``effort_roughness``, in the effort unit) expressed in per mille of the
axis's rated effort (the 0x6071 unit, so N and V axes share one scale), ``w`` in um per per-mille
(default :data:`DEFAULT_WEIGHT`). J is infinite when the run leaves the following-error window (or
the soft limits) or when the effort limit clips the command on more than :data:`MAX_CLIPPED`
cycles: such gains are outside the limits, however small their error.

Why w = 0.05 um per per mille: on the embedded machine the starting gains give x 0.19 um max error
with 10.5 per mille roughness (0.53 um of J) and z 19.9 um with 20 per mille (1.0 um of J). At
w = 0.05 halving x's roughness is worth more than its whole tracking error, so on a stiff,
well-modelled axis the search cannot buy 0.01 um with a buzzing effort; on z (error dominated)
chattering is a ~5 % term that breaks near-ties and penalises gains that multiply it. Measured: on x
the 200-candidate search lowered the max error 0.19 -> 0.12 um at unchanged roughness (1.05 N/cycle;
the circle's roughness hardly depends on these four gains); on z 19.9 -> 11.8 um at 1.4x roughness.

Speed: linear plants (two-mass, no effects) run the whole sample as one numpy batch
(plant_emulator/batch.py, array-valued settings, the same control-law code); nonlinear plants
(rigid-x has Coulomb friction) run candidate by candidate on SimAxis in a process pool.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from typing import Any

import numpy as np

from drivectl.machine.config import MachineConfig

#: um of max error per per mille (of rated effort) of effort roughness; see the module text
DEFAULT_WEIGHT = 0.05
#: a run whose command the effort limit clipped on more cycles than this is outside the limits
MAX_CLIPPED = 5

COST_TEXT = ("J = max|e| [um] + w * du_rms / (rated/1000) [um], w = {w:g} um per per mille of rated effort; "
             "infinite if the run leaves the following-error window or the effort limit clips > {c} cycles")


@dataclass
class Metrics:
    max_um: float
    du_rms: float  # effort unit per cycle
    cost: float
    ok: bool = True
    clipped: int = 0
    detail: str = ""

    def to_json(self) -> dict[str, float | None]:
        return {"max_um": _finite_or_none(self.max_um), "du_rms": _finite_or_none(self.du_rms),
                "cost": _finite_or_none(self.cost)}


def _finite_or_none(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def cost_of(max_um: float, du_rms: float, rated: float, weight: float) -> float:
    """The stated cost J (um) of one run's figures; see the module text."""
    if not (math.isfinite(max_um) and math.isfinite(du_rms)):
        return math.inf
    return max_um + weight * du_rms / (rated * 1e-3)


# --------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Job:
    """What a worker needs to run candidates (picklable)."""

    cfg: MachineConfig
    axis: str
    controller: str
    base: dict[str, Any]
    duration: float
    weight: float
    #: the plant the run plays when it is not the model (a perturbed corner, controllers/robust.py)
    plant: Any = None


def profile_of(job: Job) -> Any:
    from drivectl.machine.build import axis_profile

    return axis_profile(job.cfg, job.axis)


def simulate(job: Job, gains: Mapping[str, float], profile: Any = None) -> Metrics:
    """One SimAxis run of ``gains`` (the exact path `drivectl trace --sim` takes)."""
    from drivectl.controllers.base import SettingsError
    from drivectl.controllers.registry import make_controller
    from drivectl.controllers.runtime.servo import run
    from drivectl.machine.build import axis_model, model_specs, open_machine
    from drivectl.tracefile.metrics import effort_roughness, tracking_error

    cfg, name = job.cfg, job.axis
    ac = cfg.axis(name)
    profile = profile if profile is not None else profile_of(job)
    spec = model_specs(cfg, [name])[name]  # the search runs the axis's model (its model key, else its plant)
    try:
        ctrl = make_controller(job.controller, cfg.cycle_s, {**job.base, **gains}, plant=spec, axis=name)
    except SettingsError as exc:  # a cross-field rule the bounds missed: not a usable candidate
        return Metrics(math.inf, math.inf, math.inf, ok=False, detail=str(exc))
    if job.plant is not None:
        machine = _corner_machine(cfg, name, job.plant, profile.start_position)
    else:
        machine = open_machine(cfg, [name], sim=True, plant=axis_model(cfg, name),
                               start={name: profile.start_position})
    with machine:
        try:
            with np.errstate(all="ignore"):
                res = run(machine.axes[name], ctrl, profile, duration=job.duration, limits=ac.limits)
        except (OverflowError, FloatingPointError, ValueError) as exc:  # a diverging candidate
            return Metrics(math.inf, math.inf, math.inf, ok=False, detail=str(exc))
    metrics = metrics_of(res, ac.rated_effort, job.weight, effort_roughness, tracking_error)
    from drivectl.controllers.robust import settles

    tr = res.trace
    if metrics.ok and not settles(tr.ref - tr.pos, np.diff(tr.ref, prepend=tr.ref[:1])):
        return Metrics(metrics.max_um, metrics.du_rms, math.inf, ok=False, clipped=metrics.clipped,
                       detail="the error does not settle (unstable or limit-cycling)")
    return metrics


def _corner_machine(cfg: MachineConfig, name: str, spec: Any, start: float) -> Any:
    """SimAxis playing ``spec`` (a perturbed model), quantised as open_machine(sim=True) quantises."""
    from drivectl.driver.units import EffortScale
    from drivectl.machine.build import Machine
    from drivectl.plant_emulator.sim_axis import SimAxis

    ac = cfg.axis(name)
    axis = SimAxis(spec.build(cfg.cycle_s), name=name, resolution=ac.encoder_m_per_count,
                   effort_scale=EffortScale(ac.rated_effort), initial_position=start)
    return Machine({name: axis}, {name: spec}, "sim (SimAxis, a perturbed model)")


def metrics_of(res: Any, rated: float, weight: float, roughness: Callable, tracking: Callable) -> Metrics:
    tr = res.trace
    max_um = tracking(tr.ref, tr.pos)["max"] * 1e6 if len(tr) else math.inf
    du = roughness(tr.effort)
    clipped = res.clipped.get(tr.meta.get("axis", ""), 0) if res.clipped else 0
    ok = res.ok and clipped <= MAX_CLIPPED
    cost = cost_of(max_um, du, rated, weight) if ok else math.inf
    detail = res.detail or (f"effort clipped on {clipped} cycles" if clipped > MAX_CLIPPED else "")
    return Metrics(max_um, du, cost, ok=ok, clipped=clipped, detail=detail)


def _run_chunk(job: Job, chunk: Sequence[tuple[int, dict[str, float]]]) -> list[tuple[int, float]]:
    """Worker: the costs of a chunk of (index, gains); the profile is loaded once per chunk."""
    profile = profile_of(job)
    return [(i, simulate(job, g, profile).cost) for i, g in chunk]


class _Guard:
    """Wraps a batch controller with what the servo loop does around it, per member: clip to the
    effort limit (counting clipped cycles), quantise the sent effort to per mille of rated (0x6071),
    check the following-error window and the soft limits, and measure the roughness of the command
    as recorded (clipped, before quantisation) -- so the batch ranks candidates as SimAxis would."""

    def __init__(self, inner: Any, members: int, limits: Any, rated: float, dt: float):
        self.inner = inner
        self.dt = dt
        self.n = members
        self.lim = limits
        self.rated = rated
        self.reset()

    def reset(self) -> None:
        self.inner.reset()
        n = self.n
        self.clipped = np.zeros(n, dtype=int)
        self.failed = np.zeros(n, dtype=bool)
        self.outside = np.zeros(n, dtype=int)  # consecutive cycles outside the window
        self.sq_du = np.zeros(n)
        self.prev: np.ndarray | None = None
        self.k = 0

    def prepare(self, profile: Any, times: np.ndarray) -> None:
        prepare = getattr(self.inner, "prepare", None)
        if prepare is not None:
            prepare(profile, times)

    def step(self, reference: Any, feedback: Any) -> np.ndarray:
        with np.errstate(all="ignore"):
            u = np.broadcast_to(np.asarray(self.inner.step(reference, feedback), dtype=float), (self.n,))
            m = self.lim.max_effort
            over = np.abs(u) > m
            self.clipped += over
            u = np.clip(u, -m, m)
            if self.prev is not None:
                self.sq_du += (u - self.prev) ** 2
            self.prev = u
            err = np.abs(reference.position - np.asarray(feedback.position, dtype=float))
            out = ~(err <= self.lim.following_error)  # NaN counts as outside
            self.outside = np.where(out, self.outside + 1, 0)
            # the loop stops once the excursion has lasted following_time (cycles since it began)
            limit_cycles = self.lim.following_time / self.dt
            self.failed |= out & ((self.outside - 1) >= limit_cycles - 1e-9)
            if self.lim.position is not None:
                p = np.asarray(feedback.position, dtype=float)
                self.failed |= ~((p >= self.lim.position[0]) & (p <= self.lim.position[1]))
            scale = self.rated / 1000.0
            sent = np.rint(np.nan_to_num(u) / scale) * scale
        self.k += 1
        return sent


def _batch_costs(job: Job, gains: list[dict[str, float]]) -> np.ndarray:
    """Every candidate at once on a linear plant (plant_emulator/batch.py)."""
    from drivectl.controllers.registry import make_controller
    from drivectl.machine.build import model_specs
    from drivectl.plant_emulator.batch import run_batch

    cfg, name = job.cfg, job.axis
    ac = cfg.axis(name)
    spec = model_specs(cfg, [name])[name]
    plant = (job.plant if job.plant is not None else spec).build(cfg.cycle_s, substeps=1)
    keys = list(gains[0])
    arrays = {k: np.array([g[k] for g in gains], dtype=float) for k in keys}
    ctrl = make_controller(job.controller, cfg.cycle_s, {**job.base, **arrays}, plant=spec, axis=name)
    guard = _Guard(ctrl, len(gains), ac.limits, ac.rated_effort, cfg.cycle_s)
    with np.errstate(all="ignore"):
        res = run_batch(plant, guard, profile_of(job), len(gains), duration=job.duration,
                        resolution=ac.encoder_m_per_count)
    n = max(res.cycles - 1, 1)
    du = np.sqrt(guard.sq_du / n)
    cost = res.max_error * 1e6 + job.weight * du / (ac.rated_effort * 1e-3)
    bad = ~res.finite | guard.failed | (guard.clipped > MAX_CLIPPED) | ~np.isfinite(cost)
    return np.where(bad, np.inf, cost)


def batch_ok(cfg: MachineConfig, axis: str) -> bool:
    from drivectl.machine.build import model_specs
    from drivectl.plant_emulator.batch import check_linear

    try:
        check_linear(model_specs(cfg, [axis])[axis].build(cfg.cycle_s, substeps=1))
    except ValueError:
        return False
    return True


def evaluate_robust(jobs_set: Sequence[Job], model: Any, pts: list[dict[str, float]], use_batch: bool,
                     pool: ProcessPoolExecutor | None, jobs: int, bar: Any) -> tuple[np.ndarray, int]:
    """Each candidate's worst cost over the model and its corners, and how many candidates were rejected
    as unstable on some corner. Candidates whose loop is linear (a ``loop_matrix``) are checked first by
    the spectral radius on every corner and not simulated when unstable."""
    costs = np.zeros(len(pts))
    rejected = np.zeros(len(pts), dtype=bool)
    corners_ = [j.plant for j in jobs_set if j.plant is not None]
    if corners_:
        rejected = _linear_rejects(jobs_set[0], model, corners_, pts)
    alive = [i for i in range(len(pts)) if not rejected[i]]
    unstable = int(rejected.sum())
    sim_unstable = np.zeros(len(pts), dtype=bool)
    for job in jobs_set:
        if alive:
            part = _evaluate(job, [pts[i] for i in alive], use_batch, pool, jobs, bar)
            costs[alive] = np.maximum(costs[alive], part)
            if job.plant is not None:
                sim_unstable[alive] |= ~np.isfinite(part)
        if bar is not None and len(alive) < len(pts):
            bar.update(len(pts) - len(alive))
    costs[rejected] = np.inf
    # a candidate out of the limits on the model itself is not "unstable on a corner"
    return costs, unstable + int(sim_unstable.sum())


def _linear_rejects(job: Job, model: Any, corners_: Sequence[Any], pts: list[dict[str, float]]) -> np.ndarray:
    """Candidates whose closed loop (linear controller, linear corner) has a spectral radius >= 1 on any."""
    from drivectl.controllers.base import SettingsError
    from drivectl.controllers.registry import make_controller
    from drivectl.controllers.robust import _is_linear, spectral_radius

    out = np.zeros(len(pts), dtype=bool)
    linear = [c for c in corners_ if _is_linear(c)]
    if not linear:
        return out
    for i, g in enumerate(pts):
        try:
            ctrl = make_controller(job.controller, job.cfg.cycle_s, {**job.base, **g}, plant=model, axis=job.axis)
        except SettingsError:
            out[i] = True
            continue
        if not hasattr(ctrl, "loop_matrix"):
            return out  # not a linear loop: the simulation decides
        out[i] = any(spectral_radius(ctrl, c) >= 1.0 for c in linear)
    return out


def _evaluate(job: Job, pts: list[dict[str, float]], use_batch: bool, pool: ProcessPoolExecutor | None,
              jobs: int, bar: Any) -> np.ndarray:
    if use_batch:
        costs = _batch_costs(job, pts)
        if bar is not None:
            bar.update(len(pts))
        return costs
    costs = np.full(len(pts), np.inf)
    indexed = list(enumerate(pts))
    if pool is None:
        profile = profile_of(job)
        for i, g in indexed:
            costs[i] = simulate(job, g, profile).cost
            if bar is not None:
                bar.update(1)
        return costs
    # small chunks: the pool stays busy to the end and the progress bar moves
    size = max(1, len(indexed) // (jobs * 6))
    futures = [pool.submit(_run_chunk, job, indexed[i:i + size]) for i in range(0, len(indexed), size)]
    for fut in as_completed(futures):
        done = fut.result()
        for i, c in done:
            costs[i] = c
        if bar is not None:
            bar.update(len(done))
    return costs

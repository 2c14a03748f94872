"""`drivectl explain`: name what the model is missing, add it, and show the gap shrink.

A recorded trace (format v1; the four required columns suffice) is held against a plant. The tool

1. measures the gap: a *windowed simulation error*. The trace is cut into ~150 ms windows; each
   window starts the plant from the measured state (position; velocity from ``vel_m_s`` or a
   Savitzky-Golay derivative of ``pos_m``) and drives it open loop with the recorded effort under
   the transport rule (the effort on row k acts from t(k+1) to t(k+2)); the gap is the RMS of
   simulated minus measured position over all windows, in m. Restarting every window keeps the
   open-loop simulation from drifting (friction integrates) while still letting every force the
   model lacks show as a position error of its own shape.
2. fits every effect of the vocabulary (plant_emulator/effects.py, the code the emulator runs) on
   that same gap: coarse grids, then finer ones around the best, all candidates of a grid simulated
   at once (tools/explain_sim.py). The position-periodic force is first located by a period scan of
   the one-step force residual, because its gap is far too multimodal in the period for a grid.
3. decides: the effect with the smallest gap after, charged a penalty per parameter, wins if it
   shrinks the gap by more than a threshold calibrated on clean traces (docs/explain.md); else
   ``none``. The runners-up and their shrink are the evidence.
4. writes the augmented plant (``PlantSpec.with_effect(...).to_toml()``, loadable by ``--plant``),
   a PNG and a report, and recomputes the gap with the augmented plant.

Library: :func:`explain` (trace, plant spec) -> :class:`ExplainResult`. CLI: :func:`add_explain_parser`
and :func:`cmd_explain`, wired into tools/cli.py by the lead.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from drivectl.plant_emulator.models import Plant, PlantError, PlantSpec, load_plant
from drivectl.tools.explain_sim import BatchSim, Windows, internal_state, make_windows, window_rms
from drivectl.tools.trace import REQUIRED, Trace, TraceError

#: window of the gap, s (the issue's ~150 ms: long enough for a missing force to move the axis
#: measurably, short enough that friction and force noise do not make the open loop drift)
WINDOW_S = 0.150
#: the least a trace must hold to decide anything: this many windows with motion in them
MIN_MOVING_WINDOWS = 8
#: relative tolerance on the sample time (a recorder's timestamps, rounded to 1 us in the file)
DT_TOLERANCE = 0.02
#: a trace "moves" in a window when its position spans this many encoder counts or more
MOVING_SPAN_M = 5e-6

#: substeps per cycle in the coarse rounds of a fit (the plant's own, 10-20, in the last round):
#: measured on the test traces, 2-5 substeps move the gap by < 0.1 um for rigid plants; the
#: backlash contact needs 5 for the coarse search to point at the right width
COARSE_SUBSTEPS = 2
COARSE_SUBSTEPS_TWO_BODY = 5

#: decision: the best effect must shrink the gap by at least this much to be named (calibrated on
#: clean traces, whose best spurious shrink stays far below; docs/explain.md)
NONE_SHRINK = 0.35
#: penalty per parameter on the squared gap (an information-criterion style charge: an effect with
#: one more free parameter must explain that much more of the squared gap to be preferred)
PARAM_PENALTY = 0.04

GAP_METRIC = ("windowed simulation error: RMS of simulated minus measured position (m) over 150 ms windows, "
              "each started from the measured state and driven open loop by the recorded effort "
              "(effort of row k acting from t(k+1) to t(k+2))")

PARAM_NAMES: dict[str, tuple[str, ...]] = {
    "stribeck": ("excess_force", "velocity"),
    "backlash": ("width",),
    "periodic": ("amplitude", "period"),
    "mass": ("mass",),
    "viscous": ("scale",),
    "delay": ("delay",),
    "offset": ("force",),
    "spring": ("stiffness",),
    "resonance": ("frequency", "damping"),
    "saturation": ("limit",),
}


class ExplainError(ValueError):
    """The trace cannot be explained (bad input, or too little in it to decide): one line naming the file."""


# --------------------------------------------------------------------------------------------------
# Data
# --------------------------------------------------------------------------------------------------


@dataclass
class Prepared:
    """The trace as the fitters see it."""

    source: str
    t: np.ndarray
    pos: np.ndarray
    vel: np.ndarray
    effort: np.ndarray
    dt: float
    spec: PlantSpec
    windows: Windows
    vel_source: str
    effort_unit: str

    @property
    def applied(self) -> np.ndarray:
        """Effort acting during step j (t(j) -> t(j+1)): the row before (transport rule)."""
        return np.concatenate(([0.0], self.effort[:-1]))


def prepare(trace: Trace, spec: PlantSpec, source: str = "<trace>") -> Prepared:
    """Check the trace and cut it into windows; every problem is one ExplainError line."""
    for name in REQUIRED:
        if name not in trace.columns:
            raise ExplainError(f"{source}: missing column {name!r}")
    cols = {k: np.asarray(trace.columns[k], dtype=float) for k in REQUIRED}
    for name, col in cols.items():
        bad = ~np.isfinite(col)
        if bad.any():
            raise ExplainError(f"{source}: column {name}: not a finite number at data row {int(np.argmax(bad)) + 1}")
    t = cols["time_s"]
    if len(t) < 3:
        raise ExplainError(f"{source}: cannot decide: {len(t)} rows, too short")
    steps = np.diff(t)
    if np.any(steps <= 0):
        raise ExplainError(f"{source}: column time_s: not increasing at data row {int(np.argmax(steps <= 0)) + 2}")
    dt = float(np.median(steps))
    if np.max(np.abs(steps - dt)) > DT_TOLERANCE * dt + 2e-6:
        row = int(np.argmax(np.abs(steps - dt))) + 2
        raise ExplainError(f"{source}: column time_s: non-uniform sample time at data row {row} "
                           f"(step {steps[row - 2]:.6g} s, median {dt:.6g} s); explain needs a fixed cycle")
    unit = trace.meta.get("effort_unit", "") if trace.meta else ""
    if unit and unit != spec.effort_unit:
        raise ExplainError(f"{source}: effort_unit {unit!r} but plant {spec.name} takes {spec.effort_unit!r}")
    if "dt_s" in (trace.meta or {}):
        try:
            meta_dt = float(trace.meta["dt_s"])
        except ValueError:
            raise ExplainError(f"{source}: dt_s: expected a number, got {trace.meta['dt_s']!r}") from None
        if abs(meta_dt - dt) > DT_TOLERANCE * dt:
            raise ExplainError(f"{source}: dt_s {meta_dt:g} s disagrees with the time column ({dt:g} s)")
    pos = cols["pos_m"]
    vel_source = "vel_m_s column"
    if "vel_m_s" in trace.columns and np.all(np.isfinite(trace.columns["vel_m_s"])):
        vel = np.asarray(trace.columns["vel_m_s"], dtype=float)
    else:
        vel = estimate_velocity(pos, dt)
        vel_source = "Savitzky-Golay derivative of pos_m"
    length = max(20, int(round(WINDOW_S / dt)))
    if len(t) < 2 * length:
        raise ExplainError(f"{source}: cannot decide: {len(t) * dt:.3g} s of data, need several {WINDOW_S:g} s windows")
    # which side a lash rests on is decided by efforts above a quarter of the Coulomb level
    fc = 0.5 * (spec.params.get("fc_pos", 0.0) + spec.params.get("fc_neg", 0.0))
    side_threshold = 0.25 * fc if fc > 0 else 0.05 * float(np.max(np.abs(cols["effort"])))
    win = make_windows(pos, vel, cols["effort"], dt, length, side_threshold=side_threshold)
    span = np.ptp(win.measured, axis=1)
    moving = int(np.sum(span > MOVING_SPAN_M))
    if moving < MIN_MOVING_WINDOWS:
        raise ExplainError(f"{source}: cannot decide: the axis moves in only {moving} of {len(span)} windows of "
                           f"{WINDOW_S * 1e3:g} ms (need {MIN_MOVING_WINDOWS})")
    return Prepared(source, t, pos, vel, cols["effort"], dt, spec, win, vel_source, spec.effort_unit)


def estimate_velocity(pos: np.ndarray, dt: float) -> np.ndarray:
    """Velocity from quantised positions: a cubic Savitzky-Golay derivative over 15 samples.

    Why this one: 15 ms is short against the jerk-limited profile's acceleration phases (the cubic
    follows them without lag) and long enough to average the 76 nm counts to ~0.1 mm/s noise,
    whose effect on a 150 ms window start is ~ (v error) x window / 2, far below a um.
    """
    from scipy.signal import savgol_filter

    n = min(15, len(pos) - (1 - len(pos) % 2))
    if n < 5:
        return np.gradient(pos, dt)
    return savgol_filter(pos, n, 3, deriv=1, delta=dt, mode="interp")


# --------------------------------------------------------------------------------------------------
# Gap evaluation
# --------------------------------------------------------------------------------------------------


def candidate_specs(base: PlantSpec, effect: str, params: list[dict[str, float]]) -> list[PlantSpec]:
    return [base.with_effect(effect, **p) for p in params]


def _internal(prep: Prepared, plants: list[Plant]) -> tuple[np.ndarray, np.ndarray] | None:
    """Reconstructed internal state of a linear mode (resonance) at the window starts, else None.

    Only where body 0 carries no friction and the coupling has no dead zone is the relative motion
    linear and driven by measured quantities alone (tools/explain_sim.internal_state); backlash
    starts quasi-static with the screw against the side the effort pushes it to.
    """
    if not all(p.n_bodies == 2 and not p.gap and not p.design.bodies[0].has_coulomb
               and p.design.bodies[0].c_pos == 0 and p.design.bodies[0].c_neg == 0 for p in plants):
        return None
    table_acc = np.concatenate((np.diff(prep.vel) / prep.dt, [0.0]))
    return internal_state(plants, prep.applied, table_acc, prep.windows.start)


def gaps_of(prep: Prepared, specs: list[PlantSpec], substeps: int | None = None) -> np.ndarray:
    """The windowed gap of each plant, m."""
    plants = [s.build(prep.dt) for s in specs]
    sim = BatchSim(plants, substeps=substeps).run(prep.windows, _internal(prep, plants))
    return window_rms(sim, prep.windows)


def simulate_windows(prep: Prepared, spec: PlantSpec) -> np.ndarray:
    """Windowed simulation of one plant, (W, L)."""
    plants = [spec.build(prep.dt)]
    return BatchSim(plants).run(prep.windows, _internal(prep, plants))[:, 0, :]


# --------------------------------------------------------------------------------------------------
# Fitters: each returns (params, gap) with params named as in the vocabulary (+ extras such as phase)
# --------------------------------------------------------------------------------------------------


@dataclass
class Fit:
    effect: str
    params: dict[str, float]
    gap: float
    extra: dict[str, float] = field(default_factory=dict)  # parameters outside the vocabulary (phase)
    note: str = ""

    @property
    def n_params(self) -> int:
        return len(self.params) + len(self.extra)

    @property
    def all_params(self) -> dict[str, float]:
        return {**self.params, **self.extra}


def _scan(prep: Prepared, effect: str, grid: list[dict[str, float]], substeps: int | None = None) -> np.ndarray:
    return gaps_of(prep, candidate_specs(prep.spec, effect, grid), substeps)


def _fit_1d(prep: Prepared, effect: str, name: str, values: np.ndarray,
            fixed: dict[str, float] | None = None, log: bool = False, rounds: int = 2,
            lo: float | None = None, hi: float | None = None, coarse: int = COARSE_SUBSTEPS) -> Fit:
    """Grid, then finer grids around the best point (each grid simulated at once).

    The coarse rounds use ``coarse`` substeps per cycle (the gap changes by well under the noise
    floor, see COARSE_SUBSTEPS); the last round, whose gap is reported, uses the plant's own.
    """
    fixed = fixed or {}
    values = np.asarray(values, dtype=float)
    best_v, best_g = math.nan, math.inf
    for r in range(rounds + 1):
        sub = None if r == rounds else coarse
        gaps = _scan(prep, effect, [{**fixed, name: float(v)} for v in values], sub)
        i = int(np.argmin(gaps))
        if r == rounds:
            # only the last round's gaps are exact; it includes the best coarse point
            best_v, best_g = float(values[i]), float(gaps[i])
            break
        a = values[max(i - 1, 0)]
        b = values[min(i + 1, len(values) - 1)]
        if log:
            values = np.exp(np.linspace(math.log(a), math.log(b), 9))
        else:
            values = np.linspace(a, b, 9)
        if lo is not None:
            values = np.maximum(values, lo)
        if hi is not None:
            values = np.minimum(values, hi)
    return Fit(effect, {**fixed, name: best_v}, best_g)


def _fit_2d(prep: Prepared, effect: str, names: tuple[str, str], g1: np.ndarray, g2: np.ndarray,
            log: tuple[bool, bool], rounds: int = 2, coarse: int = COARSE_SUBSTEPS) -> Fit:
    """2-D grid, then 5 x 5 grids around the best point (coarse substeps but in the last round)."""
    best: tuple[float, float] = (math.nan, math.nan)
    best_g = math.inf
    a1, a2 = np.asarray(g1, float), np.asarray(g2, float)
    for r in range(rounds + 1):
        grid = [{names[0]: float(x), names[1]: float(y)} for x in a1 for y in a2]
        gaps = _scan(prep, effect, grid, None if r == rounds else coarse).reshape(len(a1), len(a2))
        i, j = np.unravel_index(int(np.argmin(gaps)), gaps.shape)
        if r == rounds:
            best, best_g = (float(a1[i]), float(a2[j])), float(gaps[i, j])
            break

        def around(arr: np.ndarray, k: int, is_log: bool) -> np.ndarray:
            lo_, hi_ = arr[max(k - 1, 0)], arr[min(k + 1, len(arr) - 1)]
            if is_log:
                return np.exp(np.linspace(math.log(lo_), math.log(hi_), 5))
            return np.linspace(lo_, hi_, 5)

        a1, a2 = around(a1, i, log[0]), around(a2, j, log[1])
    return Fit(effect, {names[0]: best[0], names[1]: best[1]}, best_g)


def fit_offset(prep: Prepared) -> Fit:
    top = max(20.0, 0.5 * float(np.max(np.abs(prep.effort))))
    return _fit_1d(prep, "offset", "force", np.linspace(-top, top, 25))


def fit_spring(prep: Prepared) -> Fit:
    qmax = max(float(np.max(np.abs(prep.pos))), 1e-3)
    top = max(float(np.max(np.abs(prep.effort))), 10.0) / qmax
    return _fit_1d(prep, "spring", "stiffness", np.linspace(0.0, top, 25), lo=0.0)


def fit_mass(prep: Prepared) -> Fit:
    m = prep.spec.nominal_mass
    return _fit_1d(prep, "mass", "mass", m * np.exp(np.linspace(math.log(0.4), math.log(2.5), 21)), log=True)


def fit_viscous(prep: Prepared) -> Fit:
    return _fit_1d(prep, "viscous", "scale", np.linspace(0.0, 3.0, 25), lo=0.0)


def fit_delay(prep: Prepared) -> Fit:
    return _fit_1d(prep, "delay", "delay", np.linspace(0.0, 10.0 * prep.dt, 26), lo=0.0, coarse=5)


def fit_saturation(prep: Prepared) -> Fit:
    # limits between the 10th percentile and the peak of the commanded |effort|, log-spaced: a clipped loop
    # winds up, so the peak command can be many times the limit
    mags = np.abs(prep.effort)
    peak = float(np.max(mags))
    fc = 0.5 * (prep.spec.params.get("fc_pos", 0.0) + prep.spec.params.get("fc_neg", 0.0))
    # down to half the Coulomb level (a drive clipped lower could not move the axis at all)
    low = max(min(float(np.percentile(mags, 10)), 0.5 * fc if fc > 0 else math.inf), 1e-4 * peak)
    fit = _fit_1d(prep, "saturation", "limit", np.exp(np.linspace(math.log(low), math.log(1.02 * peak), 81)),
                  log=True, lo=1e-6, rounds=4)
    fit.note = f"peak commanded effort {peak:.4g}"
    return fit


def fit_stribeck(prep: Prepared) -> Fit:
    fc = max(prep.spec.params.get("fc_pos", 1.0), prep.spec.params.get("fc_neg", 1.0))
    excess = np.linspace(0.05, 1.2, 9) * fc
    velocity = np.exp(np.linspace(math.log(2e-4), math.log(2e-2), 9))
    return _fit_2d(prep, "stribeck", ("excess_force", "velocity"), excess, velocity, (False, True))


def fit_backlash(prep: Prepared) -> Fit:
    return _fit_1d(prep, "backlash", "width", np.exp(np.linspace(math.log(1e-6), math.log(200e-6), 12)),
                   log=True, rounds=2, coarse=COARSE_SUBSTEPS_TWO_BODY)


def fit_resonance(prep: Prepared) -> Fit:
    nyq = 0.5 / prep.dt
    # a lightly damped mode has a sharp minimum in frequency: 12 % steps, then refined 5 x 5 twice
    freq = np.exp(np.arange(math.log(8.0), math.log(0.9 * nyq), math.log(1.12)))
    damping = np.array([0.02, 0.07, 0.25, 0.7])
    return _fit_2d(prep, "resonance", ("frequency", "damping"), freq, damping, (True, True), rounds=3, coarse=2)


def force_residual(prep: Prepared) -> tuple[np.ndarray, np.ndarray]:
    """One-step force residual of the nominal plant and the rows it is valid on.

    Each step j is simulated from the measured state (q_j, v_j) with the applied effort; the
    velocity the plant misses, divided by the plant's velocity gain per unit force, is the force
    the model lacks during that step. Valid only while the axis moves (a sticking model absorbs any
    force), so rows slower than 1 mm/s or with a reversal inside the step are dropped.
    """
    n = len(prep.pos)
    starts = np.arange(1, n - 1)
    win = make_windows(prep.pos, prep.vel, prep.effort, prep.dt, 1, history=2, starts=starts)
    plant = prep.spec.build(prep.dt)
    sim = BatchSim([plant])
    _, v_sim = sim.run_with_velocity(win)
    gain = prep.dt / prep.spec.nominal_mass
    r = np.full(n, np.nan)
    r[starts] = (prep.vel[starts + 1] - v_sim[:, 0, 0]) / gain
    v = prep.vel
    ok = np.zeros(n, dtype=bool)
    ok[starts] = (np.abs(v[starts]) > 1e-3) & (np.abs(v[starts + 1]) > 1e-3) & (np.sign(v[starts]) == np.sign(
        v[starts + 1]))
    return r, ok


def fit_periodic(prep: Prepared) -> Fit:
    """Period scan of the force residual against position, then a refinement on the gap."""
    r, ok = force_residual(prep)
    q, v = prep.pos[ok], prep.vel[ok]
    y = r[ok]
    if len(y) < 200:
        return Fit("periodic", {"amplitude": 0.0, "period": 0.01}, math.inf, {"phase": 0.0})
    # nuisance regressors: what other effects would leave in the residual (offset, Coulomb and viscous
    # per direction, spring, mass error through the acceleration)
    acc = np.gradient(prep.vel, prep.dt)[ok]
    pos_dir = (v > 0).astype(float)
    X0 = np.column_stack([np.ones_like(q), pos_dir, v, v * pos_dir, q - q.mean(), acc])
    beta, *_ = np.linalg.lstsq(X0, y, rcond=None)
    res = y - X0 @ beta
    span = float(np.ptp(q))
    kmin = 2 * math.pi / min(0.05, max(span, 1e-3))
    kmax = 2 * math.pi / 0.8e-3
    dk = 2 * math.pi / (6.0 * max(span, 1e-3))
    ks = np.arange(kmin, kmax, dk)
    power = np.empty(len(ks))
    for a in range(0, len(ks), 64):
        kk = ks[a:a + 64, None]
        ph = kk * q[None, :]
        s, c = np.sin(ph) @ res, np.cos(ph) @ res
        power[a:a + 64] = s * s + c * c
    best_k = float(ks[int(np.argmax(power))])
    # refine the wavenumber finely around the peak, with a proper 2-column least squares
    best = (0.0, best_k, 0.0, -math.inf)
    for k in np.linspace(best_k - dk, best_k + dk, 41):
        Xp = np.column_stack([X0, np.sin(k * q), np.cos(k * q)])
        coef, *_ = np.linalg.lstsq(Xp, y, rcond=None)
        rss = float(np.sum((y - Xp @ coef) ** 2))
        if -rss > best[3]:
            best = (float(coef[-2]), float(k), float(coef[-1]), -rss)
    a, k, b, _ = best
    amp = math.hypot(a, b)
    phase = math.atan2(b, a) % (2 * math.pi)
    period = 2 * math.pi / k
    # refine amplitude (the residual regression sees the force through the closed loop's noise)
    specs, grid = [], []
    for fa in (0.7, 0.85, 1.0, 1.15, 1.3):
        for dp in (-0.004, 0.0, 0.004):
            for dph in (-0.3, 0.0, 0.3):
                p = {"amplitude": amp * fa, "period": period * (1 + dp), "phase": (phase + dph) % (2 * math.pi)}
                grid.append(p)
                specs.append(prep.spec.with_effect("periodic", **p))
    gaps = gaps_of(prep, specs)
    i = int(np.argmin(gaps))
    p = grid[i]
    return Fit("periodic", {"amplitude": p["amplitude"], "period": p["period"]}, float(gaps[i]),
               {"phase": p["phase"]}, note=f"period scan peak at {period * 1e3:.3f} mm")


FITTERS: dict[str, Callable[[Prepared], Fit]] = {
    "offset": fit_offset,
    "spring": fit_spring,
    "mass": fit_mass,
    "viscous": fit_viscous,
    "delay": fit_delay,
    "saturation": fit_saturation,
    "stribeck": fit_stribeck,
    "periodic": fit_periodic,
    "backlash": fit_backlash,
    "resonance": fit_resonance,
}


# --------------------------------------------------------------------------------------------------
# The result
# --------------------------------------------------------------------------------------------------


@dataclass
class ExplainResult:
    effect: str
    params: dict[str, float]
    gap_before: float
    gap_after: float
    gap_metric: str
    report: str
    evidence: dict[str, Any]
    augmented: PlantSpec
    extra: dict[str, float] = field(default_factory=dict)
    files: list[Path] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        """Exactly the keys of the issue."""
        return {"effect": self.effect, "params": dict(self.params), "gap_before": float(self.gap_before),
                "gap_after": float(self.gap_after), "gap_metric": self.gap_metric}


def explain(trace: Trace, plant_spec: PlantSpec, *, out_dir: str | Path | None = None,
            source: str = "<trace>", stem: str = "explain") -> ExplainResult:
    """Name the effect the plant misses in ``trace``, fit it, and measure the gap before and after."""
    t_start = time.perf_counter()
    # a plant that already has two bodies: the two-body effects fail to build and are skipped
    prep = prepare(trace, plant_spec, source)
    gap0 = float(gaps_of(prep, [plant_spec])[0])
    fits: list[Fit] = []
    skipped: dict[str, str] = {}
    for name, fitter in FITTERS.items():
        try:
            fits.append(fitter(prep))
        except PlantError as exc:
            skipped[name] = str(exc)
    fits.sort(key=lambda f: _score(f, gap0))
    best = fits[0]
    shrink = 1.0 - best.gap / gap0 if gap0 > 0 else 0.0
    effect = best.effect if shrink >= NONE_SHRINK else "none"
    if effect == "saturation" and best.params["limit"] >= float(np.max(np.abs(prep.effort))):
        effect = "none"  # a limit above every command clips nothing: no evidence
    if effect == "none":
        augmented = plant_spec
        params: dict[str, float] = {}
        extra: dict[str, float] = {}
        gap1 = gap0
    else:
        params = {k: float(best.params[k]) for k in PARAM_NAMES[effect]}
        extra = dict(best.extra)
        augmented = plant_spec.with_effect(effect, **params, **extra)
        gap1 = float(gaps_of(prep, [augmented])[0])
    evidence = {
        "gap_before_m": gap0,
        "candidates": [{"effect": f.effect, "params": f.all_params, "gap_m": f.gap,
                        "shrink": 1.0 - f.gap / gap0 if gap0 > 0 else 0.0, "score": _score(f, gap0),
                        "note": f.note} for f in fits],
        "none_threshold": NONE_SHRINK,
        "param_penalty": PARAM_PENALTY,
        "windows": int(len(prep.windows.start)),
        "window_s": prep.windows.length * prep.dt,
        "velocity_from": prep.vel_source,
        "skipped": skipped,
        "seconds": time.perf_counter() - t_start,
    }
    evidence.update(_locate(prep, plant_spec, augmented if effect != "none" else None))
    result = ExplainResult(effect, params, gap0, gap1, GAP_METRIC, "", evidence, augmented, extra)
    result.report = format_report(result, prep)
    if out_dir is not None:
        result.files = write_outputs(result, prep, Path(out_dir), stem)
    return result


def _score(f: Fit, gap0: float) -> float:
    """Squared gap after, charged PARAM_PENALTY of the squared gap before per parameter."""
    return f.gap ** 2 + PARAM_PENALTY * f.n_params * gap0 ** 2


def _locate(prep: Prepared, nominal: PlantSpec, augmented: PlantSpec | None) -> dict[str, Any]:
    """Where the nominal model disagrees: the gap by speed, by direction, near reversals, by |effort|."""
    win = prep.windows
    sim = simulate_windows(prep, nominal)
    err = sim - win.measured
    rows = win.start[:, None] + np.arange(1, win.length + 1)[None, :]
    v = prep.vel[rows]
    u = np.abs(prep.applied[rows])
    vmax = float(np.max(np.abs(prep.vel))) or 1.0
    out: dict[str, Any] = {}

    def rms(mask: np.ndarray) -> float:
        return float(np.sqrt(np.mean(err[mask] ** 2))) if mask.any() else math.nan

    out["gap_by_speed_m"] = {
        "standstill": rms(np.abs(v) < 1e-4),
        "slow (<10% vmax)": rms((np.abs(v) >= 1e-4) & (np.abs(v) < 0.1 * vmax)),
        "fast (>=10% vmax)": rms(np.abs(v) >= 0.1 * vmax),
    }
    out["gap_by_direction_m"] = {"+": rms(v > 1e-4), "-": rms(v < -1e-4)}
    rev = np.zeros_like(v, dtype=bool)
    sgn = np.sign(prep.vel)
    flips = np.flatnonzero((sgn[1:] * sgn[:-1] < 0) | ((sgn[1:] != 0) & (sgn[:-1] == 0))) + 1
    near = np.zeros(len(prep.vel), dtype=bool)
    span = int(round(0.05 / prep.dt))
    for k in flips:
        near[max(0, k - span):k + span] = True
    rev = near[rows]
    out["gap_near_starts_and_reversals_m"] = rms(rev)
    out["gap_elsewhere_m"] = rms(~rev)
    out["gap_at_high_effort_m"] = rms(u > 0.8 * float(np.max(u)))
    if augmented is not None:
        err1 = simulate_windows(prep, augmented) - win.measured
        per0 = np.sqrt(np.mean(err ** 2, axis=1))
        per1 = np.sqrt(np.mean(err1 ** 2, axis=1))
        out["windows_improved"] = int(np.sum(per1 < 0.8 * per0))
        out["windows_worse"] = int(np.sum(per1 > 1.25 * per0))
    return out


# --------------------------------------------------------------------------------------------------
# Report, plot, files
# --------------------------------------------------------------------------------------------------

SIGNATURES = {
    "none": "the nominal plant already explains the data: no effect shrinks the gap beyond the noise floor",
    "stribeck": "extra friction at low speed: the axis breaks away later and decelerates harder near standstill",
    "backlash": "lost motion when the force reverses: the table stands while the screw crosses the gap",
    "periodic": "a force that repeats with position (lead error, runout): the residual is a sine of q",
    "mass": "the residual follows the acceleration: the moving mass differs from the model's",
    "viscous": "the residual grows with speed: the viscous friction differs from the model's",
    "delay": "the measured motion lags the effort: the drive applies it later than the transport delay",
    "offset": "a constant force: the residual has one sign in both directions of motion",
    "spring": "a force proportional to position: the residual grows with q",
    "resonance": "the table follows the force through a lightly damped mode: ringing at one frequency",
    "saturation": "the acceleration stops following the command when |effort| is large: the drive clips it",
}

UNITS = {"excess_force": "effort", "velocity": "m/s", "width": "m", "amplitude": "effort", "period": "m",
         "mass": "kg", "scale": "", "delay": "s", "force": "effort", "stiffness": "effort/m", "frequency": "Hz",
         "damping": "", "limit": "effort", "phase": "rad"}


def format_report(res: ExplainResult, prep: Prepared) -> str:
    ev = res.evidence
    unit = prep.effort_unit
    lines = [f"explain {prep.source} against plant {prep.spec.name}", ""]
    lines.append(f"effect: {res.effect}")
    lines.append(f"  {SIGNATURES[res.effect]}")
    for k, val in {**res.params, **res.extra}.items():
        u = UNITS.get(k, "").replace("effort", unit)
        lines.append(f"  {k} = {val:.6g} {u}".rstrip())
    shrink = 1 - res.gap_after / res.gap_before if res.gap_before > 0 else 0.0
    lines.append("")
    lines.append(f"gap before: {res.gap_before * 1e6:.3f} um   after: {res.gap_after * 1e6:.3f} um   "
                 f"(shrink {100 * shrink:.1f} %)")
    lines.append(f"gap metric: {res.gap_metric}")
    lines.append(f"  {ev['windows']} windows of {ev['window_s'] * 1e3:.0f} ms; "
                 f"start velocity from {ev['velocity_from']}")
    lines.append("")
    lines.append("where the nominal model disagrees (RMS position error of the windows, um):")
    for k, val in ev["gap_by_speed_m"].items():
        lines.append(f"  speed {k:<18} {val * 1e6:9.3f}")
    for k, val in ev["gap_by_direction_m"].items():
        lines.append(f"  moving {k:<17} {val * 1e6:9.3f}")
    lines.append(f"  near starts/reversals    {ev['gap_near_starts_and_reversals_m'] * 1e6:9.3f}")
    lines.append(f"  elsewhere                {ev['gap_elsewhere_m'] * 1e6:9.3f}")
    lines.append(f"  at |effort| > 80 % peak  {ev['gap_at_high_effort_m'] * 1e6:9.3f}")
    if "windows_improved" in ev:
        lines.append(f"  windows improved by the fit: {ev['windows_improved']}, made worse: {ev['windows_worse']}")
    lines.append("")
    lines.append(f"candidates (named if shrink >= {100 * NONE_SHRINK:.0f} % after a penalty of "
                 f"{100 * PARAM_PENALTY:.0f} % of the squared gap per parameter):")
    for c in ev["candidates"]:
        ps = ", ".join(f"{k}={v:.4g}" for k, v in c["params"].items())
        lines.append(f"  {c['effect']:<11} gap {c['gap_m'] * 1e6:9.3f} um  shrink {100 * c['shrink']:6.1f} %  ({ps})")
    if res.effect != "none":
        runner = next((c for c in ev["candidates"][1:]), None)
        if runner is not None:
            lines.append(f"  runner-up {runner['effect']} leaves {runner['gap_m'] * 1e6:.3f} um against "
                         f"{ev['candidates'][0]['gap_m'] * 1e6:.3f} um")
    for name, why in ev["skipped"].items():
        lines.append(f"  {name}: not tried ({why})")
    return "\n".join(lines) + "\n"


def stitched(prep: Prepared, sim: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows and values of a windowed simulation laid end to end, for plotting."""
    win = prep.windows
    rows = (win.start[:, None] + np.arange(1, win.length + 1)[None, :]).ravel()
    return rows, sim.ravel()


def write_outputs(res: ExplainResult, prep: Prepared, out: Path, stem: str) -> list[Path]:
    from drivectl.tools.trace import atomic_write_text

    out.mkdir(parents=True, exist_ok=True)
    files = []
    toml_path = out / f"{stem}.plant.toml"
    comment = (f"augmented by drivectl explain from {prep.source}\n"
               f"effect {res.effect}; gap {res.gap_before * 1e6:.3f} um -> {res.gap_after * 1e6:.3f} um")
    atomic_write_text(toml_path, res.augmented.to_toml(comment=comment))
    files.append(toml_path)
    rep = out / f"{stem}.report.txt"
    atomic_write_text(rep, res.report)
    files.append(rep)
    files.append(plot_explain(res, prep, out / f"{stem}.png"))
    return files


def plot_explain(res: ExplainResult, prep: Prepared, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sim0 = simulate_windows(prep, prep.spec)
    rows, s0 = stitched(prep, sim0)
    fig, axes = plt.subplots(3, 1, figsize=(10, 10))
    ax = axes[0]
    t = prep.t
    ax.plot(t, prep.pos * 1e3, "k-", lw=1.0, label="measured")
    ax.plot(t[rows], s0 * 1e3, ".", ms=1.0, color="tab:red", label="nominal (windowed)")
    e0 = (s0 - prep.pos[rows]) * 1e6
    if res.effect != "none":
        _, s1 = stitched(prep, simulate_windows(prep, res.augmented))
        ax.plot(t[rows], s1 * 1e3, ".", ms=1.0, color="tab:green", label=f"with {res.effect}")
        e1 = (s1 - prep.pos[rows]) * 1e6
    else:
        e1 = None
    ax.set_xlabel("time (s)")
    ax.set_ylabel("position (mm)")
    ax.set_title(f"explain: {res.effect}; gap {res.gap_before * 1e6:.2f} -> {res.gap_after * 1e6:.2f} um")
    ax.legend(loc="best", markerscale=8)
    for ax, x, label in ((axes[1], prep.vel[rows] * 1e3, "velocity (mm/s)"),
                         (axes[2], prep.pos[rows] * 1e3, "position (mm)")):
        ax.plot(x, e0, ".", ms=1.0, color="tab:red", label="nominal")
        if e1 is not None:
            ax.plot(x, e1, ".", ms=1.0, color="tab:green", label=f"with {res.effect}")
        ax.set_xlabel(label)
        ax.set_ylabel("sim - measured (um)")
        ax.legend(loc="best", markerscale=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


# --------------------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------------------


def add_explain_parser(subparsers: Any) -> argparse.ArgumentParser:
    """``drivectl explain TRACE.csv --plant NAME|FILE [--json] [--out DIR]``."""
    p = subparsers.add_parser(
        "explain", help="name what the plant model is missing in a trace, fit it, show the gap shrink",
        description="Hold a recorded trace (format v1) against a plant, name the missing effect (none, stribeck, "
        "backlash, periodic, mass, viscous, delay, offset, spring, resonance, saturation), fit it, write the "
        "augmented plant TOML, a report and a PNG, and print the gap before and after.")
    p.add_argument("trace", metavar="TRACE.csv")
    p.add_argument("--plant", required=True, metavar="NAME|FILE", help="the model: built-in plant or plant TOML")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")
    p.add_argument("--out", metavar="DIR", help="folder for STEM.plant.toml, STEM.report.txt, STEM.png "
                   "(default: beside the trace)")
    p.add_argument("--write-config", nargs="?", const="", metavar="FILE",
                   help="also point axes.AXIS.plant (AXIS: the trace's) at the augmented plant in FILE (default: "
                   "the --config in use), comments kept, the old file backed up as FILE.STAMP.bak")
    return p


def cmd_explain(args: argparse.Namespace) -> int:
    """Exit 0 with a result (``none`` included); 2 with one line on stderr for bad input."""
    from drivectl.tools.config import ConfigError

    path = Path(args.trace)
    try:
        spec = load_plant(args.plant)
        if getattr(args, "write_config", None) is not None:  # before the work
            from drivectl.tools.config_io import target_file

            args.write_config = str(target_file(args.write_config, getattr(args, "config", None)))
        trace = Trace.read(path)
        out = Path(args.out) if args.out else path.parent
        res = explain(trace, spec, out_dir=out, source=str(path), stem=path.stem + ".explain")
    except (ExplainError, TraceError, PlantError, ConfigError) as exc:
        print(f"drivectl: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(res.to_json()))
    else:
        print(res.report, end="")
        for f in res.files:
            print(f"wrote {f}")
    if getattr(args, "write_config", None) is not None:  # tools/config_io.py
        from drivectl.tools.config_io import merge_into, target_file

        axis = trace.meta.get("axis", "")
        plant = next((f for f in res.files if str(f).endswith(".plant.toml")), None)
        try:
            if plant is None:
                raise ConfigError("--write-config: no augmented plant was written to merge")
            target = target_file(args.write_config, getattr(args, "config", None))
            backup = merge_into(target, axis, {"plant": str(Path(plant).resolve())})
        except ConfigError as exc:
            print(f"drivectl: {exc}", file=sys.stderr)
            return 2
        if not args.json:
            print(f"merged axes.{axis}.plant into {target}" + (f" (old file kept as {backup})" if backup else ""))
    return 0

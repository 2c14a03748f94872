"""`drivectl explain`: name what the model is missing, add it, and show the gap shrink.

A recorded trace (format v1; the four required columns suffice) is held against a plant:

1. the gap (tools/explain/data.py): a windowed simulation error, each ~150 ms window started from
   the measured state and driven open loop by the recorded effort; untrustworthy window starts left
   out; the data's own floor estimated from the trace;
2. candidates (tools/explain/fit.py): every effect of the vocabulary (docs/effects.md) fitted on that
   same gap on top of the current model, all candidates of a grid simulated at once
   (tools/explain/sim.py);
3. effects one after another: the strongest first, then, with it in the model, the next, refitting
   all named ones together, for as long as the next one's gain is significant against the floor
   (robust over windows: no single window decides; more windows improved than worsened);
4. what is left (tools/explain/report.py): the report (ending with what remains unexplained against
   the floor), a PNG, and the augmented plant TOML (loadable as a plant or a model).

Method and calibration: docs/explain.md. Library: :func:`explain` (trace, plant spec) ->
:class:`ExplainResult`. CLI: :func:`add_explain_parser` and :func:`cmd_explain`.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import threading
import time
from collections.abc import Iterable
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from drivectl.plant_emulator.models import PlantError, PlantSpec, load_plant
from drivectl.tools.cli.exits import exits_on_error
from drivectl.tools.explain.data import (  # noqa: F401  (re-exported: the library's names)
    GAP_METRIC,
    ExplainError,
    Prepared,
    gaps_of,
    noise_floor,
    prepare,
    simulate_windows,
    window_errors,
    window_mse,
)
from drivectl.tools.explain.fit import (
    FITTERS,
    OPTIONAL_PARAMS,
    PARAM_NAMES,
    SPLITTING,
    Fit,
    batch_groups,
    refine_jointly,
    run_fitter,
)
from drivectl.tools.explain.report import format_report, locate, write_outputs
from drivectl.tracefile.format import Trace

#: ranking: penalty per parameter on the squared gap (an information-criterion style charge: among
#: candidates, one with one more free parameter must explain that much more of the squared gap to be
#: preferred; calibrated on the single-effect set, docs/explain.md)
PARAM_PENALTY = 0.04
#: naming: the best candidate is named when its robust gain in squared gap, less PARAM_CHARGE
#: squared floors per parameter (what fitting noise buys), is at least MARGIN squared floors
MARGIN = 1.0
PARAM_CHARGE = 0.25
#: ... and it improves at least this many windows
MIN_IMPROVED = 3
#: a window counts as improved (worsened) when its RMS error falls below 0.9x (rises above 1.1x)
WINDOW_CHANGE = 0.10
#: no single window decides: the windows with the largest gains count in the robust gain only as much as
#: the next largest (winsorised, not left out: an effect that shows at a few starts or reversals, a faint
#: stribeck or a lash, keeps its gain, while one window's transient no longer decides)
TOP_WINDOWS_CAPPED = 2
#: a mode damped at least this much has no resonant peak to speak of (1.0002 at 0.7; none from 1/sqrt 2):
#: it lags, it does not ring. 0.7 is also the resonance grid's top damping: a fit there asked for at least that
OVERDAMPED = 0.7
#: the most effects named in one trace
MAX_EFFECTS = 4
#: before stopping, the floor is also read with each of this many next effects on top of the best (the
#: one-mass ones: the splitting ones cost half a round)
LOOKAHEAD = 8
#: a named effect is tried against at most this many simpler candidates (fewer parameters) at the end
SIMPLER_TRIES = 2
#: after a round, at most this many of its best other candidates are fitted again
NEXT_CANDIDATES = len(FITTERS)
#: the two-body candidates that gained nothing in a round are fitted again in the next only when the
#: effect just named could have masked them: it took the gap down to this share or less (a 2.5 mm periodic
#: force hid a 66 Hz mode: 50 -> 9 um; docs/explain.md)
RETRY_GAP_FALL = 0.5
#: a fitter that refines an effect already named by a simpler fitter (key -> the key it refines), tried in
#: the later rounds in its place: while the gap is large the ranking's charge per parameter is too, so a
#: direction dependence is first named as plain viscous and shows only once the rest is explained
#: (EMPS, viscous x 0.6: plain viscous, 73.7 um left, where c+/c- and the offset leave 37.5; docs/explain.md)
REFINES = {"viscous+-": "viscous"}


@dataclass
class ExplainResult:
    """``effect``/``params`` the first named effect (``none``/{} without one), ``effects`` all of them in
    order with their parameters and the gap after each; ``gap_before`` the nominal plant's,
    ``gap_after`` the whole augmented model's."""

    effect: str
    params: dict[str, float]
    gap_before: float
    gap_after: float
    gap_metric: str
    report: str
    evidence: dict[str, Any]
    augmented: PlantSpec
    extra: dict[str, float] = field(default_factory=dict)
    effects: list[dict[str, Any]] = field(default_factory=list)
    floor: float = math.nan
    files: list[Path] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        """The issue's keys: effect, params, gap_before, gap_after, gap_metric, effects."""
        return {"effect": self.effect, "params": dict(self.params), "gap_before": float(self.gap_before),
                "gap_after": float(self.gap_after), "gap_metric": self.gap_metric,
                "effects": [{"effect": e["effect"], "params": dict(e["params"]), "gap_after": float(e["gap_after"])}
                            for e in self.effects]}


# --------------------------------------------------------------------------------------------------
# Threads, processes, progress
# --------------------------------------------------------------------------------------------------


@contextmanager
def _one_blas_thread() -> Any:
    """The fits are many small matrix operations: BLAS threads only contend (a 10 s trace took 13-61 s
    with default threading on a loaded 2-core machine, 4 s CPU with one thread). threadpoolctl is a
    declared dependency and imported plainly: a silent fallback once hid a 4x slowdown."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):
        yield


def choose_workers() -> int:
    """Processes for the independent fits: the cores that are free (DRIVECTL_EXPLAIN_WORKERS overrides).

    One core for this process and each core that is at least half free (cores minus the 1-minute load):
    under one other CPU-bound job on two cores (load ~1) two processes share the cores with it, which
    measured faster than one (bench/explain_speed.py); one process when other threads run in this
    process (a fork would copy their locks) or when nothing is free.
    """
    env = os.environ.get("DRIVECTL_EXPLAIN_WORKERS", "").strip()
    if env:
        try:
            return max(1, int(env))
        except ValueError:
            raise ExplainError(f"DRIVECTL_EXPLAIN_WORKERS: expected an integer, got {env!r}") from None
    if threading.active_count() > 1 or not hasattr(os, "fork"):
        return 1
    return free_cores()


def free_cores() -> int:
    """One core for this process and each core that is at least half free (cores minus the 1-minute load),
    at least 1 (choose_workers; drivectl health's embedded Dask cluster, whose workers are spawned, not
    forked)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    try:
        load = os.getloadavg()[0]
    except OSError:
        load = float(cores)
    return int(max(1, min(cores, math.floor(cores - load + 1.5))))


def _worker_init() -> None:
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1)


#: the expensive fitters first, so that a pool ends together
COST_ORDER = ("resonance", "backlash", "stribeck", "coulomb", "viscous+-", "saturation", "periodic", "delay")


def _warm_imports(plot: bool) -> None:
    """What the main process will import later anyway (the plot), imported while the workers fit: the main
    process would only wait for them. (Not scipy.signal: nothing on explain's path needs it, and it costs
    ~1 s; tools/explain/savgol.py, explain_sim.internal_state.)"""
    if plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot  # noqa: F401


def _run_fits(keys: list[str], prep: Prepared, pool: Any, bar: Any,
              warm: Any = None) -> tuple[list[Fit], dict[str, str]]:
    keys = sorted(keys, key=lambda k: COST_ORDER.index(k) if k in COST_ORDER else len(COST_ORDER))
    fits: list[Fit] = []
    failed: dict[str, str] = {}

    def done(key: str, fit: Fit | None, exc: Exception | None) -> None:
        if fit is not None and math.isfinite(fit.gap):
            fits.append(fit)
        elif exc is not None:
            failed[key] = str(exc)
        if bar is not None:
            bar.update(1)

    if pool is None:
        for key in keys:
            try:
                done(key, run_fitter(key, prep), None)
            except PlantError as exc:
                done(key, None, exc)
    else:
        futures = {key: pool.submit(run_fitter, key, prep) for key in keys}
        if warm is not None:
            warm()
        for key, fut in futures.items():
            try:
                done(key, fut.result(), None)
            except PlantError as exc:
                done(key, None, exc)
    fits.sort(key=lambda f: list(FITTERS).index(f.key))
    return fits, failed


# --------------------------------------------------------------------------------------------------
# Deciding
# --------------------------------------------------------------------------------------------------


def _build(nominal: PlantSpec, fits: Iterable[Fit]) -> PlantSpec:
    spec = nominal
    for f in fits:
        spec = f.add_to(spec)
    return spec


def _window_stats(cur: np.ndarray, new: np.ndarray) -> dict[str, float]:
    """Robust gain in squared gap of ``new`` over ``cur`` (per-window MSE, (W,)) and window counts."""
    d = cur - new
    desc = np.sort(d)[::-1]
    k = min(TOP_WINDOWS_CAPPED, len(d) - 1)
    excess = np.clip(desc[:k] - max(float(desc[k]), 0.0), 0.0, None)
    robust = (float(np.sum(d)) - float(np.sum(excess))) / len(d)
    lo, hi = (1 - WINDOW_CHANGE) ** 2, (1 + WINDOW_CHANGE) ** 2
    return {"gain": float(np.mean(d)), "robust_gain": robust,
            "improved": int(np.sum(new < lo * cur)), "worse": int(np.sum(new > hi * cur))}


def _mse_of(prep: Prepared, specs: list[PlantSpec]) -> tuple[np.ndarray, np.ndarray]:
    """Per-window MSE and rough part (W, C) of plants that may differ in body count (simulated in groups)."""
    out = np.empty((len(prep.windows.start), len(specs)))
    rough = np.empty_like(out)
    for idx in batch_groups(specs):
        out[:, idx], rough[:, idx] = window_errors(prep, [specs[i] for i in idx])
    return out, rough


def explain(trace: Trace, plant_spec: PlantSpec, *, out_dir: str | Path | None = None,
            source: str = "<trace>", stem: str = "explain", progress: bool = False,
            workers: int | None = None) -> ExplainResult:
    """Name the effects the plant misses in ``trace``, fit them, and measure the gap before and after."""
    with _one_blas_thread():
        return _explain(trace, plant_spec, out_dir, source, stem, progress, workers)


def _explain(trace: Trace, nominal: PlantSpec, out_dir: str | Path | None, source: str, stem: str,
             progress: bool, workers: int | None) -> ExplainResult:
    t_start = time.perf_counter()
    cpu_start = _cpu_seconds()
    prep = prepare(trace, nominal, source)
    two_body = len(nominal.design().bodies) == 2
    refused = {k: "needs a one-mass plant (this plant already has two bodies)" for k in SPLITTING if two_body}
    keys = [k for k in FITTERS if k not in refused]
    n_workers = choose_workers() if workers is None else max(1, int(workers))
    pool = None
    if n_workers > 1:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        pool = ProcessPoolExecutor(n_workers, mp_context=multiprocessing.get_context("fork"),
                                   initializer=_worker_init)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(keys), desc="explain: fits", unit="fit", delay=2.0, file=sys.stderr, leave=False)
    try:
        mse_all, rough = window_errors(prep, [nominal])
        mse_cur = mse_all[:, 0]
        gap0 = math.sqrt(float(np.mean(mse_cur)))
        floor = _floor_of(prep, mse_cur, rough[:, 0])
        named: list[Fit] = []
        current = nominal
        rounds: list[dict[str, Any]] = []
        failed_all: dict[str, str] = {}
        first_rank: list[str] = []
        gap_at: dict[str, float] = {}  # fitter key -> the gap of the effects up to it, fitted jointly
        prefix_gaps: dict[tuple[str, ...], float] = {}  # the named keys after a round -> that model's gap
        for r in range(MAX_EFFECTS):
            if r == 0:
                round_keys = keys
            else:
                have = {f.effect for f in named}
                round_keys = [k for k in first_rank if run_effect(k) not in have
                              or _refined(k, named) is not None][:NEXT_CANDIDATES]
                # a mode or lash masked in round 1 by a stronger effect (a periodic force) shows only once
                # that one is in: the splitting ones are tried again, at their cost (half a round), when
                # the effect just named took most of the gap (one that took less could not hide them)
                if math.sqrt(float(np.mean(mse_cur))) <= RETRY_GAP_FALL * rounds[-1]["gap_m"]:
                    round_keys += [k for k in keys if k in SPLITTING and k not in round_keys
                                   and run_effect(k) not in have]
                if bar is not None:
                    bar.total += len(round_keys)
                    bar.refresh()
            if not round_keys:
                break
            warm = (lambda: _warm_imports(out_dir is not None)) if r == 0 else None
            fits, failed = _run_fits(round_keys, prep.on(current), pool, bar, warm)
            failed_all.update(failed)
            if not fits:
                break
            gap_cur = math.sqrt(float(np.mean(mse_cur)))
            mses, rough = _mse_of(prep, [f.add_to(current) for f in fits])
            # the floor is the least over every model tried: an effect left out raises a model's rough part
            floor = min(floor, *(_floor_of(prep, mses[:, i], rough[:, i]) for i in range(len(fits))))
            cands = []
            for i, f in enumerate(fits):
                st = _window_stats(mse_cur, mses[:, i])
                charge = PARAM_PENALTY * f.n_params * gap_cur ** 2
                cands.append((st["robust_gain"] - charge, f, st))
            cands.sort(key=lambda c: -c[0])
            lag_note = _overdamped_after_delay(cands, floor)
            if r == 0:
                alone = [(f, st) for _, f, st in cands]  # every candidate on the nominal plant, by score
            # the next round refits the other candidates; the two-body ones (half the cost of a round)
            # only when they showed a clear gain in this one. An effect that gains nothing alone can
            # still be needed once another is in (a constant force against direction-dependent friction)
            first_rank = [c[1].key for c in cands if c[1] is not cands[0][1] and (
                c[1].key not in SPLITTING or c[2]["robust_gain"] > 0.5 * floor ** 2)]
            score, best, st = cands[0]
            decision = ""
            ok = True
            if best.effect == "saturation" and best.params["limit"] >= float(np.max(np.abs(prep.effort))):
                ok, decision = False, "the best, saturation, clips nothing (limit above every command): no evidence"
            j = _refined(best.key, named)
            trial = named + [best] if j is None else [*named[:j], _merge_refined(named[j], best), *named[j + 1:]]
            if ok:
                # all named parameters refitted together (the first alone: a finer optimum than its grid),
                # so that the next round's gain is the new effect's, not a better fit of the old ones
                trial = refine_jointly(prep, nominal, trial)
            spec_trial = _build(nominal, trial)
            mse_t, rough_t = _mse_of(prep, [spec_trial])
            mse_trial = mse_t[:, 0]
            floor = min(floor, _floor_of(prep, mse_trial, rough_t[:, 0]))
            st_trial = _window_stats(mse_cur, mse_trial)
            if ok and st_trial["robust_gain"] - PARAM_CHARGE * best.n_params * floor ** 2 < MARGIN * floor ** 2:
                # two effects can mask each other: each leaves the other's in-window structure in every
                # window, which the floor (read from that rough part) takes for noise. One more model is
                # tried for the floor before stopping: the best with the next effect, refitted together
                lower = _floor_with_next(prep, nominal, trial, cands, floor, st_trial, pool)
                if lower < floor:
                    rounds_note = f"floor {floor * 1e6:.2f} -> {lower * 1e6:.2f} um with the next effect in"
                    floor = lower
                else:
                    rounds_note = ""
            else:
                rounds_note = ""
            charge = PARAM_CHARGE * best.n_params * floor ** 2
            net = st_trial["robust_gain"] - charge
            if ok:
                if net < MARGIN * floor ** 2:
                    ok = False
                    decision = (f"stop: the best, {best.key}, gains {st_trial['robust_gain'] / floor ** 2:.2f} "
                                f"floor^2, {net / floor ** 2:.2f} after its parameter charge (needs {MARGIN:g})")
                elif st_trial["improved"] < MIN_IMPROVED:
                    ok = False
                    decision = (f"stop: the best, {best.key}, improves only {st_trial['improved']} windows "
                                f"(needs {MIN_IMPROVED})")
                else:
                    what = f"named {best.effect}" if j is None else f"{named[j].key} refined to {best.key}"
                    decision = (f"{what}: gain {st_trial['robust_gain'] / floor ** 2:.2f} floor^2, "
                                f"{net / floor ** 2:.2f} after its parameter charge; {st_trial['improved']} windows "
                                f"better, {st_trial['worse']} worse")
            if lag_note:
                rounds_note = f"{lag_note}; {rounds_note}" if rounds_note else lag_note
            if rounds_note:
                decision += f" ({rounds_note})"
            rounds.append({
                "model": [f.effect for f in named], "gap_m": gap_cur, "decision": decision,
                "candidates": [{"effect": f.effect, "key": f.key, "params": f.all_params, "gap_m": f.gap,
                                "shrink": 1.0 - f.gap / gap_cur if gap_cur > 0 else 0.0,
                                "robust_gain_floor2": s["robust_gain"] / floor ** 2 if floor > 0 else math.inf,
                                "improved": s["improved"], "worse": s["worse"], "score": sc, "note": f.note}
                               for sc, f, s in cands],
            })
            if not ok:
                break
            # an effect the joint refit no longer needs (its gain gone, e.g. a lash width driven to nothing) is dropped
            named, current, mse_cur = _prune(prep, nominal, trial, mse_trial, floor)
            prefix_gaps[tuple(f.key for f in named)] = math.sqrt(float(np.mean(mse_cur)))
            if len(named) < len(trial):
                kept = {f.key for f in named}  # (the kept ones are refitted: new objects, same keys)
                rounds[-1]["decision"] += "; dropped after the joint refit: " + ", ".join(
                    f.effect for f in trial if f.key not in kept) + " (the others refitted without it)"
        if named:
            named, current, mse_cur, swaps = _simplify(prep, nominal, named, mse_cur, floor, alone)
            gap_at = _prefix_gaps(prep, nominal, named, mse_cur, prefix_gaps)
            for old_fit, new_fit in swaps:
                if new_fit is None:
                    rounds[-1]["decision"] += (f"; then {old_fit.key} dropped: the others refitted without it "
                                               f"explain as much within the floor")
                else:
                    rounds[-1]["decision"] += (f"; then {old_fit.key} replaced by the simpler {new_fit.key} "
                                               f"(as good within the floor)")
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
        if bar is not None:
            bar.close()
    gap1 = math.sqrt(float(np.mean(mse_cur)))
    effects = []
    for f in named:
        g = gap_at[f.key]
        params = {k: float(f.params[k]) for k in (*PARAM_NAMES[f.effect], *OPTIONAL_PARAMS[f.effect])
                  if k in f.params}
        effects.append({"effect": f.effect, "params": params, "gap_after": g, "extra": dict(f.extra), "key": f.key})
    first = effects[0] if effects else None
    evidence: dict[str, Any] = {
        "gap_before_m": gap0,
        "floor_m": floor,
        "margin": MARGIN,
        "param_penalty": PARAM_PENALTY,
        "param_charge": PARAM_CHARGE,
        "rounds": rounds,
        "candidates": rounds[0]["candidates"] if rounds else [],
        "windows": int(len(prep.windows.start)),
        "windows_dropped": dict(prep.dropped or {}),
        "window_s": prep.windows.length * prep.dt,
        "velocity_from": prep.vel_source,
        "transport_delay_cycles": prep.transport,
        "encoder_m_per_count": prep.resolution,
        "refused": refused,
        "skipped": {**refused, **failed_all},
        "workers": n_workers,
    }
    evidence.update(locate(prep, nominal))
    if named:
        st = _window_stats(window_mse(prep, [nominal])[:, 0], mse_cur)
        evidence["windows_improved"], evidence["windows_worse"] = st["improved"], st["worse"]
    result = ExplainResult(first["effect"] if first else "none", dict(first["params"]) if first else {},
                           gap0, gap1, GAP_METRIC, "", evidence, current,
                           dict(first["extra"]) if first else {}, effects, floor)
    result.report = format_report(result, prep)
    if out_dir is not None:
        result.files = write_outputs(result, prep.on(nominal), Path(out_dir), stem)
    evidence["seconds"] = time.perf_counter() - t_start
    evidence["cpu_seconds"] = _cpu_seconds() - cpu_start
    return result


def _cpu_seconds() -> float:
    """CPU time of this process and of its finished children (the worker processes)."""
    import resource

    ch = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + ch.ru_utime + ch.ru_stime


def run_effect(key: str) -> str:
    """The effect a fitter key adds (``viscous+-`` adds ``viscous``)."""
    return key.rstrip("+-")


def _prefix_gaps(prep: Prepared, nominal: PlantSpec, named: list[Fit], mse: np.ndarray,
                 seen: dict[tuple[str, ...], float]) -> dict[str, float]:
    """The gap after each named effect: of the effects up to it, fitted jointly (the whole model's for the
    last). A later joint refit moves the earlier effects' parameters (the EMPS record's c+/c- settle beside
    the offset named after them: with that offset left out they leave 144 um where the nominal plant left
    74), so the final parameters of a prefix say nothing about what it explains. A prefix the rounds
    already fitted jointly keeps that round's gap; one they did not (after a refinement or a
    simplification) is refitted; the better of that and the final parameters counts."""
    out = {named[-1].key: math.sqrt(float(np.mean(mse)))}
    for j in range(len(named) - 1):
        prefix = named[:j + 1]
        keys = tuple(f.key for f in prefix)
        if keys in seen:
            out[prefix[-1].key] = seen[keys]
            continue
        candidates = [prefix, refine_jointly(prep, nominal, prefix)]
        out[prefix[-1].key] = float(np.min(_gaps_grouped_of(prep, nominal, candidates)))
    return out


def _overdamped_after_delay(cands: list[tuple[float, Fit, dict[str, float]]], floor: float) -> str:
    """Put `delay`, when it is significant too, before a best `resonance` damped at OVERDAMPED or more
    (in place).

    Such a mode has no resonant peak: its response lags the force but does not ring, the signature of
    a delay, and fitted first it absorbs the delay and stands in for it (a 0.9 ms delay + 120 Hz mode
    was named as one 72 Hz mode at damping 0.7-1.0). Behind the delay, the mode is fitted again in the
    next round on top of it. Returns a note for the report ("" when nothing moved).
    """
    best = cands[0][1]
    if best.key != "resonance" or best.params.get("damping", 0.0) < OVERDAMPED:
        return ""
    need = (MARGIN + PARAM_CHARGE) * floor ** 2  # the naming rule for one parameter
    j = next((i for i, c in enumerate(cands) if c[1].key == "delay" and c[2]["robust_gain"] >= need), None)
    if j is None:
        return ""
    cands.insert(0, cands.pop(j))  # the lag's own effect takes the mode's place
    return (f"resonance at damping {best.params['damping']:.2f} (>= {OVERDAMPED:g}: no resonant peak, a lag) "
            f"ranked after delay")


def _refined(key: str, named: list[Fit]) -> int | None:
    """The index of the named fit that fitter ``key`` refines (REFINES), or None."""
    base = REFINES.get(key)
    return next((i for i, f in enumerate(named) if f.key == base), None)


def _merge_refined(old: Fit, new: Fit) -> Fit:
    """The refined fit, fitted on top of ``old`` (viscous scales multiply), as one fit of the effect."""
    s = old.params["scale"]
    params = {"scale": s * new.params["scale"], "scale_neg": s * new.params.get("scale_neg", new.params["scale"])}
    return Fit(old.effect, params, new.gap, dict(new.extra), new.note, new.key)


def _floor_of(prep: Prepared, mse: np.ndarray, rough: np.ndarray) -> float:
    """The floor read from one model: its rough part's estimate (explain_data.noise_floor), and never more
    than that model's own gap (the noise cannot leave more than the whole error; an effect with in-window
    structure left out reads the rough part high, up to several times the gap)."""
    return min(noise_floor(prep, rough), math.sqrt(float(np.mean(mse))))


def _floor_with_next(prep: Prepared, nominal: PlantSpec, trial: list[Fit], cands: list[tuple[float, Fit, dict]],
                     floor: float, st_trial: dict[str, float], pool: Any) -> float:
    """The floor read from models with the round's best *and* a next effect (each of the round's
    LOOKAHEAD best other effects fitted on top of it).

    Tried only where that could change the decision: the best improves windows (st_trial). A model
    closer to the machine leaves less rough part, so the floor (the least over every model tried) can
    only fall; on a clean trace it stays at the noise.
    """
    if st_trial["robust_gain"] <= 0 or st_trial["improved"] < MIN_IMPROVED:
        return floor
    have = {f.effect for f in trial}
    keys = []
    for _, f, _st in cands[1:]:
        if f.effect not in have and f.key not in SPLITTING and run_effect(f.key) not in {run_effect(k) for k in keys}:
            keys.append(f.key)
    keys = keys[:LOOKAHEAD]
    if not keys:
        return floor
    base = _build(nominal, trial)
    fits, _ = _run_fits(keys, prep.on(base), pool, None)
    if not fits:
        return floor
    mses, rough = _mse_of(prep, [f.add_to(base) for f in fits])
    return min(floor, *(_floor_of(prep, mses[:, i], rough[:, i]) for i in range(len(fits))))


def _simplify(prep: Prepared, nominal: PlantSpec, named: list[Fit], mse: np.ndarray, floor: float,
              alone: list[tuple[Fit, dict[str, float]]]) -> tuple[list[Fit], PlantSpec, np.ndarray, list]:
    """The simplest of near-equal explanations, once the naming is done.

    Effects named in order trade along valleys: while the axis moves, a constant force (offset) and a
    Coulomb or viscous friction that differs by direction push alike, and the first, strongest round
    can take the two-parameter one for a one-parameter cause (only standstill tells them apart). So each
    named effect is tried (a) left out, the others refitted jointly without it, and (b) replaced by a
    candidate with fewer parameters (from its fit on the nominal plant, refitted jointly with the
    others); it goes when its extra parameters do not earn MARGIN floor^2 over the simpler model.
    Returns (named, model, per-window MSE, [(removed, replacement or None), ...]).
    """
    swaps: list[tuple[Fit, Fit | None]] = []
    by_key = {k.key: k for k, _ in alone}
    done: set[str] = set()
    while True:
        # the effect with the most parameters first: the one most likely to stand in for a simpler cause
        left = [f for f in named if f.key not in done]
        if not left:
            break
        f = max(left, key=lambda g: g.n_params)
        done.add(f.key)
        i = named.index(f)
        others = [g for j, g in enumerate(named) if j != i]
        have = {g.effect for g in others}
        tries: list[Fit | None] = [None] if others else []
        tries += [k for k, st in alone if k.n_params < f.n_params and k.key != f.key and k.effect not in have
                  and st["robust_gain"] > 0][:SIMPLER_TRIES]
        for k in tries:
            start = [*named[:i], *([k] if k is not None else []), *named[i + 1:]]
            # the others start where they were, or from their own fit on the nominal plant when that is
            # better: the one taken out may have carried part of them (a Coulomb asymmetry an offset)
            alt = [by_key.get(g.key, g) if g is not k else g for g in start]
            gaps = _gaps_grouped_of(prep, nominal, [start, alt])
            trial = refine_jointly(prep, nominal, alt if gaps[1] < gaps[0] else start)
            mse_t, _ = _mse_of(prep, [_build(nominal, trial)])
            saved = PARAM_CHARGE * (f.n_params - (k.n_params if k is not None else 0)) * floor ** 2
            loss = _window_stats(mse_t[:, 0], mse)["robust_gain"] - saved
            if loss < MARGIN * floor ** 2:
                swaps.append((f, trial[i] if k is not None else None))
                named, mse = trial, mse_t[:, 0]
                break
    return named, _build(nominal, named), mse, swaps


def _gaps_grouped_of(prep: Prepared, nominal: PlantSpec, models: list[list[Fit]]) -> np.ndarray:
    """The gap of each model (a list of fits on the nominal plant)."""
    specs = [_build(nominal, m) for m in models]
    mses, _ = _mse_of(prep, specs)
    return np.sqrt(np.mean(mses, axis=0))


def _prune(prep: Prepared, nominal: PlantSpec, fits: list[Fit], mse: np.ndarray,
           floor: float) -> tuple[list[Fit], PlantSpec, np.ndarray]:
    """Drop named effects that no longer earn their parameters once the others were refitted with them;
    the ones kept are then refitted together without the dropped (fitted beside it, they sat where it
    had pulled them: the next round would find their own optimum and credit it to its candidate)."""
    dropped = False
    while len(fits) > 1:
        specs = [_build(nominal, fits[:i] + fits[i + 1:]) for i in range(len(fits))]
        mses, _ = _mse_of(prep, specs)
        losses = [(_window_stats(mses[:, i], mse)["robust_gain"] - PARAM_CHARGE * f.n_params * floor ** 2, i)
                  for i, f in enumerate(fits)]
        loss, i = min(losses)
        if loss >= MARGIN * floor ** 2:
            break
        fits = fits[:i] + fits[i + 1:]
        mse = mses[:, i]
        dropped = True
    if dropped:
        refit = refine_jointly(prep, nominal, fits)
        mse_r, _ = _mse_of(prep, [_build(nominal, refit)])
        if float(np.mean(mse_r[:, 0])) < float(np.mean(mse)):
            fits, mse = refit, mse_r[:, 0]
    return fits, _build(nominal, fits), mse


# --------------------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------------------


def add_explain_parser(subparsers: Any) -> argparse.ArgumentParser:
    """``drivectl explain TRACE.csv --plant NAME|FILE [--json] [--out DIR]``."""
    p = subparsers.add_parser(
        "explain", help="name what the plant model is missing in a trace, fit it, show the gap shrink",
        description="Hold a recorded trace (format v1) against a plant, name the missing effects one after another "
        "(vocabulary: docs/effects.md), fit them, write the augmented plant TOML, a report and a PNG, and print the "
        "gap before and after and what remains against the data's own floor.")
    p.add_argument("trace", metavar="TRACE.csv|LOG", help="a trace, or a CAN log (.asc .blf .log .trc .csv .mf4): "
                   "converted first as trace --from-log does (docs/guide/buslog.md)")
    p.add_argument("--plant", required=True, metavar="NAME|FILE", help="the model: built-in plant or plant TOML")
    p.add_argument("--axis", help="with a CAN log: the axis of the configuration it holds (its node, EDS, encoder, "
                   "rated effort; default x)")
    p.add_argument("--node", type=int, metavar="N", help="with a CAN log: the drive's node-ID (default: the axis's)")
    p.add_argument("--eds", metavar="FILE", help="with a CAN log: the drive's EDS (default: the axis's)")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")
    p.add_argument("--out", metavar="DIR", help="folder for STEM.plant.toml, STEM.report.txt, STEM.png "
                   "(default: beside the trace)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--write-config", nargs="?", const="", metavar="FILE",
                   help="also point axes.AXIS.plant (AXIS: the trace's) at the augmented plant in FILE (default: "
                   "the --config in use), comments kept, the old file backed up as FILE.STAMP.bak")
    return p


@exits_on_error
def cmd_explain(args: argparse.Namespace) -> int:
    """Exit 0 with a result (``none`` included); 2 with one line on stderr for bad input (the code each
    error carries, drivectl/errors.py)."""
    from drivectl.machine.config import ConfigError

    path = Path(args.trace)
    spec = load_plant(args.plant)
    if getattr(args, "write_config", None) is not None:  # before the work
        from drivectl.machine.config_io import target_file

        args.write_config = str(target_file(args.write_config, getattr(args, "config", None)))
    out = Path(args.out) if args.out else path.parent
    from drivectl.tools.buslog import is_bus_log

    if is_bus_log(path):  # a CAN log: its trace first (beside the report), then the trace explained
        from drivectl.tools.buslog import log_to_trace

        path = log_to_trace(path, axis=getattr(args, "axis", None) or "x", out_dir=out,
                            node=getattr(args, "node", None), eds=getattr(args, "eds", None),
                            config=getattr(args, "config", None), progress=not getattr(args, "quiet", False))
        if not args.json:
            print(f"converted {args.trace} -> {path}")
    trace = Trace.read(path)
    res = explain(trace, spec, out_dir=out, source=str(path), stem=path.stem + ".explain",
                  progress=not getattr(args, "quiet", False))
    if args.json:
        print(json.dumps(res.to_json()))
    else:
        print(res.report, end="")
        for f in res.files:
            print(f"wrote {f}")
    if getattr(args, "write_config", None) is not None:  # machine/config_io.py
        from drivectl.machine.config_io import merge_into, target_file

        axis = trace.meta.get("axis", "")
        plant = next((f for f in res.files if str(f).endswith(".plant.toml")), None)
        if plant is None:
            raise ConfigError("--write-config: no augmented plant was written to merge")
        target = target_file(args.write_config, getattr(args, "config", None))
        backup = merge_into(target, axis, {"plant": str(Path(plant).resolve())})
        if not args.json:
            print(f"merged axes.{axis}.plant into {target}" + (f" (old file kept as {backup})" if backup else ""))
    return 0

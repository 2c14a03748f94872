"""`drivectl tune --axis x`: search a controller's gains on the axis's model, then verify on the axis.

The search runs the axis's plant model (the configured plant, no bus) under the axis's profile,
with the cost of tools/commissioning/tune_cost.py (J: the largest tracking error plus a weighted
roughness of the effort; infinite outside the limits).

Candidates: candidate 0 is the starting gains (the axis's settings, or the controller's defaults),
so the best is never worse than what the axis has. Then a seeded scrambled Sobol sample in log space
over x0.3 .. x3 of each starting gain, clipped to the range the Settings class declares; the last
quarter of the budget refines around the best three (x/ 1.25 boxes). Gains whose starting value is 0
are not searched (no scale to search around).

Verification: one trace of the best gains on the axis (default the emulated CiA 402 drive on the
virtual bus, ``--sim`` SimAxis). The predicted metrics come from SimAxis with the best gains, so on
the emulator (whose plant is the model, same quantisation, same transport delay) predicted and
measured agree to the bit; on a real axis their difference is the model's error.

Library: :func:`tune` -> :class:`TuneResult`. CLI: :func:`add_tune_parser`, :func:`cmd_tune`.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
from collections.abc import Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from drivectl.errors import InputError
from drivectl.machine.config import MachineConfig
from drivectl.tools.cli.exits import exits_on_error
from drivectl.tools.commissioning.tune_cost import (
    COST_TEXT,
    DEFAULT_WEIGHT,
    MAX_CLIPPED,
    Job,
    Metrics,
    batch_ok,
    evaluate_robust,
    metrics_of,
    simulate,
)

#: search box around each starting gain, as factors (log-uniform inside)
SPAN = (0.3, 3.0)
#: share of the budget spent refining around the best, and how many best seed the refinement
REFINE_SHARE = 0.25
REFINE_TOP = 3
REFINE_FACTOR = 1.25

#: which gains are searched, per controller
TUNED_GAINS: dict[str, tuple[str, ...]] = {
    "asmc": ("gamma", "rho", "h", "k_in"),
    "pid": ("kp", "kd", "ki"),
    "pid-dob": ("kp", "kd", "ki"),
    "pid-nftsm": ("m_tilde", "accel_filter_hz", "kp", "rho1"),
    "smc": ("m_tilde", "c"),
    "vprl": ("m_tilde", "c"),
    "mbc": ("bandwidth_hz", "observer_hz"),
}


class TuneError(InputError):
    """A tune request cannot be served; one line."""


@dataclass
class TuneResult:
    axis: str
    controller: str
    candidates: int
    seconds: float  # wall seconds of the search
    duration: float  # simulated (and verified) run length, s
    weight: float
    method: str  # "batch" (numpy, linear plant) or "pool (N jobs)" / "serial"
    start: dict[str, float]
    best: dict[str, float]
    predicted: Metrics
    start_metrics: Metrics
    costs: np.ndarray  # every candidate's cost, candidate 0 = the starting gains
    bounds: dict[str, tuple[float, float]]
    settings: dict[str, Any]  # the full settings table to write (axis settings + best gains)
    measured: Metrics | None = None
    verified_on: str = ""
    fixed: list[str] = field(default_factory=list)
    corners: int = 0  # perturbed models scored beside the nominal one
    spread: float = 0.0  # their relative perturbation
    unstable: int = 0  # candidates rejected as unstable on some corner
    model_differs: bool = False  # the axis's model is not its plant (the verification then shows the mismatch)

    def to_json(self) -> dict[str, Any]:
        return {"axis": self.axis, "controller": self.controller, "candidates": self.candidates,
                "seconds": self.seconds, "best": dict(self.best), "predicted": self.predicted.to_json(),
                "measured": self.measured.to_json() if self.measured is not None else None}


# --------------------------------------------------------------------------------------------------
def search_space(controller: str, start: Mapping[str, float],
                 full: Mapping[str, Any] | None = None) -> tuple[dict[str, tuple[float, float]], list[str]]:
    """Log-space bounds per tuned gain: SPAN around the start, inside the declared range (and, for
    asmc, k_min <= k_in <= k_bar, which its settings check; ``full`` = the whole settings)."""
    full = full or {}
    from drivectl.controllers.registry import controller_class

    meta = {f.name: f.metadata for f in dataclasses.fields(controller_class(controller).SettingsClass)}
    bounds: dict[str, tuple[float, float]] = {}
    fixed: list[str] = []
    for name in TUNED_GAINS[controller]:
        v = float(start[name])
        if not v > 0:
            fixed.append(name)
            continue
        lo, hi = v * SPAN[0], v * SPAN[1]
        m = meta[name]
        # stay strictly inside open ends (a relative nudge: the ends here are 0 or 1)
        if m.get("lo") is not None:
            lo = max(lo, m["lo"] * (1 + 1e-9) + (1e-12 if m.get("lo_open") else 0.0))
        if m.get("hi") is not None:
            hi = min(hi, m["hi"] * (1 - 1e-9) - (1e-12 if m.get("hi_open") else 0.0))
        if controller == "asmc" and name == "k_in":
            hi = min(hi, float(full.get("k_bar", math.inf)))
            lo = max(lo, float(full.get("k_min", 0.0)))
        if not 0 < lo < hi:
            fixed.append(name)
            continue
        bounds[name] = (lo, hi)
    return bounds, fixed


def _sample(bounds: Mapping[str, tuple[float, float]], n: int, seed: int) -> list[dict[str, float]]:
    """``n`` points of a scrambled Sobol sequence, log-uniform in ``bounds``."""
    from scipy.stats import qmc

    if n <= 0 or not bounds:
        return []
    keys = list(bounds)
    m = max(0, math.ceil(math.log2(n)))
    u = qmc.Sobol(len(keys), scramble=True, seed=seed).random_base2(m)[:n]  # base-2 size: balanced, no warning
    lo = np.log([bounds[k][0] for k in keys])
    hi = np.log([bounds[k][1] for k in keys])
    pts = np.exp(lo + u * (hi - lo))
    return [{k: float(p[j]) for j, k in enumerate(keys)} for p in pts]


def _refine(bounds: Mapping[str, tuple[float, float]], centres: Sequence[Mapping[str, float]], n: int,
            seed: int) -> list[dict[str, float]]:
    """``n`` points in x/ REFINE_FACTOR boxes around ``centres`` (shared out), inside ``bounds``."""
    out: list[dict[str, float]] = []
    for j, c in enumerate(centres):
        share = n // len(centres) + (1 if j < n % len(centres) else 0)
        box = {k: (max(lo, c[k] / REFINE_FACTOR), min(hi, c[k] * REFINE_FACTOR)) for k, (lo, hi) in bounds.items()}
        box = {k: (lo, hi) if hi > lo else (lo, lo * (1 + 1e-12)) for k, (lo, hi) in box.items()}
        out += _sample(box, share, seed + 1000 + j)
    return out


def starting_gains(cfg: MachineConfig, axis: str,
                   controller: str) -> tuple[dict[str, Any], dict[str, float], dict[str, Any]]:
    """The axis's settings table for ``controller`` and the starting values of its tuned gains
    (as the controller actually runs them: model-based controllers add their paper's table)."""
    from drivectl.controllers.registry import make_controller
    from drivectl.machine.build import model_specs
    from drivectl.tools.cli.checks import carry_settings

    ac = cfg.axis(axis)
    # another controller keeps the axis's settings it also takes (as trace --controller does)
    base = dict(ac.controller_settings) if controller == ac.controller else carry_settings(
        ac.controller_settings, controller)[0]
    spec = model_specs(cfg, [axis])[axis]
    ctrl = make_controller(controller, cfg.cycle_s, base, plant=spec, axis=axis,
                           source=f"{cfg.source}: axes.{axis}.controller_settings")
    full = ctrl.settings.as_dict()
    return base, {k: float(full[k]) for k in TUNED_GAINS[controller]}, full


def tune(
    cfg: MachineConfig,
    axis_name: str,
    *,
    controller: str | None = None,
    candidates: int = 200,
    seconds: float | None = None,
    seed: int = 0,
    jobs: int | None = None,
    weight: float = DEFAULT_WEIGHT,
    verify: bool = True,
    sim: bool = False,
    progress: bool = False,
    corners: int | None = None,
    spread: float = 0.10,
) -> TuneResult:
    """Search ``candidates`` gain sets of ``controller`` (default the axis's) on the axis's model and
    return the best; with ``verify`` run it once on the axis (``sim``: SimAxis, else the configured bus).

    ``seconds`` shortens the run (default the profile's duration); ``jobs`` worker processes for
    nonlinear plants (default ``os.cpu_count()``; 1 = in this process).

    Robust: every candidate is scored on the model and on its perturbed corners (controllers/robust.py:
    every +-``spread`` corner of the parameters that matter, or a seeded ``corners`` of them; 0 = the
    model alone), its cost the worst of them; a candidate unstable on any is rejected -- for a controller
    with a linear loop on a linear model by the spectral radius of the closed loop (before any run), else
    by the simulation (leaving the limits, or an error that does not settle).
    """
    from drivectl.controllers.registry import controller_class

    ac = cfg.axis(axis_name)
    name = controller or ac.controller
    controller_class(name)  # unknown names fail here, before any work
    if name not in TUNED_GAINS:
        raise TuneError(f"tune: controller {name!r}: no tunable gains declared")
    if candidates < 1:
        raise TuneError(f"tune: candidates: must be >= 1, got {candidates}")
    if seconds is not None and not seconds > 0:
        raise TuneError(f"tune: seconds: must be > 0, got {seconds}")
    if not (weight >= 0 and math.isfinite(weight)):
        raise TuneError(f"tune: weight: must be a finite number >= 0, got {weight}")
    if corners is not None and corners < 0:
        raise TuneError(f"tune: corners: must be >= 0, got {corners}")
    if not (math.isfinite(spread) and 0 < spread < 1):
        raise TuneError(f"tune: spread: must be in (0, 1), got {spread}")
    jobs = max(1, jobs or os.cpu_count() or 1)

    base, start, full = starting_gains(cfg, axis_name, name)
    bounds, fixed = search_space(name, start, full)
    from drivectl.machine.build import axis_profile

    profile = axis_profile(cfg, axis_name)
    duration = float(seconds) if seconds is not None else float(profile.duration)
    job = Job(cfg, axis_name, name, base, duration, weight)
    # the batch needs array-valued settings (plant_emulator/batch.py); a design-time controller has none
    use_batch = getattr(controller_class(name), "batch_settings", True) and batch_ok(cfg, axis_name)
    from drivectl.controllers.robust import corners as corner_specs
    from drivectl.machine.build import model_specs

    model = model_specs(cfg, [axis_name])[axis_name]
    perturbed = [] if corners == 0 else corner_specs(model, spread, corners)
    jobs_set = [job] + [dataclasses.replace(job, plant=c) for c in perturbed]

    t0 = time.perf_counter()
    n_refine = int(round(candidates * REFINE_SHARE)) if candidates >= 8 and bounds else 0
    first = [dict(start)] + _sample(bounds, candidates - 1 - n_refine, seed)
    first = [dict(start) | g for g in first]  # fixed gains keep their start value
    bar = _bar(candidates * len(jobs_set), progress)
    pool = None
    unstable = 0
    try:
        if not use_batch and jobs > 1 and candidates > 1:
            pool = ProcessPoolExecutor(max_workers=jobs)
        costs, bad = evaluate_robust(jobs_set, model, first, use_batch, pool, jobs, bar)
        unstable += bad
        pts = list(first)
        if n_refine:
            order = [i for i in np.argsort(costs, kind="stable") if math.isfinite(costs[i])][:REFINE_TOP]
            centres = [pts[i] for i in order] or [dict(start)]
            more = [dict(start) | g for g in _refine(bounds, centres, n_refine, seed)]
            if more:
                extra, bad = evaluate_robust(jobs_set, model, more, use_batch, pool, jobs, bar)
                costs = np.concatenate([costs, extra])
                unstable += bad
                pts += more
    finally:
        if pool is not None:
            pool.shutdown()
        if bar is not None:
            bar.close()
    wall = time.perf_counter() - t0

    # candidate 0 is the start: the best is never worse than it, on the same (worst-case) score
    i_best = int(np.argmin(costs)) if np.any(np.isfinite(costs)) else 0
    best = pts[i_best]
    # the prediction: SimAxis, the path the verification takes (for the batch path, also the check
    # that its ranking figure matches a full servo-loop run)
    predicted = simulate(job, best, profile)
    start_metrics = predicted if i_best == 0 else simulate(job, start, profile)
    method = "batch (numpy, linear plant)" if use_batch else (f"pool ({jobs} processes)" if pool else "serial")
    result = TuneResult(axis_name, name, len(pts), wall, duration, weight, method, dict(start), dict(best),
                        predicted, start_metrics, costs, bounds, {**base, **best}, fixed=fixed)
    result.corners, result.spread, result.unstable = len(perturbed), spread, unstable
    if verify:
        from drivectl.machine.build import axis_model

        result.model_differs = axis_model(cfg, axis_name) != cfg.axis(axis_name).plant
        result.measured, result.verified_on = verify_gains(cfg, axis_name, name, result.settings, duration,
                                                           weight, sim=sim)
    return result


def verify_gains(cfg: MachineConfig, axis: str, controller: str, settings: Mapping[str, Any], duration: float,
                 weight: float, *, sim: bool = False) -> tuple[Metrics, str]:
    """One trace of ``settings`` on the axis (bus or SimAxis) and its metrics under the same cost."""
    from drivectl.controllers.registry import make_controller
    from drivectl.controllers.runtime.servo import run
    from drivectl.machine.build import axis_profile, model_specs, open_machine
    from drivectl.tracefile.metrics import effort_roughness, tracking_error

    ac = cfg.axis(axis)
    profile = axis_profile(cfg, axis)
    spec = model_specs(cfg, [axis])[axis]  # the controller believes the model; the axis plays its plant
    ctrl = make_controller(controller, cfg.cycle_s, dict(settings), plant=spec, axis=axis)
    with open_machine(cfg, [axis], sim=sim, start={axis: profile.start_position}) as machine:
        res = run(machine.axes[axis], ctrl, profile, duration=duration, limits=ac.limits)
        bus = machine.bus
    return metrics_of(res, ac.rated_effort, weight, effort_roughness, tracking_error), bus


def _bar(total: int, enabled: bool) -> Any:
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, unit="cand", leave=False, desc="tune", file=sys.stderr)


# --------------------------------------------------------------------------------------------------
def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float | np.floating):
        return repr(float(v))  # exact round trip: the file holds the gains that were verified
    return json.dumps(str(v))


def settings_toml(result: TuneResult) -> str:
    """The best gains as a `[axes.AXIS.controller_settings]` table (the axis's other settings kept)."""
    lines = [f"# drivectl tune --axis {result.axis}: controller {result.controller}, {result.candidates} "
             f"candidates on the model, {result.duration:g} s of the profile",
             "# " + COST_TEXT.format(w=result.weight, c=MAX_CLIPPED),
             f"# predicted: max {result.predicted.max_um:.4g} um, du_rms {result.predicted.du_rms:.4g}, "
             f"J {result.predicted.cost:.4g}"]
    if result.measured is not None:
        m = result.measured
        lines.append(f"# measured on {result.verified_on}: max {m.max_um:.4g} um, du_rms {m.du_rms:.4g}, "
                     f"J {m.cost:.4g}")
    lines.append(f'# requires [axes.{result.axis}] controller = "{result.controller}"')
    lines.append(f"[axes.{result.axis}.controller_settings]")
    lines += [f"{k} = {_toml_value(v)}" for k, v in result.settings.items()]
    return "\n".join(lines) + "\n"


def report(result: TuneResult) -> str:
    r = result
    out = [f"tune: axis {r.axis}, controller {r.controller}: {r.candidates} candidates in {r.seconds:.1f} s "
           f"({r.method}), {r.duration:g} s runs on the model",
           "cost: " + COST_TEXT.format(w=r.weight, c=MAX_CLIPPED)]
    finite = int(np.isfinite(r.costs).sum())
    if r.corners:
        out.append(f"robust: scored on the model and {r.corners} +-{100 * r.spread:g} % corners (worst counts); "
                   f"{r.unstable} candidates unstable on some corner, rejected")
    out.append(f"      {finite} of {r.candidates} candidates inside the limits")
    if r.fixed:
        out.append(f"not searched (start value 0): {', '.join(r.fixed)}")
    head = f"{'gain':<16} {'start':>12} {'best':>12} {'searched range':>26}"
    out += ["", head, "-" * len(head)]
    for k in r.best:
        lo, hi = r.bounds.get(k, (math.nan, math.nan))
        rng = f"{lo:.4g} .. {hi:.4g}" if k in r.bounds else "fixed"
        out.append(f"{k:<16} {r.start[k]:>12.5g} {r.best[k]:>12.5g} {rng:>26}")
    out.append("")
    cols = [("start (model)", r.start_metrics), ("predicted", r.predicted)]
    if r.measured is not None:
        cols.append(("measured", r.measured))
    head = f"{'':<12}" + "".join(f" {c:>16}" for c, _ in cols)
    out += [head, "-" * len(head)]
    for label, attr, fmt in (("max um", "max_um", ".4g"), ("du rms", "du_rms", ".4g"), ("cost J", "cost", ".4g")):
        out.append(f"{label:<12}" + "".join(f" {format(getattr(m, attr), fmt):>16}" for _, m in cols))
    if r.measured is not None:
        m, p = r.measured, r.predicted
        if not m.ok:
            out.append(f"verification on {r.verified_on}: STOPPED ({m.detail})")
        else:
            rel = abs(m.cost - p.cost) / max(abs(p.cost), 1e-12)
            if r.model_differs:
                note = " (the axis plays its plant, the search ran its model: the gap is the mismatch)"
            elif "SimAxis" in r.verified_on:
                note = " (SimAxis runs the model itself: they must agree)"
            elif "emulated" in r.verified_on:
                note = " (the emulated drive's plant is the model: they should agree; a gap is a bus/drive bug)"
            else:
                note = " (a real axis: the gap is what the model misses)"
            out.append(f"verified on {r.verified_on}: cost differs from the prediction by {100 * rel:.2g} %{note}")
    else:
        out.append("not verified (--no-verify)")
    return "\n".join(out) + "\n"


def add_tune_parser(subparsers: Any) -> argparse.ArgumentParser:
    """``drivectl tune --axis NAME [...]``."""
    p = subparsers.add_parser(
        "tune", help="search a controller's gains on the axis's model, then verify them on the axis",
        description="Search the gains of the axis's controller on its plant model in simulation (seeded Sobol "
        "sample in log space, x0.3..x3 around the current gains inside their declared ranges, then a local "
        "refinement), minimising J = max|e| [um] + w * RMS(diff(effort)) / (rated/1000); gains that leave the "
        "following-error window or clip the effort limit are rejected. Prints the gains and the predicted "
        "metrics, runs one verification trace on the axis and prints predicted beside measured, and writes "
        "the gains as a TOML table.")
    p.add_argument("--axis", default="x", help="axis name (default x)")
    p.add_argument("--controller", help=f"controller to tune (default the axis's; {', '.join(TUNED_GAINS)})")
    p.add_argument("--candidates", type=int, default=200, help="gain sets simulated (default 200)")
    p.add_argument("--seconds", type=float, help="run length, s (default the profile's duration)")
    p.add_argument("--seed", type=int, default=0, help="seed of the quasi-random sample (default 0)")
    p.add_argument("--jobs", type=int, default=os.cpu_count(), help="worker processes (default: all CPUs)")
    p.add_argument("--weight", type=float, default=DEFAULT_WEIGHT,
                   help=f"w, um of max error per per mille of effort roughness (default {DEFAULT_WEIGHT})")
    p.add_argument("--corners", type=int, metavar="N",
                   help="score every candidate on N perturbed models too (default: every +-spread corner of the "
                   "parameters that matter, 64 for two-mass; 0 = the model alone); the worst counts, a candidate "
                   "unstable on any is rejected")
    p.add_argument("--spread", type=float, default=0.10, help="relative perturbation of the corners (default 0.10)")
    p.add_argument("--no-verify", action="store_true", help="skip the verification trace on the axis")
    p.add_argument("--sim", action="store_true", help="verify on SimAxis instead of the configured bus")
    p.add_argument("--model", metavar="NAME|FILE", help="the model the search runs and the controller believes "
                   "(default: the axis's model key, else its plant); the verification runs on the axis")
    p.add_argument("--out", metavar="TOML", help="where to write the gains (default traces/tune-AXIS.toml)")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")
    p.add_argument("--write-config", nargs="?", const="", metavar="FILE",
                   help="also merge the gains (and the controller) into axes.AXIS of FILE (default: the --config "
                   "in use), comments kept, the old file backed up as FILE.STAMP.bak")
    p.add_argument("--target", metavar="gm=8dB,pm=45deg,ms=2",
                   help="stability-margin targets: search the gains (of a law with a linear form: pid, pid-dob, mbc) "
                   "that meet every one on the model and every corner, for the highest bandwidth (or --objective "
                   "tracking), then measure the margins on the axis (bode --loop open)")
    p.add_argument("--objective", choices=("bandwidth", "tracking"), default="bandwidth",
                   help="with --target: the highest closed-loop bandwidth (default) or the best tracking score J")
    return p


def _cmd_targets(args: argparse.Namespace, cfg: MachineConfig, targets: dict[str, float]) -> int:
    """`tune --target`: tools/commissioning/tune_margins.py."""
    from drivectl.tools.commissioning import tune_margins as tm

    res = tm.tune_to_targets(cfg, args.axis, targets, controller=args.controller, objective=args.objective,
                             candidates=args.candidates, seed=args.seed, corners=args.corners, spread=args.spread,
                             verify=not args.no_verify, sim=args.sim, seconds=args.seconds, weight=args.weight,
                             progress=sys.stderr.isatty())
    note = f"tuned by drivectl tune --target {tm.target_text(res.targets)}"
    return _write_result(args, res, tm.settings_toml(res), note, tm.report(res))


def _write_result(args: argparse.Namespace, res: Any, toml_text: str, note: str, text: str) -> int:
    """The tuned gains out: the TOML file (atomically), --write-config's merge, the report or --json; exit 1
    when the verification run was stopped."""
    from drivectl.tracefile.format import atomic_write_text

    out = Path(args.out) if args.out else Path("traces") / f"tune-{res.axis}.toml"
    atomic_write_text(out, toml_text)
    merged = ""
    if getattr(args, "write_config", None) is not None:  # machine/config_io.py: comments kept, old file backed up
        from drivectl.machine.config_io import merge_into, target_file

        target = target_file(args.write_config, getattr(args, "config", None))
        backup = merge_into(target, res.axis, {"controller": res.controller}, res.settings, note=note)
        merged = f"merged axes.{res.axis}.controller_settings into {target}" + (
            f" (old file kept as {backup})" if backup else "")
    if args.json:
        print(json.dumps(res.to_json()))
    else:
        print(text, end="")
        print(f"wrote {out}")
        if merged:
            print(merged)
    if res.measured is not None and not res.measured.ok:
        print(f"drivectl: verification stopped: {res.measured.detail}", file=sys.stderr)
        return 1
    return 0


@exits_on_error
def cmd_tune(args: argparse.Namespace) -> int:
    """Exit 0 done (the verification completed); 1 the verification run was stopped by a limit or the
    axis; 2 bad input, with one line on stderr (the code each error carries, drivectl/errors.py)."""
    from drivectl.machine.build import with_model
    from drivectl.machine.config import ConfigError, load_config

    cfg = with_model(load_config(getattr(args, "config", None)), args.axis, getattr(args, "model", None))
    if args.out and Path(args.out).is_dir():  # before the search: the gains could not be written after it
        raise ConfigError(f"tune: --out {args.out}: is a folder; give the TOML file to write "
                          "(default traces/tune-AXIS.toml)")
    if getattr(args, "write_config", None) is not None:  # before the search and the verification run
        from drivectl.machine.config_io import target_file

        args.write_config = str(target_file(args.write_config, getattr(args, "config", None)))
    if getattr(args, "target", None) is not None:
        from drivectl.tools.commissioning.tune_margins import parse_targets

        return _cmd_targets(args, cfg, parse_targets(args.target))  # parsed before anything runs or moves
    if getattr(args, "objective", "bandwidth") != "bandwidth":
        raise TuneError("tune: --objective: only with --target (without it, tune minimises the tracking cost J)")
    res = tune(cfg, args.axis, controller=args.controller, candidates=args.candidates, seconds=args.seconds,
               seed=args.seed, jobs=args.jobs, weight=args.weight, verify=not args.no_verify, sim=args.sim,
               progress=sys.stderr.isatty(), corners=args.corners, spread=args.spread)
    return _write_result(args, res, settings_toml(res), f"tuned by drivectl tune ({res.candidates} candidates)",
                         report(res))

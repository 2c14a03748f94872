"""`drivectl tune --target gm=8dB,pm=45deg,ms=2`: gains that meet stability-margin targets on every plant
corner, searched on the model, then verified on the axis with `bode --loop open`'s measurement.

The search (on the model, no run): the same candidates `tune` draws (candidate 0 the axis's gains, a seeded
Sobol sample in log space over x0.3 .. x3 of each, a refinement about the best), each scored by the loop
``L = -K(z) P(z)`` of the law's linear form (controllers/linear_form.py) around every corner's linear part
(the corners `tune` uses: controllers/robust.py, every +-spread corner of the parameters that matter, the
nominal model among them), on a 0.25 Hz grid up to Nyquist. A candidate is feasible when its loop is
stable on every corner (the spectral radius of the closed loop, with the one-cycle transport delay, is
below 1) and every corner meets every target: ``|gm| >= GM`` (the phase crossover nearest 0 dB, either
side: a conditionally stable loop must also tolerate a gain loss), ``|pm| >= PM`` (the gain crossover
nearest 0 deg) and ``Ms <= MS``. Of the feasible ones the search keeps the highest closed-loop bandwidth
(its worst corner), or with ``--objective tracking`` the best tracking score J of `tune` (simulated on the
model, for the :data:`TRACKING_SCORED` widest-band feasible candidates).

No feasible candidate: one line naming the binding target (the one that, dropped, leaves the most
candidates feasible; or the one no candidate meets even alone) and the best any candidate reached.

Only laws with a linear form can be searched this way (pid, pid-dob, mbc): a sliding-mode or TDE law has no
L on the model (its measured margins are describing-function estimates); asking is refused in one line.
"""

from __future__ import annotations

import math
import re
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from drivectl.machine.config import MachineConfig
from drivectl.tools.commissioning.tune import TuneError

#: the margin targets a --target names, with the unit each must carry and the range that is possible
TARGETS = {"gm": ("dB", 0.0, 40.0), "pm": ("deg", 0.0, 90.0), "ms": ("", 1.0, math.inf)}
#: the model grid, Hz: 0.25 Hz resolves a lightly damped mode's phase crossover (two-mass: ~8 Hz wide)
GRID_DF = 0.25
#: --objective tracking: how many of the widest-band feasible candidates are simulated for J
TRACKING_SCORED = 16


def parse_targets(text: str) -> dict[str, float]:
    """``gm=8dB,pm=45deg,ms=2`` -> {"gm": 8.0, "pm": 45.0, "ms": 2.0}; TuneError (one line naming the item)
    on a target that is not a number with its unit, an unknown name, or an impossible value."""
    out: dict[str, float] = {}
    for item in (x.strip() for x in text.split(",")):
        if not item:
            continue
        name, _, value = item.partition("=")
        name = name.strip().lower()
        if name not in TARGETS:
            raise TuneError(f"tune: --target {item}: unknown target {name!r} (gm=<dB>dB, pm=<deg>deg, ms=<number>)")
        unit, lo, hi = TARGETS[name]
        m = re.fullmatch(r"\s*([-+]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?)\s*([A-Za-z°]*)\s*", value)
        got_unit = m.group(2).lower().replace("°", "deg") if m else None
        if m is None or got_unit != unit.lower():
            example = {"gm": "gm=8dB", "pm": "pm=45deg", "ms": "ms=2"}[name]
            raise TuneError(f"tune: --target {item}: not a number with its unit "
                            f"({'in ' + unit if unit else 'a plain number'}, e.g. {example})")
        v = float(m.group(1))
        why = {"gm": "a gain margin is > 0 dB (and above 40 dB no loop of these laws tracks anything)",
               "pm": "a phase margin is > 0 deg and below 90 deg: on an inertia (-180 deg) these laws add at most "
                     "+90 deg of lead, and the transport delay takes some of it",
               "ms": "the sensitivity peak Ms = max |S| is at least 1 (Bode's sensitivity integral)"}[name]
        if not (lo < v < hi if name != "ms" else lo <= v < hi) or not math.isfinite(v):
            raise TuneError(f"tune: --target {item}: impossible: {why}")
        if name in out:
            raise TuneError(f"tune: --target {item}: {name} given twice")
        out[name] = v
    if not out:
        raise TuneError("tune: --target: no target given (e.g. gm=8dB,pm=45deg,ms=2)")
    return out


def target_text(targets: Mapping[str, float]) -> str:
    return ", ".join({"gm": f"gm>={targets['gm']:g}dB", "pm": f"pm>={targets['pm']:g}deg",
                      "ms": f"ms<={targets['ms']:g}"}[k] for k in targets)


@dataclass
class CornerMargins:
    name: str
    gm_db: float
    pm_deg: float
    ms: float
    bandwidth_hz: float
    stable: bool


@dataclass
class TargetResult:
    axis: str
    controller: str
    targets: dict[str, float]
    objective: str
    candidates: int
    feasible: int
    seconds: float
    best: dict[str, float]
    start: dict[str, float]
    settings: dict[str, Any]
    corners: list[CornerMargins]  # the best gains on every corner (the nominal model first)
    tracking: Any = None  # Metrics of the best (objective tracking)
    measured: Any = None  # OpenLoopResult on the axis
    verified_on: str = ""
    model_differs: bool = False
    fixed: list[str] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        meas = None
        if self.measured is not None and self.measured.ok:
            meas = self.measured.to_json()
        worst = {"gm_db": min(abs(c.gm_db) for c in self.corners), "pm_deg": min(abs(c.pm_deg) for c in self.corners),
                 "ms": max(c.ms for c in self.corners), "bandwidth_hz": min(c.bandwidth_hz for c in self.corners)}
        return {"axis": self.axis, "controller": self.controller, "targets": dict(self.targets),
                "objective": self.objective, "candidates": self.candidates, "feasible": self.feasible,
                "best": dict(self.best), "worst_corner": {k: _json_num(v) for k, v in worst.items()},
                "measured": meas}


def _json_num(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def _closed_loop_radius(form: Any, ad: np.ndarray, bd: np.ndarray) -> float:
    """Spectral radius of the law's linear form closed around a plant (exact ZOH) with the command one
    cycle in flight: state [plant, command in flight, law]."""
    n_p, n_k = ad.shape[0], form.A.shape[0]
    cp = np.zeros((2, n_p))
    cp[0, -2] = cp[1, -1] = 1.0
    size = n_p + 1 + n_k
    m = np.zeros((size, size))
    m[:n_p, :n_p] = ad
    m[:n_p, n_p] = bd[:, 0]
    m[n_p, :n_p] = form.D @ cp
    m[n_p, n_p + 1:] = form.C
    m[n_p + 1:, :n_p] = form.B @ cp
    m[n_p + 1:, n_p + 1:] = form.A
    return float(np.max(np.abs(np.linalg.eigvals(m))))


class LoopScorer:
    """Every corner's plant response on the grid, computed once; then a candidate's margins on all of them."""

    def __init__(self, cfg: MachineConfig, axis: str, controller: str, base: Mapping[str, Any], model: Any,
                 corner_specs: list[Any]):
        from drivectl.controllers.linear_model import discretise
        from drivectl.tools.commissioning.frf import linear_matrices
        from drivectl.tools.commissioning.margins import plant_response

        self.cfg, self.axis, self.controller, self.base, self.model = cfg, axis, controller, dict(base), model
        self.dt = cfg.cycle_s
        self.freqs = np.arange(GRID_DF, 0.5 / self.dt, GRID_DF)
        self.specs = [model, *corner_specs]
        self.names = ["model (nominal)", *[s.name for s in corner_specs]]
        self.responses = np.stack([plant_response(s, self.dt, self.freqs) for s in self.specs])  # (C, F, 2)
        self.discrete = [discretise(*linear_matrices(s.design()), self.dt) for s in self.specs]

    def law(self, gains: Mapping[str, float]) -> Any:
        from drivectl.controllers.registry import make_controller

        return make_controller(self.controller, self.dt, {**self.base, **gains}, plant=self.model, axis=self.axis)

    def score(self, gains: Mapping[str, float]) -> list[CornerMargins]:
        from drivectl.controllers.base import SettingsError
        from drivectl.tools.commissioning.margins import margins_batch

        try:
            form = self.law(gains).linear_form()
        except SettingsError:
            return [CornerMargins(n, 0.0, 0.0, math.inf, math.nan, False) for n in self.names]
        k = form.response(self.freqs)  # the law's K is the same on every corner: it believes the model
        loops = -np.einsum("fi,cfi->cf", k, self.responses)
        b = margins_batch(self.freqs, loops)
        return [CornerMargins(n, float(b["gm_db"][i]), float(b["pm_deg"][i]), float(b["ms"][i]),
                              float(b["bandwidth_hz"][i]), _closed_loop_radius(form, *self.discrete[i]) < 1.0)
                for i, n in enumerate(self.names)]


def meets(c: CornerMargins, targets: Mapping[str, float]) -> dict[str, bool]:
    """Which targets one corner meets (an unstable corner meets none)."""
    ok = {"gm": abs(c.gm_db) >= targets.get("gm", 0.0), "pm": abs(c.pm_deg) >= targets.get("pm", 0.0),
          "ms": c.ms <= targets.get("ms", math.inf)}
    return {k: c.stable and v for k, v in ok.items() if k in targets}


def tune_to_targets(cfg: MachineConfig, axis_name: str, targets: Mapping[str, float], *, controller: str | None = None,
                    objective: str = "bandwidth", candidates: int = 200, seed: int = 0, corners: int | None = None,
                    spread: float = 0.10, verify: bool = True, sim: bool = False, seconds: float | None = None,
                    weight: float | None = None, progress: bool = False) -> TargetResult:
    """The search of the module text; with ``verify`` the best gains' open loop measured on the axis
    (``sim``: SimAxis, else the configured bus). TuneError (one line) when nothing meets the targets."""
    from drivectl.controllers.registry import controller_class, make_controller
    from drivectl.controllers.robust import corners as corner_specs
    from drivectl.machine.build import model_specs
    from drivectl.tools.commissioning.tune import (
        REFINE_SHARE,
        REFINE_TOP,
        TUNED_GAINS,
        _refine,
        _sample,
        search_space,
        starting_gains,
    )

    ac = cfg.axis(axis_name)
    name = controller or ac.controller
    controller_class(name)
    if objective not in ("bandwidth", "tracking"):
        raise TuneError(f"tune: --objective {objective}: expected bandwidth or tracking")
    if name not in TUNED_GAINS:
        raise TuneError(f"tune: controller {name!r}: no tunable gains declared")
    if candidates < 1:
        raise TuneError(f"tune: candidates: must be >= 1, got {candidates}")
    if not (math.isfinite(spread) and 0 < spread < 1):
        raise TuneError(f"tune: spread: must be in (0, 1), got {spread}")
    model = model_specs(cfg, [axis_name])[axis_name]
    probe = make_controller(name, cfg.cycle_s, {}, plant=model, axis=axis_name) if name != ac.controller else None
    if (probe or make_controller(ac.controller, cfg.cycle_s, ac.controller_settings, plant=model,
                                 axis=axis_name)).linear_form() is None:
        raise TuneError(f"tune: --target: controller {name} has no linear form (a sliding-mode / time-delay-estimation "
                        "law): its margins cannot be searched on the model; use pid, pid-dob or mbc, or measure it "
                        "with bode --loop open (a describing-function estimate)")
    base, start, full = starting_gains(cfg, axis_name, name)
    bounds, fixed = search_space(name, start, full)
    perturbed = [] if corners == 0 else corner_specs(model, spread, corners)
    scorer = LoopScorer(cfg, axis_name, name, base, model, perturbed)

    t0 = time.perf_counter()
    n_refine = int(round(candidates * REFINE_SHARE)) if candidates >= 8 and bounds else 0
    pts = [dict(start) | g for g in [dict(start)] + _sample(bounds, candidates - 1 - n_refine, seed)]
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=candidates, unit="cand", leave=False, desc="tune --target")
    scores = []
    for g in pts:
        scores.append(scorer.score(g))
        if bar is not None:
            bar.update()

    def bandwidth(sc: list[CornerMargins]) -> float:
        bws = [c.bandwidth_hz for c in sc]
        return min(bws) if all(math.isfinite(b) for b in bws) else -math.inf

    def feasible(sc: list[CornerMargins]) -> bool:
        return all(all(meets(c, targets).values()) for c in sc)

    if n_refine:
        # refine about the best feasible (else the start): what the first sample found
        ranked = sorted((i for i in range(len(pts)) if feasible(scores[i])), key=lambda i: -bandwidth(scores[i]))
        centres = [pts[i] for i in ranked[:REFINE_TOP]] or [dict(start)]
        more = [dict(start) | g for g in _refine(bounds, centres, n_refine, seed)]
        for g in more:
            pts.append(g)
            scores.append(scorer.score(g))
            if bar is not None:
                bar.update()
    if bar is not None:
        bar.close()
    ok = [i for i in range(len(pts)) if feasible(scores[i])]
    if not ok:
        raise TuneError(_refusal(name, targets, scores, len(pts), len(scorer.specs)))
    ok.sort(key=lambda i: -bandwidth(scores[i]))
    tracking = None
    if objective == "tracking":
        from drivectl.machine.build import axis_profile
        from drivectl.tools.commissioning.tune_cost import DEFAULT_WEIGHT, Job, simulate

        profile = axis_profile(cfg, axis_name)
        job = Job(cfg, axis_name, name, base, float(seconds or profile.duration),
                  DEFAULT_WEIGHT if weight is None else weight)
        runs = [(simulate(job, {k: pts[i][k] for k in TUNED_GAINS[name]}, profile), i)
                for i in ok[:TRACKING_SCORED]]
        tracking, i_best = min(runs, key=lambda r: r[0].cost)
    else:
        i_best = ok[0]
    best = {k: float(pts[i_best][k]) for k in TUNED_GAINS[name]}
    res = TargetResult(axis_name, name, dict(targets), objective, len(pts), len(ok), time.perf_counter() - t0, best,
                       dict(start), {**base, **best}, scores[i_best], tracking, fixed=fixed)
    if verify:
        from drivectl.machine.build import axis_model
        from drivectl.tools.commissioning.margins import measure_open_loop

        res.model_differs = axis_model(cfg, axis_name) != ac.plant
        law = make_controller(name, cfg.cycle_s, res.settings, plant=model, axis=axis_name)
        res.measured = measure_open_loop(cfg, axis_name, sim=sim, controller=law)
        res.verified_on = res.measured.bus
    return res


def _refusal(controller: str, targets: Mapping[str, float], scores: list[list[CornerMargins]], n: int,
             n_corners: int) -> str:
    """The one line when no candidate meets every target: the binding one and the best reached."""
    def count(keys: set[str]) -> int:
        return sum(all(all(v for k, v in meets(c, targets).items() if k in keys) for c in sc) for sc in scores)

    names = list(targets)
    alone = {k: count({k}) for k in names}
    impossible = [k for k in names if alone[k] == 0]
    if impossible:
        binding = impossible[0]
    else:
        binding = max(names, key=lambda k: (count(set(names) - {k}), -alone[k]))
    worst = {"gm": lambda sc: min(abs(c.gm_db) if c.stable else 0.0 for c in sc),
             "pm": lambda sc: min(abs(c.pm_deg) if c.stable else 0.0 for c in sc),
             "ms": lambda sc: max(c.ms if c.stable else math.inf for c in sc)}[binding]
    vals = [worst(sc) for sc in scores]
    reached = max(vals) if binding != "ms" else min(vals)
    unit = {"gm": " dB", "pm": " deg", "ms": ""}[binding]
    item = {"gm": f"gm={targets['gm']:g}dB", "pm": f"pm={targets['pm']:g}deg", "ms": f"ms={targets['ms']:g}"}[binding]
    return (f"tune: --target: no gains of {controller} meet {target_text(targets)} on every corner ({n} candidates, "
            f"{n_corners} plants); binding: {item} (the best candidate's worst corner reached {reached:.3g}{unit})")


def report(res: TargetResult) -> str:
    """Per corner and on the axis, the margins achieved beside the targets."""
    t = res.targets
    out = [f"tune --target {target_text(t)}: axis {res.axis}, controller {res.controller}: {res.candidates} candidates "
           f"on the model in {res.seconds:.1f} s, {res.feasible} meet every target on every corner; objective "
           + ("highest bandwidth (worst corner)" if res.objective == "bandwidth" else
              f"best tracking score J among the {min(res.feasible, TRACKING_SCORED)} widest-band feasible")]
    head = f"{'gain':<16} {'start':>12} {'best':>12}"
    out += ["", head, "-" * len(head)]
    out += [f"{k:<16} {res.start[k]:>12.5g} {res.best[k]:>12.5g}" for k in res.best]
    if res.fixed:
        out.append(f"not searched (start value 0): {', '.join(res.fixed)}")
    cells = [("gm", ">= ", 9), ("pm", ">= ", 9), ("ms", "<= ", 7)]
    tgt = f"{'targets':<34}" + "".join(f" {(op + format(t[k], 'g')) if k in t else '':>{w}}" for k, op, w in cells)
    head = f"{'plant':<34} {'|gm| dB':>9} {'|pm| deg':>9} {'Ms':>7} {'bw Hz':>8}"
    out += ["", head, "-" * len(head), tgt]
    # corners that differ only in what the linear loop does not see (a rigid axis's Coulomb levels) read
    # the same: one row each, with how many alike
    rows: dict[tuple, list[CornerMargins]] = {}
    for c in res.corners:
        key = (round(abs(c.gm_db), 2), round(abs(c.pm_deg), 2), round(c.ms, 3), round(c.bandwidth_hz, 2), c.stable)
        rows.setdefault(key, []).append(c)
    for same in rows.values():
        c = same[0]
        name = c.name + (f" (+{len(same) - 1} alike)" if len(same) > 1 else "")
        out.append(f"{name:<34} {abs(c.gm_db):>9.2f} {abs(c.pm_deg):>9.2f} {c.ms:>7.3f} {c.bandwidth_hz:>8.2f}"
                   + ("" if c.stable else "  UNSTABLE"))
    m = res.measured
    if m is None:
        out.append("not verified (--no-verify)")
    elif not m.ok:
        out.append(f"verification on {res.verified_on}: STOPPED ({m.detail})")
    else:
        mm = m.margins

        def v(x: Any, fmt: str, absolute: bool = True) -> str:
            return "-" if x.value is None else format(abs(x.value) if absolute else x.value, fmt)

        out.append(f"{'measured on the axis':<34} {v(mm.gm_db, '.2f'):>9} {v(mm.pm_deg, '.2f'):>9} "
                   f"{v(mm.ms, '.3f', False):>7} {v(mm.bandwidth_hz, '.2f', False):>8}")
        met = {"gm": mm.gm_db.value is not None and abs(mm.gm_db.value) >= t.get("gm", 0),
               "pm": mm.pm_deg.value is not None and abs(mm.pm_deg.value) >= t.get("pm", 0),
               "ms": mm.ms.value is not None and mm.ms.value <= t.get("ms", math.inf)}
        missed = [k for k in t if not met[k]]
        where = f"verified on {res.verified_on} (bode --loop open, +- one standard error: gm {mm.gm_db.text('dB')}, " \
                f"pm {mm.pm_deg.text('deg')}, Ms {mm.ms.text('', '.3f')})"
        out.append(where)
        gap = " (the axis plays its plant, the search ran its model: the gap is the mismatch)" \
            if res.model_differs else ""
        out.append("every target met on the axis" if not missed else f"NOT met on the axis: {', '.join(missed)}{gap}")
        for note in {x.note for x in (mm.gm_db, mm.pm_deg, mm.ms) if x.value is None and x.note}:
            out.append(f"note: {note}")
    if res.tracking is not None:
        out.append(f"tracking on the model: max {res.tracking.max_um:.4g} um, du_rms {res.tracking.du_rms:.4g}, "
                   f"J {res.tracking.cost:.4g}")
    return "\n".join(out) + "\n"


def settings_toml(res: TargetResult) -> str:
    from drivectl.tools.commissioning.tune import _toml_value

    lines = [f"# drivectl tune --axis {res.axis} --target {target_text(res.targets)}: controller {res.controller}, "
             f"{res.candidates} candidates on the model and {len(res.corners) - 1} corners",
             f'# requires [axes.{res.axis}] controller = "{res.controller}"', f"[axes.{res.axis}.controller_settings]"]
    lines += [f"{k} = {_toml_value(v)}" for k, v in res.settings.items()]
    return "\n".join(lines) + "\n"

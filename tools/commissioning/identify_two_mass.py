"""Identify a two-mass axis (paper 000 eq (1)) from its closed-loop frequency response.

``drivectl identify --axis z``: the axis holds its position under its controller while bode's multisine
is added to the effort (tools/commissioning/frf.py: ``H = S_ry / S_ru``, unbiased in closed loop); the model's FRF
from effort to table position (ZOH, transport delay) is then fitted to the measured one over the
coherent lines by nonlinear least squares (scipy's ``least_squares``).

**Parameters and what the data can tell apart.** Effort on the screw side m1, table m2 measured,
spring k and damper n between them, viscous b1 (screw) and b2 (table) to ground. Without b1 and b2,
the response from effort to table position is

    X2 / U = (n s + k) / (s^2 (m1 m2 s^2 + (m1 + m2)(n s + k)))

which depends on m1, m2, k, n only through three numbers: the total mass M = m1 + m2 (the rigid-body
line, 1 / (M s^2) below the mode), the mode w0^2 = k M / (m1 m2) and the damping n / (m1 m2). One
direction of the four is not in this response at all: the split of the mass between the two bodies
(r = m2 / M), with k following it. Only the small viscous friction to ground (b2 on the table, 1.6 V s/m
against the 5.4 V s/m of n in Table 1) breaks the tie, weakly. The fit is therefore parameterised in
the combinations the data holds -- log M, log f0 (the mode, Hz), log n, log b2 -- plus the split r,
with b1 held at the prior model's value (8e-4 V s/m in Table 1: below anything the response shows).
Each parameter's 1-sigma relative uncertainty comes from the fit's Jacobian at the optimum (covariance
(J^T J)^-1 scaled by the residual variance), propagated to m1, m2, k by the delta method; the report
flags every parameter above :data:`POORLY_IDENTIFIED` as poorly identifiable. Measured on the exact
and on perturbed plants: M and f0 to 0.1-0.2 %, r (hence m2 and k) only to several per cent.

**Residual.** The complex log ratio log(H_model / H_measured) on each line (log-magnitude in nepers,
phase in radians), weighted by the line's expected scatter: with ``P`` averaged periods and the
coherence g^2, var(log H) ~ (1 - g^2) / (2 P g^2). Lines with a coherence below
:data:`MIN_COHERENCE` are left out.

The written model TOML is an ordinary plant file (loads with ``--model`` and ``--plant``) with an
``[identified]`` table: the well-identified combinations (total_mass, mode_hz, damping ratio) with
their uncertainties and the names of the poorly identifiable parameters, for a controller design
that should lean on the former (plant_emulator/models.py keeps it as ``PlantSpec.identified``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.optimize import least_squares

from drivectl.plant_emulator.models import PlantSpec

#: lines with a u-y coherence below this are not fitted
MIN_COHERENCE = 0.8
#: a parameter whose 1-sigma relative uncertainty exceeds this is flagged poorly identifiable
POORLY_IDENTIFIED = 0.02
#: the fitted parameters, in the order of the vector the optimiser sees (all but r in log)
FIT_VECTOR = ("log_total_mass", "log_mode_hz", "logit_split", "log_n", "log_b2")
#: parameters reported, with units (V for the paper's axis; the plant's effort unit in general)
REPORTED = ("m1", "m2", "k", "n", "b2", "total_mass", "mode_hz", "damping_ratio")


class TwoMassError(ValueError):
    """The response cannot support the fit (too few coherent lines, no mode in the band)."""


def _unpack(theta: np.ndarray, b1: float) -> dict[str, float]:
    total, f0 = math.exp(theta[0]), math.exp(theta[1])
    r = 1.0 / (1.0 + math.exp(-theta[2]))
    m2 = r * total
    m1 = total - m2
    k = (2 * math.pi * f0) ** 2 * m1 * m2 / total
    return {"m1": m1, "m2": m2, "k": k, "n": math.exp(theta[3]), "b1": b1, "b2": math.exp(theta[4])}


def combinations(p: dict[str, float]) -> dict[str, float]:
    """Total mass, mode (Hz, undamped: sqrt(k M / (m1 m2)) / 2 pi) and its damping ratio."""
    total = p["m1"] + p["m2"]
    mu = p["m1"] * p["m2"] / total
    w0 = math.sqrt(p["k"] / mu)
    return {"total_mass": total, "mode_hz": w0 / (2 * math.pi), "damping_ratio": p["n"] / (2 * math.sqrt(p["k"] * mu))}


def _pack(p: dict[str, float]) -> np.ndarray:
    c = combinations(p)
    r = p["m2"] / c["total_mass"]
    return np.array([math.log(c["total_mass"]), math.log(c["mode_hz"]), math.log(r / (1 - r)), math.log(p["n"]),
                     math.log(max(p["b2"], 1e-9))])


@dataclass
class TwoMassFit:
    params: dict[str, float]  # m1, m2, k, n, b1, b2 (b1 held)
    rel_std: dict[str, float]  # 1-sigma relative uncertainty of each REPORTED parameter
    lines: int  # lines fitted
    residual_rms: float  # weighted residual RMS (1: the scatter the coherence predicts)
    misfit_db: float  # RMS of the log-magnitude misfit, dB (unweighted)
    misfit_deg: float  # RMS of the phase misfit, deg
    poorly: list[str] = field(default_factory=list)

    @property
    def combos(self) -> dict[str, float]:
        return combinations(self.params)

    def value(self, key: str) -> float:
        return self.params[key] if key in self.params else self.combos[key]

    def spec(self, prior: PlantSpec, name: str) -> PlantSpec:
        """The prior plant with the fitted parameters (its disturbance and effects kept) and the
        ``identified`` table."""
        params = dict(prior.params)
        params.update({k: v for k, v in self.params.items()})
        ident: dict[str, Any] = {"method": "closed-loop FRF fit (drivectl identify)"}
        for key in ("total_mass", "mode_hz", "damping_ratio"):
            ident[key] = self.combos[key]
            ident[f"{key}_rel_std"] = self.rel_std[key]
        ident["rel_std"] = {k: self.rel_std[k] for k in ("m1", "m2", "k", "n", "b2")}
        ident["poorly_identified"] = list(self.poorly)
        return replace(prior, name=name, params=params, identified=ident)


def fit_two_mass(freqs: np.ndarray, frf: np.ndarray, coherence: np.ndarray, periods: int, dt: float,
                 prior: PlantSpec, *, mode_hz: float | None = None, total_mass: float | None = None) -> TwoMassFit:
    """Fit m1, m2, k, n, b2 of ``prior`` (a two-mass spec: the start, and b1 and the rest held) to the
    measured FRF on the lines with enough coherence. ``mode_hz`` / ``total_mass``, when known from the
    data (bode's peak, the low-frequency line), start the search there."""
    from drivectl.tools.commissioning.frf import model_frf

    if prior.model != "two-mass":
        raise TwoMassError(f"identify: model {prior.name} is {prior.model}, not two-mass")
    good = np.isfinite(frf) & (np.abs(frf) > 0) & (coherence >= MIN_COHERENCE)
    if good.sum() < 10:
        raise TwoMassError(f"identify: {int(good.sum())} line(s) with coherence >= {MIN_COHERENCE}; need 10 "
                           "(raise --seconds or the amplitude)")
    f, h, coh = freqs[good], frf[good], np.clip(coherence[good], 0.0, 1.0 - 1e-9)
    weight = np.sqrt(2.0 * max(periods, 1) * coh / (1.0 - coh))
    log_h = np.log(h)
    start = dict(prior.params)
    if mode_hz is not None or total_mass is not None:
        c = combinations(start)
        total = total_mass or c["total_mass"]
        f0 = mode_hz or c["mode_hz"]
        r = start["m2"] / c["total_mass"]
        start = {**start, **_unpack(np.array([math.log(total), math.log(f0), math.log(r / (1 - r)),
                                              math.log(start["n"]), math.log(max(start["b2"], 1e-6))]), start["b1"])}
    b1 = float(prior.params["b1"])
    base = replace(prior, effects=())  # the FRF of the base model (effects with dynamics are not fitted here)

    def residual(theta: np.ndarray) -> np.ndarray:
        p = _unpack(theta, b1)
        hm = model_frf(replace(base, params={**base.params, **p}), dt, f)
        d = np.log(hm) - log_h
        d = d.real + 1j * np.angle(np.exp(1j * d.imag))  # phase difference wrapped to (-pi, pi]
        return np.concatenate([d.real * weight, d.imag * weight])

    theta0 = _pack(start)
    sol = least_squares(residual, theta0, x_scale=1.0, method="trf", max_nfev=400)
    p = _unpack(sol.x, b1)
    n_res, n_par = 2 * len(f), len(theta0)
    dof = max(n_res - n_par, 1)
    s2 = float(np.sum(sol.fun**2)) / dof
    jtj = sol.jac.T @ sol.jac
    try:
        cov = np.linalg.inv(jtj) * s2
    except np.linalg.LinAlgError:
        cov = np.linalg.pinv(jtj) * s2
    rel_std = _propagate(sol.x, cov, b1)
    d = sol.fun[: len(f)] / weight
    ph = sol.fun[len(f):] / weight
    poorly = [k for k in ("m1", "m2", "k", "n", "b2") if rel_std[k] > POORLY_IDENTIFIED]
    return TwoMassFit(p, rel_std, len(f), math.sqrt(s2), float(np.sqrt(np.mean((d * 20 / math.log(10)) ** 2))),
                      float(np.degrees(np.sqrt(np.mean(ph**2)))), poorly)


def _propagate(theta: np.ndarray, cov: np.ndarray, b1: float) -> dict[str, float]:
    """1-sigma relative uncertainty of every REPORTED parameter, by the delta method on log values."""

    def logs(th: np.ndarray) -> np.ndarray:
        p = _unpack(th, b1)
        c = combinations(p)
        return np.log([p["m1"], p["m2"], p["k"], p["n"], p["b2"], c["total_mass"], c["mode_hz"], c["damping_ratio"]])

    base = logs(theta)
    jac = np.zeros((len(base), len(theta)))
    for i in range(len(theta)):
        step = 1e-6
        th = theta.copy()
        th[i] += step
        jac[:, i] = (logs(th) - base) / step
    var = np.einsum("ij,jk,ik->i", jac, cov, jac)
    return {k: float(math.sqrt(max(v, 0.0))) for k, v in zip(REPORTED, var, strict=True)}


# --------------------------------------------------------------------------------------------------
# drivectl identify --axis z
# --------------------------------------------------------------------------------------------------

UNITS = {"m1": "{u} s^2/m", "m2": "{u} s^2/m", "k": "{u}/m", "n": "{u} s/m", "b2": "{u} s/m",
         "total_mass": "{u} s^2/m", "mode_hz": "Hz", "damping_ratio": "1"}


def identify_two_mass(cfg: Any, name: str, prior: PlantSpec, *, sim: bool = False, model: str | None = None,
                      plant: str | None = None, seconds: float = 20.0, noise: float = 0.0) -> tuple[TwoMassFit, Any]:
    """Measure the closed-loop FRF of axis ``name`` (bode's multisine, the axis's controller on ``prior``)
    and fit ``prior``'s two-mass parameters to it; returns (fit, bode result)."""
    from drivectl.tools.commissioning.bode import PERIOD_S, measure_frf

    res = measure_frf(cfg, name, sim=sim, seconds=seconds, model=model, plant=plant, noise=noise)
    if not res.ok:
        raise TwoMassError(f"identify: the loop stopped during the excitation ({res.stop}): {res.detail}")
    periods = max(int(seconds / PERIOD_S), 3) - 1  # the first period is dropped
    total = None
    fit = fit_two_mass(res.freqs, res.frf, res.coherence, periods, cfg.cycle_s, prior, mode_hz=res.mode_hz,
                       total_mass=total)
    return fit, res


#: constant speeds of the friction runs on a two-mass axis, m/s (each way, over 80 % of the soft limits)
FRICTION_SPEEDS = (0.005, 0.01, 0.02, 0.04)


def friction_runs(cfg: Any, name: str, prior: PlantSpec, *, sim: bool = False, plant: str | None = None,
                  noise: float = 0.0) -> dict[str, float]:
    """Constant-velocity runs under the axis's controller (on ``prior``) across its soft limits, both
    ways, at :data:`FRICTION_SPEEDS`: per direction, Coulomb level and viscous slope of the mean effort
    against the speed (tools/commissioning/identify.py, ``fit_friction``): fc_pos, c_pos, fc_neg, c_neg."""
    from drivectl.controllers.registry import make_controller
    from drivectl.machine.build import open_machine
    from drivectl.tools.commissioning.identify import fit_friction, friction_points, identification_profile, record_run

    ac = cfg.axis(name)
    lo, hi = ac.limits.position if ac.limits.position is not None else (-0.05, 0.05)
    center, half = 0.5 * (lo + hi), 0.4 * (hi - lo)
    speeds = tuple(v for v in FRICTION_SPEEDS if 2 * half / v >= 0.6) or (FRICTION_SPEEDS[0],)
    profile = identification_profile(center, half, speeds, amax=1.0, jmax=40.0)
    ctrl = make_controller(ac.controller, cfg.cycle_s, ac.controller_settings, plant=prior, axis=name,
                           source=f"{cfg.source}: axes.{name}.controller_settings")
    with open_machine(cfg, [name], sim=sim, plant=plant, noise=noise, start={name: profile.start_position}) as m:
        trace = record_run(m.axes[name], ctrl, profile, ac.limits)
    period = 1.0 / prior.params["disturbance_frequency"] if prior.params.get("disturbance_frequency") else 0.0
    return fit_friction(_whole_periods(trace, period) if period > 0 else friction_points([trace]))


def _whole_periods(trace: Any, period: float) -> list[Any]:
    """The settled constant-velocity stretches, each cut to a whole number of the model's disturbance
    periods (paper 000's d = 0.1 sin(pi t) is 0.1 V: at 10 mm/s it is six times the viscous force, and
    averages out only over whole periods); stretches shorter than one period are dropped."""
    from drivectl.tools.commissioning.identify import FrictionPoint, _runs, _velocity

    dt = trace.dt
    v_ref = np.gradient(trace.ref, dt)
    steady = (np.abs(v_ref) >= 1e-3) & (np.abs(np.gradient(v_ref)) <= 1e-3 * np.abs(v_ref) + 1e-9)
    v = _velocity(trace)
    n_period = int(round(period / dt))
    skip = int(round(0.25 / dt))
    points = []
    for i0, i1 in _runs(steady):
        i0 += skip
        whole = (i1 - i0) // n_period * n_period
        if whole <= 0:
            continue
        sl = slice(i0, i0 + whole)
        points.append(FrictionPoint(float(v[sl].mean()), float(trace.effort[sl].mean()), float("nan"), whole))
    return points


def _has_coulomb(spec: PlantSpec) -> bool:
    return any(b.has_coulomb for b in spec.design().bodies)


def cmd_identify_two_mass(args: Any, cfg: Any, prior: PlantSpec, plant: PlantSpec, merge: Any) -> int:
    """``drivectl identify --axis z``: the table, the model TOML, ``--json``, ``--write-config``."""
    import json
    import sys
    import time
    from pathlib import Path

    from drivectl.tools.commissioning.learn import LINEAR_EFFECTS
    from drivectl.tracefile.format import atomic_write_text

    t0 = time.perf_counter()
    fit, res = identify_two_mass(cfg, args.axis, prior, sim=args.sim, model=getattr(args, "model", None),
                                 plant=getattr(args, "plant", None), seconds=args.seconds,
                                 noise=getattr(args, "noise", 0.0))
    friction = None
    if getattr(args, "friction", False) or _has_coulomb(prior):  # the axis has friction to measure
        friction = friction_runs(cfg, args.axis, prior, sim=args.sim, plant=getattr(args, "plant", None),
                                 noise=getattr(args, "noise", 0.0))
    seconds = time.perf_counter() - t0
    path = Path(args.out) / f"{args.axis}-identified.toml"
    # effects that change the dynamics were not fitted (the fit is of the base model): not carried over
    kept = tuple(e for e in prior.effects if e[0] not in LINEAR_EFFECTS)
    from drivectl.plant_emulator.effects import EFFECTS

    friction_note = ""
    if friction is not None:
        levels = {"force_pos": max(friction["fc_pos"], 0.0), "force_neg": max(friction["fc_neg"], 0.0)}
        if "coulomb" in EFFECTS:
            kept = tuple(e for e in kept if e[0] != "coulomb") + (("coulomb", levels),)
            friction_note = "written as a coulomb effect"
        else:
            friction_note = "not written: this version's effects have no coulomb term for a two-mass model"
    spec = fit.spec(replace(prior, effects=kept), f"{args.axis}-identified")
    if friction is not None:
        spec.identified["friction_runs"] = dict(friction)
    where = "SimAxis" if args.sim else cfg.bus.interface
    atomic_write_text(path, spec.to_toml(
        f"identified by drivectl identify --axis {args.axis} on {where}: closed-loop FRF (multisine "
        f"{res.freqs[0]:g}-{res.freqs[-1]:g} Hz, {args.seconds:g} s) fitted over {fit.lines} coherent lines\n"
        f"load with --model {path} (or --plant)\n"
        f"well identified: total_mass, mode_hz (see [identified]); poorly (1-sigma > "
        f"{100 * POORLY_IDENTIFIED:g} %): {', '.join(fit.poorly) or 'none'}\n"
        f"b1 and the disturbance are {prior.name}'s (not identified)"))
    merged = merge(args, cfg, path)
    ref = combinations(prior.params)
    truth = None
    if plant.model == "two-mass" and (plant.params != prior.params) and cfg.bus.interface == "virtual":
        truth = {**plant.params, **combinations(plant.params)}  # the emulated drive's plant: the true values
    model_vals = {**prior.params, **ref}
    if args.json:
        out = {"axis": args.axis, "method": "closed-loop FRF fit", "identified": {k: fit.value(k) for k in REPORTED},
               "rel_std": dict(fit.rel_std), "poorly_identified": fit.poorly,
               "model": {k: model_vals[k] for k in REPORTED},
               "rel_err": {k: fit.value(k) / model_vals[k] - 1.0 for k in REPORTED},
               "plant_file": str(path), "seconds": seconds, "lines": fit.lines}
        if friction is not None:
            out["friction"] = dict(friction)
        if truth is not None:
            out["plant"] = {k: truth[k] for k in REPORTED}
            out["plant_rel_err"] = {k: fit.value(k) / truth[k] - 1.0 for k in REPORTED}
        print(json.dumps(out))
        return 0
    u = prior.effort_unit
    print(f"axis {args.axis}: closed-loop FRF under its controller, multisine {res.freqs[0]:g}-{res.freqs[-1]:g} Hz "
          f"for {args.seconds:g} s, fitted over {fit.lines} coherent lines (misfit {fit.misfit_db:.2f} dB, "
          f"{fit.misfit_deg:.2f} deg; {seconds:.1f} s)")
    against = "plant" if truth is not None else "model"
    head = f"{'parameter':<26} {'identified':>11} {'+-1 sigma':>10} {against:>11} {'difference':>11}"
    print(head)
    for k in REPORTED:
        v = fit.value(k)
        other = (truth or model_vals)[k]
        label = f"{k} ({UNITS[k].format(u=u)})"
        flag = "  poorly identifiable" if k in fit.poorly else ""
        print(f"{label:<26} {v:>11.5g} {100 * fit.rel_std[k]:>8.3f} % {other:>11.5g} {100 * (v / other - 1):>+9.3f} %"
              f"{flag}")
    if fit.poorly:
        print(f"poorly identifiable (1-sigma > {100 * POORLY_IDENTIFIED:g} %): {', '.join(fit.poorly)}: from effort to "
              "table position the split of the mass between screw and table barely shows; a design should lean on "
              "total_mass and mode_hz ([identified] in the file)", file=sys.stdout)
    if friction is None:
        print(f"friction: {prior.name} has viscous friction only (b2 fitted, b1 held); no constant-velocity runs "
              "(--friction makes them)")
    else:
        print(f"friction (constant-velocity runs, {', '.join(f'{1e3 * v:g}' for v in FRICTION_SPEEDS)} mm/s both "
              f"ways): fc+ {friction['fc_pos']:.4g} {u}, c+ {friction['c_pos']:.4g} {u} s/m, fc- "
              f"{friction['fc_neg']:.4g} {u}, c- {friction['c_neg']:.4g} {u} s/m ({friction_note}; the FRF's "
              f"b1 + b2 = {fit.params['b1'] + fit.params['b2']:.4g} {u} s/m)")
    print(f"wrote {path}   (loads with --model {path})")
    if merged:
        print(merged)
    return 0

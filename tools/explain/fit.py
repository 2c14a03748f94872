"""Candidates of `drivectl explain`: one fitter per way of adding an effect, each fitted on the gap itself.

Each fitter takes the data held against the current model (``prep.spec``: the nominal plant with the
effects named so far) and returns the best parameters of its effect on top of it, by grids of
candidate plants simulated at once (tools/explain/sim.py) and refined around the best point. The
grids and why: docs/explain.md.

Each fit also carries the standard uncertainty of its parameters (:func:`uncertainty`), read from the
per-window errors of its last, exact grid: no simulation beyond the fit's own (docs/health.md).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from drivectl.plant_emulator.effects import EFFECTS
from drivectl.plant_emulator.models import PlantSpec
from drivectl.tools.explain.data import Prepared, gaps_of, window_mse
from drivectl.tools.explain.sim import BatchSim, make_windows

#: substeps per cycle in the coarse rounds of a fit (the plant's own, 10-20, in the last round):
#: measured on the test traces, 2-5 substeps move the gap by < 0.1 um for rigid plants; the
#: backlash contact needs 5 for the coarse search to point at the right width
COARSE_SUBSTEPS = 2
COARSE_SUBSTEPS_TWO_BODY = 5
#: a curvature of the windows' mean error below this fraction of the grid's largest mean error is
#: rounding, not information: a parameter the run does not see gets a curvature of +-1e-17 whose sign
#: depends on the CPU's BLAS kernels (seen: inf on one CPU, a finite guess on another)
FLAT_RTOL = 1e-9

#: the vocabulary parameters each effect reports (required ones; optional ones when fitted)
PARAM_NAMES: dict[str, tuple[str, ...]] = {
    name: tuple(p.name for p in e.params if not p.optional) for name, e in EFFECTS.items()
}
#: parameters a fit may carry beyond PARAM_NAMES that are still vocabulary parameters
OPTIONAL_PARAMS: dict[str, tuple[str, ...]] = {
    name: tuple(p.name for p in e.params if p.optional) for name, e in EFFECTS.items()
}


@dataclass
class Fit:
    """One fitted candidate: ``params`` are vocabulary names, ``extra`` the optional ones not reported
    as parameters of the effect (the periodic phase), ``key`` the fitter that made it."""

    effect: str
    params: dict[str, float]
    gap: float
    extra: dict[str, float] = field(default_factory=dict)
    note: str = ""
    key: str = ""
    #: standard uncertainty (one sigma, the parameter's unit) of each of ``params`` (:func:`uncertainty`;
    #: inf where the last grid cannot tell the values apart); empty for a fit not made on a grid
    uncertainty: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.key = self.key or self.effect

    @property
    def n_params(self) -> int:
        return len(self.params) + len(self.extra)

    @property
    def all_params(self) -> dict[str, float]:
        return {**self.params, **self.extra}

    def add_to(self, spec: PlantSpec) -> PlantSpec:
        return spec.with_effect(self.effect, **self.all_params)


def _scan(prep: Prepared, effect: str, grid: list[dict[str, float]], substeps: int | None = None) -> np.ndarray:
    return gaps_of(prep, [prep.spec.with_effect(effect, **p) for p in grid], substeps)


def _scan_windows(prep: Prepared, effect: str, grid: list[dict[str, float]]) -> np.ndarray:
    """Per-window mean squared error (W, C) of each grid point, at the plant's own substeps (the last,
    exact round: its gaps are ``sqrt(mean over W)``, as :func:`_scan`'s)."""
    return window_mse(prep, [prep.spec.with_effect(effect, **p) for p in grid])


def uncertainty(points: np.ndarray, mse: np.ndarray, best: int, names: tuple[str, ...]) -> dict[str, float]:
    """Standard uncertainty of the parameters of the best grid point, from the per-window errors of
    the grid: the sandwich (M-estimator) covariance of the least mean per-window error.

    A fit minimises F(x) = mean over windows w of m_w(x), the window's mean squared error. Each window
    starts from the measured state, so the windows' errors are independent samples of the noise
    (within a window they are strongly correlated, which is why the samples are not counted one by
    one). Near the best point each m_w is a quadratic fitted over the grid (one least squares for all
    windows at once); with H the mean Hessian and S the covariance of the windows' gradients at the
    best point, the best point's covariance is ``H^-1 S H^-1 / W`` (the noise moves the mean gradient
    by sqrt(S / W), the curvature turns that into a move of the minimum). The grid's own resolution
    (a step d: d / sqrt 12) is added in quadrature. Where the grid cannot tell its points apart (flat
    or concave along a parameter) that parameter's uncertainty is inf: the run says nothing about it.

    ``points``: (C, d) parameter values of the grid (``names`` their order), ``mse``: (W, C).
    """
    X = np.asarray(points, dtype=float).reshape(len(points), -1)
    d = X.shape[1]
    x0 = X[best]
    half = 0.5 * np.ptp(X, axis=0)
    scale = np.where(half > 0, half, 1.0)
    u = (X - x0) / scale
    cols = [np.ones(len(u))] + [u[:, a] for a in range(d)]
    pairs = [(a, b) for a in range(d) for b in range(a, d)]
    cols += [u[:, a] * u[:, b] for a, b in pairs]
    Q = np.column_stack(cols)
    inf = {n: math.inf for n in names}
    W = mse.shape[0]
    if W < 2 or np.linalg.matrix_rank(Q) < Q.shape[1]:
        return inf  # too few distinct values of a parameter to read a curvature
    coef, *_ = np.linalg.lstsq(Q, np.asarray(mse, dtype=float).T, rcond=None)  # (K, W)
    grads = coef[1:1 + d]  # (d, W): each window's gradient at the best point
    c = coef[1 + d:].mean(axis=1)
    H = np.zeros((d, d))
    for (a, b), v in zip(pairs, c, strict=True):
        if a == b:
            H[a, a] = 2.0 * v
        else:
            H[a, b] = H[b, a] = v
    S = np.atleast_2d(np.cov(grads, ddof=1))
    var = np.full(d, math.inf)
    flat = FLAT_RTOL * float(np.max(np.abs(np.mean(mse, axis=0))))
    try:
        ok = bool(np.all(np.linalg.eigvalsh(H) > flat))
    except np.linalg.LinAlgError:
        ok = False
    if ok:
        Hi = np.linalg.inv(H)
        var = np.diag(Hi @ S @ Hi) / W
    else:  # not a minimum in every direction jointly: each parameter alone where it has a curvature
        diag = np.diag(H)
        pos = diag > flat
        var[pos] = np.diag(S)[pos] / (diag[pos] ** 2 * W)
    out = {}
    for a, n in enumerate(names):
        vals = np.unique(X[:, a])
        step = float(np.min(np.diff(vals))) if len(vals) > 1 else 0.0
        out[n] = float(math.sqrt(max(var[a], 0.0) * scale[a] ** 2 + step * step / 12.0))
    return out


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
    sigma: dict[str, float] = {}
    for r in range(rounds + 1):
        grid = [{**fixed, name: float(v)} for v in values]
        if r == rounds:
            # only the last round's gaps are exact; it includes the best coarse point
            mse = _scan_windows(prep, effect, grid)
            gaps = np.sqrt(np.mean(mse, axis=0))
            i = int(np.argmin(gaps))
            best_v, best_g = float(values[i]), float(gaps[i])
            sigma = uncertainty(values[:, None], mse, i, (name,))
            break
        gaps = _scan(prep, effect, grid, coarse)
        i = int(np.argmin(gaps))
        a = values[max(i - 1, 0)]
        b = values[min(i + 1, len(values) - 1)]
        values = np.exp(np.linspace(math.log(a), math.log(b), 9)) if log else np.linspace(a, b, 9)
        if lo is not None:
            values = np.maximum(values, lo)
        if hi is not None:
            values = np.minimum(values, hi)
    return Fit(effect, {**fixed, name: best_v}, best_g, uncertainty=sigma)


def _fit_2d(prep: Prepared, effect: str, names: tuple[str, str], g1: np.ndarray, g2: np.ndarray,
            log: tuple[bool, bool], rounds: int = 2, coarse: int = COARSE_SUBSTEPS) -> Fit:
    """2-D grid, then 5 x 5 grids around the best point (coarse substeps but in the last round)."""
    best: tuple[float, float] = (math.nan, math.nan)
    best_g = math.inf
    a1, a2 = np.asarray(g1, float), np.asarray(g2, float)
    sigma: dict[str, float] = {}
    for r in range(rounds + 1):
        grid = [{names[0]: float(x), names[1]: float(y)} for x in a1 for y in a2]
        if r == rounds:
            mse = _scan_windows(prep, effect, grid)
            flat = np.sqrt(np.mean(mse, axis=0))
            k = int(np.argmin(flat))
            i, j = np.unravel_index(k, (len(a1), len(a2)))
            best, best_g = (float(a1[i]), float(a2[j])), float(flat[k])
            sigma = uncertainty(np.array([[g[names[0]], g[names[1]]] for g in grid]), mse, k, names)
            break
        gaps = _scan(prep, effect, grid, coarse).reshape(len(a1), len(a2))
        i, j = np.unravel_index(int(np.argmin(gaps)), gaps.shape)

        def around(arr: np.ndarray, k: int, is_log: bool) -> np.ndarray:
            lo_, hi_ = arr[max(k - 1, 0)], arr[min(k + 1, len(arr) - 1)]
            if is_log:
                return np.exp(np.linspace(math.log(lo_), math.log(hi_), 5))
            return np.linspace(lo_, hi_, 5)

        a1, a2 = around(a1, i, log[0]), around(a2, j, log[1])
    return Fit(effect, {names[0]: best[0], names[1]: best[1]}, best_g, uncertainty=sigma)


def _coulomb_level(prep: Prepared) -> tuple[float, float]:
    """The current model's total Coulomb friction (+, -); a scale from the effort when it has none."""
    d = prep.spec.design()
    fp = sum(b.fc_pos for b in d.bodies)
    fn = sum(b.fc_neg for b in d.bodies)
    if fp <= 0 and fn <= 0:
        s = 0.05 * float(np.max(np.abs(prep.effort)))
        return s, s
    return fp, fn


def fit_offset(prep: Prepared) -> Fit:
    top = max(20.0 if prep.effort_unit == "N" else 0.0, 0.5 * float(np.max(np.abs(prep.effort))))
    return _fit_1d(prep, "offset", "force", np.linspace(-top, top, 25))


def fit_spring(prep: Prepared) -> Fit:
    qmax = max(float(np.max(np.abs(prep.pos))), 1e-3)
    top = max(float(np.max(np.abs(prep.effort))), 1e-6) / qmax
    return _fit_1d(prep, "spring", "stiffness", np.linspace(0.0, top, 25), lo=0.0)


def fit_mass(prep: Prepared) -> Fit:
    m = prep.spec.nominal_mass
    return _fit_1d(prep, "mass", "mass", m * np.exp(np.linspace(math.log(0.4), math.log(2.5), 21)), log=True)


def fit_viscous(prep: Prepared) -> Fit:
    return _fit_1d(prep, "viscous", "scale", np.linspace(0.0, 3.0, 25), lo=0.0)


def fit_viscous_per_direction(prep: Prepared) -> Fit:
    """scale and scale_neg apart (direction-dependent viscous friction, as a fatigued screw shows)."""
    g = np.linspace(0.0, 3.0, 7)
    fit = _fit_2d(prep, "viscous", ("scale", "scale_neg"), g, g, (False, False), rounds=3)
    fit.key = "viscous+-"
    return fit


def fit_coulomb(prep: Prepared) -> Fit:
    fp, fn = _coulomb_level(prep)
    return _fit_2d(prep, "coulomb", ("force_pos", "force_neg"), np.linspace(0.0, 2.4, 7) * fp,
                   np.linspace(0.0, 2.4, 7) * fn, (False, False), rounds=3)


def fit_delay(prep: Prepared) -> Fit:
    return _fit_1d(prep, "delay", "delay", np.linspace(0.0, 10.0 * prep.dt, 26), lo=0.0, coarse=5)


def fit_saturation(prep: Prepared) -> Fit:
    # limits between the 10th percentile and the peak of the commanded |effort|, log-spaced: a clipped loop
    # winds up, so the peak command can be many times the limit
    mags = np.abs(prep.effort)
    peak = float(np.max(mags))
    fc = 0.5 * sum(_coulomb_level(prep))
    # down to half the Coulomb level (a drive clipped lower could not move the axis at all)
    low = max(min(float(np.percentile(mags, 10)), 0.5 * fc if fc > 0 else math.inf), 1e-4 * peak)
    fit = _fit_1d(prep, "saturation", "limit", np.exp(np.linspace(math.log(low), math.log(1.02 * peak), 81)),
                  log=True, lo=1e-6, rounds=4)
    fit.note = f"peak commanded effort {peak:.4g}"
    return fit


def fit_stribeck(prep: Prepared) -> Fit:
    fc = max(_coulomb_level(prep))
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
    """One-step force residual of the current model and the rows it is valid on.

    Each step j is simulated from the measured state (q_j, v_j) with the applied effort; the
    velocity the plant misses, divided by the plant's velocity gain per unit force, is the force
    the model lacks during that step. Valid only while the axis moves (a sticking model absorbs any
    force), so rows slower than 1 mm/s or with a reversal inside the step are dropped.
    """
    n = len(prep.pos)
    plant = prep.spec.build(prep.dt)
    # the efforts a step reads go back by the model's delay (a named `delay` of several cycles) plus two
    history = 2 + (plant.delay[0] + 1 if plant.delay else 0)
    starts = np.arange(history, n - 1)
    win = make_windows(prep.pos, prep.vel, prep.effort, prep.dt, 1, history=history, starts=starts,
                       transport=prep.transport)
    _, v_sim = BatchSim([plant]).run_with_velocity(win)
    gain = prep.dt / prep.spec.nominal_mass
    r = np.full(n, np.nan)
    r[starts] = (prep.vel[starts + 1] - v_sim[:, 0, 0]) / gain
    v = prep.vel
    ok = np.zeros(n, dtype=bool)
    ok[starts] = (np.abs(v[starts]) > 1e-3) & (np.abs(v[starts + 1]) > 1e-3) & (np.sign(v[starts]) == np.sign(
        v[starts + 1]))
    return r, ok


def _scan_power(q: np.ndarray, res: np.ndarray, kmin: float, dk: float, n: int) -> np.ndarray:
    """Periodogram ``|sum_i res_i exp(j k q_i)|^2`` at ``k = kmin + m dk``, ``m < n``.

    Each wavenumber is split as ``kmin + b M dk`` plus ``i dk`` (``M`` ~ sqrt(n)), so
    ``exp(j k q) = exp(j (kmin + b M dk) q) * exp(j i dk q)``: about 2 sqrt(n) complex exponentials per
    sample instead of 2 n sines and cosines, and one complex matrix product. The same sums (no recurrence
    to drift), ~1e-13 relative to the peak (tests/test_explain_scan.py).
    """
    m = max(1, math.isqrt(max(n - 1, 0)) + 1)
    nb = -(-n // m)
    inner = np.exp(1j * (np.arange(m)[:, None] * dk) * q[None, :])  # (M, N)
    outer = np.exp(1j * (kmin + np.arange(nb)[:, None] * (m * dk)) * q[None, :]) * res  # (B, N)
    z = (outer @ inner.T).reshape(-1)[:n]  # z[b M + i]
    return z.real * z.real + z.imag * z.imag


def _refine_wavenumber(X0: np.ndarray, y: np.ndarray, q: np.ndarray, ks: np.ndarray) -> tuple[float, float, float]:
    """(sin coefficient, k, cos coefficient) of the least squares of ``y`` on ``[X0, sin kq, cos kq]``
    with the smallest residual over ``ks``.

    All wavenumbers at once through Frisch-Waugh-Lovell: ``y`` and the sin/cos columns are projected
    off the span of ``X0`` once (its SVD, rank-cut as lstsq does), leaving a 2 x 2 solve per
    wavenumber; the same coefficients as one lstsq per wavenumber to ~1e-14
    (tests/test_explain_scan.py), a few times faster.
    """
    u, sv, _ = np.linalg.svd(X0, full_matrices=False)
    u = u[:, sv > sv[0] * np.finfo(float).eps * max(X0.shape[0], X0.shape[1] + 2)]
    r = y - u @ (u.T @ y)
    ph = q[:, None] * ks[None, :]
    S, C = np.sin(ph), np.cos(ph)
    S -= u @ (u.T @ S)
    C -= u @ (u.T @ C)
    ss, cc, sc = (np.einsum("nk,nk->k", S, S), np.einsum("nk,nk->k", C, C), np.einsum("nk,nk->k", S, C))
    hs, hc = r @ S, r @ C
    det = ss * cc - sc * sc
    a = (cc * hs - sc * hc) / det
    b = (ss * hc - sc * hs) / det
    R = r[:, None] - S * a - C * b  # residuals formed directly: no cancellation in the comparison
    i = int(np.argmin(np.einsum("nk,nk->k", R, R)))
    return float(a[i]), float(ks[i]), float(b[i])


def fit_periodic(prep: Prepared) -> Fit:
    """Period scan of the force residual against position, then a refinement on the gap."""
    r, ok = force_residual(prep)
    q, v = prep.pos[ok], prep.vel[ok]
    y = r[ok]
    if len(y) < 200:
        return Fit("periodic", {"amplitude": 0.0, "period": 0.01}, math.inf, {"phase": 0.0},
                   uncertainty={"amplitude": math.inf, "period": math.inf})
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
    power = _scan_power(q, res, kmin, dk, len(ks))
    best_k = float(ks[int(np.argmax(power))])
    # refine the wavenumber finely around the peak, with a proper 2-column least squares
    a, k, b = _refine_wavenumber(X0, y, q, np.linspace(best_k - dk, best_k + dk, 41))
    amp = math.hypot(a, b)
    phase = math.atan2(b, a) % (2 * math.pi)
    period = 2 * math.pi / k
    # refine amplitude (the residual regression sees the force through the closed loop's noise)
    grid = []
    points = []  # the same points with the phase not wrapped (a quadratic across 0 = 2 pi)
    for fa in (0.7, 0.85, 1.0, 1.15, 1.3):
        for dp in (-0.004, 0.0, 0.004):
            for dph in (-0.3, 0.0, 0.3):
                grid.append({"amplitude": amp * fa, "period": period * (1 + dp),
                             "phase": (phase + dph) % (2 * math.pi)})
                points.append((amp * fa, period * (1 + dp), phase + dph))
    mse = _scan_windows(prep, "periodic", grid)
    gaps = np.sqrt(np.mean(mse, axis=0))
    i = int(np.argmin(gaps))
    p = grid[i]
    sigma = uncertainty(np.array(points), mse, i, ("amplitude", "period", "phase"))
    if not p["amplitude"] > 2.0 * sigma["amplitude"]:
        # no force to speak of: its period is the scan's highest noise peak, anywhere in the band
        sigma["period"] = math.inf
    return Fit("periodic", {"amplitude": p["amplitude"], "period": p["period"]}, float(gaps[i]),
               {"phase": p["phase"]}, note=f"period scan peak at {period * 1e3:.3f} mm",
               uncertainty={"amplitude": sigma["amplitude"], "period": sigma["period"]})


#: fitter key -> fitter; the key names the way an effect is added (viscous has two: one scale, or per direction)
FITTERS: dict[str, Callable[[Prepared], Fit]] = {
    "offset": fit_offset,
    "spring": fit_spring,
    "mass": fit_mass,
    "viscous": fit_viscous,
    "viscous+-": fit_viscous_per_direction,
    "coulomb": fit_coulomb,
    "delay": fit_delay,
    "saturation": fit_saturation,
    "stribeck": fit_stribeck,
    "periodic": fit_periodic,
    "backlash": fit_backlash,
    "resonance": fit_resonance,
}
#: effects that split a one-mass plant into two: not tried on a plant that already has two bodies
SPLITTING = ("backlash", "resonance")


def run_fitter(key: str, prep: Prepared) -> Fit:
    """Module-level so that a worker process can run it (pickled by name)."""
    fit = FITTERS[key](prep)
    fit.key = key
    return fit


# --------------------------------------------------------------------------------------------------
# Joint refit of several named effects
# --------------------------------------------------------------------------------------------------

#: first step of the joint search per parameter: (relative to the value, absolute floor in units of
#: the trace's peak effort for forces, else in the parameter's own unit)
_STEP: dict[str, tuple[float, float]] = {
    "scale": (0.0, 0.05), "scale_neg": (0.0, 0.05), "mass": (0.05, 0.0), "delay": (0.0, 2e-4),
    "period": (0.002, 0.0), "phase": (0.0, 0.2), "velocity": (0.15, 0.0), "width": (0.15, 0.0),
    "frequency": (0.05, 0.0), "damping": (0.2, 0.0), "stiffness": (0.1, 0.0),
}
_FORCES = ("force", "force_pos", "force_neg", "excess_force", "amplitude", "limit")


def refine_jointly(prep: Prepared, nominal: PlantSpec, fits: list[Fit], iterations: int = 6) -> list[Fit]:
    """Refit the parameters of all named effects together: a batched pattern search on the gap.

    Effects named one after another can trade against each other along narrow valleys (direction-
    dependent viscous friction against a constant force: both move the force at speed), which a
    one-at-a-time refit crosses only slowly. Each iteration simulates the centre and its neighbours
    at once (all 3^n combinations of -step/0/+step up to three parameters, otherwise the axes and
    the pairwise diagonals) at coarse substeps, moves to the best, and halves the steps when the
    centre stays best.
    """
    peak = float(np.max(np.abs(prep.effort))) or 1.0
    names: list[tuple[int, str, bool]] = []  # (fit index, parameter, in extra)
    x0: list[float] = []
    steps: list[float] = []
    for i, f in enumerate(fits):
        for extra, d in ((False, f.params), (True, f.extra)):
            for k, v in d.items():
                rel, ab = (0.1, 0.01 * peak) if k in _FORCES else _STEP.get(k, (0.1, 0.0))
                names.append((i, k, extra))
                x0.append(float(v))
                steps.append(max(rel * abs(float(v)), ab) or 0.01)
    n = len(x0)
    if n == 0:
        return fits
    x = np.array(x0)
    h = np.array(steps)
    if n <= 3:
        moves = np.array(np.meshgrid(*([[-1.0, 0.0, 1.0]] * n), indexing="ij")).reshape(n, -1).T
    else:
        rows = [np.zeros(n)]
        for a in range(n):
            for sa in (-1.0, 1.0):
                r = np.zeros(n)
                r[a] = sa
                rows.append(r)
                for b in range(a + 1, n):
                    for sb in (-1.0, 1.0):
                        r2 = r.copy()
                        r2[b] = sb
                        rows.append(r2)
        moves = np.array(rows)

    def build(theta: np.ndarray) -> PlantSpec | None:
        new = [Fit(f.effect, dict(f.params), f.gap, dict(f.extra), f.note, f.key) for f in fits]
        for (i, k, extra), v in zip(names, theta, strict=True):
            (new[i].extra if extra else new[i].params)[k] = float(v)
        spec = nominal
        try:
            for f in new:
                spec = f.add_to(spec)
        except ValueError:  # a parameter out of its range (PlantError)
            return None
        return spec

    base_prep = prep.on(nominal)
    # quadratic model of the squared gap over the moves (1, u, u u^T): its minimum is tried in the next batch
    quad = [np.ones(len(moves))] + [moves[:, a] for a in range(n)]
    quad += [moves[:, a] * moves[:, b] for a in range(n) for b in range(a, n)]
    Q = np.column_stack(quad)
    jump: np.ndarray | None = None
    for _ in range(iterations):
        cands = [x + m * h for m in moves]
        if jump is not None:
            cands.append(jump)
        specs = [build(c) for c in cands]
        ok = [i for i, s in enumerate(specs) if s is not None]
        gaps = np.full(len(cands), np.inf)
        gaps[ok] = _gaps_grouped(base_prep, [specs[i] for i in ok], COARSE_SUBSTEPS)
        best = int(np.argmin(gaps))
        jump = _quadratic_minimum(Q, gaps[:len(moves)] ** 2, n)
        jump = None if jump is None else x + jump * h
        if best < len(moves) and np.all(moves[best] == 0):
            h = h / 2
        x = cands[best]
    final = build(x)
    if final is None:
        return fits
    gap = float(_gaps_grouped(base_prep, [final], None)[0])
    out = [Fit(f.effect, dict(f.params), f.gap, dict(f.extra), f.note, f.key) for f in fits]
    for (i, k, extra), v in zip(names, x, strict=True):
        (out[i].extra if extra else out[i].params)[k] = float(v)
    for f in out:
        f.gap = gap
    return out


def _gaps_grouped(prep: Prepared, specs: list[PlantSpec], substeps: int | None) -> np.ndarray:
    """Gaps of plants that may differ in body count (one batch per kind)."""
    out = np.empty(len(specs))
    for idx in batch_groups(specs):
        out[idx] = gaps_of(prep, [specs[i] for i in idx], substeps)
    return out


def batch_groups(specs: list[PlantSpec]) -> list[list[int]]:
    """Indices of ``specs`` that one batch simulation can take together: same body count, and (two bodies)
    whether the mode is linear, so that its start state can be reconstructed for every plant of the batch."""
    groups: dict[tuple[bool, bool], list[int]] = {}
    for i, s in enumerate(specs):
        d = s.design()
        two = len(d.bodies) == 2
        linear = two and not (d.coupling and d.coupling.gap) and not d.bodies[0].has_coulomb
        groups.setdefault((two, linear), []).append(i)
    return list(groups.values())


def _quadratic_minimum(Q: np.ndarray, y: np.ndarray, n: int) -> np.ndarray | None:
    """The minimum (in move units, within +-1.5) of the quadratic fitted to ``y`` over the moves, or None."""
    good = np.isfinite(y)
    if np.sum(good) < Q.shape[1]:
        return None
    coef, *_ = np.linalg.lstsq(Q[good], y[good], rcond=None)
    g = coef[1:1 + n]
    H = np.zeros((n, n))
    k = 1 + n
    for a in range(n):
        for b in range(a, n):
            if a == b:
                H[a, a] = 2 * coef[k]
            else:
                H[a, b] = H[b, a] = coef[k]
            k += 1
    try:
        if np.any(np.linalg.eigvalsh(H) <= 0):
            return None
        u = -np.linalg.solve(H, g)
    except np.linalg.LinAlgError:
        return None
    return np.clip(u, -1.5, 1.5)

"""The trend of one fitted parameter over an axis's runs, and the test for the run at which it began to
change (docs/health.md "The method"). Pure numpy/scipy: the report feeds it the store's fits.

For a series x_0..x_{n-1} in time order:

1. **The run-to-run noise** ``sigma``: from the differences between consecutive runs, their RMS about
   their median with the largest tenth (at least one) left out, over sqrt(2), unbiased for Gaussian
   noise (a step moves one difference, which is left out; a steady trend moves all alike, which the
   median takes out; the day's temperature from shift to shift is part of it); never below the fits'
   own uncertainty where the store has one (its median), nor below half the smallest step the fitter
   makes between runs (its resolution: a fitter on a grid returns the same value on most clean runs).
2. **The series tested** is the series through a running median of three (Tukey's end-point rule at
   the ends), so that one odd run moves nothing; a change must hold for two runs to be seen.
3. **The change-point test**: for every candidate onset ``k`` with at least ``MIN_BEFORE`` runs before
   and ``MIN_AFTER`` from it on, the likelihood ratio of two changes against no change, with Gaussian
   noise of ``sigma``: a step (one level before ``k``, another from ``k`` on) and a ramp (a level
   before, a straight line from it from ``k`` on: wear that grows). ``2 log LR = (RSS_0 - RSS_k) /
   sigma^2``, each chi-square with one degree of freedom when nothing changed. The largest over every
   ``k`` and both shapes is compared with its (1 - ``ALPHA``) quantile when nothing changed: measured,
   up to ``CALIBRATED_N`` runs, on Gaussian series put through the same procedure (the noise estimated
   from each series, as it is from a real one), beyond that the chi-square quantile at ``ALPHA / (number
   of tests)`` (Bonferroni over the candidates). A false alarm on a clean series has a probability of
   about ``ALPHA`` whatever its length, and no threshold is in the parameter's units.
   The change must also hold: the last ``MIN_AFTER`` runs (through the median) all lie beyond every
   run before the onset, on the side it went.
4. **The slope** from the onset on (Theil-Sen through the raw runs: the median of the slopes between
   every two, per 100 runs; its line's value at the last run is the value now), and where it leads:
   the run and time at which the line crosses the parameter's limit, if it goes towards it.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

#: the false-alarm probability of one parameter's series, over all its candidate onsets and shapes
ALPHA = 5e-3
#: runs the test needs before a candidate onset (the level it leaves) and from it on (the change held)
MIN_BEFORE = 3
MIN_AFTER = 3
#: up to this many runs the threshold is measured (Monte Carlo) rather than taken from the chi-square
CALIBRATED_N = 60
CALIBRATION_DRAWS = 40_000



@dataclass(frozen=True)
class Change:
    """A change found in a series: ``onset`` (0-based index into the series), its shape (``step`` or
    ``ramp``), the test's statistic (2 log LR) and threshold, the noise, the level before and the last,
    and the slope from the onset on (per run)."""

    onset: int
    shape: str
    statistic: float
    threshold: float
    sigma: float
    first_value: float
    last_value: float
    slope_per_run: float


def _steps(x: np.ndarray) -> np.ndarray:
    d = np.diff(x)
    if len(d):
        d[np.abs(d) <= 1e-9 * float(np.max(np.abs(x)))] = 0.0  # rounding of a value the fitter returned again
    return d


def noise_floor(x: np.ndarray, uncertainty: np.ndarray | None = None) -> float:
    """The least noise ``x`` is judged against: half the smallest step between two runs (a fitter on a
    grid returns the same value on most clean runs: its resolution), and the fits' own uncertainty
    (its median) where the store has one."""
    d = _steps(x)
    moved = np.abs(d[d != 0])
    floor = 0.5 * float(moved.min()) if len(moved) else 0.0
    if uncertainty is not None:
        u = uncertainty[np.isfinite(uncertainty)]
        if len(u):
            floor = max(floor, float(np.median(u)))
    return floor


def noise_sigma(x: np.ndarray, uncertainty: np.ndarray | None = None) -> float:
    """The run-to-run noise of ``x`` (the module's docstring, 1.), never below :func:`noise_floor`."""
    x = np.asarray(x, dtype=float)
    if len(x) < 3:
        return noise_floor(x, uncertainty)
    return max(float(_spread_rows(x[None, :])[0]), noise_floor(x, uncertainty))


def median3(x: np.ndarray) -> np.ndarray:
    """Running median of three, Tukey's end-point rule at both ends."""
    n = len(x)
    if n < 3:
        return x.copy()
    y = x.copy()
    y[1:-1] = np.median(np.stack([x[:-2], x[1:-1], x[2:]]), axis=0)
    y[0] = np.median([x[0], y[1], 3 * y[1] - 2 * y[2]])
    y[-1] = np.median([x[-1], y[-2], 3 * y[-2] - 2 * y[-3]])
    return y


@lru_cache(maxsize=512)
def _regressors(n: int) -> tuple[np.ndarray, np.ndarray, tuple[int, ...], tuple[str, ...]]:
    """Every candidate change of a series of ``n`` runs as one centred regressor each (a step at ``k``,
    a ramp from ``k``), their squared norms, onsets and shapes: with an intercept, the residual sum of
    squares falls by ``(r . y)^2 / |r|^2`` (2 log LR times sigma^2)."""
    ks = np.arange(MIN_BEFORE, n - MIN_AFTER + 1)
    i = np.arange(n, dtype=float)
    step = (i[None, :] >= ks[:, None]).astype(float)
    ramp = np.maximum(0.0, i[None, :] - ks[:, None] + 1.0)
    r = np.concatenate([step, ramp])
    r -= r.mean(axis=1, keepdims=True)
    return r, np.sum(r * r, axis=1), tuple(int(k) for k in ks) * 2, ("step",) * len(ks) + ("ramp",) * len(ks)


def _statistics(y: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """2 log LR of every candidate change for each row of ``y`` (series through the median, shape
    (D, n)) against no change, with Gaussian noise of ``sigma`` (per row)."""
    r, norm, _, _ = _regressors(y.shape[1])
    yc = y - y.mean(axis=1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(sigma[:, None] > 0, (yc @ r.T) ** 2 / norm / (sigma[:, None] ** 2), 0.0)


def _raw_spread_rows(x: np.ndarray) -> np.ndarray:
    d = np.diff(x, axis=1)
    e = np.sort((d - np.median(d, axis=1, keepdims=True)) ** 2, axis=1)
    keep = e.shape[1] - max(1, e.shape[1] // 10)
    return np.sqrt(np.mean(e[:, :keep], axis=1) / 2.0)


@lru_cache(maxsize=512)
def _spread_bias(n: int) -> float:
    """What :func:`_raw_spread_rows` gives for Gaussian noise of 1 on ``n`` runs (leaving the largest
    differences out makes it low): measured once per ``n``, the same every time (seed ``n``)."""
    rng = np.random.default_rng(n)
    return float(np.mean(_raw_spread_rows(rng.standard_normal((20_000, n)))))


def _spread_rows(x: np.ndarray) -> np.ndarray:
    """The noise of each row of ``x`` from its differences between consecutive runs: their RMS about
    their median, the largest tenth (at least one: a step's) left out, over sqrt(2), unbiased for
    Gaussian noise."""
    return _raw_spread_rows(x) / _spread_bias(x.shape[1])


def _median3_rows(x: np.ndarray) -> np.ndarray:
    y = x.copy()
    y[:, 1:-1] = np.median(np.stack([x[:, :-2], x[:, 1:-1], x[:, 2:]]), axis=0)
    y[:, 0] = np.median(np.stack([x[:, 0], y[:, 1], 3 * y[:, 1] - 2 * y[:, 2]]), axis=0)
    y[:, -1] = np.median(np.stack([x[:, -1], y[:, -2], 3 * y[:, -2] - 2 * y[:, -3]]), axis=0)
    return y


@lru_cache(maxsize=256)
def threshold(n: int) -> float:
    """The test's threshold for a series of ``n`` runs: the (1 - ALPHA) quantile of the largest 2 log LR
    over every candidate when nothing changed. Up to ``CALIBRATED_N`` runs it is measured on
    ``CALIBRATION_DRAWS`` Gaussian series put through the same procedure (the noise estimated from
    each, as from a real series: with few runs the estimate is rough and the chi-square too lenient);
    beyond, the chi-square(1) quantile at ALPHA over the number of candidates (Bonferroni)."""
    from scipy.stats import chi2

    tests = 2 * max(1, n - MIN_BEFORE - MIN_AFTER + 1)
    bonferroni = float(chi2.isf(ALPHA / tests, 1))
    if n > CALIBRATED_N:  # the noise from many runs: chi-square, never below the calibrated one
        return max(bonferroni, threshold(CALIBRATED_N))
    rng = np.random.default_rng(n)  # the same threshold every time
    peaks = []
    for _ in range(CALIBRATION_DRAWS // 4000):
        x = rng.standard_normal((4000, n))
        peaks.append(_statistics(_median3_rows(x), _spread_rows(x)).max(axis=1))
    return max(bonferroni, float(np.quantile(np.concatenate(peaks), 1.0 - ALPHA)))


def find_change(x: np.ndarray, uncertainty: np.ndarray | None = None) -> Change | None:
    """The change in ``x`` (a parameter over runs, time order), or None: too few runs, or no change
    beyond the run-to-run noise."""
    x = np.asarray(x, dtype=float)
    n = len(x)
    if n < MIN_BEFORE + MIN_AFTER:
        return None
    sigma = max(float(_spread_rows(x[None, :])[0]), noise_floor(x, uncertainty))
    y = median3(x)
    if float(np.sum((y - y.mean()) ** 2)) == 0.0 or sigma <= 0.0:
        return None
    stats = _statistics(y[None, :], np.array([sigma]))[0]
    best = int(np.argmax(stats))
    _, _, onsets, shapes = _regressors(n)
    stat, k, shape = float(stats[best]), onsets[best], shapes[best]
    limit = threshold(n)
    if stat <= limit:
        return None
    # the change holds to the end: the last MIN_AFTER runs (through the median) all beyond every run
    # before the onset, on the side it went (a swing that came back, a day's warm afternoon, is not wear)
    before, last = y[:k], y[-MIN_AFTER:]
    if not (last.min() > before.max() if y[k:].mean() > before.mean() else last.max() < before.min()):
        return None
    # the line through the runs from the onset on, Theil-Sen (the median of the slopes between every two
    # runs: a fit that fell into another minimum on one run moves it little): its slope, and its value
    # at the last run is "now"
    from scipy.stats import theilslopes

    j = np.arange(n - k, dtype=float)
    slope, at0 = (float(c) for c in theilslopes(x[k:], j)[:2])
    return Change(onset=k, shape=shape, statistic=stat, threshold=limit, sigma=sigma,
                  first_value=float(np.median(x[:k])), last_value=at0 + slope * j[-1], slope_per_run=slope)


def runs_to_limit(last: float, slope_per_run: float, limit: float, first: float) -> float | None:
    """Runs from the last until the line from ``last`` at ``slope_per_run`` reaches ``limit``: 0 when it
    is past it already (on the far side from ``first``, the level before the change), None when it
    does not go towards it."""
    above = limit >= first  # the limit is crossed from the side the level was on
    if (last >= limit) if above else (last <= limit):
        return 0.0
    if slope_per_run == 0.0 or (slope_per_run > 0) != above:
        return None
    return (limit - last) / slope_per_run

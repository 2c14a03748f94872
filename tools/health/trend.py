"""The trend of one fitted parameter over an axis's runs, and the test for the run at which it began to
change (docs/health.md "The method"). Pure numpy/scipy: the report feeds it the store's fits.

For a series x_0..x_{n-1} in time order:

1. **The run-to-run noise** ``sigma``: from the first differences, robustly,
   ``1.4826 * MAD(diff(x)) / sqrt(2)`` (a step or a slow trend moves one difference, or all of them
   alike, and leaves their spread; the day's temperature from shift to shift is part of it), never
   below the fits' own uncertainty where the store has one (its median), nor below half the smallest
   step the fitter makes between runs (its resolution: a fitter on a grid returns the same value on
   most clean runs).
2. **The series tested** is the series through a running median of three (Tukey's end-point rule at
   the ends), so that one odd run moves nothing; a change must hold for two runs to be seen.
3. **The change-point test**: for every candidate onset ``k`` with at least ``MIN_BEFORE`` runs before
   and ``MIN_AFTER`` from it on, the likelihood ratio of two changes against no change, with Gaussian
   noise of ``sigma``: a step (one level before ``k``, another from ``k`` on) and a ramp (a level
   before, a straight line from it from ``k`` on: wear that grows). ``2 log LR = (RSS_0 - RSS_k) /
   sigma^2``, each chi-square with one degree of freedom when nothing changed. The largest over every
   ``k`` and both shapes is compared with the chi-square quantile at ``ALPHA / (number of tests)``
   (Bonferroni over the candidates): a false alarm on a clean series has a probability below ``ALPHA``
   whatever its length, and no threshold is in the parameter's units.
   The change must also hold: the last ``MIN_AFTER`` runs (through the median) all lie beyond every
   run before the onset, on the side it went.
4. **The slope** from the onset on (Theil-Sen through the raw runs: the median of the slopes between
   every two, per 100 runs; its line's value at the last run is the value now), and where it leads:
   the run and time at which the line crosses the parameter's limit, if it goes towards it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: the family-wise false-alarm probability of one parameter's series (Bonferroni over its candidate onsets)
ALPHA = 1e-3
#: runs the test needs before a candidate onset (the level it leaves) and from it on (the change held)
MIN_BEFORE = 3
MIN_AFTER = 3
#: 1.4826 * MAD estimates a Gaussian's standard deviation
MAD_TO_SIGMA = 1.4826


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


def noise_sigma(x: np.ndarray, uncertainty: np.ndarray | None = None) -> float:
    """The run-to-run noise of ``x`` (see the module's docstring, 1.)."""
    d = np.diff(x)
    if len(d) == 0:
        return 0.0
    d[np.abs(d) <= 1e-9 * float(np.max(np.abs(x)))] = 0.0  # rounding of a value the fitter returned again
    mad = float(np.median(np.abs(d - np.median(d))))
    sigma = MAD_TO_SIGMA * mad / math.sqrt(2.0)
    moved = np.abs(d[d != 0])
    if len(moved):
        sigma = max(sigma, 0.5 * float(moved.min()))
    if uncertainty is not None:
        u = uncertainty[np.isfinite(uncertainty)]
        if len(u):
            sigma = max(sigma, float(np.median(u)))
    return sigma


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


def _rss_step(y: np.ndarray, k: int) -> float:
    a, b = y[:k], y[k:]
    return float(np.sum((a - a.mean()) ** 2) + np.sum((b - b.mean()) ** 2))


def _rss_ramp(y: np.ndarray, k: int) -> float:
    """A level before ``k``, then a line from that level: y = c + s * max(0, i - k + 1)."""
    i = np.arange(len(y), dtype=float)
    h = np.maximum(0.0, i - k + 1)
    design = np.stack([np.ones_like(h), h], axis=1)
    coef, *_ = np.linalg.lstsq(design, y, rcond=None)
    r = y - design @ coef
    return float(r @ r)


def threshold(n: int) -> float:
    """The test's threshold for a series of ``n`` runs: chi-square(1) at ALPHA over the tests made."""
    from scipy.stats import chi2

    tests = 2 * max(1, n - MIN_BEFORE - MIN_AFTER + 1)
    return float(chi2.isf(ALPHA / tests, 1))


def find_change(x: np.ndarray, uncertainty: np.ndarray | None = None) -> Change | None:
    """The change in ``x`` (a parameter over runs, time order), or None: too few runs, or no change
    beyond the run-to-run noise."""
    x = np.asarray(x, dtype=float)
    n = len(x)
    if n < MIN_BEFORE + MIN_AFTER:
        return None
    sigma = noise_sigma(x, uncertainty)
    y = median3(x)
    rss0 = float(np.sum((y - y.mean()) ** 2))
    if rss0 == 0.0:
        return None
    if sigma <= 0.0:  # every run the same but for a change the median kept: no noise to judge it against
        return None
    best: tuple[float, int, str] | None = None
    for k in range(MIN_BEFORE, n - MIN_AFTER + 1):
        for shape, rss in (("step", _rss_step(y, k)), ("ramp", _rss_ramp(y, k))):
            stat = (rss0 - rss) / sigma**2
            if best is None or stat > best[0]:
                best = (stat, k, shape)
    assert best is not None
    stat, k, shape = best
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

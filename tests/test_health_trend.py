"""The change-point test of drivectl health report (tools/health/trend.py) on series of known law: its
false alarms on noise, the onset of a step and of a ramp, one odd run, a fitter's grid, a swing that
comes back, and the crossing of a limit."""

from __future__ import annotations

import numpy as np
import pytest

from drivectl.tools.health.trend import MIN_AFTER, MIN_BEFORE, find_change, median3, noise_sigma, runs_to_limit


def test_noise_alone_raises_no_change_in_hundreds_of_series():
    rng = np.random.default_rng(36)
    found = sum(find_change(1.0 + 0.02 * rng.standard_normal(n)) is not None
                for n in (8, 12, 20, 40, 100) for _ in range(100))
    assert found <= 8  # the test's level is 0.5 % per series: 2.5 expected in 500


def test_heavy_tailed_noise_and_a_day_cycle_raise_no_change():
    rng = np.random.default_rng(7)
    found = 0
    for _ in range(100):
        day = 0.03 * np.sin(2 * np.pi * np.arange(30) / 3)  # three shifts a day, warm in the afternoon
        found += find_change(1.0 + day + 0.01 * rng.standard_t(3, 30)) is not None
    assert found <= 2


def test_a_step_is_found_at_its_run():
    rng = np.random.default_rng(1)
    for k in (MIN_BEFORE, 10, 25):
        x = 1.0 + 0.02 * rng.standard_normal(30)
        x[k:] += 0.12  # six times the noise
        c = find_change(x)
        assert c is not None and abs(c.onset - k) <= 1, (k, c)
        assert c.first_value == pytest.approx(1.0, abs=0.02) and c.last_value == pytest.approx(1.12, abs=0.03)


def test_a_ramp_is_found_near_its_start_with_its_slope():
    rng = np.random.default_rng(2)
    x = 20e-6 * (1 + 0.05 * rng.standard_normal(40))
    x[15:] += 1e-6 * np.arange(1, 26)  # backlash opening 1 um a run from run 15
    c = find_change(x)
    assert c is not None and 13 <= c.onset <= 17, c
    assert c.slope_per_run == pytest.approx(1e-6, rel=0.15)
    assert c.last_value == pytest.approx(45e-6, rel=0.05)


def test_one_odd_run_and_a_grid_step_are_not_a_change():
    x = np.full(20, 88.08)
    x[[3, 9, 15]] = 88.59  # a fitter on a grid: the same value on most runs, the next step on a few
    x[-1] = 83.2  # and one run whose fit fell into another minimum, the last one
    assert find_change(x) is None
    y = np.full(20, 1.0)
    y[10] = 5.0
    assert find_change(y) is None
    assert median3(np.array([1.0, 1.0, 9.0, 1.0, 1.0]))[2] == 1.0


def test_a_swing_that_comes_back_is_not_wear():
    x = 1.0 + 0.01 * np.random.default_rng(3).standard_normal(30)
    x[10:18] += 0.1  # a hot week, then back
    assert find_change(x) is None


def test_too_few_runs_and_the_noise_estimate():
    assert find_change(np.arange(MIN_BEFORE + MIN_AFTER - 1, dtype=float)) is None
    rng = np.random.default_rng(4)
    x = 0.5 * rng.standard_normal(400)
    x[200:] += 10.0  # one step moves one difference: the estimate keeps the noise
    assert noise_sigma(x) == pytest.approx(0.5, rel=0.1)
    assert noise_sigma(x, np.full(400, 2.0)) == 2.0  # never below the fits' own uncertainty


def test_runs_to_limit():
    assert runs_to_limit(10e-6, 1e-6, 20e-6, 2e-6) == pytest.approx(10.0)  # opening towards 20 um
    assert runs_to_limit(25e-6, 1e-6, 20e-6, 2e-6) == 0.0  # past it
    assert runs_to_limit(10e-6, -1e-6, 20e-6, 2e-6) is None  # closing: not towards it
    assert runs_to_limit(80.0, -2.0, 60.0, 90.0) == pytest.approx(10.0)  # a limit below, falling to it

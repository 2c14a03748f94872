"""fit_periodic's period scan (tools/explain_fit._scan_power) against the straightforward sin/cos sums."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivectl.tools.explain_fit import _scan_power


def _direct(q: np.ndarray, res: np.ndarray, ks: np.ndarray) -> np.ndarray:
    ph = ks[:, None] * q[None, :]
    s, c = np.sin(ph) @ res, np.cos(ph) @ res
    return s * s + c * c


@pytest.mark.parametrize("n_samples, span, seed", [(3000, 0.2, 1), (1500, 0.004, 2), (800, 0.03, 3)])
def test_scan_power_matches_direct_sums(n_samples: int, span: float, seed: int) -> None:
    rng = np.random.default_rng(seed)
    q = 0.05 + span * (0.5 + 0.5 * np.sin(np.linspace(0, 9, n_samples))) + rng.normal(0, 1e-6, n_samples)
    res = rng.normal(size=n_samples) + 0.3 * np.sin(2 * math.pi * q / 4e-3)
    # the scan's own grid (fit_periodic): 0.8 mm .. 50 mm periods at 1/6 of a cycle over the span
    kmin, kmax = 2 * math.pi / min(0.05, span), 2 * math.pi / 0.8e-3
    dk = 2 * math.pi / (6.0 * span)
    ks = np.arange(kmin, kmax, dk)
    want = _direct(q, res, ks)
    got = _scan_power(q, res, kmin, dk, len(ks))
    assert got.shape == want.shape
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9 * want.max())
    assert int(np.argmax(got)) == int(np.argmax(want))


@pytest.mark.parametrize("n", [1, 2, 7, 64, 65])
def test_scan_power_any_count(n: int) -> None:
    rng = np.random.default_rng(n)
    q, res = rng.uniform(0, 0.1, 200), rng.normal(size=200)
    ks = 100.0 + 7.5 * np.arange(n)
    np.testing.assert_allclose(_scan_power(q, res, 100.0, 7.5, n), _direct(q, res, ks), rtol=1e-9,
                               atol=1e-9 * _direct(q, res, ks).max())

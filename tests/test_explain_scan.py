"""fit_periodic's period scan and wavenumber refinement (tools/explain_fit) against the straightforward sums."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivectl.tools.explain.fit import _refine_wavenumber, _scan_power


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


def _refine_direct(X0: np.ndarray, y: np.ndarray, q: np.ndarray, ks: np.ndarray) -> tuple[float, float, float]:
    best = (0.0, 0.0, 0.0, -math.inf)
    for k in ks:
        Xp = np.column_stack([X0, np.sin(k * q), np.cos(k * q)])
        coef, *_ = np.linalg.lstsq(Xp, y, rcond=None)
        rss = float(np.sum((y - Xp @ coef) ** 2))
        if -rss > best[3]:
            best = (float(coef[-2]), float(k), float(coef[-1]), -rss)
    return best[:3]


@pytest.mark.parametrize("seed, one_direction", [(1, False), (2, False), (3, True)])
def test_refine_wavenumber_matches_lstsq_per_k(seed: int, one_direction: bool) -> None:
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 6, 3000)
    q = 0.1 + 0.05 * np.sin(1.3 * t) + 0.01 * np.sin(5 * t) if not one_direction else 0.1 + 0.02 * t + 0.002 * t * t
    v = np.gradient(q, t)
    pos_dir = (v > 0).astype(float)  # all ones on a one-way move: X0 rank-deficient, as on real records
    X0 = np.column_stack([np.ones_like(q), pos_dir, v, v * pos_dir, q - q.mean(), np.gradient(v, t)])
    k0 = 2 * math.pi / 3.7e-3
    y = X0 @ rng.normal(size=6) + 0.5 * np.sin(k0 * q + 1.0) + rng.normal(size=len(q))
    dk = 2 * math.pi / (6.0 * float(np.ptp(q)))
    ks = np.linspace(k0 - dk * 0.7, k0 + dk * 1.3, 41)
    a0, k0_, b0 = _refine_direct(X0, y, q, ks)
    a1, k1, b1 = _refine_wavenumber(X0, y, q, ks)
    assert k1 == k0_
    assert a1 == pytest.approx(a0, rel=1e-9) and b1 == pytest.approx(b0, rel=1e-9)

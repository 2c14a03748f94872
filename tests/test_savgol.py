"""tools/explain/savgol.py: scipy.signal's Savitzky-Golay (mode "interp") without importing scipy.signal."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import savgol_coeffs as scipy_coeffs
from scipy.signal import savgol_filter as scipy_filter

from drivectl.tools.explain.savgol import savgol_coeffs, savgol_filter


@pytest.mark.parametrize("n", [15, 16, 400])
@pytest.mark.parametrize("window,order,deriv,delta", [(15, 3, 0, 1.0), (15, 3, 1, 0.001), (5, 2, 1, 0.5),
                                                      (15, 3, 2, 0.001), (7, 1, 2, 1.0),
                                                      (15, 5, 1, 0.001), (15, 5, 0, 1.0)])
def test_same_numbers_as_scipy(n, window, order, deriv, delta):
    x = np.cumsum(np.random.default_rng(n).normal(size=n)) * 1e-6
    want = scipy_filter(x, window, order, deriv=deriv, delta=delta, mode="interp")
    assert np.array_equal(savgol_filter(x, window, order, deriv, delta), want)
    assert np.array_equal(savgol_coeffs(window, order, deriv, delta), scipy_coeffs(window, order, deriv, delta))


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="odd"):
        savgol_coeffs(14, 3)
    with pytest.raises(ValueError, match="polyorder"):
        savgol_coeffs(5, 5)
    with pytest.raises(ValueError, match="window_length"):
        savgol_filter(np.zeros(4), 5, 2)
    with pytest.raises(ValueError, match="mode"):
        savgol_filter(np.zeros(20), 5, 2, mode="mirror")

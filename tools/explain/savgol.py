"""Savitzky-Golay smoothing and derivatives of a 1-D signal (scipy's mode "interp"), without scipy.signal.

explain needs nothing else from scipy.signal, whose import costs ~1 s (a fifth of a 10 s trace's whole
run; see docs/explain.md, speed). The computation is scipy.signal.savgol_coeffs / savgol_filter's, step
for step, on the modules explain imports anyway (scipy.linalg) or cheaply (scipy.ndimage, ~0.1 s): the
least-squares coefficients of the window's polynomial, one convolution for the interior, and at each end
the polynomial fitted to the first or last window (tests/test_savgol.py checks the same numbers).
"""

from __future__ import annotations

import math

import numpy as np

_EPS = float(np.finfo(float).eps)


def savgol_coeffs(window_length: int, polyorder: int, deriv: int = 0, delta: float = 1.0) -> np.ndarray:
    """Convolution coefficients of the centred window (odd ``window_length``)."""
    from scipy.linalg import lstsq

    _check(window_length, polyorder, deriv)
    if deriv > polyorder:
        return np.zeros(window_length)
    half = window_length // 2
    x = np.arange(-half, window_length - half, dtype=float)[::-1]  # reversed: applied as a convolution
    a = x ** np.arange(polyorder + 1, dtype=float).reshape(-1, 1)
    y = np.zeros(polyorder + 1)
    y[deriv] = float(math.factorial(deriv)) / delta ** deriv
    return lstsq(a, y, cond=_EPS * max(a.shape))[0]


def savgol_filter(x: np.ndarray, window_length: int, polyorder: int, deriv: int = 0,
                  delta: float = 1.0, mode: str = "interp") -> np.ndarray:
    """The smoothed signal (``deriv`` = 0) or its derivative, ends from the fitted end windows (the only
    ``mode``, named as scipy names it)."""
    from scipy.ndimage import convolve1d

    if mode != "interp":
        raise ValueError(f"savgol_filter: mode {mode!r}: only 'interp'")
    x = np.asarray(x, dtype=float)
    if x.ndim != 1 or window_length > len(x):
        raise ValueError(f"savgol_filter: need a 1-D signal of at least window_length = {window_length} samples")
    y = convolve1d(x, savgol_coeffs(window_length, polyorder, deriv, delta), mode="constant")
    n, half = len(x), window_length // 2
    y[:half] = _edge(x[:window_length], 0, half, polyorder, deriv, delta)
    y[n - half:] = _edge(x[n - window_length:], window_length - half, window_length, polyorder, deriv, delta)
    return y


def _check(window_length: int, polyorder: int, deriv: int) -> None:
    if window_length < 1 or window_length % 2 == 0:
        raise ValueError(f"savgol: window_length must be odd and positive, got {window_length}")
    if not 0 <= polyorder < window_length:
        raise ValueError(f"savgol: polyorder must be in 0 .. window_length - 1, got {polyorder}")
    if deriv < 0:
        raise ValueError(f"savgol: deriv must be >= 0, got {deriv}")


def _edge(xw: np.ndarray, i0: int, i1: int, polyorder: int, deriv: int, delta: float) -> np.ndarray:
    """Values i0 .. i1 - 1 of the ``polyorder`` polynomial fitted to the window ``xw`` (or its derivative)."""
    from scipy.linalg import lstsq

    t = np.arange(0, len(xw), dtype=float)
    lhs = t[:, None] ** np.arange(polyorder + 1, dtype=float)[::-1][None, :]
    scale = np.sqrt(np.sum(lhs * lhs, axis=0))  # columns scaled to unit norm before the least squares
    lhs /= scale
    c = lstsq(lhs, xw.reshape(-1, 1), cond=len(t) * _EPS)[0]
    c = (c.T / scale).T  # highest power first, (polyorder + 1, 1)
    if deriv > 0:
        m = c.shape[0]
        if m <= deriv:
            c = np.zeros_like(c[:1])
        else:
            c = c[:-deriv].copy()
            for k in range(deriv):
                c *= np.arange(m - k - 1, deriv - k - 1, -1, dtype=float).reshape(m - deriv, 1)
    i = np.arange(i0, i1, dtype=float).reshape(-1, 1)
    v = np.zeros_like(i)
    for j in range(c.shape[0]):  # Horner
        v = v * i + c[j, ...]
    return (v / delta ** deriv).reshape(-1)

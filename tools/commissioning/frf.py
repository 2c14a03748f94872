"""Frequency responses of an axis: the model's (exact ZOH discretisation of a plant spec's linear
part), the closed-loop estimate from a run with a known excitation, and the mode found in it. Used by
`drivectl bode` (tools/commissioning/bode.py) and the two-mass identification.

Estimation: the first period is dropped (transient), the remaining whole periods are averaged with
Welch's method using a rectangular window one period long, so every excited line falls exactly on
a bin (no leakage). Because the loop is closed, the plain ``H1 = S_uy / S_uu`` is biased wherever
noise enters the loop (quantisation, disturbances) and the controller feeds it back into ``u``; the
estimate used is the joint input-output one, ``H = S_ry / S_ru`` with ``r`` the injected excitation,
which is unbiased in closed loop because ``r`` is uncorrelated with that noise. ``coherence`` is the
ordinary ``u``-``y`` magnitude-squared coherence (how linear and noise-free the line is).

Mode: a lightly damped mode shows as a peak of the accelerance ``|H| w^2`` (a rigid body is flat
there, so the 1/w^2 roll-off of position does not hide the peak), with a phase drop of about 180 deg
through it. The peak is interpolated with a parabola in dB over the three lines around it; it counts
as a mode only if it stands out (prominence) and the phase, with the known delays removed, drops.

Model: the linear part of the same plant spec (bodies, viscous friction, coupling spring/damper,
table spring; Coulomb friction and dead zones have no FRF and are left out), discretised exactly for
the zero-order hold and delayed by the one-cycle transport delay of cyclic synchronous torque (plus
any extra input delay of the spec): ``pos_k`` first sees ``u_k`` at row k + 2. Its mode is the natural
frequency ``|lambda| / 2 pi`` of its lightly damped eigenvalue pair (two-mass: sqrt(k / mu) / 2 pi).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm

from drivectl.plant_emulator.models import Design, PlantSpec

#: a peak of the accelerance must rise this much (dB) above its surroundings to be called a mode
MIN_PROMINENCE_DB = 6.0
#: ... the phase, delays removed, must drop at least this much (deg) across it (a mode: ~180)
MIN_PHASE_DROP_DEG = 90.0
#: lines with a coherence below this are not used to locate the mode
MIN_COHERENCE = 0.5
#: a model eigenvalue pair counts as a mode if its damping ratio is below this
MODE_MAX_DAMPING = 0.3


class BodeError(ValueError):
    """Bad input to the measurement (amplitude, band, seconds); one line."""


# --------------------------------------------------------------------------------------------------
# Model
# --------------------------------------------------------------------------------------------------


def linear_matrices(design: Design) -> tuple[np.ndarray, np.ndarray]:
    """Continuous (Ac, Bc) of the design's linear part: state [x0, v0, (x1, v1)], effort on body 0.

    As Plant._matrices, but with the mean of direction-dependent viscous levels and the coupling
    always engaged (a dead zone has no small-signal FRF); Coulomb friction is left out."""
    n = len(design.bodies)
    ac = np.zeros((2 * n, 2 * n))
    bc = np.zeros((2 * n, 1))
    for i, b in enumerate(design.bodies):
        ac[2 * i, 2 * i + 1] = 1.0
        ac[2 * i + 1, 2 * i + 1] = -0.5 * (b.c_pos + b.c_neg) / b.mass
    bc[1, 0] = 1.0 / design.bodies[0].mass
    table = n - 1
    ac[2 * table + 1, 2 * table] -= design.table_stiffness / design.bodies[table].mass
    if design.coupling is not None and n == 2:
        k, c = design.coupling.stiffness, design.coupling.damping
        m0, m1 = design.bodies[0].mass, design.bodies[1].mass
        ac[1, :] += np.array([-k, -c, k, c]) / m0
        ac[3, :] += np.array([k, c, -k, -c]) / m1
    return ac, bc


def model_frf(spec: PlantSpec, dt: float, freqs: np.ndarray, *, transport_cycles: int = 1) -> np.ndarray:
    """Complex FRF from the recorded effort to the recorded table position, as the loop samples them:
    exact ZOH discretisation of the linear part, ``transport_cycles`` cycles of transport delay and
    the spec's extra input delay."""
    design = spec.design()
    ac, bc = linear_matrices(design)
    nx = ac.shape[0]
    aug = np.zeros((nx + 1, nx + 1))
    aug[:nx, :nx] = ac
    aug[:nx, nx:] = bc
    e = expm(aug * dt)
    ad, bd = e[:nx, :nx], e[:nx, nx:]
    cvec = np.zeros(nx)
    cvec[-2] = 1.0  # table position
    z = np.exp(1j * 2 * math.pi * np.asarray(freqs, dtype=float) * dt)
    eye = np.eye(nx)
    h = np.array([cvec @ np.linalg.solve(zi * eye - ad, bd[:, 0]) for zi in z])
    delay = transport_cycles * dt + design.input_delay
    return h * np.exp(-1j * 2 * math.pi * np.asarray(freqs) * delay)


def model_modes(spec: PlantSpec) -> list[float]:
    """Natural frequencies (Hz) of the lightly damped eigenvalue pairs of the linear model."""
    ac, _ = linear_matrices(spec.design())
    out = []
    for lam in np.linalg.eigvals(ac):
        wn = abs(lam)
        if lam.imag > 0 and wn > 0 and -lam.real / wn < MODE_MAX_DAMPING:
            out.append(float(wn / (2 * math.pi)))
    return sorted(out)


# --------------------------------------------------------------------------------------------------
# Estimation and the mode
# --------------------------------------------------------------------------------------------------


@dataclass
class Mode:
    """A resonance found in a FRF: frequency, how far it stands out, how much the phase drops."""

    freq_hz: float
    prominence_db: float
    phase_drop_deg: float


def find_mode(freqs: np.ndarray, h: np.ndarray, coherence: np.ndarray, delay_s: float) -> Mode | None:
    """The most prominent accelerance peak that qualifies as a mode (see the module doc), or None."""
    from scipy import signal  # here: the CLI imports this module to build its parser (0.9 s of scipy.signal)

    w = 2 * math.pi * freqs
    acc_db = 20 * np.log10(np.maximum(np.abs(h) * w**2, 1e-300))
    good = coherence >= MIN_COHERENCE
    masked = np.where(good, acc_db, np.nan)
    # find_peaks needs finite values: bad lines get the floor so they never form a peak
    floor = np.nanmin(masked) if np.any(good) else 0.0
    peaks, props = signal.find_peaks(np.nan_to_num(masked, nan=floor), prominence=MIN_PROMINENCE_DB)
    if len(peaks) == 0:
        return None
    phase = np.unwrap(np.angle(h * np.exp(1j * w * delay_s)))
    for i in peaks[np.argsort(props["prominences"])[::-1]]:
        if i == 0 or i == len(freqs) - 1:
            continue
        # parabola through the three lines in dB: the vertex is the peak between the lines
        y0, y1, y2 = acc_db[i - 1 : i + 2]
        denom = y0 - 2 * y1 + y2
        off = 0.5 * (y0 - y2) / denom if denom < 0 else 0.0
        f_peak = float(freqs[i] + off * (freqs[i + 1] - freqs[i]))
        lo = int(np.searchsorted(freqs, f_peak / 1.3))
        hi = min(int(np.searchsorted(freqs, f_peak * 1.3)), len(freqs) - 1)
        drop = float(np.degrees(phase[lo] - phase[hi]))
        if drop >= MIN_PHASE_DROP_DEG:
            prom = float(props["prominences"][list(peaks).index(i)])
            return Mode(f_peak, prom, drop)
    return None


def estimate_frf(r: np.ndarray, u: np.ndarray, y: np.ndarray, n: int, dt: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(freqs, H = S_ry / S_ru, u-y coherence) over whole periods of ``n`` samples (first dropped)."""
    from scipy import signal

    periods = len(u) // n
    if periods < 3:
        raise BodeError(f"bode: {len(u)} samples hold {periods} excitation periods of {n}; need at least 3")
    sl = slice(n, periods * n)  # drop the first period: the loop's transient
    kw = {"fs": 1.0 / dt, "window": "boxcar", "nperseg": n, "noverlap": 0, "detrend": "constant"}
    f, s_ry = signal.csd(r[sl], y[sl], **kw)
    _, s_ru = signal.csd(r[sl], u[sl], **kw)
    _, coh = signal.coherence(u[sl], y[sl], **kw)
    with np.errstate(divide="ignore", invalid="ignore"):
        h = s_ry / s_ru
    return f, h, coh

"""Stability margins of an axis's loop, measured: `drivectl bode --loop open`.

The measurement (as the servo tools of the trade take it): a known multisine ``r`` is added to the
controller's output inside the running loop (:class:`~drivectl.tools.commissioning.bode_excitation.
ExcitedController`), so the effort the drive applies is ``u = r + c`` with ``c`` the law's own effort. With
the loop broken at the effort, ``u = S r``: the sensitivity ``S = 1 / (1 + L)`` is the ratio of the
recorded effort to the injected disturbance at every excited line, and the open loop is ``L = (1 - S) / S``.
The position is not needed, so the encoder's quantisation enters only through the law's response to it.

Estimate, per line: the first period is dropped (the loop's transient); each remaining period gives
``S_p = U_p / R`` (one DFT bin per line, no leakage: whole periods, a rectangular window); ``S`` is their
mean, its standard error ``std(S_p) / sqrt(P)`` is the point's uncertainty, and the r-u coherence
``|sum U_p|^2 / (P sum |U_p|^2)`` says how much of ``u`` the excitation explains. ``sigma_L`` follows
from ``dL = -dS / S^2``.

Margins (:func:`margins_of`), from the lines whose coherence is at least :data:`MIN_COHERENCE` and whose
L is known to :data:`MAX_REL_ERROR` (relative standard error):

* gain margin: at each phase crossover (L crosses the negative real axis between two lines, found by
  linear interpolation of the angle of -L), ``-20 log10 |L|``; the one nearest 0 dB is reported (as
  python-control's ``stability_margins`` chooses);
* phase margin: at each gain crossover (``|L|`` crosses 1, interpolated in log |L| over log f),
  ``arg L + 180 deg``; the one nearest 0 is reported;
* the sensitivity peak ``Ms = max |S|`` (the modulus margin is ``1 / Ms``, the distance of the Nyquist
  curve from -1), its peak refined by a parabola through the three lines about it;
* the closed loop's bandwidth: where ``|T| = |1 - S|`` first falls below -3 dB.

Each comes with its uncertainty, propagated from the points' standard errors (one standard error). A
crossover that does not lie between two excited lines is not extrapolated: the value is None and the
note says where it lies (below or above the band, or at its edge).

A law with a linear form (``Controller.linear_form``: pid, pid-dob, mbc) gives the model's loop beside the
measurement (:func:`model_loop`, numpy only: the linear part of the model, exact ZOH, the one-cycle
transport delay). A nonlinear law (sliding mode, time-delay estimation) has no L; its measured "margins"
are describing-function estimates at the excitation's level, and are named so.

Library: :func:`measure_open_loop` -> :class:`OpenLoopResult`. CLI: `drivectl bode --loop open`
(tools/commissioning/bode.py).
"""

from __future__ import annotations

import io
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from drivectl.machine.config import MachineConfig
from drivectl.plant_emulator.models import PlantSpec
from drivectl.tools.commissioning.frf import BodeError, linear_matrices

#: lines whose r-u coherence is below this are left out of the margin search (the loop cancels the
#: excitation where its gain is high: S is small there and the law's response to quantisation dominates)
MIN_COHERENCE = 0.8
#: ... and lines whose L has a relative standard error above this (its phase uncertain by more than ~15 deg:
#: where |L| is tiny, S ~ 1 and the law's response to quantisation sets L's phase; z above 230 Hz read dozens
#: of spurious phase crossovers at |L| ~ -50 dB without it)
MAX_REL_ERROR = 0.25
#: default band of the open-loop measurement, Hz: the margins of a 1 kHz loop lie between a few Hz and
#: Nyquist; u = S r needs no position response, so the high lines are as clean as the low ones
OPEN_FMIN, OPEN_FMAX = 2.0, 450.0
#: |T| at the bandwidth
MINUS_3DB = 10 ** (-3.0103 / 20)
#: the predicted excitation may move the axis at most this share of its following-error window
FOLLOWING_SHARE = 0.5
#: the JSON object, key by key (the issue's contract)
JSON_KEYS = ("axis", "controller", "gm_db", "gm_hz", "pm_deg", "pm_hz", "ms", "bandwidth_hz", "coherence_min")


@dataclass
class Value:
    """A measured quantity: its value, its standard error, and a note (why it is None, or a caveat)."""

    value: float | None
    sigma: float | None = None
    note: str = ""

    def text(self, unit: str, fmt: str = ".2f") -> str:
        if self.value is None:
            return f"- ({self.note})" if self.note else "-"
        sig = f" +- {self.sigma:{fmt}}" if self.sigma is not None and math.isfinite(self.sigma) else ""
        return f"{self.value:{fmt}}{sig} {unit}".rstrip()


@dataclass
class Margins:
    gm_db: Value
    gm_hz: Value
    pm_deg: Value
    pm_hz: Value
    ms: Value
    ms_hz: Value
    bandwidth_hz: Value
    coherence_min: float | None
    band: tuple[float, float]
    #: every crossover found: (gain margin dB, Hz) at each phase crossover, (phase margin deg, Hz) at each gain one
    phase_crossovers: list[tuple[float, float]] = field(default_factory=list)
    gain_crossovers: list[tuple[float, float]] = field(default_factory=list)


# --------------------------------------------------------------------------------------------------
# Estimation
# --------------------------------------------------------------------------------------------------


def sensitivity(r: np.ndarray, u: np.ndarray, n: int, freqs: np.ndarray, dt: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(S, its standard error, the r-u coherence) at ``freqs`` (excited lines), over whole periods of
    ``n`` samples, the first dropped."""
    periods = len(u) // n
    if periods < 3:
        raise BodeError(f"bode: {len(u)} samples hold {periods} excitation periods of {n}; need at least 3")
    bins = np.rint(np.asarray(freqs) * n * dt).astype(int)
    rf = np.fft.rfft(r[:n])[bins]
    uf = np.fft.rfft(np.asarray(u[n:periods * n], dtype=float).reshape(periods - 1, n), axis=1)[:, bins]
    sp = uf / rf
    s = sp.mean(axis=0)
    p = sp.shape[0]
    sigma = np.sqrt(np.sum(np.abs(sp - s) ** 2, axis=0) / (p - 1) / p)
    coh = np.abs(uf.sum(axis=0)) ** 2 / (p * np.sum(np.abs(uf) ** 2, axis=0))
    return s, sigma, coh


def open_loop_of(s: np.ndarray, sigma_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """L = (1 - S) / S and its standard error |dS| / |S|^2."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return (1.0 - s) / s, sigma_s / np.abs(s) ** 2


def plant_response(spec: PlantSpec, dt: float, freqs: np.ndarray, *, transport_cycles: int = 1) -> np.ndarray:
    """The model's linear part from the effort to the sampled [table position, table velocity], exact ZOH,
    ``transport_cycles`` of transport delay plus the spec's extra input delay: shape (len(freqs), 2)."""
    from drivectl.controllers.linear_model import discretise

    design = spec.design()
    ad, bd = discretise(*linear_matrices(design), dt)
    nx = ad.shape[0]
    c = np.zeros((2, nx))
    c[0, -2] = c[1, -1] = 1.0
    f = np.asarray(freqs, dtype=float)
    z = np.exp(1j * 2 * math.pi * f * dt)
    x = np.linalg.solve(z[:, None, None] * np.eye(nx) - ad, np.broadcast_to(bd, (len(z), nx, 1)))[:, :, 0]
    h = x @ c.T
    delay = transport_cycles * dt + design.input_delay
    return h * np.exp(-1j * 2 * math.pi * f * delay)[:, None]


def model_loop(controller: Any, spec: PlantSpec, dt: float, freqs: np.ndarray) -> np.ndarray | None:
    """The model's open loop ``L = -K P`` at ``freqs`` for a law with a linear form, else None."""
    form = controller.linear_form()
    if form is None:
        return None
    k = form.response(freqs)
    p = plant_response(spec, dt, freqs)
    return -np.sum(k * p, axis=1)


# --------------------------------------------------------------------------------------------------
# Margins
# --------------------------------------------------------------------------------------------------


def _lerp(a: np.ndarray, i: int, t: float) -> float:
    return float(a[i] + t * (a[i + 1] - a[i]))


def _logf(f: np.ndarray, i: int, t: float) -> float:
    return float(math.exp(math.log(f[i]) + t * (math.log(f[i + 1]) - math.log(f[i]))))


def margins_of(freqs: np.ndarray, loop: np.ndarray, sigma: np.ndarray | None = None,
               coherence: np.ndarray | None = None, band: tuple[float, float] | None = None) -> Margins:
    """The margins of the loop ``loop`` sampled at ``freqs`` (ascending, Hz), with the points' standard
    errors ``sigma`` (None: an exact model) and their coherence (lines below :data:`MIN_COHERENCE`, or
    whose relative error exceeds :data:`MAX_REL_ERROR`, are left out). See the module text."""
    freqs = np.asarray(freqs, dtype=float)
    loop = np.asarray(loop, dtype=complex)
    band = band or (float(freqs[0]), float(freqs[-1]))
    sig = np.zeros(len(freqs)) if sigma is None else np.asarray(sigma, dtype=float)
    use = np.isfinite(loop) & np.isfinite(sig) & (np.abs(loop) > 0)
    if coherence is not None:
        use &= np.asarray(coherence) >= MIN_COHERENCE
    with np.errstate(divide="ignore", invalid="ignore"):
        use &= sig <= MAX_REL_ERROR * np.abs(loop)
    f, lp, sg = freqs[use], loop[use], sig[use]
    coh_min = None if coherence is None or not use.any() else float(np.min(np.asarray(coherence)[use]))
    where = f"{band[0]:g}-{band[1]:g} Hz"
    if len(f) < 3:
        none = Value(None, None, f"fewer than 3 coherent lines in {where}")
        return Margins(none, none, none, none, none, none, none, coh_min, band)
    mag = np.abs(lp)
    rel = sg / mag  # relative error of L: the error of ln|L| and of arg L (rad)
    lnm = np.log(mag)
    # phase margin: gain crossovers
    pms: list[tuple[float, float, float, float]] = []
    for i in range(len(f) - 1):
        a, b = lnm[i], lnm[i + 1]
        if a == 0 or a * b < 0:
            t = a / (a - b)
            fc = _logf(f, i, t)
            z = lp[i] * (lp[i + 1] / lp[i]) ** t  # log-interpolation of L: magnitude and (short-way) phase
            pm = float(np.remainder(np.degrees(np.angle(z)), 360.0) - 180.0)
            e = _lerp(rel, i, t)
            sf = e * (f[i + 1] - f[i]) / abs(b - a)
            pms.append((pm, math.degrees(e), fc, sf))
    if pms:
        pm = min(pms, key=lambda x: abs(x[0]))
        pm_v, pm_f = Value(pm[0], pm[1]), Value(pm[2], pm[3])
    else:
        side = "above" if lnm.min() > 0 else "below" if lnm.max() < 0 else "outside"
        note = f"no gain crossover in {where}: |L| {'> 1' if side == 'above' else '< 1'} on every coherent line, " \
               f"the crossover lies {side} the excited band; not extrapolated"
        pm_v = pm_f = Value(None, None, note)
    # gain margin: phase crossovers (L crosses the negative real axis)
    h = np.angle(-lp)
    gms: list[tuple[float, float, float, float]] = []
    for i in range(len(f) - 1):
        a, b = h[i], h[i + 1]
        if (a == 0 or a * b < 0) and abs(a - b) < math.pi:
            t = a / (a - b)
            fc = _lerp(f, i, t)
            lm = _lerp(lnm, i, t)
            e = _lerp(rel, i, t)
            sf = e * (f[i + 1] - f[i]) / abs(b - a)
            gms.append((-20 * lm / math.log(10), 20 * e / math.log(10), fc, sf))
    if gms:
        gm = min(gms, key=lambda x: abs(x[0]))
        gm_v, gm_f = Value(gm[0], gm[1]), Value(gm[2], gm[3])
    else:
        note = f"no phase crossover in {where}: L does not cross the negative real axis on the excited lines; " \
               "not extrapolated"
        gm_v = gm_f = Value(None, None, note)
    # sensitivity peak
    d = np.abs(1.0 + lp)
    i = int(np.argmin(d))
    if i in (0, len(f) - 1):
        note = f"the peak of |S| is at the band's edge ({f[i]:g} Hz, |S| {1 / d[i]:.3g}): it may lie outside; " \
               "not extrapolated"
        ms_v = ms_f = Value(None, None, note)
    else:
        c2, c1, c0 = np.polyfit(f[i - 1:i + 2] - f[i], d[i - 1:i + 2], 2)
        dmin, fmin_ = float(d[i]), float(f[i])
        if c2 > 0:
            x = -c1 / (2 * c2)
            if abs(x) <= max(f[i + 1] - f[i], f[i] - f[i - 1]):
                dmin, fmin_ = float(c0 - c1 * c1 / (4 * c2)), float(f[i] + x)
        dmin = min(dmin, float(d[i]))
        ms = 1.0 / dmin
        # |S| = 1 / |1 + L|: d|S| = |dL| |S|^2
        ms_v = Value(ms, float(sg[i]) * ms * ms)
        ms_f = Value(fmin_)
    # bandwidth of T = L / (1 + L)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_mag = np.abs(lp / (1.0 + lp))
    t_sig = sg / np.abs(1.0 + lp) ** 2  # |dT| = |dS| = |dL| |S|^2
    if t_mag[0] < MINUS_3DB:
        bw = Value(None, None, f"|T| is below -3 dB at the lowest coherent line ({f[0]:g} Hz): the bandwidth lies "
                   "below the excited band; not extrapolated")
    else:
        below = np.flatnonzero(t_mag < MINUS_3DB)
        if len(below) == 0:
            bw = Value(None, None, f"|T| stays above -3 dB up to {f[-1]:g} Hz: the bandwidth lies above the excited "
                       "band; not extrapolated")
        else:
            j = int(below[0]) - 1
            a, b = math.log(t_mag[j] / MINUS_3DB), math.log(t_mag[j + 1] / MINUS_3DB)
            t = a / (a - b)
            e = _lerp(t_sig / t_mag, j, t)
            bw = Value(_logf(f, j, t), e * (f[j + 1] - f[j]) / abs(b - a))
    return Margins(gm_v, gm_f, pm_v, pm_f, ms_v, ms_f, bw, coh_min, band, [(g[0], g[2]) for g in gms],
                   [(p[0], p[2]) for p in pms])


def margins_batch(freqs: np.ndarray, loops: np.ndarray) -> dict[str, np.ndarray]:
    """The margins of many model loops at once (rows of ``loops``, sampled at ``freqs``), with the same
    crossovers, interpolation and choice as :func:`margins_of` (no noise, no coherence): arrays per row of
    ``gm_db`` (nearest 0 dB; +inf with no phase crossover), ``pm_deg`` (nearest 0 deg; +inf with no gain
    crossover: never a binding margin), ``ms`` (the largest |S| on the grid, parabola-refined) and
    ``bandwidth_hz`` (nan where |T| does not fall through -3 dB on the grid). For ``tune --target``."""
    f = np.asarray(freqs, dtype=float)
    lp = np.asarray(loops, dtype=complex)
    lnm = np.log(np.maximum(np.abs(lp), 1e-300))
    a, b = lnm[:, :-1], lnm[:, 1:]
    cross = (a == 0) | (a * b < 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(cross, a / (a - b), 0.0)
        z = lp[:, :-1] * (lp[:, 1:] / lp[:, :-1]) ** t
    pm = np.where(cross, np.remainder(np.degrees(np.angle(z)), 360.0) - 180.0, np.inf)
    pm_near = np.take_along_axis(pm, np.argmin(np.abs(pm), axis=1)[:, None], axis=1)[:, 0]
    h = np.angle(-lp)
    ha, hb = h[:, :-1], h[:, 1:]
    pc = ((ha == 0) | (ha * hb < 0)) & (np.abs(ha - hb) < math.pi)
    with np.errstate(divide="ignore", invalid="ignore"):
        tp = np.where(pc, ha / (ha - hb), 0.0)
    gm = np.where(pc, -20 * (a + tp * (b - a)) / math.log(10), np.inf)
    gm_near = np.take_along_axis(gm, np.argmin(np.abs(gm), axis=1)[:, None], axis=1)[:, 0]
    d = np.abs(1.0 + lp)
    i = np.clip(np.argmin(d, axis=1), 1, len(f) - 2)
    rows = np.arange(len(lp))
    d0, d1, d2 = d[rows, i - 1], d[rows, i], d[rows, i + 1]
    curv = d0 - 2 * d1 + d2  # uniform grid: the parabola's vertex
    with np.errstate(divide="ignore", invalid="ignore"):
        vertex = np.where(curv > 0, d1 - (d2 - d0) ** 2 / (8 * curv), d1)
    ms = 1.0 / np.minimum(np.minimum(vertex, d1), d.min(axis=1))
    with np.errstate(divide="ignore", invalid="ignore"):
        tm = np.abs(lp / (1.0 + lp))
    below = tm < MINUS_3DB
    first = np.argmax(below, axis=1)
    ok = below.any(axis=1) & (first > 0)
    j = np.maximum(first - 1, 0)
    ta, tb = np.log(tm[rows, j] / MINUS_3DB), np.log(tm[rows, j + 1] / MINUS_3DB)
    with np.errstate(divide="ignore", invalid="ignore"):
        tt = ta / (ta - tb)
        bw = np.exp(np.log(f[j]) + tt * (np.log(f[j + 1]) - np.log(f[j])))
    return {"gm_db": gm_near, "pm_deg": pm_near, "ms": ms, "bandwidth_hz": np.where(ok, bw, np.nan)}


# --------------------------------------------------------------------------------------------------
# The measurement
# --------------------------------------------------------------------------------------------------


@dataclass
class OpenLoopResult:
    axis: str
    controller: str
    linear: bool  # the law has a linear form (else: describing-function estimates)
    plant: str
    bus: str
    amplitude: float
    effort_unit: str
    freqs: np.ndarray
    s: np.ndarray
    sigma_s: np.ndarray
    coherence: np.ndarray
    loop: np.ndarray
    sigma_loop: np.ndarray
    model_loop: np.ndarray | None
    margins: Margins | None
    model_margins: Margins | None
    periods: int
    trace: Any
    stop: str = "completed"
    detail: str = ""
    bias_velocity: float = 0.0
    stood_share: float = 0.0
    files: list[Path] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.stop == "completed"

    @property
    def kind(self) -> str:
        return "linear form" if self.linear else "nonlinear law: describing-function estimate"

    def to_json(self) -> dict[str, Any]:
        m = self.margins

        def r(v: Value | None, nd: int) -> float | None:
            return None if v is None or v.value is None else round(v.value, nd)

        return {"axis": self.axis, "controller": self.controller,
                "gm_db": r(m and m.gm_db, 3), "gm_hz": r(m and m.gm_hz, 3), "pm_deg": r(m and m.pm_deg, 3),
                "pm_hz": r(m and m.pm_hz, 3), "ms": r(m and m.ms, 4), "bandwidth_hz": r(m and m.bandwidth_hz, 3),
                "coherence_min": None if m is None or m.coherence_min is None else round(m.coherence_min, 4)}

    def csv_text(self) -> str:
        out = io.StringIO()
        out.write(f"# drivectl bode --loop open: axis {self.axis}, plant {self.plant}, {self.bus}, controller "
                  f"{self.controller} ({self.kind}); S = u / r, L = (1 - S) / S; multisine peak {self.amplitude:g} "
                  f"{self.effort_unit}, {self.periods - 1} periods averaged; sigma = one standard error\n")
        out.write("freq_hz,s_mag_db,s_phase_deg,l_mag_db,l_phase_deg,sigma_l,coherence,model_l_mag_db,"
                  "model_l_phase_deg\n")
        ml = self.model_loop if self.model_loop is not None else np.full(len(self.freqs), np.nan + 0j)
        data = np.column_stack([self.freqs, _db(self.s), np.degrees(np.angle(self.s)), _db(self.loop),
                                np.degrees(np.angle(self.loop)), self.sigma_loop, self.coherence, _db(ml),
                                np.degrees(np.angle(ml))])
        np.savetxt(out, data, fmt=["%.6g", "%.5f", "%.4f", "%.5f", "%.4f", "%.4g", "%.6f", "%.5f", "%.4f"],
                   delimiter=",")
        return out.getvalue()


def _db(h: np.ndarray) -> np.ndarray:
    return 20 * np.log10(np.maximum(np.abs(h), 1e-300))


def predicted_motion(controller: Any, spec: PlantSpec, one: np.ndarray, dt: float) -> tuple[float, float] | None:
    """For a law with a linear form: the peak position deviation (m) and the peak effort (effort unit) of
    the loop on the model driven by one period of the excitation, in periodic steady state; else None."""
    n = len(one)
    x = np.fft.rfft(one)
    f = np.fft.rfftfreq(n, dt)
    on = np.flatnonzero(np.abs(x) > 1e-9 * np.max(np.abs(x)))
    loop = model_loop(controller, spec, dt, f[on])
    if loop is None:
        return None
    s = 1.0 / (1.0 + loop)
    u = np.zeros_like(x)
    y = np.zeros_like(x)
    u[on] = x[on] * s
    y[on] = u[on] * plant_response(spec, dt, f[on])[:, 0]
    return float(np.max(np.abs(np.fft.irfft(y, n)))), float(np.max(np.abs(np.fft.irfft(u, n))))


def aligned_period(spec: PlantSpec, period_s: float) -> float:
    """``period_s`` rounded up to a whole number of periods of the disturbance the model names (two-mass:
    0.5 Hz, so 2 s): it then falls on a bin of its own and leaks into no excited line (at 1 s it leaked
    into the lowest lines as much as the excitation put there, and the loop's gain crossover on them read
    with a coherence of 0.8)."""
    f = float(getattr(spec.design(), "disturbance_frequency", 0.0) or 0.0)
    if f <= 0 or not math.isfinite(period_s):
        return period_s
    return math.ceil(period_s * f - 1e-9) / f


def measure_open_loop(cfg: MachineConfig, axis_name: str, *, sim: bool = False, seconds: float = 20.0,
                      amplitude: float | None = None, fmin: float = OPEN_FMIN, fmax: float = OPEN_FMAX,
                      model: str | None = None, plant: str | None = None, controller: Any = None,
                      bias_velocity: float | None = None, period_s: float | None = None) -> OpenLoopResult:
    """Measure the open loop of ``axis_name`` (see the module text; the arguments as
    :func:`~drivectl.tools.commissioning.bode.measure_frf`, ``period_s`` the multisine's period, default
    1 s: its inverse is the line spacing). Bad input, and an excitation the model says the axis cannot
    take within its following-error window or its effort limit, raise BodeError before anything moves."""
    from drivectl.controllers.registry import make_controller
    from drivectl.machine.build import model_specs
    from drivectl.tools.commissioning.bode import PERIOD_S, excited_run, plan_excitation, stood_share

    dt = cfg.cycle_s
    period_s = aligned_period(model_specs(cfg, [axis_name], model, plant)[axis_name],
                              PERIOD_S if period_s is None else period_s)
    if not (math.isfinite(period_s) and 0.05 <= period_s <= seconds / 3):
        raise BodeError(f"bode: --seconds {seconds:g}: holds fewer than 3 periods of the multisine ({period_s:g} s); "
                        f"give at least {3 * period_s:g} s")
    planned = plan_excitation(cfg, axis_name, seconds=seconds, amplitude=amplitude, fmin=fmin, fmax=fmax,
                              model=model, plant=plant, bias_velocity=bias_velocity, period_s=period_s)
    one, n, periods, bias, amp, spec = planned[:6]
    ac = cfg.axis(axis_name)
    law = controller or make_controller(ac.controller, dt, ac.controller_settings, plant=spec, axis=axis_name,
                                        source=f"{cfg.source}: axes.{axis_name}.controller_settings")
    pred = predicted_motion(law, spec, one, dt)
    if pred is not None:
        peak_pos, peak_u = pred
        window = ac.limits.following_error
        if window is not None and math.isfinite(window) and peak_pos > FOLLOWING_SHARE * window:
            raise BodeError(f"bode: --amplitude {amp:g} {spec.effort_unit}: the model says the excitation moves "
                            f"axis {axis_name} by up to {peak_pos * 1e3:.3g} mm, more than half its following-error "
                            f"window axes.{axis_name}.limits.following_error_m ({window * 1e3:g} mm); lower "
                            "--amplitude; nothing moved")
        if peak_u > ac.limits.max_effort:
            raise BodeError(f"bode: --amplitude {amp:g} {spec.effort_unit}: the model says the loop's effort "
                            f"reaches {peak_u:.3g} {spec.effort_unit}, beyond axes.{axis_name}.limits.max_effort "
                            f"({ac.limits.max_effort:g}); lower --amplitude; nothing moved")
    run = excited_run(cfg, axis_name, sim=sim, plant=plant, controller=law, planned=planned)
    form = law.linear_form()
    res = OpenLoopResult(axis_name, law.name, form is not None, spec.name, run.bus, amp, spec.effort_unit,
                         run.freqs, np.array([], dtype=complex), np.array([]), np.array([]),
                         np.array([], dtype=complex), np.array([]), None, None, None, periods, run.trace,
                         run.stop, run.detail, 0.0 if bias is None else bias.velocity)
    if not run.ok:
        return res
    m = run.analysed
    s, sig_s, coh = sensitivity(run.excitation[:m], run.trace.effort[:m], n, run.freqs, dt)
    loop, sig_l = open_loop_of(s, sig_s)
    res.s, res.sigma_s, res.coherence, res.loop, res.sigma_loop = s, sig_s, coh, loop, sig_l
    res.stood_share = stood_share(run)
    res.margins = margins_of(run.freqs, loop, sig_l, coh, (fmin, fmax))
    law.reset()  # the linear form is the law's, not its state's; its design is resolved now
    res.model_loop = model_loop(law, spec, dt, run.freqs)
    if res.model_loop is not None:
        res.model_margins = margins_of(run.freqs, res.model_loop, band=(fmin, fmax))
    return res


def summary_text(res: OpenLoopResult) -> str:
    """The margins, measured (with their standard errors) beside the model's loop."""
    m, mm = res.margins, res.model_margins
    assert m is not None
    f = res.freqs
    lines = [f"bode --loop open: axis {res.axis} ({res.plant}) on {res.bus}, controller {res.controller} "
             f"({res.kind})",
             f"multisine peak {res.amplitude:g} {res.effort_unit} added to the effort, {f[0]:g}-{f[-1]:g} Hz "
             f"({len(f)} lines), {res.periods - 1} periods averaged"
             + (f", about a constant-velocity bias of {res.bias_velocity * 1e3:.2f} mm/s" if res.bias_velocity else ""),
             "S = effort / injected disturbance, L = (1 - S) / S; coherence min "
             + ("-" if m.coherence_min is None else f"{m.coherence_min:.3f}")
             + f" (lines under {MIN_COHERENCE:g}, or whose L is uncertain by more than {100 * MAX_REL_ERROR:g} %, "
             "left out)"]
    if not res.linear:
        lines.append(f"{res.controller} is a nonlinear law (no linear form): these margins are describing-function "
                     f"estimates at the excitation's level ({res.amplitude:g} {res.effort_unit} peak), not the "
                     "margins of a linear loop")
    rows = [("gain margin", m.gm_db, "dB", mm and mm.gm_db),
            ("  at (phase crossover)", m.gm_hz, "Hz", mm and mm.gm_hz),
            ("phase margin", m.pm_deg, "deg", mm and mm.pm_deg),
            ("  at (gain crossover)", m.pm_hz, "Hz", mm and mm.pm_hz),
            ("sensitivity peak Ms", m.ms, "", mm and mm.ms), ("  at", m.ms_hz, "Hz", mm and mm.ms_hz),
            ("bandwidth (-3 dB of T)", m.bandwidth_hz, "Hz", mm and mm.bandwidth_hz)]
    head = f"{'':<24} {'measured (+- 1 s.e.)':<26} {'model (linear form)' if mm else ''}"
    lines += ["", head.rstrip(), "-" * len(head.rstrip())]
    notes: list[str] = []
    for label, v, unit, mv in rows:
        meas = v.text(unit) if v.value is not None else "-"
        if v.value is None and v.note and v.note not in notes:
            notes.append(v.note)
        model_txt = "" if mv is None else (mv.text(unit).replace(" +- 0.00", "") if mv.value is not None else "-")
        lines.append(f"{label:<24} {meas:<26} {model_txt}".rstrip())
    if m.ms.value is not None:
        lines.append(f"modulus margin 1/Ms {1 / m.ms.value:.3f}")
    if len(m.phase_crossovers) > 1 or len(m.gain_crossovers) > 1:
        # the reported one is the nearest to 0 dB / 0 deg; a negative gain margin is a gain *reduction* margin
        # (the loop is conditionally stable: less gain destabilises it)
        def some(items: list[str]) -> str:
            return ", ".join(items[:6]) + (f" and {len(items) - 6} more" if len(items) > 6 else "")

        lines.append("phase crossovers: " + some([f"{hz:.1f} Hz ({g:+.2f} dB)" for g, hz in m.phase_crossovers])
                     + "; gain crossovers: " + some([f"{hz:.1f} Hz ({p:+.1f} deg)" for p, hz in m.gain_crossovers]))
    if m.gm_db.value is not None and m.gm_db.value < 0:
        lines.append("the gain margin is negative: at that phase crossover |L| > 1, so it is the gain *reduction* "
                     "that destabilises the loop (conditionally stable)")
    lines += [f"note: {x}" for x in notes]
    if res.stood_share > 0:
        lines.append(f"warning: the axis stood or moved backwards in {100 * res.stood_share:.1f} % of the analysed "
                     "cycles: there its friction is not a constant force and the loop is not the linear one")
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------------------
# Output
# --------------------------------------------------------------------------------------------------


def plot_open_loop(res: OpenLoopResult, path: Path | None = None) -> bytes:
    """The Bode magnitude and phase of the measured L (with the model's, and the margins marked) beside
    its Nyquist curve and the circle of radius 1/Ms about -1; PNG bytes, written atomically to ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from drivectl.tracefile.format import atomic_write_bytes

    m = res.margins
    assert m is not None
    fig = plt.figure(figsize=(12, 6.5))
    gs = fig.add_gridspec(2, 2, width_ratios=[1.35, 1], height_ratios=[1, 1])
    ax_m = fig.add_subplot(gs[0, 0])
    ax_p = fig.add_subplot(gs[1, 0], sharex=ax_m)
    ax_n = fig.add_subplot(gs[:, 1])
    f, lp = res.freqs, res.loop
    with np.errstate(divide="ignore", invalid="ignore"):
        good = (res.coherence >= MIN_COHERENCE) & (res.sigma_loop <= MAX_REL_ERROR * np.abs(res.loop))
    ph = np.degrees(np.unwrap(np.angle(lp)))
    ph -= 360.0 * np.round((ph[np.argmin(np.abs(np.abs(lp) - 1))] + 180) / 360.0) if len(ph) else 0.0
    label = "measured L" + ("" if res.linear else " (describing-function estimate)")
    ax_m.semilogx(f[good], _db(lp[good]), lw=1.2, label=label)
    ax_m.semilogx(f[~good], _db(lp[~good]), ".", ms=2, color="0.6",
                  label=f"left out (coherence < {MIN_COHERENCE:g} or L uncertain > {100 * MAX_REL_ERROR:g} %)")
    ax_p.semilogx(f[good], ph[good], lw=1.2)
    if res.model_loop is not None:
        mp = np.degrees(np.unwrap(np.angle(res.model_loop)))
        mp += np.round((ph[good][0] - mp[good][0]) / 360.0) * 360.0 if good.any() else 0.0
        ax_m.semilogx(f, _db(res.model_loop), lw=1.0, ls="--", label="model (linear form, ZOH + 1-cycle delay)")
        ax_p.semilogx(f, mp, lw=1.0, ls="--")
    ax_m.axhline(0.0, color="k", lw=0.6)
    if m.pm_hz.value is not None:
        for ax in (ax_m, ax_p):
            ax.axvline(m.pm_hz.value, color="C2", lw=0.8, ls=":")
        ax_m.plot([m.pm_hz.value], [0.0], "o", color="C2",
                  label=f"PM {m.pm_deg.value:.1f} deg at {m.pm_hz.value:.1f} Hz")
    if m.gm_hz.value is not None:
        for ax in (ax_m, ax_p):
            ax.axvline(m.gm_hz.value, color="C3", lw=0.8, ls=":")
        ax_m.annotate("", (m.gm_hz.value, 0.0), (m.gm_hz.value, -m.gm_db.value),
                      arrowprops={"arrowstyle": "<->", "color": "C3"})
        ax_m.plot([], [], color="C3", label=f"GM {m.gm_db.value:.1f} dB at {m.gm_hz.value:.1f} Hz")
    ax_p.axhline(-180.0, color="k", lw=0.6)
    for k in (-540.0, 180.0):
        if len(ph) and ph.min() < k < ph.max():
            ax_p.axhline(k, color="k", lw=0.4, ls="--")
    ax_m.set_ylabel("|L| [dB]")
    ax_p.set_ylabel("arg L [deg]")
    ax_p.set_xlabel("frequency [Hz]")
    ax_m.legend(loc="lower left", fontsize=8)
    for ax in (ax_m, ax_p):
        ax.grid(True, which="both", alpha=0.3)
    # Nyquist: only the part near -1 matters for the margins
    ax_n.plot(lp[good].real, lp[good].imag, lw=1.2, label="measured L")
    if res.model_loop is not None:
        ax_n.plot(res.model_loop.real, res.model_loop.imag, lw=1.0, ls="--", label="model")
    ax_n.plot([-1.0], [0.0], "k+", ms=10)
    if m.ms.value is not None:
        r = 1.0 / m.ms.value
        t = np.linspace(0, 2 * math.pi, 361)
        ax_n.plot(-1 + r * np.cos(t), r * np.sin(t), color="C3", lw=1.0,
                  label=f"|1 + L| = 1/Ms = {r:.2f} (Ms {m.ms.value:.2f})")
    ax_n.set_xlim(-3, 1.5)
    ax_n.set_ylim(-2.5, 2.0)
    ax_n.set_aspect("equal")
    ax_n.axhline(0.0, color="k", lw=0.5)
    ax_n.axvline(0.0, color="k", lw=0.5)
    ax_n.set_xlabel("Re L")
    ax_n.set_ylabel("Im L")
    ax_n.grid(True, alpha=0.3)
    ax_n.legend(loc="upper left", fontsize=8)
    bw = f", bandwidth {m.bandwidth_hz.value:.1f} Hz" if m.bandwidth_hz.value is not None else ""
    fig.suptitle(f"drivectl bode --loop open: axis {res.axis} ({res.plant}), {res.controller}"
                 + ("" if res.linear else " (describing function)") + bw, fontsize=11)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    png = buf.getvalue()
    if path is not None:
        atomic_write_bytes(path, png)
    return png


def write_open_loop(res: OpenLoopResult, out_dir: str | Path) -> list[Path]:
    """``bode-open-AXIS.csv``, ``.png`` and ``.json`` (the margins) in ``out_dir``, each written atomically."""
    from drivectl.tracefile.format import atomic_write_text

    out = Path(out_dir)
    csv = out / f"bode-open-{res.axis}.csv"
    atomic_write_text(csv, res.csv_text())
    png = out / f"bode-open-{res.axis}.png"
    plot_open_loop(res, png)
    # the margins beside the figure, as --json prints them (the console's Axis page shows both)
    side = out / f"bode-open-{res.axis}.json"
    atomic_write_text(side, json.dumps({**res.to_json(), "linear": res.linear}) + "\n")
    res.files = [csv, png, side]
    return res.files

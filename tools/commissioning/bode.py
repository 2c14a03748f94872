"""`drivectl bode`: closed-loop frequency response from effort to position, overlaid on the model.

The axis holds its position under its configured controller while a known periodic multisine is
added to the controller's effort (:class:`ExcitedController`). The effort column of the run is then
the total effort the drive applies, the position column what the encoder measures, and the loop
stays closed (the controller keeps the axis in place; a limit ends the run as in any trace).

Friction: where the model has Coulomb friction (a rigid feed axis), an axis holding still sticks
whenever the loop's effort plus the excitation stays under the breakaway force, and the response is
that of stick-slip, not of the plant: a stiff loop (one that cancels a low-frequency force, as ``mbc``
does) keeps the axis stuck longest and bode then reads a false low-frequency "mode". There the
measurement runs about a slow constant-velocity bias instead (:class:`BiasRamp`; the standard way to
take a friction axis's FRF): the reference travels at ``v_b`` across the soft-limit range, ramped up
inside the first, discarded period and down after the last; at a velocity that never reverses, Coulomb
friction is one constant force, which the constant detrend removes, and the small-signal response is
the linear plant's, whatever the controller. ``v_b`` is the fastest up to 10 mm/s whose travel keeps
within 80 % of the soft limits (rigid-x, 20 s: 8 mm/s); sliding, the excitation need not beat the
breakaway force, so its default peak is the largest whose own velocity (open loop) stays under half of
``v_b`` (rigid-x: 31 N against 287 N when holding). The run checks the velocity it measured and says
how much of the time the axis stood or reversed. ``bias_velocity`` (``--bias-velocity``) sets ``v_b``;
0 holds still, as on a frictionless model (two-mass: it holds). The response is taken of ``pos - ref``,
which removes the ramp; on a hold the reference is constant and nothing changes.

The frequency response, its estimate and the mode: tools/commissioning/frf.py; the excitation and
the held or travelled reference: tools/commissioning/bode_excitation.py.

``--loop open`` takes the same run (:func:`excited_run`) to the open loop instead: the sensitivity from the
recorded effort and the injected multisine, L, and the stability margins (tools/commissioning/margins.py).

Library: :func:`measure_frf` -> :class:`BodeResult`, :func:`model_frf`, :func:`write_bode`. CLI:
:func:`add_bode_parser` and :func:`cmd_bode`.
"""

from __future__ import annotations

import argparse
import io
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from drivectl.controllers.base import Controller
from drivectl.machine.config import ConfigError, MachineConfig
from drivectl.plant_emulator.models import PlantSpec
from drivectl.tools.cli.exits import exits_on_error
from drivectl.tools.commissioning.bode_excitation import BIAS_RAMP_S, BiasRamp, ExcitedController, Hold, multisine
from drivectl.tools.commissioning.frf import BodeError, Mode, estimate_frf, find_mode, model_frf, model_modes
from drivectl.tools.commissioning.margins import OPEN_FMAX, OPEN_FMIN
from drivectl.tracefile.format import Trace, atomic_write_bytes, atomic_write_text

#: length of one multisine period, s: the frequency resolution is its inverse (1 Hz), and 1 s keeps
#: ~20 periods to average in a 20 s run; the mode's half-power width (~8 Hz on two-mass) spans many lines
PERIOD_S = 1.0
#: default band, Hz: below 5 Hz the closed loop cancels the excitation; above ~250 Hz the position
#: response of a mass falls under a few encoder counts and the estimate is quantisation noise
DEFAULT_FMIN, DEFAULT_FMAX = 5.0, 250.0
#: default peak excitation as a fraction of max_effort (small: the axis must stay near its hold point)
DEFAULT_AMPLITUDE_FRACTION = 0.05
#: ... or of the rated effort when max_effort is unlimited
DEFAULT_AMPLITUDE_RATED = 0.5
#: ... but at least this multiple of the plant's Coulomb level: below it the axis sticks and slips and
#: the response is not the linear one (rigid-x, measured: 2x Coulomb reads 5-20 dB under the model,
#: 6x within 1 dB from 20 Hz up, 5 dB low at 10 Hz where the loop holds the axis near rest)
COULOMB_MULTIPLE = 6.0
#: ... and at most this fraction of max_effort (the most --amplitude takes: a drive peak of 3x rated leaves
#: 1.5x rated for the excitation)
MAX_DEFAULT_FRACTION = 0.5
#: the slow constant-velocity bias on an axis whose model has Coulomb friction (see the module doc): at
#: most this fast (a slow feed) ...
BIAS_MAX_M_S = 0.01
#: ... and travelling at most this share of the soft-limit range about the hold point
BIAS_LIMIT_SHARE = 0.8
#: the default excitation under a bias drives the model's linear part (open loop) to at most 1 / this
#: of the bias velocity, so the velocity never crosses zero and the friction stays one constant force
BIAS_MARGIN = 2.0

CSV_COLUMNS = ("freq_hz", "mag_db", "phase_deg", "coherence", "model_mag_db", "model_phase_deg")


# --------------------------------------------------------------------------------------------------
# The measurement
# --------------------------------------------------------------------------------------------------


@dataclass
class BodeResult:
    axis: str
    plant: str
    bus: str
    freqs: np.ndarray  # Hz, the excited lines
    frf: np.ndarray  # complex, effort -> position (m per effort unit)
    coherence: np.ndarray
    model: np.ndarray  # complex, the model's FRF on the same lines
    mode: Mode | None
    model_mode_hz: float | None
    amplitude: float
    effort_unit: str
    trace: Trace
    stop: str = "completed"
    detail: str = ""
    coulomb: float = 0.0  # the plant's largest Coulomb level (effort unit): not in the linear model
    bias_velocity: float = 0.0  # m/s, the constant-velocity bias the response was measured about (0: hold)
    stood_share: float = 0.0  # under a bias: share of the analysed cycles the axis stood or moved backwards
    files: list[Path] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.stop == "completed"

    @property
    def mode_hz(self) -> float | None:
        return self.mode.freq_hz if self.mode else None

    @property
    def error_pct(self) -> float | None:
        if self.mode is None or self.model_mode_hz is None:
            return None
        return 100.0 * (self.mode.freq_hz - self.model_mode_hz) / self.model_mode_hz

    def to_json(self) -> dict[str, Any]:
        def r(x: float | None, nd: int) -> float | None:
            return None if x is None else round(x, nd)

        return {"axis": self.axis, "mode_hz": r(self.mode_hz, 3), "model_mode_hz": r(self.model_mode_hz, 3),
                "error_pct": r(self.error_pct, 3)}

    def csv_text(self) -> str:
        out = io.StringIO()
        out.write(f"# drivectl bode: axis {self.axis}, plant {self.plant}, {self.bus}; effort -> position, "
                  f"magnitude in dB re 1 m/{self.effort_unit or 'effort'}; multisine peak "
                  f"{self.amplitude:g} {self.effort_unit}"
                  + (f" about a constant-velocity bias of {self.bias_velocity:g} m/s" if self.bias_velocity else "")
                  + f"; mode {_fmt(self.mode_hz)} Hz, model "
                  f"{_fmt(self.model_mode_hz)} Hz\n")
        out.write(",".join(CSV_COLUMNS) + "\n")
        data = np.column_stack([self.freqs, _db(self.frf), _deg(self.frf), self.coherence, _db(self.model),
                                _deg(self.model)])
        np.savetxt(out, data, fmt=["%.6g", "%.6f", "%.4f", "%.6f", "%.6f", "%.4f"], delimiter=",")
        return out.getvalue()


def _db(h: np.ndarray) -> np.ndarray:
    return 20 * np.log10(np.maximum(np.abs(h), 1e-300))


def _deg(h: np.ndarray) -> np.ndarray:
    """Unwrapped phase (the delays and the mode take it well past -360 deg), its first line in (-360, 0]
    (a position response to effort starts near -90 .. -180 deg), so measured and model share a branch."""
    if len(h) == 0:
        return np.array([])
    ph = np.degrees(np.unwrap(np.angle(h)))
    return ph - 360.0 * math.ceil(ph[0] / 360.0)


def _fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.2f}"


def hold_position(cfg: MachineConfig, axis_name: str) -> float:
    """Where the axis holds during the measurement: 0 if inside the soft limits, else their middle."""
    lim = cfg.axis(axis_name).limits.position
    if lim is None or lim[0] <= 0.0 <= lim[1]:
        return 0.0
    return 0.5 * (lim[0] + lim[1])


def coulomb_level(spec: PlantSpec) -> float:
    """The largest Coulomb (+ Stribeck) force of the plant's bodies, effort unit."""
    return max((max(b.fc_pos, b.fc_neg) + b.stribeck_excess for b in spec.design().bodies), default=0.0)


def default_amplitude(spec: PlantSpec, max_effort: float, rated_effort: float) -> float:
    """Peak multisine effort: 5 % of max_effort, raised to 6x the Coulomb level, capped at 25 %."""
    coulomb = coulomb_level(spec)
    if math.isfinite(max_effort):
        return min(max(DEFAULT_AMPLITUDE_FRACTION * max_effort, COULOMB_MULTIPLE * coulomb),
                   MAX_DEFAULT_FRACTION * max_effort)
    return max(DEFAULT_AMPLITUDE_RATED * rated_effort, COULOMB_MULTIPLE * coulomb)


def excitation_peak_velocity(spec: PlantSpec, one_period: np.ndarray, dt: float) -> float:
    """Peak velocity (m/s) of the model's linear part driven open-loop by one period of the multisine,
    in periodic steady state: the excitation's lines through the velocity response ``j w H``."""
    n = len(one_period)
    x = np.fft.rfft(one_period)
    f = np.fft.rfftfreq(n, dt)
    on = np.abs(x) > 1e-9 * np.max(np.abs(x))
    v = np.zeros_like(x)
    v[on] = x[on] * 1j * 2 * math.pi * f[on] * model_frf(spec, dt, f[on])
    return float(np.max(np.abs(np.fft.irfft(v, n))))


def bias_plan(cfg: MachineConfig, axis_name: str, spec: PlantSpec, periods: int,
              bias_velocity: float | None, period_s: float = PERIOD_S) -> BiasRamp | None:
    """The constant-velocity bias for the measurement, or None (hold still). ``bias_velocity`` None:
    where the model has Coulomb friction, the fastest velocity up to :data:`BIAS_MAX_M_S` whose travel
    stays within :data:`BIAS_LIMIT_SHARE` of the soft-limit range, else hold; 0: hold. The travel is
    centred on the hold point; an explicit velocity whose travel leaves the soft limits is refused."""
    if bias_velocity is not None and not (math.isfinite(bias_velocity) and bias_velocity >= 0):
        raise BodeError(f"bode: --bias-velocity: must be >= 0 m/s, got {bias_velocity:g}")
    if bias_velocity == 0 or (bias_velocity is None and coulomb_level(spec) <= 0):
        return None
    cruise = periods * period_s  # the ramps lose half their time each: travel = v * cruise
    hold = hold_position(cfg, axis_name)
    lim = cfg.axis(axis_name).limits.position
    if bias_velocity is None:
        room = math.inf if lim is None else BIAS_LIMIT_SHARE * 2 * min(hold - lim[0], lim[1] - hold)
        bias_velocity = min(BIAS_MAX_M_S, room / cruise)
    travel = bias_velocity * cruise
    if lim is not None and not (lim[0] <= hold - 0.5 * travel and hold + 0.5 * travel <= lim[1]):
        raise BodeError(f"bode: --bias-velocity {bias_velocity:g} m/s for --seconds {cruise:g} travels "
                        f"{travel * 1e3:.1f} mm about {hold * 1e3:g} mm, more than axes.{axis_name}.limits.position_m "
                        f"({lim[0]:g} .. {lim[1]:g} m) allows; lower one of them")
    return BiasRamp(hold - 0.5 * travel, bias_velocity, cruise + BIAS_RAMP_S)


@dataclass
class ExcitedRun:
    """One run of an axis holding (or sliding about a bias) with a multisine added to its controller's
    effort: what both the closed-loop FRF and the open-loop sensitivity (tools/commissioning/margins.py)
    are estimated from."""

    trace: Trace
    excitation: np.ndarray  # the multisine as added, sample by sample (periods * n)
    n: int  # samples per period
    periods: int
    freqs: np.ndarray  # the excited lines, Hz
    spec: PlantSpec  # the model (what the controller believes)
    plant: PlantSpec  # what the axis plays
    bias: BiasRamp | None
    amplitude: float
    controller: Controller  # the inner law (without the excitation)
    bus: str
    stop: str
    detail: str
    dt: float

    @property
    def ok(self) -> bool:
        return self.stop == "completed"

    @property
    def analysed(self) -> int:
        """Rows analysed: whole periods only (the bias's ramp down after them is not)."""
        return min(len(self.trace), self.periods * self.n)


def check_band(fmin: float, fmax: float, dt: float) -> None:
    nyq = 0.5 / dt
    if not (0 < fmin < fmax <= nyq):
        raise BodeError(f"bode: band --fmin {fmin:g} .. --fmax {fmax:g} Hz: need 0 < fmin < fmax <= {nyq:g} Hz "
                        "(Nyquist)")


class Plan(NamedTuple):
    """The excitation planned (and checked) before anything opens."""

    one: np.ndarray  # one period of the multisine
    n: int  # samples per period
    periods: int
    bias: BiasRamp | None
    amplitude: float
    spec: PlantSpec  # the model
    plant: PlantSpec  # what the axis plays
    freqs: np.ndarray  # the excited lines, Hz


def plan_excitation(cfg: MachineConfig, axis_name: str, *, seconds: float = 20.0, amplitude: float | None = None,
                    fmin: float = DEFAULT_FMIN, fmax: float = DEFAULT_FMAX, model: str | None = None,
                    plant: str | None = None, bias_velocity: float | None = None, period_s: float = PERIOD_S
                    ) -> Plan:
    """Check the request and plan the excitation before anything opens. BodeError / ConfigError (one
    line) on bad input."""
    from drivectl.machine.build import model_specs, plant_specs

    ac = cfg.axis(axis_name)  # ConfigError for an unknown axis, before anything opens
    dt = cfg.cycle_s
    if not (math.isfinite(seconds) and seconds > 0):
        raise BodeError(f"bode: --seconds: must be > 0, got {seconds:g}")
    check_band(fmin, fmax, dt)
    max_eff = ac.limits.max_effort
    plants = plant_specs(cfg, [axis_name], plant)
    spec = model_specs(cfg, [axis_name], model, plant, plants=plants)[axis_name]
    n = int(round(period_s / dt))
    periods = max(3, int(round(seconds / period_s, 9)))
    bias = bias_plan(cfg, axis_name, spec, periods, bias_velocity, period_s)
    if amplitude is None and bias is not None:
        # sliding, the friction is no threshold to beat: the largest excitation whose own velocity
        # (open loop, peak) stays within 1 / BIAS_MARGIN of the bias, so the axis never reverses
        unit, _ = multisine(n, dt, fmin, fmax, 1.0)
        amplitude = min(abs(bias.velocity) / (BIAS_MARGIN * excitation_peak_velocity(spec, unit, dt)),
                        MAX_DEFAULT_FRACTION * max_eff)
    elif amplitude is None:
        amplitude = default_amplitude(spec, max_eff, ac.rated_effort)
    # the excitation alone must leave the controller most of the effort range, else clipping (a
    # nonlinearity) corrupts the estimate
    if not (math.isfinite(amplitude) and 0 < amplitude <= 0.5 * max_eff):
        raise BodeError(f"bode: --amplitude: must be > 0 and at most half of axes.{axis_name}.limits.max_effort "
                        f"({0.5 * max_eff:g}), got {amplitude:g}")
    one, lines = multisine(n, dt, fmin, fmax, amplitude)
    return Plan(one, n, periods, bias, amplitude, spec, plants[axis_name], lines)


def excited_run(cfg: MachineConfig, axis_name: str, *, sim: bool = False, seconds: float = 20.0,
                amplitude: float | None = None, fmin: float = DEFAULT_FMIN, fmax: float = DEFAULT_FMAX,
                model: str | None = None, plant: str | None = None, controller: Controller | None = None,
                noise: float = 0.0, seed: int = 0, bias_velocity: float | None = None, period_s: float = PERIOD_S,
                planned: Plan | None = None) -> ExcitedRun:
    """Run the axis under its controller (or ``controller``) with the multisine added to the effort (see
    :func:`measure_frf` for the arguments); ``planned``: the result of :func:`plan_excitation` already
    made (and checked) by the caller."""
    from drivectl.controllers.registry import make_controller
    from drivectl.controllers.runtime.servo import Channel, run_channels
    from drivectl.machine.build import machine_meta, open_machine

    ac = cfg.axis(axis_name)
    dt = cfg.cycle_s
    one, n, periods, bias, amplitude, spec, plant_spec, lines = planned or plan_excitation(
        cfg, axis_name, seconds=seconds, amplitude=amplitude, fmin=fmin, fmax=fmax, model=model, plant=plant,
        bias_velocity=bias_velocity, period_s=period_s)
    exc = np.tile(one, periods)
    inner = controller or make_controller(ac.controller, dt, ac.controller_settings, plant=spec, axis=axis_name,
                                          source=f"{cfg.source}: axes.{axis_name}.controller_settings")
    ctrl = ExcitedController(inner, exc)
    profile: Hold | BiasRamp = bias or Hold(hold_position(cfg, axis_name), periods * n * dt)
    # periods * n rows exactly (the row count is duration / dt + 1, so one dt short), then the bias's
    # ramp down to rest after the last period (not analysed)
    rows = periods * n + (int(round(BIAS_RAMP_S / dt)) if bias else 0)
    machine = open_machine(cfg, [axis_name], sim=sim, plant=plant, start={axis_name: profile.start_position},
                           noise=noise, seed=seed)
    try:
        what = f"constant-velocity bias {bias.velocity * 1e3:.3g} mm/s" if bias else "hold"
        what += " + multisine on the effort"
        meta = machine_meta(cfg, machine, plant_spec, spec, what)
        res = run_channels([Channel(machine.axes[axis_name], ctrl, profile, ac.limits, meta)],
                           duration=(rows - 1) * dt)
    finally:
        machine.close()
    return ExcitedRun(res.trace, exc, n, periods, lines, spec, plant_spec, bias, amplitude, inner,
                      machine.bus, res.stop.value, res.detail, dt)


def measure_frf(
    cfg: MachineConfig,
    axis_name: str,
    *,
    sim: bool = False,
    seconds: float = 20.0,
    amplitude: float | None = None,
    fmin: float = DEFAULT_FMIN,
    fmax: float = DEFAULT_FMAX,
    model: str | None = None,
    plant: str | None = None,
    controller: Controller | None = None,
    noise: float = 0.0,
    seed: int = 0,
    bias_velocity: float | None = None,
) -> BodeResult:
    """Hold ``axis_name`` under its configured controller, add a multisine of peak ``amplitude``
    (effort unit; default 5 % of max_effort) on [fmin, fmax] Hz to the effort for ``seconds``, and
    estimate the FRF effort -> position beside the model's. ``sim`` runs on SimAxis, else on the
    configured bus (the emulated drives on the virtual bus by default). A run stopped by a limit
    returns a result with ``ok`` False (and no FRF: arrays empty). ``model`` (``--model``) is the plant
    the controller believes and the overlay shows; ``plant`` (``--plant``) what the emulated drive
    plays (see :func:`~drivectl.machine.build.model_specs`); ``controller`` replaces the axis's.
    ``bias_velocity`` (m/s): the constant-velocity bias (:func:`bias_plan`; None: automatic where the
    model has Coulomb friction, 0: hold still)."""
    dt = cfg.cycle_s
    run = excited_run(cfg, axis_name, sim=sim, seconds=seconds, amplitude=amplitude, fmin=fmin, fmax=fmax,
                      model=model, plant=plant, controller=controller, noise=noise, seed=seed,
                      bias_velocity=bias_velocity)
    tr, spec, bias, n, exc = run.trace, run.spec, run.bias, run.n, run.excitation
    models = model_modes(spec)
    in_band = [f for f in models if fmin <= f <= fmax]
    model_mode = in_band[0] if in_band else None
    base = BodeResult(axis_name, spec.name, run.bus, np.array([]), np.array([], dtype=complex), np.array([]),
                      np.array([], dtype=complex), None, model_mode, run.amplitude, spec.effort_unit, tr,
                      run.stop, run.detail, coulomb_level(spec), 0.0 if bias is None else bias.velocity)
    if not run.ok:
        return base
    m = run.analysed
    # pos - ref: the bias's ramp is not in the response (on a hold, ref is a constant the detrend removes)
    f, h, coh = estimate_frf(exc[:m], tr.effort[:m], (tr.pos - tr.ref)[:m], n, dt)
    keep = (f >= fmin - 1e-9) & (f <= fmax + 1e-9)
    base.freqs, base.frf, base.coherence = f[keep], h[keep], coh[keep]
    if bias is not None:
        base.stood_share = stood_share(run)
    base.model = model_frf(spec, dt, base.freqs)
    # delays removed for the phase test: transport cycle, half-cycle of the hold, extra input delay
    base.mode = find_mode(base.freqs, base.frf, base.coherence, 1.5 * dt + spec.design().input_delay)
    return base


def stood_share(run: ExcitedRun) -> float:
    """Under a bias: the share of the analysed cycles the axis stood or moved backwards (velocity over 5
    cycles; one count per cycle is 0.08 mm/s)."""
    if run.bias is None:
        return 0.0
    tr, n, m, dt = run.trace, run.n, run.analysed, run.dt
    v = (tr.pos[n + 5 : m] - tr.pos[n : m - 5]) / (5 * dt)
    return float(np.mean(v * math.copysign(1.0, run.bias.velocity) <= 0.0))


# --------------------------------------------------------------------------------------------------
# Output
# --------------------------------------------------------------------------------------------------


def plot_bode(res: BodeResult, path: Path) -> Path:
    """Magnitude, phase and coherence over frequency, measured beside the model; written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_m, ax_p, ax_c) = plt.subplots(3, 1, figsize=(8, 8), sharex=True,
                                           gridspec_kw={"height_ratios": [3, 2, 1]})
    f = res.freqs
    ax_m.semilogx(f, _db(res.frf), lw=1.2, label="measured (closed loop)")
    ax_m.semilogx(f, _db(res.model), lw=1.0, ls="--", label="model (linear part, ZOH + 1-cycle delay)")
    ax_p.semilogx(f, _deg(res.frf), lw=1.2)
    ax_p.semilogx(f, _deg(res.model), lw=1.0, ls="--")
    ax_c.semilogx(f, res.coherence, lw=1.0, color="C2")
    for ax, x, style, label in ((ax_m, res.mode_hz, "-", "mode"), (ax_m, res.model_mode_hz, ":", "model mode")):
        if x is not None:
            for a in (ax_m, ax_p, ax_c):
                a.axvline(x, color="C3", ls=style, lw=0.8, label=f"{label} {x:.2f} Hz" if a is ax else None)
    ax_m.set_ylabel(f"|position / effort| [dB re 1 m/{res.effort_unit or 'effort'}]")
    ax_m.legend(loc="best", fontsize=8)
    ax_p.set_ylabel("phase [deg]")
    ax_c.set_ylabel("coherence")
    ax_c.set_ylim(0, 1.05)
    ax_c.set_xlabel("frequency [Hz]")
    for ax in (ax_m, ax_p, ax_c):
        ax.grid(True, which="both", alpha=0.3)
    err = f", error {res.error_pct:+.2f} %" if res.error_pct is not None else ""
    ax_m.set_title(f"drivectl bode: axis {res.axis} ({res.plant}), mode {_fmt(res.mode_hz)} Hz, "
                   f"model {_fmt(res.model_mode_hz)} Hz{err}")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())
    return path


def write_bode(res: BodeResult, out_dir: str | Path) -> list[Path]:
    """``bode-AXIS.csv`` and ``bode-AXIS.png`` in ``out_dir``, each written atomically."""
    out = Path(out_dir)
    csv = out / f"bode-{res.axis}.csv"
    atomic_write_text(csv, res.csv_text())
    png = plot_bode(res, out / f"bode-{res.axis}.png")
    res.files = [csv, png]
    return res.files


def summary_text(res: BodeResult) -> str:
    """A short table (a few lines around the mode and decade points) and the mode beside the model's."""
    lines = [f"bode: axis {res.axis} ({res.plant}) on {res.bus}, multisine peak {res.amplitude:g} "
             f"{res.effort_unit}, {res.freqs[0]:g}-{res.freqs[-1]:g} Hz"]
    head = f"{'freq Hz':>8} {'mag dB':>9} {'phase':>9} {'coh':>6} {'model dB':>9} {'m phase':>9}"
    lines += [head, "-" * len(head)]
    picks = [x for x in (10, 20, 50, 100, 200, res.mode_hz, res.model_mode_hz) if x is not None]
    rows = sorted({int(np.argmin(np.abs(res.freqs - x))) for x in picks if res.freqs[0] <= x <= res.freqs[-1]})
    mag, ph, mmag, mph = _db(res.frf), _deg(res.frf), _db(res.model), _deg(res.model)
    for i in rows:
        lines.append(f"{res.freqs[i]:>8.1f} {mag[i]:>9.2f} {ph[i]:>9.1f} {res.coherence[i]:>6.3f} "
                     f"{mmag[i]:>9.2f} {mph[i]:>9.1f}")
    if res.mode is not None:
        err = f", error {res.error_pct:+.2f} %" if res.error_pct is not None else ""
        lines.append(f"mode: {res.mode.freq_hz:.2f} Hz (peak +{res.mode.prominence_db:.1f} dB, phase drop "
                     f"{res.mode.phase_drop_deg:.0f} deg); model {_fmt(res.model_mode_hz)} Hz{err}")
    else:
        lines.append(f"mode: none found in the band; model {_fmt(res.model_mode_hz)} Hz")
    if res.coulomb > 0 and res.bias_velocity > 0:
        lines.append(f"measured about a constant-velocity bias of {res.bias_velocity * 1e3:.2f} mm/s: the axis "
                     f"slides, its Coulomb friction ({res.coulomb:g} {res.effort_unit}) is a constant force "
                     "outside the response")
        if res.stood_share > 0:
            lines.append(f"warning: the axis stood or moved backwards in {100 * res.stood_share:.1f} % of the "
                         "analysed cycles: where it stuck the response is not the plant's (lower --amplitude)")
    elif res.coulomb > 0:
        lines.append(f"note: the model is the linear part; this plant's Coulomb friction ({res.coulomb:g} "
                     f"{res.effort_unit}) is not in it and lowers the measured response where the axis sticks")
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------------------


def add_bode_parser(subparsers: Any) -> argparse.ArgumentParser:
    """``drivectl bode --axis NAME [--sim] [--seconds S] [--amplitude A] [--fmin F --fmax F] [--out DIR] [--json]``."""
    p = subparsers.add_parser(
        "bode", help="closed-loop frequency response effort -> position, its mode, beside the model's",
        description="Hold the axis under its configured controller, add a multisine to the effort, estimate "
        "the frequency response from effort to position (averaged over whole periods), find the mode "
        "(accelerance peak with a phase drop) and write bode-AXIS.csv and bode-AXIS.png overlaid on the "
        "model's response. Runs on the configured bus (default: emulated drives on the virtual bus); --sim "
        "on SimAxis.")
    p.add_argument("--axis", default="x", help="axis name (default x)")
    p.add_argument("--out", default="traces", metavar="DIR", help="folder for bode-AXIS.csv/.png (default traces)")
    p.add_argument("--json", action="store_true",
                   help='print exactly one JSON object {"axis", "mode_hz", "model_mode_hz", "error_pct"}')
    p.add_argument("--sim", action="store_true", help="run on SimAxis (no bus)")
    p.add_argument("--model", metavar="NAME|FILE",
                   help="the plant the controller believes and the overlay shows (default: the axis's model, else "
                   "its plant)")
    p.add_argument("--plant", metavar="NAME|FILE", help="override what the emulated drive plays (default: the axis's "
                   "plant)")
    p.add_argument("--seconds", type=float, default=20.0, help="excitation length in s (default 20)")
    p.add_argument("--amplitude", type=float, metavar="EFFORT",
                   help="peak of the multisine in the effort unit (default 5 %% of the axis's max_effort)")
    p.add_argument("--bias-velocity", type=float, metavar="M_S",
                   help="measure about this constant velocity (m/s) so a friction axis never sticks (default: "
                   "automatic where the model has Coulomb friction, twice the excitation's peak velocity; 0 = "
                   "hold still)")
    p.add_argument("--fmin", type=float, help=f"lowest line, Hz (default {DEFAULT_FMIN:g}; --loop open "
                   f"{OPEN_FMIN:g})")
    p.add_argument("--fmax", type=float, help=f"highest line, Hz (default {DEFAULT_FMAX:g}; --loop open {OPEN_FMAX:g})")
    p.add_argument("--loop", choices=("closed", "open"), default="closed",
                   help="closed (default): the response effort -> position and its mode; open: the sensitivity S "
                   "= effort / injected disturbance, the open loop L = (1 - S) / S and its stability margins (gain "
                   "and phase margin, Ms, bandwidth), written to bode-open-AXIS.csv/.png; --json then prints "
                   '{"axis", "controller", "gm_db", "gm_hz", "pm_deg", "pm_hz", "ms", "bandwidth_hz", "coherence_min"}')
    p.add_argument("--period", type=float, metavar="S",
                   help="--loop open: the multisine's period, s (default 1, rounded up to whole periods of a "
                   "disturbance the model names); its inverse is the line spacing")
    return p


@exits_on_error
def cmd_bode(args: argparse.Namespace) -> int:
    """0 done; 1 the loop was stopped by a limit or the axis failed; 2 bad input (one line on stderr; the
    code each error carries, drivectl/errors.py)."""
    from drivectl.machine.config import load_config
    from drivectl.tracefile.format import TraceError
    from drivectl.tracefile.stream import check_output_folder

    cfg = load_config(getattr(args, "config", None))
    try:  # before the axis moves: the response goes there after the measurement
        check_output_folder(args.out, "--out", 5_000_000)
    except TraceError as exc:
        raise ConfigError(str(exc)) from None
    if getattr(args, "loop", "closed") == "open":
        return _cmd_open(cfg, args)
    if getattr(args, "period", None) is not None:
        raise BodeError("bode: --period: only with --loop open (the closed loop's period is 1 s)")
    res = measure_frf(cfg, args.axis, sim=args.sim, seconds=args.seconds, amplitude=args.amplitude,
                      fmin=DEFAULT_FMIN if args.fmin is None else args.fmin,
                      fmax=DEFAULT_FMAX if args.fmax is None else args.fmax, model=args.model, plant=args.plant,
                      bias_velocity=args.bias_velocity)
    if not res.ok:
        _stopped(res)
        return 1
    write_bode(res, args.out)
    if args.json:
        print(json.dumps(res.to_json()))
    else:
        print(summary_text(res), end="")
        for p in res.files:
            print(f"wrote {p}")
    return 0


def _stopped(res: Any) -> None:
    """The one line of a measurement the loop stopped: the end state as the drive reported it."""
    from drivectl.controllers.runtime.safe_stop import end_state_line

    m = res.trace.meta  # the end state as the drive reported it after the stop (never assumed)
    after = m.get("safe_after_cycles", "unknown")
    ended = end_state_line({res.axis: m.get("safe_state", "unknown")},
                           {res.axis: None if after == "unknown" else int(after)})
    print(f"drivectl: bode: loop stopped ({res.stop}): {res.detail}; quick stop ({ended}), "
          "no response written", file=sys.stderr)


def _cmd_open(cfg: MachineConfig, args: argparse.Namespace) -> int:
    """`bode --loop open`: the margins (tools/commissioning/margins.py)."""
    from drivectl.tools.commissioning import margins as mg

    res = mg.measure_open_loop(cfg, args.axis, sim=args.sim, seconds=args.seconds, amplitude=args.amplitude,
                               fmin=mg.OPEN_FMIN if args.fmin is None else args.fmin,
                               fmax=mg.OPEN_FMAX if args.fmax is None else args.fmax, model=args.model,
                               plant=args.plant, bias_velocity=args.bias_velocity, period_s=args.period)
    if not res.ok:
        _stopped(res)
        return 1
    mg.write_open_loop(res, args.out)
    if args.json:
        print(json.dumps(res.to_json()))
    else:
        print(mg.summary_text(res), end="")
        for p in res.files:
            print(f"wrote {p}")
    return 0

"""The trace as `drivectl explain` sees it: checks, velocity, windows, the gap and the data's floor.

Method and the reasons for each choice: docs/explain.md. In short:

* the *gap* is a windowed simulation error: ~150 ms windows, each started from the measured state and
  driven open loop by the recorded effort under the trace's transport rule (``# transport_delay_cycles``,
  default 1: the effort on row k acts from t(k+1) to t(k+2)); RMS of simulated minus measured position;
* without a velocity column the start velocity is the slope of a local quintic over 15 samples
  (:func:`estimate_velocity`: flat to 2 % up to 75 Hz, so a loop's own oscillation does not read as a
  mass error); windows whose start velocity cannot be trusted are moved or left out before any model
  sees them: the first rows of the trace and every start on a kink of the position (a velocity step,
  a discontinuity), found by the misfit of the local polynomial that estimates it;
* the *floor* is what the data's own noise leaves, estimated from the data (:func:`noise_floor`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np

from drivectl.errors import InputError
from drivectl.plant_emulator.models import Plant, PlantSpec
from drivectl.tools.explain.sim import BatchSim, Windows, internal_state, make_windows, window_rms
from drivectl.tracefile.format import REQUIRED, Trace

#: window of the gap, s (long enough for a missing force to move the axis measurably, short enough
#: that friction and force noise do not make the open loop drift)
WINDOW_S = 0.150
#: the least a trace must hold to decide anything: this many windows with motion in them
MIN_MOVING_WINDOWS = 8
#: relative tolerance on the sample time (a recorder's timestamps, rounded to 1 us in the file)
DT_TOLERANCE = 0.02
#: a trace "moves" in a window when its position spans this many encoder counts or more
MOVING_COUNTS = 64
#: encoder resolution assumed when the trace does not give ``encoder_m_per_count`` (drivectl's default)
DEFAULT_RESOLUTION_M = 76.29e-9
#: the floor's smooth part of a window's error: polynomials in t up to this order (see _projector)
SMOOTH_ORDER = 2
#: Savitzky-Golay window for the start velocity (samples, odd) and its polynomial order: a quintic,
#: not a cubic, because a cubic over 15 ms passes a 50 Hz velocity oscillation at 95 % (vprl's loop
#: oscillates there), and the missing 5 % at every start reads as a 5 % mass error (docs/explain.md)
SG_LENGTH = 15
SG_ORDER = 5
#: a window start is on a kink when the local polynomial misses the positions around it by this many
#: times the trace's median misfit (and by more than 3 counts): a velocity step it cannot follow
KINK_FACTOR = 8.0

GAP_METRIC = ("windowed simulation error: RMS of simulated minus measured position (m) over 150 ms windows, "
              "each started from the measured state and driven open loop by the recorded effort "
              "(effort of row k acting from t(k+d) to t(k+d+1), d = the trace's transport_delay_cycles, default 1)")


class ExplainError(InputError):
    """The trace cannot be explained (bad input, or too little in it to decide): one line naming the file."""


@dataclass
class Prepared:
    """The trace as the fitters see it; ``spec`` is the model the current fit starts from."""

    source: str
    t: np.ndarray
    pos: np.ndarray
    vel: np.ndarray
    effort: np.ndarray
    dt: float
    spec: PlantSpec
    windows: Windows
    vel_source: str
    effort_unit: str
    transport: int = 1
    resolution: float = DEFAULT_RESOLUTION_M
    dropped: dict[str, int] | None = None  # windows left out, by reason

    @property
    def applied(self) -> np.ndarray:
        """Effort acting during step j (t(j) -> t(j+1)) under the transport rule."""
        return applied_rows(self.effort, self.transport)

    def on(self, spec: PlantSpec) -> Prepared:
        """The same data held against another model (the nominal plant with the effects named so far)."""
        return replace(self, spec=spec)


def applied_rows(effort: np.ndarray, transport: int) -> np.ndarray:
    if transport == 0:
        return np.asarray(effort, dtype=float)
    return np.concatenate((np.zeros(transport), effort[:-transport]))


def _meta_number(trace: Trace, key: str, source: str) -> float | None:
    raw = (trace.meta or {}).get(key)
    if raw is None or raw == "":
        return None
    try:
        value = float(raw)
    except ValueError:
        raise ExplainError(f"{source}: {key}: expected a number, got {raw!r}") from None
    if not math.isfinite(value):
        raise ExplainError(f"{source}: {key}: expected a finite number, got {raw!r}")
    return value


def prepare(trace: Trace, spec: PlantSpec, source: str = "<trace>") -> Prepared:
    """Check the trace and cut it into windows; every problem is one ExplainError line."""
    for name in REQUIRED:
        if name not in trace.columns:
            raise ExplainError(f"{source}: missing column {name!r}")
    cols = {k: np.asarray(trace.columns[k], dtype=float) for k in REQUIRED}
    for name, col in cols.items():
        if name == "ref_m" and trace.meta.get("ref") == "none":
            continue  # explain needs only effort and position (a bus log in CST carries no reference)
        bad = ~np.isfinite(col)
        if bad.any():
            raise ExplainError(f"{source}: column {name}: not a finite number at data row {int(np.argmax(bad)) + 1}")
    t = cols["time_s"]
    if len(t) < 3:
        raise ExplainError(f"{source}: cannot decide: {len(t)} rows, too short")
    steps = np.diff(t)
    if np.any(steps <= 0):
        raise ExplainError(f"{source}: column time_s: not increasing at data row {int(np.argmax(steps <= 0)) + 2}")
    dt = float(np.median(steps))
    if np.max(np.abs(steps - dt)) > DT_TOLERANCE * dt + 2e-6:
        row = int(np.argmax(np.abs(steps - dt))) + 2
        raise ExplainError(f"{source}: column time_s: non-uniform sample time at data row {row} "
                           f"(step {steps[row - 2]:.6g} s, median {dt:.6g} s); explain needs a fixed cycle")
    unit = trace.meta.get("effort_unit", "") if trace.meta else ""
    if unit and unit != spec.effort_unit:
        raise ExplainError(f"{source}: effort_unit {unit!r} but plant {spec.name} takes {spec.effort_unit!r}")
    meta_dt = _meta_number(trace, "dt_s", source)
    if meta_dt is not None and abs(meta_dt - dt) > DT_TOLERANCE * dt:
        raise ExplainError(f"{source}: dt_s {meta_dt:g} s disagrees with the time column ({dt:g} s)")
    transport = _meta_number(trace, "transport_delay_cycles", source)
    if transport is None:
        transport = 1
    elif transport not in (0.0, 1.0):
        raise ExplainError(f"{source}: transport_delay_cycles: expected 0 or 1, "
                           f"got {trace.meta['transport_delay_cycles']!r}")
    resolution = _meta_number(trace, "encoder_m_per_count", source)
    if resolution is not None and not resolution > 0:
        raise ExplainError(f"{source}: encoder_m_per_count: must be > 0, got {trace.meta['encoder_m_per_count']!r}")
    resolution = resolution or DEFAULT_RESOLUTION_M
    pos = cols["pos_m"]
    vel_source = "vel_m_s column"
    if "vel_m_s" in trace.columns and np.all(np.isfinite(trace.columns["vel_m_s"])):
        vel = np.asarray(trace.columns["vel_m_s"], dtype=float)
    else:
        vel = estimate_velocity(pos, dt)
        vel_source = "Savitzky-Golay derivative of pos_m"
    length = max(20, int(round(WINDOW_S / dt)))
    if len(t) < 2 * length:
        raise ExplainError(f"{source}: cannot decide: {len(t) * dt:.3g} s of data, need several {WINDOW_S:g} s windows")
    # which side a lash rests on is decided by efforts above a quarter of the Coulomb level
    fc = 0.5 * (spec.params.get("fc_pos", 0.0) + spec.params.get("fc_neg", 0.0))
    side_threshold = 0.25 * fc if fc > 0 else 0.05 * float(np.max(np.abs(cols["effort"])))
    if vel_source == "vel_m_s column":
        # the recorder's velocity needs no local fit: windows from the first row, none moved
        starts, dropped = np.arange(0, len(t) - length, length), {}
    else:
        starts, dropped = window_starts(pos, length, resolution)
    transport = int(transport)
    win = make_windows(pos, vel, cols["effort"], dt, length, starts=starts, side_threshold=side_threshold,
                       transport=transport)
    span = np.ptp(win.measured, axis=1)
    moving_span = max(5e-6, MOVING_COUNTS * resolution)
    moving = int(np.sum(span > moving_span))
    if moving < MIN_MOVING_WINDOWS:
        raise ExplainError(f"{source}: cannot decide: the axis moves in only {moving} of {len(span)} windows of "
                           f"{WINDOW_S * 1e3:g} ms (need {MIN_MOVING_WINDOWS})")
    return Prepared(source, t, pos, vel, cols["effort"], dt, spec, win, vel_source, spec.effort_unit,
                    transport, resolution, dropped)


def estimate_velocity(pos: np.ndarray, dt: float) -> np.ndarray:
    """Velocity from quantised positions: a quintic Savitzky-Golay derivative over 15 samples.

    Why this one: the start velocity of a window must be unbiased for what the loop does, not only
    for the profile: a velocity error e at a start grows to e x t over the window, and when e is a
    fixed fraction of the high-frequency motion (a filter's attenuation of a loop's own oscillation)
    a mass error absorbs it at every start. The quintic's slope passes 50 Hz at 99.8 % and 75 Hz at
    98 % (a cubic over the same 15 samples: 95 % and 80 %); its noise gain is 1.8 x the cubic's
    (0.27 per count and sample: ~6 um/s at 76 nm counts, 0.5 um over a window), and the span is the
    same, so the start rows and the kink test stay where they were.
    """
    from drivectl.tools.explain.savgol import savgol_filter  # not scipy.signal's: its import costs ~1 s

    n = min(SG_LENGTH, len(pos) - (1 - len(pos) % 2))
    if n < 5:
        return np.gradient(pos, dt)
    return savgol_filter(pos, n, SG_ORDER, deriv=1, delta=dt, mode="interp")


def _local_misfit(pos: np.ndarray) -> np.ndarray:
    """RMS misfit of the local polynomial (SG_ORDER) through the SG_LENGTH positions centred on each
    row (nan at the edges)."""
    from drivectl.tools.explain.savgol import savgol_filter  # not scipy.signal's: its import costs ~1 s

    n = len(pos)
    half = SG_LENGTH // 2
    smooth = savgol_filter(pos, SG_LENGTH, SG_ORDER, mode="interp")
    r2 = (pos - smooth) ** 2
    c = np.concatenate(([0.0], np.cumsum(r2)))
    out = np.full(n, np.nan)
    idx = np.arange(half, n - half)
    out[idx] = np.sqrt((c[idx + half + 1] - c[idx - half]) / SG_LENGTH)
    return out


def window_starts(pos: np.ndarray, length: int, resolution: float) -> tuple[np.ndarray, dict[str, int]]:
    """Non-overlapping window starts, leaving out those whose start state cannot be trusted.

    The start velocity comes from a local polynomial; where the position has a kink (the axis set in
    motion by a velocity step, as a circle's start; a jump) it cannot follow, its slope is
    wrong by mm/s, and that one window's open-loop error (~ v error x window) would outweigh the
    rest of the trace. Such a start is moved past the kink (up to half a window); the first rows
    of the trace, where the polynomial has no past, are skipped.
    """
    n = len(pos)
    half = SG_LENGTH // 2
    misfit = _local_misfit(pos)
    typical = float(np.nanmedian(misfit)) if np.any(np.isfinite(misfit)) else 0.0
    limit = max(KINK_FACTOR * typical, 3.0 * resolution)
    bad = ~(misfit <= limit)  # nan (edges) counts as bad
    starts = []
    dropped = {"kink at the start": 0}
    s = half
    while s + length < n:
        k = s
        while k < min(s + length // 2, n - length - 1) and bad[k]:
            k += 1
        if bad[k]:
            dropped["kink at the start"] += 1
            s += length
            continue
        starts.append(k)
        s = k + length
    return np.asarray(starts, dtype=int), {k: v for k, v in dropped.items() if v}


# --------------------------------------------------------------------------------------------------
# The gap
# --------------------------------------------------------------------------------------------------


def _internal(prep: Prepared, plants: list[Plant]) -> tuple[np.ndarray, np.ndarray] | None:
    """Reconstructed internal state of a linear two-body mode at the window starts, else None.

    Only where body 0 carries no Coulomb friction and the coupling has no dead zone is the relative
    motion linear and driven by measured quantities alone (tools/explain_sim.internal_state);
    backlash starts quasi-static with the screw against the side the effort pushes it to.
    """
    if not all(p.n_bodies == 2 and not p.gap and not p.design.bodies[0].has_coulomb
               and p.design.bodies[0].c_pos == p.design.bodies[0].c_neg for p in plants):
        return None
    table_acc = np.concatenate((np.diff(prep.vel) / prep.dt, [0.0]))
    return internal_state(plants, prep.applied, table_acc, prep.windows.start, prep.vel, prep.t)


def simulate(prep: Prepared, specs: list[PlantSpec], substeps: int | None = None) -> np.ndarray:
    """Windowed simulation of each plant: (W, C, L)."""
    # built at the batch's substep count, so that BatchSim need not compile each plant a second time
    plants = [s.build(prep.dt, int(substeps) if substeps else None) for s in specs]
    return BatchSim(plants, substeps=substeps).run(prep.windows, _internal(prep, plants))


def gaps_of(prep: Prepared, specs: list[PlantSpec], substeps: int | None = None) -> np.ndarray:
    """The windowed gap of each plant, m."""
    return window_rms(simulate(prep, specs, substeps), prep.windows)


def window_mse(prep: Prepared, specs: list[PlantSpec], substeps: int | None = None) -> np.ndarray:
    """Mean squared error per window and plant: (W, C); the gap is the square root of its mean over
    windows (:func:`gaps_of`, from the same simulation)."""
    err = simulate(prep, specs, substeps)
    err -= prep.windows.measured[:, None, :]
    np.multiply(err, err, out=err)  # in place, as window_rms: no second array of the simulation's size
    return np.mean(err, axis=-1)


def window_errors(prep: Prepared, specs: list[PlantSpec]) -> tuple[np.ndarray, np.ndarray]:
    """Per window and plant (W, C): the mean squared error, and the part of it no smooth correction
    explains (the floor's raw material, see :func:`noise_floor`)."""
    err = simulate(prep, specs) - prep.windows.measured[:, None, :]
    mse = np.mean(err * err, axis=-1)
    resid = err @ _projector(err.shape[-1]).T
    return mse, np.mean(resid * resid, axis=-1)


def simulate_windows(prep: Prepared, spec: PlantSpec) -> np.ndarray:
    """Windowed simulation of one plant, (W, L)."""
    return simulate(prep, [spec])[:, 0, :]


# --------------------------------------------------------------------------------------------------
# The floor
# --------------------------------------------------------------------------------------------------


@lru_cache(maxsize=8)
def _walk_stats(length: int) -> tuple[float, float]:
    """For a doubly integrated white force over a window: the share of its squared error that survives
    removing the smooth part (_projector), and the median over its mean of that surviving part (computed, not tuned).

    A window's error from white force noise is the double sum of the noise (a random walk in
    velocity, integrated): covariance S; the projected part P x has covariance P S P, whose
    eigenvalues give its distribution (sum of lambda_i z_i^2), sampled with a fixed seed.
    """
    k = np.arange(1, length + 1)
    i = np.arange(length)
    coef = np.clip(k[:, None] - i[None, :], 0, None).astype(float)  # x = coef @ w
    S = coef @ coef.T
    P = _projector(length)
    lam = np.clip(np.linalg.eigvalsh(P @ S @ P), 0.0, None)
    share = float(np.sum(lam) / np.trace(S))
    top = np.sort(lam)[::-1][:20]
    z = np.random.default_rng(0).standard_normal((20000, len(top)))
    samples = (z * z) @ top
    return share, float(np.median(samples) / np.mean(samples))


@lru_cache(maxsize=8)
def _projector(length: int) -> np.ndarray:
    """Projector off the span of t .. t^SMOOTH_ORDER over a window: a start-velocity error, and a missing
    force that varies slowly within the window (constant, linear or quadratic in time: an offset, a
    spring or viscous force as the axis moves, a mass error through a smooth acceleration)."""
    k = np.arange(1, length + 1, dtype=float) / length
    X = np.column_stack([k ** p for p in range(1, SMOOTH_ORDER + 1)])
    return np.eye(length) - X @ np.linalg.pinv(X)


def noise_floor(prep: Prepared, rough: np.ndarray) -> float:
    """The gap the data's own noise leaves, m, from one model's per-window rough part ``rough`` (W,)
    (the second output of :func:`window_errors`).

    Two parts, both estimated from the trace:

    * force noise: per window, what no smooth correction (a start-velocity error, a slowly varying
      force: the span of t .. t^4) explains, scaled back by the share of a doubly integrated white force
      that such a projection leaves, and the median over windows read as a mean through that
      noise's own distribution (:func:`_walk_stats`): the median keeps windows hit by an effect
      from raising it. An effect that varies within a window (a short period, a mode) also
      leaves a rough part: the floor is the least over every model tried (explain), which approaches
      the noise as the model approaches the machine;
    * start velocity: without a velocity column, the noise of the local polynomial's slope (from its
      position misfit and the filter's noise gain) carried over a window (v error x t).
    """
    L = prep.windows.length
    share, median_ratio = _walk_stats(L)
    force_part = float(np.median(rough)) / median_ratio / share
    vel_part = 0.0
    if prep.vel_source != "vel_m_s column":
        misfit = _local_misfit(prep.pos)
        sigma_q = float(np.nanmedian(misfit)) * math.sqrt(SG_LENGTH / (SG_LENGTH - SG_ORDER - 1))
        sigma_v = sigma_q * _sg_slope_gain() / prep.dt
        T = L * prep.dt
        vel_part = sigma_v ** 2 * T * T / 3.0
    # never below the encoder's own quantisation (a noise-free simulated trace would give zero)
    return max(math.sqrt(force_part + vel_part), prep.resolution / math.sqrt(12.0))


@lru_cache(maxsize=1)
def _sg_slope_gain() -> float:
    """Noise gain of the Savitzky-Golay slope (per sample), sqrt(sum h^2)."""
    from drivectl.tools.explain.savgol import savgol_coeffs

    h = savgol_coeffs(SG_LENGTH, SG_ORDER, deriv=1)
    return float(np.sqrt(np.sum(h * h)))

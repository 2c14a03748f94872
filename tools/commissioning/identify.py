"""Identify a rigid feed axis (paper 004 eq (4)-(5)): mass m and friction fc(dir) sgn(v) + c(dir) v.

The procedure, as paper 004 section 1 runs it (PID + DOB, constant-velocity runs, a line fitted to
friction against velocity), made explicit:

1. **Run** a back-and-forth at several speeds (:func:`identification_profile`) under a position loop
   (PID + DOB by default), recording a trace. Any :class:`~drivectl.driver.axis.Axis` will do: the
   caller gives a factory that returns an enabled-able axis sitting at the profile's start.
2. **Friction** (:func:`fit_friction`): on each constant-velocity stretch, after the transient has
   settled, the mean commanded effort against the mean measured velocity. At constant velocity
   m q'' averages to zero, so the mean effort *is* the friction -- whatever the controller, its
   gains and its nominal mass. We use it rather than the DOB's estimate g^ (the paper's route):
   g^ equals the same number once converged, but its transient depends on the observer's nominal
   mass, which is what we are identifying, and on its bandwidth. (The bench prints g^ beside it as a
   cross-check.) Per direction, fc and c come from a linear least-squares fit F = fc + c |v|.
3. **Mass** (:func:`fit_mass`): on the acceleration stretches, the effort that acted minus the
   identified friction, regressed on the measured acceleration through the origin. The effort is
   aligned by the transport delay (the effort on trace row k acts from t(k+1) to t(k+2), DESIGN.md)
   with the mean acceleration (v_k - v_(k-1)) / dt of the interval it acted on; forgetting that
   shifts by 1 ms and biases m with the jerk.

Everything works on traces (the four required columns; ``vel_m_s`` when present, else velocity
from positions), so ``drivectl identify`` can run it on a trace file of any axis.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from drivectl.controllers.base import Controller
from drivectl.driver.axis import Axis
from drivectl.errors import EXIT_STOPPED, DrivectlError
from drivectl.tracefile.format import Trace

#: constant speeds of the default run, m/s (5 .. 100 mm/s, as for paper 004's Fig. 2)
DEFAULT_SPEEDS = (0.005, 0.01, 0.02, 0.04, 0.07, 0.1)

RIGID_KEYS = ("m", "c_pos", "c_neg", "fc_pos", "fc_neg")


class IdentificationError(DrivectlError, ValueError):
    """The data cannot support the fit (too few stretches, one direction missing...)."""

    exit_code = EXIT_STOPPED  # the data cannot be fitted: the run happened, its result is refused


# --------------------------------------------------------------------------------------------------
# the run
# --------------------------------------------------------------------------------------------------


def identification_profile(
    center: float = 0.0,
    half_stroke: float = 0.05,
    speeds: Iterable[float] = DEFAULT_SPEEDS,
    amax: float = 2.0,
    jmax: float = 100.0,
    dwell: float = 0.2,
) -> Any:
    """From ``center - half_stroke``: for each speed, out to ``center + half_stroke`` and back.

    Starts and ends at ``center - half_stroke``; jerk-limited moves, a dwell after each. The high
    acceleration (2 m/s^2, 100 m/s^3) makes the inertial force (~180 N) larger than the friction on
    the acceleration stretches, which is what the mass fit needs.
    """
    from drivectl.profiles.dwell import Dwell
    from drivectl.profiles.ptp import PointToPoint
    from drivectl.profiles.sequence import Sequence as ProfileSequence

    a, b = center - half_stroke, center + half_stroke
    segments: list[Any] = [Dwell(a, dwell, name="settle")]
    for i, v in enumerate(speeds):
        segments += [
            PointToPoint(a, b, v, amax, jmax, name=f"out {i}"),
            Dwell(b, dwell, name=f"dwell out {i}"),
            PointToPoint(b, a, v, amax, jmax, name=f"back {i}"),
            Dwell(a, dwell, name=f"dwell back {i}"),
        ]
    return ProfileSequence(segments, name="identify")


class _Recorder:
    """Wraps a controller to record its disturbance estimate (if it has one) after every step."""

    def __init__(self, controller: Controller):
        self.inner = controller
        self.dt = controller.dt
        self.name = controller.name
        self.g_hat: list[float] = []

    def reset(self) -> None:
        self.inner.reset()
        self.g_hat.clear()

    def step(self, reference: Any, feedback: Any) -> float:
        u = self.inner.step(reference, feedback)
        self.g_hat.append(float(getattr(self.inner, "disturbance_estimate", np.nan)))
        return u

    def describe(self) -> dict[str, Any]:
        return self.inner.describe()


def record_run(axis: Axis, controller: Controller, profile: Any, limits: Any = None) -> Trace:
    """Run ``profile`` on ``axis`` under ``controller``; the trace gains a ``dob_N`` column (g^)."""
    from drivectl.controllers.runtime.servo import Limits, run

    rec = _Recorder(controller)
    result = run(axis, rec, profile, limits=limits or Limits(following_error=2e-3))  # type: ignore[arg-type]
    if not result.ok:
        raise IdentificationError(f"identification run stopped: {result.detail}")
    tr = result.trace
    cols = dict(tr.columns)
    cols["dob_N"] = np.asarray(rec.g_hat[: len(tr)])
    return Trace(cols, dict(tr.meta))


# --------------------------------------------------------------------------------------------------
# the fits
# --------------------------------------------------------------------------------------------------


@dataclass
class FrictionPoint:
    """One settled constant-velocity stretch."""

    velocity: float  # mean measured velocity, m/s
    effort: float  # mean commanded effort, N
    dob: float  # mean DOB estimate g^ over the same samples (nan without one)
    samples: int


@dataclass
class RigidIdentification:
    m: float
    c_pos: float
    c_neg: float
    fc_pos: float
    fc_neg: float
    points: list[FrictionPoint] = field(default_factory=list)
    mass_samples: int = 0

    def as_dict(self) -> dict[str, float]:
        return {k: getattr(self, k) for k in RIGID_KEYS}

    def friction(self, v: np.ndarray) -> np.ndarray:
        """The identified friction force at velocity ``v`` (signed; 0 at v = 0)."""
        v = np.asarray(v, dtype=float)
        pos = self.fc_pos + self.c_pos * v
        neg = -self.fc_neg + self.c_neg * v
        return np.where(v > 0, pos, np.where(v < 0, neg, 0.0))


def _velocity(trace: Trace) -> np.ndarray:
    if "vel_m_s" in trace.columns:
        return np.asarray(trace.columns["vel_m_s"], dtype=float)
    return np.gradient(trace.pos, trace.time)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) index pairs of the True runs of ``mask``."""
    edges = np.diff(np.concatenate(([0], mask.astype(np.int8), [0])))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True))


def friction_points(
    traces: Iterable[Trace], *, settle_s: float = 0.25, min_duration_s: float = 0.15, min_speed: float = 1e-3
) -> list[FrictionPoint]:
    """The settled constant-velocity stretches of the reference, with mean effort and velocity.

    A stretch is where the reference velocity is constant (its change per cycle below 1e-3 of the
    speed) and at least ``min_speed``; its first ``settle_s`` are dropped (the loop's transient
    after the acceleration), and what remains must last ``min_duration_s``.
    """
    points = []
    for tr in traces:
        dt = tr.dt
        v_ref = np.gradient(tr.ref, dt)
        dv = np.abs(np.gradient(v_ref))
        steady = (np.abs(v_ref) >= min_speed) & (dv <= 1e-3 * np.abs(v_ref) + 1e-9)
        v = _velocity(tr)
        dob = np.asarray(tr.columns.get("dob_N", np.full(len(tr), np.nan)), dtype=float)
        skip = int(round(settle_s / dt))
        need = int(round(min_duration_s / dt))
        for i0, i1 in _runs(steady):
            i0 += skip
            if i1 - i0 < need:
                continue
            sl = slice(i0, i1)
            points.append(FrictionPoint(float(v[sl].mean()), float(tr.effort[sl].mean()),
                                        float(dob[sl].mean()), i1 - i0))
    return points


def fit_friction(points: Sequence[FrictionPoint], source: str = "effort") -> dict[str, float]:
    """fc and c per direction by linear least squares of |F| = fc + c |v| (``source``: effort or dob)."""
    out = {}
    for sign, tag in ((1.0, "pos"), (-1.0, "neg")):
        sel = [p for p in points if p.velocity * sign > 0]
        speeds = {round(abs(p.velocity), 4) for p in sel}
        if len(speeds) < 2:
            raise IdentificationError(
                f"identify: need constant-velocity stretches at two speeds or more moving {tag}, "
                f"got {len(speeds)}"
            )
        v = np.array([abs(p.velocity) for p in sel])
        f = np.array([sign * (p.effort if source == "effort" else p.dob) for p in sel])
        a = np.column_stack([np.ones_like(v), v])
        (fc, c), *_ = np.linalg.lstsq(a, f, rcond=None)
        out[f"fc_{tag}"] = float(fc)
        out[f"c_{tag}"] = float(c)
    return out


def fit_mass(
    traces: Iterable[Trace],
    friction: Callable[[np.ndarray], np.ndarray],
    *,
    delay_cycles: int = 1,
    min_accel: float = 0.2,
    min_speed: float = 2e-3,
) -> tuple[float, int]:
    """m = sum(a (f - F(v))) / sum(a^2) over the acceleration stretches; returns (m, samples).

    Interval k-1 -> k: mean acceleration (v_k - v_(k-1)) / dt, mean velocity (v_(k-1) + v_k) / 2,
    and the effort that acted on it, the row ``k - 1 - delay_cycles``. Samples where the velocity is
    below ``min_speed`` (near a standstill the axis may stick and the friction is not the sliding
    friction of the model) or the reference acceleration below ``min_accel`` are left out.
    """
    num = den = 0.0
    count = 0
    lag = 1 + delay_cycles
    for tr in traces:
        dt = tr.dt
        v = _velocity(tr)
        a_ref = np.gradient(np.gradient(tr.ref, dt), dt)
        k = np.arange(lag, len(tr))
        acc = (v[k] - v[k - 1]) / dt
        vm = 0.5 * (v[k] + v[k - 1])
        f = tr.effort[k - lag]
        ok = (np.abs(a_ref[k]) >= min_accel) & (np.abs(v[k]) >= min_speed) & (np.abs(v[k - 1]) >= min_speed)
        ok &= np.sign(v[k]) == np.sign(v[k - 1])
        if not ok.any():
            continue
        r = f[ok] - friction(vm[ok])
        num += float(np.sum(acc[ok] * r))
        den += float(np.sum(acc[ok] ** 2))
        count += int(ok.sum())
    if count < 10 or den <= 0.0:
        raise IdentificationError("identify: no acceleration stretches to fit the mass on")
    return num / den, count


def fit_rigid(
    traces: Iterable[Trace], *, delay_cycles: int = 1, settle_s: float = 0.25
) -> RigidIdentification:
    """Friction from the constant-velocity stretches, then the mass from the acceleration stretches."""
    traces = list(traces)
    points = friction_points(traces, settle_s=settle_s)
    fr = fit_friction(points)
    ident = RigidIdentification(m=float("nan"), points=points, **fr)
    ident.m, ident.mass_samples = fit_mass(traces, ident.friction, delay_cycles=delay_cycles)
    return ident


def identify_rigid(
    axis_factory: Callable[[float], Axis] | None = None,
    *,
    traces: Iterable[Trace] | None = None,
    controller_factory: Callable[[float], Controller] | None = None,
    profile: Any = None,
    delay_cycles: int = 1,
    settle_s: float = 0.25,
    limits: Any = None,
) -> dict[str, Any]:
    """Identify m, c_pos, c_neg, fc_pos, fc_neg of a rigid axis; returns a dict (SI).

    Either ``traces`` (already recorded runs) or ``axis_factory(start_position) -> Axis``: an axis
    sitting at ``start_position`` (for SimAxis, its ``initial_position``; for a drive, after homing
    there). ``controller_factory(dt)`` gives the loop (default: PID + DOB with Table 1's gains and a
    100 kg nominal mass -- the result does not depend on that guess, see the module text);
    ``profile`` defaults to :func:`identification_profile`. The dict holds the five parameters, the
    fit object under ``"fit"`` and the traces under ``"traces"``.
    """
    if traces is None:
        if axis_factory is None:
            raise ValueError("identify_rigid: give an axis_factory or traces")
        profile = profile or identification_profile()
        axis = axis_factory(profile.start_position)
        if controller_factory is None:
            from drivectl.controllers.pid import PidDob

            def controller_factory(dt: float) -> Controller:
                return PidDob(dt, ff_mass=100.0)

        traces = [record_run(axis, controller_factory(axis.dt), profile, limits)]
    traces = list(traces)
    ident = fit_rigid(traces, delay_cycles=delay_cycles, settle_s=settle_s)
    return {**ident.as_dict(), "fit": ident, "traces": traces}

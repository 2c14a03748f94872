"""Iterative learning control: the same move N times, a feedforward correction learned from each run's error.

``drivectl trace --repeat N --learn``. Users repeat one move thousands of times a
shift; what repeats in its error (the lag of the loop on the move's jerk, a mode the feedforward
does not cancel, friction where the model is wrong) can be learned and taken off by a correction
added to the controller's effort (:class:`~drivectl.controllers.learning.LearnedFeedforward`, any
controller). Method (a frequency-domain, model-inverse ILC with a zero-phase Q-filter):

* **The loop's response to the correction.** The correction ``c`` enters where the effort does, so
  its effect on the error is through the closed loop: e_(j+1) = e_j - G c-step, with G the process
  sensitivity P / (1 + P C) of *this* controller on *this* model (one-cycle transport delay
  included). G is measured, not derived, so it holds for any controller, adaptive or nonlinear
  ones included: two simulations of the model's linear part (Coulomb friction and the forces that
  do not change the dynamics left out: holding still, Coulomb friction would stick the axis and
  hide the dynamics that act while it moves) holding the profile's start, one with a pulse on the
  correction, the difference being G's impulse response (:func:`loop_response`).
* **The update.** c_(j+1) = Q(c_j + L e_j) with L = gain * conj(G) / (|G|^2 + eps) (G's inverse
  where G is large, regularised where it is small: a time-delay estimator cancels a slow correction
  as a disturbance, so G is small at low frequencies and the feedback handles those anyway), applied
  over the whole run in the frequency domain (zero-padded to twice its length, so the non-causal
  inverse -- it looks ahead over the transport delay -- does not wrap around). The error of run j is
  then (1 - gain) times the last one in the pass band, for an exact model; 0 < gain <= 1 with the
  model's phase within 90 deg of the truth converges.
* **Robustness: Q.** A zero-phase low-pass (Butterworth, forward and backward) on the whole update
  below ``q_hz``: noise and disturbances that do not repeat are not learned (each run's share of them
  is filtered and then halved by the gain, so they settle at a bounded level instead of
  accumulating), and nothing is learned near a mode the model may place wrongly (default: half the
  model's lowest mode, at most 50 Hz).

**The repetitions** are one continuous run (:class:`RepeatedProfile`): the move, a jerk-limited
return to its start and a hold (0.5 s), again, so the loop never stops and the controller keeps its
state between repetitions as it would on the machine (an observer stays converged; a controller reset
at each start instead met the plant's disturbance with a cold estimate, a repetition-to-repetition
variation the learning cannot remove). :class:`RepeatingLearner` adds the correction in each
repetition's rows, records the error and updates the correction at the repetition's last row; one
trace per repetition is cut from the run (``AXIS-rep01.csv`` ...). A repetition whose RMS error is
more than :data:`DIVERGENCE_RATIO` times the best one's steps back to the best correction with half the
gain (printed): a loop further from its model than the gain tolerates does not run away.

The learned correction is saved as ``AXIS-learned.npz`` (correction, dt, cycles, profile name and a
hash of its sampled reference, axis, effort unit, controller, how it was learned) and reused with
``--learned FILE``, which must match the run (dt, length, profile) or is refused with one line.
"""

from __future__ import annotations

import argparse
import hashlib
import math
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from drivectl.controllers.base import Controller
from drivectl.controllers.learning import LearnedFeedforward
from drivectl.driver.axis import Feedback
from drivectl.errors import InputError
from drivectl.plant_emulator.models import PlantSpec
from drivectl.profiles.base import Reference

#: learning gain: the error in the pass band shrinks by (1 - gain) per run on an exact model
DEFAULT_GAIN = 0.5
#: the Q-filter's corner when the model has no mode: above it the loop's own noise dominates
DEFAULT_Q_HZ = 50.0
#: ... and as a fraction of the model's lowest mode (a +-10 % model still has the phase right there)
Q_MODE_FRACTION = 0.5
#: regularisation of the inverse, relative to the largest |G| in the pass band
REGULARISATION = 1e-2
#: effects that change the loop's small-signal dynamics (kept in the response model); the others
#: (friction, forces, saturation, dead zones) are left out of it
LINEAR_EFFECTS = ("mass", "viscous", "delay", "spring", "resonance")
#: cycles of hold before the response pulse
PULSE_AT = 20
#: the correction is 0 for the first cycles of a run, then ramps up over START_RAMP_S (see Learning)
START_OFF_CYCLES = 4
START_RAMP_S = 0.005
#: the response pulse is scaled to move the axis about this much (m): the scale of what is learned
RESPONSE_PEAK_M = 5e-6


class LearnedFileError(InputError):
    """A learned-correction file that does not fit the run; one line naming the file and the field."""


# --------------------------------------------------------------------------------------------------
# the loop's response to the correction
# --------------------------------------------------------------------------------------------------


def linear_part(spec: PlantSpec) -> PlantSpec:
    """``spec`` without Coulomb friction, without its disturbance and with only the effects that change
    the small-signal dynamics (:data:`LINEAR_EFFECTS`)."""
    params = dict(spec.params)
    for key in ("fc_pos", "fc_neg", "disturbance_amplitude"):
        if key in params:
            params[key] = 0.0
    effects = tuple(e for e in spec.effects if e[0] in LINEAR_EFFECTS)
    return replace(spec, params=params, effects=effects, name=f"{spec.name} (linear part)")


def loop_response(model: PlantSpec, make_controller: Any, dt: float, cycles: int, position: float,
                  amplitude: float) -> np.ndarray:
    """Impulse response g (m per effort unit, ``cycles`` samples) of the closed loop from the correction
    to the measured position, holding ``position`` on the linear part of ``model``: a pulse of
    ``amplitude`` on the correction at one cycle, minus the same run without it."""
    lin = linear_part(model)
    n = cycles + PULSE_AT
    base = _hold_run(lin, make_controller, dt, n, position, 0.0)
    g = (_hold_run(lin, make_controller, dt, n, position, amplitude) - base)[PULSE_AT:] / amplitude
    peak = float(np.max(np.abs(g))) * amplitude
    if np.all(np.isfinite(g)) and peak > 0:
        # a nonlinear law (fractional powers, adaptive gains) answers small errors with more gain: measure at
        # the scale the learning works at, a pulse that moves the axis by about RESPONSE_PEAK_M
        amplitude *= min(max(RESPONSE_PEAK_M / peak, 1e-3), 1e3)
        g = (_hold_run(lin, make_controller, dt, n, position, amplitude) - base)[PULSE_AT:] / amplitude
    if not np.all(np.isfinite(g)) or not np.any(g):
        raise LearnedFileError(f"learn: the loop on the model {model.name} does not respond to the correction")
    return g


def _hold_run(lin: PlantSpec, make_controller: Any, dt: float, n: int, position: float, pulse: float) -> np.ndarray:
    from drivectl.controllers.runtime.servo import run
    from drivectl.plant_emulator.sim_axis import SimAxis
    from drivectl.tools.commissioning.bode_excitation import Hold

    corr = np.zeros(n)
    corr[PULSE_AT] = pulse
    # no encoder or effort quantisation: the response is well below a count for most of its length
    axis = SimAxis(lin.build(dt), name="learn", resolution=None, effort_scale=None, initial_position=position)
    with np.errstate(all="ignore"):
        res = run(axis, LearnedFeedforward(make_controller(), corr), Hold(position, (n - 1) * dt))
    if not res.ok or len(res.trace) < n:
        raise LearnedFileError(f"learn: the loop on the model {lin.name} did not hold its position while its "
                               f"response was measured ({res.detail})")
    return np.asarray(res.trace.pos, dtype=float)


def default_q_hz(model: PlantSpec, dt: float) -> float:
    from drivectl.tools.commissioning.frf import model_modes

    modes = model_modes(linear_part(model))
    q = min([DEFAULT_Q_HZ] + [Q_MODE_FRACTION * f for f in modes])
    return min(q, 0.4 / dt)


@dataclass
class Learning:
    """The update law for one axis: c_(j+1) = Q(c_j + L e_j) over runs of ``cycles`` samples."""

    g: np.ndarray  # the loop's impulse response, correction -> position (loop_response)
    dt: float
    gain: float = DEFAULT_GAIN
    q_hz: float = DEFAULT_Q_HZ

    def __post_init__(self) -> None:
        if not (0.0 < self.gain <= 1.0):
            raise LearnedFileError(f"--learn-gain: must be in (0, 1], got {self.gain:g}")
        if not (0.0 < self.q_hz < 0.5 / self.dt):
            raise LearnedFileError(f"--learn-hz: must be in (0, {0.5 / self.dt:g}) Hz, got {self.q_hz:g}")
        n = len(self.g)
        self.cycles = n
        self._nfft = 1 << (2 * n - 1).bit_length()
        big_g = np.fft.rfft(self.g, self._nfft)
        f = np.fft.rfftfreq(self._nfft, self.dt)
        band = f <= self.q_hz
        eps = (REGULARISATION * np.max(np.abs(big_g[band]))) ** 2
        self._l = self.gain * np.conj(big_g) / (np.abs(big_g) ** 2 + eps)
        from scipy import signal  # here, not at import: every drivectl command imports this module

        self._b, self._a = signal.butter(2, self.q_hz, fs=1.0 / self.dt)
        # nothing in the first cycles, then a short raised-cosine ramp: a controller starts with empty
        # histories (a time-delay estimator has no acceleration for its first cycles, eq 21 of paper 000)
        # and answers a correction there unlike the running loop whose response was measured
        k = np.arange(n) - START_OFF_CYCLES
        ramp = max(int(round(START_RAMP_S / self.dt)), 1)
        self._taper = np.where(k < 0, 0.0, 0.5 - 0.5 * np.cos(np.pi * np.clip(k, 0, ramp) / ramp))

    def set_gain(self, gain: float) -> None:
        self._l *= gain / self.gain
        self.gain = gain

    def q(self, x: np.ndarray) -> np.ndarray:
        """The zero-phase Q-filter (forward and backward: no lag, 4th order in magnitude)."""
        from scipy import signal

        return signal.filtfilt(self._b, self._a, x, padtype="constant") if len(x) > 12 else np.asarray(x)

    def update(self, correction: np.ndarray, error: np.ndarray) -> np.ndarray:
        """The next run's correction from this run's correction and error (ref - pos), both ``cycles`` long."""
        e = np.zeros(self.cycles)
        m = min(len(error), self.cycles)
        e[:m] = error[:m]
        step = np.fft.irfft(self._l * np.fft.rfft(e, self._nfft), self._nfft)[: self.cycles]
        return self.q(np.asarray(correction, dtype=float) + step) * self._taper


# --------------------------------------------------------------------------------------------------
# the learned-correction file
# --------------------------------------------------------------------------------------------------


def reference_hash(ref: np.ndarray) -> str:
    """A short hash of a sampled reference (to the nanometre): a profile edited under the same name differs."""
    return hashlib.sha1(np.round(np.asarray(ref, dtype=float) * 1e9).astype(np.int64).tobytes()).hexdigest()[:16]


@dataclass
class LearnedCorrection:
    axis: str
    correction: np.ndarray
    dt: float
    profile: str
    ref_hash: str
    effort_unit: str
    controller: str
    how: str = ""

    @property
    def cycles(self) -> int:
        return len(self.correction)

    def save(self, path: Path) -> Path:
        import io

        from drivectl.tracefile.format import atomic_write_bytes

        buf = io.BytesIO()
        np.savez(buf, correction=self.correction, dt=self.dt, profile=self.profile, ref_hash=self.ref_hash,
                 axis=self.axis, effort_unit=self.effort_unit, controller=self.controller, how=self.how,
                 format="drivectl learned v1")
        atomic_write_bytes(path, buf.getvalue())
        return path

    @classmethod
    def load(cls, path: str | Path) -> LearnedCorrection:
        p = Path(path)
        try:
            with np.load(p, allow_pickle=False) as data:
                fields = {k: data[k] for k in data.files}
        except FileNotFoundError:
            raise LearnedFileError(f"{p}: no such learned-correction file") from None
        except (OSError, ValueError) as exc:
            raise LearnedFileError(f"{p}: not a learned-correction file (.npz from --learn): {exc}") from None
        for key in ("correction", "dt", "profile", "ref_hash", "axis", "effort_unit", "controller"):
            if key not in fields:
                raise LearnedFileError(f"{p}: {key}: missing (not a file written by drivectl trace --learn)")
        corr = np.asarray(fields["correction"], dtype=float)
        if corr.ndim != 1 or not np.all(np.isfinite(corr)):
            raise LearnedFileError(f"{p}: correction: expected a finite 1-D sequence")
        dt = float(fields["dt"])
        if not (math.isfinite(dt) and dt > 0):
            raise LearnedFileError(f"{p}: dt: must be > 0, got {dt!r}")
        return cls(str(fields["axis"]), corr, dt, str(fields["profile"]), str(fields["ref_hash"]),
                   str(fields["effort_unit"]), str(fields["controller"]), str(fields.get("how", "")))

    def check(self, source: str, *, dt: float, cycles: int, profile: str, ref_hash: str, effort_unit: str) -> None:
        """One line naming the file and the field unless this correction fits the run."""
        if self.profile != profile:
            raise LearnedFileError(f"{source}: profile: learned on {self.profile!r}, this run follows {profile!r}")
        if abs(self.dt - dt) > 1e-12:
            raise LearnedFileError(f"{source}: dt: learned at {self.dt:g} s, this run's cycle is {dt:g} s")
        if self.cycles != cycles:
            raise LearnedFileError(f"{source}: length: {self.cycles} cycles learned, this run has {cycles}")
        if self.ref_hash != ref_hash:
            raise LearnedFileError(f"{source}: profile: {profile!r} samples to a different reference than the one "
                                   "it was learned on (edited since?)")
        if self.effort_unit != effort_unit:
            raise LearnedFileError(f"{source}: effort_unit: learned in {self.effort_unit}, the axis's is {effort_unit}")


# --------------------------------------------------------------------------------------------------
# the repeated run
# --------------------------------------------------------------------------------------------------


def add_learning_arguments(t: argparse.ArgumentParser) -> None:
    t.add_argument("--repeat", type=int, default=1, metavar="N",
                   help="run the same move N times (one trace per repetition: AXIS-rep01.csv ...); between "
                   "repetitions the axis is brought back to the start by a return move")
    t.add_argument("--learn", action="store_true",
                   help="learn a feedforward correction from each repetition's error (iterative learning "
                   "control) and save it as AXIS-learned.npz in --out")
    t.add_argument("--learned", action="append", default=[], metavar="FILE",
                   help="add a learned correction (AXIS-learned.npz) to the axis's effort; with --learn, start "
                   "learning from it (repeatable, one per axis)")
    t.add_argument("--learn-gain", type=float, default=DEFAULT_GAIN, metavar="G",
                   help=f"learning gain in (0, 1] (default {DEFAULT_GAIN})")
    t.add_argument("--learn-hz", type=float, metavar="HZ",
                   help="corner of the learning's Q-filter (default: half the model's lowest mode, at most "
                   f"{DEFAULT_Q_HZ:g} Hz)")


def wants_learning(args: argparse.Namespace) -> bool:
    return bool(getattr(args, "learn", False) or getattr(args, "learned", None) or getattr(args, "repeat", 1) != 1)


#: a repetition whose RMS error exceeds the best one's by this factor makes the learning step back
DIVERGENCE_RATIO = 1.25
#: the return move between repetitions: gentle, jerk-limited
RETURN_VMAX, RETURN_AMAX, RETURN_JMAX = 0.05, 0.5, 10.0
#: held at the start before the next repetition, s
RETURN_SETTLE_S = 0.5


@dataclass
class RepeatPlan:
    """What ``trace --repeat/--learn/--learned`` will do, checked before anything opens."""

    repeat: int
    cycles: int
    refs: dict[str, np.ndarray]
    profile_names: dict[str, str]
    corrections: dict[str, np.ndarray]
    given: dict[str, str]  # axis -> the --learned file its correction came from


def prepare_repeated(args: argparse.Namespace, cfg: Any, names: list[str], profiles: dict[str, Any],
                     specs: dict[str, PlantSpec]) -> RepeatPlan | None:
    """None for a plain trace; else the plan, every flag and --learned file checked (one line, exit 2)."""
    from drivectl.controllers.runtime.servo import check_run_length
    from drivectl.machine.config import ConfigError

    if not wants_learning(args):
        return None
    reps = args.repeat
    if not (isinstance(reps, int) and 1 <= reps <= 1000):
        raise ConfigError(f"--repeat: expected 1..1000 repetitions, got {reps}")
    if args.paced:
        raise ConfigError("--repeat/--learn: not with --paced (the repetitions run in lockstep)")
    if args.fault:
        raise ConfigError("--repeat/--learn: not with --fault")
    if not (0.0 < args.learn_gain <= 1.0):
        raise ConfigError(f"--learn-gain: must be in (0, 1], got {args.learn_gain:g}")
    if args.learn_hz is not None and not (0.0 < args.learn_hz < 0.5 / cfg.cycle_s):
        raise ConfigError(f"--learn-hz: must be in (0, {0.5 / cfg.cycle_s:g}) Hz, got {args.learn_hz:g}")
    dt = cfg.cycle_s
    duration = args.duration
    total = max((duration if duration is not None else profiles[n].duration) for n in names)
    cycles = check_run_length(total, dt, "--duration" if duration is not None else "profile: duration")
    t = np.arange(cycles) * dt
    refs = {n: np.asarray(profiles[n].sample(t)[0], dtype=float) for n in names}
    profile_names = {n: args.profile or cfg.axis(n).profile for n in names}
    corrections = {n: np.zeros(cycles) for n in names}
    given: dict[str, str] = {}
    for text in args.learned:
        lc = LearnedCorrection.load(text)
        if lc.axis not in names:
            raise LearnedFileError(f"{text}: axis: learned on axis {lc.axis!r}, not in this run ({', '.join(names)})")
        if lc.axis in given:
            raise LearnedFileError(f"{text}: axis: a second correction for axis {lc.axis} (also {given[lc.axis]})")
        lc.check(text, dt=dt, cycles=cycles, profile=profile_names[lc.axis], ref_hash=reference_hash(refs[lc.axis]),
                 effort_unit=specs[lc.axis].effort_unit)
        corrections[lc.axis] = lc.correction.copy()
        given[lc.axis] = text
    return RepeatPlan(reps, cycles, refs, profile_names, corrections, given)


class RepeatedProfile:
    """``repeat`` times: ``profile`` for ``cycles`` rows, then back to its start (a jerk-limited move)
    and a hold, ``between`` rows in all; one continuous reference, so that the loop never stops and
    the controller keeps its state from one repetition to the next, as on a machine. Rows, not seconds,
    delimit the parts, so every repetition samples its profile at exactly the times of the first."""

    def __init__(self, profile: Any, dt: float, cycles: int, between: int, repeat: int, end: float):
        from drivectl.profiles.ptp import PointToPoint

        self.name = getattr(profile, "name", "profile")
        self.source = getattr(profile, "source", None)
        self.profile, self.dt, self.cycles, self.between, self.repeat = profile, dt, cycles, between, repeat
        self.start_position = float(profile.sample(np.array([0.0]))[0][0])
        self._back = None
        if abs(end - self.start_position) > 1e-12:
            self._back = PointToPoint(end, self.start_position, RETURN_VMAX, RETURN_AMAX, RETURN_JMAX, name="return")
        self.period = cycles + between
        self.rows = repeat * cycles + (repeat - 1) * between
        self.duration = (self.rows - 1) * dt

    @staticmethod
    def between_rows(end: float, start: float, dt: float) -> int:
        from drivectl.profiles.ptp import PointToPoint

        move = 0.0 if abs(end - start) <= 1e-12 else PointToPoint(end, start, RETURN_VMAX, RETURN_AMAX,
                                                                   RETURN_JMAX).move_time
        return int(math.ceil((move + RETURN_SETTLE_S) / dt))

    def sample(self, t: np.ndarray) -> tuple[np.ndarray, ...]:
        tt = np.asarray(t, dtype=float)
        k = np.rint(tt.ravel() / self.dt).astype(np.int64)
        j = np.clip(k, 0, None) % self.period
        inside = j < self.cycles
        out = [np.zeros(k.shape) for _ in range(4)]
        if inside.any():
            parts = self.profile.sample(j[inside] * self.dt)
            for o, part in zip(out, parts, strict=True):
                o[inside] = part
        back = ~inside
        if back.any():
            local = (j[back] - self.cycles + 1) * self.dt  # the repetition's last row is the move's t = 0
            if self._back is not None:
                parts = self._back.sample(local)
            else:
                z = np.zeros(local.shape)
                parts = (z + self.start_position, z, z, z)
            for o, part in zip(out, parts, strict=True):
                o[back] = part
        return tuple(o.reshape(tt.shape) for o in out)


class RepeatingLearner(Controller):
    """The axis's controller plus, in each repetition's rows, the current correction; records the error
    and, at each repetition's last row, updates the correction for the next one (``Learning``) and calls
    ``on_repetition(axis, rep, max_um, rms_um)``. Outside the repetitions (return, hold) the controller
    alone. It is reset once, at the start of the run: its state carries over, as on a machine."""

    SettingsClass = None  # type: ignore[assignment] - a wrapper

    def __init__(self, axis: str, inner: Controller, correction: np.ndarray, schedule: RepeatedProfile,
                 learning: Learning | None, on_repetition: Any):
        self.axis = axis
        self.inner = inner
        self.name = inner.name  # type: ignore[misc]
        self.dt = inner.dt
        self.schedule = schedule
        self.learning = learning
        self.on_repetition = on_repetition
        self.correction = np.asarray(correction, dtype=float).copy()
        self.used: list[np.ndarray] = []  # the correction each repetition ran with
        self.best: tuple[float, np.ndarray] | None = None
        self._c = self.correction.tolist()
        self._e = np.zeros(schedule.cycles)
        self._k = 0

    def reset(self) -> None:
        self.inner.reset()
        self._k = 0

    def prepare(self, profile: Any, times: np.ndarray) -> None:
        self.inner.prepare(profile, times)

    def step(self, reference: Reference, feedback: Feedback) -> float:
        k = self._k
        self._k = k + 1
        u = self.inner.step(reference, feedback)
        rep, j = divmod(k, self.schedule.period)
        if j >= self.schedule.cycles:
            return u
        u += self._c[j]
        self.inner.note_applied(u)
        self._e[j] = reference.position - feedback.position
        if j == self.schedule.cycles - 1:
            self._end_of_repetition(rep + 1)
        return u

    def _end_of_repetition(self, rep: int) -> None:
        e = self._e
        max_um, rms_um = float(np.max(np.abs(e))) * 1e6, float(np.sqrt(np.mean(e * e))) * 1e6
        self.used.append(self.correction)
        note = ""
        lr = self.learning
        if lr is not None:
            if self.best is None or rms_um <= self.best[0]:
                self.best = (rms_um, self.correction)
                self.correction = lr.update(self.correction, e)
            elif rms_um > DIVERGENCE_RATIO * self.best[0]:
                # worse than the best run by more than noise explains: the loop differs from the model
                # more than the gain tolerates; back to the best correction, half the gain
                lr.set_gain(lr.gain / 2)
                self.correction = self.best[1]
                note = (f"error rose to {rms_um:.3f} um rms (best {self.best[0]:.3f}): back to the best correction, "
                        f"learning gain halved to {lr.gain:g}")
            else:
                self.correction = lr.update(self.correction, e)
            self._c = self.correction.tolist()
        if self.on_repetition is not None:
            self.on_repetition(self.axis, rep, max_um, rms_um, note)

    def describe(self) -> dict[str, Any]:
        return {**self.inner.describe(), "learned": "learning" if self.learning else "given correction"}


def run_repeated(args: argparse.Namespace, request: Any, plan: RepeatPlan, *, cfg: Any, names: list[str],
                 profiles: dict[str, Any], specs: dict[str, PlantSpec], models: dict[str, PlantSpec],
                 controllers: dict[str, Controller], builders: dict[str, Any], effects: list, faults: Any) -> int:
    """``trace --repeat N [--learn] [--learned FILE]``: one continuous run of N repetitions with return
    moves between them; returns the exit code (as plain ``trace``)."""
    from drivectl.controllers.runtime.servo import Channel, StopReason, run_channels
    from drivectl.machine.build import machine_meta, open_machine
    from drivectl.tracefile.format import Trace

    reps, cycles, refs = plan.repeat, plan.cycles, plan.refs
    profile_names, given = plan.profile_names, plan.given
    dt = cfg.cycle_s

    learners: dict[str, Learning] = {}
    if args.learn:
        for n in names:
            ac = cfg.axis(n)
            q_hz = args.learn_hz if args.learn_hz is not None else default_q_hz(models[n], dt)
            lim = ac.limits.max_effort
            amplitude = 0.02 * (lim if math.isfinite(lim) else 10 * ac.rated_effort)
            g = loop_response(models[n], builders[n], dt, cycles, float(refs[n][0]),
                              amplitude)
            learners[n] = Learning(g, dt, args.learn_gain, q_hz)

    between = max(RepeatedProfile.between_rows(float(refs[n][-1]), float(refs[n][0]), dt) for n in names)
    schedules = {n: RepeatedProfile(profiles[n], dt, cycles, between, reps, float(refs[n][-1])) for n in names}
    out = Path(args.out)
    rows: dict[int, dict[str, tuple[float, float]]] = {}

    def on_repetition(axis: str, rep: int, max_um: float, rms_um: float, note: str) -> None:
        rows.setdefault(rep, {})[axis] = (max_um, rms_um)
        if len(rows[rep]) == len(names):
            print(f"{rep:>4} " + " ".join(f"{rows[rep][n][0]:>12.3f} {rows[rep][n][1]:>12.3f}" for n in names),
                  flush=True)
        if note:
            print(f"     {axis}: {note}", flush=True)

    wrappers = {n: RepeatingLearner(n, controllers[n], plan.corrections[n], schedules[n], learners.get(n),
                                    on_repetition) for n in names}
    machine = open_machine(cfg, names, sim=args.sim, plant=args.plant, effects=effects, noise=args.noise,
                           seed=args.seed, start={n: p.start_position for n, p in profiles.items()},
                           bus_log=args.bus_log, lockstep=getattr(args, "clock", None) == "lockstep")
    what = "learning" if args.learn else ("with the learned correction" if given else "plain")
    print(f"trace: axis {','.join(names)}, {reps} repetition(s) of {cycles} cycles of {dt * 1e3:g} ms with "
          f"{between * dt:.2f} s back to the start between them, on {machine.bus}, {what} (Ctrl-C stops safely)",
          file=sys.stderr, flush=True)
    if learners:
        print("  learning: " + "; ".join(f"{n}: gain {lr.gain:g}, Q {lr.q_hz:.1f} Hz, loop response on "
                                         f"{models[n].name}" for n, lr in learners.items()), file=sys.stderr)
    head = f"{'rep':>4} " + " ".join(f"{n + ' max um':>12} {n + ' rms um':>12}" for n in names)
    print(head)
    print("-" * len(head))
    try:
        channels = []
        for n in names:
            ac = cfg.axis(n)
            meta = machine_meta(cfg, machine, specs[n], models[n], profile_names[n], effects)
            axis = machine.axes[n]
            limits = ac.limits_with(axis.drive_limits()) if ac.limits_from_drive else ac.limits
            channels.append(Channel(axis, wrappers[n], schedules[n], limits, meta))
        result = run_channels(channels, stop_request=request)
    finally:
        machine.close()
    written: list[Path] = []
    done = len(rows)
    for n, tr in result.traces.items():
        for rep in range(1, reps + 1):
            k0 = (rep - 1) * schedules[n].period
            if k0 >= len(tr):
                break
            k1 = min(k0 + cycles, len(tr))
            cols = {c: np.asarray(v)[k0:k1] for c, v in tr.columns.items()}
            cols["time_s"] = np.arange(k1 - k0) * dt
            meta = dict(tr.meta, repetition=f"{rep}/{reps}", cycles=str(k1 - k0))
            origin = "learning" if args.learn and rep > 1 else ("from " + given[n] if n in given else "none")
            meta["learned"] = origin
            if k1 - k0 < cycles:
                meta["stop"] = result.stop.value
            written.append(Trace(cols, meta).write(out / f"{n}-rep{rep:02d}.csv"))
    if args.learn:
        for n in names:
            w, lr = wrappers[n], learners[n]
            lc = LearnedCorrection(n, w.best[1] if w.best is not None else w.correction, dt, profile_names[n],
                                   reference_hash(refs[n]), specs[n].effort_unit, controllers[n].name,
                                   f"{done} repetition(s), gain {lr.gain:g}, Q {lr.q_hz:.1f} Hz, "
                                   f"model {models[n].name}")
            written.append(lc.save(out / f"{n}-learned.npz"))
    if done and not args.no_plot:
        table = [{n: {"max_um": rows[r][n][0], "rms_um": rows[r][n][1]} for n in names}
                 for r in sorted(rows) if len(rows[r]) == len(names)]
        written.append(plot_repetitions(table, names, out / f"{'-'.join(names)}-repetitions.png"))
    for p in written:
        print(f"wrote {p}")
    if not result.ok:
        # the end state as the drives reported it after the stop, never a fixed sentence
        from drivectl.controllers.runtime.safe_stop import all_confirmed, end_state_line

        f = result.fault
        ended = f"quick stop ({end_state_line(f.safe_state, f.safe_after)})" if f is not None else "quick stop"
        if result.stop is StopReason.INTERRUPTED:
            if not result.enabled:
                ended = "before the axes were enabled: nothing moved"
            print(f"drivectl: interrupted after {done} repetition(s); {ended}, traces kept", file=sys.stderr)
            return 128 + request.signum if request.signum else 130
        print(f"drivectl: stopped: {result.detail}; {ended}, traces kept", file=sys.stderr)
        unconfirmed = f is not None and not all_confirmed(f.safe_after)
        return 3 if (result.stop is StopReason.FAULT or unconfirmed) else 1
    return 0


def plot_repetitions(rows: list[dict[str, dict[str, float]]], names: list[str], path: Path) -> Path:
    """Max and RMS error per repetition, log scale; written atomically."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from drivectl.tracefile.format import atomic_write_bytes

    fig, ax = plt.subplots(figsize=(7, 4))
    reps = np.arange(1, len(rows) + 1)
    for n in names:
        ax.semilogy(reps, [r[n]["max_um"] for r in rows], "o-", label=f"{n} max")
        ax.semilogy(reps, [r[n]["rms_um"] for r in rows], "s--", label=f"{n} rms")
    ax.set_xlabel("repetition")
    ax.set_ylabel("tracking error [um]")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("drivectl trace --repeat: error per repetition")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())
    return path

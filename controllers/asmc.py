"""Adaptive sliding-mode control with a nonlinear sliding surface, paper 004 (Zhou et al. 2021).

One axis. The paper's M, C, f_c, gamma, beta, Phi, k, h are diagonal 2x2 matrices, so the X and Y
loops are independent and each is this controller with its column of Table 3 (``Asmc.for_plant``).

Surface (eq 6) and its nonlinear damping term (eq 7)::

    S   = (gamma + Phi beta) e + e'                 e = r - q
    Phi = eta (exp(-e) + exp(e))

Control law (eq 15, the adaptive version of eq 9)::

    f = M [r'' + k(t) S + Phi' beta e + h sat(S) + (gamma + Phi beta) e'] + C(dir) q' + f_c(dir) sgn(v)

Choices where the paper is silent or inconsistent (DESIGN.md, "The papers"):

* **Sign of e.** Eq (6) prints e = q - r. With the plant M q'' + C q' + f_c sgn(q') = f - d (eq 5)
  and the law (15), the surface obeys S' = -k S - h sat(S) + d/M only for e = r - q (then
  S' = Phi' beta e + lam e' + r'' - q''); with e = q - r every feedback term of (15) would push the
  error up. We use e = r - q, as eq (21) (e'' = r'' - q'') does.
* **Units.** The force law is SI: e in m, S in m/s, k in 1/s so that k S is m/s^2 inside M [...]
  (Table 3 prints k in kg/s, which only fits k S outside M; eq (15) puts it inside). The adaptation
  and the smoothing use S in mm/s, because that is the unit of Table 3's delta and Delta; rho then
  has units 1/(s mm^2/s^2) for laws 13-14 -- a number we take from Table 3 as printed.
* **exp(e) in eq (7)** takes e in mm (the paper's unit for the circle and the errors). It hardly
  matters: Phi = 2 eta cosh(e), and for the errors of this loop (|e| < 0.05 mm) cosh(e) - 1 < 1.3e-3
  in mm, 1e-9 in m; only a start-up error of a millimetre would raise the damping noticeably (by
  54 % at 1 mm). Phi' = eta (exp(e) - exp(-e)) e' (e' in mm/s) is evaluated analytically.
  gamma + Phi beta is used as 1/s (Table 3: gamma, beta in 1/s, eta in Hz): 60 1/s on X, 100 on Y.
* **h, the switching gain** (eq 10, h >= |d|; not in Table 3). We give h in N: the force h sat(S)
  is the h sgn(S) term of (15) with M already applied, so eq (10) compares like with like.
  Default 5 N: about 10 % of the Coulomb level, four times the 2 % of the total friction at the
  circle's 25 mm/s (~1.3 N) that an identification leaves (bench/identify_friction.py), and in the
  boundary layer it adds a gain h / (M Delta) = 5 / (88 * 0.9e-3) = 63 1/s to k, the order of
  gamma, which the 1 kHz loop with its 1 ms transport delay carries with margin. Larger h buys
  little here (the simulated plant is the model, d is only the delay and the quantisation) and
  costs chattering on a real axis.
* **sgn(S) -> S / (|S| + Delta)** (eq 24), with S and Delta in mm/s.
* **sgn(q') in the friction compensation.** The paper writes the measured velocity. At a reversal
  the measured velocity is zero while the axis sticks, so sgn(q') = 0 removes the compensation
  exactly when it is needed and the axis stays stuck until the error has built up a full Coulomb
  force (on the circle's X start, a reversal: 93-102 um, against 0.2 um with sgn(r')); a quantised
  q' near zero also toggles the +-47 N term (chattering). Default ``friction_sign = "reference"``:
  sgn(r'), noise-free, one step per reversal, the direction the axis is commanded to move in.
  ``"measured"`` is the paper's literal choice. ``friction_band`` (mm/s) smooths either sign as
  v / (|v| + band), 0 being the hard sign (the default: with the noise-free reference a band only
  costs, 16 um at that reversal for 0.1 mm/s). The viscous term C(dir) q' uses the measured
  velocity (continuous through zero), c_pos or c_neg by its sign; f_c(dir) by the sign used.
* **Gain laws** (11)-(14): their left sides are rates dk/dt (eq 18-23 differentiate k; printed as
  k_i or k-bar_i). Integrated by forward Euler at dt, after the effort of the cycle is computed with
  the current k, and clamped to [lower, k_bar] (the "k <= k_bar" beside each law):

  - 11: k' = rho |s| (while k <= k_bar). Never falls.
  - 12: k' = rho |s| sgn(|s| - delta) while k > k*, else k = k*. Table 3 gives no k*; we use k_in
    (the paper: k "changes adaptively from k_in"), i.e. the lower clamp of law 12 is k_in. (Plestan
    et al., the paper's ref [26], let k rise at a small rate below k*; with k* = k_in the floor is
    the same.)
  - 13: k' = rho s^2 if |s| >= delta else rho (|s| - delta).
  - 14: k' = rho s^2 if |s| >= delta else -rho s^2 (the paper's law).

  Laws 11, 13 and 14 have no lower bound in the paper beyond "k positive" (its Lyapunov argument
  needs k > 0); ``k_min`` (default 0) is that floor: a negative k would turn k S into positive
  feedback.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from drivectl.controllers.base import SCALAR_OPS, Controller, Settings, SettingsError, choice, outside_band, param
from drivectl.driver.axis import Feedback
from drivectl.profiles.base import Reference


def default_model() -> dict[str, float]:
    """Table 2, X axis, as the built-in plant rigid-x holds it (one place for the numbers)."""
    from drivectl.plant_emulator.models import load_plant

    return dict(load_plant("rigid-x").params)
MODEL_KEYS = ("mass", "c_pos", "c_neg", "fc_pos", "fc_neg")

#: Table 3, per axis (only beta, delta, rho, Delta differ; gamma, eta, k_in, k_bar are equal)
TABLE3 = {
    "x": {"gamma": 50.0, "beta": 1.0, "delta": 0.9, "k_in": 50.0, "rho": 6.0, "Delta": 0.9, "eta": 5.0,
          "k_bar": 100.0},
    "y": {"gamma": 50.0, "beta": 5.0, "delta": 1.3, "k_in": 50.0, "rho": 4.0, "Delta": 1.3, "eta": 5.0,
          "k_bar": 100.0},
}

LAWS = (11, 12, 13, 14)

#: standstill: slower than this the axis sticks or creeps (a force at the Coulomb level exactly moves it at
#: 0.1 um/s: the integral, held while it slips, would leave it creeping 0.5 um off for 0.3 s)
CREEP_M_S = 1e-5


def standstill_gain_at(gain: float, tuned_cycle_s: float, dt: float) -> float:
    """The standstill gain at cycle ``dt`` of one tuned at ``tuned_cycle_s``: scaled by (tuned / dt)^2 at a
    longer cycle, so the rest loop (the model's mass on the standstill stiffness, behind the one-cycle
    transport delay) keeps its natural frequency times the cycle, the phase the delay takes from it; never
    raised at a shorter one. y's 300 N/(um s), tuned at 1 ms, stood in a 585-925 um limit cycle at 2 ms and
    holds there at 75 (docs/standstill.md, "The cycle")."""
    return gain * min(1.0, (tuned_cycle_s / dt) ** 2)


@dataclass
class AsmcSettings(Settings):
    law: int = choice(14, LAWS, doc="gain law, paper 004 eq (11)-(14)")
    gamma: Any = param(50.0, lo=0.0, unit="1/s", doc="surface slope, eq (6)")
    beta: Any = param(1.0, lo=0.0, unit="1/s", doc="weight of Phi, eq (6)")
    eta: Any = param(5.0, lo=0.0, unit="Hz", doc="scale of Phi, eq (7)")
    rho: Any = param(6.0, lo=0.0, doc="adaptation rate (s in mm/s)")
    delta: Any = param(0.9, lo=0.0, unit="mm/s", doc="boundary of the gain laws (12)-(14)")
    Delta: Any = param(0.9, lo=0.0, lo_open=True, unit="mm/s", doc="smoothing of sgn(S), eq (24)")
    k_in: Any = param(50.0, lo=0.0, unit="1/s", doc="initial gain k(0); also k* of law (12)")
    k_bar: Any = param(100.0, lo=0.0, lo_open=True, unit="1/s", doc="upper bound of k")
    k_min: Any = param(0.0, lo=0.0, unit="1/s", doc="lower bound of k for laws 11, 13, 14")
    h: Any = param(5.0, lo=0.0, unit="N", doc="switching gain, eq (10) h >= |d| (not in Table 3)")
    friction_sign: str = choice(
        "reference", ("reference", "measured"), doc="velocity whose sign selects the Coulomb compensation"
    )
    friction_band: Any = param(0.0, lo=0.0, unit="mm/s", doc="smoothing of that sign (0: hard sign)")
    standstill_gain: float = param(0.0, lo=0.0, unit="N/(um s)",
                                   doc="integral action at standstill (the reference rests, the axis sticks) "
                                   "on the error outside standstill_band_m; 0: the paper's law (docs/standstill.md)")
    standstill_band_m: float = param(1.5e-7, lo=0.0, unit="m", doc="standstill: the error left alone")
    standstill_s: float = param(0.05, lo=0.0, lo_open=True, unit="s",
                                doc="standstill: integral time; the stiffness on the error outside the band is "
                                "standstill_gain x standstill_s (mbc's standstill, docs/standstill.md)")
    standstill_cycle_s: float = param(0.001, lo=0.0, lo_open=True, unit="s",
                                      doc="the cycle standstill_gain is tuned for; at a longer cycle it acts "
                                      "scaled by (standstill_cycle_s / cycle)^2 (docs/standstill.md)")

    def validate(self, source: str = "settings", prefix: str = "") -> None:
        super().validate(source, prefix)
        if np.any(np.asarray(self.k_in) > np.asarray(self.k_bar)):
            raise SettingsError(f"{source}: {prefix}k_in: must be <= k_bar ({_show(self.k_bar)}), "
                                f"got {_show(self.k_in)}")
        if np.any(np.asarray(self.k_min) > np.asarray(self.k_in)):
            raise SettingsError(f"{source}: {prefix}k_min: must be <= k_in ({_show(self.k_in)}), "
                                f"got {_show(self.k_min)}")


def _show(value: Any) -> str:
    arr = np.asarray(value)
    return f"{float(arr):g}" if arr.ndim == 0 else f"array with min {arr.min():g}, max {arr.max():g}"


def gain_rate(law: int, s_mm: float, rho: float, delta: float) -> float:
    """dk/dt of gain law ``law`` (paper 004 eq (11)-(14)) for the surface s in mm/s (scalar).

    The bounds (k <= k_bar, law 12's k > k*) are clamps applied by the caller.
    """
    a = s_mm if s_mm >= 0.0 else -s_mm
    if law == 14:
        return rho * s_mm * s_mm if a >= delta else -rho * s_mm * s_mm
    if law == 13:
        return rho * s_mm * s_mm if a >= delta else rho * (a - delta)
    if law == 12:
        return rho * a if a > delta else -rho * a if a < delta else 0.0
    if law == 11:
        return rho * a
    raise SettingsError(f"asmc: law: must be one of {LAWS}, got {law!r}")


def _gain_rate_array(law: int, s_mm: np.ndarray, rho: Any, delta: Any) -> np.ndarray:
    a = np.abs(s_mm)
    s2 = s_mm * s_mm
    if law == 14:
        return np.where(a >= delta, rho * s2, -rho * s2)
    if law == 13:
        return np.where(a >= delta, rho * s2, rho * (a - delta))
    if law == 12:
        return rho * a * np.sign(a - delta)
    return rho * a


def _model(model: Mapping[str, float] | None) -> dict[str, float]:
    """Validate the nominal model (mass, c_pos, c_neg, fc_pos, fc_neg as magnitudes)."""
    if model is None:
        return default_model()
    params = model if isinstance(model, Mapping) else getattr(model, "params", None)
    if not isinstance(params, Mapping):
        raise SettingsError(f"controller asmc: model: expected a mapping or a PlantSpec, got {model!r}")
    out = {}
    for key in MODEL_KEYS:
        if key not in params:
            raise SettingsError(f"controller asmc: model.{key}: missing")
        value = params[key]
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
            raise SettingsError(f"controller asmc: model.{key}: expected a finite number, got {value!r}")
        if value < 0 or (key == "mass" and value == 0):
            raise SettingsError(
                f"controller asmc: model.{key}: must be {'> 0' if key == 'mass' else '>= 0'}, got {value!r}"
            )
        out[key] = float(value)
    return out


class Asmc(Controller):
    """Paper 004's adaptive SMC on one rigid axis; effort in N. See the module text for every choice.

    ``model`` is the nominal plant of eq (5): a mapping with mass, c_pos, c_neg, fc_pos, fc_neg
    (magnitudes, SI), or a PlantSpec; default Table 2's X axis. State: the adaptive gain ``k``.
    """

    name = "asmc"
    origin = "paper 004"
    SettingsClass = AsmcSettings

    def __init__(
        self,
        dt: float,
        settings: Settings | Mapping[str, Any] | None = None,
        *,
        model: Mapping[str, float] | Any | None = None,
        **kwargs: Any,
    ):
        self.model = _model(model)
        super().__init__(dt, settings, **kwargs)

    @classmethod
    def for_plant(cls, dt: float, plant_spec: Any, axis: str = "x", **settings: Any) -> Asmc:
        """Table 3's column for ``axis`` and the nominal model from the plant's parameters."""
        if axis not in TABLE3:
            raise SettingsError(f"controller {cls.name}: axis: must be 'x' or 'y', got {axis!r}")
        return cls(dt, {**TABLE3[axis], **settings}, model=plant_spec)

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), **{f"model_{k}": v for k, v in self.model.items()}}

    # ---------------------------------------------------------------------------------------------
    def reset(self) -> None:
        s = self.settings
        if self.ops is SCALAR_OPS:
            self.k = s.k_in
        else:
            shapes = [np.shape(v) for v in s.as_dict().values() if isinstance(v, np.ndarray)]
            self.k = np.broadcast_to(np.asarray(s.k_in, dtype=float), np.broadcast_shapes(*shapes)).copy()
        #: the last surface value, mm/s (for inspection and tests)
        self.s_mm = 0.0
        self._law = int(s.law)
        # the gain's lower clamp: k* = k_in for law 12, k_min otherwise
        self._k_lo = s.k_in if self._law == 12 else s.k_min
        if self.ops is SCALAR_OPS:
            # plain floats for the fast path (attribute reads of a dataclass are slower than locals)
            m = self.model
            self._c = (
                float(s.gamma), float(s.beta), float(s.eta), float(s.rho), float(s.delta),
                float(s.Delta), float(s.k_bar), float(self._k_lo), float(s.h),
                m["mass"], m["c_pos"], m["c_neg"], m["fc_pos"], m["fc_neg"],
                s.friction_sign == "reference", float(s.friction_band) * 1e-3,
            )
        #: the standstill integral force, N (its stiffness part aside): built only while the reference rests
        #: and the axis sticks, started from the law's last Coulomb compensation (docs/standstill.md)
        self.hold_force = 0.0
        gain = standstill_gain_at(float(s.standstill_gain), float(s.standstill_cycle_s), self.dt) * 1e6  # N/(m s)
        self._hold_rate = gain * self.dt  # N per m of error per cycle
        self._hold_band = float(s.standstill_band_m)
        self._hold_stiffness = gain * float(s.standstill_s)  # N/m

    def adapt(self, s_mm: Any) -> Any:
        """One cycle of the gain law for surface ``s_mm`` (mm/s): k += dt dk/dt, clamped. Returns k."""
        s = self.settings
        if self.ops is SCALAR_OPS:
            k = self.k + self.dt * gain_rate(self._law, s_mm, s.rho, s.delta)
            lo, hi = self._k_lo, s.k_bar
            self.k = lo if k < lo else hi if k > hi else k
        else:
            k = self.k + self.dt * _gain_rate_array(self._law, np.asarray(s_mm), s.rho, s.delta)
            self.k = np.clip(k, self._k_lo, s.k_bar)
        return self.k

    def step(self, reference: Reference, feedback: Feedback) -> Any:
        if self.ops is not SCALAR_OPS:
            return self._step_array(reference, feedback)
        (gamma, beta, eta, rho, delta, Delta, k_bar, k_lo, h,
         mass, c_pos, c_neg, fc_pos, fc_neg, use_ref, band) = self._c
        v = feedback.velocity
        e = reference.position - feedback.position  # m, e = r - q (see module text)
        de = reference.velocity - v  # m/s
        ex = math.exp(1e3 * e)  # exp(e) with e in mm, eq (7)
        exi = 1.0 / ex
        phi = eta * (ex + exi)
        lam = gamma + phi * beta
        dphi = eta * (ex - exi) * (1e3 * de)  # dPhi/dt, e and e' in mm, mm/s
        S = lam * e + de  # m/s, eq (6)
        s_mm = 1e3 * S
        a = s_mm if s_mm >= 0.0 else -s_mm
        sat = s_mm / (a + Delta)  # eq (24), in mm/s
        k = self.k
        acc = reference.acceleration + k * S + dphi * beta * e + lam * de
        # friction compensation: viscous on the measured velocity, Coulomb on the chosen sign
        visc = (c_pos if v > 0.0 else c_neg) * v
        vs = reference.velocity if use_ref else v
        if band > 0.0:
            coul = (fc_pos if vs > 0.0 else fc_neg) * vs / ((vs if vs >= 0.0 else -vs) + band)
        else:
            coul = fc_pos if vs > 0.0 else -fc_neg if vs < 0.0 else 0.0
        f = mass * acc + h * sat + visc + coul
        if self._hold_rate:
            f += self._standstill(reference, v, e, coul)
        # adaptation (after the effort: this cycle used k(t_k)); inline gain_rate for speed
        law = self._law
        if law == 14:
            rate = rho * s_mm * s_mm if a >= delta else -rho * s_mm * s_mm
        elif law == 13:
            rate = rho * s_mm * s_mm if a >= delta else rho * (a - delta)
        elif law == 12:
            rate = rho * a if a > delta else -rho * a if a < delta else 0.0
        else:
            rate = rho * a
        k += self.dt * rate
        self.k = k_lo if k < k_lo else k_bar if k > k_bar else k
        self.s_mm = s_mm
        return f

    def _standstill(self, reference: Reference, v: float, e: float, coul: float) -> float:
        """The standstill force (docs/standstill.md), mbc's standstill on this law: at rest the law's own
        stiffness, M k lambda (0.5 N/um on y), cannot pass the Coulomb friction (51 N) short of a 100 um
        error, so a resting axis stands where it stuck. While the reference rests, a stiffness
        (standstill_gain x standstill_s, 15 N/um on y, mbc's on x) acts on the error outside the band, and
        while the axis also sticks the integral of that error builds (held while the axis slips): the
        integral breaks the axis away, the stiffness stops its slip near the target instead of letting
        the integral, at the breakaway level, carry it through to the other side (the hunting under
        force noise). Both are released as the reference moves (the law's own Coulomb compensation takes
        over)."""
        if reference.velocity != 0.0 or reference.acceleration != 0.0:
            # while moving, what the hold starts from: the law's Coulomb compensation of the last moving
            # cycle (mbc keeps its disturbance estimate, the friction, where the motion left it)
            self.hold_force = coul
            return 0.0
        out = outside_band(e, self._hold_band)
        if -CREEP_M_S < v < CREEP_M_S:
            self.hold_force += self._hold_rate * out
        return self.hold_force + self._hold_stiffness * out

    def _step_array(self, reference: Reference, feedback: Feedback) -> np.ndarray:
        """The same law on numpy arrays (a batch of gain sets; feedback may be arrays too)."""
        s = self.settings
        m = self.model
        v = np.asarray(feedback.velocity, dtype=float)
        e = reference.position - np.asarray(feedback.position, dtype=float)
        de = reference.velocity - v
        ex = np.exp(1e3 * e)
        exi = 1.0 / ex
        phi = s.eta * (ex + exi)
        lam = s.gamma + phi * s.beta
        dphi = s.eta * (ex - exi) * (1e3 * de)
        S = lam * e + de
        s_mm = 1e3 * S
        sat = s_mm / (np.abs(s_mm) + s.Delta)
        acc = reference.acceleration + self.k * S + dphi * s.beta * e + lam * de
        visc = np.where(v > 0.0, m["c_pos"], m["c_neg"]) * v
        vs = np.broadcast_to(reference.velocity, v.shape) if s.friction_sign == "reference" else v
        fc = np.where(vs > 0.0, m["fc_pos"], m["fc_neg"])
        band = np.asarray(s.friction_band, dtype=float) * 1e-3
        safe = np.where(band > 0.0, band, 1.0)
        coul = fc * np.where(band > 0.0, vs / (np.abs(vs) + safe), np.sign(vs))
        f = m["mass"] * acc + s.h * sat + visc + coul
        self.adapt(s_mm)
        self.s_mm = s_mm
        return f

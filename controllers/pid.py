"""PID in force units, and paper 004's PID + disturbance observer (eqs (2)-(3), Table 1).

Both work in SI (gains in N/m, N s/m, N/(m s)); Table 1 prints N/mm, so its P = 3000 N/mm is
``kp = 3.0e6``. The tracking error is e = r - q (the sign that makes +kp e a restoring force).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from drivectl.controllers.base import SCALAR_OPS, Controller, Settings, SettingsError, choice, param
from drivectl.controllers.dob import DisturbanceObserver
from drivectl.driver.axis import Feedback
from drivectl.profiles.base import Reference

#: Table 1 of paper 004, in SI (the paper prints N/mm, N s/mm, N/(mm s)); I differs per axis
TABLE1_KI = {"x": 2.0e5, "y": 2.5e5}


@dataclass
class PidSettings(Settings):
    kp: Any = param(3.0e6, lo=0.0, unit="N/m", doc="proportional gain")
    ki: Any = param(2.0e5, lo=0.0, unit="N/(m s)", doc="integral gain")
    kd: Any = param(1.0e4, lo=0.0, unit="N s/m", doc="derivative gain, on e' = r' - q'")
    ff_mass: Any = param(0.0, lo=0.0, unit="kg", doc="acceleration feed-forward ff_mass * r'' (0: none)")
    d_filter_hz: Any = param(
        0.0, lo=0.0, unit="Hz", doc="first-order low-pass on the derivative term (0: none)"
    )
    i_limit: Any = param(0.0, lo=0.0, unit="N", doc="clamp of the integral term (0: unlimited)")


class Pid(Controller):
    """f = ff_mass r'' + kp e + ki int(e) + kd LPF(e'), e = r - q.

    The derivative uses the drive's measured velocity (e' = r' - q'), not a difference of quantised
    positions: 76 nm counts differenced at 1 ms would be 76 um/s steps. ``d_filter_hz`` low-passes
    it when the velocity is noisy (a real encoder); each Hz of filter costs phase, so it is off by
    default. The integral is the rectangle rule at dt (explicit state ``integral``, in m s).
    """

    name = "pid"
    SettingsClass = PidSettings

    def reset(self) -> None:
        self.integral = 0.0  # int(e) dt, m s
        self.d_state = 0.0  # filtered e', m/s
        self._d_started = False
        s = self.settings
        # discrete first-order low-pass: y += a (x - y), a = 1 - exp(-2 pi fc dt); a = 1 when off
        fc = s.d_filter_hz
        if self.ops is SCALAR_OPS:
            self._d_alpha = 1.0 - math.exp(-2.0 * math.pi * fc * self.dt) if fc > 0.0 else 1.0
        else:
            self._d_alpha = self.ops.where(fc > 0, 1.0 - self.ops.exp(-2.0 * math.pi * fc * self.dt), 1.0)

    def _pid(self, reference: Reference, feedback: Feedback) -> Any:
        s = self.settings
        e = reference.position - feedback.position
        de = reference.velocity - feedback.velocity
        if self._d_started:
            self.d_state = self.d_state + self._d_alpha * (de - self.d_state)
        else:
            self.d_state = de  # the filter starts at the first value (no start-up kick)
            self._d_started = True
        self.integral = self.integral + e * self.dt
        i_term = s.ki * self.integral
        lim = s.i_limit
        if self.ops is SCALAR_OPS:
            if lim > 0.0 and (i_term > lim or i_term < -lim):
                # anti-windup by clamping the stored integral, so it unwinds at once when e turns
                i_term = lim if i_term > 0 else -lim
                self.integral = i_term / s.ki
        else:
            clamped = self.ops.clip(i_term, -lim, lim)
            i_term = self.ops.where(lim > 0, clamped, i_term)
            safe_ki = self.ops.where(s.ki > 0, s.ki, 1.0)
            self.integral = self.ops.where(s.ki > 0, i_term / safe_ki, self.integral)
        return s.ff_mass * reference.acceleration + s.kp * e + i_term + s.kd * self.d_state

    def step(self, reference: Reference, feedback: Feedback) -> Any:
        return self._pid(reference, feedback)

    def _pid_rows(self, x: Any, pos: Any, vel: Any) -> tuple[Any, Any, Any]:
        """The PID's step on rows over [state, position, velocity] (controllers/linear_form.py), the
        reference held: (integral after the step, filtered e' after it, the PID term). Without the clamp
        (``i_limit``): linear for deviations inside it."""
        s = self.settings
        integral = x[0] - self.dt * pos  # e = -position
        d = (1.0 - self._d_alpha) * x[1] - self._d_alpha * vel  # e' = -velocity
        return integral, d, s.ki * integral + s.kd * d - s.kp * pos

    def linear_form(self) -> Any:
        """State [integral, filtered e'] (before the step); see :meth:`Controller.linear_form`."""
        from drivectl.controllers.linear_form import basis, from_rows

        if self.ops is not SCALAR_OPS:
            return None  # a batch of gain sets has no single form
        x, pos, vel = basis(2)
        integral, d, u = self._pid_rows(x, pos, vel)
        return from_rows([integral, d], u, self.dt)


@dataclass
class PidDobSettings(PidSettings):
    # Table 1 (X axis) in SI; ff_mass is the nominal mass m of eq (2) (Table 2, X)
    ff_mass: Any = param(88.08, lo=0.0, lo_open=True, unit="kg", doc="nominal mass m of eqs (2)-(3)")
    # 10 Hz, critically damped: settled (5 time constants of 16 ms) within 0.1 s of a new constant
    # velocity, a third of the position loop's 29 Hz so the two do not fight, and w0 dt = 0.06, where
    # the discrete observer behaves as the continuous one. Table 1 literally: see controllers/dob.py.
    dob_hz: Any = param(10.0, lo=0.0, lo_open=True, unit="Hz", doc="observer natural frequency w0 / 2 pi")
    dob_zeta: Any = param(1.0, lo=0.0, lo_open=True, doc="observer damping ratio")
    # CiA 402 cyclic synchronous torque: the effort computed at sample k acts from t(k+1) (DESIGN.md)
    delay_cycles: int = choice(1, (0, 1, 2, 3, 4), doc="transport delay of the effort, whole cycles")


class PidDob(Pid):
    """Paper 004 eq (2): f = m r'' + P e + D e' + I int(e) + g^, with g^ from the DOB of eq (3).

    Eq (2) is printed ``f = m (r'' - P e' - D e' - I int(e)) + g^``. Table 1 gives P in N/mm, D in
    N s/mm, I in N/(mm s): force gains, so they cannot sit inside m (...) next to r'' (that would make
    the loop gain m P = 264 000 N/mm). Read consistently:

    * only r'' is multiplied by m (acceleration feed-forward with the nominal mass);
    * P, D, I multiply e, e', int(e) directly, in N per unit;
    * the first "P e'" is a typo for P e (e' appears twice), and with e = r - q the feedback terms
      are +P e + D e' + I int(e) (the printed minus signs belong to e = q - r, eq (6)'s convention);
    * + g^ cancels the friction: the plant is m q'' = f - g (eq (1)).

    Closed loop on the nominal plant: m e'' + D e' + P e + I int(e) = g - g^. With Table 1 (x):
    w_n = sqrt(P/m) = 185 rad/s (29 Hz), zeta = D / (2 sqrt(P m)) = 0.31, the integral zero at
    I/P = 0.067 rad/s; crossover 203 rad/s with 34 deg of phase margin, of which the 1.5 ms of
    sampling and transport delay take 17: stable, lightly damped (34 % overshoot on a step,
    tests/test_controllers_004.py), as the paper's stiff identification loop is.

    The DOB's gains: see controllers/dob.py (Table 1's k_ev, k_ed taken literally give a 20 s
    observer; we set w0 = 2 pi dob_hz, critically damped by default). ``disturbance_estimate`` is
    g^ (N), the friction the observer currently sees; identification reads it. The observer is fed
    the command this controller returned; when the servo loop clips it (``Limits.max_effort``) g^
    takes the missing force for friction until the clipping ends.
    """

    name = "pid-dob"
    origin = "paper 004"
    SettingsClass = PidDobSettings

    @classmethod
    def for_plant(cls, dt: float, plant_spec: Any, axis: str = "x", **settings: Any) -> PidDob:
        """Table 1's column for ``axis`` (x, y; another axis, such as z, takes the defaults, Table 1's X, as
        ``pid`` does: set its gains) with the plant's nominal mass: Table 2's on a rigid plant, the total
        ``m1 + m2`` on a two-mass one (below its mode the axis moves as that one body, the rigid model
        m q'' = f - g the observer assumes)."""
        base: dict[str, Any] = {"ff_mass": _mass_of(plant_spec)}
        if axis in TABLE1_KI:
            base["ki"] = TABLE1_KI[axis]
        return cls(dt, {**base, **settings})

    def reset(self) -> None:
        super().reset()
        s = self.settings
        w0 = 2.0 * math.pi * s.dob_hz
        self.observer = DisturbanceObserver(self.dt, s.ff_mass, w0, s.dob_zeta, int(s.delay_cycles))
        self.last_effort = 0.0

    def note_applied(self, effort: Any) -> None:
        # the observer compares the effort that acted with the motion (controllers/base.py)
        self.last_effort = effort

    @property
    def disturbance_estimate(self) -> Any:
        """The DOB's friction estimate g^, in the effort unit (N)."""
        return self.observer.g_hat

    def linear_form(self) -> Any:
        """State [integral, filtered e', v^, g^, f(k-1), ..., f(k-1-delay)] (before the step): the observer
        of controllers/dob.py fed this law's own past efforts; see :meth:`Controller.linear_form`."""
        from drivectl.controllers.linear_form import basis, from_rows

        if self.ops is not SCALAR_OPS:
            return None
        ob = self.observer
        nd = ob.delay_cycles + 1
        x, pos, vel = basis(4 + nd)
        acting = x[4 + ob.delay_cycles]  # the command that moved the axis since the last sample
        v_pred = x[2] + self.dt * (acting - x[3]) / ob.mass
        innov = vel - v_pred
        v_hat = v_pred + self.dt * ob.l1 * innov
        g_hat = x[3] - self.dt * ob.l2 * innov
        integral, d, u = self._pid_rows(x, pos, vel)
        f = u + g_hat
        return from_rows([integral, d, v_hat, g_hat, f, *x[4:4 + nd - 1]], f, self.dt)

    def step(self, reference: Reference, feedback: Feedback) -> Any:
        g_hat = self.observer.step(self.last_effort, feedback.velocity)
        f = self._pid(reference, feedback) + g_hat
        self.last_effort = f
        return f


def _mass_of(plant_spec: Any) -> float:
    """The nominal moving mass of a PlantSpec (its parameters' bodies in total: ``mass``, or ``m1 + m2``;
    its effects are not the model) or of a mapping of a rigid plant's parameters (``mass``)."""
    if not isinstance(plant_spec, Mapping):
        return float(plant_spec.without_effects().nominal_mass)
    if "mass" not in plant_spec:
        raise SettingsError("plant: mass: missing (pid-dob needs the nominal mass of eqs (2)-(3))")
    return float(plant_spec["mass"])

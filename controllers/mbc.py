"""Model-based control (``mbc``): exact-inverse feed-forward, a Kalman filter with disturbance states and
LQR state feedback on the state predicted over the transport delay, all designed from the model.

Nothing to hand-tune: the design takes the model (a PlantSpec: rigid or two-mass, with its effects) and
two bandwidths with physical meaning, and computes every gain (``scipy.linalg.solve_discrete_are``).

* **Feed-forward** (controllers/linear_model.py): the effort the model needs so that its table follows the
  reference exactly, for the cycle in which the command will act (one cycle later: the transport delay of
  cyclic synchronous torque; plus any ``delay`` effect of the model), held as the drive holds it; plus the
  forces the model knows outside its linear part (Coulomb and viscous friction per direction, Stribeck,
  periodic, offset). It needs the reference ahead of time: :meth:`Mbc.prepare` takes the profile and the
  run's cycle times before the run (the servo loop calls it) and computes the whole table at once. Without
  it (a caller that only steps) the reference is extrapolated from its derivatives at constant jerk, which
  is exact except within two cycles of a jerk switch. On a two-mass model the snap impulse of the exact
  inverse at each jerk switch is spread over a short centred window computed from the model
  (``snap = "spread"``, :meth:`LinearModel.snap_spread`: 3.2 ms on two-mass): it cut the effort's
  roughness by a third (bench/precision.py, docs/precision.md).
* **Kalman filter** on the model discretised exactly for the cycle, with the command in flight (the one
  sent last cycle, acting now) and two disturbance states: an effort-equivalent disturbance d and its
  rate. Where the model names a disturbance frequency (paper 000's d = 0.1 sin(pi t)) d is an oscillator at
  it (an internal model: a sinusoid is tracked without lag); otherwise a ramp (d' a random walk). The
  filter is fed the effort minus the model's friction compensation (what the friction takes is not
  accelerating anything), so d is what the model did not explain. Steady-state gains.
* **State feedback**: LQR on the model with the table position weighted to put the rigid-body mode at
  ``bandwidth_hz`` (about 0.7 damping), applied to the state predicted one cycle ahead (when the
  command will start acting), against the reference state there; d predicted over that cycle is
  cancelled.

Choices: the linear part uses the mean of the two directions' viscous coefficients (the difference is a
known force, in the feed-forward); measurement noise defaults to the quantisation of a 76.29 nm encoder
and of its velocity in counts per second; the observer bandwidth sets the disturbance process noise by
the rigid-body approximation (q = M^2 w^8 sigma_x^2 dt for the chain position - velocity - d - d').
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.linalg import solve_discrete_are

from drivectl.controllers.base import Controller, Settings, SettingsError, choice, outside_band, param
from drivectl.controllers.linear_model import LinearModel, discretise
from drivectl.driver.axis import Feedback
from drivectl.profiles.base import Reference


@dataclass
class MbcSettings(Settings):
    bandwidth_hz: float = param(0.0, lo=0.0, hi=200.0, unit="Hz",
                                doc="state-feedback bandwidth (rigid-body mode of the LQR loop); 0: from the model "
                                "(AUTO_HZ: 40 Hz with a coupling mode, 80 Hz for a rigid axis)")
    observer_hz: float = param(0.0, lo=0.0, hi=200.0, unit="Hz",
                               doc="Kalman filter's disturbance bandwidth; 0: from the model (AUTO_HZ: 20 Hz)")
    mode_damping: float = param(10.0, lo=0.0, doc="LQR weight on the coupling's deflection rate (two-mass): "
                                "active damping of the axial mode, relative to the position weight")
    position_noise_m: float = param(2.2e-8, lo=0.0, lo_open=True, unit="m",
                                    doc="position measurement noise (76.29 nm counts: 22 nm)")
    velocity_noise_m_s: float = param(2.2e-5, lo=0.0, lo_open=True, unit="m/s",
                                      doc="velocity measurement noise")
    force_noise: float = param(0.0, lo=0.0, unit="effort", doc="white force noise on the driven body")
    disturbance: str = choice("auto", ("auto", "ramp"),
                              doc="auto: an oscillator at the model's disturbance frequency, else a ramp")
    friction_ff: bool = choice(True, (True, False), doc="compensate the model's friction in the feed-forward")
    feedforward: bool = choice(True, (True, False), doc="the model-inverse feed-forward (off: feedback only)")
    snap: str = choice("spread", ("spread", "exact"),
                       doc="two-mass: the inverse's snap impulse at each jerk switch spread over the window "
                       "the model sets (controllers/linear_model.py), or held in one cycle (exact)")
    standstill: bool = choice(True, (True, False),
                              doc="a model with Coulomb friction: while the reference rests and the axis sticks, "
                              "the filter is frozen (docs/standstill.md)")
    standstill_band_m: float = param(1.5e-7, lo=0.0, unit="m",
                                     doc="standstill: the error left alone (no integral action inside it)")
    standstill_s: float = param(0.05, lo=0.0, lo_open=True, unit="s",
                                doc="standstill: integral time of the error outside the band")


#: (bandwidth_hz, observer_hz) when the settings leave them 0, by the model's number of bodies: a coupling
#: mode (two-mass) limits both (every +-10 % corner stays stable with margin: largest spectral radius 0.983);
#: a rigid axis carries twice the state-feedback bandwidth (0.964 on rigid-x's 32 corners), which the friction
#: it must reject at its reversals needs (bench/precision.py: x with Stribeck and noise 15.6 -> 11.0 um, with
#: explain's model 2.4 um)
AUTO_HZ = {2: (40.0, 20.0), 1: (80.0, 20.0)}


class _Extrapolated:
    """A reference extrapolated at constant jerk from one sample (the fallback without preview)."""

    def __init__(self, ref: Reference):
        self.ref = ref

    def sample(self, t: np.ndarray) -> tuple[np.ndarray, ...]:
        r = self.ref
        t = np.asarray(t, dtype=float)
        p = r.position + t * (r.velocity + t * (0.5 * r.acceleration + t * r.jerk / 6.0))
        v = r.velocity + t * (r.acceleration + 0.5 * t * r.jerk)
        a = r.acceleration + t * r.jerk
        return p, v, a, np.full_like(t, r.jerk)


@dataclass
class Design:
    """The matrices of one design (also what the robust check needs)."""

    A: np.ndarray  # plant, discrete (n x n)
    B: np.ndarray  # (n x 1)
    K: np.ndarray  # state feedback (n,)
    F: np.ndarray  # estimator model: plant + disturbance (n+2 square)
    G: np.ndarray  # (n+2,)
    L: np.ndarray  # Kalman gain (n+2 x 2)
    H: np.ndarray  # measurement: table position and velocity (2 x n+2)
    gd: np.ndarray  # disturbance cancellation: effort per unit of the 2 disturbance states


def design(model: LinearModel, settings: MbcSettings, dt: float, disturbance_hz: float = 0.0) -> Design:
    """Every gain of the controller from the model and the settings."""
    n = model.n
    ac, bc = model.continuous()
    A, B = discretise(ac, bc, dt)
    # LQR: table position weighted (M w^2)^2, effort 1 -> rigid mode at ~w, damping ~0.7
    M = model.total_mass
    w = 2.0 * math.pi * settings.bandwidth_hz
    Q = np.zeros((n, n))
    Q[n - 2, n - 2] = (M * w * w) ** 2
    Q += np.eye(n) * 1e-9 * Q[n - 2, n - 2]
    if n == 4 and settings.mode_damping:
        # weight on the coupling's deflection rate: the LQR damps the axial mode actively
        dv = np.array([0.0, 1.0, 0.0, -1.0])
        Q += np.outer(dv, dv) * settings.mode_damping * (M * w) ** 2
    R = np.array([[1.0]])
    X = solve_discrete_are(A, B, Q, R)
    K = np.linalg.solve(R + B.T @ X @ B, B.T @ X @ A).ravel()
    # estimator model: [x; d; d'] with d an effort on body 0
    na = n + 2
    fa = np.zeros((na, na))
    fa[:n, :n] = ac
    # how d enters: where the model names a disturbance (paper 000: d1 = d2 = d, a force on every body)
    # that structure; otherwise an acceleration common to every body (what a mass error or a force on
    # the whole axis does), in effort units of the total mass: d / M on each body
    paper = model.design.disturbance_amplitude > 0
    for i in range(model.n_bodies):
        fa[2 * i + 1, n] = 1.0 / model.masses[i] if paper else 1.0 / M
    bd = fa[:n, n].copy()
    fa[n, n + 1] = 1.0
    wd = 2.0 * math.pi * disturbance_hz
    fa[n + 1, n] = -wd * wd
    ba = np.zeros((na, 1))
    ba[:n, 0] = bc[:, 0]
    F, Gm = discretise(fa, ba, dt)
    H = np.zeros((2, na))
    H[0, n - 2] = 1.0
    H[1, n - 1] = 1.0
    sx, sv = settings.position_noise_m, settings.velocity_noise_m_s
    Rn = np.diag([sx * sx, sv * sv])
    wo = 2.0 * math.pi * settings.observer_hz
    q_rate = (M * wo**4 * sx) ** 2 * dt * dt  # variance of d' increments per cycle
    Qn = np.zeros((na, na))
    Qn[n + 1, n + 1] = q_rate
    f_var = settings.force_noise**2 + (1e-6 * M * wo * wo * sx) ** 2
    gb = Gm[:, 0]
    Qn += np.outer(gb, gb) * f_var
    Qn += np.eye(na) * 1e-30
    Pk = solve_discrete_are(F.T, H.T, Qn, Rn)
    Lk = Pk @ H.T @ np.linalg.inv(H @ Pk @ H.T + Rn)
    # cancelling d: the effort du and the state offset dx (the coupling's deflection) per unit of d that
    # hold the table still against it (quasi-static: d is slow); positions of the table and velocities 0
    vel = list(range(1, n, 2))
    free = [j for j in range(0, n - 2, 2)]  # positions of the bodies other than the table
    sysm = np.column_stack([ac[vel][:, free], bc[vel, 0]]) if free else bc[vel]
    sol = np.linalg.solve(sysm, -bd[vel])
    dx = np.zeros(n)
    dx[free] = sol[:-1]
    du = float(sol[-1])
    dxv = np.roll(dx, 1)  # the deflection's rate: dx d' on the velocities
    # u = uff + K (xref + dx d + dxv d' - x) + du d, with d its mean over the cycle the command acts in
    gd = float(K @ dx) * np.array([1.0, 0.0]) + float(K @ dxv) * np.array([0.0, 1.0]) + du * np.array([1.0, 0.5 * dt])
    return Design(A, B, K, F, Gm[:, 0], Lk, H, gd)


class Mbc(Controller):
    """Model-based control of one axis (see the module text). ``model`` is a PlantSpec (its linear part,
    friction and effects); :meth:`for_plant` is how configuration builds it."""

    name = "mbc"
    origin = "model-based (exact inverse + Kalman + LQR)"
    SettingsClass = MbcSettings
    #: the gains come from a design (Riccati equations), not array maths: no batch of gain sets
    batch_settings = False

    def __init__(self, dt: float, settings: Settings | Mapping[str, Any] | None = None, *, model: Any = None,
                 **kwargs: Any):
        if model is None:
            from drivectl.plant_emulator.models import load_plant

            model = load_plant("two-mass")
        try:
            self.model = LinearModel.from_spec(model)
        except (ValueError, AttributeError) as exc:
            raise SettingsError(f"controller mbc: model: {exc}") from None
        self.spec = model
        self._table: tuple[np.ndarray, ...] | None = None
        self._design_for: Any = None
        self._auto: list[str] = []
        super().__init__(dt, settings, **kwargs)

    @classmethod
    def for_plant(cls, dt: float, plant_spec: Any, axis: str = "x", **settings: Any) -> Mbc:
        """Designed from the model ``plant_spec`` (the axis name is not needed: nothing per axis)."""
        return cls(dt, settings, model=plant_spec)

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), "model": getattr(self.spec, "name", "model")}

    # ---------------------------------------------------------------------------------------------
    def _ensure_design(self) -> None:
        s = self.settings
        auto = dict(zip(("bandwidth_hz", "observer_hz"), AUTO_HZ[self.model.n_bodies], strict=True))
        auto = {k: v for k, v in auto.items() if not getattr(s, k)}
        if auto:
            # 0 = from the model: resolved into (a copy of) the settings, so the design, the trace's metadata
            # and tune's starting point all see the number
            s = self.settings = dataclasses.replace(s, **auto)
            self._auto += list(auto)
        key = tuple(s.as_dict().values())
        if self._design_for == key:
            return
        dist_hz = self.model.design.disturbance_frequency if s.disturbance == "auto" else 0.0
        self.d = design(self.model, s, self.dt, dist_hz)
        d = self.d
        n = self.model.n
        na = n + 2
        # predictor form: s(k+1|k) = Mp s(k|k-1) + Np y(k) + G u_net(k-1)
        self._Mp = d.F @ (np.eye(na) - d.L @ d.H)
        self._Np = d.F @ d.L
        self._n = n
        # the cycle as one product: s' = W [s, y_pos, y_vel, u_prev] and u = (uff + K xref) - Kf s', with
        # Kf s' = (Kf W) [s, y_pos, y_vel, u_prev] as the last row (one numpy call a cycle, not two)
        W = np.column_stack([self._Mp, self._Np, d.G])
        self._Kf = np.concatenate([d.K, -d.gd])
        self._WK = np.ascontiguousarray(np.vstack([W, self._Kf @ W]))
        # standstill (docs/standstill.md): only where the model has Coulomb friction, the set-valued force
        # that holds a resting axis; the integral gain acts on the table position error outside the band
        self._hold = bool(s.standstill) and any(b.has_coulomb for b in self.model.design.bodies)
        self._hold_band = float(s.standstill_band_m)
        self._hold_gain = float(d.K[n - 2]) * self.dt / float(s.standstill_s)
        self._design_for = key
        self._rest = (math.nan, 0.0, 0.0)
        self._row_map: tuple[float, float, float, float] | None = None  # made at the first row that needs it

    def reset(self) -> None:
        self._ensure_design()
        na = self._n + 2
        # the cycle's input [s(k|k-1) (plant state, d, d'), y_pos, y_vel, u_prev], twice: each cycle's product
        # goes into the other one (s' and Kf s' in its first na + 1 places), which then becomes the input
        self._bufs = tuple((z, z[:na], z[:na + 1]) for z in (np.zeros(na + 3), np.zeros(na + 3)))
        self._z, self._s, _ = self._bufs[0]  # _s: a view, the estimate lives inside the cycle's input
        self._other = 1
        self._started = False
        self._u_prev = 0.0  # net command sent last cycle (acting now)
        self._fk = 0.0  # the friction compensation in it
        self._k = 0  # cycle index into the prepared table
        self._rest: tuple[float, float, float] = (math.nan, 0.0, 0.0)  # (position, row) of the last hold

    @property
    def spread(self) -> float:
        """The window of the snap spread, s (0: exact inverse)."""
        return self.model.snap_spread(self.dt) if self.settings.snap == "spread" else 0.0

    def feedforward(self, profile: Any, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The feed-forward for a run at ``times``: the linear part's effort and the known forces, row k for
        the command computed at times[k] (acting over the next cycle but one, after the transport delay)."""
        times = np.asarray(times, dtype=float)
        dt = self.dt
        delay = self.model.extra_delay / dt
        n_t = len(times)
        tt = times[0] + dt * (np.arange(n_t + 1) + 1.0 + delay)
        s = self.settings
        if s.feedforward:
            # the reference moves between times[0] and the first instant a command can act (the delay):
            # what the model needed over that span goes into the first command, so nothing is lost
            both = self.model.held_effort(profile, np.concatenate([times[:1], tt]), self.spread)
            uff = both[1:]
            uff[0] += both[0] * (tt[0] - times[0]) / dt
        else:
            uff = np.zeros(n_t)
        fk = self.model.held_known_forces(profile, tt, self.spread) if s.friction_ff else np.zeros(n_t)
        return uff, fk

    def preview(self, profile: Any, times: np.ndarray) -> tuple[list[float], ...] | None:
        """The feed-forward for the whole run ahead, one row per cycle of ``times`` (controllers/base.py:
        ``prepare`` installs it, step k then uses row k). Reads only the design: safe beside ``step``."""
        times = np.asarray(times, dtype=float)
        if len(times) < 2:
            return None
        uff, fk = self.feedforward(profile, times)
        xref = self.model.reference_states(profile, times[0] + self.dt * (np.arange(len(times)) + 1.0),
                                           self.spread)
        # the rows before the first command of the run can act (the transport delay and any delay effect):
        # the plant can only be where the run found it, coasting; a reference state that has moved on
        # would make the feedback push against the feed-forward's own catching up (it did: a 0.5 V spike
        # and its rebound in the first two cycles of seed-000)
        x0 = self.model.reference_states(profile, times[:1], self.spread)[0]
        for k in range(min(int(self.model.extra_delay / self.dt + 1e-9) + 1, len(xref))):
            xref[k] = x0
            xref[k, 0::2] += x0[1::2] * self.dt * (k + 1)
        r = profile.sample(times)[0]
        # the reference state enters the law only as K xref: folded into the feed-forward ahead of time
        ffk = uff + xref @ self.d.K
        return r.tolist(), ffk.tolist(), fk.tolist()

    def use_preview(self, preview: tuple[list[float], ...] | None) -> None:
        self._table = preview
        self._k = 0

    def _row(self, reference: Reference) -> tuple[float, float]:
        """(feed-forward of the linear part plus K times the reference state one cycle ahead, known forces)."""
        k = self._k
        tab = self._table
        if tab is not None and k < len(tab[0]) and abs(reference.position - tab[0][k]) <= 1e-12:
            return tab[1][k], tab[2][k]
        rest = reference.velocity == 0.0 and reference.acceleration == 0.0 and reference.jerk == 0.0
        if rest and reference.position == self._rest[0]:
            return self._rest[1], self._rest[2]  # a hold: the same row every cycle, computed once
        w = self._row_map if self._row_map is not None else self._make_row_map()
        lin = (w[0] * reference.position + w[1] * reference.velocity + w[2] * reference.acceleration
               + w[3] * reference.jerk)
        fk = 0.0
        if self.settings.friction_ff and self.model.has_known_forces:
            fk = float(self.model.held_known_forces(_Extrapolated(reference), self._row_tt, self.spread)[0])
        if rest:
            self._rest = (reference.position, lin, fk)
        return lin, fk

    def _make_row_map(self) -> tuple[float, float, float, float]:
        """The linear part of a row without preview (feed-forward plus K times the reference state), as
        weights on the reference's (position, velocity, acceleration, jerk): the row of a reference
        extrapolated at constant jerk is linear in those four (the model, the spread and the filter of its
        flat output are), so four evaluations at the design replace the polynomial work of every cycle."""
        dt = self.dt
        self._row_tt = dt * (np.array([1.0, 2.0]) + self.model.extra_delay / dt)
        times = np.array([dt, 2 * dt])
        w = []
        for unit in np.eye(4):
            ext = _Extrapolated(Reference(*map(float, unit)))
            uff = float(self.model.held_effort(ext, self._row_tt, self.spread)[0]) if self.settings.feedforward else 0.0
            w.append(uff + float(self.model.reference_states(ext, times, self.spread)[0] @ self.d.K))
        self._row_map = (w[0], w[1], w[2], w[3])
        return self._row_map

    def loop_matrix(self, A: np.ndarray, B: np.ndarray, C: np.ndarray) -> np.ndarray:
        """The closed loop around a linear plant ``x(k+1) = A x(k) + B u(k-1)``, ``y = C x`` (table position
        and velocity), as one matrix on [x, command in flight, estimator state]: stable iff its spectral
        radius is < 1 (controllers/robust.py). Reference and feed-forward are inputs, not in it."""
        d = self.d
        n_p = A.shape[0]
        na = self._n + 2
        kf = np.concatenate([d.K, -d.gd])
        size = n_p + 1 + na
        M = np.zeros((size, size))
        M[:n_p, :n_p] = A
        M[:n_p, n_p] = B[:, 0]
        sx = self._Np @ C  # estimator rows: s' = Np C x + G u_prev + Mp s
        M[n_p + 1:, :n_p] = sx
        M[n_p + 1:, n_p] = d.G
        M[n_p + 1:, n_p + 1:] = self._Mp
        M[n_p, :] = -kf @ M[n_p + 1:, :]  # u = -K x^ + gd d^
        return M

    def linear_form(self) -> Any:
        """State [s(k|k-1), the net command sent last cycle] (before the step), the reference held and the
        standstill not engaged (it engages only at rest on a Coulomb model); see
        :meth:`Controller.linear_form`."""
        from drivectl.controllers.linear_form import basis, from_rows

        na = self._n + 2
        x, pos, vel = basis(na + 1)
        s_next = self._Mp @ x[:na] + np.outer(self._Np[:, 0], pos) + np.outer(self._Np[:, 1], vel) \
            + np.outer(self.d.G, x[na])
        u = -(self._Kf @ s_next)
        return from_rows([*s_next, u], u, self.dt)

    @property
    def disturbance_estimate(self) -> float:
        """The disturbance d the Kalman filter currently estimates (effort unit; see the module text)."""
        return float(self._s[self._n])

    def step(self, reference: Reference, feedback: Feedback) -> float:
        n = self._n
        s = self._s
        if not self._started:
            # start the estimate at the first sample, at rest (the reference state's shape)
            s[:n:2] = feedback.position
            s[1:n:2] = feedback.velocity
            self._started = True
        ffk, fk = self._row(reference)
        if (self._hold and feedback.velocity == 0.0 and reference.velocity == 0.0
                and reference.acceleration == 0.0 and reference.jerk == 0.0):
            return self._stand(reference, feedback, ffk, fk)
        # s(k+1|k) from s(k|k-1), the sample y(k) and the command acting over [k, k+1]
        z = self._z
        na = n + 2
        z[na] = feedback.position
        z[na + 1] = feedback.velocity
        z[na + 2] = self._u_prev
        other = self._other
        z_next, s_next, out = self._bufs[other]
        self._WK.dot(z, out)  # the array's own dot: np.dot's, without its keyword and dispatch layer (~1 us)
        self._z, self._s, self._other = z_next, s_next, 1 - other
        # the command acts over [k+1, k+2]: feedback K (xref - s) on the state predicted at k+1, and the
        # disturbance over that cycle cancelled (gd)
        u_net = ffk - out.item(na)  # a Python float (no numpy scalar in between)
        self._u_prev = u_net
        self._fk = fk
        self._k += 1
        return u_net + fk

    def _stand(self, reference: Reference, feedback: Feedback, ffk: float, fk: float) -> float:
        """A cycle at standstill: the reference rests and the axis sticks (docs/standstill.md). Friction
        then holds whatever net force is below the breakaway, so the filter, which knows no stiction,
        would read the missing motion as a disturbance and wind d up through the stiction band (the
        hunting). Instead the estimate is the measurement at rest, d' is 0 and d changes only by the
        integral action on the error outside the band, slow against the loop."""
        n = self._n
        s = self._s
        s[:n:2] = feedback.position
        s[1:n:2] = 0.0
        s[n + 1] = 0.0
        e = reference.position - feedback.position
        s[n] -= self._hold_gain * outside_band(e, self._hold_band)
        u_net = ffk - float(np.dot(self._Kf, s))
        self._u_prev = u_net
        self._fk = fk
        self._k += 1
        return u_net + fk

    def shift(self, delta: float) -> None:
        """The coordinates moved by ``delta`` (a home offset): the estimate's positions move with them."""
        if self._started:
            self._s[:self._n:2] -= delta

    def skipped(self, cycles: int) -> None:
        """The estimate carried over ``cycles`` cycles without a sample, the last command held (as the drive
        held it): the filter's open-loop prediction, so the next sample is not taken for a disturbance."""
        if not self._started:
            return
        F, G, u = self.d.F, self.d.G, self._u_prev
        s = self._s
        for _ in range(cycles):
            s[:] = F @ s + G * u

    def note_applied(self, effort: Any) -> None:
        """The effort actually sent (a learned feed-forward added to ours): the filter must know the
        command in flight, or it takes the addition for a disturbance and cancels it."""
        self._u_prev = float(effort) - self._fk

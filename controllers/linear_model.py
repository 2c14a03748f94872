"""The model a model-based controller believes, in the forms its design needs.

From a :class:`~drivectl.plant_emulator.models.PlantSpec` (base model + effects) this builds:

* the linear part: bodies, viscous friction (the mean of the two directions), the coupling spring and
  damper (engaged), a spring to ground on the table; continuous ``(Ac, Bc)`` with the effort on body 0,
  and the exact zero-order-hold discretisation for the cycle (as ``plant_emulator.models`` steps it);
* the exact inverse of the linear part (flatness): with the table position ``x_t = Q(s) Z``, the
  driven body ``x_0 = P_t(s) Z`` and the effort ``u = Delta(s) Z`` (``Delta = P_0 P_t - Q^2`` for two
  bodies, ``P_0`` for one), a reference ``r(t)`` gives the flat output ``z = r / Q`` and from it every
  state and the effort at any instant (:meth:`LinearModel.reference_states`);
* held by the drive: the effort computed at sample k acts, after the one-cycle transport delay of cyclic
  synchronous torque (plus any ``delay`` effect), constant over one cycle. The feed-forward for that
  cycle is the mean of the exact continuous effort over it, ``(1/dt) [Delta(s)/s Z]`` between its ends:
  it gives every body exactly the momentum the reference needs in each cycle, needs the reference only
  up to its jerk (a ruckig profile's jerk is piecewise constant; its snap, impulses at the switches,
  would make a continuous inverse impulsive), and is smooth (no sampling-zero ringing, which an exact
  sample-by-sample inverse of a ZOH plant has: its zero near -1 alternates the effort). What remains
  is the intersample difference of a held effort, O(dt^2) in position (tests/test_mbc.py measures it);
* the snap spread (two bodies): the inverse needs the reference's snap, an impulse of ``Delta_4 dj`` at
  every switch of a jerk-limited reference's jerk; held over one cycle it is a one-cycle pulse of
  ``Delta_4 dj / dt`` (0.2 V at 40 m/s^3 on two-mass), four times the effort's own step per cycle in a
  jerk phase (``Delta_2 dj dt``), and it made most of the effort's roughness. With ``spread`` T it is
  spread over a centred window T (the jerk that drives the snap term is averaged over T), which keeps
  the impulse's momentum and its first moment, so the table is back on the reference after the window
  but for a little ringing of the mode (the spread pulse's spectrum at the mode is below the impulse's:
  13 % on two-mass); open loop on seed-000 the table moves at most 0.14 um off where the exact inverse
  puts it (tests/test_mbc.py), closed loop the state feedback damps the ringing.
  :meth:`LinearModel.snap_spread` is the T at which the spread pulse's step per cycle is no larger than
  the jerk's own: ``Delta_4 / (Delta_2 dt)`` = ``1 / (w_m^2 dt)`` for the coupling mode w_m (3.2 ms on
  two-mass at 1 kHz);
* the forces outside the linear part that the model knows (direction-dependent Coulomb and viscous
  friction, Stribeck, periodic, offset): evaluated on the reference states and added to the
  feed-forward (:meth:`LinearModel.known_forces`). On the driven body they are cancelled exactly; on
  the table of a two-mass model quasi-statically (the force passes the stiff coupling unchanged below
  the mode).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.polynomial import polynomial as P
from scipy.linalg import expm

#: sub-samples per cycle of the first-order filter 1/Q(s) on the jerk and of the friction averages
SUBSAMPLES = 8


def discretise(ac: np.ndarray, bc: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact zero-order-hold discretisation (one expm of the augmented matrix)."""
    n, m = bc.shape
    aug = np.zeros((n + m, n + m))
    aug[:n, :n] = ac
    aug[:n, n:] = bc
    e = expm(aug * dt)
    return e[:n, :n], e[:n, n:]


def _first_order(x: np.ndarray, alpha: float, y0: float) -> np.ndarray:
    """y[i] = alpha y[i-1] + (1 - alpha) x[i], y[-1] = y0. Its memory is short next to the run (alpha^J below
    1e-16 after J taps; 37 on two-mass): a truncated convolution, exact to rounding; a loop otherwise."""
    taps = int(math.ceil(math.log(1e-16) / math.log(alpha))) if 0.0 < alpha < 1.0 else 0
    if 0 < taps <= 4096:
        kernel = (1.0 - alpha) * alpha ** np.arange(taps)
        y = np.convolve(x, kernel)[: len(x)]
        y += y0 * alpha ** np.arange(1, len(x) + 1)
        return y
    y = np.empty(len(x))
    acc = y0
    for i, xi in enumerate(x.tolist()):
        acc = alpha * acc + (1.0 - alpha) * xi
        y[i] = acc
    return y


@dataclass
class LinearModel:
    """The linear part of a plant design and the forces it knows outside it."""

    masses: tuple[float, ...]
    viscous: tuple[float, ...]  # mean of c_pos, c_neg per body
    stiffness: float  # coupling (two bodies), 0 for one
    damping: float
    table_stiffness: float
    design: Any  # the plant_emulator Design (friction, periodic, offset, delay)
    effort_unit: str

    @classmethod
    def from_spec(cls, spec: Any) -> LinearModel:
        design = spec.design()
        bodies = design.bodies
        if len(bodies) not in (1, 2):
            raise ValueError(f"model {spec.name}: {len(bodies)} bodies; the model-based design takes one or two")
        cpl = design.coupling
        return cls(
            masses=tuple(b.mass for b in bodies),
            viscous=tuple(0.5 * (b.c_pos + b.c_neg) for b in bodies),
            stiffness=cpl.stiffness if cpl else 0.0,
            damping=cpl.damping if cpl else 0.0,
            table_stiffness=design.table_stiffness,
            design=design,
            effort_unit=design.effort_unit,
        )

    @property
    def n_bodies(self) -> int:
        return len(self.masses)

    @property
    def n(self) -> int:
        return 2 * self.n_bodies

    @property
    def total_mass(self) -> float:
        return sum(self.masses)

    @property
    def extra_delay(self) -> float:
        """Delay of the effort beyond the transport delay (a ``delay`` effect), s."""
        return float(self.design.input_delay)

    # -- state space -----------------------------------------------------------------------------
    def continuous(self) -> tuple[np.ndarray, np.ndarray]:
        """``(Ac, Bc)``: state [x0, v0(, x1, v1)], effort on body 0."""
        nb = self.n_bodies
        ac = np.zeros((2 * nb, 2 * nb))
        bc = np.zeros((2 * nb, 1))
        for i, (m, c) in enumerate(zip(self.masses, self.viscous, strict=True)):
            ac[2 * i, 2 * i + 1] = 1.0
            ac[2 * i + 1, 2 * i + 1] = -c / m
        bc[1, 0] = 1.0 / self.masses[0]
        t = nb - 1
        ac[2 * t + 1, 2 * t] -= self.table_stiffness / self.masses[t]
        if nb == 2:
            from drivectl.plant_emulator.models import add_coupling

            add_coupling(ac, self.stiffness, self.damping, *self.masses)
        return ac, bc

    def discrete(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        return discretise(*self.continuous(), dt)

    # -- flatness ----------------------------------------------------------------------------------
    def polynomials(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(Q, P_t, Delta) as coefficient arrays, lowest power first: x_t = Q Z, x_0 = P_t Z, u = Delta Z.
        Kept per parameter set: a controller's cycle asks for them, and they change only with the model."""
        key = (self.masses, self.viscous, self.stiffness, self.damping, self.table_stiffness)
        kept = self.__dict__.get("_polynomials")
        if kept is None or kept[0] != key:
            kept = (key, self._polynomials_of_model())
            self.__dict__["_polynomials"] = kept
        return kept[1]

    def _polynomials_of_model(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        kt = self.table_stiffness
        if self.n_bodies == 1:
            m, c = self.masses[0], self.viscous[0]
            return np.array([1.0]), np.array([1.0]), np.array([kt, c, m])
        m0, m1 = self.masses
        b0, b1 = self.viscous
        k, n = self.stiffness, self.damping
        q = np.array([k, n])
        p0 = np.array([k, b0 + n, m0])
        pt = np.array([k + kt, b1 + n, m1])
        delta = P.polysub(P.polymul(p0, pt), P.polymul(q, q))
        return q, pt, delta

    def snap_spread(self, dt: float) -> float:
        """The window over which the snap impulse is spread (module text): ``Delta_4 / (Delta_2 dt)``, s;
        0 for one body (its inverse needs no snap)."""
        if self.n_bodies == 1:
            return 0.0
        delta = self.polynomials()[2]
        return float(delta[4] / (delta[2] * dt))

    def _flat(self, profile: Any, times: np.ndarray, spread: float = 0.0) -> list[np.ndarray]:
        """z, z', z'', z''' at ``times`` (z = r / Q(s)); ``spread``: the window of the snap spread, s.

        One body: z = r. Two bodies: Q = k (1 + tau s), tau = n / k (0.13 ms on two-mass): z and its
        first two derivatives by the series in tau up to the jerk (the next term is tau^4 snap, below
        1e-15 m), z''' = jerk through the first-order filter, stepped exactly over sub-samples of each
        cycle (the jerk is piecewise constant, so this is exact but for a switch inside a sub-sample).
        With a spread, the jerk entering that filter is its centred average over the window; the filter
        starts from the jerk before times[0] as it is (what the run's first commands must catch up with).
        """
        r, v, a, j = profile.sample(times)
        if self.n_bodies == 1:
            return [r, v, a, j]
        k, n = self.stiffness, self.damping
        tau = n / k
        z = (r - tau * v + tau**2 * a - tau**3 * j) / k
        z1 = (v - tau * a + tau**2 * j) / k
        z2 = (a - tau * j) / k
        if tau <= 0.0:
            return [z, z1, z2, j / k]
        dt = float(times[1] - times[0]) if len(times) > 1 else 1.0
        h = dt / SUBSAMPLES
        fine = times[0] + h * np.arange((len(times) - 1) * SUBSAMPLES + 1)
        # jerk held over each sub-sample at its midpoint value (piecewise constant: exact inside segments)
        pad = int(round(0.5 * spread / h))  # sub-samples each side of the centred window
        jm = profile.sample(times[0] + h * (np.arange(-pad, len(fine) - 1 + pad) + 0.5))[3]
        if pad:
            jm = np.convolve(jm, np.full(2 * pad + 1, 1.0 / (2 * pad + 1)), "valid")
        # the filter's state at times[0]: the jerk just before (a profile holds before its start)
        jf0 = float(profile.sample(times[:1] - 0.5 * h)[3][0])
        filt = _first_order(jm, math.exp(-h / tau), jf0)
        jf = np.empty(len(times))
        jf[0] = jf0
        jf[1:] = filt[SUBSAMPLES - 1 :: SUBSAMPLES]
        return [z, z1, z2, jf / k]

    def reference_states(self, profile: Any, times: np.ndarray, spread: float = 0.0) -> np.ndarray:
        """The model's state at ``times`` when its table follows the profile exactly (with the snap spread
        over ``spread`` s: the driven body's velocity as the spread effort moves it): shape (len, n)."""
        z = self._flat(profile, times, spread)
        if self.n_bodies == 1:
            return np.stack([z[0], z[1]], axis=1)
        _, pt, _ = self.polynomials()
        x0 = pt[0] * z[0] + pt[1] * z[1] + pt[2] * z[2]
        v0 = pt[0] * z[1] + pt[1] * z[2] + pt[2] * z[3]
        r, v = profile.sample(times)[:2]
        return np.stack([x0, v0, r, v], axis=1)

    def held_effort(self, profile: Any, times: np.ndarray, spread: float = 0.0) -> np.ndarray:
        """The linear part's effort held over [t_i, t_i+1] for each consecutive pair of ``times``: the mean
        of the exact continuous effort, the snap spread over ``spread`` s (see the module text). Length
        len(times) - 1."""
        z = self._flat(profile, times, spread)
        _, _, delta = self.polynomials()
        dt = np.diff(times)
        # antiderivative of Delta(s) Z without its constant term: sum_i delta_i z^(i-1)
        prim = np.zeros(len(times))
        for i in range(1, len(delta)):
            prim += delta[i] * z[i - 1]
        out = np.diff(prim) / dt
        if delta[0]:
            # int z over the cycle, exact for a cubic: dt (z_a + z_b) / 2 - dt^2 (z'_b - z'_a) / 12
            iz = dt * 0.5 * (z[0][:-1] + z[0][1:]) - dt**2 * (z[1][1:] - z[1][:-1]) / 12.0
            out += delta[0] * iz / dt
        return out

    # -- forces outside the linear part ------------------------------------------------------------
    @property
    def has_known_forces(self) -> bool:
        d = self.design
        asym = any(b.c_pos != b.c_neg for b in d.bodies)
        return asym or any(b.has_coulomb for b in d.bodies) or bool(d.periodic) or d.table_offset != 0.0

    def known_forces(self, states: np.ndarray) -> np.ndarray:
        """The force the effort must add to cancel what the model knows outside its linear part, at the
        given model states (rows): friction of each body beyond the mean viscous term (Coulomb by
        direction, Stribeck, the direction-dependent viscous part), periodic and constant table forces."""
        d = self.design
        out = np.zeros(len(states))
        for i, b in enumerate(d.bodies):
            v = states[:, 2 * i + 1]
            sgn = np.sign(v)
            pos = v > 0.0
            c_lin = 0.5 * (b.c_pos + b.c_neg)
            out += np.where(pos, b.c_pos - c_lin, b.c_neg - c_lin) * v
            out += sgn * np.where(pos, b.fc_pos, b.fc_neg)
            if b.stribeck_excess:
                out += sgn * b.stribeck_excess * np.exp(-((v / b.stribeck_velocity) ** 2))
        x_t = states[:, -2]
        for amp, period, phase in d.periodic:
            out -= amp * np.sin(2 * math.pi * x_t / period + phase)
        out -= d.table_offset
        return out

    def held_known_forces(self, profile: Any, times: np.ndarray, spread: float = 0.0) -> np.ndarray:
        """:meth:`known_forces` averaged over each cycle [t_i, t_i+1] (sub-sampled: a reversal inside a
        cycle gets the share of each direction). Length len(times) - 1."""
        if not self.has_known_forces:
            return np.zeros(len(times) - 1)
        dt = float(times[1] - times[0])
        subs = 4
        fine = times[:-1, None] + dt * (np.arange(subs) + 0.5)[None, :] / subs
        f = self.known_forces(self.reference_states(profile, fine.ravel(), spread))
        return f.reshape(-1, subs).mean(axis=1)

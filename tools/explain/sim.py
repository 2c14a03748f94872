"""Windowed open-loop simulation for `drivectl explain`, vectorised over windows and candidate plants.

The gap of `explain` restarts the plant from the measured state every ~150 ms and drives it with the
recorded effort (transport rule: the effort on row k acts from t(k+1) to t(k+2)). Fitting an effect
means evaluating that gap for many candidate parameter sets, so this module steps *all windows and all
candidates at once* with numpy: flat arrays over (window, candidate), one Python iteration per substep.

Exactness: the candidates are real :class:`~drivectl.plant_emulator.models.Plant` objects (built
from ``PlantSpec.with_effect``), and this module reads their compiled matrices (exact ZOH
discretisation per direction of motion and contact state), friction levels, delay split, limit and
table forces, and repeats ``Plant._step_one`` / ``Plant._step_two`` operation for operation (Moreau
Coulomb friction, substep-midpoint table forces, per-substep delay weights). With the plant's own
substep count the result equals ``Plant.step`` to rounding (tests/test_explain_sim.py checks it); fewer
substeps are used only for the coarse search of a fit, never for the reported gaps.

Speed (issue 17 point 6; bench/explain_speed.py): a one-body plant whose input is constant over a cycle
(no Stribeck, periodic, time disturbance or delay) takes a whole cycle in closed form wherever the body
keeps moving one way (friction is then a constant force: s -> P_n s + Q_n u, the substep map composed)
or stays stuck, and runs the substeps only for the few (window, candidate) pairs that stop, start or
reverse within that cycle: the same numbers to ~1e-14 m, 2-8x faster at 10 substeps. A linearly coupled
two-body plant (a resonance; friction on the table only) does the same, its table velocity checked on
every substep since the mode rings (equal to ~1e-12 m). Everything else
runs the substeps, operation for operation as Plant.step orders them, with the selections a batch does not need
(direction-independent friction, a00 = 1 and a10 = 0 without a spring) left out.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from drivectl.plant_emulator.models import Plant


@dataclass
class Windows:
    """Where the windows start and what drives them (all arrays indexed by window)."""

    start: np.ndarray  # (W,) row of the initial state
    length: int  # steps per window
    q0: np.ndarray  # (W,) measured position at the start
    v0: np.ndarray  # (W,) estimated velocity at the start
    t0: np.ndarray  # (W,) time at the start (plant time, for time-dependent disturbances)
    applied: np.ndarray  # (W, H + L) effort acting in each step (transport rule), H rows of history first
    history: int  # H
    measured: np.ndarray  # (W, L) measured position after each step (rows start+1 .. start+L)
    initial_force: np.ndarray  # (W,) effort acting in the first step (for the two-body initial state)
    side_force: np.ndarray  # (W,) the last clearly non-zero effort up to the start (which side a lash rests on; 0 none)


def make_windows(pos: np.ndarray, vel: np.ndarray, effort: np.ndarray, dt: float, length: int,
                 history: int = 16, starts: np.ndarray | None = None, side_threshold: float = 0.0,
                 transport: int = 1) -> Windows:
    """Non-overlapping windows of ``length`` steps covering the trace (or the given ``starts``).

    ``side_threshold``: an effort at least this large decides on which side of a dead zone the screw
    rests; below it (a dwell holding ~0) the screw stays where the last such effort pushed it.
    ``transport``: cycles between the row an effort is logged on and the cycle it acts in (1 in
    CiA 402 cyclic synchronous torque; 0 on a rig that applies it in the cycle it computes it).
    """
    n = len(pos)
    if starts is None:
        starts = np.arange(0, n - length, length)
    starts = np.asarray(starts, dtype=int)
    # transport rule: the effort on row k acts from t(k+d) to t(k+d+1), i.e. step j (t(j) -> t(j+1))
    # is driven by effort[j - d]; before the first row nothing acted
    applied_rows = (np.asarray(effort, dtype=float) if transport == 0
                    else np.concatenate((np.zeros(transport), effort[:-transport])))
    padded = np.concatenate((np.zeros(history), applied_rows))
    idx = starts[:, None] + np.arange(-history, length)[None, :] + history
    applied = padded[idx]
    meas = pos[starts[:, None] + np.arange(1, length + 1)[None, :]]
    big = np.abs(applied_rows) > side_threshold
    last = np.maximum.accumulate(np.where(big, np.arange(n), 0))
    # 0 where no effort has decided the side yet (the trace's start): the screw rests where power-up left it
    side = np.where(big[last], applied_rows[last], 0.0)[starts]
    return Windows(starts, length, pos[starts].copy(), vel[starts].copy(), starts * dt, applied, history, meas,
                   applied_rows[starts].copy(), side)


#: whole cycles in closed form (BatchSim._cycle_one, _cycle_two) from this many substeps per cycle on: measured
#: on a 10 s trace and the EMPS record, with 2 substeps the per-cycle bookkeeping costs about what it saves,
#: with 10 it is 2-8x faster (one body) and 1.2-2.7x (two, where the mode makes the table stop more often)
CYCLE_MIN_SUBSTEPS = 4


class BatchSim:
    """C candidate plants (same body count) stepped over W windows at once."""

    def __init__(self, plants: Sequence[Plant], substeps: int | None = None):
        if not plants:
            raise ValueError("BatchSim: no plants")
        self.plants = list(plants)
        p0 = self.plants[0]
        self.dt = p0.dt
        self.nb = p0.n_bodies
        self.two = self.nb == 2 or bool(p0.gap)
        if any((p.n_bodies == 2 or bool(p.gap)) != self.two for p in self.plants):
            raise ValueError("BatchSim: candidates must share the body count")
        self.substeps = int(substeps or max(p.substeps for p in self.plants))
        C = len(self.plants)
        ns = 2 * self.nb
        # rebuild each candidate at the common substep (same design, so the same physics)
        compiled = [p if p.substeps == self.substeps else Plant(p.design, p.dt, self.substeps, p.name)
                    for p in self.plants]
        self.h = self.dt / self.substeps
        # matrices per combination of (engaged, dir0, dir1); a plant without asymmetry or gap
        # has only some of them, which stand in for the rest (as Plant.step looks them up)
        K = 8
        self.A = np.zeros((C, K, ns, ns))
        self.B = np.zeros((C, K, ns, self.nb))
        for c, p in enumerate(compiled):
            for e in (0, 1):
                for d0 in (0, 1):
                    for d1 in (0, 1):
                        A, B = p.substep_matrices(bool(e), 1 - 2 * d0, 1 - 2 * d1)
                        k = e * 4 + d0 * 2 + d1
                        self.A[c, k] = np.asarray(A)
                        self.B[c, k] = np.asarray(B)
        d = [p.design for p in compiled]
        self.fc_pos = np.array([[b.fc_pos for b in x.bodies] for x in d])  # (C, nb)
        self.fc_neg = np.array([[b.fc_neg for b in x.bodies] for x in d])
        self.st_exc = np.array([[b.stribeck_excess for b in x.bodies] for x in d])
        self.st_vel = np.array([[b.stribeck_velocity for b in x.bodies] for x in d])
        self.coulomb = np.array([[b.has_coulomb for b in x.bodies] for x in d]).any(axis=0)  # per body
        self.offset = np.array([x.table_offset for x in d])
        per = [x.periodic[0] if x.periodic else (0.0, 1.0, 0.0) for x in d]
        if any(len(x.periodic) > 1 for x in d):
            raise ValueError("BatchSim: at most one periodic term")
        self.per_amp = np.array([p[0] for p in per])
        self.per_k = np.array([2 * math.pi / p[1] for p in per])
        self.per_phase = np.array([p[2] for p in per])
        self.has_periodic = bool(np.any(self.per_amp != 0))
        self.has_offset = bool(np.any(self.offset != 0))
        self.dist_a = np.array([x.disturbance_amplitude for x in d])
        self.dist_w = np.array([2 * math.pi * x.disturbance_frequency for x in d])
        self.has_dist = bool(np.any(self.dist_a != 0))
        self.limit = np.array([x.input_limit for x in d])
        self.delay_cycles = np.array([p.delay[0] if p.delay else 0 for p in compiled])
        self.delay_frac = np.array([p.delay[1] if p.delay else 0.0 for p in compiled])
        self.delayed = any(p.delay for p in compiled)
        self.gap = np.array([p.gap for p in compiled])
        self.stiff = np.array([x.coupling.stiffness if x.coupling else 0.0 for x in d])
        self.masses = np.array([[b.mass for b in x.bodies] for x in d])
        self.damp = np.array([x.coupling.damping if x.coupling else 0.0 for x in d])
        self.c_pos = np.array([[b.c_pos for b in x.bodies] for x in d])
        self.c_neg = np.array([[b.c_neg for b in x.bodies] for x in d])
        self.cycle_ok = False
        if self.two:
            self._two_body_tables()
        else:
            self._one_body_tables()

    # ---------------------------------------------------------------------------------------------
    def _initial(self, win: Windows) -> list[np.ndarray]:
        """Start state per (window, candidate): the measured position and velocity.

        Two bodies start moving together (no relative velocity) with the coupling loaded as it is
        in quasi-static motion under the effort acting then: spring extension
        (m1 (f - F0) + m0 F1) / (k M) from equal accelerations (F0, F1 the bodies' friction at v0),
        and with backlash the screw on the side of the dead zone that the effort pushes it to.
        """
        W, C = len(win.start), len(self.plants)
        q = np.broadcast_to(win.q0[:, None], (W, C)).copy()
        v = np.broadcast_to(win.v0[:, None], (W, C)).copy()
        if not self.two:
            return [q, v]
        f = win.initial_force[:, None]
        m0, m1 = self.masses[:, 0][None, :], self.masses[:, 1][None, :]
        pos = v > 0
        F = []
        for b in (0, 1):
            c = np.where(pos, self.c_pos[:, b][None, :], self.c_neg[:, b][None, :])
            fc = np.where(pos, self.fc_pos[:, b][None, :], -self.fc_neg[:, b][None, :])
            F.append(np.where(v == 0, 0.0, c * v + fc))
        k = np.maximum(self.stiff[None, :], 1e-9)
        ext = (m1 * (f - F[0]) + m0 * F[1]) / (k * (m0 + m1))
        half = 0.5 * self.gap[None, :]
        # against the side the screw rests on; an effort below the threshold pulling the other way
        # only relaxes the contact (|ext| is small then), it does not cross the dead zone. Before any
        # effort decided a side (the trace's first window) the screw sits in the middle, relaxed: the
        # plant's own rest state, and the guess that is off by at most half the width either way
        side = np.sign(win.side_force[:, None])
        rel = ext + side * half
        # body 0 (screw or motor side) leads the table by rel
        return [q + rel, v.copy(), q, v]

    def run(self, win: Windows, internal: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """Simulated table position after each step: (W, C, L).

        ``internal`` = (relative position, relative velocity) of body 0 against the table at each
        window start, (W, C), for two-body plants whose internal state was reconstructed from the
        data before the window (see :func:`internal_state`); default: quasi-static.
        """
        if self.two:
            return self._run_two(win, internal)
        return self._run_one(win)[0]

    def run_with_velocity(self, win: Windows) -> tuple[np.ndarray, np.ndarray]:
        """Simulated table position and velocity after each step: two (W, C, L)."""
        if self.two:
            return self._run_two(win, None, with_velocity=True)
        return self._run_one(win)

    # ---------------------------------------------------------------------------------------------
    # One body: whole cycles in closed form where nothing switches, substeps only where something does
    # ---------------------------------------------------------------------------------------------

    def _one_body_tables(self) -> None:
        """Per-candidate coefficients of the one-body step, (C,) arrays, and (where a whole cycle can be
        taken at once) the cycle's propagation: P_i = A^i and Q_i = (I + A + ... + A^(i-1)) B for
        i = 1..n substeps, per direction of motion (the plant's own A, B composed, no new physics)."""
        A, B = self.A, self.B
        t: dict[str, np.ndarray] = {}
        for tag, k in (("p", 0), ("n", 2)):
            t["a00" + tag], t["a01" + tag] = A[:, k, 0, 0], A[:, k, 0, 1]
            t["a10" + tag], t["a11" + tag] = A[:, k, 1, 0], A[:, k, 1, 1]
            t["b0" + tag], t["b1" + tag] = B[:, k, 0, 0], B[:, k, 1, 0]
        t["fcp"], t["fcn"] = self.fc_pos[:, 0], self.fc_neg[:, 0]
        # for the substeps' Moreau step: the impulse that holds a body, b1 fc, and the one a sliding body
        # takes moving up (with direction-dependent B these depend on the direction too: left to the step)
        t["nfcp"], t["g1p"], t["g1n"] = -t["fcp"], t["b1p"] * t["fcp"], t["b1p"] * t["fcn"]
        t["exc"], t["stv"] = self.st_exc[:, 0], self.st_vel[:, 0]
        t["off"], t["lim"], t["nlim"] = self.offset, self.limit, -self.limit
        t["pa"], t["pk"], t["pp"] = self.per_amp, self.per_k, self.per_phase
        t["da"], t["dw"] = self.dist_a, self.dist_w
        t["dc"], t["df"] = self.delay_cycles, self.delay_frac
        self._t1 = t
        self._rigid = bool(np.all(A[:, [0, 2], 0, 0] == 1.0) and np.all(A[:, [0, 2], 1, 0] == 0.0))
        self._symmetric = bool(np.array_equal(A[:, 0], A[:, 2]) and np.array_equal(B[:, 0], B[:, 2]))
        self._stribeck = bool(np.any(self.st_exc[:, 0] != 0))
        # whole cycles need an input that is constant over the cycle and friction that is a constant force
        # ... and enough substeps to be worth it: with 2 the per-cycle bookkeeping costs what it saves
        self.cycle_ok = self.substeps >= CYCLE_MIN_SUBSTEPS and not (
            self._stribeck or self.has_periodic or self.has_dist or self.delayed)
        if not self.cycle_ok:
            return
        n = self.substeps
        C = len(self.plants)
        self._spring = not self._rigid
        for tag, k in (("p", 0), ("n", 2)):
            P = np.empty((C, n + 1, 2, 2))
            Q = np.empty((C, n + 1, 2))
            P[:, 0] = np.eye(2)
            Q[:, 0] = 0.0
            for i in range(1, n + 1):
                P[:, i] = A[:, k] @ P[:, i - 1]
                Q[:, i] = np.einsum("cij,cj->ci", A[:, k], Q[:, i - 1]) + B[:, k, :, 0]
            t["P" + tag], t["Q" + tag] = P, Q
            if self._spring:
                # sticking with a spring: x -> alpha x per substep (the holding force cancels the rest)
                alpha = t["a00" + tag] - t["b0" + tag] * t["a10" + tag] / t["b1" + tag]
                t["al" + tag] = alpha
                t["aln" + tag] = alpha ** n
                t["aln1" + tag] = alpha ** (n - 1)

    def _run_one(self, win: Windows) -> tuple[np.ndarray, np.ndarray]:
        W, C, L = len(win.start), len(self.plants), win.length
        x, v = self._initial(win)
        out = np.empty((W, C, L))
        out_v = np.empty((W, C, L))
        if not self.cycle_ok:
            # substeps for every window and candidate (flat arrays; the coefficients gathered once)
            cidx = np.tile(np.arange(C), W)
            widx = np.repeat(np.arange(W), C)
            co = self._gather(cidx)
            xf, vf = x.reshape(-1), v.reshape(-1)
            for j in range(L):
                xf, vf = self._substeps_one(win, j, xf, vf, widx, co)
                out[:, :, j] = xf.reshape(W, C)
                out_v[:, :, j] = vf.reshape(W, C)
            return out, out_v
        for j in range(L):
            x, v = self._cycle_one(win, j, x, v)
            out[:, :, j] = x
            out_v[:, :, j] = v
        return out, out_v

    def _gather(self, cidx: np.ndarray) -> dict[str, np.ndarray]:
        """The per-candidate coefficients of the substep kernel for flat elements of candidates ``cidx``."""
        keys = ["lim", "nlim", "a00p", "a01p", "a10p", "a11p", "b0p", "b1p",
                "a00n", "a01n", "a10n", "a11n", "b0n", "b1n"]
        keys += ["fcp", "fcn", "nfcp", "g1p", "g1n"] if self.coulomb[0] else []
        keys += ["exc", "stv"] if self._stribeck else []
        keys += ["off"] if self.has_offset or self.has_periodic else []
        keys += ["pa", "pk", "pp"] if self.has_periodic else []
        keys += ["da", "dw"] if self.has_dist else []
        keys += ["dc", "df"] if self.delayed else []
        return {k: self._t1[k][cidx] for k in keys}

    #: velocity (m/s) a whole cycle must keep away from 0 to be taken in closed form (a stop or a reversal
    #: inside the cycle is left to the substeps; far above the 1e-15 below which a substep zeroes it)
    CYCLE_V_MARGIN = 1e-12

    def _cycle_one(self, win: Windows, j: int, x: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Step j for every (window, candidate): in closed form where the body keeps moving one way (the
        Coulomb force is then a constant force against it) or stays stuck all cycle; by substeps elsewhere.

        Equal to the substeps to rounding: a moving body's substep is the affine map s -> A s + B (f - D fc)
        as long as its velocity keeps the sign D (checked on every substep's velocity, or on the two ends
        where the velocity is monotone: no spring); a stuck body stays stuck while the applied force stays
        within the friction level."""
        t = self._t1
        n = self.substeps
        H = win.history
        f = np.minimum(np.maximum(win.applied[:, H + j][:, None], t["nlim"][None, :]), t["lim"][None, :])
        if self.has_offset:
            f = f + t["off"][None, :]
        pos = v > 0.0
        coul = bool(self.coulomb[0])
        Pp, Pn, Qp, Qn = t["Pp"], t["Pn"], t["Qp"], t["Qn"]
        if coul:
            u = np.where(pos, f - t["fcp"][None, :], f + t["fcn"][None, :])
        else:
            u = f

        def sel(ap: np.ndarray, an: np.ndarray) -> np.ndarray:
            return ap if self._symmetric else np.where(pos, ap, an)

        p00 = sel(Pp[None, :, n, 0, 0], Pn[None, :, n, 0, 0])
        p01 = sel(Pp[None, :, n, 0, 1], Pn[None, :, n, 0, 1])
        p11 = sel(Pp[None, :, n, 1, 1], Pn[None, :, n, 1, 1])
        q0 = sel(Qp[None, :, n, 0], Qn[None, :, n, 0])
        q1 = sel(Qp[None, :, n, 1], Qn[None, :, n, 1])
        if self._spring:
            p10 = sel(Pp[None, :, n, 1, 0], Pn[None, :, n, 1, 0])
            xn = p00 * x + p01 * v + q0 * u
            vn = p10 * x + p11 * v + q1 * u
        else:
            xn = x + p01 * v + q0 * u
            vn = p11 * v + q1 * u
        sgn = np.where(pos, 1.0, -1.0)
        eps = self.CYCLE_V_MARGIN
        moving = (sgn * v > eps) & (sgn * vn > eps)
        if self._spring and n > 1:
            # the velocity of a spring-mass need not be monotone over the cycle: every substep's
            pos3 = pos[..., None]
            vi = (np.where(pos3, Pp[None, :, 1:n, 1, 0], Pn[None, :, 1:n, 1, 0]) * x[..., None]
                  + np.where(pos3, Pp[None, :, 1:n, 1, 1], Pn[None, :, 1:n, 1, 1]) * v[..., None]
                  + np.where(pos3, Qp[None, :, 1:n, 1], Qn[None, :, 1:n, 1]) * u[..., None])
            moving &= np.all(sgn[..., None] * vi > eps, axis=-1)
        x_new = np.where(moving, xn, x)
        v_new = np.where(moving, vn, 0.0)
        rest = v == 0.0
        if coul:
            fpos = f >= 0.0
            level = np.where(fpos, t["fcp"][None, :], t["fcn"][None, :])
            if self._spring:
                # stuck all cycle: the free velocity a10 x + b1 f within b1 fc at the first and the last
                # substep's start (x -> alpha x moves it monotonically between them)
                a10 = np.where(fpos, t["a10p"][None, :], t["a10n"][None, :])
                b1 = np.where(fpos, t["b1p"][None, :], t["b1n"][None, :])
                al1 = np.where(fpos, t["aln1p"][None, :], t["aln1n"][None, :])
                aln = np.where(fpos, t["alnp"][None, :], t["alnn"][None, :])
                fcp, fcn = b1 * t["fcp"][None, :], b1 * t["fcn"][None, :]
                vf0 = a10 * x + b1 * f
                vf1 = a10 * (al1 * x) + b1 * f
                held = ((vf0 <= fcp) & (vf0 >= -fcn) & (vf1 <= fcp) & (vf1 >= -fcn))
                stuck = rest & held
                x_new = np.where(stuck, aln * x, x_new)
            else:
                stuck = rest & (np.abs(f) <= level)
        else:
            stuck = np.zeros_like(rest)
        odd = np.flatnonzero(~(moving | stuck))
        if len(odd):
            C = len(self.plants)
            w, c = np.divmod(odd, C)
            xs, vs = self._substeps_one(win, j, x.reshape(-1)[odd], v.reshape(-1)[odd], w, self._gather(c))
            x_new.reshape(-1)[odd] = xs
            v_new.reshape(-1)[odd] = vs
        return x_new, v_new

    def _substeps_one(self, win: Windows, j: int, x: np.ndarray, v: np.ndarray, w: np.ndarray,
                      co: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Step j by the plant's substeps for flat elements (windows ``w``, coefficients ``co`` gathered for
        their candidates): Plant._step_one operation for operation. What does not change within the cycle
        (the force without a periodic, time or delayed part, its products with B) is computed once, and
        products of two coefficients once per gather: the same numbers, fewer passes over the arrays."""
        H = win.history
        h = self.h
        lim = co["lim"]
        const_f = not (self.delayed or self.has_periodic or self.has_dist)
        if self.delayed:
            dc = co["dc"]
            cur = win.applied[w, H + j - dc]
            prev = win.applied[w, H + j - dc - 1]
        else:
            f_in = np.minimum(np.maximum(win.applied[w, H + j], co["nlim"]), lim)  # np.clip's numbers, cheaper
            if self.has_offset and const_f:
                f_in = f_in + co["off"]
        coul = bool(self.coulomb[0])
        forces = self.has_offset or self.has_periodic
        rigid = self._rigid
        sym = self._symmetric
        if sym:
            a00, a01, a10, a11, b0, b1 = co["a00p"], co["a01p"], co["a10p"], co["a11p"], co["b0p"], co["b1p"]
        if const_f:
            f = f_in
            fpos = f >= 0.0
            if sym:
                b0f, b1f = b0 * f, b1 * f
        for i in range(self.substeps):
            if not const_f:
                if self.delayed:
                    w_prev = np.clip((co["df"] * self.dt - i * h) / h, 0.0, 1.0)
                    f = np.clip(w_prev * prev + (1.0 - w_prev) * cur, -lim, lim)
                else:
                    f = f_in
                if forces:
                    f = f + co["off"]
                    if self.has_periodic:
                        xm = x + 0.5 * h * v
                        f = f + co["pa"] * np.sin(co["pk"] * xm + co["pp"])
                if self.has_dist:
                    f = f + co["da"] * np.sin(co["dw"] * (win.t0[w] + j * self.dt + (i + 0.5) * h))
            if not sym:
                d = (v > 0.0) | ((v == 0.0) & (fpos if const_f else f >= 0.0))
                a01, a11 = np.where(d, co["a01p"], co["a01n"]), np.where(d, co["a11p"], co["a11n"])
                b0, b1 = np.where(d, co["b0p"], co["b0n"]), np.where(d, co["b1p"], co["b1n"])
                if not rigid:
                    a00, a10 = np.where(d, co["a00p"], co["a00n"]), np.where(d, co["a10p"], co["a10n"])
            if not (sym and const_f):
                b0f, b1f = b0 * f, b1 * f
            # x + a01 v + b0 f and a11 v + b1 f, added in that order (IEEE addition commutes)
            if rigid:  # a00 = 1 and a10 = 0 exactly: the same numbers without four operations
                xf = a01 * v
                xf += x
            else:
                xf = a00 * x
                xf += a01 * v
            xf += b0f
            if rigid:
                vf = a11 * v
            else:
                vf = a10 * x
                vf += a11 * v
            vf += b1f
            if coul:
                positive = vf > 0.0
                # Moreau: the impulse opposes vf, limited to fc h; a body it can stop sticks (vf = 0
                # sticks too: -0/b1 adds nothing). Sliding, the impulse is -fc (moving up) or +fc.
                if self._stribeck:
                    lim_c = np.where(positive, co["fcp"], co["fcn"])
                    r = v / co["stv"]
                    lim_c = lim_c + co["exc"] * np.exp(-r * r)
                    held = b1 * lim_c
                    nvf = -vf
                    slide = np.copysign(lim_c, nvf)
                else:
                    held = np.where(positive, co["g1p"], co["g1n"]) if sym else b1 * np.where(
                        positive, co["fcp"], co["fcn"])
                    nvf = -vf
                    # = copysign(fc, -vf) wherever it is taken (vf = 0 always sticks)
                    slide = np.where(positive, co["nfcp"], co["fcn"])
                lam = np.where(np.abs(vf) <= held, np.divide(nvf, b1, out=nvf), slide)
                xf += b0 * lam
                vf += b1 * lam
                vf[np.abs(vf) < 1e-15] = 0.0
            x, v = xf, vf
        return x, v

    def _two_body_tables(self) -> None:
        """Coefficient-major substep matrices (24 rows: row r of [A | B] at 6 r .. 6 r + 5; columns candidate x 8
        states of motion), which states of motion matter, and where a whole cycle can be taken at once its
        propagation per direction of the table (P_i = A^i, Q_i = (I + ... + A^(i-1)) B, i = 1..n)."""
        A, B = self.A, self.B
        C = len(self.plants)
        rows = np.concatenate((A.reshape(C * 8, 4, 4), B.reshape(C * 8, 4, 2)), axis=2)
        self._table2 = rows.reshape(C * 8, 24).T.copy()

        def same(a: int, b: int) -> bool:
            return bool(np.array_equal(A[:, a], A[:, b]) and np.array_equal(B[:, a], B[:, b]))

        has_gap = bool(np.any(self.gap > 0))
        # index of the matrices: engaged 4, body 0 moving - 2, table moving - 1
        self._screw_free = not has_gap and same(4, 6) and same(5, 7)  # body 0's direction changes nothing
        self._fixed2 = self._screw_free and same(4, 5)  # nor does the table's
        # whether any direction of motion selects other matrices (no: only the contact state does)
        self._dirs2 = not all(same(e, e + k) for e in (0, 4) for k in (1, 2, 3))
        self._stribeck2 = [bool(np.any(self.st_exc[:, b] != 0)) for b in (0, 1)]
        n = self.substeps
        self.cycle_ok = (self._screw_free and n >= CYCLE_MIN_SUBSTEPS and not self.coulomb[0]
                         and not (any(self._stribeck2) or self.has_periodic or self.has_dist or self.delayed))
        if not self.cycle_ok:
            return
        self._P2, self._Q2 = {}, {}
        for tag, k in (("p", 4), ("n", 5)):
            P = np.empty((n + 1, C, 4, 4))
            Q = np.empty((n + 1, C, 4, 2))
            P[0], Q[0] = np.eye(4), 0.0
            for i in range(1, n + 1):
                P[i] = A[:, k] @ P[i - 1]
                Q[i] = A[:, k] @ Q[i - 1] + B[:, k]
            self._P2[tag], self._Q2[tag] = P, Q

    def _params_two(self, cid: np.ndarray, wid: np.ndarray, win: Windows) -> dict[str, Any]:
        """Per-element parameters of the two-body substeps for flat elements of candidates ``cid``."""
        p: dict[str, Any] = {"cid": cid, "wid": wid, "base": cid * 8, "lim": self.limit[cid], "nlim": -self.limit[cid],
                             "gap": self.gap[cid], "kh": self.stiff[cid] * (0.5 * self.gap[cid]),
                             "off": self.offset[cid] if (self.has_offset or self.has_periodic) else np.zeros(len(cid)),
                             "fcp": self.fc_pos[cid].T, "fcn": self.fc_neg[cid].T,
                             "exc": self.st_exc[cid].T, "stv": self.st_vel[cid].T}
        p["half"] = 0.5 * p["gap"]
        if self.has_periodic:
            p["pa"], p["pk"], p["pp"] = self.per_amp[cid], self.per_k[cid], self.per_phase[cid]
        if self.has_dist:
            p["da"], p["dw"], p["t0"] = self.dist_a[cid], self.dist_w[cid], win.t0[wid]
        if self.delayed:
            p["dc"], p["df"] = self.delay_cycles[cid], self.delay_frac[cid]
        p["G"] = np.take(self._table2, p["base"] + 4, axis=1).reshape(4, 6, len(cid)) if self._fixed2 else None
        if self.cycle_ok:
            n = self.substeps
            for tag in ("p", "n"):
                P, Q = self._P2[tag], self._Q2[tag]
                # the state after the cycle: rows r of [P_n | Q_n], (4, 6, N); the table velocity after each
                # earlier substep: row 3 of [P_i | Q_i], i = 1..n-1, (n-1, 6, N)
                p["fin" + tag] = np.ascontiguousarray(np.concatenate((P[n], Q[n]), axis=-1)[cid].transpose(1, 2, 0))
                p["chk" + tag] = np.ascontiguousarray(
                    np.concatenate((P[1:n, :, 3], Q[1:n, :, 3]), axis=-1)[:, cid].transpose(0, 2, 1))
        return p

    def _run_two(self, win: Windows, internal: tuple[np.ndarray, np.ndarray] | None = None,
                 with_velocity: bool = False) -> Any:
        """Two bodies on flat (window x candidate) rows: whole cycles in closed form where the coupling is
        linear and the table keeps moving one way (_cycle_two), else Plant._step_two's substeps (_substeps_two)."""
        W, C, L = len(win.start), len(self.plants), win.length
        init = self._initial(win)
        if internal is not None:
            init[0] = init[2] + internal[0]
            init[1] = init[3] + internal[1]
        s = [np.ascontiguousarray(np.broadcast_to(a, (W, C))).reshape(-1) for a in init]
        out = np.empty((W, C, L))
        out_v = np.empty((W, C, L)) if with_velocity else None
        par = self._params_two(np.tile(np.arange(C), W), np.repeat(np.arange(W), C), win)
        if self._fixed2:  # every (window, candidate): the candidates' matrices broadcast over the windows
            par["grid"] = self._table2[:, np.arange(C) * 8 + 4].reshape(4, 6, C).copy()
        for j in range(L):
            s = self._cycle_two(win, j, s, par) if self.cycle_ok else self._substeps_two(win, j, s, par)
            out[:, :, j] = s[2].reshape(W, C)
            if out_v is not None:
                out_v[:, :, j] = s[3].reshape(W, C)
        return (out, out_v) if with_velocity else out

    def _cycle_two(self, win: Windows, j: int, s: list[np.ndarray], par: dict[str, Any]) -> list[np.ndarray]:
        """Step j in closed form for the elements whose table keeps moving one way all cycle (its Coulomb
        friction a constant force then; body 0 carries none and its direction changes no matrix), checked
        on every substep's table velocity; by substeps for the rest (a stop, a start, a reversal)."""
        f0 = np.minimum(np.maximum(win.applied[par["wid"], win.history + j], par["nlim"]), par["lim"])
        f1 = par["off"]
        x0, v0, x1, v1 = s
        pos = v1 > 0.0
        coul = bool(self.coulomb[1])
        eps = self.CYCLE_V_MARGIN
        new = None
        ok = None
        for tag, sign in (("p", 1.0), ("n", -1.0)):
            u1 = (f1 - par["fcp"][1] if sign > 0 else f1 + par["fcn"][1]) if coul else f1
            z = np.stack((x0, v0, x1, v1, np.broadcast_to(f0, x0.shape), np.broadcast_to(u1, x0.shape)))
            fin = np.einsum("rkN,kN->rN", par["fin" + tag], z)
            if self._fixed2 and not coul:  # linear, one set of matrices: nothing can switch
                return list(fin)
            good = (sign * v1 > eps) & (sign * fin[3] > eps)
            if self.substeps > 1:  # the mode rings: every substep's table velocity, not only the ends
                good &= np.all(sign * np.einsum("ikN,kN->iN", par["chk" + tag], z) > eps, axis=0)
            mine = pos if sign > 0 else ~pos
            new = fin if new is None else np.where(mine, fin, new)
            ok = (mine & good) if ok is None else ok | (mine & good)
        assert new is not None and ok is not None
        new = [np.array(r) for r in new]
        odd = np.flatnonzero(~ok)
        if len(odd):
            sub = {k: (v[..., odd] if isinstance(v, np.ndarray) else v) for k, v in par.items() if k != "grid"}
            res = self._substeps_two(win, j, [a[odd] for a in s], sub)
            for r in range(4):
                new[r][odd] = res[r]
        return new

    def _substeps_two(self, win: Windows, j: int, s: list[np.ndarray], par: dict[str, Any]) -> list[np.ndarray]:
        """Step j by the plant's substeps for flat elements with parameters ``par``: Plant._step_two operation
        for operation. The state and the substep's two forces are one (6, N) array and each element's
        [A | B] one (4, 6, N) block gathered from the coefficient-major table (or, where every element has its
        candidate's one set of matrices, (4, 6, C) broadcast over the windows): the affine map is one einsum,
        which adds its terms one after the other over k (n, the contiguous axis, is the inner loop), in the
        plant's order ``A[r][0] x0 + ... + B[r][1] f1``: the same numbers (tests/test_explain_sim.py compares
        them with Plant.step), in a few calls and without a (4, 6, N) product in memory."""
        h, dt, H = self.h, self.dt, win.history
        wid, lim_in = par["wid"], par["lim"]
        half, kh = par["half"], par["kh"]
        fcp, fcn, exc, stv = par["fcp"], par["fcn"], par["exc"], par["stv"]
        has_gap = bool(np.any(par["gap"] > 0))
        G = par["G"]
        grid = par.get("grid")
        table = self._table2
        n_el = len(s[0])
        z = np.empty((6, n_el))  # x0, v0, x1, v1, f0, f1
        z[:4] = s
        if self.delayed:
            cur = win.applied[wid, H + j - par["dc"]]
            prev = win.applied[wid, H + j - par["dc"] - 1]
        else:
            f_in = np.minimum(np.maximum(win.applied[wid, H + j], par["nlim"]), lim_in)
        if G is None:
            # matrix index: engaged 4, body 0 moving - 2, table moving - 1 (see _two_body_tables)
            base = par["base"]
            base4, base5 = base + 4, base + 5
            gapped = par["gap"] > 0
        coul = [b for b in (1, 0) if self.coulomb[b]]
        for i in range(self.substeps):
            x0, v0, x1, v1 = z[0], z[1], z[2], z[3]
            if self.delayed:
                w_prev = np.clip((par["df"] * dt - i * h) / h, 0.0, 1.0)
                f0 = np.clip(w_prev * prev + (1.0 - w_prev) * cur, -lim_in, lim_in)
            else:
                f0 = f_in
            f1 = par["off"]
            if self.has_periodic:
                xm = x1 + 0.5 * h * v1
                f1 = f1 + par["pa"] * np.sin(par["pk"] * xm + par["pp"])
            if self.has_dist:
                dist = par["da"] * np.sin(par["dw"] * (par["t0"] + j * dt + (i + 0.5) * h))
                f0 = f0 + dist
                f1 = f1 + dist
            if G is None:
                engaged = True
                if has_gap:
                    rel = x0 - x1
                    over = (rel > half) & gapped
                    under = (rel < -half) & gapped
                    push = np.where(over, kh, 0.0) - np.where(under, kh, 0.0)
                    f0 = f0 + push
                    f1 = f1 - push
                    engaged = over | under | ~gapped
                if self._screw_free:  # only the table's direction selects the matrices
                    col = np.where((v1 > 0.0) | ((v1 == 0.0) & (f1 + f0 >= 0.0)), base4, base5)
                elif not self._dirs2:  # only the contact state does
                    col = np.where(engaged, base4, base)
                else:
                    d1 = (v1 > 0.0) | ((v1 == 0.0) & (f1 + f0 >= 0.0))
                    d0 = (v0 > 0.0) | ((v0 == 0.0) & (f0 >= 0.0))
                    col = np.where(engaged, base4, base) + np.where(d0, 0, 2) + np.where(d1, 0, 1)
                gs = np.take(table, col, axis=1).reshape(4, 6, n_el)
            else:
                gs = G
            z[4] = f0
            z[5] = f1
            new = affine_two(gs, z, grid)
            for body in coul:
                vi = 2 * body + 1
                vf = new[vi]
                g = gs[vi, 4 + body]
                lim = np.where(vf > 0.0, fcp[body], fcn[body])
                if self._stribeck2[body]:
                    r_ = z[vi] / stv[body]
                    lim = lim + exc[body] * np.exp(-r_ * r_)
                # Moreau, as in _substeps_one; the impulse through the body's column of B
                nvf = -vf
                lam = np.where(np.abs(vf) <= g * lim, nvf / g, np.copysign(lim, nvf))
                new += gs[:, 4 + body] * lam
                vb = new[vi]
                vb[np.abs(vb) < 1e-15] = 0.0
            z[:4] = new
        return [z[0], z[1], z[2], z[3]]


#: elements from which the two-body substep's affine map is one einsum: with very few (one), einsum may
#: make the six terms its inner loop and add them in another order than the plant's
EINSUM_MIN = 16


def affine_two(g: np.ndarray, z: np.ndarray, grid: np.ndarray | None = None) -> np.ndarray:
    """Rows r of [A | B], (4, 6, n) per element, applied to z = (x0, v0, x1, v1, f0, f1), (6, n): (4, n), the
    terms added one after the other as Plant._step_two adds them. ``grid``: the same [A | B] per candidate,
    (4, 6, C), for n = windows x C elements in window-major order (broadcast; ``g`` then unused)."""
    n = z.shape[-1]
    if n < EINSUM_MIN:
        return np.multiply(g, z).sum(axis=1)
    if grid is not None:
        return np.einsum("rkc,kwc->rwc", grid, z.reshape(6, -1, grid.shape[-1])).reshape(4, n)
    return np.einsum("rkn,kn->rn", g, z)


def window_rms(sim: np.ndarray, win: Windows, mask: np.ndarray | None = None) -> np.ndarray:
    """RMS over windows and steps of simulated minus measured position, per candidate: (C,)."""
    err = sim - win.measured[:, None, :]
    if mask is not None:
        err = err[mask]
    np.multiply(err, err, out=err)  # in place: err * err, without a second array of the simulation's size
    return np.sqrt(np.mean(err, axis=(0, -1)))


#: longest stretch of the trace between two states of :func:`internal_state`'s recursion (longer gaps between
#: the rows asked for are split): its (points x stretch) input matrix stays about the size of the trace
STATE_STRETCH = 256


def internal_state(plants: Sequence[Plant], applied: np.ndarray, table_acc: np.ndarray,
                   rows: np.ndarray, table_vel: np.ndarray | None = None,
                   times: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Relative state (x0 - x1, v0 - v1) of a linearly coupled two-body plant at ``rows``: (len(rows), C).

    Body 0 (the motor side of ``resonance``) carries no friction, so its motion relative to the
    measured table obeys a linear equation driven by the recorded effort and the measured table
    acceleration: m0 d'' = f - k d - c d' - m0 a1 (with a viscous b0 on body 0, as on ``two-mass``:
    - b0 (d' + v1), the table velocity measured; the model's own time disturbance on body 0 added
    to f). Filtering the whole trace through it (exact
    ZOH discretisation, from rest at row 0) reconstructs the mode's state at every window start:
    a lightly damped mode rings on from one window into the next, which a start "at rest relative
    to each other" would miss. ``applied[j]`` and ``table_acc[j]`` act during step j.

    Computed only where it is needed: from one row asked for to the next (at most STATE_STRETCH
    steps), s(p) = A^d s(p - d) + sum_q A^q B u(p - 1 - q), the sums of all stretches one product
    with the powers A^q B, the A^d steps a short loop over the rows (all plants at once). numpy and
    scipy.linalg only: scipy.signal's lfilter would cost its import (~1 s, most of a short trace's
    explain) and filters the whole trace.
    """
    from drivectl.plant_emulator.models import _discretise

    n = len(applied)
    C = len(plants)
    want = np.clip(np.asarray(rows, dtype=int), 0, n - 1)
    # the points of the recursion: every row asked for, and enough between them that no stretch is longer
    # than STATE_STRETCH; the state at point 0 is the rest the filter starts from
    marks = np.unique(np.concatenate(([0], want)))
    fill = [np.arange(a + STATE_STRETCH, b, STATE_STRETCH) for a, b in zip(marks[:-1], marks[1:], strict=True)
            if b - a > STATE_STRETCH]
    pts = np.unique(np.concatenate([marks, *fill])) if fill else marks
    span = np.diff(pts)  # steps from each point to the next
    M = int(span.max()) if len(span) else 1
    q = np.arange(M)
    src = pts[1:, None] - 1 - q[None, :]  # inputs u(p - 1 - q) of each stretch, newest first
    valid = q[None, :] < span[:, None]
    src = np.where(valid, src, n)  # column n of the padded inputs is 0
    a_d = np.empty((C, 2, 2))
    b_d = np.empty((C, 2))
    u = np.zeros((C, n + 1))
    for c, p in enumerate(plants):
        d = p.design
        m0 = d.bodies[0].mass
        b0 = d.bodies[0].c_pos
        k, cc = d.coupling.stiffness, d.coupling.damping
        ac = np.array([[0.0, 1.0], [-k / m0, -(cc + b0) / m0]])
        bc = np.array([[0.0], [1.0]])
        A, B = (np.asarray(x) for x in _discretise(ac, bc, p.dt))
        a_d[c], b_d[c] = A, B[:, 0]
        f = np.asarray(applied, dtype=float)
        if b0 and table_vel is not None:
            f = f - b0 * table_vel
        if d.disturbance_amplitude and times is not None:
            f = f + d.disturbance_amplitude * np.sin(2 * math.pi * d.disturbance_frequency * (times + 0.5 * p.dt))
        u[c, :n] = f / m0 - table_acc
    # A^q (q = 0..M) and A^q B (q < M), all plants at once
    powers = np.empty((M + 1, C, 2, 2))
    powers[0] = np.eye(2)
    for i in range(1, M + 1):
        powers[i] = a_d @ powers[i - 1]
    hq = np.einsum("qcij,cj->cqi", powers[:M], b_d)  # (C, M, 2)
    forced = np.matmul(u[:, src], hq)  # (C, K, 2)
    states = np.zeros((len(pts), C, 2))
    s = np.zeros((C, 2))
    for i, d_steps in enumerate(span):
        s = np.einsum("cij,cj->ci", powers[d_steps], s) + forced[:, i]
        states[i + 1] = s
    at = states[np.searchsorted(pts, want)]  # (R, C, 2)
    return np.ascontiguousarray(at[..., 0]), np.ascontiguousarray(at[..., 1])

"""The one-body kernel of :class:`~drivectl.tools.explain.sim.BatchSim`: whole cycles in closed form
where the body keeps moving one way or stays stuck, the plant's substeps (operation for operation as
``Plant._step_one``) only for the (window, candidate) pairs that stop, start or reverse within a cycle.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from drivectl.tools.explain.sim import Windows


class OneBodyKernel:
    """The one-body methods of BatchSim (a mixin: the tables and arrays are BatchSim's)."""

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
        self.cycle_ok = self.substeps >= self.cycle_min_substeps and not (
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

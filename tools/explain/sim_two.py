"""The two-body kernel of :class:`~drivectl.tools.explain.sim.BatchSim` (a coupled screw and table,
with or without a dead zone): the plant's substeps operation for operation as ``Plant._step_two``,
and for a linearly coupled pair with friction on the table only, whole cycles in closed form.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from drivectl.tools.explain.sim import Windows


class TwoBodyKernel:
    """The two-body methods of BatchSim (a mixin: the tables and arrays are BatchSim's)."""

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
        self.cycle_ok = (self._screw_free and n >= self.cycle_min_substeps and not self.coulomb[0]
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

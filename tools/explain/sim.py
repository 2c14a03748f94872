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
(direction-independent friction, a00 = 1 and a10 = 0 without a spring) left out. The kernels:
tools/explain/sim_one.py (one body) and tools/explain/sim_two.py (two bodies).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from drivectl.plant_emulator.models import Plant
from drivectl.tools.explain.sim_one import OneBodyKernel
from drivectl.tools.explain.sim_two import TwoBodyKernel, affine_two  # noqa: F401 (affine_two: read here too)


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


class BatchSim(OneBodyKernel, TwoBodyKernel):
    """C candidate plants (same body count) stepped over W windows at once."""

    #: velocity (m/s) a whole cycle must keep away from 0 to be taken in closed form (a stop or a reversal
    #: inside the cycle is left to the substeps; far above the 1e-15 below which a substep zeroes it)
    CYCLE_V_MARGIN = 1e-12

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
        self.cycle_min_substeps = CYCLE_MIN_SUBSTEPS  # read per instance: the kernels live in sim_one/sim_two
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

"""The linear form of a control law: what a linear controller does to small deviations, as a discrete
state space from the sampled feedback [position, velocity] to the effort, with the reference held.

A law whose step is linear in the feedback about a held reference (PID, PID + disturbance observer, the
model-based Kalman + LQR law) returns one from ``Controller.linear_form()``; the sliding-mode and
time-delay-estimation laws (sign, fractional powers, switching gains) have none and return None. Used
for stability margins on the model (tools/commissioning/margins.py, ``tune --target``) and as what a
measured open loop is checked against (tests/test_margins.py, with python-control as the reference).

Convention: at sample k the law reads ``y_k = [position_k, velocity_k]`` and returns ``u_k``::

    x_{k+1} = A x_k + B y_k,    u_k = C x_k + D y_k

(with the reference constant, so ``u`` is the law's own effort, not the excitation added after it). The
loop the drive closes then has the open-loop ``L = -K(z) P(z)``, ``P`` the plant from the effort to
[position, velocity] with the one-cycle transport delay and the zero-order hold.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class LinearForm:
    """``x' = A x + B y``, ``u = C x + D y``; y = [position, velocity], u = effort; sampled at ``dt``."""

    A: np.ndarray  # (n, n)
    B: np.ndarray  # (n, 2)
    C: np.ndarray  # (n,)
    D: np.ndarray  # (2,)
    dt: float

    def response(self, freqs: np.ndarray) -> np.ndarray:
        """K(e^{j w dt}) at ``freqs`` (Hz): shape (len(freqs), 2), effort per [position, velocity]."""
        z = np.exp(1j * 2 * math.pi * np.asarray(freqs, dtype=float) * self.dt)
        n = self.A.shape[0]
        if n == 0:
            return np.tile(self.D.astype(complex), (len(z), 1))
        # one batched solve for every frequency: (zI - A)^-1 B, then C ... + D
        x = np.linalg.solve(z[:, None, None] * np.eye(n) - self.A, np.broadcast_to(self.B, (len(z), n, 2)))
        return np.einsum("j,fjk->fk", self.C, x) + self.D

    def simulate(self, y: np.ndarray) -> np.ndarray:
        """The effort for a sequence of feedback rows ``y`` (shape (N, 2)), from the zero state."""
        x = np.zeros(self.A.shape[0])
        u = np.empty(len(y))
        for k, yk in enumerate(np.asarray(y, dtype=float)):
            u[k] = self.C @ x + self.D @ yk
            x = self.A @ x + self.B @ yk
        return u


def from_rows(next_rows: list[np.ndarray], out_row: np.ndarray, dt: float) -> LinearForm:
    """A LinearForm from the law written as rows over ``[x, position, velocity]``: ``next_rows[i]`` the
    coefficients of the i-th state after the step, ``out_row`` those of the effort (so each law states its
    update once, in the order its ``step`` runs, instead of as hand-assembled matrices)."""
    rows = np.array(next_rows, dtype=float).reshape(len(next_rows), -1)
    nx = rows.shape[0]
    return LinearForm(rows[:, :nx], rows[:, nx:], np.asarray(out_row[:nx], dtype=float),
                      np.asarray(out_row[nx:], dtype=float), dt)


def basis(nx: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rows of the states (nx of them), of the position and of the velocity, over [x, position,
    velocity]: the variables :func:`from_rows` writes a law in."""
    eye = np.eye(nx + 2)
    return eye[:nx], eye[nx], eye[nx + 1]

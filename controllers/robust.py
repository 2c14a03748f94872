"""Robustness of a controller design: the set of perturbed models it must hold on, and the check.

A design that is only stable on its nominal model is not a design: the machine differs (the issue this
answers measured ``tune``'s nominal-only PID-NFTSM gains unstable on 16 of 64 corners). The perturbed set
is every +-``rel`` corner of the parameters that matter (:data:`CORNER_PARAMS`: for two-mass the two
masses, the stiffness and the three damping coefficients, 2^6 = 64 corners; for a rigid axis the mass and
the friction, 32), or a seeded subset of ``count`` of them.

The check, per corner:

* **linear loop** (the controller exposes ``loop_matrix``: :class:`~drivectl.controllers.mbc.Mbc`; the
  corner's linear part): the closed-loop matrix of the discretised loop -- the corner's plant (exact ZOH),
  the command in flight (the one-cycle transport delay), the controller's own states -- and its spectral
  radius; stable iff < 1. Exact for the linear part, and cheap (one eigenvalue problem).
* **otherwise** (a nonlinear controller or plant): a simulation of the axis's move on the corner (SimAxis,
  as ``tune`` runs it); unstable when the run leaves the limits, does not stay finite, or its error does
  not settle (:func:`settles`: growing at the end, or not decaying in a final hold).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import random
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

#: parameters perturbed per base model (those that change the dynamics the loop sees)
CORNER_PARAMS: dict[str, tuple[str, ...]] = {
    "two-mass": ("m1", "m2", "k", "n", "b1", "b2"),
    "rigid": ("mass", "c_pos", "c_neg", "fc_pos", "fc_neg"),
}
#: default relative perturbation of every corner
DEFAULT_REL = 0.10
#: a simulated run whose tail error stays above this (and near its peak) is not settling
DIVERGED_UM = 5.0


def corners(spec: Any, rel: float = DEFAULT_REL, count: int | None = None, seed: int = 0,
            params: Sequence[str] | None = None) -> list[Any]:
    """Every +-``rel`` corner of ``spec``'s parameters (``params``, default :data:`CORNER_PARAMS` of its
    model; those it lacks or holds at 0 are skipped), or a seeded subset of ``count`` of them. Each is a
    PlantSpec named ``NAME corner +-+...`` (signs in ``params`` order)."""
    if not (math.isfinite(rel) and 0 < rel < 1):
        raise ValueError(f"corners: rel: must be in (0, 1), got {rel!r}")
    names = [p for p in (params or CORNER_PARAMS.get(spec.model, ())) if spec.params.get(p, 0.0) != 0.0]
    signs = list(itertools.product((1, -1), repeat=len(names)))
    if count is not None:
        if count < 1:
            raise ValueError(f"corners: count: must be >= 1, got {count!r}")
        if count < len(signs):
            signs = random.Random(seed).sample(signs, count)
    out = []
    for sg in signs:
        params_ = dict(spec.params)
        for p, s in zip(names, sg, strict=True):
            params_[p] = spec.params[p] * (1 + s * rel)
        label = "".join("+" if s > 0 else "-" for s in sg)
        out.append(dataclasses.replace(spec, params=params_, name=f"{spec.name} corner {label}"))
    return out


@dataclass
class CornerResult:
    name: str
    stable: bool
    radius: float | None = None  # spectral radius (linear check)
    max_um: float | None = None  # largest error (simulation check)
    detail: str = ""


def spectral_radius(controller: Any, true_spec: Any) -> float:
    """Spectral radius of ``controller``'s loop closed around ``true_spec``'s linear part (with the
    transport delay). The controller must expose ``loop_matrix(A, B, C)``."""
    from drivectl.controllers.linear_model import LinearModel

    lm = LinearModel.from_spec(true_spec)
    A, B = lm.discrete(controller.dt)
    n = lm.n
    C = np.zeros((2, n))
    C[0, n - 2] = 1.0
    C[1, n - 1] = 1.0
    M = controller.loop_matrix(A, B, C)
    return float(np.max(np.abs(np.linalg.eigvals(M))))


def check_corners(make: Any, specs: Sequence[Any], *, simulate: Any = None) -> list[CornerResult]:
    """Check one design on each of ``specs``: ``make(spec)`` builds the controller for the loop (its model
    stays the nominal one: only the plant is the corner), ``simulate(spec)`` runs it and returns
    (completed, error per cycle in m, the reference's change per cycle) for the nonlinear check
    (:func:`settles`). Linear when the controller has
    ``loop_matrix`` and the corner's plant has no nonlinearity; simulation otherwise."""
    out = []
    for spec in specs:
        ctrl = make(spec)
        if hasattr(ctrl, "loop_matrix") and _is_linear(spec):
            rho = spectral_radius(ctrl, spec)
            out.append(CornerResult(spec.name, rho < 1.0, radius=rho))
            continue
        if simulate is None:
            raise ValueError(f"corner {spec.name}: not a linear loop and no simulation given")
        completed, error, ref_step = simulate(spec)
        stable = bool(completed and settles(error, ref_step))
        max_um = float(np.max(np.abs(error))) * 1e6 if len(error) else math.nan
        detail = "" if stable else ("run stopped" if not completed else "the error does not settle")
        out.append(CornerResult(spec.name, stable, max_um=max_um, detail=detail))
    return out


def settles(error: np.ndarray, ref_step: np.ndarray) -> bool:
    """Does a simulated run's error (m, per cycle) look like a stable loop's? Not when it is not finite,
    when it grows (the largest error of the last fifth is over three times that of the rest and above
    :data:`DIVERGED_UM`), or, where the run ends holding still (``ref_step``, the reference's change per
    cycle, is 0 over its last 50 cycles or more), when the error does not decay over that hold (the
    largest of its second half is at least half that of its first half, and above DIVERGED_UM): a stable
    loop settles in the hold, a diverging or limit-cycling one does not."""
    e = np.abs(np.asarray(error, dtype=float)) * 1e6
    if e.size == 0 or not np.all(np.isfinite(e)):
        return False
    cut = max(1, int(0.8 * e.size))
    tail, head = float(e[cut:].max(initial=0.0)), float(e[:cut].max(initial=0.0))
    if tail > DIVERGED_UM and tail > 3.0 * head:
        return False
    moving = np.flatnonzero(np.asarray(ref_step)[: e.size])
    hold = e[moving[-1] + 1:] if moving.size else e
    if hold.size < 50:
        return True
    half = hold.size // 2
    first, second = float(hold[:half].max()), float(hold[half:].max())
    return not (second > DIVERGED_UM and second >= 0.5 * first)


def _is_linear(spec: Any) -> bool:
    d = spec.design()
    return not (any(b.has_coulomb for b in d.bodies) or d.periodic or d.table_offset
                or (d.coupling is not None and d.coupling.gap > 0) or d.input_delay
                or any(b.c_pos != b.c_neg for b in d.bodies) or math.isfinite(d.input_limit))

"""Many gain sets at once: N copies of a linear plant stepped together under one controller whose
gains are arrays of shape (N,).

Why numpy vectorisation and not a JIT: the controllers are written once against ``self.ops``
(scalar maths for a single run, numpy for arrays, see controllers/base.py), so the batch runs the
very code that runs on the axis; a JIT would need a second, restricted copy of every control law
and a heavy compiler dependency. The plant's exact discretisation makes its step one small matrix
product per cycle for the whole batch.

Only plants whose dynamics are linear qualify (``two-mass`` and effect-free linear variants):
Coulomb friction and dead zones need per-member branching that the single-run plant does better.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from drivectl.controllers.base import Controller
from drivectl.driver.axis import Feedback
from drivectl.plant_emulator.models import Plant
from drivectl.profiles.base import Profile, Reference


@dataclass
class BatchResult:
    """Per-member figures of a batch run (arrays of shape (N,)) and the wall-clock-free sizes."""

    max_error: np.ndarray  # m
    rms_error: np.ndarray  # m
    effort_rms_diff: np.ndarray  # effort unit per cycle
    finite: np.ndarray  # bool: the member never blew up
    cycles: int
    members: int


def check_linear(plant: Plant) -> None:
    d = plant.design
    if any(b.has_coulomb for b in d.bodies) or plant.gap or d.periodic or d.input_delay or d.table_offset:
        raise ValueError(f"batch: plant {plant.name} is not linear (Coulomb friction, dead zone, periodic or "
                         "delay effects); simulate it member by member")
    if math.isfinite(d.input_limit):
        raise ValueError(f"batch: plant {plant.name} has a saturation effect; simulate it member by member")


def run_batch(
    plant: Plant,
    controller: Controller,
    profile: Profile,
    members: int,
    *,
    duration: float | None = None,
    transport_delay: bool = True,
    resolution: float | None = None,
) -> BatchResult:
    """Simulate ``members`` copies of ``plant`` under ``controller`` (array gains) in lockstep.

    Same time model as SimAxis: the effort computed from sample k acts from t(k+1) with the
    transport delay, from t(k) without; positions quantised to ``resolution`` when given.
    """
    check_linear(plant)
    dt = plant.dt
    total = duration if duration is not None else profile.duration
    n = int(round(total / dt)) + 1
    t = np.arange(n) * dt
    pr, vr, ar, jr = (a.tolist() for a in profile.sample(t))

    if plant.substeps != 1:
        raise ValueError("batch: a linear plant steps once per cycle; build it with substeps=1")
    nb = plant.n_bodies
    A = np.array(plant.A)
    B = np.array(plant.B)
    # state as rows (2 nb, N): each state variable is one contiguous array over the batch
    s = np.zeros((2 * nb, members))
    s[0::2] = profile.sample(np.array([0.0]))[0][0]
    nxt = np.empty_like(s)
    b_u = B[:, :1].copy()  # the effort acts on body 0, column vector for broadcasting
    b_d = B.sum(axis=1)  # paper 000's d1 = d2 acts on every body
    dist_a, dist_w = plant.design.disturbance_amplitude, 2 * math.pi * plant.design.disturbance_frequency
    h = plant.h
    inv_res = 1.0 / resolution if resolution else 0.0

    max_err = np.zeros(members)
    sq_err = np.zeros(members)
    sq_du = np.zeros(members)
    latched = np.zeros(members)
    prev_u = np.zeros(members)
    e = np.empty(members)
    controller.reset()
    prepare = getattr(controller, "prepare", None)  # reference preview (controllers/base.py)
    if prepare is not None:
        prepare(profile, t)
    for k in range(n):
        pos = s[-2]
        vel = s[-1]
        if resolution:
            pos = np.rint(pos * inv_res) * resolution
            vel = np.rint(vel * inv_res) * resolution
        u = controller.step(Reference(pr[k], vr[k], ar[k], jr[k]), Feedback(k * dt, pos, vel))
        if np.ndim(u) == 0:
            u = np.full(members, u)
        np.subtract(pr[k], pos, out=e)
        np.abs(e, out=e)
        np.maximum(max_err, e, out=max_err)
        e *= e
        sq_err += e
        if k:
            np.subtract(u, prev_u, out=e)
            e *= e
            sq_du += e
        prev_u = u
        applied = latched if transport_delay else u
        np.matmul(A, s, out=nxt)
        nxt += b_u * applied
        if dist_a:
            nxt += (dist_a * math.sin(dist_w * (k * dt + 0.5 * h))) * b_d[:, None]
        s, nxt = nxt, s
        if transport_delay:
            latched = u
    finite = np.isfinite(max_err) & np.isfinite(sq_err)
    return BatchResult(
        max_error=max_err,
        rms_error=np.sqrt(sq_err / n),
        effort_rms_diff=np.sqrt(sq_du / max(n - 1, 1)),
        finite=finite,
        cycles=n,
        members=members,
    )

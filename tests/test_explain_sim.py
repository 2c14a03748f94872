"""The batch kernel of `drivectl explain` (tools/explain/sim.py): whole cycles in closed form equal the
substeps, a batch equals its members run alone, and both equal Plant.step.

No trace recording here: an open-loop effort with reversals, stops and dwells (where Coulomb friction
holds the axis) drives the plant itself, so every branch of the kernel is taken in a fraction of a second.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm

from drivectl.plant_emulator.models import PlantSpec, load_plant
from drivectl.tools.explain import sim as explain_sim
from drivectl.tools.explain.sim import BatchSim, make_windows

DT = 0.001
BASE = load_plant("rigid-x")
#: direction-independent friction (as the EMPS reference model): the kernel skips the direction there
SYMMETRIC = PlantSpec("sym", "rigid", "N", {"mass": 95.0, "c_pos": 200.0, "c_neg": 200.0, "fc_pos": 20.0,
                                             "fc_neg": 20.0})


@pytest.fixture(scope="module")
def data() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """pos, vel, effort of the nominal plant under a 3 s effort with reversals and two dwells at zero."""
    n = 3000
    t = np.arange(n) * DT
    rng = np.random.default_rng(5)
    effort = 90.0 * np.sin(2 * np.pi * 1.3 * t) + 35.0 * np.sin(2 * np.pi * 7.0 * t) + rng.normal(0, 3.0, n)
    effort[(t > 0.9) & (t < 1.2)] = 0.0
    effort[(t > 2.1) & (t < 2.3)] = 20.0  # within the Coulomb level: the axis stays put
    plant = BASE.build(DT)
    st = plant.initial_state()
    pos, vel = np.empty(n), np.empty(n)
    applied = np.concatenate(([0.0], effort[:-1]))  # the transport rule of make_windows
    for k in range(n):
        pos[k], vel[k] = plant.position(st), plant.velocity(st)
        plant.step(st, float(applied[k]))
    return pos, vel, effort


def _windows(data):
    pos, vel, effort = data
    return make_windows(pos, vel, effort, DT, 150)


BATCHES = {
    "nominal": [BASE],
    "viscous per direction": [BASE.with_effect("viscous", scale=s, scale_neg=2.0 - s) for s in (0.3, 1.0, 1.7)],
    "offset": [BASE.with_effect("offset", force=f) for f in (-40.0, 0.0, 25.0)],
    "spring": [BASE.with_effect("spring", stiffness=k) for k in (0.0, 500.0, 4000.0)],
    "coulomb": [BASE.with_effect("coulomb", force_pos=a, force_neg=b) for a, b in ((0.0, 0.0), (20.0, 80.0))],
    "mass and saturation": [BASE.with_effect("mass", mass=60.0), BASE.with_effect("saturation", limit=50.0)],
    "spring and offset": [BASE.with_effect("spring", stiffness=3.0).with_effect("offset", force=-5.0)],
    "symmetric": [SYMMETRIC, SYMMETRIC.with_effect("offset", force=3.0).with_effect("spring", stiffness=50.0)],
}


def _fast_and_slow(specs, data, monkeypatch):
    """The batch run with whole cycles in closed form, then with substeps only; checks they agree and
    returns the substep run's velocities."""
    plants = [s.build(DT) for s in specs]
    win = _windows(data)
    fast = BatchSim(plants)
    assert fast.cycle_ok  # the closed form is taken for these
    x_fast, v_fast = fast.run_with_velocity(win)
    monkeypatch.setattr(explain_sim, "CYCLE_MIN_SUBSTEPS", 10 ** 6)
    slow = BatchSim(plants)
    assert not slow.cycle_ok
    x_slow, v_slow = slow.run_with_velocity(win)
    assert np.max(np.abs(x_fast - x_slow)) < 1e-12
    assert np.max(np.abs(v_fast - v_slow)) < 1e-10
    return v_slow


@pytest.mark.parametrize("name", list(BATCHES))
def test_whole_cycles_equal_the_substeps(data, name, monkeypatch):
    v_slow = _fast_and_slow(BATCHES[name], data, monkeypatch)
    # the trace has stuck rows and moving rows (both branches ran)
    assert np.mean(v_slow == 0.0) > 0.01 and np.mean(np.abs(v_slow) > 1e-3) > 0.5


def test_batch_equals_each_member_alone(data):
    specs = [s for batch in ("viscous per direction", "offset", "coulomb") for s in BATCHES[batch]]
    plants = [s.build(DT) for s in specs]
    win = _windows(data)
    batch = BatchSim(plants)
    together = batch.run(win)
    for c, p in enumerate(plants):
        # at the batch's substeps (a member without Coulomb friction alone would take 1)
        alone = BatchSim([p], substeps=batch.substeps).run(win)[:, 0]
        assert np.max(np.abs(together[:, c] - alone)) < 1e-15


@pytest.mark.parametrize("name", ["spring", "offset", "viscous per direction", "symmetric"])
def test_whole_cycles_equal_plant_step(data, name):
    pos, vel, effort = data
    win = make_windows(pos, vel, effort, DT, 150, starts=np.array([100, 850, 2050]))
    for spec in BATCHES[name]:
        plant = spec.build(DT)
        sim = BatchSim([plant]).run(win)
        for w in range(len(win.start)):
            st = plant.initial_state()
            st.s = [float(win.q0[w]), float(win.v0[w])]
            xs = []
            for j in range(win.length):
                plant.step(st, float(win.applied[w, win.history + j]))
                xs.append(plant.position(st))
            assert np.max(np.abs(np.array(xs) - sim[w, 0])) < 1e-12


def test_cycle_propagation_is_the_exact_discretisation_over_a_cycle():
    """P_n = expm(Ac dt) and Q_n = the zero-order-hold input matrix over dt, per direction of motion."""
    for spec in BATCHES["spring"] + BATCHES["viscous per direction"]:
        plant = spec.build(DT)
        sim = BatchSim([plant])
        b = plant.design.bodies[0]
        for tag, c in (("p", b.c_pos), ("n", b.c_neg)):
            ac = np.array([[0.0, 1.0], [-plant.design.table_stiffness / b.mass, -c / b.mass]])
            aug = np.zeros((3, 3))
            aug[:2, :2] = ac
            aug[1, 2] = 1.0 / b.mass
            e = expm(aug * DT)
            n = sim.substeps
            assert np.allclose(sim._t1["P" + tag][0, n], e[:2, :2], rtol=0, atol=1e-12)
            assert np.allclose(sim._t1["Q" + tag][0, n], e[:2, 2], rtol=1e-12, atol=1e-18)


@pytest.mark.parametrize("spec", [
    load_plant("two-mass"),  # the same matrices in every state of motion: gathered once
    load_plant("two-mass").with_effect("offset", force=0.05).with_effect("coulomb", force_pos=0.02, force_neg=0.04),
    BASE.with_effect("resonance", frequency=40.0, damping=0.05),  # the table's direction selects them
    BASE.with_effect("backlash", width=20e-6),  # every state of motion
], ids=["two-mass", "two-mass+offset+coulomb", "resonance", "backlash"])
def test_two_bodies_equal_plant_step(data, spec):
    pos, vel, effort = data
    scale = 0.01 if spec.effort_unit == "V" else 1.0  # the two-mass axis takes volts
    win = make_windows(pos, vel, effort * scale, DT, 150, starts=np.array([100, 850, 2050]))
    plant = spec.build(DT)
    sim = BatchSim([plant]).run(win)
    init = BatchSim([plant])._initial(win)
    for w in range(len(win.start)):
        st = plant.initial_state()
        st.s = [float(a[w, 0]) for a in init]
        st.t = float(win.t0[w])
        xs = []
        for j in range(win.length):
            plant.step(st, float(win.applied[w, win.history + j]))
            xs.append(plant.position(st))
        assert np.max(np.abs(np.array(xs) - sim[w, 0])) < 1e-12


@pytest.mark.parametrize("load,workers", [(0.0, 2), (1.0, 2), (1.4, 2), (1.6, 1), (3.5, 1)])
def test_workers_follow_the_free_cores(monkeypatch, load, workers):
    """Two cores: a pool while at most one other job runs (load <= 1.5), else one process."""
    from drivectl.tools.explain import core as explain

    monkeypatch.delenv("DRIVECTL_EXPLAIN_WORKERS", raising=False)
    monkeypatch.setattr(explain.os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    monkeypatch.setattr(explain.os, "getloadavg", lambda: (load, load, load))
    monkeypatch.setattr(explain.threading, "active_count", lambda: 1)
    assert explain.choose_workers() == workers


@pytest.mark.parametrize("specs", [
    [BASE.with_effect("resonance", frequency=f, damping=z) for f, z in ((12.0, 0.02), (40.0, 0.05), (300.0, 0.7))],
    [BASE.with_effect("offset", force=-20.0).with_effect("resonance", frequency=60.0, damping=0.1)],
    [SYMMETRIC.with_effect("resonance", frequency=25.0, damping=0.03)],
], ids=["resonance", "resonance+offset", "symmetric resonance"])
def test_two_body_whole_cycles_equal_the_substeps(data, specs, monkeypatch):
    v_slow = _fast_and_slow(specs, data, monkeypatch)
    assert np.mean(v_slow == 0.0) > 0.01  # the table sticks somewhere: the substeps ran too


# --- the substep kernels against Plant.step where no whole cycle is taken (issue 17 point 6) ---


@pytest.mark.parametrize("spec,substeps", [
    (BASE.with_effect("periodic", amplitude=30.0, period=0.004, phase=0.5), None),  # a force that varies per substep
    (BASE.with_effect("stribeck", excess_force=25.0, velocity=0.002), None),
    (BASE.with_effect("delay", delay=0.0017), None),  # the delay's weights per substep
    (BASE.with_effect("viscous", scale=0.6, scale_neg=1.5).with_effect("offset", force=8.0), 2),  # coarse scans
    (SYMMETRIC.with_effect("offset", force=3.0), 2),
    (BASE.with_effect("spring", stiffness=2000.0), 2),
    (load_plant("two-mass").with_effect("periodic", amplitude=0.05, period=0.01, phase=1.0), None),
    (load_plant("two-mass").with_effect("delay", delay=0.0023), None),
    (BASE.with_effect("viscous", scale=0.6, scale_neg=1.5).with_effect("backlash", width=15e-6), 5),
    (BASE.with_effect("viscous", scale=0.6, scale_neg=1.5).with_effect("resonance", frequency=50.0, damping=0.05), 2),
], ids=["periodic", "stribeck", "delay", "asymmetric coarse", "symmetric coarse", "spring coarse", "two-mass periodic",
        "two-mass delay", "asymmetric backlash", "asymmetric resonance coarse"])
def test_substeps_equal_plant_step(data, spec, substeps):
    """The per-substep kernels (_substeps_one, _substeps_two: invariants computed once per cycle, the two-body
    map as one einsum) equal the plant's own step at the same substep count."""
    pos, vel, effort = data
    scale = 0.01 if spec.effort_unit == "V" else 1.0
    win = make_windows(pos, vel, effort * scale, DT, 150, starts=np.array([100, 850, 2050]), history=16)
    plant = spec.build(DT, substeps)
    sim = BatchSim([plant])
    assert not sim.cycle_ok
    x = sim.run(win)
    init = sim._initial(win)
    for w in range(len(win.start)):
        st = plant.initial_state()
        st.s = [float(a[w, 0]) for a in init]
        st.t = float(win.t0[w])
        if plant.history_len:  # the efforts that acted before the window, oldest first
            st.history = [float(e) for e in win.applied[w, win.history - plant.history_len:win.history]]
        xs = []
        for j in range(win.length):
            plant.step(st, float(win.applied[w, win.history + j]))
            xs.append(plant.position(st))
        assert np.max(np.abs(np.array(xs) - x[w, 0])) < 1e-12


@pytest.mark.parametrize("n", [1, 2, 15, 16, 17, 300])
def test_two_body_map_adds_in_the_plants_order(n):
    """affine_two is bit for bit A[r][0] x0 + A[r][1] v0 + ... + B[r][1] f1, left to right, as Plant._step_two
    adds it (einsum from EINSUM_MIN elements on; with one element it would reorder the terms)."""
    rng = np.random.default_rng(n)
    C = 3 if n % 3 == 0 else 1
    g_c = rng.normal(size=(4, 6, C)) * 10.0 ** rng.uniform(-8, 3, size=(4, 6, C))
    z = rng.normal(size=(6, n)) * 10.0 ** rng.uniform(-8, 3, size=(6, n))
    g = np.tile(g_c, (1, 1, n // C))
    want = np.array([g[r, 0] * z[0] + g[r, 1] * z[1] + g[r, 2] * z[2] + g[r, 3] * z[3] + g[r, 4] * z[4]
                     + g[r, 5] * z[5] for r in range(4)])
    assert np.array_equal(explain_sim.affine_two(g, z), want)
    assert np.array_equal(explain_sim.affine_two(g, z, g_c), want)


def test_internal_state_equals_the_state_space_recursion(data):
    """The mode's state at the window starts (stretches between them, powers of A) equals stepping
    s <- A s + B u sample by sample, here with starts far apart (stretches split at STATE_STRETCH)."""
    from drivectl.plant_emulator.models import _discretise

    pos, vel, effort = data
    n = len(pos)
    acc = np.gradient(vel, DT)
    rows = np.array([0, 5, 160, 1200, 1201, 2999, 4000])  # a row past the end reads the last
    specs = [BASE.with_effect("resonance", frequency=f, damping=z) for f, z in ((9.0, 0.02), (120.0, 0.3))]
    plants = [s.build(DT) for s in specs]
    d, v = explain_sim.internal_state(plants, effort, acc, rows)
    for c, p in enumerate(plants):
        m0 = p.design.bodies[0].mass
        k, cc = p.design.coupling.stiffness, p.design.coupling.damping
        A, B = (np.asarray(x) for x in _discretise(np.array([[0.0, 1.0], [-k / m0, -cc / m0]]),
                                                    np.array([[0.0], [1.0]]), DT))
        s = np.zeros(2)
        traj = np.empty((n, 2))
        for j in range(n):
            traj[j] = s
            s = A @ s + B[:, 0] * (effort[j] / m0 - acc[j])
        want = traj[np.clip(rows, 0, n - 1)]
        for got, col in ((d[:, c], 0), (v[:, c], 1)):
            assert np.max(np.abs(got - want[:, col])) <= 1e-12 * np.max(np.abs(want[:, col]))

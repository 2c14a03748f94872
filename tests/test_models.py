"""Plant models: analytic responses, energy balance, the 89 Hz mode, Coulomb friction, TOML input."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivectl.plant_emulator.models import PlantError, load_plant, plant_from_mapping

DT = 0.001


def test_builtin_plants_load_with_table_values():
    x = load_plant("rigid-x")
    assert x.params == {"mass": 88.08, "c_pos": 467.2, "c_neg": 530.6, "fc_pos": 45.5, "fc_neg": 47.9}
    y = load_plant("rigid-y")
    assert y.params["mass"] == 97.9 and y.params["fc_neg"] == 51.2
    tm = load_plant("two-mass")
    assert tm.params["k"] == pytest.approx(4.1814e4) and tm.effort_unit == "V"


def test_rigid_constant_force_matches_analytic_solution():
    # m v' = F - fc - c v from rest: v(t) = (F - fc)/c (1 - exp(-c t / m)), exact at every sample
    spec = load_plant("rigid-x")
    plant = spec.build(DT)
    state = plant.initial_state()
    m, c, fc, force = 88.08, 467.2, 45.5, 150.0
    for k in range(1, 501):
        plant.step(state, force)
        t = k * DT
        v = (force - fc) / c * (1 - math.exp(-c * t / m))
        x = (force - fc) / c * (t - m / c * (1 - math.exp(-c * t / m)))
        assert state.s[1] == pytest.approx(v, rel=1e-9, abs=1e-12)
        assert state.s[0] == pytest.approx(x, rel=1e-9, abs=1e-13)


def test_rigid_direction_dependent_friction():
    plant = load_plant("rigid-x").build(DT)
    ends = {}
    for sign in (1, -1):
        state = plant.initial_state()
        for _ in range(5000):
            plant.step(state, sign * 200.0)
        ends[sign] = state.s[1]
    assert ends[1] == pytest.approx((200 - 45.5) / 467.2, rel=1e-6)
    assert ends[-1] == pytest.approx(-(200 - 47.9) / 530.6, rel=1e-6)


def test_coulomb_friction_sticks_below_breakaway_and_never_chatters():
    plant = load_plant("rigid-x").build(DT)
    state = plant.initial_state()
    for _ in range(200):
        plant.step(state, 45.0)  # just below fc+ = 45.5: must not move at all
    assert state.s == [0.0, 0.0]
    # moving, then the force drops below Coulomb: the axis stops and stays stopped, v exactly 0
    for _ in range(300):
        plant.step(state, 100.0)
    assert state.s[1] > 0
    vs = []
    for _ in range(2000):
        plant.step(state, 20.0)
        vs.append(state.s[1])
    vs = np.array(vs)
    stop = int(np.argmax(vs == 0.0))
    assert stop > 0 and np.all(vs[stop:] == 0.0)
    assert np.all(vs >= 0.0)  # no sign flip around zero speed


def test_rigid_energy_balance_with_viscous_friction():
    # without Coulomb: work in = kinetic energy + viscous dissipation (exact discretisation)
    spec = load_plant("rigid-x")
    spec = type(spec)(**{**spec.__dict__, "params": {**spec.params, "fc_pos": 0.0, "fc_neg": 0.0,
                                                      "c_neg": 467.2}})
    plant = spec.build(DT, substeps=50)
    state = plant.initial_state()
    work = diss = 0.0
    for k in range(2000):
        f = 300.0 * math.sin(2 * math.pi * 2 * k * DT)
        x0, v0 = state.s
        plant.step(state, f)
        x1, v1 = state.s
        work += f * (x1 - x0)  # force held over the step: work = F dx exactly
        diss += 467.2 * ((v0 + v1) / 2) ** 2 * DT
    ke = 0.5 * 88.08 * state.s[1] ** 2
    assert work == pytest.approx(ke + diss, rel=2e-3)


def test_two_mass_axial_mode_at_89_hz():
    spec = load_plant("two-mass")
    p = spec.params
    mu = p["m1"] * p["m2"] / (p["m1"] + p["m2"])
    f_expected = math.sqrt(p["k"] / mu) / (2 * math.pi)
    assert f_expected == pytest.approx(89.2, abs=0.05)
    # free response of the relative coordinate after an impulse (no disturbance, no damping to
    # ground): count zero crossings of x1 - x2 over 1 s
    spec = type(spec)(**{**spec.__dict__, "params": {**p, "disturbance_amplitude": 0.0, "n": 0.0}})
    plant = spec.build(0.0001)
    state = plant.initial_state()
    plant.step(state, 50.0)
    rel = []
    for _ in range(10000):
        plant.step(state, 0.0)
        rel.append(state.s[0] - state.s[2])
    rel = np.array(rel)
    crossings = np.sum(np.signbit(rel[1:]) != np.signbit(rel[:-1]))
    assert crossings / 2 == pytest.approx(f_expected, abs=1.0)


def test_two_mass_undamped_energy_is_conserved():
    spec = load_plant("two-mass")
    p = {**spec.params, "n": 0.0, "b1": 0.0, "b2": 0.0, "disturbance_amplitude": 0.0}
    spec = type(spec)(**{**spec.__dict__, "params": p})
    plant = spec.build(DT)
    state = plant.initial_state()
    plant.step(state, 10.0)

    def energy(s):
        x1, v1, x2, v2 = s
        return 0.5 * p["m1"] * v1**2 + 0.5 * p["m2"] * v2**2 + 0.5 * p["k"] * (x1 - x2) ** 2

    e0 = energy(state.s)
    for _ in range(20000):
        plant.step(state, 0.0)
    assert energy(state.s) == pytest.approx(e0, rel=1e-9)


def test_two_mass_is_linear_so_one_substep_is_exact():
    plant1 = load_plant("two-mass").build(DT)
    plant8 = load_plant("two-mass").build(DT, substeps=8)
    assert plant1.substeps == 1
    s1, s8 = plant1.initial_state(), plant8.initial_state()
    for k in range(3000):
        u = 3.0 * math.sin(7 * k * DT) + (1.0 if k % 400 < 200 else -1.0)
        plant1.step(s1, u)
        plant8.step(s8, u)
    # the disturbance is evaluated at substep midpoints; everything else is exact
    assert s1.s[2] == pytest.approx(s8.s[2], rel=1e-6, abs=1e-12)


def test_rigid_substep_halving_changes_tracking_by_less_than_one_percent():
    from helpers import PdController, SineProfile

    from drivectl.controllers.runtime.servo import run
    from drivectl.plant_emulator.sim_axis import SimAxis

    errs = []
    for sub in (10, 20):
        axis = SimAxis(load_plant("rigid-x").build(DT, substeps=sub), resolution=None)
        res = run(axis, PdController(DT), SineProfile(amplitude=0.01, freq=0.5, duration=4.0))
        errs.append(np.abs(res.trace.error).max())
    assert abs(errs[0] - errs[1]) / errs[1] < 0.01


@pytest.mark.parametrize(
    "data, key",
    [
        ({"model": "rigid"}, "params"),
        ({"model": "rigid-ish", "params": {}}, "model"),
        ({"model": "rigid", "params": {"mass": 88.0, "c_pos": 1, "c_neg": 1, "fc_pos": 1}}, "params.fc_neg"),
        ({"model": "rigid", "params": {"mass": -1, "c_pos": 1, "c_neg": 1, "fc_pos": 1, "fc_neg": 1}}, "params.mass"),
        ({"model": "rigid", "params": {"mass": "heavy", "c_pos": 1, "c_neg": 1, "fc_pos": 1, "fc_neg": 1}},
         "params.mass"),
        ({"model": "rigid", "params": {"mass": 1, "c_pos": 1, "c_neg": 1, "fc_pos": 1, "fc_neg": 1, "k": 3}},
         "params.k"),
        ({"model": "rigid", "effort_unit": "A", "params": {}}, "effort_unit"),
        ({"model": "rigid", "params": {"mass": 1, "c_pos": 1, "c_neg": 1, "fc_pos": 1, "fc_neg": 1},
          "effects": [{"name": "backlash", "width": -1e-6}]}, "effects[0].width"),
        ({"model": "rigid", "params": {"mass": 1, "c_pos": 1, "c_neg": 1, "fc_pos": 1, "fc_neg": 1},
          "effects": [{"name": "wobble"}]}, "effects[0].name"),
        ({"model": "two-mass", "params": {"m1": 1, "m2": 1, "k": 1, "n": 0, "b1": 0, "b2": 0},
          "effects": [{"name": "backlash", "width": 1e-5}]}, "effects"),
        ({"model": "rigid", "color": "red", "params": {}}, "color"),
    ],
)
def test_bad_plant_tables_name_the_file_and_key(data, key):
    with pytest.raises(PlantError) as info:
        plant_from_mapping(data, source="bad.toml", name="bad")
    msg = str(info.value)
    assert msg.startswith("bad.toml: ") and key in msg and "\n" not in msg


def test_bad_plant_files(tmp_path):
    with pytest.raises(PlantError, match="no such built-in plant"):
        load_plant("rigid-z")
    garbled = tmp_path / "g.toml"
    garbled.write_text("model = [\n")
    with pytest.raises(PlantError, match=r"g.toml: not valid TOML"):
        load_plant(garbled)
    with pytest.raises(PlantError, match="no such plant file"):
        load_plant(tmp_path / "missing.toml")


def test_plant_spec_round_trips_through_toml(tmp_path):
    spec = load_plant("rigid-y").with_effect("stribeck", excess_force=12.0, velocity=0.002)
    path = tmp_path / "aug.toml"
    path.write_text(spec.to_toml("augmented by a test"))
    back = load_plant(path)
    assert back.params == spec.params and back.effects == spec.effects and back.model == "rigid"


def test_seed_000_tracking_error_is_independent_of_substeps():
    # the issue's accuracy criterion on paper 000's scenario: halving the substeps changes the
    # max tracking error of PID-NFTSM by < 1 % (the linear part is exact, so it barely moves)
    from drivectl.controllers.pid_nftsm import TdePidNftsm
    from drivectl.controllers.runtime.servo import run
    from drivectl.plant_emulator.sim_axis import SimAxis
    from drivectl.profiles.ptp import PointToPoint

    profile = PointToPoint(0.0, 0.065, 0.1, 1.0, 40.0, hold_until=2.5)
    errs = []
    for sub in (2, 4):
        axis = SimAxis(load_plant("two-mass").build(DT, substeps=sub), transport_delay=False, resolution=None,
                       enabled=True)
        errs.append(np.abs(run(axis, TdePidNftsm(DT), profile).trace.error).max())
    assert abs(errs[0] - errs[1]) / errs[1] < 0.01

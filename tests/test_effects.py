"""Each effect of the vocabulary shows its own signature in a simulated trace."""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers import PdController, SineProfile

from drivectl.controllers.runtime.servo import run
from drivectl.plant_emulator.effects import EFFECTS, VOCABULARY, parse_effect
from drivectl.plant_emulator.models import PlantError, load_plant
from drivectl.plant_emulator.sim_axis import SimAxis

DT = 0.001
RIGID = ("rigid-x", "rigid-y")


def _open_loop(spec, efforts, substeps=None):
    plant = spec.build(DT, substeps=substeps)
    state = plant.initial_state()
    xs, vs = [], []
    for u in efforts:
        plant.step(state, u)
        xs.append(plant.position(state))
        vs.append(plant.velocity(state))
    return np.array(xs), np.array(vs), state


def _closed_loop(spec, profile=None, **pd):
    axis = SimAxis(spec.build(DT), resolution=None)
    return run(axis, PdController(DT, **pd), profile or SineProfile(0.01, 0.5, 4.0)).trace


def test_vocabulary_is_the_design_table():
    assert VOCABULARY == ("none", "stribeck", "backlash", "periodic", "mass", "viscous", "coulomb", "delay",
                          "offset", "spring", "resonance", "saturation")
    expected = {
        "stribeck": ("excess_force", "velocity"), "backlash": ("width",), "periodic": ("amplitude", "period"),
        "mass": ("mass",), "viscous": ("scale",), "coulomb": ("force_pos", "force_neg"), "delay": ("delay",),
        "offset": ("force",),
        "spring": ("stiffness",), "resonance": ("frequency", "damping"), "saturation": ("limit",),
    }
    assert {name: e.required for name, e in EFFECTS.items()} == expected


@pytest.mark.parametrize("plant", RIGID)
def test_direction_dependent_friction(plant):
    """coulomb replaces fc+/fc-, viscous scale_neg scales c- alone: the steady speeds under a push say so."""
    base = load_plant(plant)
    c_pos, c_neg = base.params["c_pos"], base.params["c_neg"]
    spec = base.with_effect("coulomb", force_pos=30.0, force_neg=70.0).with_effect("viscous", scale=0.8,
                                                                                    scale_neg=1.3)
    for push, c, fc in ((150.0, 0.8 * c_pos, 30.0), (-150.0, 1.3 * c_neg, 70.0)):
        _, v, _ = _open_loop(spec, np.full(4000, push))
        assert v[-1] == pytest.approx((push - np.sign(push) * fc) / c, rel=1e-6)
    # scale alone still scales both (the existing contract)
    d = base.with_effect("viscous", scale=2.0).design()
    assert (d.bodies[0].c_pos, d.bodies[0].c_neg) == (2 * c_pos, 2 * c_neg)
    # on the two-mass plant (no Coulomb in the model) the friction goes on the table
    two = load_plant("two-mass").with_effect("coulomb", force_pos=0.2, force_neg=0.3).design()
    assert (two.bodies[0].fc_pos, two.bodies[1].fc_pos, two.bodies[1].fc_neg) == (0.0, 0.2, 0.3)


@pytest.mark.parametrize("plant", RIGID)
def test_stribeck_raises_breakaway_to_coulomb_plus_excess(plant):
    base = load_plant(plant)
    fc = base.params["fc_pos"]
    push = np.full(300, fc + 8.0)  # above Coulomb, below Coulomb + excess
    x_nom, _, _ = _open_loop(base, push)
    x_str, _, _ = _open_loop(base.with_effect("stribeck", excess_force=10.0, velocity=0.002), push)
    assert x_nom[-1] > 1e-5 and x_str[-1] == 0.0
    # above breakaway it moves, and at speed >> velocity the extra friction has vanished
    x_fast, v_fast, _ = _open_loop(base.with_effect("stribeck", excess_force=10.0, velocity=0.002),
                                   np.full(3000, fc + 60.0))
    _, v_nom, _ = _open_loop(base, np.full(3000, fc + 60.0))
    assert x_fast[-1] > 0 and v_fast[-1] == pytest.approx(v_nom[-1], rel=1e-4)


@pytest.mark.parametrize("plant", RIGID)
def test_backlash_gives_lost_motion_of_width_at_reversal(plant):
    width = 40e-6
    spec = load_plant(plant).with_effect("backlash", width=width)
    design = spec.design()
    assert [round(b.mass / design.total_mass, 3) for b in design.bodies] == [0.3, 0.7]
    assert design.bodies[1].fc_pos == pytest.approx(0.9 * load_plant(plant).params["fc_pos"])
    # push forward, then backward: the screw travels through the gap before the table follows
    efforts = [200.0] * 200 + [-200.0] * 200
    plant_ = spec.build(DT)
    state = plant_.initial_state()
    rels = []
    for u in efforts:
        plant_.step(state, u)
        rels.append(state.s[0] - state.s[2])
    rels = np.array(rels)
    # in contact the relative position sits at +-width/2 plus the contact compression
    # (~150 N through a ~117 N/um contact: about 1.3 um)
    assert width / 2 < rels[150] < width / 2 + 2e-6
    assert -width / 2 - 2e-6 < rels[-1] < -width / 2
    # closed loop: tracking error jumps at reversals, compared with the nominal plant
    tr_nom = _closed_loop(load_plant(plant))
    tr_bl = _closed_loop(spec)
    late = tr_nom.time > 0.5  # after the start transient of the sine
    assert np.abs(tr_bl.error[late]).max() > 2 * np.abs(tr_nom.error[late]).max()


@pytest.mark.parametrize("plant", RIGID)
def test_periodic_force_appears_at_its_spatial_frequency(plant):
    amp, period = 15.0, 0.004
    spec = load_plant(plant).with_effect("periodic", amplitude=amp, period=period)
    from drivectl.profiles.base import Reference

    class Ramp:  # constant 20 mm/s: the force repeats every period/v = 0.2 s (5 Hz)
        duration = 2.0
        start_position = 0.0

        def sample(self, t):
            return 0.02 * t, np.full_like(t, 0.02), np.zeros_like(t), np.zeros_like(t)

        def at(self, t):
            return Reference(0.02 * t, 0.02)

    tr = _closed_loop(spec, Ramp())
    # steady speed, exactly 8 periods of 5 Hz (no leakage); the PD cancels the periodic force
    window = slice(400, 2000)
    t = tr.time[window]

    def at_5hz(u):
        return abs(2 / len(u) * np.sum((u - u.mean()) * np.exp(-2j * math.pi * 5.0 * t)))

    assert at_5hz(tr.effort[window]) == pytest.approx(amp, rel=0.1)
    tr_nom = _closed_loop(load_plant(plant), Ramp())
    assert at_5hz(tr_nom.effort[window]) < 0.05 * amp


@pytest.mark.parametrize("plant", RIGID)
def test_mass_changes_acceleration(plant):
    base = load_plant(plant)
    f = base.params["fc_pos"] + 300.0
    _, v_nom, _ = _open_loop(base, [f] * 5)
    _, v_mass, _ = _open_loop(base.with_effect("mass", mass=1.5 * base.params["mass"]), [f] * 5)
    # early on viscous friction is negligible: acceleration ~ (f - fc) / m
    assert v_nom[-1] / v_mass[-1] == pytest.approx(1.5, rel=0.01)


@pytest.mark.parametrize("plant", RIGID)
def test_viscous_scale_changes_terminal_speed(plant):
    base = load_plant(plant)
    f = base.params["fc_pos"] + 100.0
    _, v_nom, _ = _open_loop(base, [f] * 6000)
    _, v_sc, _ = _open_loop(base.with_effect("viscous", scale=2.0), [f] * 6000)
    assert v_nom[-1] / v_sc[-1] == pytest.approx(2.0, rel=1e-3)


@pytest.mark.parametrize("plant", RIGID)
def test_delay_shifts_the_response(plant):
    base = load_plant(plant)
    f = [base.params["fc_pos"] + 200.0] * 30
    _, v_nom, _ = _open_loop(base, f)
    _, v_del, _ = _open_loop(base.with_effect("delay", delay=0.005), f)
    assert np.all(v_del[:5] == 0.0) and v_del[6] > 0
    assert v_del[20] == pytest.approx(v_nom[15], rel=1e-6)
    # a fractional delay (2.5 ms) lands between the whole-cycle ones
    _, v_half, _ = _open_loop(base.with_effect("delay", delay=0.0025), f)
    _, v_2, _ = _open_loop(base.with_effect("delay", delay=0.002), f)
    _, v_3, _ = _open_loop(base.with_effect("delay", delay=0.003), f)
    assert v_3[10] < v_half[10] < v_2[10]


@pytest.mark.parametrize("plant", RIGID)
def test_offset_pushes_and_holding_needs_opposite_effort(plant):
    base = load_plant(plant)
    force = base.params["fc_pos"] + 30.0
    x, _, _ = _open_loop(base.with_effect("offset", force=force), [0.0] * 500)
    assert x[-1] > 0  # drifts towards +q with no effort
    x, _, _ = _open_loop(base.with_effect("offset", force=-force), [0.0] * 500)
    assert x[-1] < 0


@pytest.mark.parametrize("plant", RIGID)
def test_spring_pulls_back_to_zero(plant):
    k = 20000.0
    spec = load_plant(plant).with_effect("spring", stiffness=k)
    f = 200.0
    x, v, _ = _open_loop(spec, [f] * 5000)
    fc = load_plant(plant).params["fc_pos"]
    # settles where k q balances the effort less friction (somewhere in the stiction band)
    assert (f - fc) / k - 1e-9 <= x[-1] <= (f + fc) / k
    assert v[-1] == 0.0


@pytest.mark.parametrize("plant", RIGID)
def test_resonance_rings_at_its_frequency(plant):
    freq = 60.0
    base = load_plant(plant)
    # without Coulomb friction, so that the table never sticks (a stuck table would ring at
    # sqrt(k / m1), the motor side alone, instead of the free-free sqrt(k / mu))
    base = type(base)(**{**base.__dict__, "params": {**base.params, "fc_pos": 0.0, "fc_neg": 0.0}})
    spec = base.with_effect("resonance", frequency=freq, damping=0.02)
    # a force pulse excites the mode; the relative velocity rings at the resonance
    plant_ = spec.build(0.0002, substeps=1)
    state = plant_.initial_state()
    vs = []
    for k in range(5000):
        plant_.step(state, 2000.0 if k < 5 else 0.0)
        vs.append(state.s[3] - state.s[1])  # relative velocity: the mode alone
    vs = np.array(vs)
    stop = int(np.argmax(np.abs(vs) < 1e-12)) or len(vs)
    seg = vs[:max(stop, 200)]
    spectrum = np.abs(np.fft.rfft(seg * np.hanning(len(seg)), n=1 << 16))
    f_axis = np.fft.rfftfreq(1 << 16, 0.0002)
    assert f_axis[np.argmax(spectrum)] == pytest.approx(freq, rel=0.03)


@pytest.mark.parametrize("plant", RIGID)
def test_saturation_clips_applied_effort(plant):
    base = load_plant(plant)
    lim = base.params["fc_pos"] + 100.0
    _, v_sat, _ = _open_loop(base.with_effect("saturation", limit=lim), [5000.0] * 5000)
    _, v_lim, _ = _open_loop(base, [lim] * 5000)
    assert v_sat[-1] == pytest.approx(v_lim[-1], rel=1e-9)


def test_effects_apply_to_two_mass_too_where_they_make_sense():
    tm = load_plant("two-mass")
    for name, params in [("stribeck", {"excess_force": 0.5, "velocity": 0.001}), ("periodic",
                         {"amplitude": 0.2, "period": 0.01}), ("mass", {"mass": 2.0}), ("viscous", {"scale": 2.0}),
                         ("delay", {"delay": 0.002}), ("offset", {"force": 0.1}), ("spring", {"stiffness": 10.0}),
                         ("saturation", {"limit": 5.0})]:
        plant = tm.with_effect(name, **params).build(DT)
        state = plant.initial_state()
        for _ in range(100):
            plant.step(state, 3.0)
        assert math.isfinite(state.s[2])
    with pytest.raises(PlantError, match="two bodies"):
        tm.with_effect("backlash", width=1e-5).build(DT)


@pytest.mark.parametrize(
    "text, fragment",
    [("wobble:x=1", "unknown effect"), ("backlash:width=-1", "width: must be > 0"),
     ("backlash", "width: missing"), ("periodic:amplitude=1", "period: missing"),
     ("stribeck:excess_force=abc,velocity=1", "expected a number"), ("delay:lag=0.1", "lag: not a parameter"),
     ("backlash:width", "expected name=value")],
)
def test_effect_flags_are_validated(text, fragment):
    with pytest.raises(PlantError) as info:
        parse_effect(text)
    assert fragment in str(info.value) and "\n" not in str(info.value)


def test_parse_effect():
    assert parse_effect("periodic:amplitude=12,period=0.01") == ("periodic", {"amplitude": 12.0, "period": 0.01})

"""Paper 004's controllers: ASMC with gain laws (11)-(14), PID + DOB, and the rigid-axis identification."""

from __future__ import annotations

import numpy as np
import pytest

from drivectl.controllers.asmc import LAWS, Asmc, default_model, gain_rate
from drivectl.controllers.base import SettingsError
from drivectl.controllers.dob import DisturbanceObserver
from drivectl.controllers.pid import Pid, PidDob
from drivectl.controllers.registry import make_controller
from drivectl.controllers.runtime.servo import run
from drivectl.driver.axis import Feedback
from drivectl.plant_emulator.models import load_plant
from drivectl.plant_emulator.sim_axis import SimAxis
from drivectl.profiles.base import Reference
from drivectl.profiles.circle import Circle
from drivectl.profiles.ptp import PointToPoint
from drivectl.tools.commissioning.identify import identify_rigid
from drivectl.tracefile.metrics import tracking_error

DT = 0.001
RIGID_X = load_plant("rigid-x")


def _circle_run(law: int, **settings):
    profile = Circle(axis="x")
    axis = SimAxis(RIGID_X.build(DT), name="x", initial_position=profile.start_position)
    ctrl = Asmc.for_plant(DT, RIGID_X, axis="x", law=law, **settings)
    return ctrl, run(axis, ctrl, profile)


# --------------------------------------------------------------------------------------------------
# ASMC on the circle
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("law", LAWS)
def test_each_law_tracks_the_circle_on_rigid_x(law):
    # Measured (transport delay + 76.29 nm quantisation on): mean 0.023-0.025 um, max 0.19-0.24 um for
    # every law -- the plant is the model, so what is left is a few encoder counts. The bounds (mean
    # 0.1 um, max 1 um = 13 counts) leave 4x margin and still fail on any real defect: the paper's
    # literal sgn(q') friction compensation gives 93-102 um, a 0.1 mm/s smoothing band 16 um, and a
    # wrong sign or unit in the surface diverges.
    ctrl, res = _circle_run(law)
    assert res.ok, res.detail
    err = tracking_error(res.trace.ref, res.trace.pos)
    assert err["mean"] < 0.1e-6
    assert err["max"] < 1.0e-6
    lo = ctrl.settings.k_in if law == 12 else ctrl.settings.k_min
    assert lo <= ctrl.k <= ctrl.settings.k_bar
    if law == 11:
        assert ctrl.k >= ctrl.settings.k_in  # law 11 never lowers the gain
    if law == 13:
        # inside the boundary layer all run, law 13 lowers k by rho (|s| - delta) ~ 5 /s: to its floor
        assert ctrl.k == ctrl.settings.k_min


def test_measured_velocity_friction_sign_sticks_at_the_reversal():
    # why the default compensates Coulomb friction on sgn(r'): with sgn(q') x sticks at its start
    _, res = _circle_run(14, friction_sign="measured")
    assert tracking_error(res.trace.ref, res.trace.pos)["max"] > 20e-6


# --------------------------------------------------------------------------------------------------
# gain laws, fed by hand
# --------------------------------------------------------------------------------------------------


def test_law14_rises_outside_the_boundary_and_falls_inside():
    c = Asmc(DT, law=14, k_in=50.0, k_bar=100.0, rho=6.0, delta=0.9)
    k = c.k
    for s in (2.0, -3.0, 0.9, -0.9):  # |s| >= delta: k' = rho s^2
        new = c.adapt(s)
        assert new == pytest.approx(k + DT * 6.0 * s * s, rel=1e-12)
        assert new > k
        k = new
    for s in (0.5, -0.8, 0.1):  # |s| < delta: k' = -rho s^2
        new = c.adapt(s)
        assert new == pytest.approx(k - DT * 6.0 * s * s, rel=1e-12)
        assert new < k
        k = new
    assert c.adapt(0.0) == k  # s = 0: no change
    for _ in range(200):  # large |s| drives k to k_bar and no further
        c.adapt(100.0)
    assert c.k == 100.0
    low = Asmc(DT, law=14, k_in=0.01, k_min=0.0, rho=6.0)
    for _ in range(100):
        low.adapt(0.8)
    assert low.k == 0.0  # floored at k_min, never negative


def test_other_laws_by_their_definitions():
    dt, rho, delta = DT, 6.0, 0.9
    assert gain_rate(11, -2.0, rho, delta) == pytest.approx(12.0)
    assert gain_rate(12, 2.0, rho, delta) == pytest.approx(12.0)
    assert gain_rate(12, 0.5, rho, delta) == pytest.approx(-3.0)
    assert gain_rate(13, 2.0, rho, delta) == pytest.approx(24.0)
    assert gain_rate(13, -0.5, rho, delta) == pytest.approx(rho * (0.5 - delta))
    c12 = Asmc(dt, law=12, k_in=50.0)
    c12.adapt(0.5)  # would fall, but k* = k_in is law 12's floor
    assert c12.k == 50.0
    c12.adapt(2.0)
    assert c12.k == pytest.approx(50.0 + dt * 12.0)


@pytest.mark.parametrize("law", LAWS)
def test_step_adapts_like_gain_rate(law):
    # the inlined fast path must apply the same law as gain_rate
    c = Asmc(DT, law=law, k_in=60.0)
    ref = Reference(0.01, 0.02, 0.0)
    for fb in (Feedback(0.0, 0.01 - 5e-6, 0.0201), Feedback(0.0, 0.01 - 2e-5, 0.018)):
        k0 = c.k
        c.step(ref, fb)
        expect = k0 + DT * gain_rate(law, c.s_mm, c.settings.rho, c.settings.delta)
        lo = c.settings.k_in if law == 12 else c.settings.k_min
        assert c.k == pytest.approx(min(max(expect, lo), c.settings.k_bar), rel=1e-12)


def test_smoothing_eq24():
    # switch everything off but h sat(S): gamma = beta = 0 makes S = e', k = 0, no friction model
    model = {"mass": 88.08, "c_pos": 0.0, "c_neg": 0.0, "fc_pos": 0.0, "fc_neg": 0.0}
    c = Asmc(DT, model=model, gamma=0.0, beta=0.0, k_in=0.0, rho=0.0, h=10.0, Delta=0.9)
    for s_mm, sat in ((0.9, 0.5), (-2.7, -0.75), (0.0, 0.0), (900.0, 900.0 / 900.9)):
        c.reset()
        f = c.step(Reference(0.0, s_mm * 1e-3, 0.0), Feedback(0.0, 0.0, 0.0))
        assert f == pytest.approx(10.0 * sat, rel=1e-12, abs=1e-12)


def test_for_plant_picks_table3_column_and_model():
    y = make_controller("asmc", DT, {"law": 13}, plant=load_plant("rigid-y"), axis="y")
    assert isinstance(y, Asmc)
    assert (y.settings.beta, y.settings.delta, y.settings.rho, y.settings.Delta) == (5.0, 1.3, 4.0, 1.3)
    assert y.settings.law == 13 and y.model["mass"] == 97.9
    x = Asmc(DT)
    table2_x = {"mass": 88.08, "c_pos": 467.2, "c_neg": 530.6, "fc_pos": 45.5, "fc_neg": 47.9}
    assert x.model == default_model() == table2_x and x.settings.law == 14


def test_array_gains_match_scalar_runs():
    gammas = np.array([40.0, 50.0, 70.0])
    batch = Asmc(DT, gamma=gammas, law=14)
    singles = [Asmc(DT, gamma=float(g), law=14) for g in gammas]
    pid_batch = PidDob(DT, kp=np.array([2e6, 3e6, 4e6]), d_filter_hz=np.array([0.0, 200.0, 400.0]))
    pid_singles = [PidDob(DT, kp=kp, d_filter_hz=fc) for kp, fc in ((2e6, 0.0), (3e6, 200.0), (4e6, 400.0))]
    rng = np.random.default_rng(1)
    for i in range(50):
        ref = Reference(0.01 + 1e-4 * i, 0.025, -0.01)
        fb = Feedback(i * DT, 0.01 + 1e-4 * i + rng.normal(0, 3e-5), 0.025 + rng.normal(0, 2e-3))
        np.testing.assert_allclose(batch.step(ref, fb), [c.step(ref, fb) for c in singles], rtol=1e-12)
        expect = [c.step(ref, fb) for c in pid_singles]
        np.testing.assert_allclose(pid_batch.step(ref, fb), expect, rtol=1e-12)
    np.testing.assert_allclose(batch.k, [c.k for c in singles], rtol=1e-12)


def test_scalar_path_returns_plain_floats():
    ref, fb = Reference(0.01, 0.02, 0.1), Feedback(0.0, 0.00999, 0.0199)
    for c in (Asmc(DT), Pid(DT), PidDob(DT)):
        assert type(c.step(ref, fb)) is float


# --------------------------------------------------------------------------------------------------
# PID + DOB
# --------------------------------------------------------------------------------------------------


class _Step:
    """A 0.1 mm position step at t = 50 ms (r' = r'' = 0: no derivative kick)."""

    duration = 0.5
    start_position = 0.0

    def sample(self, t):
        t = np.asarray(t, dtype=float)
        z = np.zeros_like(t)
        return np.where(t >= 0.05, 1e-4, 0.0), z, z, z


def test_pid_dob_step_response():
    # Table 1 on rigid-x: w_n = 185 rad/s, zeta = 0.31 -> ~36 % overshoot in theory; measured 34 %,
    # within 2 um of the target 90 ms after the step, 0.06 um off at the end. Without the DOB the
    # axis sticks ~7 um short (Coulomb friction against a slow integrator).
    tr = run(SimAxis(RIGID_X.build(DT)), PidDob.for_plant(DT, RIGID_X), _Step()).trace
    overshoot = tr.pos.max() / 1e-4 - 1.0
    assert 0.2 < overshoot < 0.45
    outside = np.flatnonzero(np.abs(tr.error) > 2e-6)
    assert tr.time[outside[-1]] - 0.05 < 0.15
    assert abs(tr.error[-1]) < 1e-6
    plain = run(SimAxis(RIGID_X.build(DT)), Pid(DT), _Step()).trace
    assert abs(plain.error[-1]) > 3e-6


@pytest.mark.parametrize("speed", [0.02, -0.06])
def test_dob_converges_to_the_friction_at_constant_speed(speed):
    start = -0.04 if speed > 0 else 0.04
    profile = PointToPoint(start, -start, abs(speed), 2.0, 100.0)
    ctrl = PidDob.for_plant(DT, RIGID_X)
    estimates = []

    class Recording:
        dt, name = DT, "rec"

        def reset(self):
            ctrl.reset()

        def step(self, reference, feedback):
            u = ctrl.step(reference, feedback)
            estimates.append(ctrl.disturbance_estimate)
            return u

        def describe(self):
            return ctrl.describe()

    tr = run(SimAxis(RIGID_X.build(DT), initial_position=start), Recording(), profile).trace
    p = RIGID_X.params
    truth = p["fc_pos"] + p["c_pos"] * speed if speed > 0 else -p["fc_neg"] + p["c_neg"] * speed
    t_cruise_end = profile.phase_times[4]  # end of the constant-velocity phase
    k = int(t_cruise_end / DT) - 5
    assert abs(tr.columns["vel_m_s"][k] - speed) < 1e-4
    assert estimates[k] == pytest.approx(truth, rel=0.02)


def test_dob_alone_tracks_a_constant_friction():
    # open loop: m v' = f - g with f = 100 N, g = 60 N; the observer sees f and v only
    m, g, f = 88.08, 60.0, 100.0
    obs = DisturbanceObserver(DT, m, 2 * np.pi * 10.0, 1.0, delay_cycles=0)
    v = 0.0
    obs.step(0.0, v)
    for _ in range(300):  # 0.3 s = 19 time constants of the 10 Hz observer
        v += DT * (f - g) / m
        obs.step(f, v)
    assert obs.g_hat == pytest.approx(g, rel=1e-3)


# --------------------------------------------------------------------------------------------------
# identification
# --------------------------------------------------------------------------------------------------


def test_identification_recovers_rigid_x_within_2_percent():
    def axis_at(start):
        return SimAxis(RIGID_X.build(DT), initial_position=start)

    out = identify_rigid(axis_at, controller_factory=lambda dt: PidDob(dt, ff_mass=100.0))  # wrong mass
    p = RIGID_X.params
    truth = {"m": p["mass"], "c_pos": p["c_pos"], "c_neg": p["c_neg"], "fc_pos": p["fc_pos"],
             "fc_neg": p["fc_neg"]}
    for key, value in truth.items():
        assert out[key] == pytest.approx(value, rel=0.02), key


# --------------------------------------------------------------------------------------------------
# settings
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("cls", "kwargs", "field"),
    [
        (Asmc, {"gamma": -1.0}, "gamma"),
        (Asmc, {"rho": -0.5}, "rho"),
        (Asmc, {"h": -5.0}, "h"),
        (Asmc, {"law": 15}, "law"),
        (Asmc, {"Delta": 0.0}, "Delta"),
        (Asmc, {"k_in": 150.0}, "k_in"),
        (Asmc, {"friction_sign": "guess"}, "friction_sign"),
        (Asmc, {"lambda": 3.0}, "lambda"),
        (Pid, {"kd": -1.0}, "kd"),
        (PidDob, {"kp": -3.0e6}, "kp"),
        (PidDob, {"dob_hz": 0.0}, "dob_hz"),
        (PidDob, {"gain": 1.0}, "gain"),
    ],
)
def test_bad_settings_name_the_field(cls, kwargs, field):
    with pytest.raises(SettingsError, match=rf"\b{field}\b"):
        cls(DT, **kwargs)


def test_bad_model_names_the_key():
    with pytest.raises(SettingsError, match=r"model\.mass"):
        Asmc(DT, model={**default_model(), "mass": -1.0})
    with pytest.raises(SettingsError, match=r"model\.fc_neg"):
        Asmc(DT, model={k: v for k, v in default_model().items() if k != "fc_neg"})


def test_the_library_circle_runs_in_so_y_follows_within_a_micrometre():
    """y (ASMC law 14, the embedded 300 N peak) on the library circle, SimAxis in lockstep: its 0.2 s
    run-in keeps y within 1 um; eq (25)'s step to the full feed at t = 0 costs ~150 um at that peak
    (the momentum 97.9 kg x 25 mm/s at 247 N net: bounded by physics, not by the law)."""
    from drivectl.machine.build import axis_profile, open_machine
    from drivectl.machine.config import load_config

    cfg = load_config()
    ac = cfg.axis("y")
    errors = {}
    for name, profile in (("library", axis_profile(cfg, "y")), ("eq25", Circle("y"))):
        with open_machine(cfg, ["y"], sim=True, start={"y": profile.start_position}) as m:
            ctrl = make_controller(ac.controller, cfg.cycle_s, ac.controller_settings, plant=load_plant("rigid-y"),
                                   axis="y")
            res = run(m.axes["y"], ctrl, profile, limits=ac.limits, duration=1.0)
        assert res.ok, res.detail
        errors[name] = max(abs(r - p) for r, p in zip(res.trace.ref, res.trace.pos, strict=True)) * 1e6
    assert errors["library"] <= 1.0
    assert errors["eq25"] > 140.0

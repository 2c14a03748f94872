"""Paper 000's controllers: TDE + SMC, TDE + VPRL, TDE + PID-NFTSM (simulated time, deterministic)."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import numpy as np
import pytest

from drivectl.controllers.base import ARRAY_OPS, SCALAR_OPS, SettingsError
from drivectl.controllers.pid_nftsm import TdePidNftsm, nftsm_gammas, nftsm_theta
from drivectl.controllers.runtime.servo import run
from drivectl.controllers.tde_smc import TdeSmc
from drivectl.controllers.vprl import TdeVprl
from drivectl.driver.axis import Feedback
from drivectl.plant_emulator.models import load_plant
from drivectl.plant_emulator.sim_axis import SimAxis
from drivectl.profiles.base import Reference
from drivectl.profiles.ptp import PointToPoint

DT = 0.001
ALL = (TdeSmc, TdeVprl, TdePidNftsm)
SETTINGS_DIR = Path(__file__).resolve().parent.parent / "controllers" / "settings"


def _axis() -> SimAxis:
    """The paper's simulation: two-mass plant, no transport delay, exact sensor."""
    return SimAxis(load_plant("two-mass").build(DT), transport_delay=False, resolution=None, enabled=True)


def _seed000() -> PointToPoint:
    return PointToPoint(0.0, 0.065, 0.1, 1.0, 40.0, hold_until=2.5)


class _Step:
    """A position step of ``height`` at ``t0`` (velocity and acceleration references 0)."""

    name = "step"

    def __init__(self, height: float, t0: float, duration: float):
        self.height, self.t0, self.duration = height, t0, duration
        self.start_position = 0.0

    def sample(self, t):
        t = np.asarray(t, dtype=float)
        zero = np.zeros_like(t)
        return np.where(t >= self.t0, self.height, 0.0), zero, zero.copy(), zero.copy()

    def at(self, t: float) -> Reference:
        return Reference(self.height if t >= self.t0 else 0.0)


# --------------------------------------------------------------------------------------------------
# the paper's comparison


def test_seed000_order_and_paper_figures():
    profile = _seed000()
    paper = {"smc": 68.2, "vprl": 28.4, "pid-nftsm": 13.8}
    got = {}
    for cls in ALL:
        res = run(_axis(), cls(DT), profile, duration=2.5)
        assert res.ok, (cls.name, res.detail)
        got[cls.name] = float(np.max(np.abs(res.trace.error))) * 1e6
    assert got["pid-nftsm"] < got["vprl"] < got["smc"], got
    for name, figure in paper.items():
        assert 0.75 * figure <= got[name] <= 1.25 * figure, (name, got[name], figure)


def test_pid_nftsm_effort_is_smoother_than_the_baselines():
    # the paper's second claim (Figs 6-8): the PID-NFTSM voltage does not chatter
    profile = _seed000()
    rough = {}
    for cls in ALL:
        effort = run(_axis(), cls(DT), profile, duration=2.5).trace.effort
        rough[cls.name] = float(np.sqrt(np.mean(np.diff(effort) ** 2)))
    assert rough["pid-nftsm"] < 0.5 * min(rough["smc"], rough["vprl"]), rough


@pytest.mark.parametrize("cls, tol_um", [(TdeSmc, 40.0), (TdeVprl, 20.0), (TdePidNftsm, 20.0)])
def test_1mm_step_settles_with_bounded_overshoot(cls, tol_um):
    res = run(_axis(), cls(DT), _Step(1e-3, 0.01, 1.5), duration=1.5)
    assert res.ok
    tr = res.trace
    overshoot = (tr.pos.max() - 1e-3) / 1e-3
    assert overshoot < 0.10
    # SMC keeps chattering (its eps2 sgn(s) term) at ~20 um, the others settle to a few um
    assert np.max(np.abs(tr.error[tr.time >= 1.25])) < tol_um * 1e-6


@pytest.mark.parametrize("cls", ALL)
def test_reset_restores_the_initial_behaviour(cls):
    ctrl = cls(DT)
    first = run(_axis(), ctrl, _seed000(), duration=0.5).trace  # run() calls reset() itself
    second = run(_axis(), ctrl, _seed000(), duration=0.5).trace
    assert np.array_equal(first.effort, second.effort)
    # and an explicit reset after stepping by hand
    ref, fb = Reference(1e-4, 0.01, 0.1), Feedback(0.0, 0.0, 0.0)
    ctrl.reset()
    a = [ctrl.step(ref, Feedback(k * DT, 1e-6 * k, 1e-3)) for k in range(20)]
    ctrl.step(ref, fb)
    ctrl.reset()
    b = [ctrl.step(ref, Feedback(k * DT, 1e-6 * k, 1e-3)) for k in range(20)]
    assert a == b


@pytest.mark.parametrize("cls", ALL)
def test_scalar_path_returns_plain_floats(cls):
    ctrl = cls(DT)
    assert ctrl.ops is SCALAR_OPS
    for k in range(5):
        u = ctrl.step(Reference(1e-4 * k, 0.01, 0.1), Feedback(k * DT, 1e-5 * k, 0.005))
        assert type(u) is float
    # numpy scalars in the settings are taken as floats (no numpy-scalar maths in the float path)
    ctrl = cls(DT, m_tilde=np.float64(0.07))
    assert type(ctrl.step(Reference(1e-4), Feedback(0.0, 0.0, 0.0))) is float


# --------------------------------------------------------------------------------------------------
# settings


def test_beta_out_of_range_names_the_field():
    with pytest.raises(SettingsError) as exc:
        TdePidNftsm(DT, beta=1.2)
    assert str(exc.value) == "controller pid-nftsm: beta: must be in (0.5, 1), got 1.2"


@pytest.mark.parametrize(
    "cls, key, value",
    [
        (TdeSmc, "eps1", -1.0),
        (TdeSmc, "c", -15.0),
        (TdeVprl, "alpha2", -60.0),
        (TdeVprl, "r2", 1.0),
        (TdePidNftsm, "kp", -500.0),
        (TdePidNftsm, "kd", 0.0),
        (TdePidNftsm, "mu", 0.0),
        (TdePidNftsm, "mu", 1.0),
        (TdePidNftsm, "mu", 0),
        (TdePidNftsm, "beta", 0.5),
        (TdePidNftsm, "phi", 0.0),
        (TdePidNftsm, "m_tilde", 0.0),
        (TdeSmc, "m_tilde", -0.06),
        (TdeVprl, "accel_filter_hz", -40.0),
        (TdePidNftsm, "accel_source", "encoder"),
        (TdePidNftsm, "kp", np.array([500.0, -1.0])),
        (TdeSmc, "eps2", "1"),
    ],
)
def test_bad_setting_raises_one_line_naming_the_field(cls, key, value):
    with pytest.raises(SettingsError) as exc:
        cls(DT, **{key: value})
    msg = str(exc.value)
    assert msg.startswith(f"controller {cls.name}: {key}: ")
    assert "\n" not in msg


def test_unknown_setting_is_an_error():
    with pytest.raises(SettingsError) as exc:
        TdeVprl(DT, gamma=1.0)
    msg = str(exc.value)
    assert msg.startswith("controller vprl: gamma: unknown setting")
    assert "\n" not in msg


def test_paper_defaults():
    s = TdePidNftsm(DT).settings
    assert (s.lambda1, s.lambda2, s.beta, s.phi) == (1.0, 1.0, 0.8, 0.001)
    assert (s.kp, s.ki, s.kd, s.rho1, s.rho2, s.mu, s.a1) == (500.0, 20.0, 6.0, 120.0, 80.0, 0.8, 3.0)
    assert (s.eta, s.big_delta, s.delta, s.k1max) == (1.0, 2.0, 0.05, 5.0)
    s = TdeSmc(DT).settings
    assert (s.c, s.eps1, s.eps2) == (15.0, 120.0, 1.0)
    s = TdeVprl(DT).settings
    assert (s.c, s.alpha1, s.alpha2, s.r1, s.r2) == (15.0, 120.0, 60.0, 2.0, 0.7)
    for cls in ALL:
        assert cls.origin == "paper 000"
    assert [c.name for c in ALL] == ["smc", "vprl", "pid-nftsm"]


@pytest.mark.parametrize("cls", ALL)
def test_settings_files_hold_the_defaults(cls):
    path = SETTINGS_DIR / f"{cls.name}.toml"
    with path.open("rb") as f:
        table = tomllib.load(f)
    assert cls(DT, table).settings.as_dict() == cls.SettingsClass().as_dict()


# --------------------------------------------------------------------------------------------------
# batch mode: arrays of gains, the same code


def _synthetic_feedback(n_members: int, cycles: int):
    """References and per-member feedback that visit every branch of the laws.

    Errors swing through +-phi (1 mm) with both signs; every 37th cycle a 1.5 m/s velocity error
    drives |s| above 1 (VPRL's r1 branch) and |s2| above Delta (the adaptive law's outer band).
    """
    t = np.arange(cycles) * DT
    r = 0.01 * np.sin(2 * np.pi * 2.0 * t)
    rv = 0.01 * 2 * np.pi * 2.0 * np.cos(2 * np.pi * 2.0 * t)
    ra = -0.01 * (2 * np.pi * 2.0) ** 2 * np.sin(2 * np.pi * 2.0 * t)
    amp = np.array([2e-3, 5e-4, 1.5e-3])[:n_members, None]
    freq = np.array([3.0, 7.0, 5.0])[:n_members, None]
    e = amp * np.sin(2 * np.pi * freq * t + np.arange(n_members)[:, None])
    ed = amp * 2 * np.pi * freq * np.cos(2 * np.pi * freq * t + np.arange(n_members)[:, None])
    x = r - e
    v = rv - ed
    v[:, ::37] += 1.5
    refs = [Reference(float(r[k]), float(rv[k]), float(ra[k])) for k in range(cycles)]
    return t, refs, x, v


@pytest.mark.parametrize(
    "cls, gains",
    [
        (TdeSmc, {"c": [10.0, 15.0, 20.0], "eps2": [0.5, 1.0, 2.0], "m_tilde": [0.05, 0.06, 0.07]}),
        (
            TdeVprl,
            {"alpha1": [100.0, 120.0, 140.0], "r1": [1.5, 2.0, 2.5], "r2": [0.5, 0.7, 0.9], "c": 15.0},
        ),
        (
            TdePidNftsm,
            {
                "kp": [400.0, 500.0, 650.0],
                "beta": [0.7, 0.8, 0.9],
                "mu": [0.6, 0.8, 0.95],
                "m_tilde": [0.1, 0.15, 0.2],
                "accel_filter_hz": [0.0, 40.0, 60.0],
                "k1_init": [0.0, 2.5, 5.0],
            },
        ),
    ],
)
def test_batch_of_gains_matches_scalar_controllers(cls, gains):
    n, cycles = 3, 400
    t, refs, x, v = _synthetic_feedback(n, cycles)
    batch = cls(DT, **{k: np.asarray(g) if isinstance(g, list) else g for k, g in gains.items()})
    assert batch.ops is ARRAY_OPS
    singles = [
        cls(DT, **{k: (g[i] if isinstance(g, list) else g) for k, g in gains.items()}) for i in range(n)
    ]
    for k in range(cycles):
        u = batch.step(refs[k], Feedback(t[k], x[:, k], v[:, k]))
        assert np.shape(u) == (n,)
        expected = [
            singles[i].step(refs[k], Feedback(t[k], float(x[i, k]), float(v[i, k]))) for i in range(n)
        ]
        np.testing.assert_allclose(u, expected, rtol=1e-12, atol=1e-12)


def test_batch_adaptive_gain_visits_both_domains():
    # eq (15)'s two branches are both exercised by the synthetic feedback above
    t, refs, x, v = _synthetic_feedback(3, 400)
    ctrl = TdePidNftsm(DT, kp=np.array([400.0, 500.0, 650.0]))
    k1 = []
    for k in range(400):
        ctrl.step(refs[k], Feedback(t[k], x[:, k], v[:, k]))
        k1.append(np.array(ctrl.k1_hat))
    k1 = np.array(k1)
    assert (k1 <= 0.0).any() and ((k1 > 0.0) & (k1 < 5.0)).any()


# --------------------------------------------------------------------------------------------------
# eq (7): the NFTSM function


def test_theta_is_continuous_with_its_slope_at_phi():
    beta, phi = 0.8, 0.001
    g1, g2 = nftsm_gammas(beta, phi)
    for sign in (1.0, -1.0):
        inner = nftsm_theta(sign * phi * (1 - 1e-12), beta, phi, g1, g2)
        outer = nftsm_theta(sign * phi * (1 + 1e-12), beta, phi, g1, g2)
        at = nftsm_theta(sign * phi, beta, phi, g1, g2)
        assert at[0] == pytest.approx(sign * phi**beta, rel=1e-12)
        assert at[1] == pytest.approx(beta * phi ** (beta - 1), rel=1e-12)
        assert inner[0] == pytest.approx(outer[0], rel=1e-9)
        assert inner[1] == pytest.approx(outer[1], rel=1e-9)


def test_theta_branches():
    beta, phi = 0.8, 0.001
    g1, g2 = nftsm_gammas(beta, phi)
    assert g1 == pytest.approx((2 - beta) * phi ** (beta - 1))
    assert g2 == pytest.approx((beta - 1) * phi ** (beta - 2))
    for e in (3e-3, -0.02, 0.5):  # |e| >= phi: sig(e)^beta
        theta, slope = nftsm_theta(e, beta, phi, g1, g2)
        assert theta == pytest.approx(math.copysign(abs(e) ** beta, e), rel=1e-12)
        assert slope == pytest.approx(beta * abs(e) ** (beta - 1), rel=1e-12)
    for e in (4e-4, -7e-4, 1e-9):  # |e| < phi: gamma1 e + gamma2 sgn(e) e^2, nonsingular
        theta, slope = nftsm_theta(e, beta, phi, g1, g2)
        assert theta == pytest.approx(g1 * e + g2 * math.copysign(e * e, e), rel=1e-12)
        assert slope == pytest.approx(g1 + 2 * g2 * abs(e), rel=1e-12)
    assert nftsm_theta(0.0, beta, phi, g1, g2) == (0.0, g1)  # no singularity at e = 0
    # the slope is the derivative of theta (eq 10), on both sides of phi
    for e in (5e-4, 2e-3):
        h = 1e-9
        num = (nftsm_theta(e + h, beta, phi, g1, g2)[0] - nftsm_theta(e - h, beta, phi, g1, g2)[0]) / (2 * h)
        assert num == pytest.approx(nftsm_theta(e, beta, phi, g1, g2)[1], rel=1e-5)
    # array maths gives the same, with no warnings from the branch not taken (e = 0 included)
    es = np.array([-2e-3, -phi, -1e-4, 0.0, 1e-4, phi, 2e-3])
    with np.errstate(all="raise"):
        th, sl = nftsm_theta(es, beta, phi, g1, g2, ARRAY_OPS)
    for i, e in enumerate(es):
        s_th, s_sl = nftsm_theta(float(e), beta, phi, g1, g2)
        assert th[i] == pytest.approx(s_th, rel=1e-13, abs=1e-300)
        assert sl[i] == pytest.approx(s_sl, rel=1e-13)


def test_effort_is_continuous_across_phi():
    # a fresh controller's first effort as the error crosses |e| = phi: no jump from eq (7)'s switch
    phi = 0.001
    efforts = []
    for e in (phi * (1 - 1e-10), phi * (1 + 1e-10)):
        ctrl = TdePidNftsm(DT)
        efforts.append(ctrl.step(Reference(0.01 + e, 0.02, 0.0), Feedback(0.0, 0.01, 0.01)))
    assert efforts[0] == pytest.approx(efforts[1], rel=1e-7)


# --------------------------------------------------------------------------------------------------
# TDE details


def test_tde_estimate_is_zero_until_t_above_2dt_then_second_difference():
    ctrl = TdeSmc(DT)
    xs = [0.0, 1e-6, 4e-6, 9e-6, 16e-6]  # x = t^2 / 2 * 2 m/s^2: x'' = 2 m/s^2
    accs = []
    for x in xs:
        ctrl._accel(x, 0.0)
        accs.append(ctrl._acc)
    assert accs[:3] == [0.0, 0.0, 0.0]
    assert accs[3] == pytest.approx(2.0, rel=1e-6)
    assert accs[4] == pytest.approx(2.0, rel=1e-6)


def test_tde_uses_its_own_previous_output():
    ctrl = TdeSmc(DT, m_tilde=0.5)
    ref = Reference(1e-4, 0.0, 0.0)
    fb = Feedback(0.0, 0.0, 0.0)  # standing still: x2'' estimate stays 0
    u0 = ctrl.step(ref, fb)
    u1 = ctrl.step(ref, fb)
    # same u_c both cycles, so u1 = m~ u_c + u0 = 2 u0
    assert u1 == pytest.approx(2 * u0, rel=1e-15)


def test_low_pass_is_first_order_with_the_exact_pole():
    ctrl = TdePidNftsm(DT, accel_filter_hz=40.0)
    assert ctrl._alpha == pytest.approx(1 - math.exp(-2 * math.pi * 40.0 * DT), rel=1e-15)
    assert TdePidNftsm(DT, accel_filter_hz=0.0)._alpha == 1.0

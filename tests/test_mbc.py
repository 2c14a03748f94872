"""The model-based controller (controllers/mbc.py), its model inverse and the robust check.

Simulated time, deterministic, each test well under a second or two."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from drivectl.controllers.base import SettingsError
from drivectl.controllers.linear_model import LinearModel
from drivectl.controllers.mbc import Mbc
from drivectl.controllers.registry import make_controller
from drivectl.controllers.robust import check_corners, corners, spectral_radius
from drivectl.controllers.runtime.servo import run
from drivectl.plant_emulator.models import load_plant
from drivectl.plant_emulator.sim_axis import SimAxis
from drivectl.profiles.ptp import PointToPoint

DT = 0.001


def _seed000() -> PointToPoint:
    return PointToPoint(0.0, 0.065, 0.1, 1.0, 40.0, hold_until=1.2)


def _quiet_two_mass():
    spec = load_plant("two-mass")
    return dataclasses.replace(spec, params={**spec.params, "disturbance_amplitude": 0.0})


def _open_loop(spec, profile, ctrl: Mbc | None = None) -> np.ndarray:
    """The feed-forward alone (no feedback) on the exact plant, with the one-cycle transport delay:
    the error r - x at every sample."""
    ctrl = ctrl or Mbc(DT, model=spec)
    n = int(round(profile.duration / DT)) + 1
    t = np.arange(n) * DT
    uff, fk = ctrl.feedforward(profile, t)
    plant = spec.build(DT)
    state = plant.initial_state(profile.start_position)
    y = np.empty(n)
    in_flight = 0.0
    for k in range(n):
        y[k] = plant.position(state)
        plant.step(state, in_flight)  # the command of cycle k-1 acts over [k, k+1]
        in_flight = uff[k] + fk[k]
    return profile.sample(t)[0] - y


def test_inverse_reproduces_the_reference_on_the_exact_two_mass_plant() -> None:
    e = _open_loop(_quiet_two_mass(), _seed000())
    # 65 mm at 0.1 m/s through the 89 Hz mode, open loop: within half a micrometre at every sample
    assert np.max(np.abs(e)) < 0.5e-6
    # and it ends where the reference ends (no lost momentum, no drift)
    assert abs(e[-1]) < 0.2e-6


def _open_loop_snap(snap: str) -> tuple[np.ndarray, np.ndarray]:
    spec, profile = _quiet_two_mass(), _seed000()
    ctrl = Mbc(DT, {"snap": snap}, model=spec)
    t = np.arange(int(round(profile.duration / DT)) + 1) * DT
    uff, _ = ctrl.feedforward(profile, t)
    return _open_loop(spec, profile, ctrl), uff


def test_snap_spread_smooths_the_effort_for_little_tracking() -> None:
    # the exact inverse holds the snap impulse of every jerk switch in one cycle (a 0.2 V pulse at 40 m/s^3);
    # spread over the window the model sets (3.2 ms: 1 / (w_m^2 dt)) the effort's first difference drops
    # by a third and more, the table stays within 0.15 um of where the exact inverse puts it (open loop:
    # the mode rings a little, the spread pulse's spectrum at 89 Hz being 13 % below the impulse's)
    assert LinearModel.from_spec(_quiet_two_mass()).snap_spread(DT) == pytest.approx(3.18e-3, rel=0.01)
    assert LinearModel.from_spec(load_plant("rigid-x")).snap_spread(DT) == 0.0
    e_exact, u_exact = _open_loop_snap("exact")
    e_spread, u_spread = _open_loop_snap("spread")
    du = {k: float(np.sqrt(np.mean(np.diff(u) ** 2))) for k, u in (("exact", u_exact), ("spread", u_spread))}
    assert du["spread"] < 0.7 * du["exact"]
    assert np.max(np.abs(e_spread - e_exact)) < 0.15e-6
    # the spread keeps the impulse's momentum and first moment: no lasting offset
    assert abs(e_spread[-1]) < 0.2e-6


def test_no_feedback_kick_before_the_first_command_acts() -> None:
    # the first command acts one cycle after the run starts: the reference state of that instant is where
    # the plant was, so on the exact plant the feedback's share of the first command is nil (it was 0.18 V,
    # then -0.16 V: the feedback pushing against the feed-forward's own catching up)
    spec, profile = _quiet_two_mass(), _seed000()
    ctrl = Mbc(DT, model=spec)
    res = run(SimAxis(spec.build(DT), resolution=76.29e-9), ctrl, profile)
    assert res.ok
    t = res.trace.columns["time_s"]
    uff, fk = ctrl.feedforward(profile, t)
    feedback = res.trace.columns["effort"] - uff - fk
    assert np.max(np.abs(feedback[:3])) < 0.03


def test_inverse_with_friction_on_the_exact_rigid_plant() -> None:
    # rigid-x: direction-dependent Coulomb and viscous friction, compensated in the feed-forward
    e = _open_loop(load_plant("rigid-x"), _seed000())
    assert np.max(np.abs(e)) < 0.2e-6
    # without the friction compensation the same run is millimetres off: the test can fail
    spec = load_plant("rigid-x")
    lm = LinearModel.from_spec(spec)
    assert lm.has_known_forces


def test_kalman_filter_converges_on_a_known_disturbance() -> None:
    # the model knows no offset; the axis has a 30 N constant force: the filter must find it, and the
    # loop must hold the position against it (no Coulomb friction: its stiction would hold the 30 N)
    base = load_plant("rigid-x")
    spec = dataclasses.replace(base, params={**base.params, "fc_pos": 0.0, "fc_neg": 0.0})
    plant = spec.with_effect("offset", force=30.0)
    ctrl = Mbc(DT, model=spec)
    axis = SimAxis(plant.build(DT), resolution=76.29e-9)
    hold = PointToPoint(0.0, 0.0, 0.1, 1.0, 40.0, hold_until=1.0)
    res = run(axis, ctrl, hold)
    assert res.ok
    # d enters like the effort: the estimate is the force itself (and -d is what the command adds)
    assert ctrl.disturbance_estimate == pytest.approx(30.0, rel=0.02)
    e = res.trace.columns["ref_m"] - res.trace.columns["pos_m"]
    assert np.max(np.abs(e[-200:])) < 0.2e-6


def test_kalman_filter_tracks_paper_000_sinusoid() -> None:
    spec = load_plant("two-mass")  # d1 = d2 = 0.1 sin(pi t): the model names it, the filter models it
    ctrl = Mbc(DT, model=spec)
    axis = SimAxis(spec.build(DT), resolution=76.29e-9)
    seen = []
    step = ctrl.step

    def spy(reference, feedback):
        u = step(reference, feedback)
        seen.append((axis.drive.state.t, ctrl.disturbance_estimate))
        return u

    ctrl.step = spy
    res = run(axis, ctrl, _seed000())
    assert res.ok
    t, d_hat = np.array(seen[-300:]).T
    assert np.max(np.abs(d_hat - 0.1 * np.sin(np.pi * t))) < 0.005  # 5 % of the amplitude
    e = res.trace.columns["ref_m"] - res.trace.columns["pos_m"]
    assert np.max(np.abs(e)) < 1.5e-6  # nominal seed-000 under the disturbance, 76 nm counts


def test_robust_check_flags_a_known_unstable_corner() -> None:
    nominal = load_plant("two-mass")
    cs = corners(nominal)
    assert len(cs) == 64
    assert len(corners(nominal, count=10)) == 10
    # a fast observer that trusts the mode's model: stable on the nominal plant, unstable where the
    # mode is 10 % higher (masses -10 %, stiffness +10 %)
    fast = {"observer_hz": 40.0, "bandwidth_hz": 20.0, "mode_damping": 0.0}
    ctrl = Mbc(DT, fast, model=nominal)
    assert spectral_radius(ctrl, nominal) < 1.0
    stiff = next(c for c in cs if c.name.endswith("--+---"))
    assert spectral_radius(ctrl, stiff) > 1.0
    results = check_corners(lambda spec: ctrl, cs)  # one design (the nominal model) on every corner
    assert not all(r.stable for r in results)
    assert not next(r for r in results if r.name == stiff.name).stable
    # the default design holds on every corner
    designed = Mbc(DT, model=nominal)
    default = check_corners(lambda spec: designed, cs)
    assert all(r.stable for r in default)


def test_robust_simulation_check_flags_a_run_that_does_not_settle() -> None:
    spec = load_plant("rigid-x")  # Coulomb friction: not a linear loop, so the check simulates
    one = corners(spec, count=1)
    t = np.arange(2000) * DT
    hold = np.where(t < 1.0, 1e-4, 0.0)  # the reference moves for 1 s, then holds
    decaying = 40e-6 * np.exp(-t / 0.1)
    ringing = 40e-6 * np.sin(2 * np.pi * 89 * t)  # a limit cycle on the mode: it never settles
    growing = 1e-6 * np.exp(t / 0.3)
    runs = {"decaying": (True, decaying, hold), "ringing": (True, ringing, hold), "growing": (True, growing, hold),
            "stopped": (False, decaying, hold), "moving": (True, ringing, np.full_like(t, 1e-4))}
    stable = {k: check_corners(lambda s: object(), one, simulate=lambda s, r=r: r)[0].stable for k, r in runs.items()}
    # a steady error while the reference still moves is tracking, not instability
    assert stable == {"decaying": True, "ringing": False, "growing": False, "stopped": False, "moving": True}


def test_settings_are_validated() -> None:
    with pytest.raises(SettingsError, match=r"^controller mbc: bandwidth_hz: must be in \[0, 200\], got -1"):
        Mbc(DT, {"bandwidth_hz": -1.0})
    # 0 = from the model: resolved to a number the trace and tune see
    assert Mbc(DT, {"bandwidth_hz": 0.0}, model=load_plant("rigid-x")).settings.bandwidth_hz == 80.0
    assert Mbc(DT, model=load_plant("two-mass")).settings.as_dict()["observer_hz"] == 20.0
    with pytest.raises(SettingsError, match=r"controller mbc: bogus: unknown setting"):
        Mbc(DT, {"bogus": 1.0})
    with pytest.raises(SettingsError, match=r"friction_ff: must be one of"):
        Mbc(DT, {"friction_ff": "yes"})
    with pytest.raises(SettingsError, match=r"^machine.toml: axes.z: controller mbc: observer_hz"):
        make_controller("mbc", DT, {"observer_hz": -1.0}, plant=load_plant("two-mass"),
                        source="machine.toml: axes.z")
    for exc in (SettingsError("x"),):
        assert "\n" not in str(exc)


def test_without_preview_the_controller_still_tracks() -> None:
    # a caller that never calls prepare(): the reference is extrapolated from its derivatives
    spec = load_plant("two-mass")
    ctrl = Mbc(DT, model=spec)
    ctrl.prepare = lambda profile, times: None
    res = run(SimAxis(spec.build(DT), resolution=76.29e-9), ctrl, _seed000())
    assert res.ok
    e = res.trace.columns["ref_m"] - res.trace.columns["pos_m"]
    assert np.max(np.abs(e)) < 2e-6  # 0.81 um against 0.50 with the preview

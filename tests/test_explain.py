"""`drivectl explain`: none on clean traces, each effect named and fitted, bad input, JSON, the TOML round trip.

Traces are made by bench/explain_traces.py exactly as the issue prescribes (SimAxis with 76.29 nm
quantisation, force noise, the one-cycle transport delay; a controller that knows only the nominal
plant; a back-and-forth commissioning profile). The full set is bench/explain_score.py.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

from explain_traces import Case, make_trace  # noqa: E402

from drivectl.plant_emulator.models import load_plant  # noqa: E402
from drivectl.tools.explain.core import (  # noqa: E402
    PARAM_NAMES,
    ExplainError,
    add_explain_parser,
    cmd_explain,
    explain,
    gaps_of,
    prepare,
    window_mse,
)
from drivectl.tools.explain.sim import BatchSim, make_windows  # noqa: E402
from drivectl.tracefile.format import Trace  # noqa: E402

PROFILE = {"start": 0.0, "distance": 0.05, "speeds": [0.02, 0.06, 0.1], "amax": 0.5, "jmax": 20.0, "dwell": 0.3,
           "repeats": 1}
PROFILE_B = {"start": -0.02, "distance": -0.04, "speeds": [0.03, 0.08], "amax": 0.8, "jmax": 30.0, "dwell": 0.4,
             "repeats": 2}

#: one trace per effect, mid-range magnitudes, alternating plants, controllers and profiles
EFFECT_CASES = [
    ("stribeck", {"excess_force": 15.0, "velocity": 0.001}, "rigid-x", "pid-dob", {}, PROFILE),
    # named right since the two best windows count as the third instead of being left out (docs/explain.md)
    ("backlash", {"width": 40e-6}, "rigid-x", "pid", {}, PROFILE),
    ("periodic", {"amplitude": 12.0, "period": 0.008}, "rigid-x", "pid", {}, PROFILE_B),
    ("mass", {"mass": 115.0}, "rigid-y", "pid-dob", {}, PROFILE),
    ("viscous", {"scale": 1.6}, "rigid-x", "asmc", {}, PROFILE),
    ("delay", {"delay": 0.002}, "rigid-y", "pid", {}, PROFILE),
    ("offset", {"force": -20.0}, "rigid-x", "pid", {"d_filter_hz": 200.0, "ff_mass": 80.0}, PROFILE_B),
    ("spring", {"stiffness": 8000.0}, "rigid-y", "asmc", {}, PROFILE_B),
    ("resonance", {"frequency": 40.0, "damping": 0.05}, "rigid-y", "pid",
     {"kp": 5.0e5, "kd": 2.0e3, "ki": 2.0e4, "d_filter_hz": 30.0, "ff_mass": 88.0}, PROFILE),
    ("saturation", {"limit": 0.6}, "rigid-y", "pid-dob", {}, PROFILE),
]


def _case(effect, params, plant, controller, settings, profile, seed=11, noise=1.0, extra=None) -> Case:
    return Case(effect, dict(params), plant, controller, dict(settings), dict(profile), noise, seed, dict(extra or {}))


@pytest.fixture(scope="module")
def clean_traces() -> dict[str, Trace]:
    out = {}
    for i, (ctrl, settings) in enumerate((("asmc", {}), ("pid", {"d_filter_hz": 200.0, "ff_mass": 80.0}))):
        tr, _ = make_trace(_case("none", {}, ("rigid-x", "rigid-y")[i], ctrl, settings, PROFILE, seed=100 + i,
                                 noise=1.5))
        out[ctrl] = tr
    return out


@pytest.mark.parametrize("controller", ["asmc", "pid"])
def test_clean_trace_is_none(clean_traces, controller):
    tr = clean_traces[controller]
    plant = "rigid-x" if controller == "asmc" else "rigid-y"
    res = explain(tr, load_plant(plant))
    assert res.effect == "none", res.report
    assert res.params == {} and res.gap_after == res.gap_before
    assert res.gap_before < 20e-6  # the noise floor of a 1.5 N force noise: a few um


@pytest.mark.parametrize("effect,params,plant,controller,settings,profile", EFFECT_CASES,
                         ids=[c[0] if isinstance(c, tuple) and isinstance(c[0], str) else c.values[0]
                              for c in EFFECT_CASES])
def test_effect_named_and_fitted(effect, params, plant, controller, settings, profile, tmp_path):
    extra = {"phase": 1.0} if effect == "periodic" else {}
    tr, truth = make_trace(_case(effect, params, plant, controller, settings, profile, extra=extra))
    res = explain(tr, load_plant(plant), out_dir=tmp_path, stem="t")
    assert res.effect == effect, res.report
    for k in PARAM_NAMES[effect]:
        # the Stribeck velocity trades against the excess along a ridge of the gap (the impulse of
        # the extra friction through a start is ~ excess x velocity); docs/explain.md
        rel = 0.35 if (effect, k) == ("stribeck", "velocity") else 0.25
        assert res.params[k] == pytest.approx(truth[k], rel=rel), (k, res.params, truth)
    assert res.gap_after < 0.5 * res.gap_before
    # the augmented plant loads back and carries the effect
    spec = load_plant(tmp_path / "t.plant.toml")
    assert spec.effects[-1][0] == effect
    assert (tmp_path / "t.png").stat().st_size > 10_000
    assert "gap before" in (tmp_path / "t.report.txt").read_text()


def test_batch_simulation_equals_plant_step(clean_traces):
    """The vectorised windows repeat Plant.step exactly (rigid with effects, and two bodies)."""
    tr = clean_traces["asmc"]
    vel = tr.columns["vel_m_s"]
    base = load_plant("rigid-x")
    for spec in (base.with_effect("stribeck", excess_force=10.0, velocity=0.003),
                 base.with_effect("delay", delay=0.0017), base.with_effect("periodic", amplitude=5, period=0.01),
                 base.with_effect("backlash", width=20e-6)):
        plant = spec.build(0.001)
        win = make_windows(tr.pos, vel, tr.effort, 0.001, 150, starts=np.array([300, 2000, 4100]))
        sim = BatchSim([plant]).run(win)
        init = BatchSim([plant])._initial(win)
        for w in range(3):
            st = plant.initial_state()
            st.s = [float(a[w, 0]) for a in init]
            st.t = float(win.t0[w])
            if plant.history_len:
                st.history = list(win.applied[w, win.history - plant.history_len:win.history])
            xs = []
            for j in range(150):
                plant.step(st, float(win.applied[w, win.history + j]))
                xs.append(plant.position(st))
            assert np.max(np.abs(np.array(xs) - sim[w, 0])) < 1e-12


def test_velocity_column_is_optional(clean_traces):
    """A recorder with only the four required columns: velocity from the positions, still none."""
    tr = clean_traces["asmc"]
    four = Trace({k: tr.columns[k] for k in ("time_s", "ref_m", "pos_m", "effort")}, {"effort_unit": "N"})
    res = explain(four, load_plant("rigid-x"))
    assert res.effect == "none", res.report


def test_json_has_exactly_the_keys(clean_traces, tmp_path, capsys):
    import argparse

    path = clean_traces["asmc"].write(tmp_path / "x.csv")
    parser = argparse.ArgumentParser()
    add_explain_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["explain", str(path), "--plant", "rigid-x", "--json", "--out", str(tmp_path / "o")])
    assert cmd_explain(args) == 0
    out = capsys.readouterr().out
    obj = json.loads(out)
    assert out.count("\n") == 1
    assert set(obj) == {"effect", "params", "gap_before", "gap_after", "gap_metric", "effects"}
    assert obj["effect"] == "none" and math.isfinite(obj["gap_before"]) and obj["effects"] == []
    assert load_plant(tmp_path / "o" / "x.explain.plant.toml").effects == ()


def _write(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


@pytest.mark.parametrize("body,needle", [
    ("time_s,ref_m,pos_m\n0,0,0\n0.001,0,0\n", "missing column(s) effort"),
    ("time_s,ref_m,pos_m,effort\n0,0,0,0\n0.001,0,nan,0\n", "not a finite number"),
    ("time_s,ref_m,pos_m,effort\n" + "".join(f"{0.001 * i + (0.0004 if i == 50 else 0):.6f},0,0,0\n"
                                              for i in range(400)), "non-uniform sample time"),
    ("time_s,ref_m,pos_m,effort\n" + "".join(f"{0.001 * i:.6f},0,0,0\n" for i in range(100)), "cannot decide"),
    ("time_s,ref_m,pos_m,effort\n" + "".join(f"{0.001 * i:.6f},0,0,0\n" for i in range(5000)), "cannot decide"),
])
def test_bad_input_one_line_error(tmp_path, capsys, body, needle):
    import argparse

    path = _write(tmp_path, "bad.csv", "# drivectl trace v1\n# effort_unit: N\n" + body)
    parser = argparse.ArgumentParser()
    add_explain_parser(parser.add_subparsers(dest="command"))
    assert cmd_explain(parser.parse_args(["explain", str(path), "--plant", "rigid-x"])) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and needle in err and str(path) in err


def test_prepare_rejects_unit_mismatch(clean_traces):
    tr = clean_traces["asmc"]
    with pytest.raises(ExplainError, match="effort_unit"):
        prepare(Trace(dict(tr.columns), {**tr.meta, "effort_unit": "V"}), load_plant("rigid-x"), "x.csv")


def test_gap_of_the_true_plant_is_the_noise_floor(clean_traces):
    tr = clean_traces["asmc"]
    prep = prepare(tr, load_plant("rigid-x"))
    g = gaps_of(prep, [load_plant("rigid-x")])[0]
    assert 0 < g < 20e-6


# --------------------------------------------------------------------------------------------------
# Issue 17: several effects, the two-mass axis, robust windows, real conventions, the measured records
# --------------------------------------------------------------------------------------------------


def test_two_effects_named_in_order_with_json(tmp_path, capsys):
    """The issue's miss: viscous x0.47 + a 10 N periodic force was answered `none` with a 330 um gap."""
    import argparse

    case = _case("viscous", {"scale": 0.47}, "rigid-x", "pid", {}, PROFILE, seed=21)
    case.more = [("periodic", {"amplitude": 10.0, "period": 0.006, "phase": 0.5})]
    tr, _ = make_trace(case)
    path = tr.write(tmp_path / "pair.csv")
    parser = argparse.ArgumentParser()
    add_explain_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["explain", str(path), "--plant", "rigid-x", "--json", "--out", str(tmp_path), "--quiet"])
    assert cmd_explain(args) == 0
    obj = json.loads(capsys.readouterr().out)
    named = [e["effect"] for e in obj["effects"]]
    assert set(named) >= {"viscous", "periodic"}, obj
    assert obj["effect"] == named[0] and obj["params"] == obj["effects"][0]["params"]
    gaps = [e["gap_after"] for e in obj["effects"]]
    assert gaps == sorted(gaps, reverse=True) and gaps[-1] == pytest.approx(obj["gap_after"])
    viscous = next(e for e in obj["effects"] if e["effect"] == "viscous")
    assert viscous["params"]["scale"] == pytest.approx(0.47, rel=0.25)
    # the augmented plant carries both, and the report ends with the remainder against the floor
    spec = load_plant(tmp_path / "pair.explain.plant.toml")
    assert {e[0] for e in spec.effects} >= {"viscous", "periodic"}
    last = (tmp_path / "pair.explain.report.txt").read_text().strip().splitlines()[-1]
    assert "unexplained" in last and "times the floor" in last


def _z_case(effect, params, seed=31):
    prof = {"start": 0.0, "distance": 0.05, "speeds": [0.03, 0.08], "amax": 0.6, "jmax": 20.0, "dwell": 0.3,
            "repeats": 2}
    return _case(effect, params, "two-mass", "pid-nftsm", {"m_tilde": 0.15, "accel_filter_hz": 150.0}, prof,
                 seed=seed, noise=0.01)


def test_two_mass_axis_named_and_split_effects_refused(tmp_path):
    """z (two-mass, V): an effect is named; backlash and resonance are refused with one line each."""
    tr, truth = make_trace(_z_case("offset", {"force": 0.15}))
    res = explain(tr, load_plant("two-mass"), out_dir=tmp_path, stem="z")
    assert res.effect == "offset", res.report
    assert res.params["force"] == pytest.approx(0.15, rel=0.25)
    for name in ("backlash", "resonance"):
        line = next(x for x in res.report.splitlines() if x.strip().startswith(f"{name}:"))
        assert "not tried" in line and "one-mass" in line


def test_clean_circle_without_velocity_column_is_none():
    """Issue 17: every clean y circle without the velocity column was called `mass` (the circle's start:
    a velocity step the local cubic cannot follow)."""
    case = _case("none", {}, "rigid-y", "asmc", {"law": 14}, {"library": "circle"}, seed=5, noise=1.0)
    case.vel_column = False
    tr, _ = make_trace(case)
    assert "vel_m_s" not in tr.columns
    res = explain(tr, load_plant("rigid-y"))
    assert res.effect == "none" and res.effects == [], res.report
    assert "kink" in res.report or res.evidence["windows"] > 60


def test_transport_delay_cycles_from_the_trace():
    """A rig that applies the effort in the cycle it computes it (`# transport_delay_cycles: 0`)."""
    from drivectl.controllers.registry import make_controller
    from drivectl.controllers.runtime.servo import Limits, run
    from drivectl.plant_emulator.sim_axis import SimAxis
    from drivectl.profiles.sequence import back_and_forth

    spec = load_plant("rigid-x")
    axis = SimAxis(spec.build(0.001), transport_delay=False, resolution=76.29e-9, force_noise=1.0, seed=3, name="x")
    ctrl = make_controller("pid", 0.001, {}, plant=spec, axis="x")
    tr = run(axis, ctrl, back_and_forth(**PROFILE), limits=Limits(following_error=0.02)).trace
    zero = Trace(dict(tr.columns), {**tr.meta, "transport_delay_cycles": "0"})
    assert explain(zero, spec).effect == "none"
    with pytest.raises(ExplainError, match="transport_delay_cycles"):
        prepare(Trace(dict(tr.columns), {**tr.meta, "transport_delay_cycles": "2"}), spec, "x.csv")
    with pytest.raises(ExplainError, match="encoder_m_per_count"):
        prepare(Trace(dict(tr.columns), {**tr.meta, "encoder_m_per_count": "-1"}), spec, "x.csv")



def test_offset_not_taken_for_direction_dependent_coulomb():
    """While the axis moves a constant force and Coulomb friction that differs by direction push alike;
    of two explanations equal within the floor the simpler one is named (an offset, not coulomb)."""
    case = _case("viscous", {"scale": 0.55}, "rigid-y", "pid", {}, PROFILE, seed=7)
    case.more = [("offset", {"force": 18.0})]
    tr, _ = make_trace(case)
    res = explain(tr, load_plant("rigid-y"), workers=1)
    named = {e["effect"]: e["params"] for e in res.effects}
    assert set(named) == {"viscous", "offset"}, res.report
    assert named["offset"]["force"] == pytest.approx(18.0, rel=0.15)
    assert "replaced by the simpler offset" in res.report or res.effects[0]["effect"] != "coulomb"


def test_masked_effects_both_named():
    """A mass error and a short-period force each leave the other's in-window structure in every window,
    which read as noise put the floor near the gap itself (issue 17: answered `none` at 377 um)."""
    case = _case("mass", {"mass": 60.0}, "rigid-x", "asmc", {}, PROFILE_B, seed=9)
    case.more = [("periodic", {"amplitude": 20.0, "period": 0.0045, "phase": 1.0})]
    tr, _ = make_trace(case)
    res = explain(tr, load_plant("rigid-x"), workers=1)
    named = {e["effect"]: e["params"] for e in res.effects}
    assert {"mass", "periodic"} <= set(named), res.report
    assert named["mass"]["mass"] == pytest.approx(60.0, rel=0.1)


def test_no_single_window_decides_but_a_few_do():
    """The robust gain: one window's transient (or two) counts only as much as the third best window, while
    an effect that shows in a few windows (a faint stribeck at its starts) keeps its gain."""
    from drivectl.tools.explain.core import _window_stats

    cur = np.full(60, 4.0)
    one = cur.copy()
    one[7] = 0.0  # one window explained, the rest unchanged
    assert _window_stats(cur, one)["robust_gain"] == pytest.approx(0.0)
    few = cur.copy()
    few[[3, 17, 29, 41]] = 0.0  # four starts explained
    st = _window_stats(cur, few)
    assert st["robust_gain"] == pytest.approx(4 * 4.0 / 60)
    assert st["improved"] == 4 and st["worse"] == 0


def test_periodic_fit_on_top_of_a_long_delay(clean_traces):
    """The one-step force residual on a model with a named 6 ms delay reads efforts 6 cycles back (it
    raised IndexError in the lookahead of a shipped clean trace)."""
    from drivectl.tools.explain.fit import fit_periodic, force_residual

    prep = prepare(clean_traces["asmc"], load_plant("rigid-x").with_effect("delay", delay=0.0057))
    r, ok = force_residual(prep)
    assert ok.sum() > 1000 and np.all(np.isfinite(r[ok]))
    assert math.isfinite(fit_periodic(prep).gap)


def test_velocity_estimate_passes_a_loops_oscillation():
    """Without the velocity column a window starts from the slope of a local polynomial; vprl's loop
    oscillates at ~50 Hz, where a cubic over 15 samples read 95 % of the velocity: the missing 5 % at
    every start was fitted as a 5 % mass error on clean traces (issue 17, point 4)."""
    from drivectl.tools.explain.data import estimate_velocity

    dt, res = 0.001, 76.29e-9
    t = np.arange(0, 2.0, dt)
    amp_v = 2.7e-3  # m/s at 50 Hz, as vprl on the library's circle
    w = 2 * math.pi * 50.0
    pos = 0.01 * t + amp_v / w * np.sin(w * t)
    vel = 0.01 + amp_v * np.cos(w * t)
    est = estimate_velocity(np.round(pos / res) * res, dt)
    err = (est - vel)[20:-20]
    assert np.sqrt(np.mean(err ** 2)) < 0.02 * amp_v / math.sqrt(2)  # within 2 % of the oscillation's RMS


def test_vprl_circle_without_velocity_column_is_none():
    """The clean circle of the shipped vprl loop, without the velocity column, against its own plant
    (3 s of it: before the quintic start velocity it was called `mass`, gap 11.6 -> 3.7 um)."""
    case = _case("none", {}, "rigid-x", "vprl", {"m_tilde": 10.0, "accel_filter_hz": 0.0}, {"library": "circle"},
                 seed=6, noise=1.0)
    case.vel_column = False
    tr, _ = make_trace(case)
    n = int(round(3.0 / 0.001)) + 1
    short = Trace({k: np.asarray(v)[:n] for k, v in tr.columns.items()}, dict(tr.meta))
    res = explain(short, load_plant("rigid-x"), workers=1)
    assert res.effect == "none" and res.effects == [], res.report


def test_lash_starts_in_the_middle_before_any_effort():
    """The trace's first window: no effort has pushed the screw to a side yet, so a lash starts relaxed in
    the middle of its dead zone (the plant's rest state). Started against the + side instead, the true plant
    missed that window by ~86 um (the motor side breaks away alone, then hits the table) and a 65 Hz
    `resonance` fitted the trace better than the true lash (pairs: viscous + 14 um lash)."""
    import dataclasses

    width = 15e-6
    tr, _ = make_trace(_case("backlash", {"width": width}, "rigid-y", "asmc", {}, PROFILE, seed=5))
    prep = prepare(tr, load_plant("rigid-y"))
    assert prep.windows.side_force[0] == 0.0 and np.all(prep.windows.side_force[1:] != 0.0)
    spec = load_plant("rigid-y").with_effect("backlash", width=width)
    first = math.sqrt(window_mse(prep, [spec])[0, 0])
    pushed = dataclasses.replace(prep.windows, side_force=np.where(prep.windows.side_force == 0, 1.0,
                                                                   prep.windows.side_force))
    against = math.sqrt(window_mse(dataclasses.replace(prep, windows=pushed), [spec])[0, 0])
    assert first < width  # off by less than the lash itself
    assert against > 3 * first


def test_overdamped_mode_ranked_after_delay():
    """A `resonance` at damping >= 0.7 has no resonant peak: it lags without ringing, a delay's signature.
    Ranked first it stood in for a 0.9 ms delay + 120 Hz mode (named as one 72 Hz mode at damping 0.7);
    behind the delay, the mode is found on top of it in the next round. A ringing mode stays first."""
    from drivectl.tools.explain.core import _overdamped_after_delay
    from drivectl.tools.explain.fit import Fit

    st = {"robust_gain": 3.0}

    def cands(damping: float, delay_gain: float = 2.0) -> list:
        return [(3.0, Fit("resonance", {"frequency": 72.0, "damping": damping}, 1.0), st),
                (2.0, Fit("mass", {"mass": 90.0}, 1.0), st),
                (1.0, Fit("delay", {"delay": 1e-3}, 1.0), {"robust_gain": delay_gain})]

    c = cands(0.7)
    assert "ranked after delay" in _overdamped_after_delay(c, 1.0)
    assert [x[1].key for x in c] == ["delay", "resonance", "mass"]
    # a ringing mode, or a delay that would not be named itself (1.25 floor^2 needed): the mode stays first
    for c in (cands(0.3), cands(0.9, delay_gain=1.2)):
        assert _overdamped_after_delay(c, 1.0) == "" and c[0][1].key == "resonance"

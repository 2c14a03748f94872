"""`drivectl bode --loop open`: the measured open loop and its margins, checked against python-control.

The loops compared (LOOPS below), each measured on the emulated CiA 402 drive over the lockstep virtual
bus, with a multisine added to the law's effort:

* x (rigid-x, about the 10 mm/s bias that keeps its Coulomb friction one constant force): pid (paper 004's
  Table 1 gains), pid-dob (Table 1 + the 10 Hz observer), mbc (the axis's default);
* z (two-mass): pid (gains for a 5 Hz loop; the defaults are paper 004's N/m for a 88 kg axis), pid-dob
  (the same PID gains, the observer at 2 Hz under that loop, its nominal mass m1 + m2 = 1.45 V s^2/m as a
  configuration selecting it on z builds it; GM 9.9 dB, PM 42.8 deg, Ms 1.66), mbc (the default).

The reference (bench/margins.py ``reference_margins``, which the benchmark uses too): python-control's
``stability_margins`` on the discrete loop L = -K(z) z^-1 P_zoh(z) built from the plant's parameters (the
controller's linear form at 1 kHz, the one-cycle transport delay, the zero-order hold), evaluated as
frequency data on a dense grid (python-control's polynomial method misplaces the phase crossovers of the
pid-dob loop: poles near z = 1 in a 9th-order polynomial), its crossovers restricted to the excited band
and chosen as python-control chooses (nearest 0 dB, nearest 0 deg). Agreement: 1 dB, 3 deg, 5 % of Ms.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from drivectl.controllers.registry import make_controller
from drivectl.driver.axis import Feedback
from drivectl.machine.config import load_config
from drivectl.plant_emulator.models import load_plant
from drivectl.profiles.base import Reference
from drivectl.tools.commissioning.bode import add_bode_parser, cmd_bode
from drivectl.tools.commissioning.margins import JSON_KEYS, measure_open_loop, summary_text

pytest.importorskip("control")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from margins import reference_margins  # noqa: E402 - bench/margins.py: the python-control reference, one place

#: PID gains for the two-mass axis: a 5 Hz loop, gain-stabilised below the 89 Hz mode
Z_PID = {"kp": 1430.0, "kd": 45.0, "ki": 4500.0, "d_filter_hz": 150.0}
#: pid-dob on z: those gains, the observer below the loop (at its default 10 Hz, above it, the loop is only
#: conditionally stable: GM -8.8 dB at 3.9 Hz)
Z_DOB = {**Z_PID, "dob_hz": 2.0}
#: (axis, controller, settings, seconds, multisine period): short multisines (z's period is 2 s, whole
#: periods of its 0.5 Hz disturbance)
LOOPS = [("x", "pid", {}, 3.0, 0.5), ("x", "pid-dob", {}, 3.0, 0.5), ("x", "mbc", {}, 3.0, 0.5),
         ("z", "pid", Z_PID, 6.0, 2.0), ("z", "pid-dob", Z_DOB, 6.0, 2.0), ("z", "mbc", {}, 6.0, 2.0)]


@pytest.fixture(autouse=True)
def _embedded_config(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("DRIVECTL_CONFIG", raising=False)


@pytest.mark.parametrize(("axis", "controller", "settings", "seconds", "period"), LOOPS,
                         ids=[f"{a}-{c}" for a, c, *_ in LOOPS])
def test_measured_margins_agree_with_python_control(axis, controller, settings, seconds, period) -> None:
    cfg = load_config(None)
    spec = load_plant(cfg.axis(axis).plant)
    law = make_controller(controller, cfg.cycle_s, settings, plant=spec, axis=axis)
    res = measure_open_loop(cfg, axis, controller=law, seconds=seconds, period_s=period)
    assert res.ok, res.detail
    assert "emulated" in res.bus and res.linear
    m = res.margins
    ref = reference_margins(law, spec, cfg.cycle_s, math.copysign(1.0, res.bias_velocity) if res.bias_velocity else 0,
                            (float(res.freqs[0]), float(res.freqs[-1])))
    # every margin of these loops lies in the band: measured, and by python-control
    assert None not in (ref["gm_db"], ref["pm_deg"], m.gm_db.value, m.pm_deg.value, m.ms.value)
    assert abs(m.gm_db.value - ref["gm_db"]) < 1.0
    assert abs(m.pm_deg.value - ref["pm_deg"]) < 3.0
    assert abs(m.ms.value / ref["ms"] - 1) < 0.05
    # the uncertainty is a standard error, small beside the tolerance on a clean emulated loop
    assert 0 <= m.pm_deg.sigma < 1.0 and 0 <= m.gm_db.sigma < 0.5
    # and the model's loop, from the law's linear form in numpy, is the same loop
    mm = res.model_margins
    assert abs(mm.gm_db.value - ref["gm_db"]) < 0.2 and abs(mm.pm_deg.value - ref["pm_deg"]) < 0.3
    assert m.coherence_min >= 0.8


def test_linear_form_is_the_law() -> None:
    """The linear form steps as the law itself on any feedback sequence (the reference held)."""
    rng = np.random.default_rng(1)
    x, z = load_plant("rigid-x"), load_plant("two-mass")
    for name, spec, st in (("pid", x, {"d_filter_hz": 200.0}), ("pid-dob", x, {}), ("pid-dob", z, Z_DOB),
                           ("mbc", x, {}), ("mbc", z, {})):
        law = make_controller(name, 0.001, st, plant=spec, axis="z" if spec is z else "x")
        form = law.linear_form()
        y = rng.normal(size=(400, 2)) * np.array([1e-6, 1e-4])
        y[0] = 0.0  # a law starts its state at the first sample: from rest, as the form does
        u = np.array([law.step(Reference(0.0), Feedback(k * 1e-3, *y[k])) for k in range(len(y))])
        assert np.max(np.abs(u - form.simulate(y))) < 1e-9 * np.max(np.abs(u)), name
    # pid-dob's nominal mass on the two-mass axis: the whole moving mass, screw side and table
    assert make_controller("pid-dob", 0.001, {}, plant=z, axis="z").settings.ff_mass == pytest.approx(1.3016 + 0.1484)
    for name in ("asmc", "smc", "vprl", "pid-nftsm"):
        assert make_controller(name, 0.001, {}, plant=x).linear_form() is None


def _run(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="drivectl")
    sub = p.add_subparsers(dest="command")
    add_bode_parser(sub)
    return cmd_bode(p.parse_args(["bode", *argv]))


def test_cli_json_exact_keys_and_files(tmp_path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = _run(["--axis", "z", "--loop", "open", "--seconds", "6", "--out", str(tmp_path), "--json"])
    out, err = capsys.readouterr()
    assert rc == 0, err
    lines = out.strip().splitlines()
    assert len(lines) == 1
    obj = json.loads(lines[0])
    assert tuple(obj) == JSON_KEYS
    assert obj["axis"] == "z" and obj["controller"] == "mbc"
    assert all(isinstance(obj[k], float) for k in JSON_KEYS[2:])
    assert (tmp_path / "bode-open-z.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rows = [r for r in (tmp_path / "bode-open-z.csv").read_text().splitlines() if r and not r.startswith("#")]
    assert rows[0].startswith("freq_hz,s_mag_db") and len(rows) > 800  # 0.5 Hz lines, 2-450 Hz


def test_crossover_outside_the_band_is_null_not_extrapolated(capsys: pytest.CaptureFixture[str], tmp_path) -> None:
    # x's mbc loop crosses 0 dB at 33 Hz: a band from 100 Hz holds no gain crossover, and no Ms peak inside it
    rc = _run(["--axis", "x", "--loop", "open", "--sim", "--seconds", "2", "--period", "0.5", "--fmin", "100",
               "--out", str(tmp_path), "--json"])
    assert rc == 0
    obj = json.loads(capsys.readouterr().out)
    assert obj["pm_deg"] is None and obj["pm_hz"] is None and obj["bandwidth_hz"] is None
    assert obj["gm_db"] is None or obj["gm_hz"] >= 100  # the 78 Hz crossover is outside too
    cfg = load_config(None)
    res = measure_open_loop(cfg, "x", sim=True, seconds=2, period_s=0.5, fmin=100)
    text = summary_text(res)
    assert "the crossover lies below the excited band; not extrapolated" in text
    assert "|T| is below -3 dB at the lowest coherent line" in text


def test_nonlinear_law_is_named_a_describing_function_estimate(capsys, tmp_path) -> None:
    """y runs paper 004's ASMC (sliding mode): no linear form, no model loop, and the output says so."""
    rc = _run(["--axis", "y", "--loop", "open", "--sim", "--seconds", "2", "--period", "0.5", "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert rc == 0
    assert "asmc (nonlinear law: describing-function estimate)" in out
    assert "describing-function estimates at the excitation's level" in out
    assert "model (linear form)" not in out
    res = measure_open_loop(load_config(None), "y", sim=True, seconds=2, period_s=0.5)
    assert not res.linear and res.model_loop is None and res.margins.pm_deg.value is not None


def test_excitation_beyond_the_following_window_exit_2(tmp_path, monkeypatch, capsys) -> None:
    # z's window narrowed to 0.1 mm: the model says 1 V of multisine moves the table 0.15 mm
    from drivectl.machine.config import DEFAULT_CONFIG_TOML

    text = DEFAULT_CONFIG_TOML.replace("max_effort = 5.0                # V\nfollowing_error_m = 0.001",
                                       "max_effort = 5.0                # V\nfollowing_error_m = 0.0001")
    assert text != DEFAULT_CONFIG_TOML
    (tmp_path / "m.toml").write_text(text)
    monkeypatch.setenv("DRIVECTL_CONFIG", str(tmp_path / "m.toml"))
    out = tmp_path / "out"
    out.mkdir()
    assert _run(["--axis", "z", "--loop", "open", "--amplitude", "1", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "axes.z.limits.following_error_m (0.1 mm)" in err[0] and "nothing moved" in err[0]
    assert not list(out.iterdir())


@pytest.mark.parametrize(("argv", "words"), [
    (["--axis", "z", "--amplitude", "2.5"], "axes.z.limits.max_effort"),  # mbc's Ms 6.4 takes 2.5 V to 14.8 V
    (["--axis", "z", "--amplitude", "3"], "at most half of axes.z.limits.max_effort"),
    (["--axis", "x", "--seconds", "1"], "--seconds 1"),
    (["--axis", "x", "--fmax", "600"], "--fmax 600"),
    (["--axis", "w"], "axes.w"),
])
def test_bad_input_exit_2_before_anything_moves(argv, words, tmp_path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = _run([*argv, "--loop", "open", "--out", str(tmp_path)])
    cap = capsys.readouterr()
    assert rc == 2 and cap.out == ""
    lines = cap.err.strip().splitlines()
    assert len(lines) == 1 and words in lines[0], lines
    assert not list(tmp_path.iterdir())


def test_period_only_with_the_open_loop(tmp_path, capsys: pytest.CaptureFixture[str]) -> None:
    assert _run(["--axis", "x", "--period", "0.5", "--out", str(tmp_path)]) == 2
    assert "--period" in capsys.readouterr().err

"""Issue 16 point 2: identify a two-mass axis from its closed-loop frequency response."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from drivectl.plant_emulator.models import load_plant
from drivectl.tools.cli.main import main
from drivectl.tools.commissioning.bode import model_frf
from drivectl.tools.commissioning.identify_two_mass import combinations, fit_two_mass
from drivectl.tracefile.format import Trace

# the machine differs from its model: masses, stiffness and damping each 10 % off
PERTURBED = {"m1": 1.1, "m2": 0.9, "k": 1.1, "n": 0.9}


def _perturbed(tmp_path):
    base = load_plant("two-mass")
    params = {k: v * PERTURBED.get(k, 1.0) for k, v in base.params.items()}
    path = tmp_path / "corner.toml"
    path.write_text(replace(base, params=params).to_toml("two-mass, one +-10 % corner"))
    return path, params


def test_the_fit_recovers_every_parameter_from_an_exact_response():
    base = load_plant("two-mass")
    true = {k: v * PERTURBED.get(k, 1.0) for k, v in base.params.items()}
    f = np.arange(5.0, 251.0)
    h = model_frf(replace(base, params=true), 0.001, f)
    fit = fit_two_mass(f, h, np.full(len(f), 0.999), 19, 0.001, base)  # starts from the nominal model
    for k in ("m1", "m2", "k", "n", "b2"):
        assert fit.params[k] == pytest.approx(true[k], rel=1e-4), k
    assert fit.combos["mode_hz"] == pytest.approx(combinations(true)["mode_hz"], rel=1e-6)


def test_identify_on_a_perturbed_two_mass_plant(tmp_path, capsys):
    """The total mass and the mode within 1 % (here: 0.03 %) with force noise on the plant; the split of
    the mass (m2, k) is flagged as poorly identifiable; the model TOML loads as --model."""
    plant, true = _perturbed(tmp_path)
    out = tmp_path / "o"
    argv = ["identify", "--axis", "z", "--sim", "--plant", str(plant), "--model", "two-mass", "--noise", "0.05",
            "--out", str(out), "--json"]
    assert main(argv) == 0
    data = json.loads(capsys.readouterr().out)
    tc = combinations(true)
    assert data["identified"]["total_mass"] == pytest.approx(tc["total_mass"], rel=0.01)
    assert data["identified"]["mode_hz"] == pytest.approx(tc["mode_hz"], rel=0.01)
    assert data["plant_rel_err"]["total_mass"] == pytest.approx(0.0, abs=0.002)
    # the uncertainty says which is which: the combinations tight, the split loose
    assert data["rel_std"]["total_mass"] < 0.002 and data["rel_std"]["mode_hz"] < 0.002
    assert {"m2", "k"} <= set(data["poorly_identified"]) and "total_mass" not in data["poorly_identified"]
    assert data["rel_std"]["m2"] > 5 * data["rel_std"]["total_mass"]
    spec = load_plant(data["plant_file"])
    assert spec.identified["total_mass"] == pytest.approx(data["identified"]["total_mass"])
    assert "m2" in spec.identified["poorly_identified"]
    # the identified model drives the controller of a trace on the perturbed plant
    assert main(["trace", "--axis", "z", "--sim", "--plant", str(plant), "--model", data["plant_file"],
                 "--duration", "0.5", "--no-plot", "--quiet", "--out", str(out)]) == 0
    assert Trace.read(out / "z.csv").meta["model"] == data["plant_file"]


def test_identify_z_prints_the_table(tmp_path, capsys):
    assert main(["identify", "--axis", "z", "--sim", "--seconds", "6", "--out", str(tmp_path)]) == 0
    text = capsys.readouterr().out
    assert "total_mass" in text and "mode_hz" in text and "+-1 sigma" in text
    assert (tmp_path / "z-identified.toml").exists()


def test_friction_runs_on_two_mass_average_whole_disturbance_periods(tmp_path, capsys):
    """--friction: constant-velocity runs; their mean effort over whole periods of the model's 0.5 Hz
    disturbance gives the viscous friction b1 + b2 (1.611 V s/m) and no Coulomb level."""
    assert main(["identify", "--axis", "z", "--sim", "--friction", "--seconds", "4", "--out", str(tmp_path),
                 "--json"]) == 0
    fr = json.loads(capsys.readouterr().out)["friction"]
    b = load_plant("two-mass").params
    for tag in ("pos", "neg"):
        assert fr[f"c_{tag}"] == pytest.approx(b["b1"] + b["b2"], rel=0.02)
        assert abs(fr[f"fc_{tag}"]) < 0.005  # V

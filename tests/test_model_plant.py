"""Issue 16 point 1: plant (what the emulated drive plays) and model (what the controller believes) are
two things: the ``model`` key of an axis, ``--model`` on trace / bode / tune, validated like every key."""

from __future__ import annotations

from pathlib import Path

import pytest

from drivectl.machine.build import model_specs, plant_specs, with_model
from drivectl.machine.config import ConfigError, load_config
from drivectl.plant_emulator.models import PlantError, load_plant
from drivectl.tools.cli.main import main
from drivectl.tracefile.format import Trace

CONFIG = """\
[axes.x]
plant = "rigid-x"
{model}
controller = "asmc"
profile = "short-move"
[axes.x.controller_settings]
law = 14
[axes.x.limits]
position_m = [-0.1, 0.1]
max_effort = 2000.0
"""


def _config(tmp_path: Path, model: str) -> Path:
    p = tmp_path / "machine.toml"
    p.write_text(CONFIG.format(model=model))
    return p


def test_model_defaults_to_the_plant_and_follows_plant_override():
    cfg = load_config(None)
    assert cfg.axis("x").model is None
    assert model_specs(cfg, ["x"])["x"].name == "rigid-x"
    # --plant alone changes both (as before); --model then parts them
    assert model_specs(cfg, ["x"], plant="rigid-y")["x"].name == "rigid-y"
    assert model_specs(cfg, ["x"], "rigid-x", plant="rigid-y")["x"].name == "rigid-x"


def test_model_key_parts_controller_from_plant(tmp_path, capsys):
    path = _config(tmp_path, 'model = "rigid-y"')
    cfg = load_config(path)
    assert cfg.axis("x").model == "rigid-y"
    assert plant_specs(cfg, ["x"])["x"].name == "rigid-x" and model_specs(cfg, ["x"])["x"].name == "rigid-y"
    out = tmp_path / "o"
    assert main(["--config", str(path), "trace", "--sim", "--no-plot", "--quiet", "--duration", "0.3",
                 "--out", str(out)]) == 0
    tr = Trace.read(out / "x.csv")
    assert tr.meta["plant"] == "rigid-x" and tr.meta["model"] == "rigid-y"
    # ASMC's nominal model is the model's (Table 2, y), not the plant's
    assert float(tr.meta["model_mass"]) == pytest.approx(load_plant("rigid-y").params["mass"])
    assert main(["--config", str(path), "config", "show"]) == 0
    assert 'model = "rigid-y"' in capsys.readouterr().out


def test_model_flag_overrides_and_the_mismatch_shows(tmp_path):
    same, other = tmp_path / "same", tmp_path / "other"
    args = ["trace", "--sim", "--no-plot", "--quiet", "--axis", "x", "--duration", "2"]
    assert main([*args, "--out", str(same)]) == 0
    assert main([*args, "--model", "rigid-y", "--out", str(other)]) == 0
    a, b = Trace.read(same / "x.csv"), Trace.read(other / "x.csv")
    assert b.meta["model"] == "rigid-y" and b.meta["plant"] == "rigid-x"
    assert abs(b.error).max() > 3 * abs(a.error).max()  # a wrong model costs tracking


@pytest.mark.parametrize(
    "model, argv, fragments",
    [
        ('model = "no-such.toml"', [], ("machine.toml", "axes.x.model", "no-such.toml")),
        ("model = 3", [], ("machine.toml", "axes.x.model", "expected a non-empty string")),
        ('model = "two-mass"', [], ("machine.toml", "axes.x.model", "effort in V")),
        ("", ["--model", "nowhere.toml"], ("--model", "nowhere.toml")),
    ],
)
def test_bad_model_is_one_line_exit_2_before_anything_moves(tmp_path, capsys, model, argv, fragments):
    path = _config(tmp_path, model)
    out = tmp_path / "o"
    rc = main(["--config", str(path), "trace", "--no-plot", "--quiet", "--out", str(out), *argv])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1
    for f in fragments:
        assert f in err
    assert not out.exists()


def test_with_model_validates_and_sets_the_key():
    cfg = load_config(None)
    assert with_model(cfg, "x", None) is cfg
    assert with_model(cfg, "x", "rigid-y").axis("x").model == "rigid-y"
    with pytest.raises(PlantError, match="--model"):
        with_model(cfg, "x", "nope")
    with pytest.raises(ConfigError, match="axes.q"):
        with_model(cfg, "q", "rigid-y")


def test_bode_overlay_is_the_model(tmp_path, capsys):
    assert main(["bode", "--axis", "z", "--sim", "--seconds", "4", "--model", str(_stiffer(tmp_path)),
                 "--out", str(tmp_path), "--json"]) == 0
    import json

    data = json.loads(capsys.readouterr().out)
    # the overlay is the believed model (k x 1.21: mode x 1.1); the measurement the plant's 89.2 Hz
    assert data["model_mode_hz"] == pytest.approx(1.1 * 89.17, rel=0.01)
    assert data["mode_hz"] == pytest.approx(89.17, rel=0.01)


def _stiffer(tmp_path: Path) -> Path:
    spec = load_plant("two-mass")
    params = dict(spec.params, k=spec.params["k"] * 1.21)
    p = tmp_path / "stiff.toml"
    from dataclasses import replace

    p.write_text(replace(spec, params=params).to_toml("two-mass, k x 1.21"))
    return p

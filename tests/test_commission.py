"""Commissioning commands on the embedded emulated machine."""

from __future__ import annotations

import json

import pytest

from drivectl.machine.config import load_config
from drivectl.plant_emulator.models import load_plant
from drivectl.tools.cli.main import main


def test_config_show_and_init_round_trip(tmp_path, capsys):
    assert main(["config", "show"]) == 0
    out = capsys.readouterr().out
    assert "[axes.x]" in out and 'controller = "asmc"' in out and "<embedded default>" in out
    path = tmp_path / "machine.toml"
    assert main(["config", "init", str(path)]) == 0
    cfg = load_config(path)
    assert set(cfg.axes) == {"x", "y", "z"} and cfg.axis("z").controller == "mbc"
    assert main(["config", "init", str(path)]) == 2  # no silent overwrite
    assert "exists" in capsys.readouterr().err


def test_scan_lists_every_emulated_node(capsys):
    assert main(["scan", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    nodes = {n["node"]: n for n in data["nodes"]}
    assert set(nodes) == {1, 2, 3}
    assert all(n["vendor_id"] == 0x00D71C70 and n["nmt"] == "PRE-OPERATIONAL" for n in nodes.values())
    assert [nodes[i]["serial"] for i in (1, 2, 3)] == [1, 2, 3]


def test_status_decodes_state_mode_and_error(capsys):
    assert main(["status", "--axis", "x", "--json"]) == 0
    s = json.loads(capsys.readouterr().out)["x"]
    assert s["power_state"] == "Switch On Disabled" and s["error"] == "no error" and s["nmt"] == "PRE-OPERATIONAL"
    # a fresh drive holds its EDS default; the configured limit is written when an axis connects
    limit = (s["max_torque_permille"], s["max_torque"], s["max_effort"], s["effort_unit"])
    assert limit == (32767, 3276.7, 300.0, "N")


@pytest.mark.parametrize(("command", "state"), [("enable", "Operation Enabled"), ("disable", "Switch On Disabled"),
                                                ("fault-reset", "Switch On Disabled")])
def test_power_commands_reach_their_state(command, state, capsys):
    assert main([command, "--axis", "y"]) == 0
    assert capsys.readouterr().out.strip() == f"axis y: {state}"


def test_identify_recovers_the_emulated_axis_and_writes_a_loadable_plant(tmp_path, capsys):
    assert main(["identify", "--axis", "x", "--out", str(tmp_path), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert max(abs(v) for v in data["rel_err"].values()) < 0.02
    spec = load_plant(data["plant_file"])
    assert spec.params["mass"] == pytest.approx(88.08, rel=0.02)


def test_identify_refuses_a_model_it_cannot_fit(tmp_path, capsys):
    # a two-mass plant believed rigid: the constant-velocity method needs a rigid model in the effort's unit
    assert main(["identify", "--axis", "z", "--model", "rigid-x", "--out", str(tmp_path)]) == 2
    assert "effort in N" in capsys.readouterr().err

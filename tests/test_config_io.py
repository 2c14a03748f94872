"""Issue 18 point 9, the configuration round trip: ``config show`` prints every key in use and loads back
to the same configuration; results merge into the file on request (``--write-config``) with the comments
kept and the old file backed up; a merge that would not load writes nothing."""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path

import pytest

from drivectl.machine.config import DEFAULT_CONFIG_TOML, ConfigError, load_config, parse_config
from drivectl.machine.config_io import merge_into, show_text
from drivectl.tools.cli.main import main

# a file that leaves things to defaults and to the drive, on a socketcand bus
SPARSE = """\
# my press, hand-tuned
cycle_s = 0.002
[bus]
interface = "socketcand"
channel = "can0"
port = 29537
[axes.a]
plant = "rigid-x"
controller = "pid"
profile = "short-move"
max_lost_cycles = 7
[axes.a.controller_settings]
kp = 2.5e6          # raised after the 2024 rebuild
[axes.a.limits]
max_speed_m_s = 1.5
following_time_s = 0.02
"""


# every table and key a session, the run checks, the bus budget and the stop's escalation read
EVERYTHING = DEFAULT_CONFIG_TOML.replace("clipped_warn = 0.01", "clipped_warn = 0.02", 1).replace(
    "node_id = 2", 'node_id = 2\nlast_resort = "none"', 1).replace(
    'interface = "virtual"', 'interface = "virtual"\npdo_mapping = "compact"\nload_ceiling_pct = 60', 1).replace(
    "[axes.z.emulator]\n", "[axes.z.emulator]\nhome_switch_m = 0.01\nhard_stops_m = [-0.2, 0.2]\n", 1) + """
[axes.z.motion]
max_velocity_m_s = 0.05
jog_deadman_s = 0.3
[axes.z.homing]
method = "switch"
direction = "positive"
hard_stop_effort = 2.0
"""


def _same(a, b) -> None:
    assert dataclasses.replace(a, source="") == dataclasses.replace(b, source="")
    for name in a.axes:
        assert a.axes[name].limits_from_drive == b.axes[name].limits_from_drive


@pytest.mark.parametrize("text", [DEFAULT_CONFIG_TOML, SPARSE, EVERYTHING], ids=["embedded", "sparse", "everything"])
def test_config_show_loads_back_to_the_same_configuration(tmp_path, text):
    path = tmp_path / "m.toml"
    path.write_text(text)
    cfg = load_config(path)
    shown = show_text(cfg)
    _same(cfg, parse_config(tomllib.loads(shown), "shown"))
    for key in ("max_lost_cycles", "rpdo_timeout_ms", "max_speed_m_s", "following_error_m", "position_m",
                "max_effort", "eds", "encoder_m_per_count", "rated_effort", "node_id", "port", "host",
                "last_resort", "max_jump_m", "load_ceiling_pct", "pdo_mapping", "[checks]", "clipped_warn",
                "motion]", "jog_deadman_s", "homing]"):
        assert key in shown, key


def test_config_show_prints_the_keys_it_used_to_drop(capsys):
    assert main(["config", "show"]) == 0
    out = capsys.readouterr().out
    x = tomllib.loads(out)["axes"]["x"]
    assert x["max_lost_cycles"] == 3 and x["limits"]["max_speed_m_s"] == 2.0
    # the deadline is the axis's physics' unless configured (docs/timing.md): shown as a comment
    assert "rpdo_timeout_ms" not in x and "rpdo_timeout_ms not set" in out
    assert "# gamma = " in out  # the controller's values the file leaves out, as comments


def test_merge_keeps_comments_backs_up_and_loads(tmp_path):
    path = tmp_path / "m.toml"
    path.write_text(SPARSE)
    backup = merge_into(path, "a", {"controller": "pid-dob"}, {"kp": 3.0e6, "kd": 1.2e4}, note="tuned")
    text = path.read_text()
    assert "# my press, hand-tuned" in text
    cfg = load_config(path)
    a = cfg.axis("a")
    assert a.controller == "pid-dob" and a.controller_settings == {"kp": 3.0e6, "kd": 1.2e4}
    assert a.max_lost_cycles == 7 and a.limits.max_speed == 1.5  # the rest untouched
    assert backup is not None and backup.read_text() == SPARSE
    # a second merge keeps the first backup and makes another
    backup2 = merge_into(path, "a", {"plant": "rigid-y"})
    assert backup2 != backup and backup.read_text() == SPARSE and load_config(path).axis("a").plant == "rigid-y"


@pytest.mark.parametrize(("axis", "values", "fragment"), [
    ("w", {"plant": "rigid-x"}, "axes.w: no such axis"),
    ("a", {"max_lost_cycles": 500}, "max_lost_cycles"),
    ("a", {"controller": "lqr"}, "'lqr'"),
])
def test_a_merge_that_would_not_load_writes_nothing(tmp_path, axis, values, fragment):
    path = tmp_path / "m.toml"
    path.write_text(SPARSE)
    with pytest.raises(ConfigError) as err:
        merge_into(path, axis, values)
    assert fragment in str(err.value) and "\n" not in str(err.value)
    assert path.read_text() == SPARSE and sorted(p.name for p in tmp_path.iterdir()) == ["m.toml"]


def test_tune_write_config_merges_the_verified_gains(tmp_path, capsys):
    path = tmp_path / "m.toml"
    path.write_text(DEFAULT_CONFIG_TOML)
    rc = main(["--config", str(path), "tune", "--axis", "z", "--candidates", "4", "--seconds", "0.3", "--jobs", "1",
               "--no-verify", "--out", str(tmp_path / "t.toml"), "--write-config"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    assert f"merged axes.z.controller_settings into {path}" in out.out
    tuned = tomllib.loads((tmp_path / "t.toml").read_text())["axes"]["z"]["controller_settings"]
    merged = load_config(path).axis("z").controller_settings
    assert {k: merged[k] for k in tuned} == tuned
    assert "# For paper 000's PID-NFTSM set controller" in path.read_text()  # the file's comments kept
    assert len(list(tmp_path.glob("m.toml.*.bak"))) == 1


def test_write_config_without_a_file_in_use_is_one_line(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("DRIVECTL_CONFIG", raising=False)
    rc = main(["identify", "--axis", "x", "--sim", "--out", str(tmp_path), "--write-config"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "--write-config" in err, err


def test_identify_write_config_points_the_axis_model_at_the_identified_plant(tmp_path, capsys):
    path = tmp_path / "m.toml"
    path.write_text(DEFAULT_CONFIG_TOML)
    rc = main(["--config", str(path), "identify", "--axis", "x", "--sim", "--out", str(tmp_path),
               "--write-config", str(path)])
    out = capsys.readouterr()
    assert rc == 0, out.err
    model = load_config(path).axis("x").model  # what the controller believes; the plant stays rigid-x
    assert Path(model) == (tmp_path / "x-identified.toml").resolve()
    assert load_config(path).axis("x").plant == "rigid-x"

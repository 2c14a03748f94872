"""Issue 19 point 4: the bus load of the configured axes, mapping and cycle; over the ceiling refused
with one line, before anything is configured or enabled."""

from __future__ import annotations

import pytest

from drivectl.tools.bus_budget import axes_per_bus, bus_load, frame_bits
from drivectl.tools.cli import main


def test_frame_bits_and_the_issue_figures():
    assert frame_bits(0) == (47, 55) and frame_bits(4) == (79, 95) and frame_bits(6) == (95, 115)
    assert frame_bits(8) == (111, 135)
    two = bus_load(2, 0.001, 1_000_000)  # the issue measured 58.7 % (71 % with worst-case stuffing)
    assert two.nominal_pct == pytest.approx(58.5) and two.bound_pct == pytest.approx(70.5)
    assert axes_per_bus(0.001, 1_000_000) == 2 and axes_per_bus(0.002, 1_000_000) == 5
    compact = bus_load(3, 0.001, 1_000_000, "compact")
    assert compact.nominal_pct == pytest.approx(61.7) and axes_per_bus(0.001, 1_000_000, mapping="compact") == 3


def _cfg(tmp_path, bus_extra: str = "", cycle: float = 0.001):
    text = [f"cycle_s = {cycle}", "[bus]", 'interface = "virtual"', bus_extra]
    for i, name in enumerate("xyz", 1):
        text += [f"[axes.{name}]", f"node_id = {i}", "rated_effort = 100.0", 'plant = "rigid-x"',
                 'controller = "pid"', 'profile = "short-move"']
    p = tmp_path / "m.toml"
    p.write_text("\n".join(text) + "\n")
    return p


def test_three_axes_at_1khz_refused_in_one_line_before_anything_moves(tmp_path, capsys):
    p = _cfg(tmp_path)
    rc = main(["--config", str(p), "trace", "--axis", "x,y,z", "--duration", "0.01", "--out", str(tmp_path),
               "--quiet", "--no-plot"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert "85.4 % bus load (103.0 % with worst-case stuffing) for 3 axes" in err[0]
    assert "70 % ceiling (bus.load_ceiling_pct): 2 axes fit" in err[0]
    assert not list(tmp_path.glob("*.csv"))


def test_a_longer_cycle_or_a_higher_ceiling_lets_it_run_and_the_start_line_tells_the_load(tmp_path, capsys):
    p = _cfg(tmp_path, cycle=0.002)
    rc = main(["--config", str(p), "trace", "--axis", "x,y,z", "--duration", "0.01", "--out", str(tmp_path),
               "--quiet", "--no-plot"])
    err = capsys.readouterr().err
    assert rc == 0, err
    assert "bus load 42.7 % of 1 Mbit/s (51.5 % with worst-case stuffing): 3 axes" in err
    p = _cfg(tmp_path, "load_ceiling_pct = 90")
    rc = main(["--config", str(p), "trace", "--axis", "x,y,z", "--duration", "0.01", "--out", str(tmp_path),
               "--quiet", "--no-plot"])
    assert rc == 2 and "103.0 % with worst-case stuffing" in capsys.readouterr().err  # the bound still holds


def test_config_show_prints_the_budget_and_a_bad_ceiling_is_one_line(tmp_path, capsys):
    assert main(["--config", str(_cfg(tmp_path)), "config", "show"]) == 0
    out = capsys.readouterr().out
    assert "# bus load 85.4 % of 1 Mbit/s" in out and "OVER" in out
    p = _cfg(tmp_path, "load_ceiling_pct = 150")
    rc = main(["--config", str(p), "config", "show"])
    assert rc == 2 and "bus.load_ceiling_pct: a per cent of the bitrate" in capsys.readouterr().err

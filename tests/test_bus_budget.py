"""Issue 19 point 4: the bus load of the configured axes, mapping and cycle; over the ceiling refused
with one line, before anything is configured or enabled."""

from __future__ import annotations

import pytest

from drivectl.machine.bus_budget import axes_per_bus, bus_load, frame_bits
from drivectl.tools.cli.main import main


def test_frame_bits_and_the_issue_figures():
    assert frame_bits(0) == (47, 55) and frame_bits(4) == (79, 95) and frame_bits(6) == (95, 115)
    assert frame_bits(8) == (111, 135)
    two = bus_load(2, 0.001, 1_000_000)  # the issue measured 58.7 % (71 % with worst-case stuffing)
    assert two.nominal_pct == pytest.approx(58.5) and two.bound_pct == pytest.approx(70.5)
    assert axes_per_bus(0.001, 1_000_000) == 2 and axes_per_bus(0.002, 1_000_000) == 5
    compact = bus_load(3, 0.001, 1_000_000, "compact")
    assert compact.nominal_pct == pytest.approx(61.7) and axes_per_bus(0.001, 1_000_000, mapping="compact") == 3


def _cfg(tmp_path, bus_extra: str = "", cycle: float = 0.001, axes: str = "xyz"):
    text = [f"cycle_s = {cycle}", "[bus]", 'interface = "virtual"', bus_extra]
    for i, name in enumerate(axes, 1):
        text += [f"[axes.{name}]", f"node_id = {i}", "rated_effort = 100.0", 'plant = "rigid-x"',
                 'controller = "pid"', 'profile = "short-move"']
    p = tmp_path / "m.toml"
    p.write_text("\n".join(text) + "\n")
    return p


def _trace(tmp_path, p, axes: str, *extra: str) -> int:
    return main(["--config", str(p), "trace", "--axis", axes, "--duration", "0.05", "--out", str(tmp_path / "out"),
                 "--quiet", "--no-plot", *extra])


def test_over_the_ceiling_refused_in_one_line_before_anything_moves(tmp_path, capsys):
    p = _cfg(tmp_path, 'pdo_mapping = "full"')
    assert _trace(tmp_path, p, "x,y,z") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert "85.4 % bus load (103.0 % with worst-case stuffing) for 3 axes" in err[0]
    assert "70 % ceiling (bus.load_ceiling_pct): 2 axes fit" in err[0]
    p = _cfg(tmp_path, axes="vwxyz")  # five axes: even the minimal mapping takes 83.7 %
    assert _trace(tmp_path, p, "v,w,x,y,z") == 2
    err = capsys.readouterr().err
    assert "83.7 % bus load (100.5 % with worst-case stuffing) for 5 axes" in err and "4 axes fit" in err
    p = _cfg(tmp_path, 'pdo_mapping = "compact"', axes="wxyz")  # four compact: 80.7 %
    assert _trace(tmp_path, p, "w,x,y,z") == 2
    err = capsys.readouterr().err
    assert "80.7 % bus load (97.5 % with worst-case stuffing) for 4 axes" in err and "3 axes fit" in err
    assert not (tmp_path / "out").exists() or not list((tmp_path / "out").glob("*.csv"))


def test_auto_mapping_three_axes_compact_and_bit_for_bit_with_sim(tmp_path, capsys):
    """Three axes at 1 kHz: the full mapping would take 85.4 %, so "auto" maps compactly (61.7 %); the
    velocity is then derived on the host, by SimAxis the same way: --sim equals the bus bit for bit."""
    import numpy as np

    from drivectl.tracefile.format import Trace

    p = _cfg(tmp_path)
    assert _trace(tmp_path, p, "x,y,z") == 0
    err = capsys.readouterr().err
    assert "bus load 61.7 % of 1 Mbit/s (74.5 % with worst-case stuffing): 3 axes, compact mapping" in err
    bus = {n: Trace.read(tmp_path / "out" / f"{n}.csv") for n in "xyz"}  # AXIS.csv: the latest run
    assert _trace(tmp_path, p, "x,y,z", "--sim") == 0
    sim = {n: Trace.read(tmp_path / "out" / f"{n}.csv") for n in "xyz"}
    for name in bus:
        for col in ("pos_m", "effort", "vel_m_s"):
            assert np.array_equal(bus[name].columns[col], sim[name].columns[col]), (name, col)


def test_a_longer_cycle_keeps_the_full_mapping_and_the_start_line_tells_the_load(tmp_path, capsys):
    p = _cfg(tmp_path, cycle=0.002)
    assert _trace(tmp_path, p, "x,y,z") == 0
    assert "bus load 42.7 % of 1 Mbit/s (51.5 % with worst-case stuffing): 3 axes, full mapping" in \
        capsys.readouterr().err


def test_config_show_prints_the_budget_and_bad_keys_are_one_line(tmp_path, capsys):
    assert main(["--config", str(_cfg(tmp_path, 'pdo_mapping = "full"')), "config", "show"]) == 0
    out = capsys.readouterr().out
    assert "# bus load 85.4 % of 1 Mbit/s" in out and "OVER" in out
    for extra, msg in (("load_ceiling_pct = 150", "bus.load_ceiling_pct: a per cent of the bitrate"),
                       ('pdo_mapping = "tiny"', "bus.pdo_mapping: expected")):
        rc = main(["--config", str(_cfg(tmp_path, extra)), "config", "show"])
        assert rc == 2 and msg in capsys.readouterr().err

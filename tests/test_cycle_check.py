"""Before doctor recommends a longer cycle, each axis's controller is simulated at it
(tools/commissioning/cycle_check.py, docs/timing.md "The cycle doctor recommends")."""

from __future__ import annotations

from helpers import default_config_with

from drivectl.tools.commissioning.cycle_check import PEAK_TO_PEAK_M, hold_at


def machine(**y_settings: object):
    return default_config_with("y", **y_settings)


def test_a_gain_tuned_for_another_cycle_is_caught_before_the_cycle_is_recommended():
    """y's standstill gain, said to be tuned at 2 ms but 1 ms's, stands in a limit cycle at 2 ms: named."""
    bad = hold_at(machine(standstill_cycle_s=0.002), "y", 0.002)
    assert bad.holds is False and bad.effort_at_limit and bad.peak_to_peak_m > 100e-6, bad
    assert "does NOT hold at 2 ms" in bad.text() and "retune" in bad.text()


def test_the_shipped_axes_hold_at_2_ms():
    cfg = machine()
    for name in ("x", "y", "z"):
        h = hold_at(cfg, name, 0.002)
        assert h.holds is True and h.peak_to_peak_m <= PEAK_TO_PEAK_M and not h.effort_at_limit, h
        assert h.text().startswith("holds at 2 ms in simulation")

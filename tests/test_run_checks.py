"""Issue 18 point 6: a [checks] fault threshold stops the run the cycle it is passed (quick stop, the end
state the drive reported, the trace kept, exit 3), not after the profile; warnings are judged at the end."""

from __future__ import annotations

import pytest
from helpers import SimWallClock

from drivectl.controllers.registry import make_controller
from drivectl.controllers.runtime.run_checks import RunChecks, RunGuard
from drivectl.controllers.runtime.servo import Channel, Pacer, StopReason, run_channels
from drivectl.driver.axis import Axis
from drivectl.machine.build import open_machine
from drivectl.machine.config import DEFAULT_CONFIG_TOML, load_config
from drivectl.profiles.library import load_profile
from drivectl.tools.cli.main import main
from drivectl.tracefile.format import Trace


class _Axis(Axis):
    def __init__(self, name: str, lost: int | None = None) -> None:
        self.name = name
        if lost is not None:
            self.lost_total = lost


class _Ch:
    def __init__(self, axis: _Axis) -> None:
        self.axis, self.clipped = axis, 0


class _Pacer:
    missed = 0


def test_the_mid_run_base_is_the_cycles_so_far_but_at_least_the_minimum():
    checks = RunChecks(clipped_fault=0.5, extrapolated_fault=0.05, missed_deadlines_fault=0.05, fault_min_cycles=100)
    x, y = _Ch(_Axis("x", lost=7)), _Ch(_Axis("y"))  # x was already 7 cycles bridged before this run
    pacer = _Pacer()
    g = RunGuard(checks, 10_000, [x, y], pacer)
    # before 100 cycles: 5 % of 100 = 5 events allowed; the sixth is a fault whatever the cycle
    pacer.missed = 5
    assert g.check(10) is None
    pacer.missed = 6
    axis, line = g.check(10)
    assert axis == "x" and line == ("axis x: 6 deadlines missed (paced) in the first 10 cycles, more than "
                                    "checks.missed_deadlines_fault 5.0% allows (5 of 100 cycles)")
    # later: a fraction of the cycles so far (the limit grows: 1000 cycles allow 50)
    pacer.missed = 50
    assert g.check(1000) is None
    y.clipped = 500
    assert g.check(1000) is None
    y.clipped = 501
    assert g.check(1000)[0] == "y"
    y.clipped = 0
    x.axis.lost_total = 7 + 50
    assert g.check(1000) is None  # counted from the run's start
    x.axis.lost_total = 7 + 51
    assert "51 cycles run on an extrapolated position" in g.check(1000)[1]


def test_a_short_run_is_judged_on_its_length_and_a_fraction_of_one_never_trips():
    ch = _Ch(_Axis("x"))
    g = RunGuard(RunChecks(clipped_fault=0.5), 40, [ch])  # 40 cycles < fault_min_cycles: the base is 40
    ch.clipped = 20
    assert g.check(20) is None
    ch.clipped = 21
    assert "(20 of 40 cycles)" in g.check(21)[1]
    g = RunGuard(RunChecks(clipped_warn=1.0, clipped_fault=1.0), 40, [ch])
    ch.clipped = 40
    assert g.check(40) is None


def test_fault_min_cycles_is_checked():
    with pytest.raises(ValueError, match="checks.fault_min_cycles"):
        RunChecks(fault_min_cycles=0)
    with pytest.raises(ValueError, match="checks.fault_min_cycles"):
        RunChecks(fault_min_cycles=2.5)
    with pytest.raises(ValueError, match="checks.fault_min_cycles"):
        RunChecks(fault_min_cycles=0.0)  # as the TOML reader hands it over
    assert RunChecks(fault_min_cycles=200.0).fault_min_cycles == 200


def test_clipped_past_the_fault_threshold_stops_the_run_mid_run(tmp_path, capsys):
    """The effort clipped in nearly every cycle (issue 18: 2479 of 2501 said "completed"): stopped once more
    than half of the first 1000 cycles are clipped, the stop verified by the drive, the trace kept."""
    path = tmp_path / "machine.toml"
    # a weak drive (0.5 N) that the window lets lag: clipped nearly every cycle, no other limit trips
    text = DEFAULT_CONFIG_TOML.replace("max_effort = 300.0              # N", "max_effort = 0.5 # N", 1).replace(
        "following_error_m = 0.001       # window", "following_error_m = 0.09", 1)
    assert text != DEFAULT_CONFIG_TOML
    path.write_text(text)
    rc = main(["--config", str(path), "trace", "--axis", "x", "--duration", "2.5", "--out", str(tmp_path / "out"),
               "--no-plot", "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 3, err
    assert err[-1].startswith("drivectl: fault: run check at cycle ") and "clipped" in err[-1], err
    assert "more than checks.clipped_fault 50.0% allows (500 of 1000 cycles); stopped (x " in err[-1]
    tr = Trace.read(tmp_path / "out" / "x.csv")
    m = tr.meta
    assert m["stop"] == "fault" and m["fault_kind"] == "run check" and int(m["effort_clipped_cycles"]) == 501
    assert len(tr) < 1000 and m["safe_state"].split(" (")[0] in ("Switch On Disabled", "Quick Stop Active")
    assert m["safe_after_cycles"] != "unknown"



class _Slow:
    """A controller whose every step takes 1.6 cycles of wall time: each cycle starts later than the last
    (missed deadlines), while the gap between two SYNCs stays within the drive's two-cycle window."""

    def __init__(self, inner, clock: SimWallClock) -> None:
        self.inner, self.clock, self.dt = inner, clock, inner.dt

    def reset(self) -> None:
        self.inner.reset()

    def describe(self):
        return self.inner.describe()

    def step(self, ref, fb):
        self.clock.t += 1.6 * self.dt
        return self.inner.step(ref, fb)


def test_missed_deadlines_past_the_fault_threshold_stop_a_paced_run():
    cfg = load_config(None)
    ac = cfg.axis("x")
    prof = load_profile(ac.profile)
    clock = SimWallClock()
    m = open_machine(cfg, ["x"], start={"x": prof.start_position})
    try:
        ctrl = make_controller(ac.controller, cfg.cycle_s, ac.controller_settings, plant=m.specs["x"], axis="x")
        res = run_channels([Channel(m.axes["x"], _Slow(ctrl, clock), prof, ac.limits)], duration=2.0,
                           pace=Pacer(cfg.cycle_s, now=clock.now, sleep=clock.sleep), checks=RunChecks())
    finally:
        m.close()
    assert res.stop is StopReason.FAULT and res.fault.kind == "run check", res.detail
    assert "51 deadlines missed (paced)" in res.fault.detail and "(50 of 1000 cycles)" in res.fault.detail
    assert res.cycles < 60 and res.fault.safe_after["x"] is not None
    assert res.trace.meta["missed_deadlines"] == "51"

"""drivectl health report on histories with the wear hidden in the emulated plant (tests/health_history.py):
fingerprint runs a shift apart, each with its own noise seed and the day's temperature on the viscous
friction; viscous friction growing from run 3 on, backlash opening from run 3 on, and a clean history.
Every run goes through the session, the store and the analysis on a two-worker LocalCluster; the report
must find the onset, name the effect, and raise nothing on the clean history."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("duckdb")
pytest.importorskip("pyarrow")
pytest.importorskip("distributed")

from health_history import backlash_from, clean, make_history, viscous_from  # noqa: E402

from drivectl.tools.cli.main import main  # noqa: E402

RUNS = 8
ONSET = 3
ALARM_KEYS = {"effect", "param", "onset_run", "onset_utc", "first_value", "last_value", "slope_per_100_runs"}


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    root = tmp_path_factory.mktemp("health")
    s = root / "store"
    make_history(s, root / "clean", clean, RUNS, machine="clean", seed=1)
    make_history(s, root / "viscous", viscous_from(ONSET, 0.06), RUNS, machine="worn-screw", seed=2)
    make_history(s, root / "backlash", backlash_from(ONSET, 3e-6), RUNS, machine="loose-nut", seed=3)
    assert main(["health", "analyze", "--store", str(s), "--workers", "2"]) == 0
    return s


def _report(capsys, store, machine):
    capsys.readouterr()
    assert main(["health", "report", "--store", str(store), "--machine", machine, "--axis", "x", "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_viscous_growth_is_found_at_its_onset_and_named(store, capsys):
    rep = _report(capsys, store, "worn-screw")
    assert set(rep) == {"machine", "axis", "runs", "alarms", "trends"}
    assert (rep["machine"], rep["axis"], rep["runs"]) == ("worn-screw", "x", RUNS)
    assert rep["alarms"], rep["alarms"]
    a = rep["alarms"][0]
    assert set(a) == ALARM_KEYS
    assert (a["effect"], a["param"]) == ("viscous", "scale")
    assert ONSET - 1 <= a["onset_run"] <= ONSET + 1
    assert a["onset_utc"] == f"2026-11-0{2 + (a['onset_run'] * 8 + 6) // 24}T{(a['onset_run'] * 8 + 6) % 24:02d}:00:00Z"
    # the plant's scale went 1.0 -> 1.3 (times the day's +-3 %): the fits follow it
    assert a["first_value"] == pytest.approx(1.0, abs=0.04)
    assert a["last_value"] == pytest.approx(1.0 + 0.06 * (RUNS - ONSET), abs=0.08)
    assert a["slope_per_100_runs"] == pytest.approx(6.0, rel=0.35)
    # the Coulomb and mass fits move with it; they follow, they are not the effect named
    assert {x["effect"] for x in rep["alarms"]} == {"viscous"}
    trend = rep["trends"]["viscous.scale"]
    assert [p[0] for p in trend] == list(range(RUNS)) and all(len(p) == 3 for p in trend)


def test_backlash_opening_is_found_at_its_onset_and_named(store, capsys):
    rep = _report(capsys, store, "loose-nut")
    assert rep["alarms"], rep["alarms"]
    a = rep["alarms"][0]
    assert (a["effect"], a["param"]) == ("backlash", "width")
    assert ONSET - 1 <= a["onset_run"] <= ONSET + 1
    assert a["first_value"] < 3e-6 < 10e-6 < a["last_value"]
    assert a["slope_per_100_runs"] > 0


def test_a_clean_history_raises_no_alarm(store, capsys):
    rep = _report(capsys, store, "clean")
    assert rep["runs"] == RUNS and rep["alarms"] == []
    assert len(rep["trends"]) >= 15  # every parameter of every effect has its series from the first run


def test_fleet_table_ranks_the_worn_axes_first_and_the_plot(store, capsys, tmp_path):
    capsys.readouterr()
    assert main(["health", "report", "--store", str(store)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split()[:3] == ["machine", "axis", "runs"]
    order = [ln.split()[0] for ln in lines[1:]]
    assert set(order[:2]) == {"worn-screw", "loose-nut"} and order[2] == "clean"
    assert "backlash.width from run" in lines[1 + order.index("loose-nut")]
    assert lines[1 + order.index("clean")].endswith("none")
    png = tmp_path / "trend.png"
    assert main(["health", "report", "--store", str(store), "--machine", "worn-screw", "--axis", "x",
                 "--plot", str(png)]) == 0
    out = capsys.readouterr().out
    assert "ALARM viscous.scale: changed at run" in out and "limit 1.5" in out
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_report_refusals_are_one_line(store, capsys, tmp_path):
    capsys.readouterr()
    assert main(["health", "report", "--store", str(store), "--json"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--json: the selection holds 3 axes" in err
    assert main(["health", "report", "--store", str(tmp_path / "none")]) == 2
    assert "no health store there" in capsys.readouterr().err
    assert main(["health", "report", "--store", str(store), "--machine", "nope"]) == 2
    assert "no runs for --machine nope" in capsys.readouterr().err

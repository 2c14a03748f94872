"""drivectl health analyze: every run without fits, fitted on a two-worker LocalCluster with explain's
fitters, one parameter set per vocabulary effect; incremental (a second pass fits nothing)."""

from __future__ import annotations

import pytest

duckdb = pytest.importorskip("duckdb")
pytest.importorskip("pyarrow")
pytest.importorskip("distributed")

from drivectl.plant_emulator.effects import EFFECTS  # noqa: E402
from drivectl.tools.cli.main import main  # noqa: E402
from drivectl.tools.explain.fit import PARAM_NAMES  # noqa: E402
from drivectl.tools.health.store import CATALOG  # noqa: E402


def test_analyze_fits_every_effect_of_every_new_run_on_two_workers(tmp_path, capsys):
    traces = []
    for seed in (1, 2):
        out = tmp_path / f"t{seed}"
        assert main(["trace", "--axis", "x", "--sim", "--duration", "1.5", "--noise", "0.5", "--seed", str(seed),
                     "--out", str(out), "--no-plot", "--quiet"]) == 0
        traces += [str(p) for p in out.glob("x-*.csv")]
    store = str(tmp_path / "store")
    assert main(["health", "ingest", *traces, "--machine", "m1", "--store", store]) == 0
    capsys.readouterr()
    assert main(["health", "analyze", "--store", store, "--workers", "2"]) == 0
    assert "2 runs fitted, 0 failed" in capsys.readouterr().out
    con = duckdb.connect(str(tmp_path / "store" / CATALOG), read_only=True)
    fits = con.execute("SELECT run, effect, parameter, value, gap FROM fits ORDER BY ALL").fetchall()
    con.close()
    runs = {f[0] for f in fits}
    assert len(runs) == 2
    want = {(e, p) for e in EFFECTS for p in PARAM_NAMES[e]}
    for run in runs:
        assert {(f[1], f[2]) for f in fits if f[0] == run} == want
    # the plant is the model (no wear): the mass fit lands on the model's mass, a real fit
    from drivectl.plant_emulator.models import load_plant

    mass = load_plant("rigid-x").design().total_mass
    assert all(f[3] == pytest.approx(mass, rel=0.05) for f in fits if f[1:3] == ("mass", "mass"))
    assert all(f[4] > 0 for f in fits)
    assert main(["health", "analyze", "--store", store, "--workers", "2"]) == 0
    assert "0 runs fitted" in capsys.readouterr().out

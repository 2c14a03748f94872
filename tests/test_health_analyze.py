"""drivectl health analyze: every run without fits, fitted on a two-worker LocalCluster with explain's
fitters, one parameter set per vocabulary effect with its uncertainty, against the axis's baseline (the
model of its first runs, kept in the catalog, or the configured commissioning model); incremental (a
second pass fits nothing); the same code on a scheduler given by address."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

duckdb = pytest.importorskip("duckdb")
pytest.importorskip("pyarrow")
distributed = pytest.importorskip("distributed")

from drivectl.plant_emulator.effects import EFFECTS  # noqa: E402
from drivectl.plant_emulator.models import load_plant  # noqa: E402
from drivectl.tools.cli.main import main  # noqa: E402
from drivectl.tools.explain.data import prepare  # noqa: E402
from drivectl.tools.explain.fit import PARAM_NAMES, run_fitter, uncertainty  # noqa: E402
from drivectl.tools.health.analyze import analyze, combine_baseline  # noqa: E402
from drivectl.tools.health.store import CATALOG, Store  # noqa: E402
from drivectl.tracefile.format import Trace  # noqa: E402


def _traces(tmp_path, seeds, *extra: str, duration: str = "1.5") -> list[str]:
    out = []
    for seed in seeds:
        d = tmp_path / f"t{seed}{''.join(extra)}"
        assert main(["trace", "--axis", "x", "--sim", "--duration", duration, "--noise", "0.5", "--seed", str(seed),
                     "--out", str(d), "--no-plot", "--quiet", *extra]) == 0
        out += [str(p) for p in d.glob("x-*.csv")]
    return out


def _fits(store) -> list[tuple]:
    con = duckdb.connect(str(store / CATALOG), read_only=True)
    try:
        return con.execute("SELECT run, effect, parameter, value, uncertainty, gap FROM fits ORDER BY ALL").fetchall()
    finally:
        con.close()


def test_analyze_fits_every_effect_of_every_new_run_on_two_workers(tmp_path, capsys):
    traces = _traces(tmp_path, (1, 2, 3))
    store = tmp_path / "store"
    assert main(["health", "ingest", *traces[:2], "--machine", "m1", "--store", str(store)]) == 0
    capsys.readouterr()
    # two runs: the baseline (the model of the first 3) is not there yet; the runs wait, nothing fails
    assert main(["health", "analyze", "--store", str(store), "--workers", "2"]) == 0
    out = capsys.readouterr()
    assert "0 runs fitted, 0 failed" in out.out and "first 3 runs: 2 so far" in out.err
    assert main(["health", "ingest", traces[2], "--machine", "m1", "--store", str(store)]) == 0

    def interrupt(res) -> None:  # Ctrl-C as the first result is in
        raise KeyboardInterrupt

    with Store(store) as s, pytest.raises(KeyboardInterrupt):
        analyze(s, workers=2, on_fit=interrupt)
    assert len({f[0] for f in _fits(store)}) == 1  # what finished is kept
    assert main(["health", "analyze", "--store", str(store), "--workers", "2"]) == 0
    assert "2 runs fitted, 0 failed" in capsys.readouterr().out  # incremental: the other two
    fits = _fits(store)
    runs = {f[0] for f in fits}
    assert len(runs) == 3
    want = {(e, p) for e in EFFECTS for p in PARAM_NAMES[e]}
    for run in runs:
        assert {(f[1], f[2]) for f in fits if f[0] == run} == want
    # the plant is the model (no wear): the mass fit lands on the model's mass, within its uncertainty
    mass = load_plant("rigid-x").design().total_mass
    for f in fits:
        if f[1:3] == ("mass", "mass"):
            assert 0 < f[4] < 0.05 * mass and abs(f[3] - mass) < 4 * f[4]
    assert all(f[5] > 0 for f in fits)
    # every parameter the runs constrain has its uncertainty (NULL only where the run says nothing)
    for e, p in [("mass", "mass"), ("viscous", "scale"), ("coulomb", "force_neg"), ("offset", "force"),
                 ("delay", "delay"), ("backlash", "width")]:
        assert all(f[4] is not None and f[4] > 0 for f in fits if f[1:3] == (e, p)), (e, p)
    # the first 1.5 s of x's circle move it one way only (its velocity never positive): the runs say nothing
    # of the Coulomb force in the other direction, on any CPU (fit.py FLAT_RTOL)
    assert all(max(Trace.read(t).columns["vel_m_s"]) <= 0.0 for t in traces)
    assert all(f[4] is None for f in fits if f[1:3] == ("coulomb", "force_pos"))
    con = duckdb.connect(str(store / CATALOG), read_only=True)
    kept = con.execute("SELECT machine, axis, runs FROM baselines").fetchall()
    con.close()
    assert [(m, a) for m, a, _ in kept] == [("m1", "x")] and len(json.loads(kept[0][2])) == 3
    assert main(["health", "analyze", "--store", str(store), "--workers", "2"]) == 0
    assert "0 runs fitted" in capsys.readouterr().out


def test_a_scheduler_by_address_runs_the_same_code_and_a_configured_model_is_the_baseline(tmp_path, capsys):
    traces = _traces(tmp_path, (4,))
    store = tmp_path / "store"
    cfg = tmp_path / "machine.toml"
    from drivectl.machine.config import DEFAULT_CONFIG_TOML

    # the commissioning model: 20 % more viscous friction than the plant has, so the fit reads 1/1.2
    model = tmp_path / "commissioned.toml"
    model.write_text(load_plant("rigid-x").with_effect("viscous", scale=1.2).to_toml())
    cfg.write_text(DEFAULT_CONFIG_TOML.replace('# model = "rigid-x"', f'model = "{model}"'))
    assert main(["--config", str(cfg), "health", "ingest", *traces, "--machine", "m1", "--store", str(store)]) == 0
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                  silence_logs=40) as cluster:
        assert main(["--config", str(cfg), "health", "analyze", "--store", str(store), "--scheduler",
                     cluster.scheduler_address]) == 0
    assert "1 runs fitted, 0 failed" in capsys.readouterr().out
    scale = [f for f in _fits(store) if f[1:3] == ("viscous", "scale")]
    assert len(scale) == 1 and scale[0][3] == pytest.approx(1 / 1.2, abs=max(0.02, 3 * scale[0][4]))
    with Store(store) as s:
        assert s.baseline("m1", "x") is None  # a configured model is not kept: the configuration says it


def test_a_scheduler_that_does_not_answer_is_one_line(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("drivectl.tools.health.analyze.CONNECT_TIMEOUT_S", 1.0)
    traces = _traces(tmp_path, (5,))
    store = tmp_path / "store"
    assert main(["health", "ingest", *traces, "--machine", "m1", "--store", str(store)]) == 0
    capsys.readouterr()
    assert main(["health", "analyze", "--store", str(store), "--scheduler", "tcp://127.0.0.1:9"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--scheduler tcp://127.0.0.1:9: cannot connect" in err[0]


def test_the_baseline_is_the_effects_a_majority_of_the_first_runs_show():
    nominal = load_plant("rigid-x")
    named = [[{"effect": "viscous", "params": {"scale": 1.2}}, {"effect": "offset", "params": {"force": 3.0}}],
             [{"effect": "viscous", "params": {"scale": 1.4}}, {"effect": "backlash", "params": {"width": 1e-5}}],
             [{"effect": "viscous", "params": {"scale": 1.3}}, {"effect": "backlash", "params": {"width": 2e-5}}]]
    spec = combine_baseline(nominal, named)
    # viscous in all three (median 1.3); offset in one (left out); backlash in two, but a lash splits the
    # axis, and its own fit is its trend: left out of the baseline
    assert spec.effects == (("viscous", {"scale": 1.3}),)


def test_uncertainty_is_the_sandwich_of_the_window_errors():
    """A known quadratic per window: m_w(x) = (x - a_w)^2 with a_w spread sigma over W windows; the least mean
    error is mean(a_w), whose standard error is sigma / sqrt W; the sandwich must say that (plus the grid's
    resolution in quadrature), and inf along a parameter the errors do not depend on."""
    rng = np.random.default_rng(0)
    W, sigma = 400, 0.3
    a = 1.0 + sigma * rng.standard_normal(W)
    x = np.linspace(0.8, 1.2, 9)
    mse = (x[None, :] - a[:, None]) ** 2
    best = int(np.argmin(mse.mean(axis=0)))
    got = uncertainty(x[:, None], mse, best, ("p",))["p"]
    want = math.sqrt((np.std(a, ddof=1) / math.sqrt(W)) ** 2 + 0.05 ** 2 / 12)
    assert got == pytest.approx(want, rel=1e-6)
    # a second parameter that changes nothing: inf for it, the first still read alone
    grid = np.array([(u, v) for u in x for v in (0.0, 1.0, 2.0)])
    mse2 = (grid[None, :, 0] - a[:, None]) ** 2
    u2 = uncertainty(grid, mse2, int(np.argmin(mse2.mean(axis=0))), ("p", "q"))
    assert math.isinf(u2["q"]) and u2["p"] == pytest.approx(want, rel=1e-6)


def test_a_fit_carries_an_uncertainty_that_covers_the_spread_over_noise_seeds(tmp_path):
    """Honest, not decorative: the viscous scale of a worn plant (x 1.3) fitted on traces that differ only by
    their noise seed scatters by no more than about the uncertainty each fit reports."""
    values, sigmas = [], []
    for path in _traces(tmp_path, range(1, 6), "--effect", "viscous:scale=1.3", duration="2"):
        prep = prepare(Trace.read(path), load_plant("rigid-x"), path)
        fit = run_fitter("viscous", prep)
        values.append(fit.params["scale"])
        sigmas.append(fit.uncertainty["scale"])
    values, sigmas = np.array(values), np.array(sigmas)
    assert np.all(np.isfinite(sigmas)) and np.all(sigmas > 0)
    assert np.all(np.abs(values - 1.3) < 4 * sigmas)
    assert np.std(values, ddof=1) < 2 * np.median(sigmas)


def test_analyze_on_a_store_with_nothing_new_starts_no_cluster(tmp_path):
    with Store(tmp_path / "store") as s:
        assert analyze(s, scheduler="tcp://127.0.0.1:9") == (0, 0)  # no connection tried: nothing to do


def test_health_baseline_runs_in_the_configuration(tmp_path):
    from drivectl.machine.config import DEFAULT_CONFIG_TOML, ConfigError, load_config

    cfg = tmp_path / "machine.toml"
    cfg.write_text(DEFAULT_CONFIG_TOML + "\n[health]\nbaseline_runs = 5\n")
    assert load_config(str(cfg)).health_baseline_runs == 5
    cfg.write_text(DEFAULT_CONFIG_TOML + "\n[health]\nbaseline_runs = 0\n")
    with pytest.raises(ConfigError, match=r"machine.toml: health.baseline_runs: expected an integer >= 1, got 0"):
        load_config(str(cfg))

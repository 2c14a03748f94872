"""The health store (drivectl health ingest): Parquet per run, a DuckDB catalog, idempotent by sha256,
refusals in one line, order by started_utc, and a killed ingest that leaves the catalog as it was."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("duckdb")
pq = pytest.importorskip("pyarrow.parquet")

from drivectl.tools.cli.main import main  # noqa: E402
from drivectl.tools.health.store import CATALOG, KILL_HOOK_ENV, Store  # noqa: E402
from drivectl.tracefile.format import Trace  # noqa: E402


def _trace(path: Path, n: int, seed: int, **meta: str) -> Path:
    """A short trace (format v1) written by the project's own writer."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 1e-3
    ref = 0.01 * np.sin(2 * np.pi * t)
    cols = {"time_s": t, "ref_m": ref, "pos_m": ref + 1e-7 * rng.standard_normal(n),
            "effort": 10 * rng.standard_normal(n), "vel_m_s": np.gradient(ref, t)}
    return Trace(cols, {"axis": "x", "dt_s": "0.001", "plant": "rigid-x", "controller": "mbc", "stop": "completed",
                        **meta}).write(path)


@pytest.fixture
def traces(tmp_path):
    d = tmp_path / "traces"
    # started_utc in the header wins over the file name's stamp, which wins over the mtime
    a = _trace(d / "x-20261101T080000Z.csv", 300, 1, started_utc="2026-12-02T08:00:00Z")
    b = _trace(d / "x-20261030T080000Z.csv", 250, 2, started_utc="2026-12-03T08:00:00Z")
    c = _trace(d / "x-20261201T090000Z.csv", 200, 3)
    return a, b, c


def _catalog(store: Path) -> list[tuple]:
    import duckdb

    con = duckdb.connect(str(store / CATALOG), read_only=True)
    try:
        return con.execute("SELECT run_index, sha256, started_utc, started_from, samples, parquet, duration_s "
                           "FROM runs_ordered ORDER BY run_index").fetchall()
    finally:
        con.close()


def test_ingest_keeps_samples_in_parquet_and_orders_by_started_utc(tmp_path, traces, capsys):
    store = tmp_path / "store"
    a, b, c = traces
    d = _trace(tmp_path / "traces" / "run.csv", 150, 4)  # no header, no stamp: its mtime, 2026-11-15
    when = datetime(2026, 11, 15, tzinfo=UTC).timestamp()
    os.utime(d, (when, when))
    assert main(["health", "ingest", str(a), str(b), str(c), str(d), "--machine", "m1", "--store", str(store)]) == 0
    assert "4 added" in capsys.readouterr().out
    rows = _catalog(store)
    # d (mtime 11-15), c (file name 12-01), a (header 12-02; its name says 11-01), b (header 12-03; name 10-30)
    assert [r[4] for r in rows] == [150, 200, 300, 250]
    assert [r[3] for r in rows] == ["mtime", "file name", "header", "header"]
    assert [r[2].isoformat() for r in rows] == ["2026-11-15T00:00:00", "2026-12-01T09:00:00",
                                                "2026-12-02T08:00:00", "2026-12-03T08:00:00"]
    for r, path in zip(rows, (d, c, a, b), strict=True):
        table = pq.read_table(store / r[5])
        trace = Trace.read(path)
        assert table.num_rows == len(trace) == r[4]
        assert table.column_names == list(trace.columns)
        np.testing.assert_array_equal(table.column("pos_m").to_numpy(), trace.pos)
        assert r[6] == pytest.approx(len(trace) * 1e-3)


def test_the_same_trace_twice_changes_nothing(tmp_path, traces, capsys):
    store = tmp_path / "store"
    a, b, _ = traces
    assert main(["health", "ingest", str(a), "--machine", "m1", "--store", str(store)]) == 0
    before = _catalog(store)
    files = sorted(store.rglob("*.parquet"))
    mtimes = [f.stat().st_mtime_ns for f in files]
    capsys.readouterr()
    assert main(["health", "ingest", str(a), "--machine", "m1", "--store", str(store)]) == 0
    assert "0 added, 1 already there" in capsys.readouterr().out
    assert _catalog(store) == before
    assert sorted(store.rglob("*.parquet")) == files and [f.stat().st_mtime_ns for f in files] == mtimes
    # a copy under another name is the same run (its sha256)
    copy = tmp_path / "copy.csv"
    copy.write_bytes(a.read_bytes())
    assert main(["health", "ingest", str(copy), str(b), "--machine", "m1", "--store", str(store)]) == 0
    assert len(_catalog(store)) == 2


def test_bad_files_are_refused_in_one_line_and_the_others_go_in(tmp_path, traces, capsys):
    store = tmp_path / "store"
    a, b, c = traces
    foreign = tmp_path / "foreign.csv"
    foreign.write_text("when,what\n1,2\n")
    garbled = tmp_path / "x-20261203T000000Z.csv"
    garbled.write_text(a.read_text().replace("0.001000,", "0.001000,zz", 1))
    incomplete = tmp_path / "x-20261204T000000Z.csv"  # a streamed record cut by a kill: no end marker
    incomplete.write_text(a.read_text().replace("# dt_s", "# recording: streamed\n# dt_s"))
    missing = tmp_path / "gone.csv"
    argv = [str(a), str(foreign), str(b), str(garbled), str(incomplete), str(missing), str(c)]
    assert main(["health", "ingest", *argv, "--machine", "m1", "--store", str(store)]) == 2
    cap = capsys.readouterr()
    lines = cap.err.strip().splitlines()
    assert len(lines) == 4
    for bad, line in zip((foreign, garbled, incomplete, missing), lines, strict=True):
        assert str(bad) in line
    assert "incomplete" in lines[2]
    assert "3 added, 0 already there, 4 refused" in cap.out
    assert len(_catalog(store)) == 3
    assert main(["health", "ingest", str(a), str(b), "--machine", "m1", "--store", str(store)]) == 0


def test_a_killed_ingest_leaves_the_catalog_as_it_was(tmp_path, traces):
    store = tmp_path / "store"
    a, b, _ = traces
    with Store(store) as s:
        assert s.ingest(a, "m1").status == "added"
    before = _catalog(store)
    env = {**os.environ, KILL_HOOK_ENV: "1"}
    p = subprocess.run([sys.executable, "-m", "drivectl", "health", "ingest", str(b), "--machine", "m1",
                        "--store", str(store)], env=env, capture_output=True, text=True, timeout=60)
    assert p.returncode == -signal.SIGKILL, p.stderr
    assert len(list(store.rglob("*.parquet"))) == 2  # b's samples were in place when it died
    assert _catalog(store) == before
    # the next ingest of b writes it again and catalogs it
    with Store(store) as s:
        assert s.ingest(b, "m1").status == "added"
        assert len(s.runs()) == 2


def test_store_from_the_configuration_and_the_machine_name_checked(tmp_path, traces, capsys, monkeypatch):
    a = traces[0]
    cfg = tmp_path / "machine.toml"
    from drivectl.machine.config import DEFAULT_CONFIG_TOML

    cfg.write_text(DEFAULT_CONFIG_TOML + '\n[health]\nstore = "health-store"\n')
    assert main(["--config", str(cfg), "health", "ingest", str(a), "--machine", "m1"]) == 0
    assert len(_catalog(tmp_path / "health-store")) == 1
    from drivectl.machine.config import load_config
    from drivectl.machine.config_io import show_text

    shown = show_text(load_config(cfg))
    assert f'[health]\nstore = "{tmp_path / "health-store"}"' in shown
    bad = tmp_path / "bad.toml"
    bad.write_text(DEFAULT_CONFIG_TOML + '\n[health]\nstores = "x"\n')
    assert main(["--config", str(bad), "health", "ingest", str(a), "--machine", "m1"]) == 2
    assert "health.stores: unknown key" in capsys.readouterr().err
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg"))
    monkeypatch.delenv("DRIVECTL_CONFIG", raising=False)
    assert main(["health", "ingest", str(a), "--machine", "m1"]) == 0
    assert len(_catalog(tmp_path / "xdg" / "drivectl" / "health")) == 1
    capsys.readouterr()
    assert main(["health", "ingest", str(a), str(a), "--machine", "../up", "--store", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--machine" in err[0]
    assert not (tmp_path / "s").exists()  # refused before the store is made


def test_a_bus_log_goes_in_through_the_converter_and_is_refused_without_it(tmp_path, monkeypatch):
    import types

    log = tmp_path / "quench.asc"
    log.write_text("date Thu Dec 3 08:00:00 2026\n")
    store = tmp_path / "store"
    with Store(store) as s:
        monkeypatch.setitem(sys.modules, "drivectl.tools.buslog", None)  # no converter: import fails
        out = list(s.ingest_all([log], "m1"))
        assert out[0].status == "refused" and str(log) in out[0].detail and "bus log" in out[0].detail
        calls = []

        def log_to_trace(path, *, axis, out_dir, node=None, eds=None, config=None):
            calls.append((Path(path), axis))
            return _trace(Path(out_dir) / f"{axis}.csv", 120, 9, axis=axis)

        fake = types.SimpleNamespace(is_bus_log=lambda p: Path(p).suffix == ".asc", log_to_trace=log_to_trace)
        monkeypatch.setitem(sys.modules, "drivectl.tools.buslog", fake)
        assert s.ingest(log, "m1", axis="y").status == "added"
        assert calls == [(log, "y")]
        (run,) = s.runs()
        assert run["axis"] == "y" and run["samples"] == 120 and run["started_from"] == "mtime"
        assert s.ingest(log, "m1", axis="y").status == "present"  # the log's sha256


def test_without_the_health_extra_one_line_names_it(tmp_path, traces, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "duckdb", None)
    assert main(["health", "ingest", str(traces[0]), "--machine", "m1", "--store", str(tmp_path / "s")]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert "duckdb" in line and "pip install 'drivectl[health]'" in line

"""The health store (docs/health.md): one Parquet file of samples per run and a DuckDB catalog.

```
STORE/
  catalog.duckdb                          tables runs, fits; view runs_ordered
  samples/MACHINE/AXIS/STAMP-SHA12.parquet
```
A run is its trace's sha256: ingesting the same file twice changes nothing. The Parquet file is written
to a temporary name and renamed into place first; the catalog row follows in one transaction, so a
killed ingest leaves the catalog as it was before that run (at worst a Parquet file no row names, which
the next ingest of that trace writes again under the same name).
"""

from __future__ import annotations

import json
import os
import re
import signal
import tempfile
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from drivectl.errors import InputError
from drivectl.tools.health.deps import need
from drivectl.tracefile.format import Trace, TraceError, atomic_write_bytes, file_sha256
from drivectl.tracefile.stream import clean_stale, safe_name

if TYPE_CHECKING:
    from drivectl.plant_emulator.models import PlantSpec

CATALOG = "catalog.duckdb"
SAMPLES = "samples"
#: test hook: set to 1, an ingest SIGKILLs itself after a run's Parquet file is in place and before its
#: catalog row is written (tests/test_health_store.py checks that the catalog is then unchanged)
KILL_HOOK_ENV = "DRIVECTL_HEALTH_TEST_KILL_BEFORE_CATALOG"

SCHEMA = """
CREATE TABLE IF NOT EXISTS runs (
    sha256 VARCHAR PRIMARY KEY,        -- of the file ingested (the trace, or the bus log it came from)
    machine VARCHAR NOT NULL,
    axis VARCHAR NOT NULL,
    started_utc TIMESTAMP NOT NULL,    -- UTC, no zone
    started_from VARCHAR NOT NULL,     -- 'header' (# started_utc), 'file name' (AXIS-STAMP.csv) or 'mtime'
    plant VARCHAR,
    controller VARCHAR,
    stop VARCHAR,                      -- the trace's stop reason
    duration_s DOUBLE,
    samples BIGINT,
    parquet VARCHAR NOT NULL,          -- relative to the store
    source VARCHAR,                    -- the file as it was named to ingest
    ingested_utc TIMESTAMP NOT NULL
);
CREATE TABLE IF NOT EXISTS fits (
    run VARCHAR NOT NULL,              -- runs.sha256
    effect VARCHAR NOT NULL,           -- docs/effects.md
    parameter VARCHAR NOT NULL,
    value DOUBLE,
    uncertainty DOUBLE,
    gap DOUBLE,
    PRIMARY KEY (run, effect, parameter)
);
CREATE TABLE IF NOT EXISTS baselines (
    machine VARCHAR NOT NULL,
    axis VARCHAR NOT NULL,
    model VARCHAR NOT NULL,            -- the baseline as a plant TOML (drivectl's plant file format)
    runs VARCHAR NOT NULL,             -- JSON list of the sha256 of the runs it is the model of
    made_utc TIMESTAMP NOT NULL,
    PRIMARY KEY (machine, axis)
);
CREATE OR REPLACE VIEW runs_ordered AS
    SELECT row_number() OVER (PARTITION BY machine, axis ORDER BY started_utc, sha256) - 1 AS run_index, *
    FROM runs;
"""

_STAMP = re.compile(r"(?P<axis>[A-Za-z0-9][A-Za-z0-9_+-]{0,63}?)-(?P<stamp>\d{8}T\d{6}Z)(-\d+)?\.csv(\.gz)?")
_STAMP_FMT = "%Y%m%dT%H%M%SZ"
#: suffixes of the bus logs python-can reads: refused in one line when the converter is not there
_LOG_SUFFIXES = (".asc", ".blf", ".log", ".trc", ".mf4", ".csv.log")


def default_store() -> Path:
    """``$XDG_DATA_HOME/drivectl/health``, else ``~/.local/share/drivectl/health``."""
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base) / "drivectl" / "health"


@dataclass(frozen=True)
class Outcome:
    """What became of one file: ``added``, ``present`` (already in the store) or ``refused`` (``detail``
    is the one line why, naming the file)."""

    path: Path
    status: str
    detail: str = ""
    sha256: str = ""


sha256_of = file_sha256


def started(path: Path, meta: dict[str, str]) -> tuple[datetime, str]:
    """When the run started (UTC, naive) and where that came from: the ``started_utc`` header, else the
    stamp of an ``AXIS-STAMP.csv`` name, else the file's mtime."""
    text = meta.get("started_utc", "").strip()
    if text:
        for parse in (lambda s: datetime.strptime(s, _STAMP_FMT).replace(tzinfo=UTC), datetime.fromisoformat):
            try:
                t = parse(text)
            except ValueError:
                continue
            if t.tzinfo is None:
                t = t.replace(tzinfo=UTC)
            return t.astimezone(UTC).replace(tzinfo=None), "header"
        raise TraceError(f"{path}: started_utc: expected an ISO 8601 UTC time (2026-12-03T08:21:56Z), got {text!r}")
    m = _STAMP.fullmatch(path.name)
    if m:
        return datetime.strptime(m["stamp"], _STAMP_FMT), "file name"
    return datetime.fromtimestamp(path.stat().st_mtime, UTC).replace(tzinfo=None), "mtime"


class Store:
    """A health store at ``root`` (created on first use). Use as a context manager, or :meth:`close`."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root).expanduser()
        duckdb = need("duckdb")
        try:
            self.root.mkdir(parents=True, exist_ok=True)
            self.con = duckdb.connect(str(self.root / CATALOG))
        except OSError as exc:
            raise InputError(f"--store {self.root}: cannot open: {exc.strerror or exc}") from None
        except duckdb.Error as exc:
            raise InputError(f"--store {self.root}: {CATALOG}: {str(exc).splitlines()[0]}") from None
        self.con.execute(SCHEMA)

    def __enter__(self) -> Store:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self.con.close()

    # ---------------------------------------------------------------------------------------------
    def has(self, sha: str) -> bool:
        return self.con.execute("SELECT 1 FROM runs WHERE sha256 = ?", [sha]).fetchone() is not None

    def runs(self) -> list[dict[str, Any]]:
        """Every run, in time order per machine and axis (the view ``runs_ordered``)."""
        cur = self.con.execute("SELECT * FROM runs_ordered ORDER BY machine, axis, run_index")
        names = [d[0] for d in cur.description]
        return [dict(zip(names, row, strict=True)) for row in cur.fetchall()]

    def first_runs(self, machine: str, axis: str, n: int) -> list[dict[str, Any]]:
        """The first ``n`` runs of an axis in time order (fewer when it has fewer)."""
        cur = self.con.execute("SELECT * FROM runs_ordered WHERE machine = ? AND axis = ? AND run_index < ? "
                               "ORDER BY run_index", [machine, axis, n])
        names = [d[0] for d in cur.description]
        return [dict(zip(names, row, strict=True)) for row in cur.fetchall()]

    def baseline(self, machine: str, axis: str) -> PlantSpec | None:
        """The baseline kept for an axis (drivectl health analyze), or None."""
        import tomllib

        from drivectl.plant_emulator.models import plant_from_mapping

        row = self.con.execute("SELECT model FROM baselines WHERE machine = ? AND axis = ?", [machine, axis]).fetchone()
        if row is None:
            return None
        return plant_from_mapping(tomllib.loads(row[0]), f"{self.root / CATALOG}: baselines {machine}/{axis}",
                                  f"baseline {machine}/{axis}")

    def set_baseline(self, machine: str, axis: str, spec: PlantSpec, runs: list[str]) -> None:
        """Keep an axis's baseline (one transaction)."""
        text = spec.to_toml(f"drivectl health: the baseline of {machine}/{axis}, the model of its first "
                            f"{len(runs)} runs")
        self.con.begin()
        try:
            self.con.execute("INSERT OR REPLACE INTO baselines VALUES (?, ?, ?, ?, ?)",
                             [machine, axis, text, json.dumps(runs), datetime.now(UTC).replace(tzinfo=None)])
            self.con.commit()
        except BaseException:
            self.con.rollback()
            raise

    def add_fits(self, sha: str, rows: list[tuple[str, str, float, float | None, float]]) -> None:
        """A run's fits (effect, parameter, value, uncertainty, gap), in one transaction."""
        self.con.begin()
        try:
            self.con.execute("DELETE FROM fits WHERE run = ?", [sha])
            self.con.executemany("INSERT INTO fits VALUES (?, ?, ?, ?, ?, ?)", [(sha, *r) for r in rows])
            self.con.commit()
        except BaseException:
            self.con.rollback()
            raise

    def ingest_all(self, paths: Iterable[str | Path], machine: str, *, axis: str | None = None,
                   config: Any = None) -> Iterator[Outcome]:
        """:meth:`ingest` each file; a refused one is reported and the others go on (a bad ``machine`` is
        refused once, before any file)."""
        check_machine(machine)
        for p in paths:
            try:
                yield self.ingest(Path(p), machine, axis=axis, config=config)
            except InputError as exc:
                yield Outcome(Path(p), "refused", str(exc))

    def ingest(self, path: Path, machine: str, *, axis: str | None = None, config: Any = None) -> Outcome:
        """Keep one trace (or bus log) in the store. Raises :class:`InputError` (one line naming the file)
        for a file that is unreadable, incomplete or not a trace."""
        check_machine(machine)
        try:
            sha = sha256_of(path)
        except FileNotFoundError:
            raise InputError(f"{path}: no such file") from None
        except OSError as exc:
            raise InputError(f"{path}: cannot read: {exc.strerror or exc}") from None
        if self.has(sha):
            return Outcome(path, "present", sha256=sha)
        with _as_trace(path, axis, config) as trace_path:
            trace = Trace.read(trace_path)
            when, source = started(path, trace.meta)
        if trace.meta.get("trace_complete") == "false":
            raise InputError(f"{path}: incomplete trace (no end marker: the run was killed or is still running)")
        run_axis = trace.meta.get("axis") or axis or _axis_from_name(path)
        if not run_axis or not safe_name(run_axis):
            raise InputError(f"{path}: axis: the trace names none that can be used ({run_axis!r}; give --axis)")
        named = trace.meta.get("machine")
        if named and named != machine:
            raise InputError(f"{path}: machine: the trace says {named!r}, --machine says {machine!r}")
        rel = Path(SAMPLES) / machine / run_axis / f"{when.strftime(_STAMP_FMT)}-{sha[:12]}.parquet"
        _write_parquet(self.root / rel, trace, sha)
        if os.environ.get(KILL_HOOK_ENV) == "1":  # test hook (see KILL_HOOK_ENV)
            os.kill(os.getpid(), signal.SIGKILL)
        row = [sha, machine, run_axis, when, source, trace.meta.get("plant"), trace.meta.get("controller"),
               trace.meta.get("stop"), _duration(trace), len(trace), rel.as_posix(), str(path),
               datetime.now(UTC).replace(tzinfo=None)]
        self.con.begin()
        try:
            self.con.execute(f"INSERT INTO runs VALUES ({', '.join('?' * len(row))})", row)
            self.con.commit()
        except BaseException:
            self.con.rollback()
            raise
        return Outcome(path, "added", sha256=sha)


def check_machine(machine: str) -> None:
    if not safe_name(machine):
        raise InputError(f"--machine {machine!r}: expected letters, digits, _ + - (a file name stem)")


def _duration(trace: Trace) -> float:
    dt = trace.dt
    return len(trace) * dt if dt > 0 else float(trace.time[-1] - trace.time[0])


def _axis_from_name(path: Path) -> str | None:
    m = _STAMP.fullmatch(path.name)
    return m["axis"] if m else None


def _write_parquet(path: Path, trace: Trace, sha: str) -> None:
    """The samples, one float64 column each, the trace's metadata as JSON in the file's key-value
    metadata; a temporary beside ``path``, fsync, then rename (``.NAME.PID.RANDOM.tmp``: removed by
    clean_stale once its writer is gone)."""
    pa = need("pyarrow")
    pq = need("pyarrow.parquet")
    path.parent.mkdir(parents=True, exist_ok=True)
    clean_stale(path.parent)
    table = pa.table({k: pa.array(v) for k, v in trace.columns.items()})
    table = table.replace_schema_metadata({"drivectl.trace_meta": json.dumps(trace.meta),
                                           "drivectl.sha256": sha})
    buf = pa.BufferOutputStream()  # one run is small: serialised in memory, then the project's atomic write
    pq.write_table(table, buf, compression="zstd")
    atomic_write_bytes(path, buf.getvalue().to_pybytes())


@contextmanager
def _as_trace(path: Path, axis: str | None, config: Any) -> Iterator[Path]:
    """The trace to read for ``path``: the file itself, or, for a bus log, the trace
    drivectl.tools.buslog makes of it (in a temporary folder)."""
    try:
        from drivectl.tools.buslog import is_bus_log, log_to_trace
    except ImportError:
        if path.name.lower().endswith(_LOG_SUFFIXES):
            raise InputError(f"{path}: a bus log, and this drivectl has no bus-log reader (drivectl.tools.buslog)"
                             ) from None
        yield path
        return
    if not is_bus_log(path):
        yield path
        return
    if not axis:
        raise InputError(f"{path}: a bus log: --axis names the axis it holds")
    with tempfile.TemporaryDirectory(prefix="drivectl-health-") as tmp:
        yield Path(log_to_trace(path, axis=axis, out_dir=Path(tmp), config=config))

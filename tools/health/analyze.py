"""``drivectl health analyze``: every run without fits, fitted on Dask workers with explain's own fitters.

Each run gets one fit per effect of the vocabulary (docs/effects.md), each by the fitter of
``drivectl explain`` of that name (tools/explain/fit.py ``FITTERS``, ``run_fitter``: one home for the
fitting), on top of the run's baseline. A worker reads the run's Parquet file itself (no sample goes
through the scheduler) and returns the fitted parameters; this process alone writes the catalog, one
transaction per run, so an interrupted analysis keeps every run that finished.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from drivectl.errors import InputError
from drivectl.tools.health.deps import need


def effect_fitters() -> list[str]:
    """The fitter of each vocabulary effect: the effect's own name in FITTERS (viscous: one scale; the
    per-direction variant "viscous+-" is explain's alternative, not a second parameter set)."""
    from drivectl.plant_emulator.effects import EFFECTS
    from drivectl.tools.explain.fit import FITTERS

    return [k for k in FITTERS if k in EFFECTS]


@dataclass(frozen=True)
class RunFits:
    """What a worker sends back for one run: rows (effect, parameter, value, uncertainty, gap), or why
    the run could not be fitted (one line)."""

    sha256: str
    rows: list[tuple[str, str, float, float | None, float]]
    error: str = ""
    cpu_s: float = 0.0


def baseline_name(meta: dict[str, str], configured: str | None) -> str | None:
    """The model a run is fitted against: the configuration's commissioning model (``axes.NAME.model``)
    when it names one, else the model the run's controller held (``# model:``), else its ``# plant:``."""
    return configured or meta.get("model") or meta.get("plant")


def fit_run(parquet: str, sha256: str, configured_model: str | None = None) -> RunFits:
    """On a worker: read the run's samples from ``parquet`` and fit every effect (module-level: dask
    pickles it by name)."""
    import time

    from threadpoolctl import threadpool_limits

    from drivectl.plant_emulator.models import load_plant
    from drivectl.tools.explain.data import prepare
    from drivectl.tools.explain.fit import SPLITTING, run_fitter
    from drivectl.tracefile.format import Trace

    cpu0 = time.process_time()
    try:
        pq = need("pyarrow.parquet")
        table = pq.read_table(parquet)
        raw = (table.schema.metadata or {}).get(b"drivectl.trace_meta", b"{}")
        meta = json.loads(raw)
        trace = Trace({name: table.column(name).to_numpy() for name in table.column_names}, meta, parquet)
        name = baseline_name(meta, configured_model)
        if not name:
            raise InputError(f"{parquet}: no baseline model (the trace names no model or plant, nor the "
                             "configuration)")
        spec = load_plant(name)
        rows = []
        with threadpool_limits(limits=1):
            prep = prepare(trace, spec, parquet)
            two_body = len(spec.design().bodies) == 2
            for key in effect_fitters():
                if two_body and key in SPLITTING:
                    continue
                fit = run_fitter(key, prep)
                rows += [(fit.effect, p, float(v), None, float(fit.gap)) for p, v in fit.params.items()]
        return RunFits(sha256, rows, cpu_s=time.process_time() - cpu0)
    except Exception as exc:  # noqa: BLE001 - a run that cannot be fitted is said, the others go on
        line = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        return RunFits(sha256, [], error=f"run {sha256[:12]}: {line}", cpu_s=time.process_time() - cpu0)


def pending(store: Any) -> list[dict[str, Any]]:
    """Runs without fits, in time order."""
    cur = store.con.execute("SELECT * FROM runs_ordered WHERE sha256 NOT IN (SELECT DISTINCT run FROM fits) "
                            "ORDER BY started_utc, sha256")
    names = [d[0] for d in cur.description]
    return [dict(zip(names, row, strict=True)) for row in cur.fetchall()]


def analyze(store: Any, *, scheduler: str | None = None, workers: int | None = None,
            models: dict[str, str] | None = None, progress: bool = False,
            on_error: Callable[[str], None] | None = None) -> tuple[int, int]:
    """Fit every run of ``store`` without fits on a Dask cluster: ``scheduler`` (``tcp://HOST:8786``), else
    an embedded LocalCluster of ``workers`` processes (default: the cores that are free). ``models``: axis
    -> the configured commissioning model. Returns (runs fitted, runs that failed)."""
    todo = pending(store)
    if not todo:
        return 0, 0
    distributed = need("distributed")
    cluster = None
    if scheduler:
        try:
            client = distributed.Client(scheduler, timeout="10s")
        except (OSError, TimeoutError) as exc:
            raise InputError(f"--scheduler {scheduler}: cannot connect: {exc}") from None
    else:
        from drivectl.tools.explain.core import choose_workers

        n = workers or min(choose_workers(), len(todo))
        cluster = distributed.LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                           dashboard_address=None, silence_logs=40)
        client = distributed.Client(cluster)
    models = models or {}
    done = failed = 0
    bar = None
    try:
        futures = [client.submit(fit_run, str(store.root / r["parquet"]), r["sha256"], models.get(r["axis"]),
                                 key=f"health-fit-{r['sha256']}", pure=False) for r in todo]
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=len(futures), desc="health analyze", unit="run", leave=False)
        for fut in distributed.as_completed(futures):
            res: RunFits = fut.result()
            if res.error:
                failed += 1
                if on_error:
                    on_error(res.error)
            else:
                store.add_fits(res.sha256, res.rows)
                done += 1
            if bar is not None:
                bar.update()
    finally:
        if bar is not None:
            bar.close()
        client.close()
        if cluster is not None:
            cluster.close()
    return done, failed

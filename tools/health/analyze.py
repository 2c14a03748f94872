"""``drivectl health analyze``: every run without fits, fitted on Dask workers with explain's own fitters.

Each run gets one fit per effect of the vocabulary (docs/effects.md), each by the fitter of
``drivectl explain`` of that name (tools/explain/fit.py ``FITTERS``, ``run_fitter``: one home for the
fitting, and for each value's uncertainty, ``Fit.uncertainty``), on top of its axis's baseline: the
configured commissioning model, else the model of the axis's first runs (:func:`baselines`, kept in the
catalog). A worker reads the run's Parquet file itself (no sample goes through the scheduler) and
returns the fitted parameters; this process alone writes the catalog, one transaction per run, so an
interrupted analysis keeps every run that finished. docs/health.md.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from drivectl.errors import InputError
from drivectl.tools.health.deps import need

if TYPE_CHECKING:
    from drivectl.plant_emulator.models import PlantSpec
    from drivectl.tracefile.format import Trace

#: runs of an axis whose model is its baseline when the configuration names no commissioning model
#: (``[health] baseline_runs``): a majority of them must show an effect for it to be in the baseline
BASELINE_RUNS = 3
#: how long ``--scheduler ADDRESS`` may take to answer before it is said in one line, s
CONNECT_TIMEOUT_S = 10.0


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
    #: CPU time of the fit, s: of the thread that ran it (a Dask worker's own threads, its heartbeats and
    #: messages, are not the fit's)
    cpu_s: float = 0.0


def nominal_name(meta: dict[str, str]) -> str | None:
    """The model a run names: the one its controller held (``# model:``), else its ``# plant:``."""
    return meta.get("model") or meta.get("plant")


def read_run(parquet: str) -> Trace:
    """A run's samples and metadata, read from its Parquet file (on a worker)."""
    from drivectl.tracefile.format import Trace

    pq = need("pyarrow.parquet")
    table = pq.read_table(parquet)
    meta = json.loads((table.schema.metadata or {}).get(b"drivectl.trace_meta", b"{}"))
    return Trace({name: table.column(name).to_numpy() for name in table.column_names}, meta, parquet)


def fit_run(parquet: str, sha256: str, baseline: PlantSpec) -> RunFits:
    """On a worker: read the run's samples from ``parquet`` and fit every effect on top of ``baseline``
    (module-level: dask pickles it by name). Each row carries the fit's uncertainty (explain's
    ``Fit.uncertainty``); a parameter the run does not constrain has none (NULL)."""
    import math
    import time

    from threadpoolctl import threadpool_limits

    from drivectl.tools.explain.data import prepare
    from drivectl.tools.explain.fit import SPLITTING, run_fitter

    cpu0 = time.thread_time()
    try:
        trace = read_run(parquet)
        rows = []
        with threadpool_limits(limits=1):
            prep = prepare(trace, baseline, parquet)
            two_body = len(baseline.design().bodies) == 2
            for key in effect_fitters():
                if two_body and key in SPLITTING:
                    continue
                fit = run_fitter(key, prep)
                for p, v in fit.params.items():
                    u = fit.uncertainty.get(p, math.inf)
                    rows.append((fit.effect, p, float(v), float(u) if math.isfinite(u) else None, float(fit.gap)))
        return RunFits(sha256, rows, cpu_s=time.thread_time() - cpu0)
    except Exception as exc:  # noqa: BLE001 - a run that cannot be fitted is said, the others go on
        line = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        return RunFits(sha256, [], error=f"run {sha256[:12]}: {line}", cpu_s=time.thread_time() - cpu0)


def explain_run(parquet: str, nominal: PlantSpec) -> list[dict[str, Any]]:
    """On a worker: what ``drivectl explain`` names in one run against ``nominal`` (its effects, in
    order, with their parameters): the raw material of a baseline from an axis's first runs."""
    from drivectl.tools.explain.core import explain

    res = explain(read_run(parquet), nominal, source=parquet, workers=1)
    return [{"effect": e["effect"], "params": {**e["params"], **e.get("extra", {})}} for e in res.effects]


def combine_baseline(nominal: PlantSpec, named: list[list[dict[str, Any]]]) -> PlantSpec:
    """The model of an axis's first runs: ``nominal`` with every effect explain named in a majority of
    them (``named``: one list of effects per run), each at the median of its parameters over the runs
    that named it; one-mass effects only (a lash or a mode named at commissioning is left to its own
    fit, which a two-body baseline would refuse: its width or frequency is then the trend's start)."""
    import statistics

    from drivectl.plant_emulator.effects import EFFECTS
    from drivectl.tools.explain.fit import SPLITTING

    spec = nominal
    for effect in EFFECTS:  # the vocabulary's order: one baseline for one set of runs
        if effect in SPLITTING:
            continue
        found = [next(e["params"] for e in run if e["effect"] == effect) for run in named
                 if any(e["effect"] == effect for e in run)]
        if len(found) * 2 <= len(named):
            continue
        keys = set.intersection(*(set(p) for p in found))  # an optional parameter only where all have it
        spec = spec.with_effect(effect, **{k: statistics.median(p[k] for p in found) for k in sorted(keys)})
    return spec


def pending(store: Any) -> list[dict[str, Any]]:
    """Runs without fits, in time order."""
    cur = store.con.execute("SELECT * FROM runs_ordered WHERE sha256 NOT IN (SELECT DISTINCT run FROM fits) "
                            "ORDER BY started_utc, sha256")
    names = [d[0] for d in cur.description]
    return [dict(zip(names, row, strict=True)) for row in cur.fetchall()]


def analyze(store: Any, *, scheduler: str | None = None, workers: int | None = None,
            models: dict[str, str] | None = None, baseline_runs: int = BASELINE_RUNS, progress: bool = False,
            on_error: Callable[[str], None] | None = None,
            on_note: Callable[[str], None] | None = None,
            on_fit: Callable[[RunFits], None] | None = None) -> tuple[int, int]:
    """Fit every run of ``store`` without fits against its axis's baseline, on a Dask cluster:
    ``scheduler`` (``tcp://HOST:8786``), else an embedded LocalCluster of ``workers`` processes (default:
    the cores that are free). ``models``: axis -> the configured commissioning model (the baseline where
    given); else the baseline is the model of the axis's first ``baseline_runs`` runs (:func:`baselines`).
    Returns (runs fitted, runs that failed); runs of an axis still short of its first runs wait (said
    through ``on_note``). ``on_fit`` sees each run's result as it comes (bench/health.py: its CPU time)."""
    todo = pending(store)
    if not todo:
        return 0, 0
    distributed = need("distributed")
    models = models or {}
    configured = _configured(models, {r["axis"] for r in todo})  # a bad model: one line, before any work
    client, cluster = _connect(distributed, scheduler, workers, len(todo))
    done = failed = 0
    bar = None
    try:
        base, refused = baselines(store, client, todo, configured, baseline_runs, on_note)
        for key, line in refused.items():
            n = sum(1 for r in todo if (r["machine"], r["axis"]) == key)
            failed += n
            if on_error:
                on_error(f"{key[0]}/{key[1]}: baseline: {line} ({n} runs not analysed)")
        ready = [r for r in todo if (r["machine"], r["axis"]) in base]
        futures = [client.submit(fit_run, str(store.root / r["parquet"]), r["sha256"], base[(r["machine"], r["axis"])],
                                 key=f"health-fit-{r['sha256']}", pure=False) for r in ready]
        if progress and futures:
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
            if on_fit:
                on_fit(res)
    finally:
        if bar is not None:
            bar.close()
        client.close()
        if cluster is not None:
            cluster.close()
    return done, failed


def _connect(distributed: Any, scheduler: str | None, workers: int | None, runs: int) -> tuple[Any, Any]:
    """A client of ``scheduler``, else of an embedded LocalCluster (one process per worker, one thread
    each: the fits are single-threaded numpy) on the free cores; the same client either way."""
    if scheduler:
        try:
            return distributed.Client(scheduler, timeout=f"{CONNECT_TIMEOUT_S}s"), None
        except (OSError, TimeoutError) as exc:
            raise InputError(f"--scheduler {scheduler}: cannot connect: {exc}") from None
    from drivectl.tools.explain.core import free_cores

    n = workers or max(1, min(free_cores(), runs))
    cluster = distributed.LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None,
                                       silence_logs=40)
    return distributed.Client(cluster), cluster


def _configured(models: dict[str, str], axes: set[str]) -> dict[str, PlantSpec]:
    from drivectl.plant_emulator.models import PlantError, load_plant

    out = {}
    for axis in sorted(axes & set(models)):
        try:
            out[axis] = load_plant(models[axis])
        except PlantError as exc:
            raise InputError(f"axes.{axis}.model: {exc}") from None
    return out


def baselines(store: Any, client: Any, todo: list[dict[str, Any]], configured: dict[str, PlantSpec],
              first: int, on_note: Callable[[str], None] | None = None
              ) -> tuple[dict[tuple[str, str], PlantSpec], dict[tuple[str, str], str]]:
    """The baseline of each (machine, axis) of ``todo``: the configured commissioning model of the axis,
    else the one kept in the catalog, else the model of its first ``first`` runs, made now (explain on
    each, on the workers; :func:`combine_baseline`) and kept, so that every later run is fitted against
    the same model. Returns (baselines, {axis: why it has none}); an axis with fewer runs than ``first``
    has none yet (said through ``on_note``)."""
    from drivectl.plant_emulator.models import PlantError, load_plant

    out: dict[tuple[str, str], PlantSpec] = {}
    refused: dict[tuple[str, str], str] = {}
    make: dict[tuple[str, str], tuple[PlantSpec, list[dict[str, Any]]]] = {}
    for key in sorted({(r["machine"], r["axis"]) for r in todo}):
        machine, axis = key
        if axis in configured:
            out[key] = configured[axis]
            continue
        kept = store.baseline(machine, axis)
        if kept is not None:
            out[key] = kept
            continue
        runs = store.first_runs(machine, axis, first)
        if len(runs) < first:
            if on_note:
                on_note(f"{machine}/{axis}: the baseline is the model of the first {first} runs: "
                        f"{len(runs)} so far, its runs wait")
            continue
        meta = run_meta(str(store.root / runs[0]["parquet"]))
        name = nominal_name(meta)
        try:
            if not name:
                raise PlantError("the first run names no model or plant")
            make[key] = (load_plant(name), runs)
        except PlantError as exc:
            refused[key] = str(exc).splitlines()[0]
    jobs = {key: [client.submit(explain_run, str(store.root / r["parquet"]), nominal, pure=False,
                                key=f"health-baseline-{r['sha256']}") for r in runs]
            for key, (nominal, runs) in make.items()}
    for key, futs in jobs.items():
        nominal, runs = make[key]
        try:
            spec = combine_baseline(nominal, client.gather(futs))
        except InputError as exc:  # a first run explain cannot decide on (too short, no motion)
            refused[key] = str(exc).splitlines()[0]
            continue
        store.set_baseline(key[0], key[1], spec, [r["sha256"] for r in runs])
        out[key] = spec
    return out, refused


def run_meta(parquet: str) -> dict[str, str]:
    """A run's trace metadata, from its Parquet file's footer (no samples read)."""
    pq = need("pyarrow.parquet")
    return json.loads((pq.read_schema(parquet).metadata or {}).get(b"drivectl.trace_meta", b"{}"))

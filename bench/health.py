"""drivectl health at scale: generate histories, ingest them, analyse them on 1 and then 2 Dask workers.

N traces of 10 s (default 200) over two machines' x axes, made by the emulated plant (``drivectl trace
--sim``: SimAxis under the axis's controller, the same trace as through the emulated drive; the batch
simulator of plant_emulator/batch.py takes linear plants only, and a feed axis has Coulomb friction), one
run a shift, every run with its own noise seed and the day's temperature on the viscous friction
(+-3 %). The wear is hidden: machine m1's viscous friction grows from run 40 % of its history on (to
1.6 x at the end), machine m2's backlash opens from 60 % on (to 30 um). Generation is spread on the
same Dask workers and not timed.

Then, timed: ``Store.ingest_all`` of every trace (one process, as ``drivectl health ingest``), and
``health analyze`` (tools/health/analyze.py ``analyze``: the baselines, then one fit per effect per run)
on an embedded LocalCluster of 1 worker, then on a copy of the same store with 2 workers. The fits' CPU
time per run is what the workers measured (``RunFits.cpu_s``).

Targets (docs/health.md): speedup_2_over_1 >= 1.7 on a 2-core machine, and one 10 s run analysed in
<= 3 s of one core. Wall-clock figures depend on what else the machine runs: the table says the load.

    python bench/health.py [--runs N] [--duration S] [--json] [--keep DIR]

``--json`` prints exactly {"runs", "ingest_s", "analyze_s_1", "analyze_s_2", "speedup_2_over_1",
"runs_per_min_per_worker"}; runs_per_min_per_worker is the 2-worker analysis's runs per minute over its
2 workers.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import tempfile
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path

MACHINES = ("m1", "m2")
SHIFT = timedelta(hours=8)
START = datetime(2026, 1, 5, 6, 0, tzinfo=UTC)


def wear(machine: str, i: int, n: int) -> list[str]:
    """The effects of run ``i`` of ``n`` on ``machine`` (``--effect`` texts): the day's temperature on the
    viscous friction, and the hidden wear."""
    scale = 1.0 + 0.03 * ((i % 3) - 1)  # three shifts a day: morning, afternoon, night
    effects = []
    if machine == "m1" and i >= 0.4 * n:
        scale *= 1.0 + 0.6 * (i - 0.4 * n) / (0.6 * n)
    if machine == "m2" and i >= 0.6 * n:
        effects.append(f"backlash:width={max(1e-6, 30e-6 * (i - 0.6 * n) / (0.4 * n)):.3g}")
    return [f"viscous:scale={scale:.4f}", *effects]


def make_trace(out: str, machine: str, i: int, n: int, duration: float) -> str:
    """On a worker: one run, written as format v1 with ``# machine:`` and ``# started_utc:``."""
    from drivectl.tools.cli.main import main
    from drivectl.tracefile.format import Trace

    d = Path(out) / f"{machine}-{i:04d}"
    args = ["trace", "--axis", "x", "--sim", "--duration", str(duration), "--noise", "0.5", "--seed", str(1000 * i + 7),
            "--out", str(d), "--no-plot", "--quiet"]
    for e in wear(machine, i, n):
        args += ["--effect", e]
    import contextlib
    import io

    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        if main(args) != 0:
            raise RuntimeError(f"trace {machine} {i} failed")
    src = d / "x.csv"
    trace = Trace.read(src)
    when = START + i * SHIFT
    for key in ("recording", "trace_complete"):  # written again in one piece, not streamed
        trace.meta.pop(key, None)
    trace.meta["machine"] = machine
    trace.meta["started_utc"] = when.strftime("%Y-%m-%dT%H:%M:%SZ")
    path = Path(out) / f"{machine}-x-{when.strftime('%Y%m%dT%H%M%SZ')}.csv"
    trace.write(path)
    shutil.rmtree(d)
    return str(path)


def generate(out: Path, runs: int, duration: float) -> dict[str, list[str]]:
    from distributed import Client, LocalCluster, as_completed
    from tqdm import tqdm

    per = {m: runs // len(MACHINES) + (1 if k < runs % len(MACHINES) else 0) for k, m in enumerate(MACHINES)}
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                      silence_logs=40) as cluster, Client(cluster) as client:
        futs = {client.submit(make_trace, str(out), m, i, per[m], duration, pure=False): m
                for m in MACHINES for i in range(per[m])}
        paths: dict[str, list[str]] = {m: [] for m in MACHINES}
        for fut in tqdm(as_completed(futs), total=len(futs), desc="generate", unit="trace", leave=False,
                        disable=None):
            paths[futs[fut]].append(fut.result())
    return paths


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=200, help="traces in all (default 200)")
    ap.add_argument("--duration", type=float, default=10.0, help="s per trace (default 10)")
    ap.add_argument("--json", action="store_true", help="print exactly one JSON object")
    ap.add_argument("--keep", metavar="DIR", help="generate into DIR and keep it (default: a temporary folder)")
    args = ap.parse_args()
    if args.runs < 2 * 3:
        ap.error("--runs: at least 6 (each machine's baseline is the model of its first 3 runs)")

    from drivectl.tools.health.analyze import RunFits, analyze
    from drivectl.tools.health.store import Store

    root = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="drivectl-bench-health-"))
    root.mkdir(parents=True, exist_ok=True)
    try:
        t0 = time.perf_counter()
        paths = generate(root / "traces", args.runs, args.duration)
        gen_s = time.perf_counter() - t0
        load_before = os.getloadavg()

        store1 = root / "store-1"
        t0 = time.perf_counter()
        with Store(store1) as s:
            for m in MACHINES:
                bad = [o.detail for o in s.ingest_all(sorted(paths[m]), m) if o.status == "refused"]
                if bad:
                    sys.exit(f"bench: ingest refused {bad[0]}")
        ingest_s = time.perf_counter() - t0
        store2 = root / "store-2"
        shutil.copytree(store1, store2)

        results: dict[int, dict] = {}
        for workers, store in ((1, store1), (2, store2)):
            cpu: list[float] = []

            def took(res: RunFits, cpu: list[float] = cpu) -> None:
                cpu.append(res.cpu_s)

            errors: list[str] = []
            t0 = time.perf_counter()
            with Store(store) as s:
                done, failed = analyze(s, workers=workers, on_error=errors.append, on_fit=took)
            wall = time.perf_counter() - t0
            if failed or done != args.runs:
                sys.exit(f"bench: {workers} worker(s): {done} fitted, {failed} failed: {errors[:1]}")
            results[workers] = {"wall": wall, "cpu": cpu, "load": os.getloadavg()}
    finally:
        if not args.keep:
            shutil.rmtree(root, ignore_errors=True)

    a1, a2 = results[1]["wall"], results[2]["wall"]
    out = {"runs": args.runs, "ingest_s": round(ingest_s, 2), "analyze_s_1": round(a1, 2),
           "analyze_s_2": round(a2, 2), "speedup_2_over_1": round(a1 / a2, 3),
           "runs_per_min_per_worker": round(args.runs / a2 * 60.0 / 2, 2)}
    if args.json:
        print(json.dumps(out))
        return
    cpu = results[1]["cpu"] + results[2]["cpu"]
    print(f"{args.runs} runs of {args.duration:g} s over {len(MACHINES)} machines (generated in {gen_s:.1f} s, "
          f"not timed); load average before {load_before[0]:.2f}")
    print(f"{'step':<26} {'wall s':>9} {'runs/min':>9} {'load after':>11} {'cores got':>10} {'target':>10}")
    print(f"{'ingest (1 process)':<26} {ingest_s:>9.2f} {args.runs / ingest_s * 60:>9.0f}")
    for w in (1, 2):
        r = results[w]
        # the fits' CPU over the wall time: how many cores the pass had for its fits (the machine is shared)
        print(f"{f'analyze, {w} worker(s)':<26} {r['wall']:>9.2f} {args.runs / r['wall'] * 60:>9.1f} "
              f"{r['load'][0]:>11.2f} {sum(r['cpu']) / r['wall']:>10.2f}")
    print(f"{'speedup 2 over 1':<26} {a1 / a2:>9.3f} {'':>9} {'':>11} {'':>10} {'>= 1.7':>10}")
    print(f"{'fit CPU per run (median)':<26} {statistics.median(cpu):>9.3f} {'':>9} {'':>11} {'':>10} {'<= 3 s':>10}")
    print(f"{'fit CPU per run (max)':<26} {max(cpu):>9.3f}")
    print(f"runs per minute per worker (2 workers): {out['runs_per_min_per_worker']}")


if __name__ == "__main__":
    main()

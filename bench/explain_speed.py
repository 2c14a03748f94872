"""Wall and CPU time of `drivectl explain` against issue 17's targets, quiet and under one other job.

Cases (each run as the user runs it: ``python -m drivectl explain FILE --plant P --json --quiet`` in a
fresh process, imports, report and PNG included):

* trace10: a clean 10 s trace of axis x (``drivectl trace --axis x --sim --duration 10``, made first and
  not timed) against ``rigid-x``; target 5 s wall;
* record25: the 25 s EMPS estimation record (emps-train.csv; Janot, Gautier, Brunot, "Data Set and
  Reference Models of EMPS", Nonlinear System Identification Benchmarks workshop 2019), read where it
  is ($DRIVECTL_EMPS_DIR or shared/real/emps in a parent of the repository, never copied) against the
  benchmark's symmetric reference model (bench/explain_traces.emps_plant); target 15 s wall. Skipped
  with a note where the data is absent.

"Under load" = while one CPU-bound process started by this script (a busy loop, stopped after) runs:
the issue's "the load of one other job" on this 2-core machine. CPU seconds are those of the explain
process and its worker processes (getrusage of children). explain picks its worker count itself
(tools/explain.choose_workers); ``--workers N`` forces N (DRIVECTL_EXPLAIN_WORKERS), ``--cases`` picks cases.

    python bench/explain_speed.py                      # table
    python bench/explain_speed.py --json               # exactly one JSON object on stdout
    python bench/explain_speed.py --workers 1 --cases trace10

JSON keys (seconds; null where the case was skipped): ``trace10_wall_s``, ``trace10_cpu_s``,
``trace10_wall_loaded_s``, ``trace10_cpu_loaded_s``, ``record25_wall_s``, ``record25_cpu_s``,
``record25_wall_loaded_s``, ``record25_cpu_loaded_s``, and ``load_avg_1min`` (the machine's 1-minute
load average when the script started, before its own load: read the figures against it).
Exit status 1 when a wall target is missed.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from explain_traces import emps_dir, emps_plant  # noqa: E402

TARGETS = {"trace10": 5.0, "record25": 15.0}


def _busy(stop: Any) -> None:
    x = 0
    while not stop.is_set():
        for _ in range(100_000):
            x += 1


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _drivectl(*args: str) -> list[str]:
    return [sys.executable, "-m", "drivectl", *args]


def timed_explain(path: Path, plant: str, out: Path) -> tuple[float, float]:
    """(wall s, CPU s) of one explain run; raises if it fails or does not print one JSON object."""
    cpu0, t0 = _children_cpu(), time.perf_counter()
    p = subprocess.run(_drivectl("explain", str(path), "--plant", plant, "--json", "--quiet", "--out", str(out)),
                       capture_output=True, text=True)
    wall, cpu = time.perf_counter() - t0, _children_cpu() - cpu0
    if p.returncode != 0:
        raise RuntimeError(f"explain {path.name} failed ({p.returncode}): {p.stderr.strip()[-400:]}")
    json.loads(p.stdout)
    return wall, cpu


def loaded(fn: Any) -> Any:
    """Run ``fn()`` while one CPU-bound process runs."""
    stop = multiprocessing.Event()
    proc = multiprocessing.Process(target=_busy, args=(stop,), daemon=True)
    proc.start()
    try:
        time.sleep(0.5)  # let it take its core
        return fn()
    finally:
        stop.set()
        proc.join(5)
        if proc.is_alive():
            proc.terminate()
            proc.join()


def make_trace10(folder: Path) -> Path:
    subprocess.run(_drivectl("trace", "--axis", "x", "--sim", "--duration", "10", "--out", str(folder), "--no-plot",
                             "--quiet"), check=True, capture_output=True)
    return folder / "x.csv"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")
    ap.add_argument("--workers", type=int, help="explain's worker processes (default: its own choice)")
    ap.add_argument("--cases", default="trace10,record25", help="comma-separated: trace10, record25")
    args = ap.parse_args(argv)
    wanted = [c.strip() for c in args.cases.split(",") if c.strip()]
    if bad := [c for c in wanted if c not in TARGETS]:
        ap.error(f"--cases: unknown {', '.join(bad)} (known: {', '.join(TARGETS)})")
    if args.workers is not None:
        if args.workers < 1:
            ap.error("--workers: must be >= 1")
        os.environ["DRIVECTL_EXPLAIN_WORKERS"] = str(args.workers)
    res: dict[str, Any] = {"load_avg_1min": os.getloadavg()[0]}
    notes = []
    with tempfile.TemporaryDirectory() as tmp:
        tmpd = Path(tmp)
        cases: dict[str, tuple[Path, str] | None] = {"trace10": None, "record25": None}
        if "trace10" in wanted:
            cases["trace10"] = (make_trace10(tmpd / "t10"), "rigid-x")
        d = emps_dir()
        if "record25" not in wanted:
            pass
        elif d is None:
            notes.append("record25: EMPS records absent (set DRIVECTL_EMPS_DIR), skipped")
        else:
            plant = tmpd / "emps-reference.plant.toml"
            plant.write_text(emps_plant().to_toml("EMPS reference model (symmetric), bench/explain_traces.py"))
            cases["record25"] = (d / "emps-train.csv", str(plant))
        for name, case in cases.items():
            for key in ("wall_s", "cpu_s", "wall_loaded_s", "cpu_loaded_s"):
                res[f"{name}_{key}"] = None
            if case is None:
                continue
            path, plant_arg = case
            out = tmpd / name
            print(f"explain {name} quiet ...", file=sys.stderr)
            res[f"{name}_wall_s"], res[f"{name}_cpu_s"] = timed_explain(path, plant_arg, out)
            print(f"explain {name} under one CPU-bound process ...", file=sys.stderr)
            w, c = loaded(lambda p=path, a=plant_arg, o=out: timed_explain(p, a, o))
            res[f"{name}_wall_loaded_s"], res[f"{name}_cpu_loaded_s"] = w, c
    missed = [n for n, tgt in TARGETS.items() for k in ("wall_s", "wall_loaded_s")
              if res[f"{n}_{k}"] is not None and res[f"{n}_{k}"] > tgt]
    if args.json:
        print(json.dumps(res))
    else:
        print(f"machine: {os.cpu_count()} cores, 1-min load average {res['load_avg_1min']:.2f} at the start")
        print(f"{'case':10s} {'target':>7s} {'wall':>7s} {'cpu':>7s} {'wall*':>7s} {'cpu*':>7s}"
              "  (* under one other job)")
        for n, tgt in TARGETS.items():
            def f(k: str, n: str = n) -> str:
                v = res[f"{n}_{k}"]
                return "-" if v is None else f"{v:.2f}"
            ok = "ok" if res[f"{n}_wall_s"] is not None and n not in missed else (
                "skipped" if res[f"{n}_wall_s"] is None else "MISSED")
            print(f"{n:10s} {tgt:6.1f}s {f('wall_s'):>7s} {f('cpu_s'):>7s} {f('wall_loaded_s'):>7s} "
                  f"{f('cpu_loaded_s'):>7s}  {ok}")
        for note in notes:
            print(note)
    return 1 if missed else 0


if __name__ == "__main__":
    sys.exit(main())

"""``drivectl health ...``: the health store's commands (docs/health.md)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from drivectl.errors import EXIT_BAD_INPUT, EXIT_OK, InputError
from drivectl.tools.cli.exits import exits_on_error

if TYPE_CHECKING:
    from drivectl.machine.config import MachineConfig


def add_health_parser(sub: argparse._SubParsersAction) -> None:
    h = sub.add_parser("health", help="axis health over a machine's life: the trace store",
                       description="Keep a machine's traces in a store (Parquet samples, a DuckDB catalog) for "
                       "the trend of its axes' wear (docs/health.md). Needs the health extra: "
                       "pip install 'drivectl[health]'.")
    hs = h.add_subparsers(dest="health_command", metavar="SUBCOMMAND")
    hs.required = True
    i = hs.add_parser("ingest", help="keep traces in the store (the same trace twice changes nothing)",
                      description="Keep traces in the store: the samples in Parquet, one file per run, a row each "
                      "in the catalog. A file already there (same sha256) is left alone; an unreadable, "
                      "incomplete or foreign one is refused in one line and the others go on (exit 2 then).")
    i.add_argument("traces", nargs="+", metavar="TRACE", help="trace files (format v1; bus logs when "
                   "drivectl.tools.buslog is there)")
    i.add_argument("--machine", required=True, help="the machine the traces come from")
    i.add_argument("--axis", help="the axis, where a file does not say (bus logs)")
    _store_arg(i)
    a = hs.add_parser("analyze", help="fit every run without fits, on Dask",
                      description="Fit every run of the store that has no fits yet against its axis's baseline "
                      "(the configuration's axes.NAME.model, else the model of the axis's first runs, [health] "
                      "baseline_runs, default 3): one fit per effect of the vocabulary with its uncertainty, by "
                      "explain's fitters, spread over Dask workers that read the Parquet files themselves. "
                      "Interrupted, it keeps the runs that finished.")
    _store_arg(a)
    a.add_argument("--scheduler", metavar="ADDRESS", help="a running dask scheduler (tcp://HOST:8786); default: "
                   "an embedded LocalCluster on the cores that are free")
    a.add_argument("--workers", type=int, metavar="N", help="processes of the embedded LocalCluster")


def _store_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--store", metavar="DIR", help="the store (default: [health] store in the configuration, "
                   "else $XDG_DATA_HOME/drivectl/health, else ~/.local/share/drivectl/health)")


def store_path(args: argparse.Namespace) -> tuple[Path, MachineConfig]:
    """--store, else the configuration's ``[health] store``, else the user's data folder; and the
    configuration."""
    from drivectl.machine.config import load_config
    from drivectl.tools.health.store import default_store

    cfg = load_config(args.config)
    if args.store:
        return Path(args.store), cfg
    return (Path(cfg.health_store) if cfg.health_store else default_store()), cfg


@exits_on_error
def cmd_health(args: argparse.Namespace) -> int:
    if args.health_command == "ingest":
        return _ingest(args)
    if args.health_command == "analyze":
        return _analyze(args)
    raise InputError(f"health: unknown subcommand {args.health_command!r}")


def _ingest(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from drivectl.tools.health.store import Store

    root, cfg = store_path(args)
    counts = {"added": 0, "present": 0, "refused": 0}
    from drivectl.tools.health.store import check_machine

    check_machine(args.machine)
    with Store(root) as store:
        outcomes = store.ingest_all(args.traces, args.machine, axis=args.axis, config=cfg)
        for o in tqdm(outcomes, total=len(args.traces), unit="trace", disable=None, leave=False):
            counts[o.status] += 1
            if o.status == "refused":
                tqdm.write(f"drivectl: {o.detail}", file=sys.stderr)
    print(f"health ingest: {counts['added']} added, {counts['present']} already there, "
          f"{counts['refused']} refused; store {root}")
    return EXIT_BAD_INPUT if counts["refused"] else EXIT_OK


def _analyze(args: argparse.Namespace) -> int:
    from drivectl.tools.health.analyze import analyze
    from drivectl.tools.health.store import Store

    if args.workers is not None and args.workers < 1:
        raise InputError(f"--workers: expected an integer >= 1, got {args.workers}")
    root, cfg = store_path(args)
    from drivectl.tools.health.analyze import BASELINE_RUNS

    models = {name: ax.model for name, ax in cfg.axes.items() if ax.model}
    first = cfg.health_baseline_runs or BASELINE_RUNS
    waiting: list[str] = []

    def say(line: str) -> None:
        print(f"drivectl: {line}", file=sys.stderr)

    def note(line: str) -> None:
        waiting.append(line)
        print(f"health analyze: {line}", file=sys.stderr)

    with Store(root) as store:
        try:
            done, failed = analyze(store, scheduler=args.scheduler, workers=args.workers, models=models,
                                   baseline_runs=first, progress=sys.stderr.isatty(), on_error=say, on_note=note)
        except KeyboardInterrupt:
            print("drivectl: health analyze: interrupted; the runs that finished keep their fits", file=sys.stderr)
            return 130
    print(f"health analyze: {done} runs fitted, {failed} failed; store {root}")
    return EXIT_BAD_INPUT if failed else EXIT_OK

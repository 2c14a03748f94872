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
    r = hs.add_parser("run", help="run an axis's fingerprint and keep its trace in the store",
                      description="Run the axis's fingerprint profile ([axes.NAME.health] profile, default the "
                      "library's fingerprint, ~10 s) on a session of the machine: enable, approach its start, "
                      "run it under the resident loop's limits and fault reactions, write its trace (with "
                      "# machine: and # started_utc:) and ingest it. Refused in one line, before anything "
                      "moves, where the profile would leave the soft limits or the axis cannot be enabled.")
    r.add_argument("--axis", required=True, help="the axis")
    r.add_argument("--machine", help="the machine's name in the store (default: the configuration file's "
                   "stem, 'emulated' for the embedded one)")
    r.add_argument("--out", default="traces", metavar="DIR", help="where the trace is written (default traces)")
    _store_arg(r)
    r.add_argument("--sim", action="store_true", help="SimAxis (the plant with no bus)")
    r.add_argument("--effect", action="append", default=[], metavar="NAME:k=v,...",
                   help="emulated drives only: an effect the plant plays beyond its model (repeatable; "
                   "drivectl trace --effect)")
    r.add_argument("--noise", type=float, default=0.0, metavar="EFFORT", help="emulated drives only: force "
                   "noise std, effort unit")
    r.add_argument("--seed", type=int, default=0, help="seed of the force noise")
    p = hs.add_parser("report", help="trends, change points and alarms of the store's axes",
                      description="Per axis and effect: the fitted parameter over the runs with its band, the "
                      "run at which it began to change (a change-point test against the run-to-run noise), "
                      "its slope per 100 runs and when it crosses its limit ([health.limits]); the alarms. "
                      "Without --machine/--axis, a fleet table ranks every axis by its worst alarm.")
    _store_arg(p)
    p.add_argument("--machine", help="only this machine")
    p.add_argument("--axis", help="only this axis")
    p.add_argument("--json", action="store_true", help="one JSON object: machine, axis, runs, alarms, trends "
                   "(the selection must be one axis)")
    p.add_argument("--plot", metavar="PNG", help="one panel per effect, the onset marked (one axis)")


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
    if args.health_command == "run":
        return _run(args)
    if args.health_command == "report":
        return _report(args)
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


def _run(args: argparse.Namespace) -> int:
    """``health run``: every input checked (configuration, profile, soft limits, store) before a bus
    opens; the machine's session then enables the axis, runs the fingerprint, and closes (every axis
    disabled, as the drives report it)."""
    from drivectl.driver.axis import AxisError
    from drivectl.plant_emulator.effects import parse_effect
    from drivectl.tools.cli.checks import check_output_folder
    from drivectl.tools.health.fingerprint import (
        default_machine_name,
        fingerprint_profile,
        run_fingerprint,
    )
    from drivectl.tools.health.store import Store, check_machine

    root, cfg = store_path(args)
    ac = cfg.axis(args.axis)
    machine_name = args.machine or default_machine_name(cfg)
    check_machine(machine_name)
    effects = [parse_effect(text) for text in args.effect]
    if (effects or args.noise) and not (args.sim or cfg.bus.interface == "virtual"):
        raise InputError("--effect/--noise: only for emulated drives (the virtual bus) or --sim")
    profile = fingerprint_profile(cfg, args.axis)
    _check_profile_limits(ac, profile, cfg.cycle_s)
    out = check_output_folder(args.out, "--out")
    Store(root).close()  # the store opens (and the extra is there) before anything moves
    from drivectl.session import connect

    machine = connect(cfg, axes=[args.axis], sim=args.sim, effects=effects, noise=args.noise, seed=args.seed,
                      fault_dir=out)
    states: dict[str, str] = {}
    try:
        ax = machine.axes[args.axis]
        try:
            ax.enable()
        except AxisError as exc:
            print(f"drivectl: health run: {exc}; nothing moved", file=sys.stderr)
            return 1
        result = run_fingerprint(machine, args.axis, machine_name=machine_name, out=out, store=root,
                                 profile=profile)
    finally:
        states = machine.close()
        if states:
            live = ("Operation Enabled", "Quick Stop Active", "unknown")
            print("closed: " + ", ".join(f"{n} {s}" + (" (not confirmed: it may still be powered)" if s in live
                                                       else "") for n, s in states.items()), file=sys.stderr)
    print(result.line)
    if result.status == "done":
        return EXIT_OK
    return 3 if result.status == "fault" else 1


def _check_profile_limits(ac: object, profile: object, dt: float) -> None:
    """The fingerprint inside the configuration's soft limits, before a bus opens (the session checks
    again against the drive's own when the configuration leaves them out)."""
    import math

    import numpy as np

    limits = getattr(ac, "limits", None)
    if limits is None or limits.position is None:
        return
    n = int(math.ceil(profile.duration / dt)) + 1  # type: ignore[attr-defined]
    t = np.arange(n) * dt
    limits.refuse_outside(f"axis {ac.name}: health run {getattr(profile, 'name', 'profile')}",  # type: ignore[attr-defined]
                          profile.sample(t)[0], t)  # type: ignore[attr-defined]


def _report(args: argparse.Namespace) -> int:
    import json

    from drivectl.tools.health.report import axes_in, axis_report, axis_text, fleet_text, open_catalog, plot

    root, cfg = store_path(args)
    con = open_catalog(root)
    try:
        picked = axes_in(con, args.machine, args.axis)
        if not picked:
            sel = " ".join(f"--{k} {v}" for k, v in (("machine", args.machine), ("axis", args.axis)) if v)
            raise InputError(f"--store {root}: no runs" + (f" for {sel}" if sel else ""))
        one = len(picked) == 1
        if (args.json or args.plot) and not one:
            flag = "--json" if args.json else "--plot"
            names = ", ".join(f"{m}/{a}" for m, a in picked[:6]) + (" ..." if len(picked) > 6 else "")
            raise InputError(f"{flag}: the selection holds {len(picked)} axes ({names}); name one with --machine "
                             "and --axis")
        reports = [axis_report(con, m, a, cfg.health_limits_of(a)) for m, a in picked]
    finally:
        con.close()
    if args.plot:
        plot(reports[0], args.plot)
    if args.json:
        print(json.dumps(reports[0].to_json()))
        return EXIT_OK
    if args.machine is None and args.axis is None:
        print(fleet_text(reports))
    else:
        print("\n\n".join(axis_text(r) for r in reports))
    if args.plot:
        print(f"wrote {args.plot}")
    return EXIT_OK

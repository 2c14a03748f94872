"""The `drivectl` command line.

Exit codes: 0 done; 1 the run was stopped by a limit (following error, soft limit; trace kept) or the
bus/drive refused a command, or the trace could not be written whole (disk full after the checks);
2 bad input (one line on stderr naming the file and the key); 3 a fault ended the run (drive fault,
lost TPDOs or heartbeat, unexpected boot-up, bus error, implausible position, a rogue RPDO or SYNC
producer, a foreign NMT command; axis stopped, trace kept with the fault in its metadata), or a
completed run passed a ``[checks]`` fault threshold, or a stop the drive did not confirm (the line says
the axis may still be powered and what was tried); 4 completed with warnings (missed deadlines,
clipped or extrapolated cycles past a ``[checks]`` warning threshold: a line each); 130 / 143
interrupted by SIGINT / SIGTERM (quick stop, the axes' end state as the drives reported it; the trace
kept). Every word about an axis's end state comes from the drive's own statusword after the stop
(controllers/runtime/safe_stop.py).
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from importlib import import_module
from pathlib import Path
from typing import TYPE_CHECKING

from drivectl import __version__
from drivectl.errors import EXIT_BAD_INPUT, EXIT_FAULT, EXIT_OK, EXIT_STOPPED, EXIT_WARNINGS
from drivectl.tools.cli.exits import exits_on_error

if TYPE_CHECKING:
    from drivectl.controllers.runtime.interrupt import StopRequest


@dataclass(frozen=True)
class Command:
    """One `drivectl` command: where its parser and its handler live (``module:function``, imported when
    used so the CLI starts fast) and whether it talks to drives."""

    name: str
    parser: str  # adds the command's parser (one function may add a group of commands)
    run: str  # args -> exit code
    #: Ctrl-C / SIGTERM are read at cycle boundaries there, never raised into the bus I/O
    #: (drivectl.controllers.runtime.interrupt); elsewhere (tune's search, explain, plot) they end at once
    talks_to_drives: bool = False


_HERE = "drivectl.tools.cli.main"
_COMMISSION = "drivectl.tools.commissioning.commands"
#: every command, in the order `drivectl --help` lists them
COMMANDS: tuple[Command, ...] = (
    Command("trace", f"{_HERE}:add_trace_parser", f"{_HERE}:cmd_trace", True),
    Command("config", f"{_COMMISSION}:add_commission_parsers", f"{_COMMISSION}:cmd_config"),
    Command("scan", f"{_COMMISSION}:add_commission_parsers", f"{_COMMISSION}:cmd_scan", True),
    Command("status", f"{_COMMISSION}:add_commission_parsers", f"{_COMMISSION}:cmd_status", True),
    Command("enable", f"{_COMMISSION}:add_commission_parsers", f"{_COMMISSION}:cmd_power", True),
    Command("disable", f"{_COMMISSION}:add_commission_parsers", f"{_COMMISSION}:cmd_power", True),
    Command("fault-reset", f"{_COMMISSION}:add_commission_parsers", f"{_COMMISSION}:cmd_power", True),
    Command("identify", f"{_COMMISSION}:add_commission_parsers", f"{_COMMISSION}:cmd_identify", True),
    Command("bode", "drivectl.tools.commissioning.bode:add_bode_parser", "drivectl.tools.commissioning.bode:cmd_bode",
            True),
    Command("tune", "drivectl.tools.commissioning.tune:add_tune_parser", "drivectl.tools.commissioning.tune:cmd_tune"),
    Command("emulate", "drivectl.tools.cli.emulate:add_emulate_parser", "drivectl.tools.cli.emulate:cmd_emulate",
            True),
    Command("explain", "drivectl.tools.explain.core:add_explain_parser", "drivectl.tools.explain.core:cmd_explain"),
    Command("health", "drivectl.tools.health.command:add_health_parser",
            "drivectl.tools.health.command:cmd_health"),
    Command("conformance", "drivectl.tools.conformance.suite:add_conformance_parser",
            "drivectl.tools.conformance.suite:cmd_conformance"),
    Command("shell", "drivectl.tools.cli.shell:add_shell_parser", "drivectl.tools.cli.shell:cmd_shell"),
    Command("ui", "drivectl.tools.ui.command:add_ui_parser", "drivectl.tools.ui.command:cmd_ui"),
    Command("doctor", "drivectl.tools.cli.doctor:add_doctor_parser", "drivectl.tools.cli.doctor:cmd_doctor", True),
    Command("drive", "drivectl.tools.cli.drive:add_drive_parser", "drivectl.tools.cli.drive:cmd_drive", True),
    Command("decode", "drivectl.tools.buslog.decode:add_decode_parser", "drivectl.tools.buslog.decode:cmd_decode"),
    Command("replay", "drivectl.tools.buslog.replay:add_replay_parser", "drivectl.tools.buslog.replay:cmd_replay",
            True),
    Command("plot", f"{_HERE}:add_plot_parser", f"{_HERE}:cmd_plot"),
    Command("summary", f"{_HERE}:add_summary_parser", f"{_HERE}:cmd_summary"),
)
_BY_NAME = {c.name: c for c in COMMANDS}
#: commands that talk to drives (see Command.talks_to_drives)
TALKS_TO_DRIVES = tuple(c.name for c in COMMANDS if c.talks_to_drives)


def _resolve(ref: str) -> Callable:
    module, _, name = ref.partition(":")
    return getattr(import_module(module), name)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="drivectl",
        description="Drive controller for ball-screw feed axes (CiA 402 / emulated drives).",
    )
    p.add_argument("--version", action="version", version=f"drivectl {__version__}")
    p.add_argument("--config", metavar="FILE", help="machine configuration TOML (default: $DRIVECTL_CONFIG, "
                   "else the embedded emulated machine)")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    added = set()
    for c in COMMANDS:
        if c.parser not in added:  # a group's function adds all of its commands at once
            added.add(c.parser)
            _resolve(c.parser)(sub)
    return p


def add_trace_parser(sub: argparse._SubParsersAction) -> None:
    from drivectl.controllers.registry import CONTROLLERS
    from drivectl.plant_emulator.effects import EFFECTS
    from drivectl.plant_emulator.faults import KINDS

    t = sub.add_parser("trace", help="run an axis through its profile and record a trace + plot",
                       description="Run the axis's profile under its controller on the configured bus "
                       "(default: emulated CiA 402 drives on the in-process virtual CAN bus, cyclic "
                       "synchronous torque, lockstep), write the trace (format v1) and a PNG, and print a "
                       "summary. --sim runs the same plant on SimAxis, with no bus: same trace, bit for bit.")
    t.add_argument("--axis", default="x", help="axis name, or several joined by commas (x,y)")
    t.add_argument("--plant", help="override the axis's plant: what the emulated drive plays (built-in name or TOML "
                   "file; also the controller's model unless --model or the axis's model key says otherwise)")
    t.add_argument("--model", metavar="NAME|FILE", help="the plant the controller believes (built-in name or TOML "
                   "file, e.g. from identify or explain; default: the axis's model key, else the plant)")
    t.add_argument("--controller", help=f"override the axis's controller ({', '.join(CONTROLLERS)})")
    t.add_argument("--profile", help="override the axis's profile (library name or TOML file)")
    t.add_argument("--effect", action="append", default=[], metavar="NAME:k=v,...",
                   help="add a physical effect to the simulated plant, e.g. backlash:width=20e-6 (repeatable; "
                   f"effects: {', '.join(EFFECTS)})")
    t.add_argument("--duration", type=float, help="run length in s (default: the profile's)")
    t.add_argument("--noise", type=float, default=0.0, metavar="EFFORT",
                   help="std of a Gaussian force noise on the plant, in the effort unit (default 0)")
    t.add_argument("--seed", type=int, default=0, help="seed of the force noise")
    t.add_argument("--out", default="traces", metavar="DIR", help="folder for AXIS.csv and the PNG (default traces)")
    t.add_argument("--no-plot", action="store_true", help="skip the PNG")
    t.add_argument("--bus-log", metavar="FILE", help="record every CAN frame (python-can Logger; format by suffix: "
                   ".asc .blf .log .csv .trc)")
    t.add_argument("--from-log", metavar="LOG", help="no run: turn a recorded CAN log (.asc .blf .log .trc .csv "
                   ".mf4) into the axis's trace, one row per SYNC (docs/guide/buslog.md)")
    t.add_argument("--node", type=int, metavar="N", help="with --from-log: the drive's node-ID (default: the axis's)")
    t.add_argument("--eds", metavar="FILE", help="with --from-log: the drive's EDS (default: the axis's)")
    t.add_argument("--mapping-from", choices=("configuration", "eds"), default="configuration",
                   help="with --from-log: the mapping of the PDOs the log does not configure itself: the "
                   "configuration's planned mapping (default) or the EDS's default values")
    t.add_argument("--paced", action="store_true",
                   help="run the cycles on the wall clock (1 per cycle_s) instead of lockstep; missed deadlines "
                   "are recorded in the trace (the same as --clock wall)")
    t.add_argument("--clock", choices=("lockstep", "wall"),
                   help="lockstep: across processes too, every SYNC's TPDOs are waited for and drivectl's emulated "
                   "drive steps one cycle per SYNC, so the trace is --sim's bit for bit however slow the host (a "
                   "real drive is refused: it runs on its own clock); wall: --paced. Default: lockstep in-process, "
                   "as fast as the drive answers across processes")
    from drivectl.tools.cli.approach import add_approach_flags

    add_approach_flags(t)
    t.add_argument("--sim", action="store_true",
                   help="run on SimAxis (the plant with no bus) instead of the emulated CANopen drive")
    t.add_argument("--quiet", action="store_true", help="no progress bar")
    t.add_argument("--fault", action="append", default=[], metavar="[AXIS/]KIND[:k=v,...]@TIME",
                   help="inject a fault into the emulated drive (virtual bus) TIME s after it is enabled, e.g. "
                   f"emcy-fault@0.5, tpdo-lost:cycles=10@1, bus-off@2 (repeatable; kinds: {', '.join(KINDS)}; "
                   "see docs/faults.md)")
    from drivectl.tools.commissioning.learn import add_learning_arguments

    add_learning_arguments(t)


def add_plot_parser(sub: argparse._SubParsersAction) -> None:
    pl = sub.add_parser("plot", help="plot any trace file (ours or a CSV with the four columns)")
    pl.add_argument("traces", nargs="+", metavar="TRACE.csv")
    pl.add_argument("--out", metavar="PNG", help="output PNG (default: beside the first trace)")


def add_summary_parser(sub: argparse._SubParsersAction) -> None:
    su = sub.add_parser("summary", help="tracking error, energy and chattering of trace files")
    su.add_argument("traces", nargs="+", metavar="TRACE.csv")
    su.add_argument("--json", action="store_true", help="one JSON object on stdout")


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from drivectl.controllers.runtime.interrupt import exit_code, stop_on_signals

    try:
        if args.command not in TALKS_TO_DRIVES:
            return _dispatch(args)
        with stop_on_signals() as request:
            rc = _dispatch(args)
        if request.signum and rc not in (EXIT_OK, 130, 143):
            return exit_code(request)  # it ended early because of the signal, and said why in its one line
        return rc
    except BrokenPipeError:  # `drivectl config show | head`: the reader left; nothing more to say to it
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_OK
    except KeyboardInterrupt:
        print(f"drivectl: {args.command}: interrupted", file=sys.stderr)
        return 130


@exits_on_error  # a drivectl error ends the command with the code its class carries (drivectl/errors.py)
def _dispatch(args: argparse.Namespace) -> int:
    try:
        return _resolve(_BY_NAME[args.command].run)(args)
    except NotImplementedError as exc:
        print(f"drivectl: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT


# --------------------------------------------------------------------------------------------------
def cmd_trace(args: argparse.Namespace) -> int:
    from drivectl.controllers.runtime.interrupt import stop_on_signals

    # for the whole command (main's, when it routes them): a signal during set-up is seen before the axes
    # are enabled (nothing moves), one during the run at the next cycle boundary, one while the trace is
    # written does not tear it
    if args.from_log:
        return _trace_from_log(args)
    with stop_on_signals() as request:
        return _trace(args, request)


def _trace_from_log(args: argparse.Namespace) -> int:
    """``trace --from-log``: the recorded log to a trace (tools/buslog); nothing moves, no bus opens."""
    from drivectl.machine.config import load_config
    from drivectl.tools.buslog import log_to_trace
    from drivectl.tools.cli import checks

    names = checks.parse_axes(args.axis)
    if len(names) != 1:
        raise checks.ConfigError(f"--axis {args.axis}: --from-log converts one axis (one node) at a time")
    cfg = load_config(args.config)
    path = log_to_trace(Path(args.from_log), axis=names[0], out_dir=Path(args.out), node=args.node,
                        eds=Path(args.eds) if args.eds else None, config=cfg, mapping_base=args.mapping_from,
                        progress=not args.quiet)
    from drivectl.tracefile.format import Trace

    tr = Trace.read(path, columns=("lost",))
    m = tr.meta
    print(f"trace: {args.from_log}: {len(tr)} SYNCs of node {m.get('node')}, {m.get('lost_rows')} lost, "
          f"{m.get('bad_length_pdos')} PDOs of the wrong length, cycle {float(m['dt_s']) * 1e3:g} ms "
          f"({m.get('dt_source')}), frame jitter max {float(m.get('frame_jitter_max_s', 'nan')) * 1e3:.3f} ms, "
          f"p99 {float(m.get('frame_jitter_p99_s', 'nan')) * 1e3:.3f} ms", file=sys.stderr)
    print(f"trace: mapping from {m.get('mapping_source')}", file=sys.stderr)
    if m.get("truncated"):
        print(f"trace: {args.from_log}: truncated: read as far as it goes: {m['truncated']}", file=sys.stderr)
    print(f"wrote {path}")
    return 0


def _trace(args: argparse.Namespace, request: StopRequest) -> int:
    import functools

    from drivectl.controllers.registry import make_controller
    from drivectl.controllers.runtime.servo import Channel, StopReason, check_run_length, run_channels
    from drivectl.machine.build import axis_profile, machine_meta, model_specs, open_machine, plant_specs
    from drivectl.machine.config import load_config
    from drivectl.plant_emulator.effects import parse_effect
    from drivectl.plant_emulator.faults import FaultSpecError, parse_fault
    from drivectl.tools.cli import checks
    from drivectl.tracefile.metrics import summarize
    from drivectl.tracefile.plot import plot_traces

    if args.clock == "lockstep" and args.paced:
        raise checks.ConfigError("--clock lockstep: not with --paced (that is --clock wall)")
    args.paced = args.paced or args.clock == "wall"
    cfg = load_config(args.config)
    names = checks.parse_axes(args.axis)
    checks.check_number("--noise", args.noise, lo=0.0, unit="effort unit")
    checks.check_seed(args.seed)
    checks.check_number("--duration", args.duration, lo=0.0, lo_open=True, unit="s")
    effects = [parse_effect(text) for text in args.effect]
    faults = [parse_fault(text) for text in args.fault] if args.fault else None
    for f in faults or ():
        if f.kind == "master-dead":
            raise FaultSpecError(f"--fault {f}: this process is the master; kill it instead (kill -9: the "
                                 "drive stops by itself per 0x6007), or inject it on the drive side: "
                                 "drivectl emulate --fault")
    profiles = {name: axis_profile(cfg, name, args.profile) for name in names}
    if args.duration is not None:  # before a bus opens (the cap of the run's kind is checked below)
        check_run_length(args.duration, cfg.cycle_s, "--duration", streamed=True)
    specs = plant_specs(cfg, names, args.plant, effects)  # every input checked before a bus opens
    models = model_specs(cfg, names, args.model, args.plant, plants=specs)
    controllers = {}
    builders = {}  # fresh instances of the same controllers (the learning measures the loop with them)
    for name in names:
        ac = cfg.axis(name)
        ctrl_name = args.controller or ac.controller
        settings = ac.controller_settings
        if ctrl_name != ac.controller:  # keep what the other controller also takes; say what is dropped
            settings, dropped = checks.carry_settings(settings, ctrl_name)
            if dropped:
                print(f"trace: --controller {ctrl_name}: axes.{name}.controller_settings {', '.join(dropped)} "
                      f"dropped (not {ctrl_name} settings){'; kept ' + ', '.join(settings) if settings else ''}",
                      file=sys.stderr)
        controllers[name] = make_controller(ctrl_name, cfg.cycle_s, settings, plant=models[name], axis=name,
                                            source=f"{cfg.source}: axes.{name}.controller_settings")
        builders[name] = functools.partial(make_controller, ctrl_name, cfg.cycle_s, settings, plant=models[name],
                                           axis=name)
    from drivectl.tools.commissioning.learn import prepare_repeated, run_repeated

    plan = prepare_repeated(args, cfg, names, profiles, specs)  # --repeat / --learn / --learned, checked now
    checks.check_bus_log(args.bus_log)
    # the outputs last (this creates --out): a folder we can write, with room for what the run records
    if args.duration is not None:
        cycles = check_run_length(args.duration, cfg.cycle_s, "--duration", streamed=plan is None)
    else:  # as the run will name it
        from drivectl.profiles.base import profile_label

        longest = max(profiles.values(), key=lambda p: p.duration)
        cycles = check_run_length(longest.duration, cfg.cycle_s, f"profile {profile_label(longest)}: duration",
                                  streamed=plan is None)
    checks.check_outputs(args.out, cycles, 5, len(names) * (plan.repeat if plan else 1), plot=not args.no_plot)
    if plan is not None:  # the repetitions (tools/commissioning/learn.py)
        return run_repeated(args, request, plan, cfg=cfg, names=names, profiles=profiles, specs=specs,
                            models=models, controllers=controllers, builders=builders, effects=effects,
                            faults=faults)
    machine = open_machine(cfg, names, sim=args.sim, plant=args.plant, effects=effects, noise=args.noise,
                           seed=args.seed, start={n: p.start_position for n, p in profiles.items()},
                           bus_log=args.bus_log, faults=faults, paced=args.paced, lockstep=args.clock == "lockstep")
    channels = []
    try:
        for name in names:
            ac = cfg.axis(name)
            profile = args.profile or ac.profile
            meta = machine_meta(cfg, machine, specs[name], models[name], profile, effects, faults or ())
            axis = machine.axes[name]
            # limits the configuration leaves out come from the drive (0x6065/0x6066, 0x607D)
            limits = ac.limits_with(axis.drive_limits()) if ac.limits_from_drive else ac.limits
            channels.append(Channel(axis, controllers[name], profiles[name], limits, meta))
    except BaseException:
        machine.close()
        raise

    bus_text = machine.bus  # a paced run's says so (machine/build.py)
    try:
        from drivectl.machine.bus_budget import machine_load

        load_text = "" if args.sim else f", {machine_load(cfg, names).text()}"

        def started(cycles: int) -> None:
            print(f"trace: axis {','.join(names)}, {cycles} cycles of {cfg.cycle_s * 1e3:g} ms on {bus_text}"
                  f"{load_text} (Ctrl-C stops safely)", file=sys.stderr, flush=True)
            for name in names:  # what the boot chose for each drive and what it does for what the drive lacks
                for note in machine.axes[name].boot_notes:
                    print(f"{name}: {note}", file=sys.stderr)

        from drivectl.controllers.runtime.approach import plan_approach, where_axes_stand
        from drivectl.controllers.runtime.servo import plan_run
        from drivectl.tools.cli.approach import consent

        # an axis away from its profile's start is moved there first, shown and agreed (controllers/runtime/approach.py)
        approach, moves = plan_approach(channels, where_axes_stand(channels), {n: cfg.axis(n).motion for n in names})
        if approach is not None:
            consent(args.approach, moves)
        # before the approach (the run follows it within a cycle); recorded only as it streams to --out:
        # the run's memory does not grow with its length (the summary reads the file back)
        plan = plan_run(channels, args.duration, keep=False)
        result = None
        if approach is not None:
            result = run_channels(approach, disable_at_end=False, pace=args.paced, stop_request=request)
        if result is None or result.ok:
            # the traces stream to --out as the run goes (a killed run leaves its .partial files)
            result = run_channels(plan, on_start=started, pace=args.paced,
                                  progress=not args.quiet and sys.stderr.isatty(), stop_request=request,
                                  stream=Path(args.out), checks=cfg.checks)
        if machine.master_bus is not None and machine.master_bus.mode == "off":
            machine.let_drives_run(1000, until_safe=True)  # bus-off: physical time goes on, the drives stop
    finally:
        machine.close()
    from drivectl.controllers.runtime.run_checks import apply, assess
    from drivectl.tracefile.stream import TraceWriteError, clean_stale, write_trace

    checked = assess(result.traces, cfg.checks) if result.ok else None
    if checked is not None:  # the verdict into the traces (the streamed files' trailers too)
        apply(result.traces, checked, result.paths)
    out = Path(args.out)
    clean_stale(out)
    written = []
    unwritten = []  # the disk filled or went away after the checks: the run is reported all the same
    for name, tr in result.traces.items():  # a new file per run; AXIS.csv names the latest (docs/trace-format.md)
        if name in result.paths:  # streamed during the run
            written.append(result.paths[name])
            continue
        try:  # the stream failed (disk full, folder gone): once more, whole
            written.append(write_trace(out, tr))
        except (TraceWriteError, OSError) as exc:
            unwritten.append(str(exc) if isinstance(exc, TraceWriteError) else f"{out}: cannot write the trace: {exc}")
    if not args.no_plot and result.cycles > 1:
        written.append(plot_traces(result.traces, out / f"{'-'.join(names)}.png",
                                   title=f"drivectl trace: {', '.join(names)}"))
    _print_summary({n: summarize(tr) for n, tr in result.traces.items()}, result.traces)
    if "x" in result.traces and "y" in result.traces:
        from drivectl.tracefile.metrics import contour_error

        tx, ty = result.traces["x"], result.traces["y"]
        ce = contour_error(tx.ref, ty.ref, tx.pos, ty.pos)
        print(f"contour error x-y: max {ce.max() * 1e6:.2f} um, mean {ce.mean() * 1e6:.2f} um")
    for name, tr in result.traces.items():
        lost, late = int(tr.meta.get("tpdo_lost_cycles", "0")), int(tr.meta.get("tpdo_late_frames", "0"))
        if lost or late:
            print(f"{name}: {lost} cycle(s) without TPDOs bridged by extrapolation, {late} late TPDO frame(s) "
                  "dropped (counted in the trace)")
    if args.bus_log:
        written.append(Path(args.bus_log))
    for p in written:
        print(f"wrote {p}")
    for line in unwritten:
        print(f"drivectl: {line}", file=sys.stderr)
    # every word about the axes' end state comes from what the drives reported after the stop
    from drivectl.controllers.runtime.safe_stop import all_confirmed, end_state_line

    f = result.fault
    ended = f"({end_state_line(f.safe_state, f.safe_after)})" if f is not None else ""
    if result.stop is StopReason.INTERRUPTED:
        name = request.name or "SIGINT"
        how = f"quick stop {ended}" if result.enabled else "before the axes were enabled: nothing moved"
        print(f"drivectl: interrupted by {name} after {result.cycles} cycles; {how}, trace kept", file=sys.stderr)
        return 128 + request.signum if request.signum else 130
    if f is not None and result.stop is StopReason.FAULT:
        print(f"drivectl: fault: {f.kind} at cycle {f.cycle}: {f.detail}; stopped {ended}, trace kept",
              file=sys.stderr)
        return EXIT_FAULT
    if checked is not None and checked.faults:
        for line in checked.faults:
            print(f"drivectl: fault: run check: {line}", file=sys.stderr)
        for line in checked.warnings:
            print(f"drivectl: warning: {line}", file=sys.stderr)
        return EXIT_FAULT
    if checked is not None and checked.warnings:
        for line in checked.warnings:
            print(f"drivectl: warning: {line}", file=sys.stderr)
        print("drivectl: completed with warnings", file=sys.stderr)
        return EXIT_WARNINGS
    if not result.ok:
        if f is not None and not all_confirmed(f.safe_after):  # a limit stop the drive did not confirm
            print(f"drivectl: stopped: {result.detail}; quick stop {ended}, trace kept", file=sys.stderr)
            return EXIT_FAULT
        print(f"drivectl: stopped: {result.detail}; quick stop {ended}, trace kept", file=sys.stderr)
        return EXIT_STOPPED
    return EXIT_STOPPED if unwritten else EXIT_OK


def cmd_plot(args: argparse.Namespace) -> int:
    from drivectl.tracefile.format import Trace
    from drivectl.tracefile.plot import plot_traces

    traces = {}
    for i, path in enumerate(args.traces):
        tr = Trace.read(path)
        traces[tr.meta.get("axis", Path(path).stem) + ("" if i == 0 else f"#{i}")] = tr
    out = Path(args.out) if args.out else Path(args.traces[0]).with_suffix(".png")
    plot_traces(traces, out, title=", ".join(Path(p).name for p in args.traces))
    print(f"wrote {out}")
    return EXIT_OK


def cmd_summary(args: argparse.Namespace) -> int:
    import json

    from drivectl.tracefile.format import Trace
    from drivectl.tracefile.metrics import summarize

    traces = {p: Trace.read(p) for p in args.traces}
    rows = {p: summarize(tr) for p, tr in traces.items()}
    if args.json:
        print(json.dumps(rows))
    else:
        _print_summary(rows, traces)
    return EXIT_OK


def _print_summary(rows: dict, traces: dict) -> None:
    head = (f"{'trace':<12} {'max um':>9} {'mean um':>9} {'rms um':>9} {'energy':>10} {'sigma':>9} "
            f"{'du rms':>9} {'stop':>10}")
    print(head)
    print("-" * len(head))
    for name, m in rows.items():
        tr = traces[name]
        unit = tr.effort_unit or "?"
        energy = f"{m['energy_J']:.3g} {'J' if unit == 'N' else unit + 'm'}"
        # a trace without a reference (``# ref: none``: from a bus log in CST) has no tracking error
        e = {k: f"{m[k]:>9.2f}" if math.isfinite(m[k]) else f"{'-':>9}" for k in ("max_um", "mean_um", "rms_um")}
        print(f"{str(name):<12} {e['max_um']} {e['mean_um']} {e['rms_um']} {energy:>10} "
              f"{m['sigma']:>9.3g} {m['du_rms']:>9.3g} {tr.meta.get('stop', '-'):>10}")


if __name__ == "__main__":
    raise SystemExit(main())

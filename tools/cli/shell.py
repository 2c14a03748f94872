"""``drivectl shell``: an interactive session on one connected machine, in the spirit of odrivetool.

The machine (``drivectl.connect``) is opened once and kept: its resident loop holds every enabled
axis while the person types. Commands take units (``move x 20mm``, ``jog x -5mm/s 2s``); a motion
command waits for its end and prints one line (``&`` at the end returns at once); a failing command
prints one line and the session goes on; Ctrl-C stops every axis (a controlled stop) and keeps the
session; ``exit`` (or end of input) disables the axes, verified, and shuts the bus down.

Standard input that is not a terminal is read as a script, one command a line (``#`` comments), so the
shell can be driven by a program and tested; the exit code is then 1 when a command failed.
"""

from __future__ import annotations

import cmd
import shlex
import sys
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any, TextIO

from drivectl.errors import InputError
from drivectl.tools.cli.quantity import QuantityError, format_position, parse_quantity

#: how long a motion command waits for its end unless ``timeout=`` says otherwise (s, the loop's clock)
DEFAULT_TIMEOUT_S = 60.0
#: how often a running jog is renewed (well inside the loop's 200 ms dead-man interval)
JOG_RENEW_S = 0.05

HELP = """commands (positions: m mm um nm; speeds: m/s mm/s um/s; times: s ms):
  status [AXIS]                 state, power, position, following error; loop deadlines
  enable AXIS ...|all           Operation Enabled, then hold position
  disable AXIS ...|all          torque off (verified)
  fault-reset AXIS ...|all      reset a drive fault (edge on bit 7, verified)
  move AXIS POS [speed=V]       jerk-limited move to POS (e.g. move x 20mm)
  move-by AXIS DIST [speed=V]   move by DIST from the current target
  jog AXIS V [T]                jog at V for T (default 1s), then a controlled stop
  stop [AXIS ...]               controlled stop (all axes when none named)
  home AXIS                     home by the axis's configured method
  run AXIS PROFILE [relative]   run a profile (library name or TOML file)
  capture AXIS [channels=a,b] [trigger=now|move|fault|CHANNEL>LEVEL] [pre=T] [post=T] [out=FILE]
  plot [FILE ...]               PNG of trace files (default: the last one written)
  wait T                        let time pass (the loop holds the axes)
  scan                          the drives of this machine: node, identity, power state
  live on|off [channels=a,b]    the live view of position, reference, following_error, velocity, effort
                                (a window where a display exists, else a status line)
  exit                          disable every axis and leave
a command ending in & returns at once; Ctrl-C stops every axis and keeps the session"""


class ShellError(InputError):
    """A command that cannot be carried out as typed: one line, the session goes on."""


class Shell(cmd.Cmd):
    """The command interpreter over a connected :class:`drivectl.session.Machine`."""

    def __init__(self, machine: Any, *, out: Path, stdin: TextIO, stdout: TextIO, interactive: bool,
                 live: Any = None):
        super().__init__(stdin=stdin, stdout=stdout)
        self.m = machine
        self.out = out
        self.interactive = interactive
        self.use_rawinput = interactive
        self.prompt = "drivectl> " if interactive else ""
        self.failures = 0
        self.last_written: list[Path] = []
        self.captures: list[tuple[Any, Path]] = []
        self.live = live
        self._seq = 0
        self._background: list[Any] = []  # handles of the commands given with &, until they end

    # -- the frame around every command ----------------------------------------------------------------
    def say(self, line: str) -> None:
        if self.live is not None:  # a result starts on a line of its own, not after the status line
            self.live.clear()
        self.stdout.write(line + "\n")
        self.stdout.flush()

    def precmd(self, line: str) -> str:
        line = line.strip()
        if line.startswith("#"):
            return ""
        head, _, rest = line.partition(" ")
        return head.replace("-", "_") + (" " + rest if rest else "")

    def onecmd(self, line: str) -> bool:
        from drivectl.controllers.runtime.capture import CaptureError
        from drivectl.controllers.runtime.loop import MotionFault
        from drivectl.controllers.runtime.servo import LimitError
        from drivectl.driver.axis import AxisError
        from drivectl.profiles.base import ProfileError

        try:
            return super().onecmd(line)
        except KeyboardInterrupt:
            self._interrupted()
        except (ShellError, QuantityError, LimitError, AxisError, MotionFault, CaptureError, ProfileError,
                TimeoutError) as exc:
            self.failures += 1
            self.say(f"error: {exc}")
        finally:
            self._collect_captures()
        return False

    def moving(self) -> bool:
        """Whether a command given with & is still under way."""
        self._background = [h for h in self._background if not h.done]
        return bool(self._background)

    def _interrupted(self) -> None:
        stops = self.m.stop_all("interrupted (Ctrl-C)")
        self.failures += 1
        for h in stops:
            try:
                h.wait(5.0)
            except Exception:  # noqa: BLE001 - report below what the drive says, whatever the stop raised
                pass
        self.say("interrupted: " + (", ".join(f"{a.name} {a.state} at {format_position(a.position)}"
                                                for a in self.m.axes.values()) or "no axis"))

    def emptyline(self) -> bool:
        return False

    def default(self, line: str) -> bool:
        if line in ("EOF",):
            return self.do_exit("")
        raise ShellError(f"{line.split()[0]}: unknown command (help lists them)")

    def completenames(self, text: str, *ignored: Any) -> list[str]:
        return [n.replace("_", "-") for n in super().completenames(text.replace("-", "_"), *ignored)]

    def completedefault(self, text: str, line: str, begidx: int, endidx: int) -> list[str]:
        return [n for n in [*self.m.axes, "all"] if n.startswith(text)]

    def do_help(self, arg: str) -> bool:
        self.say(HELP)
        return False

    # -- arguments -----------------------------------------------------------------------------------------
    def _args(self, arg: str, at_least: int, usage: str,
              at_most: int | None = None) -> tuple[list[str], dict[str, str], bool]:
        """The words of ``arg``: positionals, ``key=value`` options, and a trailing ``&``. Too few or too many
        positionals (``at_most``; None: any number) is a usage error before anything is done."""
        words = shlex.split(arg)
        background = bool(words) and words[-1] == "&"
        if background:
            words = words[:-1]
        elif words and words[-1].endswith("&"):
            words[-1], background = words[-1][:-1], True
        pos = [w for w in words if "=" not in w]
        opts = dict(w.split("=", 1) for w in words if "=" in w)
        if len(pos) < at_least or (at_most is not None and len(pos) > at_most):
            raise ShellError(f"usage: {usage}")
        return pos, opts, background

    def _axis(self, name: str) -> Any:
        try:
            return self.m.axes[name]
        except KeyError:
            raise ShellError(f"axis {name!r}: not on this machine (axes: {', '.join(self.m.axes)})") from None

    def _named(self, names: list[str]) -> list[Any]:
        """The axes ``names`` names ("all" among them: every axis), each once, all checked before any is used."""
        named = {ax.name: ax for ax in (self._axis(n) for n in names if n != "all")}  # a bad name raises here
        return list(self.m.axes.values()) if "all" in names else list(named.values())

    def _timeout(self, opts: dict[str, str]) -> float:
        return parse_quantity(opts.pop("timeout"), "time", what="timeout") if "timeout" in opts else DEFAULT_TIMEOUT_S

    def _no_more(self, opts: dict[str, str], command: str) -> None:
        if opts:
            raise ShellError(f"{command}: unknown option {next(iter(opts))}=")

    def _finish(self, ax: Any, handle: Any, what: str, background: bool, timeout: float) -> None:
        if background:
            self._background.append(handle)
            self.say(f"{ax.name}: {what} started")
            return
        t0 = self.m.loop.cycle
        self._wait(handle, timeout)
        took = (self.m.loop.cycle - t0) * self.m.loop.dt
        err = handle.following_error
        at = f"at {format_position(handle.position)}" if handle.position is not None else ""
        tail = f", following error {err * 1e6:.2f} um" if err is not None else ""
        if handle.status == "done" and handle.detail and not handle.settled:
            tail += f" ({handle.detail})"  # ended, but not in position: say so
        self.say(f"{ax.name}: {what} {handle.status} in {took:.3f} s; {at}{tail}")

    def _wait(self, handle: Any, timeout: float) -> None:
        """Wait for ``handle`` in slices, refreshing the live view between them."""
        deadline = timeout
        while not handle.done:
            step = min(0.1, deadline)
            try:
                handle.wait(step)
            except TimeoutError:
                deadline -= step
                if deadline <= 1e-9:
                    raise TimeoutError(f"axis {handle.axis}: {handle.kind} not done within {timeout:g} s "
                                       f"(status {handle.status})") from None
            if self.live is not None:
                self.live.refresh()
        handle.wait(0)

    # -- commands --------------------------------------------------------------------------------------
    def do_status(self, arg: str) -> bool:
        pos, opts, _ = self._args(arg, 0, "status [AXIS]")
        self._no_more(opts, "status")
        st = self.m.status()
        names = pos or list(self.m.axes)
        for name in names:
            ax = self._axis(name)
            a = st["axes"][ax.name]
            fault = f"; fault {a['fault']}" if "fault" in a else ""
            self.say(f"{name}: {a['state']}, {a['power']}, position {format_position(a['position_m'])}, "
                     f"following error {a['following_error_m'] * 1e6:.2f} um, effort {a['effort']:.3g} "
                     f"{a['effort_unit']}{fault}")
        self.say(f"loop: {st['clock']}, {st['cycles']} cycles, missed deadlines {st['missed_deadlines']} "
                 f"({st['missed_fraction'] * 100:.2f} %), worst late {st['worst_late_ms']:.2f} ms, "
                 f"stalls {st['stalls']}")
        if self.m.loop.clock == "wall":
            lat, dl = st["latency_ms"], st["deadline_ms"]
            self.say("lateness: " + ", ".join(f"{q} {v:.3f} ms" for q, v in lat.items()) + "; deadlines "
                     + ", ".join(f"{n} {v:g} ms" for n, v in dl.items()) + " (docs/timing.md)")
        return False

    def do_enable(self, arg: str) -> bool:
        pos, opts, _ = self._args(arg, 1, "enable AXIS [AXIS ...]|all")
        self._no_more(opts, "enable")
        for ax in self._named(pos):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # said here, on its own line
                ax.enable()
            if ax.timing_warning:
                self.say(f"warning: {ax.timing_warning}")
            self.say(f"{ax.name}: {ax.power.value}, holding {format_position(ax.position)}")
        return False

    def do_disable(self, arg: str) -> bool:
        pos, opts, _ = self._args(arg, 1, "disable AXIS [AXIS ...]|all")
        self._no_more(opts, "disable")
        for ax in self._named(pos):
            ax.disable()
            self.say(f"{ax.name}: {ax.power.value} (the drive reports it)")
        return False

    def do_fault_reset(self, arg: str) -> bool:
        pos, opts, _ = self._args(arg, 1, "fault-reset AXIS [AXIS ...]|all")
        self._no_more(opts, "fault-reset")
        for ax in self._named(pos):
            ax.fault_reset()
            self.say(f"{ax.name}: {ax.power.value} (fault reset, verified)")
        return False

    def _speed(self, opts: dict[str, str]) -> float | None:
        return parse_quantity(opts.pop("speed"), "velocity", what="speed") if "speed" in opts else None

    def do_move(self, arg: str) -> bool:
        pos, opts, bg = self._args(arg, 2, "move AXIS POSITION [speed=V] [timeout=T] [&]", 2)
        ax = self._axis(pos[0])
        target = parse_quantity(pos[1], "position")
        speed, timeout = self._speed(opts), self._timeout(opts)
        self._no_more(opts, "move")
        self._finish(ax, ax.move_to(target, speed=speed), f"move to {format_position(target)}", bg, timeout)
        return False

    def do_move_by(self, arg: str) -> bool:
        pos, opts, bg = self._args(arg, 2, "move-by AXIS DISTANCE [speed=V] [timeout=T] [&]", 2)
        ax = self._axis(pos[0])
        dist = parse_quantity(pos[1], "position", what="distance")
        speed, timeout = self._speed(opts), self._timeout(opts)
        self._no_more(opts, "move-by")
        self._finish(ax, ax.move_by(dist, speed=speed), f"move by {format_position(dist)}", bg, timeout)
        return False

    def do_jog(self, arg: str) -> bool:
        pos, opts, _ = self._args(arg, 2, "jog AXIS VELOCITY [DURATION]", 3)
        ax = self._axis(pos[0])
        v = parse_quantity(pos[1], "velocity")
        duration = parse_quantity(pos[2], "time", what="duration") if len(pos) > 2 else 1.0
        self._no_more(opts, "jog")
        if not duration > 0:
            raise ShellError(f"jog: duration must be > 0 s, got {pos[2]}")
        handle = ax.jog(v)
        left = duration
        while left > 1e-9 and not handle.done:  # renew inside the dead-man interval while the time runs
            step = min(JOG_RENEW_S, left)
            self.m.advance(step)
            left -= step
            if not handle.done:
                ax.jog(v)
            if self.live is not None:
                self.live.refresh()
        if handle.done and handle.status == "fault":
            handle.wait(0)  # raises with the fault
        stop = ax.stop("jog ended")
        self._wait(stop, DEFAULT_TIMEOUT_S)
        self.say(f"{ax.name}: jogged {duration - max(left, 0):.3f} s at {v * 1e3:.3f} mm/s; stopped at "
                 f"{format_position(ax.position)}")
        return False

    def do_stop(self, arg: str) -> bool:
        pos, opts, _ = self._args(arg, 0, "stop [AXIS ...|all]")
        self._no_more(opts, "stop")
        stops = []
        for ax in self._named(pos) if pos else list(self.m.axes.values()):
            if not ax.enabled:
                self.say(f"{ax.name}: not enabled ({ax.power.value})")
                continue
            stops.append((ax, ax.stop()))  # every stop under way before the first is waited for
        for ax, handle in stops:
            self._finish(ax, handle, "stop", False, DEFAULT_TIMEOUT_S)
        return False

    def do_home(self, arg: str) -> bool:
        pos, opts, bg = self._args(arg, 1, "home AXIS [timeout=T] [&]", 1)
        ax = self._axis(pos[0])
        timeout = self._timeout(opts)
        self._no_more(opts, "home")
        self._finish(ax, ax.home(), "home", bg, timeout)
        return False

    def do_run(self, arg: str) -> bool:
        from drivectl.profiles.library import load_profile

        pos, opts, bg = self._args(arg, 2, "run AXIS PROFILE [relative] [timeout=T] [&]", 3)
        ax = self._axis(pos[0])
        extra = pos[2:]
        if extra not in ([], ["relative"]):
            raise ShellError(f"run: unexpected {' '.join(extra)!r} (only 'relative' may follow the profile)")
        timeout = self._timeout(opts)
        self._no_more(opts, "run")
        profile = load_profile(pos[1])
        handle = ax.run(profile, relative=bool(extra), approach=not extra)
        self._finish(ax, handle, f"run {pos[1]}", bg, timeout)
        if not bg and handle.trace is not None:
            path = self._next_path(f"{ax.name}-run")
            self.last_written = [handle.trace.write(path)]
            self.say(f"wrote {path}")
        return False

    def do_capture(self, arg: str) -> bool:
        pos, opts, _ = self._args(arg, 1, "capture AXIS [channels=a,b] [trigger=T] [pre=T] [post=T] [out=FILE]", 1)
        ax = self._axis(pos[0])
        kw: dict[str, Any] = {}
        if "channels" in opts:
            kw["channels"] = tuple(c for c in opts.pop("channels").split(",") if c)
        if "trigger" in opts:
            kw["trigger"] = opts.pop("trigger")
        for key in ("pre", "post"):
            if key in opts:
                kw[key] = parse_quantity(opts.pop(key), "time", what=key)
        out = Path(opts.pop("out")) if "out" in opts else self._next_path(f"{ax.name}-capture")
        self._no_more(opts, "capture")
        cap = ax.capture(**kw)
        self.captures.append((cap, out))
        self.say(f"{ax.name}: capture armed (trigger {kw.get('trigger', 'now')}) -> {out}")
        return False

    def do_plot(self, arg: str) -> bool:
        from drivectl.tracefile.format import Trace
        from drivectl.tracefile.plot import plot_files_apart, plot_traces

        files = [Path(p) for p in shlex.split(arg)] or [p for p in self.last_written if p.suffix == ".csv"]
        if not files:
            raise ShellError("plot: no trace yet (give files, or run/capture first)")
        png = files[0].with_suffix(".png")
        title = ", ".join(p.name for p in files)
        if self.m.clock == "wall":  # the loop runs in this process: draw in a child (tracefile/plot.py)
            plot_files_apart({f"{i}:{p.stem}": p for i, p in enumerate(files)}, png, title)
        else:
            plot_traces({f"{i}:{p.stem}": Trace.read(p) for i, p in enumerate(files)}, png, title=title)
        self.say(f"wrote {png}")
        return False

    def do_wait(self, arg: str) -> bool:
        pos, opts, _ = self._args(arg, 1, "wait DURATION", 1)
        self._no_more(opts, "wait")
        seconds = parse_quantity(pos[0], "time", what="duration")
        if not seconds >= 0:
            raise ShellError(f"wait: duration must be >= 0 s, got {pos[0]}")
        left = seconds
        while left > 1e-9:
            step = min(0.1, left)
            self.m.advance(step)
            left -= step
            if self.live is not None:
                self.live.refresh()
        self.say(f"waited {seconds:g} s")
        return False

    def do_scan(self, arg: str) -> bool:
        for name, ax in self.m.axes.items():
            hw = self.m.hardware.axes[name]
            node, answered = hw.node_id, getattr(hw, "identity_answered", None)
            # what the drive answered at boot (the expectation may leave fields out: identity = "vendor")
            fields = zip(("vendor", "product", "revision"), answered or (), strict=False)
            said = ", ".join(f"{n} 0x{v:08X}" for n, v in fields if v is not None) or "0x1018 not read"
            who = f"node {node}, {said}" if node is not None else "no bus (SimAxis)"
            self.say(f"{name}: {who}, {ax.power.value}")
        return False

    def do_live(self, arg: str) -> bool:
        pos, opts, _ = self._args(arg, 1, "live on|off [channels=position,following_error,...]", 1)
        word = pos[0]
        if word not in ("on", "off"):
            raise ShellError("usage: live on|off [channels=position,following_error,...]")
        from drivectl.tools.cli.live import parse_channels

        try:
            channels = parse_channels(opts.pop("channels", None))
        except ValueError as exc:
            raise ShellError(str(exc)) from None
        self._no_more(opts, "live")
        if word == "off":
            if self.live is not None:
                self.live.close()
            self.live = None
            self.say("live view off")
            return False
        from drivectl.tools.cli.live import open_live_view

        if self.live is not None:
            self.live.close()
        self.live = open_live_view(self.m, self.stdout, channels)
        self.say(f"live view on ({self.live.kind}): {', '.join(channels)}")
        return False

    def do_exit(self, arg: str) -> bool:
        self._finish_captures()
        return True

    do_quit = do_exit
    do_EOF = do_exit

    # -- helpers -----------------------------------------------------------------------------------------
    def _next_path(self, stem: str) -> Path:
        self._seq += 1
        return self.out / f"{stem}-{time.strftime('%Y%m%d-%H%M%S')}-{self._seq:02d}.csv"

    def _finish_captures(self) -> None:
        """At the end of the session: a triggered capture gets its post-trigger time to fill (it is
        written then); one still armed or unfilled is named, so that a script never ends silently on
        a capture it asked for."""
        from drivectl.controllers.runtime.capture import CaptureError

        for cap, _out in self.captures:
            if cap.state == "triggered":
                try:
                    cap.wait(cap.post * cap.dt + 1.0)
                except (TimeoutError, CaptureError):
                    pass  # named below
        self._collect_captures()
        for cap, out in self.captures:
            what = "filled" if cap.state == "triggered" else "triggered"
            self.failures += 1
            self.say(f"error: capture on axis {cap.axis}: not {what} when the session ended; nothing written "
                     f"to {out}")
        self.captures = []

    def _collect_captures(self) -> None:
        """Write every capture that completed since the last command."""
        from drivectl.controllers.runtime.capture import CaptureError

        left = []
        for cap, out in self.captures:
            if not cap.done:
                left.append((cap, out))
                continue
            try:
                written = cap.write(out)
            except CaptureError as exc:
                self.say(f"error: {exc}")
                continue
            self.last_written = written
            self.say("wrote " + ", ".join(str(p) for p in written))
        self.captures = left


def run_shell(machine: Any, *, out: Path, stdin: TextIO | None = None, stdout: TextIO | None = None,
              live: bool | None = None, on_close: Callable[[], dict[str, str]] | None = None) -> int:
    """Read and run commands until ``exit`` or end of input; returns the exit code (1 when a scripted
    command failed)."""
    stdin = stdin or sys.stdin
    stdout = stdout or sys.stdout
    interactive = stdin.isatty()
    view = None
    if live or (live is None and interactive):
        from drivectl.tools.cli.live import open_live_view

        view = open_live_view(machine, stdout)
    sh = Shell(machine, out=out, stdin=stdin, stdout=stdout, interactive=interactive, live=view)
    if interactive:
        _history(True)
        sh.say(f"drivectl shell on {machine.bus}: axes {', '.join(machine.axes)} ({machine.clock}); "
               "help lists the commands")
    try:
        while True:
            try:
                sh.cmdloop()
                break
            except KeyboardInterrupt:  # between commands: the session goes on
                sh.intro = None
                if sh.moving():  # a move given with & goes on between commands: Ctrl-C stops it there too
                    sh._interrupted()
                else:
                    sh.say("^C (exit leaves the session)")
    finally:
        if view is not None:
            view.close()
        if interactive:
            _history(False)
    return 1 if (sh.failures and not interactive) else 0


def _history(load: bool) -> None:
    try:
        import readline
    except ImportError:  # no readline (Windows): no history, completion still by cmd's own
        return
    path = Path.home() / ".drivectl_history"
    try:
        if load:
            if path.exists():
                readline.read_history_file(path)
            readline.set_history_length(1000)
        else:
            readline.write_history_file(path)
    except OSError:
        pass


def add_loop_flag(parser: Any) -> None:
    """``--loop process|thread``: where the wall-clock servo loop runs (session.connect's ``loop``)."""
    parser.add_argument("--loop", choices=("process", "thread"), default=None,
                        help="the wall-clock servo loop in a process of its own (the default, or the configuration's "
                        "loop) or a thread of this one (docs/timing.md)")


def add_shell_parser(sub: Any) -> None:
    s = sub.add_parser("shell", help="an interactive session on the machine: enable, move, jog, home, capture",
                       description="Connect to the machine once and command its axes (help inside lists the "
                       "commands). Reads a script from standard input when that is not a terminal.")
    s.add_argument("--axis", default=None, help="axes to connect (default: every axis of the configuration)")
    s.add_argument("--clock", choices=("lockstep", "wall"), default=None,
                   help="the loop's clock (default: wall for a person at a terminal; for a script, lockstep "
                   "on the emulated drives, wall on a real bus)")
    s.add_argument("--sim", action="store_true", help="SimAxis (the plants with no bus)")
    add_loop_flag(s)
    s.add_argument("--out", default="traces", metavar="DIR", help="where captures and runs are written")
    live = s.add_mutually_exclusive_group()
    live.add_argument("--live", dest="live", action="store_true", default=None, help="live view on")
    live.add_argument("--no-live", dest="live", action="store_false", help="live view off")


def cmd_shell(args: Any) -> int:
    import signal

    from drivectl.session import connect
    from drivectl.tools.cli.checks import check_output_folder, parse_axes

    axes = parse_axes(args.axis) if args.axis else None
    out = check_output_folder(args.out, "--out")
    clock = args.clock or ("wall" if sys.stdin.isatty() else None)
    machine = connect(args.config, axes=axes, clock=clock, sim=args.sim, fault_dir=out, loop=args.loop)

    def terminate(signum: int, frame: object) -> None:  # noqa: ARG001 - leave through the finally below
        raise SystemExit(128 + signum)

    old = signal.signal(signal.SIGTERM, terminate)
    states: dict[str, str] = {}
    try:
        rc = run_shell(machine, out=out, live=args.live)
    finally:
        signal.signal(signal.SIGTERM, old)
        states = machine.close()
        if states:  # what each drive reported last: an axis that did not confirm may still be powered
            live = ("Operation Enabled", "Quick Stop Active", "unknown")
            print("closed: " + ", ".join(f"{n} {s}" + (" (not confirmed: it may still be powered)" if s in live
                                                       else "") for n, s in states.items()), file=sys.stderr)
    return rc

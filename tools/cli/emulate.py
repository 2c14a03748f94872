"""`drivectl emulate`: the emulated drives of a machine on a bus, until stopped.

The drives answer like real CiA 402 drives, so a second drivectl (or any CANopen tool) can be pointed
at them. Without kernel CAN the emulator is itself the adapter:

* ``--slcan``: it opens a pseudo-terminal and speaks SLCAN on it, printing the tty path; the master
  uses python-can's slcan interface on that path (``bus.interface = "slcan"``, ``channel = TTY``);
* ``--socketcand [PORT]``: it serves the socketcand protocol on 127.0.0.1 (only loopback);
* ``--interface socketcan --channel vcan0``: a kernel CAN interface, where the kernel has one.

The plant advances one cycle per SYNC received (simulated time), so a run across processes gives
the same trace as the lockstep virtual bus, bit for bit (``drivectl trace --clock lockstep`` tells the
drives so, 0x5FFF: they never run on their own clock then, however slow the master); a master paced
on the wall clock tells them to step by the slot count its SYNC's counter byte carries, so a late
master's skipped slots run on the plant as on a real drive (docs/timing.md).

``--fault [AXIS/]KIND[:k=v,...]@TIME`` breaks a drive on cue (plant_emulator/faults.py) for the
master at the other end to detect; ``master-dead`` makes the emulator stop hearing the master (as if
it had died), bus-error and bus-off need the master's own bus (``drivectl trace --fault``).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import can
import canopen

from drivectl.errors import InputError

if TYPE_CHECKING:
    from drivectl.controllers.runtime.interrupt import StopRequest


def add_emulate_parser(sub: Any) -> None:
    from drivectl.driver.network import INTERFACES
    from drivectl.plant_emulator.effects import EFFECTS
    from drivectl.plant_emulator.faults import KINDS

    e = sub.add_parser("emulate", help="run the machine's emulated drives on a bus until stopped",
                       description=__doc__.split("\n\n")[0] + " " + __doc__.split("\n\n")[1].replace("\n", " "))
    e.add_argument("--axis", default=None, help="axes to emulate, comma-separated (default: all of the config)")
    how = e.add_mutually_exclusive_group()
    how.add_argument("--slcan", action="store_true", help="be an SLCAN adapter on a new pseudo-terminal")
    how.add_argument("--socketcand", nargs="?", const=0, type=int, metavar="PORT",
                     help="serve the socketcand protocol on 127.0.0.1:PORT (default: a free port); several masters "
                     "and tools can connect at once")
    how.add_argument("--interface", choices=INTERFACES, metavar="NAME",
                     help="a python-can interface to join (socketcan, or an adapter: pcan, kvaser, ...)")
    e.add_argument("--channel", default="vcan0", help="channel for --interface (default vcan0)")
    e.add_argument("--bitrate", type=int, default=1_000_000, help="bit/s for --interface (default 1000000)")
    e.add_argument("--idle-timeout", type=float, default=30.0, metavar="S",
                   help="--socketcand: close a client that took none of the frames waiting for it for S seconds "
                   "(dead or hung; default 30; 0: never)")
    e.add_argument("--effect", action="append", default=[], metavar="NAME:k=v,...",
                   help=f"add a physical effect to every emulated plant (repeatable; effects: {', '.join(EFFECTS)})")
    e.add_argument("--plant", help="override the plants (built-in name or TOML file)")
    e.add_argument("--noise", type=float, default=0.0, help="force noise std (effort units)")
    e.add_argument("--seed", type=int, default=0)
    e.add_argument("--bus-log", metavar="FILE", help="record every frame, sent and received, stamped on the host's "
                   "clock (python-can Logger, format by suffix: .asc, .blf, .log, .csv, .trc)")
    e.add_argument("--fault", action="append", default=[], metavar="[AXIS/]KIND[:k=v,...]@TIME",
                   help=f"inject a fault TIME s after the drive is enabled (repeatable; kinds: {', '.join(KINDS)}; "
                   "see docs/faults.md)")
    e.add_argument("--eds", metavar="FILE", help="the drive impersonates this EDS (its objects, limits, PDO rules, "
                   "modes, identity; default: each axis's eds key, else drivectl's own emulated drive)")
    e.add_argument("--boot-delay-ms", type=float, default=None, metavar="MS",
                   help="boot-up message this long after power-on or an NMT reset (default 50 ms)")
    e.add_argument("--sync-loss-ms", type=float, default=None, metavar="MS",
                   help="no SYNC for this long: the drives run on their own clock (default: the master "
                        "heartbeat consumer time, 300 ms; about two cycles for a master paced in real time)")


class EmulateArgError(InputError):
    """A value given to ``drivectl emulate`` is unusable: one line naming the flag, exit 2."""


def cmd_emulate(args: argparse.Namespace) -> int:
    from drivectl.controllers.runtime.interrupt import stop_on_signals

    # SIGINT/SIGTERM only end the receive loop: raised inside the bus's queue they could leave its lock
    # held and hang the shutdown
    with stop_on_signals() as stop:
        try:
            return _emulate(args, stop)
        except EmulateArgError as exc:
            print(f"drivectl: emulate: {exc}", file=sys.stderr)
            return 2


def _check_args(args: argparse.Namespace) -> None:
    """Every flag's value, before any bus opens or file is created."""
    if args.socketcand is not None and not 0 <= args.socketcand <= 65535:
        raise EmulateArgError(f"--socketcand {args.socketcand}: expected a TCP port 0..65535 (0: a free one)")
    if not math.isfinite(args.idle_timeout) or args.idle_timeout < 0:
        raise EmulateArgError(f"--idle-timeout {args.idle_timeout}: expected seconds >= 0 (0: never)")
    if args.bitrate <= 0:
        raise EmulateArgError(f"--bitrate {args.bitrate}: expected a positive integer (bit/s)")
    if not math.isfinite(args.noise) or args.noise < 0:
        raise EmulateArgError(f"--noise {args.noise}: expected a force noise std >= 0")
    if args.axis is not None:
        names = [a.strip() for a in args.axis.split(",")]
        if not all(names):
            raise EmulateArgError(f"--axis {args.axis!r}: expected axis names separated by commas")
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise EmulateArgError(f"--axis {args.axis}: axis {dup[0]} given twice")
    if getattr(args, "eds", None) is not None:
        eds = Path(args.eds)
        if not eds.is_file():
            raise EmulateArgError(f"--eds {eds}: no such file")
        try:
            import canopen

            canopen.import_od(str(eds), 1)
        except Exception as exc:  # canopen raises many types for a bad file
            reason = (str(exc).strip().splitlines() or [type(exc).__name__])[0].rstrip(":")
            raise EmulateArgError(f"--eds {eds}: cannot be read: {reason}") from None
    if args.bus_log:
        path = Path(args.bus_log)
        if path.suffix.lower() not in _LOG_SUFFIXES:
            raise EmulateArgError(f"--bus-log {path}: unknown log format (use {', '.join(_LOG_SUFFIXES[:-1])})")
        folder = path.parent
        if not folder.is_dir():
            raise EmulateArgError(f"--bus-log {path}: folder {folder} does not exist")
        if path.is_dir():
            raise EmulateArgError(f"--bus-log {path}: is a folder, expected a file name")
        if not os.access(folder, os.W_OK | os.X_OK):
            raise EmulateArgError(f"--bus-log {path}: folder {folder} is not writable")


_LOG_SUFFIXES = (".asc", ".blf", ".log", ".csv", ".trc", ".gz")


def _open_emulator_bus(args: argparse.Namespace) -> tuple[can.BusABC, str, str]:
    """The bus the drives sit on, where it is and how a master points at it; one line naming the flag
    when it cannot be opened."""
    from drivectl.driver.network import BusOpenError, open_bus

    if args.slcan:
        from drivectl.plant_emulator.slcan import SlcanAdapterBus

        try:
            bus: can.BusABC = SlcanAdapterBus.open_pty()
        except OSError as exc:
            raise EmulateArgError(f"--slcan: cannot open a pseudo-terminal: {exc.strerror or exc}") from None
        return bus, f"slcan tty {bus.tty_path}", f'bus.interface = "slcan", bus.channel = "{bus.tty_path}"'
    if args.socketcand is not None:
        from drivectl.plant_emulator.socketcand import HOST, SocketcandServerBus

        try:
            bus = SocketcandServerBus(port=args.socketcand, idle_timeout=args.idle_timeout or None)
        except OSError as exc:
            raise EmulateArgError(f"--socketcand {args.socketcand}: cannot listen on {HOST}:{args.socketcand}: "
                                  f"{exc.strerror or exc}") from None
        return (bus, f"socketcand {HOST}:{bus.port}",
                f'bus.interface = "socketcand", bus.host = "{HOST}", bus.port = {bus.port}, bus.channel = "can0"')
    if args.interface:
        try:
            bus = open_bus(args.interface, args.channel, args.bitrate)
        except BusOpenError as exc:
            said = str(exc).split(": cannot open: ", 1)[-1]
            raise EmulateArgError(f"--interface {args.interface} --channel {args.channel}: cannot open: {said}") \
                from None
        return (bus, f"{args.interface}:{args.channel}",
                f'bus.interface = "{args.interface}", bus.channel = "{args.channel}"')
    raise EmulateArgError("choose a bus: --slcan, --socketcand [PORT] or --interface socketcan")


def _drive_priority() -> None:
    """A drive's firmware runs its cycle on a real-time clock: the emulator's threads (this one and those
    the bus starts after it) take SCHED_FIFO 49, below the master's loop (50), where the OS grants it, so
    a program beside them does not make the emulated drive late (docs/timing.md)."""
    if not hasattr(os, "sched_setscheduler"):
        return
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(49))
    except OSError as exc:
        print(f"emulate: SCHED_FIFO not granted ({exc.strerror}): the drives run at normal priority",
              file=sys.stderr, flush=True)


def _emulate(args: argparse.Namespace, stop: StopRequest) -> int:
    from drivectl.driver import cia402
    from drivectl.driver.network import BusLog, log_sent_frames
    from drivectl.machine.build import axis_profile, plant_specs, readable_eds
    from drivectl.machine.config import load_config
    from drivectl.plant_emulator.drive_constants import RPDO_TIMEOUT_ERROR
    from drivectl.plant_emulator.effects import parse_effect
    from drivectl.plant_emulator.faults import FaultInjector, FaultSpecError, parse_fault
    from drivectl.plant_emulator.node402 import EmulatedDrive, deliver

    _check_args(args)
    cfg = load_config(args.config)
    names = [a.strip() for a in args.axis.split(",")] if args.axis else list(cfg.axes)
    effects = [parse_effect(t) for t in args.effect]
    specs = plant_specs(cfg, names, args.plant, effects)
    faults = [parse_fault(t) for t in args.fault]
    for f in faults:
        if f.kind in ("bus-error", "bus-off"):
            raise FaultSpecError(f"--fault {f}: acts on the master's bus, which is in the other process "
                                 "(inject it with drivectl trace --fault on the virtual bus)")
        if f.axis is not None and f.axis not in names:
            raise FaultSpecError(f"--fault {f}: axis {f.axis!r} is not emulated here ({', '.join(names)})")
    injectors = {name: FaultInjector([f for f in faults if (f.axis or names[0]) == name]) for name in names}
    bus, where, hint = _open_emulator_bus(args)
    try:
        log = BusLog(args.bus_log) if args.bus_log else None
    except (OSError, ValueError) as exc:
        bus.shutdown()
        raise EmulateArgError(f"--bus-log {args.bus_log}: cannot write: {exc}") from None
    net = canopen.Network(bus)  # no notifier: this process pumps its own bus, in order
    _drive_priority()
    for flag, value in (("--boot-delay-ms", args.boot_delay_ms), ("--sync-loss-ms", args.sync_loss_ms)):
        if value is not None and not (value >= 0 and value < 1e6):
            bus.shutdown()
            raise EmulateArgError(f"--{flag.lstrip('-')}: expected a number of ms >= 0, got {value!r}")
    clock: dict[str, float] = {}
    if args.boot_delay_ms is not None:
        clock["boot_delay_ms"] = args.boot_delay_ms
    if args.sync_loss_ms is not None:
        clock["sync_loss_ms"] = args.sync_loss_ms
    drives = []
    for i, name in enumerate(names):
        ac = cfg.axis(name)
        # each axis stands where its configured profile starts, as `drivectl trace` expects
        start = axis_profile(cfg, name).start_position
        drive = EmulatedDrive(net, ac.node_id, specs[name].build(cfg.cycle_s), rated_effort=ac.rated_effort,
                              eds=args.eds or readable_eds(name, ac.eds), resolution=ac.encoder_m_per_count,
                              force_noise=args.noise, seed=args.seed + i,
                              initial_position=start, faults=injectors[name] if faults else None,
                              io=ac.emulator, **clock)
        drives.append(drive)
    if log is not None:
        log_sent_frames(net, log)  # stamped when sent, on the clock received frames are restamped with
    for drive in drives:
        drive.boot()
    # power-on: the drives are announced once booted (their boot-up sent), so a master that connects on
    # the announcement finds them answering, not a boot-up from before its reset command
    import time

    booting_until = time.monotonic() + 2.0
    while any(d.nmt == 0 for d in drives) and time.monotonic() < booting_until and not stop.signum:
        for drive in drives:
            drive.serve()
        time.sleep(0.002)
    nodes = ", ".join(f"{n} (node {cfg.axis(n).node_id}, {specs[n].name})" for n in names)
    print(f"emulating {nodes} on {where}", flush=True)
    print(f"point a master at it with: {hint}", flush=True)
    try:
        while not stop.signum:
            msg = bus.recv(0.01)
            # the frame first, then the drives' clocks up to now: a reset that arrived before a boot-up
            # fell due restarts the boot (the other order would send a stale boot-up after the reset)
            if msg is not None and not any(inj.deaf for inj in injectors.values()):
                # (master-dead injected: nothing from the master reaches the drives any more)
                if log is not None:
                    log.on_message_received(msg)
                deliver(net, msg)
            for drive in drives:
                code = drive.check_master()
                if code:
                    why = f"; {drive.deadline_why}" if code == RPDO_TIMEOUT_ERROR else ""
                    print(f"node {drive.node_id}: master lost ({cia402.error_text(code)}): drive stopped "
                          f"({drive.drive.power.value}, 0x603F = 0x{drive.drive.error_code:04X}){why}",
                          file=sys.stderr, flush=True)
    finally:
        for drive in drives:
            drive.close()
        if log is not None:
            log.stop()
        bus.shutdown()
    d0 = drives[0].drive if drives else None
    print(f"emulator stopped after {d0.syncs if d0 else 0} SYNCs"
          f" ({d0.free_steps if d0 else 0} plant steps on the drive's own clock)", file=sys.stderr)
    return 0

"""``drivectl replay LOG --interface I --channel C``: a recorded log played onto a bus with its own timing.

python-can's LogReader reads the log and its :class:`can.MessageSync` paces the frames by their timestamps, as
``python -m can.player`` does; ``--loop NUM`` (or ``i``: until interrupted) repeats the log as can.player's
``--loop`` does, ``--speed F`` plays F times as fast (the stamps divided by F before MessageSync). ``--node N``
plays only what drive N sent (its EMCY, TPDOs, SDO answers, heartbeat: a master tested against a recorded
drive); ``--master-of N`` only what the master sent to it and to all (NMT, SYNC, its RPDOs, SDO requests: a
drive tested against a recorded master). Error frames are not sent. Nothing else of drivectl's runs: no axis
is commanded by drivectl itself, but a drive on the bus obeys what the log's master commanded.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import can

from drivectl.driver.cia301 import (
    EMCY_BASE,
    HEARTBEAT_BASE,
    NMT_COB_ID,
    RPDO_BASE,
    SDO_RX_BASE,
    SDO_TX_BASE,
    SYNC_COB_ID,
    TPDO_BASE,
)
from drivectl.tools.buslog.convert import BusLogError, check_log


def drive_cobs(node: int) -> frozenset[int]:
    """The COB-IDs drive ``node`` sends in the predefined connection set."""
    return frozenset([EMCY_BASE + node, *(b + node for b in TPDO_BASE), SDO_TX_BASE + node, HEARTBEAT_BASE + node])


def master_cobs(node: int) -> frozenset[int]:
    """The COB-IDs a master sends to drive ``node`` (and to all: NMT, SYNC)."""
    return frozenset([NMT_COB_ID, SYNC_COB_ID, *(b + node for b in RPDO_BASE), SDO_RX_BASE + node])


def frames(log: Path, *, only: frozenset[int] | None, speed: float) -> Iterator[can.Message]:
    """The log's frames to send (error frames left out; ``only``: these COB-IDs), their stamps over ``speed``."""
    with can.LogReader(str(log)) as reader:
        for msg in reader:
            if msg.is_error_frame:
                continue
            if only is not None and (msg.is_extended_id or msg.arbitration_id not in only):
                continue
            msg.timestamp /= speed
            yield msg


def replay(log: Path, bus: can.BusABC, *, only: frozenset[int] | None = None, speed: float = 1.0,
           loops: float = 1, skip: float = 60 * 60 * 24, stop: Callable[[], bool] = lambda: False) -> int:
    """Play ``log`` onto ``bus`` until it has been played ``loops`` times or ``stop()`` (read after every frame:
    a signal) says so; the number of frames sent."""
    sent = 0
    iteration = 0
    while iteration < loops and not stop():
        for msg in can.MessageSync(frames(log, only=only, speed=speed), timestamps=True, skip=skip):
            if stop():
                break
            bus.send(msg)
            sent += 1
        iteration += 1
    return sent


def _loop(value: str) -> float:
    if value == "i":
        return math.inf
    try:
        n = int(value)
    except ValueError:
        raise argparse.ArgumentTypeError("--loop: a count, or i for until interrupted") from None
    if n < 1:
        raise argparse.ArgumentTypeError("--loop: at least 1")
    return n


def add_replay_parser(sub: Any) -> None:
    r = sub.add_parser("replay", help="play a recorded CAN log onto a bus with its own timing (python-can MessageSync)",
                       description="Play a CAN log (.asc .blf .log .trc .csv .mf4) onto a bus, paced by its "
                       "timestamps (python-can's MessageSync, as can.player). A master can be tested against a "
                       "recorded drive (--node), a drive against a recorded master (--master-of). "
                       "docs/guide/buslog.md")
    r.add_argument("log", metavar="LOG")
    r.add_argument("--interface", required=True, help="python-can interface (socketcan, pcan, virtual, ...)")
    r.add_argument("--channel", required=True, help="the interface's channel (can0, PCAN_USBBUS1, ...)")
    r.add_argument("--bitrate", type=int, default=None, help="bit/s where the interface takes it")
    who = r.add_mutually_exclusive_group()
    who.add_argument("--node", type=int, metavar="N", help="only the frames drive N sent")
    who.add_argument("--master-of", type=int, metavar="N", help="only the frames a master sent to drive N (and to all)")
    r.add_argument("--loop", type=_loop, default=1, metavar="NUM", help="play NUM times; i: until interrupted "
                   "(as can.player's --loop)")
    r.add_argument("--speed", type=float, default=1.0, metavar="F", help="play F times as fast (default 1)")


def cmd_replay(args: Any) -> int:
    from drivectl.driver.network import open_bus

    log = check_log(Path(args.log))
    for flag, node in (("--node", args.node), ("--master-of", args.master_of)):
        if node is not None and not 1 <= node <= 127:
            raise BusLogError(f"{flag} {node}: expected 1..127")
    if not args.speed > 0 or not math.isfinite(args.speed):
        raise BusLogError(f"--speed {args.speed}: expected a number > 0")
    only = drive_cobs(args.node) if args.node is not None else master_cobs(args.master_of) \
        if args.master_of is not None else None
    try:
        with can.LogReader(str(log)) as reader:
            next(iter(reader))
    except StopIteration:
        raise BusLogError(f"{log}: no CAN frames in it (not a {log.suffix} log, or an empty one)") from None
    except Exception as exc:
        raise BusLogError(f"{log}: not a readable {log.suffix} CAN log: {str(exc).splitlines()[0] if str(exc) else exc}"
                          ) from None
    from drivectl.controllers.runtime.interrupt import exit_code, stop_on_signals

    bus = open_bus(args.interface, args.channel, args.bitrate)
    try:
        with stop_on_signals() as request:  # Ctrl-C / SIGTERM end the replay after the frame in flight
            sent = replay(log, bus, only=only, speed=args.speed, loops=args.loop, stop=lambda: bool(request.signum))
    finally:
        bus.shutdown()
    where = f"{args.interface}:{args.channel}"
    if request.signum:
        print(f"replay: {log}: interrupted by {request.name} after {sent} frames sent on {where}", file=sys.stderr)
        return exit_code(request)
    print(f"replay: {log}: {sent} frames sent on {where}", file=sys.stderr)
    return 0

"""`drivectl conformance`: CiA 301 / CiA 402 checks of one node, made by canopen's own master classes.

canopen's RemoteNode (SDO client, PdoMap, NMT master, EMCY consumer) and BaseNode402 play the third
party: a PLC programme or someone's Python master would use the drive the same way. Each check resets
the node (NMT reset node: canopen's ``send_command(0x81)``, the boot-up awaited by a listener
subscribed before the command),
does one thing, and judges what the node answered against the standard; a row per check: area, name,
pass / FAIL / skip, what was seen.

Against the emulated drive of a configuration on the virtual bus, the drive runs in-process on its own
thread and wall clock (:class:`ServedEmulator`, as ``drivectl emulate`` serves it); on any other bus
the checks talk to whatever answers at the node id (a real drive, or ``drivectl emulate`` in another
process). Checks that switch the power stage on (Operation Enabled with zero torque) run on a real
drive only with ``--allow-enable``; checks that apply torque run only on the emulated drive.

Where things are: the node under test and the check registry in tools/conformance/target.py, the
checks in tools/conformance/checks.py; here running them, the emulated drive served in-process, the CLI.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
from collections.abc import Callable
from typing import Any

import can
import canopen
from canopen.profiles.p402 import BaseNode402

from drivectl.driver import cia402
from drivectl.tools.conformance.checks import CHECKS
from drivectl.tools.conformance.target import (
    EMULATOR_PRODUCT,
    EMULATOR_VENDOR,
    FAIL,
    PASS,
    SKIP,
    Failed,
    Row,
    Skip,
    Target,
)


# -- running ----------------------------------------------------------------------------------------------
def run_checks(network: canopen.Network, node_id: int, eds: str, *, emulated: bool, allow_enable: bool = False,
               only: str | None = None, progress: Callable[[Row], None] | None = None) -> list[Row]:
    od = canopen.import_od(eds, node_id)
    node = BaseNode402(node_id, od)
    network.add_node(node)
    target = Target(network, node, od, emulated, allow_enable)
    try:  # drivectl's emulated drive in another process (drivectl emulate): the torque checks may run too
        target.reset()
        vendor, product = node.sdo[cia402.IDENTITY][1].raw, node.sdo[cia402.IDENTITY][2].raw
        target.emulated = emulated or (vendor, product) == (EMULATOR_VENDOR, EMULATOR_PRODUCT)
    except (canopen.SdoAbortedError, canopen.SdoCommunicationError, canopen.nmt.NmtError):
        pass  # the first check reports it
    rows = []
    try:
        for area, name, fn in CHECKS:
            if only and only not in f"{area} {name}":
                continue
            try:
                target.reset()
                detail, result = fn(target), PASS
            except Skip as exc:
                detail, result = str(exc), SKIP
            except Failed as exc:
                detail, result = str(exc), FAIL
            except (canopen.SdoAbortedError, canopen.SdoCommunicationError, canopen.nmt.NmtError,
                    RuntimeError, ValueError, AssertionError) as exc:
                detail, result = f"{type(exc).__name__}: {exc}", FAIL
            row = Row(area, name, result, detail)
            rows.append(row)
            if progress is not None:
                progress(row)
    finally:
        try:
            node.nmt.send_command(0x81)  # leave the node as it powered on
        except can.CanError:
            pass
        network.nodes.pop(node_id, None)
    return rows


class ServedEmulator:
    """An emulated drive on a virtual channel, served on its own thread with the wall clock, as
    ``drivectl emulate`` serves it across processes (frames first, then the drive's clock)."""

    def __init__(self, channel: str, make_drive: Callable[[canopen.Network], Any]):
        from drivectl.driver.network import open_bus

        self.bus = open_bus("virtual", channel)
        self.net = canopen.Network(self.bus)
        self.drive = make_drive(self.net)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="emulated-drive", daemon=True)
        self.drive.boot()
        self._thread.start()

    def _serve(self) -> None:
        from drivectl.plant_emulator.node402 import deliver

        while not self._stop.is_set():
            msg = self.bus.recv(0.002)
            if msg is not None:
                deliver(self.net, msg)
            self.drive.serve()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.drive.close()
        self.bus.shutdown()


def format_table(rows: list[Row]) -> str:
    w_area = max(4, *(len(r.area) for r in rows)) if rows else 4
    w_name = max(5, *(len(r.name) for r in rows)) if rows else 5
    lines = [f"{'area':<{w_area}}  {'check':<{w_name}}  {'result':<6}  detail", "-" * (w_area + w_name + 30)]
    lines += [f"{r.area:<{w_area}}  {r.name:<{w_name}}  {r.result:<6}  {r.detail}" for r in rows]
    counts = {k: sum(r.result == k for r in rows) for k in (PASS, FAIL, SKIP)}
    lines.append(f"{counts[PASS]} passed, {counts[FAIL]} failed, {counts[SKIP]} skipped of {len(rows)} checks")
    return "\n".join(lines)


def add_conformance_parser(sub: Any) -> None:
    p = sub.add_parser("conformance", help="CiA 301/402 conformance checks of a node, by canopen's own master",
                       description=__doc__.split("\n\n")[0])
    p.add_argument("--axis", default=None, help="the configured axis whose node to check (default: the first)")
    p.add_argument("--node", type=int, default=None, help="node id to check instead of an axis's (1..127)")
    p.add_argument("--eds", default=None, help="EDS of that node (default: the axis's)")
    p.add_argument("--allow-enable", action="store_true",
                   help="on a real drive, also run the checks that switch its power stage on (zero torque)")
    p.add_argument("--only", default=None, metavar="TEXT", help="run only the checks whose area or name contains TEXT")
    p.add_argument("--json", action="store_true", help="one JSON object instead of the table")


def cmd_conformance(args: argparse.Namespace) -> int:
    from drivectl.driver.network import close_threaded, open_bus, threaded_network, unique_virtual_channel
    from drivectl.machine.build import plant_specs
    from drivectl.machine.config import load_config

    cfg = load_config(args.config)
    name = args.axis or next(iter(cfg.axes))
    if name not in cfg.axes:
        print(f"drivectl: conformance: --axis {name}: not in {cfg.source} ({', '.join(cfg.axes)})", file=sys.stderr)
        return 2
    ac = cfg.axis(name)
    node_id = args.node if args.node is not None else ac.node_id
    if not 1 <= node_id <= 127:
        print(f"drivectl: conformance: --node {node_id}: expected 1..127", file=sys.stderr)
        return 2
    eds = args.eds or str(ac.eds)
    b = cfg.bus
    emulator = None
    if b.interface == "virtual":
        from drivectl.plant_emulator.node402 import EmulatedDrive

        channel = unique_virtual_channel(b.channel)
        spec = plant_specs(cfg, [name])[name]
        emulator = ServedEmulator(channel, lambda net: EmulatedDrive(
            net, node_id, spec.build(cfg.cycle_s), rated_effort=ac.rated_effort, resolution=ac.encoder_m_per_count))
        net = threaded_network(open_bus("virtual", channel))
        where = f"virtual:{channel} (emulated drive, served on its own clock)"
    else:
        kwargs = {"host": b.host, "port": b.port} if b.interface == "socketcand" else {}
        net = threaded_network(open_bus(b.interface, b.channel, b.bitrate, **kwargs))
        where = f"{b.interface}:{b.channel}"
    if not args.json:
        print(f"conformance: node {node_id} on {where}, EDS {eds}", file=sys.stderr, flush=True)
    try:
        rows = run_checks(net, node_id, eds, emulated=emulator is not None, allow_enable=args.allow_enable,
                          only=args.only,
                          progress=None if args.json else lambda r: print(f"  {r.result:<4} {r.area} {r.name}",
                                                                         file=sys.stderr, flush=True))
    finally:
        close_threaded(net)
        if emulator is not None:
            emulator.close()
    failed = sum(r.result == FAIL for r in rows)
    if args.json:
        print(json.dumps({"node": node_id, "bus": where, "rows": [r.__dict__ for r in rows],
                          "passed": sum(r.result == PASS for r in rows), "failed": failed}))
    else:
        print(format_table(rows))
    return 1 if failed else 0

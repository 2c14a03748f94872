"""Conformance of the emulated drive and the bus budget (issue 19 point 5).

Runs every check of `drivectl conformance` (canopen's RemoteNode, BaseNode402, PdoMap, NMT master and EMCY
consumer as the third-party master) against the emulated drive of the embedded configuration, served
on its own thread and clock, and prints the table; then the bus budget: the most axes one 1 Mbit/s bus
carries at 1 kHz under the 70 % ceiling with the best mapping the drive takes (each of full, compact and
minimal configured on it by drivectl's master, CanopenAxis.connect: a remap it refuses rules that mapping
out), and the load of the three-axis default.

    python bench/conformance.py [--json]

``--json`` prints exactly one object: {"checks", "passed", "failed", "axes_per_bus_1khz",
"bus_load_3axes_pct"}.
"""

from __future__ import annotations

import argparse
import json
import logging

from drivectl.driver.axis import AxisError
from drivectl.driver.canopen_axis import CanopenAxis
from drivectl.driver.network import close_threaded, open_bus, threaded_network, unique_virtual_channel
from drivectl.driver.units import EffortScale, Encoder
from drivectl.machine.build import plant_specs
from drivectl.machine.bus_budget import AUTO_ORDER, axes_per_bus, bus_load, machine_load
from drivectl.machine.config import load_config
from drivectl.plant_emulator.node402 import EmulatedDrive
from drivectl.tools.conformance.suite import FAIL, PASS, ServedEmulator, format_table, run_checks


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    logging.getLogger("drivectl.emulator").setLevel(logging.ERROR)  # the malformed frames are on purpose
    cfg = load_config(None)
    ac = cfg.axis("x")
    spec = plant_specs(cfg, ["x"])["x"]
    channel = unique_virtual_channel("bench-conformance")
    emulator = ServedEmulator(channel, lambda net: EmulatedDrive(
        net, ac.node_id, spec.build(cfg.cycle_s), rated_effort=ac.rated_effort, resolution=ac.encoder_m_per_count))
    net = threaded_network(open_bus("virtual", channel))
    try:
        rows = run_checks(net, ac.node_id, str(ac.eds), emulated=True)
        taken = [m for m in AUTO_ORDER if _drive_takes(net, cfg, m)]
    finally:
        close_threaded(net)
        emulator.close()
    # bus.pdo_mapping = "auto" (the default): the first of full, compact, minimal that fits (and the drive takes)
    per_bus = max((axes_per_bus(0.001, 1_000_000, mapping=m) for m in taken), default=0)
    three = machine_load(cfg) if len(cfg.axes) == 3 else bus_load(3, 0.001, 1_000_000, "compact")
    out = {"checks": len(rows), "passed": sum(r.result == PASS for r in rows),
           "failed": sum(r.result == FAIL for r in rows), "axes_per_bus_1khz": per_bus,
           "bus_load_3axes_pct": round(three.nominal_pct, 1)}
    if args.json:
        print(json.dumps(out))
        return
    print(format_table(rows))
    print()
    best = max(taken, key=lambda m: axes_per_bus(0.001, 1_000_000, mapping=m)) if taken else None
    with_best = bus_load(per_bus, 0.001, 1_000_000, best).text() if best and per_bus else "-"
    print(f"axes per 1 Mbit/s bus at 1 kHz under 70 %: {per_bus} (target 4; mappings the drive takes: "
          f"{', '.join(taken) or 'none'}; {with_best}; see machine/bus_budget.py)")
    print(f"three-axis default: {three.text()} (target < 70 %)")


def _drive_takes(net, cfg, mapping: str) -> bool:
    """Whether the drive takes ``mapping`` as drivectl's master configures it (NMT reset, SDO remap, start)."""
    ac = cfg.axis("x")
    axis = CanopenAxis(net, ac.node_id, name="x", dt=cfg.cycle_s, effort_unit="N", eds=ac.eds,
                       encoder=Encoder(ac.encoder_m_per_count), effort_scale=EffortScale(ac.rated_effort),
                       mapping=mapping)
    try:
        axis.connect()
        return True
    except AxisError:
        return False
    finally:
        axis.close()
        net.nodes.pop(ac.node_id, None)


if __name__ == "__main__":
    main()

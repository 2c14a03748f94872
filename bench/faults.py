"""The fault matrix: every fault kind injected into the emulated machine, detection and reaction in cycles.

One lockstep run of axis x (embedded machine, short-move profile, 0.8 s) per case, the fault at
0.2 s after the drive is enabled. Per case: what the master detected, at which trace row, how many
cycles after the detection the drive had its torque off (the emulator's ground truth, not what the
master believed), and whether the trace on disk is whole (read back: every row up to the
detection, the fault's kind, cycle, statusword and 0x603F text in its metadata).

    python bench/faults.py [--json]

``--json`` prints exactly one object: {"faults": {KIND: {"detected", "safe_within_cycles",
"trace_complete"}}}; KIND is the case as ``--fault`` spells it (``tpdo-lost:cycles=10`` is the
N-cycle loss). Tolerated faults (one lost or late TPDO, a malformed frame) report 0 cycles: nothing
had to stop. The cases include a second RPDO producer, a second SYNC producer, foreign NMT commands
(Stop, Pre-operational, Reset Communication) and malformed frames (TPDO, EMCY, heartbeat, remote).
Each run streams its trace as drivectl trace does; a dead master's ``.partial`` file counts as whole
when it holds every row up to the injection. ``rogue-sync`` counts its cycles in the drive's SYNCs,
which the rogue doubles.
"""

from __future__ import annotations

import argparse
import json
import time

from drivectl.tools.conformance.fault_matrix import CASES, SAFE_BOUND_CYCLES, run_case


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print exactly one JSON object")
    ap.add_argument("--at", type=float, default=0.2, help="injection time, s after enable (default 0.2)")
    args = ap.parse_args()
    rows = []
    for case in CASES:
        t0 = time.perf_counter()
        o = run_case(case, at=args.at)
        rows.append((o, time.perf_counter() - t0))
    wall = sum(w for _, w in rows)
    if args.json:
        print(json.dumps({"faults": {o.case: {"detected": o.detected, "safe_within_cycles": o.safe_within_cycles,
                                              "trace_complete": o.trace_complete} for o, _ in rows}}))
        return
    kw = max(len("detected as"), *(len(o.kind) for o, _ in rows))  # columns as wide as their longest entry
    cw = max(len("fault (--fault)"), *(len(o.case) for o, _ in rows))
    sw = max(len("state"), *(len(o.safe_state) for o, _ in rows))
    head = (f"{'fault (--fault)':<{cw}} {'detected as':<{kw}} {'fired':>5} {'row':>5} {'detect':>7} {'safe in':>8} "
            f"{'state':<{sw}} {'trace':>6}")
    print(head)
    print("-" * len(head))
    for o, _ in rows:
        safe = "-" if o.safe_within_cycles is None else f"{o.safe_within_cycles} cyc"
        row = "-" if o.detect_cycle is None else str(o.detect_cycle)
        trace = ("partial" if o.case == "master-dead" else "whole") if o.trace_complete else "none"
        fired = "-" if o.inject_cycle is None else str(o.inject_cycle)
        det = "-" if o.detect_after is None else f"{o.detect_after} cyc"
        print(f"{o.case:<{cw}} {o.kind:<{kw}} {fired:>5} {row:>5} {det:>7} {safe:>8} {o.safe_state:<{sw}} "
              f"{trace:>6}")
        if o.note:
            print(f"{'':<{cw}} note: {o.note}")
    bad = [o.case for o, _ in rows if not (o.detected and o.safe_within_cycles is not None
                                            and o.safe_within_cycles <= o.bound_cycles)]
    print(f"\nsafe within {SAFE_BOUND_CYCLES} cycles of detection (plus the drive's RPDO deadline where only the drive "
          f"can notice: bus-off, master-dead): {len(rows) - len(bad)}/{len(rows)}"
          + (f" (not: {', '.join(bad)})" if bad else "") + f"; {wall:.1f} s wall")
    print("fired/row: trace rows of the injection and the detection; detect: cycles between them; safe in: "
          "cycles from the detection until the drive (emulator ground truth) had its torque off")


if __name__ == "__main__":
    main()

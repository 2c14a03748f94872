"""The soak: 10 minutes of simulated time, two axes in lockstep, random faults, recoveries, re-enables.

Axes x and y of the embedded machine (emulated CiA 402 drives on the virtual bus, CANopen masters)
run back-to-back random moves; before most moves a random fault is armed on a random axis (every
kind that leaves the master alive). Every fault that fired must be found in the traces (read back
from disk), memory must stay flat (tracemalloc after a warm-up of 10 %, at ten points after it and
at the end, each after a full garbage collection; the least-squares slope says what 100 more moves
would add), and no move may hang (a faulthandler guard dumps the stacks and exits after 120 s of wall time in one move).
tracemalloc slows the loop several times: 10 simulated minutes take 15-20 minutes here.

    python bench/soak.py [--minutes 10] [--seed 1] [--json]
"""

from __future__ import annotations

import argparse
import json

from drivectl.tools.conformance.soak import run_soak


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0, help="simulated minutes (default 10)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json", action="store_true", help="print exactly one JSON object")
    args = ap.parse_args()
    r = run_soak(60.0 * args.minutes, seed=args.seed, progress=not args.json)
    out = {
        "simulated_s": round(r.simulated_s, 3),
        "moves": r.moves,
        "faults_injected": sum(r.injected.values()),
        "faults_accounted": sum(r.accounted.values()),
        "unaccounted": r.unaccounted,
        "memory_warm_kib": round(r.memory_warm_kib, 1),
        "memory_end_kib": round(r.memory_end_kib, 1),
        "memory_growth_kib": round(r.memory_growth_kib, 1),
        "memory_slope_kib_per_100_moves": round(r.memory_slope_kib_per_100_moves, 2),
        "worst_move_wall_s": round(r.worst_move_wall_s, 3),
        "wall_s": round(r.wall_s, 1),
    }
    if args.json:
        print(json.dumps(out))
        return
    print(f"simulated {r.simulated_s:.1f} s in {r.moves} moves, {r.wall_s:.0f} s wall "
          f"(worst move {r.worst_move_wall_s:.2f} s wall: no hang)")
    print(f"{'fault':<28} {'injected':>9} {'accounted':>10}")
    for case in sorted(r.injected):
        print(f"{case:<28} {r.injected[case]:>9} {r.accounted[case]:>10}")
    print(f"{'all':<28} {sum(r.injected.values()):>9} {sum(r.accounted.values()):>10}   recoveries {r.recoveries}")
    for line in r.unaccounted:
        print(f"  NOT ACCOUNTED: {line}")
    print(f"memory (tracemalloc): {r.memory_warm_kib:.0f} KiB after warm-up, {r.memory_end_kib:.0f} KiB at the end "
          f"({r.memory_growth_kib:+.0f} KiB), peak {r.memory_peak_kib:.0f} KiB")
    print("memory samples (moves: KiB, after a full collection): "
          + ", ".join(f"{m}: {k:.0f}" for m, k in r.memory_samples))
    print(f"slope {r.memory_slope_kib_per_100_moves:+.1f} KiB per 100 moves")


if __name__ == "__main__":
    main()

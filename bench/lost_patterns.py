"""Lost and late TPDO answers across processes, on a simulated wall clock: how far x is from its reference.

Each row is one pattern of `tests/test_timing.py`'s `_AcrossProcesses` harness (x's master as across processes,
its TPDOs handed to it on a schedule, a wait for TPDOs that do not come taking the master's whole budget of
simulated time; the in-process drive stepping by the master's slots, as `drivectl emulate` does for a paced
master): x under mbc to 80 mm at 74 mm/s, five or ten times a pattern of lost or late answers, with or without
late wake-ups of the loop after them. Columns: max |reference - position| over the move (um) and the fault, if
any. Deterministic: the same figures on any host (docs/timing.md, "Across processes: an answer after the next
SYNC"). A few seconds of CPU per row.

    python bench/lost_patterns.py [--cycle-s 0.001] [--json]

--json prints exactly {"cycle_s", "rows": [{"pattern", "max_error_um", "fault"}]}.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))


def patterns(cycle_s: float) -> list[tuple[str, dict]]:
    s = 0.001 / cycle_s  # the 1 ms tests' patterns at the same times
    at = [int((400 + 197 * k) * s) for k in range(5)]

    def burst(n: int) -> list[int]:
        return [a + j for a in at for j in range(n)]

    rows = [("ten single losses, ten 4 ms late wake-ups",
             {"lost": [int((400 + 97 * k) * s) for k in range(10)],
              "wake_ups": {int((450 + 111 * k) * s): 0.004 for k in range(10)}}),
            ("ten late answers, ten 4-8 ms late wake-ups",
             {"late": [int((400 + 97 * k) * s) for k in range(10)],
              "wake_ups": {int((450 + 111 * k) * s): 0.004 + 0.001 * (k % 5) for k in range(10)}})]
    for n in (2, 3, 5):
        rows.append((f"five bursts of {n} lost", {"lost": burst(n)}))
        rows.append((f"five bursts of {n} lost, 6 ms late wake-ups",
                     {"lost": burst(n), "wake_ups": {a + n: 0.006 for a in at}}))
        rows.append((f"five bursts of {n} late, 6 ms late wake-ups",
                     {"late": burst(n), "wake_ups": {a + n: 0.006 for a in at}}))
    return rows


def run_row(tmp: Path, cycle_s: float, kw: dict) -> tuple[float, str | None]:
    from test_timing import _AcrossProcesses

    run = _AcrossProcesses(tmp, drive_clock="slots", cycle_s=cycle_s, **kw)
    try:
        err = run.move(int(round(1.8 / cycle_s)))
        fault = run.loop.faults[0].detail if run.loop.faults else None
    finally:
        run.close()
    return float(np.max(np.abs(err))) * 1e6, fault


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cycle-s", type=float, default=0.001, help="the servo cycle (default 0.001)")
    ap.add_argument("--json", action="store_true", help="print exactly one JSON object")
    args = ap.parse_args()
    if not 0.0005 <= args.cycle_s <= 0.004:
        ap.error(f"--cycle-s: 0.0005 to 0.004 s, got {args.cycle_s:g}")
    warnings.simplefilter("ignore")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, kw in patterns(args.cycle_s):
            err, fault = run_row(Path(tmp), args.cycle_s, kw)
            rows.append({"pattern": name, "max_error_um": round(err, 2), "fault": fault})
            if not args.json:
                print(f"{name:48s} {err:9.1f} um  {fault or ''}", flush=True)
    if args.json:
        print(json.dumps({"cycle_s": args.cycle_s, "rows": rows}))
    return 0


if __name__ == "__main__":
    sys.exit(main())

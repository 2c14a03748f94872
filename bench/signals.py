"""Ctrl-C and SIGTERM under load: does every interrupted trace stop cleanly, or does one hang?

Spawns ``drivectl trace --axis x --duration 600`` (embedded emulated drive, virtual bus) ``--runs``
times, ``--parallel`` at once so the machine is loaded, sends SIGINT or SIGTERM (alternating) right
after each prints its start line, and waits ``--hang-after`` seconds for it to exit. A run that
does not exit by then counts as hung and is killed. The hang it looks for: a KeyboardInterrupt raised
inside a CAN queue's lock leaves the lock held, and the quick stop then waits on it for ever; which is why
the signals are read at cycle boundaries (controllers/runtime/interrupt.py), between whole frames.

    python bench/signals.py [--runs 120] [--parallel 8] [--json]

``--json`` prints exactly one object: {"runs", "clean", "hung", "other", "exit_codes"}; clean is
the runs that exited 130 (SIGINT) / 143 (SIGTERM) with the trace kept.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path


def one_run(i: int, hang_after: float) -> tuple[str, int | None, bool]:
    """(signal name, exit code or None when hung, trace file present)."""
    sig = (signal.SIGINT, signal.SIGTERM)[i % 2]
    with tempfile.TemporaryDirectory() as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "drivectl", "trace", "--axis", "x", "--duration", "600", "--out", out,
             "--quiet", "--no-plot"],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"}, cwd=out,
        )
        line = proc.stderr.readline()
        if not line.startswith("trace: axis x"):
            proc.kill()
            proc.communicate()
            return sig.name, -1, False
        proc.send_signal(sig)
        try:
            proc.communicate(timeout=hang_after)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
            return sig.name, None, False
        return sig.name, proc.returncode, (Path(out) / "x.csv").exists()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=120)
    ap.add_argument("--parallel", type=int, default=8)
    ap.add_argument("--hang-after", type=float, default=60.0, help="seconds after the signal (default 60)")
    ap.add_argument("--json", action="store_true", help="print exactly one JSON object")
    args = ap.parse_args()
    for key in ("runs", "parallel"):
        if getattr(args, key) < 1:
            ap.error(f"--{key}: must be >= 1")
    t0 = time.perf_counter()
    done = 0
    results = []
    with ThreadPoolExecutor(max_workers=args.parallel) as pool:
        for r in pool.map(lambda i: one_run(i, args.hang_after), range(args.runs)):
            results.append(r)
            done += 1
            if not args.json:
                print(f"\rsignals: {done}/{args.runs} runs", end="", file=sys.stderr, flush=True)
    wall = time.perf_counter() - t0
    expected = {"SIGINT": 130, "SIGTERM": 143}
    clean = sum(1 for name, rc, kept in results if rc == expected[name] and kept)
    hung = sum(1 for _, rc, _ in results if rc is None)
    codes = Counter("hung" if rc is None else str(rc) for _, rc, _ in results)
    if args.json:
        print(json.dumps({"runs": args.runs, "clean": clean, "hung": hung, "other": args.runs - clean - hung,
                          "exit_codes": dict(sorted(codes.items()))}))
        return
    print(f"\r{'signal':<8} {'runs':>5} {'clean':>6} {'hung':>5} {'other':>6}", file=sys.stdout)
    print("-" * 34)
    for name in expected:
        mine = [r for r in results if r[0] == name]
        c = sum(1 for _, rc, kept in mine if rc == expected[name] and kept)
        h = sum(1 for _, rc, _ in mine if rc is None)
        print(f"{name:<8} {len(mine):>5} {c:>6} {h:>5} {len(mine) - c - h:>6}")
    print(f"exit codes: {dict(sorted(codes.items()))}; {args.parallel} at once, {wall:.0f} s wall")


if __name__ == "__main__":
    main()

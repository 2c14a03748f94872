"""What the loop's own process costs the user's side (issue 39 point 1): the same session, the loop a thread
of the program (``connect(loop="thread")``) or a process of its own (``loop="process"``, session_process.py).

Each mode runs in a fresh interpreter of its own (so that its memory is its own): the embedded machine's x
on the wall clock, enabled and holding, then

* connect: from ``drivectl.connect()`` to the first cycle (s);
* command: one ``x.stop()`` call, until it returns (us; through the process: one round trip on the
  manager's socket and the submit there), median and p99 of --n calls;
* applied: from that call until the loop has taken the command (its handle under way in the loop's
  record: the shared block through the process), median and p99 (ms; includes up to one cycle's wait);
* status: one ``m.status()`` (us; through the process: the shared block, and once a second a call for
  the texts and percentiles), median and p99 of 10 x --n calls;
* memory: resident set (MB) of the program's process and, through the process, of the loop's process
  (all of it locked by mlockall where granted, so every mapped page counts).

    python bench/loop_process.py [--n 300] [--json]

--json prints exactly {"connect_s_thread", "connect_s_process", "command_us_thread", "command_us_process",
"applied_ms_thread", "applied_ms_process", "status_us_thread", "status_us_process", "rss_mb_thread",
"rss_mb_process_user", "rss_mb_process_loop"} (medians). The figures are wall-clock measurements on a
shared machine: quote the load with them (printed).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time


def _rss_mb(pid: int | str = "self") -> float:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def _quantiles(xs: list[float]) -> tuple[float, float]:
    xs = sorted(xs)
    return xs[len(xs) // 2], xs[min(len(xs) - 1, int(0.99 * len(xs)))]


def one(loop: str, n: int) -> dict:
    import drivectl

    t0 = time.perf_counter()
    m = drivectl.connect(axes=["x"], clock="wall", fault_dir=None, loop=loop)
    connect_s = time.perf_counter() - t0
    try:
        x = m.axes["x"]
        x.enable()
        rt = m.loop.axes["x"]
        cmd, applied = [], []
        for _ in range(n):
            while rt.handle is not None:  # the previous stop's settling: the axis free again
                time.sleep(0.001)
            t = time.perf_counter()
            h = x.stop()
            t1 = time.perf_counter()
            spins = 0
            while rt.handle is None:  # the stop's handle under way in the loop's record (10 ms of settling)
                spins += 1
                if spins % 1000 == 0 and h.done:  # this process was descheduled past it: seen ended
                    break
            t2 = time.perf_counter()
            cmd.append((t1 - t) * 1e6)
            applied.append((t2 - t) * 1e3)
        st = []
        for _ in range(10 * n):
            t = time.perf_counter()
            m.status()
            st.append((time.perf_counter() - t) * 1e6)
        out = {"connect_s": connect_s, "command_us": _quantiles(cmd), "applied_ms": _quantiles(applied),
               "status_us": _quantiles(st), "rss_mb_user": _rss_mb(),
               "rss_mb_loop": _rss_mb(m.pid) if loop == "process" else None,
               "missed_fraction": m.status()["missed_fraction"]}
    finally:
        m.close()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=300, help="commands per mode (default 300)")
    ap.add_argument("--json", action="store_true", help="print exactly one JSON object")
    ap.add_argument("--one", choices=("thread", "process"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.n < 10:
        ap.error(f"--n: at least 10, got {args.n}")
    if args.one:
        print(json.dumps(one(args.one, args.n)))
        return
    got = {}
    for loop in ("thread", "process"):
        done = subprocess.run([sys.executable, __file__, "--one", loop, "--n", str(args.n)], capture_output=True,
                              text=True, check=False)
        if done.returncode != 0:
            print(done.stderr, file=sys.stderr)
            raise SystemExit(f"loop_process: the {loop} run failed")
        got[loop] = json.loads(done.stdout.strip().splitlines()[-1])
    th, pr = got["thread"], got["process"]
    result = {"connect_s_thread": th["connect_s"], "connect_s_process": pr["connect_s"],
              "command_us_thread": th["command_us"][0], "command_us_process": pr["command_us"][0],
              "applied_ms_thread": th["applied_ms"][0], "applied_ms_process": pr["applied_ms"][0],
              "status_us_thread": th["status_us"][0], "status_us_process": pr["status_us"][0],
              "rss_mb_thread": th["rss_mb_user"], "rss_mb_process_user": pr["rss_mb_user"],
              "rss_mb_process_loop": pr["rss_mb_loop"]}
    if args.json:
        print(json.dumps(result))
        return
    load = " ".join(f"{v:.2f}" for v in os.getloadavg())
    print(f"x holding at 1 kHz on the wall clock; {args.n} commands per mode; load average {load}")
    head = f"{'':<28} {'thread':>16} {'process':>16}"
    print(head)
    print("-" * len(head))
    print(f"{'connect (s)':<28} {th['connect_s']:>16.2f} {pr['connect_s']:>16.2f}")
    for key, what, f in (("command_us", "command x.stop() (us)", ".0f"), ("applied_ms", "command applied (ms)", ".2f"),
                         ("status_us", "status() (us)", ".1f")):
        a, b = th[key], pr[key]
        print(f"{what + ' p50 / p99':<28} {f'{a[0]:{f}} / {a[1]:{f}}':>16} {f'{b[0]:{f}} / {b[1]:{f}}':>16}")
    both = f"{pr['rss_mb_user']:.1f} + {pr['rss_mb_loop']:.1f}"
    print(f"{'memory (MB resident)':<28} {th['rss_mb_user']:>16.1f} {both:>16}")
    a, b = th["missed_fraction"] * 100, pr["missed_fraction"] * 100
    print(f"{'missed % (whole run)':<28} {a:>16.3f} {b:>16.3f}")


if __name__ == "__main__":
    main()

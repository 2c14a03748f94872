"""``drivectl doctor``: a preflight of the host, the bus and the drives before anything is enabled.

The host part runs the resident loop itself (controllers/runtime/loop.py) on the wall clock for
``--seconds``: the same thread set-up (priority, affinity, GC and GIL measures), the cycle's real work on
the configured bus (SYNC, TPDOs, RPDOs of every axis), no axis enabled. It reports the lateness
percentiles of every cycle and what the OS granted, the kernel (PREEMPT_RT or not) and the bus load, and
per axis the deadline it uses (controllers/runtime/timing.py, docs/timing.md) and whether the host meets it.

The drives part (:func:`drive_sections`, driver/drive_report.py) says, per drive, what the master found and
wrote (identity, 0x6502, mode, mapping, watchdogs, the deadline, the fallbacks) and what would stop an
enable, read without enabling (``--try-enable``: an attempt at zero torque, disabled after as the drive
confirms); ``enable`` refuses on the same timing verdict (session.py).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
from pathlib import Path
from typing import Any

VERDICTS = ("ok", "warn", "refuse")
#: exit codes per verdict (tools/cli/main.py: 0 ok, 4 warnings, 3 a refusal)
VERDICT_EXIT = {"ok": 0, "warn": 4, "refuse": 3}


def add_doctor_parser(sub: Any) -> None:
    d = sub.add_parser("doctor", help="preflight of the host, the bus and the drives (timing probe, deadlines)",
                       description="Run the resident loop's timing probe for --seconds with no axis enabled and "
                       "judge the host's lateness against every axis's deadline (docs/timing.md).")
    d.add_argument("--seconds", type=float, default=10.0, help="how long the timing probe runs (default 10)")
    d.add_argument("--axis", action="append", metavar="NAME", help="the axes to check (default: all)")
    d.add_argument("--json", action="store_true", help="one JSON object: latency_ms, deadline_ms, cycle_s, "
                   "recommended_cycle_s, granted, verdict, late_share, cpu_share, missed_fraction")
    d.add_argument("--out", metavar="PNG", default="doctor-latency.png",
                   help="the lateness histogram's plot (default doctor-latency.png; not with --json)")
    d.add_argument("--cpu", type=int, default=None, help="pin the loop's thread to this CPU")
    d.add_argument("--try-enable", action="store_true", help="after the probe, enable each drive at zero torque "
                   "and disable it again (confirmed by the drive), to say whether it enables or why not")


def kernel() -> dict[str, Any]:
    """The running kernel and whether it is PREEMPT_RT (what bounds the OS's wake-up latency)."""
    version = platform.version()
    rt = "PREEMPT_RT" in version or "PREEMPT RT" in version
    try:
        rt = rt or Path("/sys/kernel/realtime").read_text().strip() == "1"
    except OSError:
        pass
    preempt = next((m for m in ("PREEMPT_RT", "PREEMPT_DYNAMIC", "PREEMPT ") if m in version), "")
    try:  # the mode in use is the bracketed one: "always [madvise] never"
        text = Path("/sys/kernel/mm/transparent_hugepage/enabled").read_text()
        thp = text[text.index("[") + 1:text.index("]")]
    except (OSError, ValueError):
        thp = None
    return {"release": platform.release(), "version": version, "preempt_rt": rt,
            "preemption": preempt.strip() or "none or voluntary", "transparent_hugepages": thp}


def probe(cfg: Any, names: list[str], seconds: float, cpu: int | None = None,
          try_enable: bool = False) -> dict[str, Any]:
    """The loop's own timing probe: the wall-clock loop over the configured bus, no axis enabled."""
    import math

    from drivectl.controllers.registry import make_controller
    from drivectl.controllers.runtime.cycle import Channel
    from drivectl.controllers.runtime.loop import ServoLoop
    from drivectl.machine.build import open_machine, plant_specs

    specs = plant_specs(cfg, names)
    hw = open_machine(cfg, names)
    try:
        channels = [Channel(hw.axes[n], make_controller(cfg.axis(n).controller, cfg.cycle_s,
                                                        cfg.axis(n).controller_settings, plant=specs[n], axis=n),
                            None, cfg.axis(n).limits) for n in names]  # type: ignore[arg-type]
        loop = ServoLoop(channels, clock="wall", stall_s=None, fault_dir=None, cpu=cpu, realtime=True,
                         deadlines={n: d.seconds for n, d in hw.deadlines.items()})
        loop.start()
        try:
            loop.run_until(lambda: False, seconds)
            status = loop.status()
        finally:
            loop.close()
        return {"status": status, "latency": loop.latency, "deadlines": hw.deadlines,
                "drives": drive_sections(hw, names, try_enable), "cycles": status["cycles"],
                "finite": all(math.isfinite(v) for v in status["latency_ms"].values())}
    finally:
        hw.close()


def drive_sections(hw: Any, names: list[str], try_enable: bool = False) -> dict[str, dict[str, str]]:
    """Per drive, what the master found and wrote (driver/drive_report.py): identity, 0x6502, mode, mapping,
    watchdogs, the fallbacks, and what would stop an enable, read without enabling; with ``try_enable`` an
    enable attempt at zero torque (disabled after, as the drive confirms) says whether it enables or why not.
    The deadline written (0x1400:05) is the timing model's. Called after the probe's loop has stopped."""
    from drivectl.driver.canopen_axis import CanopenAxis
    from drivectl.driver.drive_report import drive_lines, enable_attempt, standing_blocker

    out: dict[str, dict[str, str]] = {}
    for n in names:
        axis = hw.axes[n]
        d = hw.deadlines.get(n)
        sec: dict[str, str] = {}
        if d is not None:
            sec["deadline"] = (f"{d.ms} ms written to 0x1400:05 ({d.source}: {d.formula})" if d.ms else
                               "0x1400:05 = 0: the drive does not watch the master's setpoints")
        if isinstance(axis, CanopenAxis):
            for what, value in drive_lines(axis):
                sec[what] = f"{sec[what]}; {value}" if what in sec else value
            if try_enable:
                ok, said = enable_attempt(axis)
                sec["enable"] = said if ok else "does not enable: " + said
            else:
                sec["enable"] = standing_blocker(axis)
        sec["power"] = axis.power.value
        out[n] = sec
    return out


def assess(deadlines: dict[str, Any], dt: float,
           latency_ms: dict[str, float]) -> tuple[str, dict[str, tuple[str, str]]]:
    """The verdict over every axis (the worst) and, per axis, its own with the figures."""
    from drivectl.controllers.runtime.timing import judge

    per = {n: judge(d.seconds, dt, latency_ms) for n, d in deadlines.items()}
    worst = max((v for v, _ in per.values()), key=VERDICTS.index, default="ok")
    return worst, per


def plot_histogram(latency: Any, deadlines: dict[str, Any], dt: float, path: str | Path) -> Path:
    """The lateness histogram (log-log) with each axis's margin (deadline - cycle) marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    used = [i for i, c in enumerate(latency.counts) if c]
    lo, hi = (used[0], used[-1] + 1) if used else (0, 1)
    edges = [latency.edge(i - 1) * 1e3 for i in range(lo, hi + 1)]  # bin i holds (edge(i-1), edge(i)]
    fig, ax = plt.subplots(figsize=(7, 3.6))
    ax.stairs(latency.counts[lo:hi], edges, fill=True)
    margins: dict[float, list[str]] = {}
    for name, d in deadlines.items():
        if d.seconds > dt:
            margins.setdefault(round((d.seconds - dt) * 1e3, 3), []).append(name)
    for margin, axes in margins.items():
        ax.axvline(margin, ls="--", lw=0.8, color="C3")
        ax.text(margin, max(latency.counts), " " + ", ".join(axes), color="C3", va="top", fontsize=8)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("lateness of the cycle's start (ms)")
    ax.set_ylabel("cycles")
    ax.set_title(f"{latency.n} cycles of {dt * 1e3:g} ms; dashed: each axis's margin (deadline - cycle)")
    fig.subplots_adjust(left=0.11, right=0.97, bottom=0.14, top=0.9)
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def cmd_doctor(args: argparse.Namespace) -> int:
    from drivectl.controllers.runtime.host import steal_s
    from drivectl.controllers.runtime.timing import WAYS_OUT, recommend_cycle
    from drivectl.machine.bus_budget import machine_load
    from drivectl.machine.config import load_config

    if not (args.seconds > 0):
        print(f"drivectl: doctor: --seconds: must be > 0, got {args.seconds:g}", file=sys.stderr)
        return 2
    cfg = load_config(args.config)
    names = list(args.axis) if args.axis else list(cfg.axes)
    for n in names:
        cfg.axis(n)
    load = machine_load(cfg, names)
    steal0 = steal_s()
    res = probe(cfg, names, args.seconds, args.cpu, args.try_enable)
    steal1 = steal_s()
    status, deadlines = res["status"], res["deadlines"]
    lat = status["latency_ms"]
    verdict, per = assess(deadlines, cfg.cycle_s, lat)
    late_share = res["latency"].share_over(0.5 * cfg.cycle_s)
    cycle, cycle_why = recommend_cycle(cfg.cycle_s, status.get("cpu_share"), late_share)
    if cycle > cfg.cycle_s and verdict == "ok":
        verdict = "warn"  # the deadlines hold, but the host does not keep this cycle's slots (timing.py)
    if args.json:
        print(json.dumps({"latency_ms": lat, "deadline_ms": {n: d.ms for n, d in deadlines.items()},
                          "cycle_s": cfg.cycle_s, "recommended_cycle_s": cycle, "granted": status["granted"],
                          "verdict": verdict, "late_share": late_share, "cpu_share": status.get("cpu_share"),
                          "missed_fraction": status["missed_fraction"]}))
        return VERDICT_EXIT[verdict]
    holds = []
    if cycle > cfg.cycle_s:  # a gain tuned at one cycle may not hold at another: simulated, said beside it
        from drivectl.tools.commissioning.cycle_check import hold_at

        holds = [hold_at(cfg, n, cycle) for n in names]
    k = kernel()
    print(f"host      {platform.node()}: {os.cpu_count()} CPUs, kernel {k['release']} "
          f"({'PREEMPT_RT' if k['preempt_rt'] else 'not PREEMPT_RT'}); load average "
          f"{' '.join(_loadavg())}")
    if not k["preempt_rt"]:  # what can hold a real-time thread off on such a kernel (docs/timing.md)
        print(f"          preemption {k['preemption']}; transparent huge pages {k['transparent_hugepages'] or '?'} "
              "(khugepaged can hold a CPU for ms: this process opts out, others may not)")
    print(f"bus       {cfg.bus.interface}:{cfg.bus.channel}: {load.text()}")
    print(f"probe     {status['cycles']} cycles of {cfg.cycle_s * 1e3:g} ms in {args.seconds:g} s, no axis enabled; "
          f"{status['missed_deadlines']} missed, {status['skipped_cycles']} skipped")
    print("lateness  " + "  ".join(f"{q} {v:.3f} ms" for q, v in lat.items()))
    print(f"cycle     {cycle * 1e3:g} ms recommended" + (" (as configured)" if cycle == cfg.cycle_s else
          f" (cycle_s = {cycle!r} in the configuration; {cfg.cycle_s * 1e3:g} ms is configured)") + f": {cycle_why}")
    for h in holds:
        print(f"          axis {h.axis}: {h.text()}")
    if any(v == "refuse" for v, _ in per.values()):  # the cycle is about slots; a refusal is about the deadlines
        print("          no cycle mends the refusal below: a longer one leaves the host less time before each "
              "deadline (deadline - cycle)")
    if steal0 and steal1:  # the hypervisor's share of the lateness (host.py): no setting in this guest helps it
        print("steal     " + ", ".join(f"{c} {(steal1[c] - steal0.get(c, steal1[c])) * 1e3:.0f} ms" for c in steal1)
              + " taken by the hypervisor during the probe (on a virtual machine: its host ran something else)")
    for what, text in status["granted"].items():
        print(f"granted   {what}: {text}")
    for n, d in deadlines.items():
        v, why = per[n]
        print(f"axis {n:<4} deadline {d.ms} ms ({d.source}: {d.formula}): {v}: {why}")
        for item, text in res["drives"].get(n, {}).items():
            if item != "deadline":
                print(f"          {item}: {text}")
    path = plot_histogram(res["latency"], deadlines, cfg.cycle_s, args.out)
    print(f"histogram {path}")
    print(f"verdict   {verdict}" + (f" ({WAYS_OUT})" if verdict != "ok" else ""))
    return VERDICT_EXIT[verdict]


def _loadavg() -> list[str]:
    try:
        return Path("/proc/loadavg").read_text().split()[:3]
    except OSError:
        return ["?"]

"""The fault matrix: every injectable fault, run on the emulated machine, checked end to end.

For each case one lockstep run of axis x (embedded machine, ``short-move`` profile by default) with
the fault injected at ``AT`` s, and the outcome measured from both sides:

* the master's side: did it detect the fault (and as what), at which cycle, and what did it record
  (the trace, read back from disk: rows, fault metadata, counters);
* the drive's side (the emulator's ground truth, not the master's belief): how many cycles after the
  detection the drive had its torque off (Switch On Disabled, Quick Stop Active, Fault). When the
  master can no longer reach the drive (bus-off, a dead master) the drive's own clock runs on
  (:meth:`Machine.let_drives_run`) and its own watchdogs must stop it.

Shared by tests/test_faults.py and bench/faults.py, so the test asserts what the bench prints.
"""

from __future__ import annotations

import math
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from drivectl.driver.cia301 import SYNC_COB_ID

#: how every case is expected to end: the master's stop (None: tolerated, the run completes) and
#: the fault kind it must report (None: no fault; "drive" = the drive stops itself, master gone)
CASES: dict[str, tuple[str | None, str | None]] = {
    "tpdo-lost": (None, None),
    "tpdo-lost:cycles=10": ("fault", "tpdo timeout"),
    "tpdo-late": (None, None),
    "sync-no-response": ("fault", "tpdo timeout"),
    "heartbeat-stop": ("fault", "heartbeat lost"),
    "emcy-fault": ("fault", "drive fault"),
    "node-reset": ("fault", "unexpected boot-up"),
    "encoder-glitch": ("fault", "implausible position"),
    "bus-error": ("fault", "bus error"),
    "bus-off": ("fault", "bus error"),
    "sdo-abort": ("refused", "sdo abort"),
    "limit-switch": ("fault", "drive fault"),
    "master-dead": ("drive", None),
    "rogue-rpdo": ("fault", "rogue rpdo"),
    "rogue-sync": ("fault", "rogue sync"),
    "foreign-nmt": ("fault", "foreign nmt"),
    "foreign-nmt:command=0x80": ("fault", "foreign nmt"),
    "foreign-nmt:command=0x82": ("fault", "foreign nmt"),
    "malformed-frame": (None, None),
    "malformed-frame:function=0x80,length=3": (None, None),
    "malformed-frame:function=0x700,length=0,cycles=5": (None, None),
    "malformed-frame:rtr=1,cycles=2": (None, None),
}

#: the bound every stop must meet: cycles from the detection to the torque off
SAFE_BOUND_CYCLES = 2


@dataclass
class Outcome:
    case: str
    detected: bool = False
    kind: str = ""  # what the master (or, for master-dead, the drive) reported
    inject_cycle: int | None = None  # trace row at which the fault fired
    detect_cycle: int | None = None  # trace row of the detection
    safe_within_cycles: int | None = None  # drive ground truth; 0 for tolerated faults
    safe_state: str = ""
    trace_complete: bool = False
    exit_reason: str = ""
    rows: int = 0
    meta: dict[str, str] = field(default_factory=dict)
    note: str = ""
    #: the bound this case must meet: SAFE_BOUND_CYCLES from the detection, plus the drive's RPDO deadline
    #: (0x1400:05, in cycles) where only the drive can notice (the master is dead or off the bus)
    bound_cycles: int = SAFE_BOUND_CYCLES

    @property
    def detect_after(self) -> int | None:
        """Cycles from the injection to the detection."""
        if self.inject_cycle is None or self.detect_cycle is None:
            return None
        return self.detect_cycle - self.inject_cycle

    @property
    def ok(self) -> bool:
        return (self.detected and self.trace_complete and self.safe_within_cycles is not None
                and self.safe_within_cycles <= self.bound_cycles)


def _deadline_cycles(machine: Any, cycle_s: float) -> int:
    """The drive's RPDO deadline (docs/timing.md) in whole cycles: how long it waits before it stops itself."""
    d = machine.deadlines.get("x")
    return math.ceil(d.ms * 1e-3 / cycle_s - 1e-9) if d is not None and d.ms else 0


def run_case(case: str, *, at: float = 0.2, profile: str = "short-move", duration: float = 0.8,
             out_dir: str | Path | None = None, config: str | None = None) -> Outcome:
    """Run one fault case (``KIND[:k=v,...]``, injected at ``at`` s) for ``duration`` s and measure its
    outcome (0.8 s: a lost heartbeat takes 300-400 ms to be noticed)."""
    from drivectl.controllers.registry import make_controller
    from drivectl.controllers.runtime.servo import SAFE_STATES, Channel, run_channels
    from drivectl.driver.axis import AxisConfigError
    from drivectl.machine.build import open_machine
    from drivectl.machine.config import load_config
    from drivectl.plant_emulator.faults import MasterDied, parse_fault
    from drivectl.profiles.library import load_profile
    from drivectl.tracefile.format import Trace

    spec = parse_fault(f"{case}@{at:g}")
    cfg = load_config(config)
    ac = cfg.axis("x")
    prof = load_profile(profile, axis="x")
    out = Outcome(case)
    tmp = None
    if out_dir is None:
        tmp = tempfile.TemporaryDirectory(prefix="drivectl-faults-")
        out_dir = tmp.name
    # the run streams its trace into a folder of its own (x-STAMP.csv, x.csv the latest), as drivectl trace does
    folder = Path(out_dir) / case.replace(":", "_").replace("=", "").replace(",", "_")
    try:
        try:
            machine = open_machine(cfg, ["x"], faults=[spec], start={"x": prof.start_position})
        except AxisConfigError as exc:
            # refused while configuring: nothing moved, nothing written
            out.detected, out.kind, out.exit_reason = True, "sdo abort" if "abort" in str(exc) else "config", str(exc)
            out.safe_within_cycles, out.safe_state = 0, "never enabled"
            out.trace_complete = not folder.exists()
            out.note = "refused before anything moved: no trace by design (exit 2)"
            return out
        with machine:
            drive = machine.drives["x"]
            history: list[tuple[int, bool]] = []  # (drive SYNC count, torque off) at every SYNC

            def watch(can_id: int, data: bytes, timestamp: float) -> None:
                d = drive.drive
                history.append((d.syncs, d.power in SAFE_STATES and d.applied == 0.0))

            drive.network.subscribe(SYNC_COB_ID, watch)  # after the drive's own handler: sees its new state
            axis = machine.axes["x"]
            ctrl = make_controller(ac.controller, cfg.cycle_s, ac.controller_settings, plant=machine.specs["x"],
                                   axis="x")
            channel = Channel(axis, ctrl, prof, ac.limits, {"injected": str(spec)})
            row0: list[int] = []  # the SYNC count of trace row 0
            try:
                result = run_channels([channel], duration=duration, on_start=lambda n: row0.append(axis.clock.cycle),
                                      stream=folder)
            except MasterDied:
                out.inject_cycle = _fired_row(machine, row0)
                safe = machine.let_drives_run(50, until_safe=True)["x"]
                out.detected = safe is not None
                out.kind = f"drive stopped itself (0x603F = 0x{drive.drive.error_code:04X})" if safe is not None else ""
                out.detect_cycle = history[-1][0] - row0[0] if row0 and history else None
                out.safe_within_cycles = safe
                out.bound_cycles = SAFE_BOUND_CYCLES + _deadline_cycles(machine, cfg.cycle_s)
                out.safe_state = drive.drive.power.value
                out.exit_reason = "master died (no exit: the process is gone)"
                # what the dead master streamed stays as a .partial file, every reader reads it (marked
                # incomplete): whole when it holds every row up to the injection
                partial = sorted(folder.glob("x-*.csv.partial"))
                back = Trace.read(partial[0]) if len(partial) == 1 else None
                out.rows = len(back) if back is not None else 0
                out.meta = dict(back.meta) if back is not None else {}
                out.trace_complete = (back is not None and out.inject_cycle is not None
                                      and out.rows >= out.inject_cycle and bool(np.isfinite(back.pos).all()))
                out.note = ("the master's streamed trace stays as a .partial file (up to its last flush); the "
                            "drive stopped on its RPDO deadline (0x1400:05) per 0x6007")
                return out
            out.inject_cycle = _fired_row(machine, row0)
            back = Trace.read(result.paths["x"])  # what the run streamed to disk, read back
            out.rows, out.meta = len(back), dict(back.meta)
            out.exit_reason = result.detail or "completed"
            n_planned = int(round(duration / cfg.cycle_s)) + 1
            finite = len(back) > 0 and bool(np.isfinite(back.pos).all() and np.isfinite(back.effort).all())
            if result.fault is None:
                counted = sum(int(back.meta.get(k, "0")) for k in ("tpdo_lost_cycles", "tpdo_late_frames",
                                                                   "malformed_frames"))
                out.detected = counted > 0
                out.kind = f"tolerated ({counted} counted)"
                out.safe_within_cycles = 0  # nothing to stop: the run went on, by design
                out.safe_state = "ran to the end, then disabled"
                out.trace_complete = len(back) == n_planned and finite and result.ok
                return out
            f = result.fault
            out.detected, out.kind, out.detect_cycle = True, f.kind, f.cycle
            needed = ("fault_kind", "fault_cycle", "fault_statusword", "fault_error", "safe_state")
            out.trace_complete = (len(back) in (f.cycle, f.cycle + 1) and finite
                                  and all(k in back.meta for k in needed))
            # ground truth: the first drive SYNC at or after the detection's with the torque off
            detect_sync = row0[0] + f.cycle if row0 else 0
            truth = next((s - detect_sync for s, off in history if s >= detect_sync and off), None)
            if truth is None and machine.master_bus is not None and machine.master_bus.mode == "off":
                idle = machine.let_drives_run(50, until_safe=True)["x"]
                last = history[-1][0] if history else detect_sync
                truth = None if idle is None else (last - detect_sync) + idle
                out.bound_cycles = SAFE_BOUND_CYCLES + _deadline_cycles(machine, cfg.cycle_s)
                out.note = "bus-off: the master cannot reach the drive; it stopped on its RPDO deadline (0x1400:05)"
            out.safe_within_cycles = truth
            out.safe_state = drive.drive.power.value
            return out
    finally:
        if tmp is not None:
            tmp.cleanup()


def _fired_row(machine, row0: list[int]) -> int | None:
    fired = machine.injectors["x"].fired
    return fired[0][1] - row0[0] if fired and row0 else None

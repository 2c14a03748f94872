"""The soak: a long two-axis lockstep run with random faults, recoveries and re-enables.

Axes x and y of the embedded machine (emulated drives on the virtual bus, CANopen masters) run
back-to-back jerk-limited moves to random targets. Before most moves a random fault is armed on a
random axis at a random time (every kind of the matrix that leaves the master alive: all but
``sdo-abort``, which only acts while configuring, and ``master-dead``). After each move:

* the trace of each axis is written (atomically) and read back: it must hold every row up to the
  stop, and the fault must be accounted for: a stopping fault in the metadata with its kind and
  axis, a tolerated one in the counters (``tpdo_lost_cycles`` / ``tpdo_late_frames``);
* the axes are recovered the way an operator would: the bus back on, a reset drive configured again
  (``connect()``), a drive in Fault reset (verified edge), a stopped heartbeat or an offset encoder
  repaired; then re-enabled by the next move.

Memory is measured with tracemalloc (after a full garbage collection: cyclic garbage waiting for
the collector is not a leak) after a warm-up, at ten points after it and at the end: the growth
must be flat, and the least-squares slope over the samples says per move what a leak would cost.
The wall time of every move is kept (a hang shows as a move that never ends: ``hang_guard_s``
aborts the soak with a traceback dump).
"""

from __future__ import annotations

import faulthandler
import gc
import random
import sys
import tempfile
import time
import tracemalloc
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

#: the faults the soak draws from, and the fault kind the master must report (None: tolerated)
SOAK_FAULTS: dict[str, str | None] = {
    "tpdo-lost": None,
    "tpdo-late": None,
    "tpdo-lost:cycles=8": "tpdo timeout",
    "sync-no-response:cycles=20": "tpdo timeout",
    "heartbeat-stop": "heartbeat lost",
    "emcy-fault": "drive fault",
    "limit-switch": "drive fault",
    "node-reset": "unexpected boot-up",
    "encoder-glitch": "implausible position",
    "bus-error": "bus error",
    "bus-off": "bus error",
}


@dataclass
class SoakResult:
    simulated_s: float = 0.0
    moves: int = 0
    injected: Counter = field(default_factory=Counter)
    accounted: Counter = field(default_factory=Counter)
    unaccounted: list[str] = field(default_factory=list)
    recoveries: int = 0
    memory_peak_kib: float = 0.0
    #: (moves, KiB) from the warm-up to the end
    memory_samples: list[tuple[int, float]] = field(default_factory=list)
    worst_move_wall_s: float = 0.0
    wall_s: float = 0.0

    @property
    def memory_warm_kib(self) -> float:
        return self.memory_samples[0][1] if self.memory_samples else 0.0

    @property
    def memory_end_kib(self) -> float:
        return self.memory_samples[-1][1] if self.memory_samples else 0.0

    @property
    def memory_growth_kib(self) -> float:
        return self.memory_end_kib - self.memory_warm_kib

    @property
    def memory_slope_kib_per_100_moves(self) -> float:
        """Least-squares slope of the memory samples: what 100 more moves would add."""
        if len(self.memory_samples) < 2:
            return 0.0
        n = len(self.memory_samples)
        mx = sum(m for m, _ in self.memory_samples) / n
        my = sum(k for _, k in self.memory_samples) / n
        sxx = sum((m - mx) ** 2 for m, _ in self.memory_samples)
        sxy = sum((m - mx) * (k - my) for m, k in self.memory_samples)
        return 100.0 * sxy / sxx if sxx else 0.0

    @property
    def all_accounted(self) -> bool:
        return not self.unaccounted and sum(self.injected.values()) == sum(self.accounted.values())


def run_soak(simulated_s: float = 600.0, *, seed: int = 1, fault_probability: float = 0.8,
             warmup_fraction: float = 0.1, hang_guard_s: float = 120.0, progress: bool = False,
             out_dir: str | Path | None = None) -> SoakResult:
    """Run the soak for ``simulated_s`` seconds of simulated time; see the module text."""
    from drivectl.controllers.registry import make_controller
    from drivectl.controllers.runtime.servo import Channel, run_channels
    from drivectl.driver.cia402 import PowerState
    from drivectl.machine.build import open_machine
    from drivectl.machine.config import load_config
    from drivectl.plant_emulator.faults import parse_fault
    from drivectl.profiles.ptp import PointToPoint
    from drivectl.tracefile.format import Trace

    rng = random.Random(seed)
    cfg = load_config(None)
    names = ["x", "y"]
    res = SoakResult()
    tmp = tempfile.TemporaryDirectory(prefix="drivectl-soak-") if out_dir is None else None
    out = Path(out_dir or tmp.name)
    t_start = time.perf_counter()
    tracemalloc.start(1)
    next_sample = warmup_fraction * simulated_s
    machine = open_machine(cfg, names, faults=[])
    try:
        ctrls = {n: make_controller(cfg.axis(n).controller, cfg.cycle_s, cfg.axis(n).controller_settings,
                                    plant=machine.specs[n], axis=n) for n in names}
        while res.simulated_s < simulated_s:
            armed = None
            duration = rng.uniform(0.3, 1.2)
            if rng.random() < fault_probability:
                case = rng.choice(list(SOAK_FAULTS))
                axis = rng.choice(names)
                at = rng.uniform(0.02, 0.6 * duration)
                if case == "heartbeat-stop":
                    duration = max(duration, at + 0.5)  # its detection takes 300-400 ms: inside this move
                spec = parse_fault(f"{axis}/{case}@{at:.3f}")
                machine.injectors[axis].arm(spec)
                armed = (case, axis, spec)
            # a move of each axis from where it stands to a random target inside +-20 mm
            channels = []
            for n in names:
                drive = machine.drives[n]
                here = drive.encoder.from_counts(drive.encoder.to_counts(drive.reported_position))
                prof = PointToPoint(here, rng.uniform(-0.02, 0.02), 0.1, 2.0, 100.0, hold_until=duration)
                channels.append(Channel(machine.axes[n], ctrls[n], prof, cfg.axis(n).limits))
            faulthandler.dump_traceback_later(hang_guard_s, exit=True)
            t0 = time.perf_counter()
            result = run_channels(channels, duration=max(ch.profile.duration for ch in channels))
            res.worst_move_wall_s = max(res.worst_move_wall_s, time.perf_counter() - t0)
            faulthandler.cancel_dump_traceback_later()
            res.moves += 1
            res.simulated_s += result.cycles * cfg.cycle_s
            traces = {}
            for n, tr in result.traces.items():
                traces[n] = Trace.read(tr.write(out / f"{n}.csv"))  # on disk and back, as a user gets it
                if len(traces[n]) != result.cycles:
                    res.unaccounted.append(f"move {res.moves}: trace {n} has {len(traces[n])} rows of "
                                           f"{result.cycles}")
            if armed is not None:
                _account(res, armed, result, traces, machine)
            res.recoveries += _recover(machine, names, PowerState)
            if res.simulated_s >= next_sample:
                res.memory_samples.append((res.moves, _traced_kib()))
                next_sample += (1.0 - warmup_fraction) * simulated_s / 10
            if progress:
                print(f"\rsoak: {res.simulated_s:7.1f} / {simulated_s:g} s simulated, {res.moves} moves, "
                      f"{sum(res.injected.values())} faults", end="", file=sys.stderr, flush=True)
        res.memory_samples.append((res.moves, _traced_kib()))
        res.memory_peak_kib = tracemalloc.get_traced_memory()[1] / 1024
    finally:
        faulthandler.cancel_dump_traceback_later()
        tracemalloc.stop()
        machine.close()
        if tmp is not None:
            tmp.cleanup()
        if progress:
            print(file=sys.stderr)
    res.wall_s = time.perf_counter() - t_start
    return res


def _traced_kib() -> float:
    gc.collect()  # garbage in reference cycles waits for the collector: not a leak
    return tracemalloc.get_traced_memory()[0] / 1024


def _account(res: SoakResult, armed, result, traces, machine) -> None:
    """Find the armed fault in what the master recorded."""
    case, axis, spec = armed
    injector = machine.injectors[axis]
    fired = any(s == spec for s, _ in injector.fired)
    if not fired:
        # the move ended before the fault's time (another stop came first, or it was armed late):
        # disarm it so that it cannot fire in the next move unaccounted
        injector.armed = [a for a in injector.armed if a.spec != spec]
        return
    res.injected[case] += 1
    expected = SOAK_FAULTS[case]
    tr = traces[axis]
    if expected is None:
        lost = int(tr.meta.get("tpdo_lost_cycles", "0")) + int(tr.meta.get("tpdo_late_frames", "0"))
        ok = lost >= 1 or result.fault is not None  # a tolerated loss inside a stop's cycles counts there
    else:
        f = result.fault
        # a bus fault is seen by whichever axis uses the bus next
        ok = (f is not None and f.kind == expected and (f.axis == axis or spec.where == "bus")
              and all(t.meta.get("fault_kind") == expected for t in traces.values()))
    if ok:
        res.accounted[case] += 1
    else:
        res.unaccounted.append(f"move {res.moves}: {spec} -> stop {result.stop.value}, fault "
                               f"{result.fault.kind if result.fault else None} on "
                               f"{result.fault.axis if result.fault else '-'}")
    injector.fired.clear()


def _recover(machine, names, PowerState) -> int:  # noqa: N803 - the enum passed in to keep imports lazy
    """Bring every axis back to Switch On Disabled, ready to be enabled: what an operator does."""
    from drivectl.driver.axis import AxisError

    done = 0
    if machine.master_bus is not None and machine.master_bus.mode:
        machine.master_bus.fail("")  # the cable is back
        machine.let_drives_run(10, until_safe=True)  # meanwhile the drives stopped on their own
        done += 1
    for n in names:
        axis, drive, inj = machine.axes[n], machine.drives[n], machine.injectors[n]
        broken = inj.heartbeat_stopped or inj.position_offset or drive.nmt.name != "OPERATIONAL"
        inj.repair()
        if not broken and drive.drive.power is PowerState.FAULT:
            # a drive fault: the reset edge on bit 7, verified by the statusword
            axis.fault_reset()
            for _ in range(10):
                try:
                    axis.read()
                    axis.write(0.0)
                except AxisError:
                    break
                if axis.power is PowerState.SWITCH_ON_DISABLED:
                    break
            broken = axis.power is not PowerState.SWITCH_ON_DISABLED
            axis.node.emcy.reset()  # canopen keeps every EMCY in a list: clear it with the fault
            done += 1
        if broken:
            axis.connect()  # NMT reset (power stage restarted) and the whole configuration again
            axis.node.emcy.reset()
            done += 1
    return done

"""The resident servo loop: one object owns the axes of a machine and closes their loops every cycle.

In cyclic synchronous torque the host *is* the position controller, so an enabled axis needs a loop
that runs as long as it is enabled. :class:`ServoLoop` cycles every axis of the machine (SYNC, TPDOs,
RPDOs: the bus and the drives' watchdogs stay fed while any is enabled, and while none is) and, for
each enabled axis, runs the same three calls as a trace run (controllers/runtime/servo.py): ``sample_axis``
-> ``control`` -> ``check_and_write``. The reference of an enabled axis comes from its
:class:`~drivectl.controllers.runtime.motion.Trajectory` (hold, move, jog, stop: ruckig) or from a profile
being run; an axis with nothing to do holds its position under its controller.

Two clocks, chosen when the loop is made:

* ``"wall"``: its own thread, one cycle per ``dt`` on the monotonic clock (pacing.Pacer). A late
  wake-up is a missed cycle: the loop resynchronises to the next slot; only a gap past an enabled
  axis's deadline is a fault (docs/timing.md); a watchdog thread quick-stops the axes when the loop
  thread does not come back at all, and the drives' own watchdogs (0x1400:05, 0x1016) when the process
  dies. In-process, the emulated drives run on this loop's clock (as across processes).
* ``"lockstep"``: no thread; time is the cycle count and advances only when the caller runs cycles
  (:meth:`ServoLoop.step`, :meth:`ServoLoop.run_until`, a handle's ``wait``). Deterministic: the same
  commands give the same trace bit for bit (tests, CI on the emulated drives).

A fault on any axis (a drive fault, lost TPDOs, a limit, a stall) quick-stops every axis of the loop
(``stop_channels``: verified from the drives' reports), fails the handles of the moves under way with
that fault, and completes every capture armed on the fault trigger (the ring's last samples, written
to ``fault_dir`` as a trace v1: the last seconds before any fault are on disk).

The garbage collector is kept out of the cycle in wall mode: the heap is frozen when the thread
starts (``gc.freeze``), automatic collection is off while it runs, and the loop collects the young
generation itself in the slack after a cycle's write. ``cpu`` pins the loop thread to a CPU and
``realtime`` asks for SCHED_FIFO where the OS allows it; the interpreter's switch interval is a tenth
of a cycle while the loop runs (a thread beside it, a program plotting, gives the GIL up within that,
not after Python's default 5 ms); ``status()`` says what was granted.
"""

from __future__ import annotations

import collections
import gc
import math
import threading
import time
from collections.abc import Callable, Mapping
from enum import Enum
from pathlib import Path
from typing import Any

from drivectl.controllers.base import Controller
from drivectl.controllers.runtime.capture import CHANNELS, Capture, Ring, Trigger
from drivectl.controllers.runtime.cycle import (
    BRAKE_WAIT_S,
    SAFE_STATES,
    Channel,
    CycleFault,
    Fault,
    Limits,
    StopReason,
    bridge,
    check_and_write,
    control,
    sample_axis,
)
from drivectl.controllers.runtime.handles import MotionFault, Move, MoveStatus, ProfileRun
from drivectl.controllers.runtime.host import HostMeasures, StealWatch
from drivectl.controllers.runtime.motion import MotionLimits, Trajectory
from drivectl.controllers.runtime.pacing import Pacer, pace_axes, slots_behind
from drivectl.controllers.runtime.safe_stop import drive_error_code, quietly, stop_channels
from drivectl.controllers.runtime.servo import STATE_CHANGE_CYCLES, trace_header
from drivectl.controllers.runtime.timing import LatencyRecord, RecentLatency
from drivectl.driver.axis import Axis, AxisError, FaultKind, Feedback
from drivectl.driver.cia402 import PowerState, error_text

CLOCKS = ("lockstep", "wall")


class AxisState(Enum):
    OFF = "off"  # not enabled (the drive may be in any state but Operation Enabled)
    ENABLING = "enabling"  # asked to enable; servoing from the cycle the drive reports Operation Enabled
    SERVO = "servo"  # enabled, its loop closed every cycle



class AxisRuntime:
    """One axis in the loop: its channel (axis, controller, limits), its reference and its state."""

    def __init__(self, channel: Channel, motion: MotionLimits, ring_size: int, ring: Ring | None = None):
        self.ch = channel
        self.name = channel.axis.name
        self.motion = motion
        self.traj = Trajectory(channel.axis.dt, motion)
        self.state = AxisState.OFF
        self.offset = 0.0  # drive position - axis position (set by homing)
        self.position = math.nan  # m, axis coordinates (offset applied)
        self.velocity = math.nan
        self.reference = math.nan
        self.following_error = 0.0
        self.effort = 0.0
        self.servo_k = 0  # cycles since it was enabled (what the limit checks count)
        self.handle: Move | None = None
        self.run: ProfileRun | None = None
        self.jog_until = 0  # loop slot (Loop.slot) at which an unrenewed jog stops (0: no jog)
        self.move_started = False
        self.ring = ring if ring is not None else Ring(ring_size)
        self.captures: list[Capture] = []
        self.fault: Fault | None = None
        self.read_error: str = ""
        self.enable_failed = ""


class ServoLoop:
    """The resident loop over ``channels`` (one per axis; their ``profile`` is not used)."""

    def __init__(
        self,
        channels: list[Channel],
        motion: dict[str, MotionLimits] | None = None,
        *,
        clock: str = "lockstep",
        stall_s: float | None = 0.05,
        deadlines: Mapping[str, float] | None = None,
        ring_s: float = 5.0,
        fault_dir: str | Path | None = None,
        gc_control: bool = True,
        gil_switch: bool = True,
        cpu: int | None = None,
        realtime: bool = False,
        io_lock: threading.RLock | None = None,
        now: Callable[[], float] = time.perf_counter,
        sleep: Callable[[float], None] | None = None,
        meta: dict[str, dict[str, str]] | None = None,
        ring: Callable[[str, int], Ring] | None = None,
        on_cycle: Callable[[], None] | None = None,
        collect_while_enabled: bool = True,
        drive_account: Callable[[str, int], str | None] | None = None,
    ):
        if clock not in CLOCKS:
            raise ValueError(f"loop: clock: expected one of {', '.join(CLOCKS)}, got {clock!r}")
        if not channels:
            raise ValueError("loop: no axes")
        if stall_s is not None and not (math.isfinite(stall_s) and stall_s > 0):
            raise ValueError(f"loop: stall_s: must be > 0, got {stall_s!r}")
        self.dt = channels[0].axis.dt
        self.clock = clock
        #: each axis's deadline (s; controllers/runtime/timing.py): the longest its drive holds a setpoint
        self.deadlines = {ch.axis.name: (deadlines or {}).get(ch.axis.name, 2 * self.dt) for ch in channels}
        #: a gap between two cycles longer than this is a stall (a fault); None: each enabled axis's deadline
        self.stall_s = stall_s
        self._first_bound = stall_s if stall_s is not None else min(self.bound_of(n) for n in self.deadlines)
        #: the watchdog thread's bound: a loop thread silent for twice this is quick-stopped from outside
        self._watch_s = max(self._first_bound if math.isfinite(self._first_bound) else 0.05, 0.05)
        self.latency = LatencyRecord()  # every wall-clock cycle's lateness since the start (status)
        self.recent = RecentLatency()  # the last 30-60 s of it (enable's check)
        self.fault_dir = Path(fault_dir) if fault_dir is not None else None
        self.gc_control = gc_control
        #: shorten the interpreter's switch interval while the wall-clock loop runs (controllers/runtime/host.py)
        self.gil_switch = gil_switch
        self.cpu = cpu
        self.realtime = realtime
        self.meta = meta or {}
        motion = motion or {}
        #: ``ring(name, size)``: each axis's ring (the loop's own process puts them in shared memory)
        self.ring_size = ring_size = max(2, int(round(ring_s / self.dt)))
        self.axes: dict[str, AxisRuntime] = {
            ch.axis.name: AxisRuntime(ch, motion.get(ch.axis.name, MotionLimits()), ring_size,
                                      ring(ch.axis.name, ring_size) if ring is not None else None)
            for ch in channels}
        #: called at the end of every cycle, a stop's too (the loop's own process publishes its status there)
        self.on_cycle = on_cycle
        #: False: no collection at all while an axis is enabled or enabling (the loop's own process: nothing else
        #: allocates)
        self.collect_while_enabled = collect_while_enabled
        #: ``drive_account(axis, 0x603F)``: what the axis's drive says of its own reaction (an emulated drive's
        #: account of its RPDO deadline, machine/build.py), added to the fault's detail; a real drive says nothing
        self.drive_account = drive_account
        self._rts = list(self.axes.values())
        self._channels = [rt.ch for rt in self._rts]
        #: every bus access of the user's side (SDO) takes it; the loop holds it during a cycle
        self.io_lock = io_lock or threading.RLock()
        self._inbox: collections.deque[Callable[[], None]] = collections.deque()
        self._now = now
        self._elapsed = 1  # cycles since the previous cycle (more after a late wake-up)
        self._sleep = sleep  # the pacer's (tests inject a clock whose sleeps pass simulated time)
        self.cycle = 0  # loop cycles run
        self.missed = 0
        self.worst_late = 0.0
        self.stalls = 0
        self.slots = 0  # wall clock: cycle slots since the start (run or skipped)
        self.slot = 0  # the slot the next cycle runs in, either clock (a late wake-up skips some): the dead man's count
        self.skipped = 0  # slots skipped because the loop was that far behind
        self._stamp = -1  # the slot of the last samples pushed into the rings (a stop's cycles follow it)
        self.late_syncs = 0  # cycles whose SYNC went out a slot or more after the cycle took its slot (_slip)
        self._pacer: Pacer | None = None
        self._k = 0  # wall clock: the pacer's slot of the cycle under way (a late SYNC moves it on: _slip)
        self._woke_missed = False  # the pacer counted the cycle under way as missed (it woke over half a period late)
        self._sync_armed = False  # the cycle's first SYNC is still to go out (_slip)
        self.gc_runs = 0
        self.gc_worst = 0.0
        self.granted: dict[str, str] = {}
        self.faults: list[Fault] = []
        self.command_errors: list[str] = []  # commands that raised in the loop (kept for status)
        self.fault_files: list[Path] = []
        self._thread: threading.Thread | None = None
        self._watchdog: threading.Thread | None = None
        self._closing = False
        self._closed = threading.Event()
        self._last_cycle_t: float | None = None
        self._stalled = False
        self._steal = StealWatch()  # a stall's message says what the hypervisor took meanwhile
        self._cpu_mark: tuple[int, float, float] | None = None  # the loop thread's CPU clock, its start, the time
        self._writer: threading.Thread | None = None
        self._pending_writes: collections.deque[tuple[Path, Capture]] = collections.deque()
        self._host = HostMeasures()  # what this loop holds of the process while it runs (wall clock)
        self.error: BaseException | None = None  # what killed the loop thread, if anything
        #: how a handle waits: run_until, or the owner's wrapper of it (the session routes Ctrl-C there)
        self.wait_until: Callable[[Callable[[], bool], float | None], bool] = self.run_until

    # -- lifetime ---------------------------------------------------------------------------------------
    def start(self) -> None:
        """Wall clock: start the loop thread (and its watchdog). Lockstep: take the first sample."""
        if self.clock == "lockstep":
            self._cycle_all()
            return
        # the watchdog first: the loop thread raises the threads it finds (controllers/runtime/host.py)
        self._watchdog = threading.Thread(target=self._watchdog_main, name="drivectl-loop-watchdog", daemon=True)
        self._watchdog.start()
        self._thread = threading.Thread(target=self._thread_main, name="drivectl-servo-loop", daemon=True)
        self._thread.start()
        if not self.run_until(lambda: self.cycle > 0, 2.0):
            raise AxisError(f"loop: no cycle within 2 s of starting ({self.error or 'the loop thread hangs'})")

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def close(self, timeout: float = 2.0) -> dict[str, str]:
        """Disable every axis (verified from the drives' reports), stop the loop. Returns, per axis, the
        power state the drive reported last ("unknown" where it never answered)."""
        states: dict[str, str] = {}
        try:
            if self._thread is None or self.running:
                for rt in self._rts:
                    self.submit(lambda rt=rt: self.disable_axis(rt, "the machine closed"))
                self.run_until(lambda: all(rt.ch.axis.power not in _ENABLED for rt in self._rts),
                               timeout if self.clock == "wall" else max(STATE_CHANGE_CYCLES * self.dt, BRAKE_WAIT_S))
        finally:
            self._closing = True
            self._closed.set()
            if self._thread is not None:
                self._thread.join(timeout)
            if self._watchdog is not None:
                self._watchdog.join(timeout)
            for rt in self._rts:
                for cap in rt.captures:
                    cap.cancel("the machine closed before it completed")
                rt.captures.clear()
            self.flush()
            self._host.release()
            for rt in self._rts:
                rt.traj.release()  # no cycle runs any more: the ruckig objects go now, not at some collection
        for rt in self._rts:
            axis = rt.ch.axis
            if axis.power in _ENABLED:
                quietly(axis.refresh_state)  # the TPDOs did not confirm it: ask the drive (by SDO on a bus)
            states[rt.name] = axis.power.value
        return states

    def flush(self, timeout: float | None = 30.0) -> list[Path]:
        """Wait for the fault captures being written; returns every file written so far."""
        if self._writer is not None:
            self._writer.join(timeout)
        return list(self.fault_files)

    # -- commands (any thread) -------------------------------------------------------------------------
    def submit(self, fn: Callable[[], None]) -> None:
        """Run ``fn`` in the loop at the next cycle boundary (at once in lockstep or on the loop thread)."""
        if self._thread is None and not self.io_lock.acquire(blocking=False):
            # lockstep, another thread is in a cycle: the next cycle starts with fn (it takes the inbox
            # first), or this thread runs it once it has the lock; never cycles later (a lock is not fair)
            self._inbox.append(fn)
            with self.io_lock:
                self._take_inbox()
        elif self._thread is None:
            try:
                fn()
            finally:
                self.io_lock.release()
        elif threading.current_thread() is self._thread or not self.running:
            with self.io_lock:
                fn()
        else:
            self._inbox.append(fn)

    def _take_inbox(self) -> None:
        """Run the submitted commands, in order (with io_lock held)."""
        inbox = self._inbox
        while inbox:
            fn = inbox.popleft()
            try:
                fn()
            except Exception as exc:  # noqa: BLE001 - a command that fails must not end the loop
                self.command_errors.append(f"{type(exc).__name__}: {exc}")

    def step(self, cycles: int = 1) -> None:
        """Lockstep: run ``cycles`` cycles on the caller's thread."""
        if self.clock != "lockstep":
            raise RuntimeError("loop: step() is for the lockstep clock; the wall clock runs by itself")
        for _ in range(cycles):
            self._cycle_all()

    def run_until(self, done: Callable[[], bool], timeout: float | None) -> bool:
        """Until ``done()``: lockstep runs cycles (``timeout`` simulated s, None: 1 h), wall waits (s)."""
        if self.clock == "lockstep":
            limit = self.cycle + (int(math.ceil(timeout / self.dt)) if timeout is not None else int(3600 / self.dt))
            while not done():
                if self.cycle >= limit:
                    return False
                self._cycle_all()
            return True
        end = None if timeout is None else time.monotonic() + timeout
        while not done():
            if self._thread is not None and not self._thread.is_alive():
                return done()
            if end is not None and time.monotonic() >= end:
                return False
            time.sleep(min(0.002, self.dt * 2))
        return True

    # -- the cycle ---------------------------------------------------------------------------------------
    def _cycle_all(self) -> None:
        """One cycle of every axis (the loop's own thread in wall mode, the caller's in lockstep)."""
        with self.io_lock:
            self._take_inbox()
            k = self.cycle
            self.slot += self._elapsed - 1  # the slots skipped before this cycle count for a jog's dead man
            if self._elapsed > 1:  # woke late: the axes' next samples belong to the slot this cycle runs in
                for rt in self._rts:
                    rt.ch.axis.skip(self._elapsed - 1)
            self._stamp = self.slot  # the rings record the slot: a capture's time (capture.Ring)
            self._sync_armed = self._pacer is not None
            try:
                for rt in self._rts:
                    if rt.state is AxisState.SERVO:
                        self._servo(rt)
                    else:
                        self._idle(rt)
            except CycleFault as exc:
                self._fault(exc.fault, exc.stop)
            except AxisError as exc:  # a write that failed (bus error): a fault like any other
                self._fault(Fault(exc.kind or FaultKind.AXIS_ERROR, self._axis_named(exc), k, str(exc)),
                            StopReason.FAULT)
            except Exception as exc:  # noqa: BLE001 - a bug in a controller or a hook: stop, never run on blind
                self._fault(Fault(FaultKind.LOOP_ERROR, self._rts[0].name, k,
                                  f"the servo loop raised {type(exc).__name__}: {exc}"), StopReason.FAULT)
            self.cycle += 1  # (a stop's own cycles were counted as they ran)
            self.slot += 1
            if self.on_cycle is not None:
                self.on_cycle()

    def _axis_named(self, exc: Exception) -> str:
        text = str(exc)
        return next((rt.name for rt in self._rts if text.startswith(f"axis {rt.name}:")), self._rts[0].name)

    def _servo(self, rt: AxisRuntime) -> None:
        """One cycle of an enabled axis: sample -> reference -> control -> record -> limits -> write."""
        ch = rt.ch
        rt.servo_k += 1
        fb = sample_axis(ch, rt.servo_k)
        s = self._stamp  # after the sample: a SYNC later than its slot moved the cycle on (_slip)
        run = rt.run
        if self._elapsed > 1:  # the loop resynchronised: the drive held the last setpoint that long
            ch.last_position = None  # no plausibility check across the gap: it restarts from this sample
            ch.controller.skipped(self._elapsed - 1)
            if run is None:  # a move's reference and a run's are functions of time: they skip as many slots
                rt.traj.skip(self._elapsed - 1)
            else:
                run.skip(self._elapsed - 1)
        if rt.offset:
            fb = Feedback(fb.time, fb.position - rt.offset, fb.velocity)
        if rt.jog_until and self.slot >= rt.jog_until:  # in slots: a late wake-up's skipped ones count
            rt.jog_until = 0
            rt.traj.stop()  # dead man: the jog was not renewed
        if run is not None:
            ref = run.next()
        else:
            ref = rt.traj.next()
        fb = bridge(ch, ref, fb, rt.servo_k)
        u = control(ch, ref, fb)
        pos = fb.position
        rt.position, rt.velocity, rt.reference, rt.effort = pos, fb.velocity, ref.position, u
        rt.following_error = ref.position - pos
        ax = ch.axis
        rt.ring.push(s, ref.position, pos, u, fb.velocity, ax.torque_actual, ax.statusword)
        if run is not None and run.k < run.n:
            i = run.k
            r = run.rows
            r[0][i] = pos
            r[1][i] = fb.velocity
            r[2][i] = u
            if run.append is not None:
                run.append(i * self.dt, ref.position, pos, u, fb.velocity)
            run.k = i + 1
        if rt.captures:
            self._captures(rt, s)
        rt.move_started = False
        check_and_write(ch, rt.servo_k, self.dt, pos, ref.position, u)
        if rt.handle is not None:
            self._progress(rt)

    def _idle(self, rt: AxisRuntime) -> None:
        """One cycle of an axis that is not servoing: sample, zero effort; take it up once enabled."""
        ax = rt.ch.axis
        try:
            fb = ax.read()
            rt.read_error = ""
        except AxisError as exc:
            rt.read_error = str(exc)
            try:
                ax.write(0.0)
            except AxisError:
                pass
            if rt.state is AxisState.ENABLING:
                rt.state = AxisState.OFF
                rt.enable_failed = str(exc)
            return
        ax.write(0.0)
        s = self._stamp  # after the sample: a SYNC later than its slot moved the cycle on (_slip)
        pos = fb.position - rt.offset
        rt.position, rt.velocity, rt.reference, rt.effort, rt.following_error = pos, fb.velocity, pos, 0.0, 0.0
        rt.ring.push(s, pos, pos, 0.0, fb.velocity, ax.torque_actual, ax.statusword)
        if rt.captures:
            self._captures(rt, s)
        if rt.state is AxisState.ENABLING:
            power = ax.power
            if power is PowerState.OPERATION_ENABLED:
                self._take_up(rt, pos)
            elif power in (PowerState.FAULT, PowerState.FAULT_REACTION_ACTIVE):
                rt.state = AxisState.OFF
                rt.enable_failed = f"drive in {power.value}"

    def _take_up(self, rt: AxisRuntime, pos: float) -> None:
        """The drive reports Operation Enabled: hold where it stands, under its controller."""
        ch = rt.ch
        ch.controller.reset()
        ch.following_since = None
        ch.last_position = None
        ch.clipped = 0
        rt.traj.hold(pos)
        rt.servo_k = 0
        rt.state = AxisState.SERVO
        rt.fault = None

    def _progress(self, rt: AxisRuntime) -> None:
        """Has the current command ended? (a move: reference arrived and in position, or timed out)."""
        h = rt.handle
        if h.status == MoveStatus.PENDING:
            h.status = MoveStatus.MOVING
        h.cycles += 1
        if rt.run is not None:
            run = rt.run
            if run.k < run.n:
                return
            rt.traj.hold(run.refs[0][run.n - 1])
            rt.run = None
            h._run = run
            h.status = MoveStatus.SETTLING
        if h.kind == "jog":
            if rt.traj.arrived:  # stopped by the dead man or stop()
                rt.handle = None
                h.finish(MoveStatus.STOPPED if h.status != MoveStatus.DONE else MoveStatus.DONE, rt,
                         "jog ended (not renewed or stopped)")
            return
        if not rt.traj.arrived:
            return
        h.status = MoveStatus.SETTLING
        m = rt.motion
        if abs(rt.traj.target - rt.position) <= m.in_position:
            h._in_position += 1
        else:
            h._in_position = 0
        h._settle_cycles += 1
        if h._in_position * self.dt >= m.in_position_time:
            h.settled = True
        elif h._settle_cycles * self.dt < m.settle_timeout:
            return
        rt.handle = None
        then, h._then = h._then, None
        h.finish(MoveStatus.DONE, rt, "" if h.settled else
               f"not within {m.in_position * 1e6:g} um of the target {m.settle_timeout:g} s after the reference "
               f"arrived (error {(rt.traj.target - rt.position) * 1e6:+.2f} um)")
        if then is not None:
            then()

    def _captures(self, rt: AxisRuntime, s: int) -> None:
        started = rt.move_started
        done = [cap for cap in rt.captures if cap.on_cycle(rt.ring, s, started)]
        for cap in done:
            rt.captures.remove(cap)
            if cap.trigger.kind == "fault":
                self._queue_fault_capture(cap)

    # -- faults and stops -----------------------------------------------------------------------------------
    def _fault(self, fault: Fault, stop: StopReason) -> None:
        """Quick stop every axis (verified), fail the moves under way, complete the fault captures."""
        why = f"fault: {fault.kind} on axis {fault.axis}: {fault.detail}"
        if self.clock == "wall":
            fault.at = time.monotonic()
        for rt in self._rts:  # the window ends at the detection: taken before the stop's own cycles
            if not rt.ring.count:
                continue
            last = int(rt.ring.slot[rt.ring.next - 1])  # the last sample before the detection
            armed = [c for c in rt.captures if c.trigger.kind == "fault"]
            if not armed and self.fault_dir is not None:  # nobody asked: the whole ring goes to disk all the same
                head = trace_header(rt.ch.axis, self.dt, None, self.meta.get(rt.name), paced=self.clock == "wall")
                armed = [Capture(rt.name, CHANNELS, Trigger("fault"), min(rt.ring.count, rt.ring.size) - 1, 0,
                                 self.dt, head)]
                rt.captures.extend(armed)
            for cap in armed:
                if cap.post:  # the stop and what follows it come as the post-trigger samples
                    cap.fire(last, why)
                    continue
                cap.complete(rt.ring, last, why)
                rt.captures.remove(cap)
                self._queue_fault_capture(cap)
        try:
            stop_channels(self._channels, fault, on_cycle=self._stop_cycle)
        except Exception as exc:  # noqa: BLE001 - the stop must not kill the loop; say so in the fault
            fault.detail += f"; the stop itself failed: {exc}"
        if self.drive_account is not None and fault.error_code is not None:
            said = self.drive_account(fault.axis, fault.error_code)
            if said:
                fault.detail += f"; its drive: {said}"
        self.faults.append(fault)
        for rt in self._rts:
            was_on = rt.state is not AxisState.OFF
            rt.state = AxisState.OFF
            rt.run = None
            rt.jog_until = 0
            if rt.name == fault.axis or was_on:
                rt.fault = fault
            if rt.handle is not None:
                h, rt.handle = rt.handle, None
                h.finish(MoveStatus.FAULT, rt, fault.detail, fault)

    def _stop_cycle(self, samples: Mapping[str, Feedback | None]) -> None:
        """One cycle of a stop (controllers/runtime/safe_stop.py): every axis's sample into its ring, so a
        fault capture's post-trigger samples show the stop itself."""
        self.cycle += 1
        self.slot += 1
        # the slot after the last samples pushed: in a cycle (a fault found there) the one the cycle's count
        # goes on from; outside one (a stall caught before the cycle) the next cycle's, which then starts
        # after the stop's (the cycle count was recorded before: the cycle after such a stop recorded the
        # stop's last number again, a capture's time did not increase and the reader refused the file)
        s = self._stamp = self._stamp + 1
        for rt in self._rts:
            fb = samples.get(rt.name)
            if fb is None:
                continue
            ax = rt.ch.axis
            pos = fb.position - rt.offset
            rt.ring.push(s, rt.reference, pos, 0.0, fb.velocity, ax.torque_actual, ax.statusword)
            if rt.captures:
                self._captures(rt, s)
        if self.on_cycle is not None:
            self.on_cycle()

    def _queue_fault_capture(self, cap: Capture) -> None:
        if self.fault_dir is None:
            return
        stamp = time.strftime("%Y%m%d-%H%M%S")
        path = self.fault_dir / f"{cap.axis}-fault-{stamp}-s{cap.trigger_slot}.csv"
        self._pending_writes.append((path, cap))
        if self._writer is None or not self._writer.is_alive():
            # files are written off the loop's thread: the cycle goes on while they are
            self._writer = threading.Thread(target=self._write_pending, name="drivectl-capture-writer", daemon=True)
            self._writer.start()

    def _write_pending(self) -> None:
        while self._pending_writes:
            path, cap = self._pending_writes.popleft()
            try:
                self.fault_files.extend(cap.write(path, plot=False))
            except OSError as exc:
                cap.detail += f"; not written: {exc}"

    def disable_axis(self, rt: AxisRuntime, why: str) -> None:
        """Torque off (the drive ramps per its options); a move under way ends as stopped."""
        rt.ch.axis.disable()
        rt.state = AxisState.OFF
        rt.run = None
        rt.jog_until = 0
        if rt.handle is not None:
            h, rt.handle = rt.handle, None
            h.finish(MoveStatus.STOPPED, rt, why)

    # -- wall clock -------------------------------------------------------------------------------------
    def _thread_main(self) -> None:
        paced = False
        try:
            self._setup_thread()
            now = self._now
            pacer = Pacer(self.dt, now=now, sleep=self._sleep)
            clk = time.pthread_getcpuclockid(threading.get_ident())
            self._cpu_mark = (clk, time.clock_gettime(clk), time.perf_counter())
            # in-process, the emulated drives run on this clock too, as across processes: a loop later than
            # the drive's RPDO deadline is caught by the drive (controllers/runtime/pacing.pace_axes)
            self._pacer = pacer
            pace_axes(self._channels, pacer.now, self._slip)
            paced = True
            k = 0
            latency, recent = self.latency, self.recent
            while not self._closing:
                late = pacer.wait(k)
                self._woke_missed = late > 0.5 * self.dt
                latency.add(late)
                recent.add(late)
                t = now()
                last = self._last_cycle_t
                if last is not None and t - last > self._first_bound:
                    self._on_stall(t - last)
                behind = slots_behind(t - pacer.t0, self.dt, k)
                if behind > 0:  # a slot or more lost: resynchronise to the next one, no burst of stale cycles
                    # this cycle takes the slot nearest to the time it samples at: the drives held the last
                    # setpoint since the previous SYNC, and the references and the controllers skip as many
                    pacer.missed += behind - 1  # slots k+1 .. now-1 (the pacer counted slot k itself)
                    self.skipped += behind  # slots k .. now-1 get no cycle of their own: this one is slot now
                    k += behind
                    self._woke_missed = False  # counted
                self._elapsed = behind + 1
                self._k = k
                self._cycle_all()
                self._last_cycle_t = now()
                k = self._k + 1
                self.slots = k
                self.missed, self.worst_late = pacer.missed, pacer.worst_late
                if self.gc_control and k % 100 == 0:
                    self._collect(pacer, k)
        except BaseException as exc:  # noqa: BLE001 - recorded; the watchdog and the drives stop the axes
            self.error = exc
            raise
        finally:
            if paced:
                pace_axes(self._channels, None)
            self._pacer = None

    def _slip(self, now: float | None = None) -> int:
        """Just before the cycle's first SYNC goes out (SyncClock.tick; in-process at its delivery, ``now`` the wall
        time the drives sample at): the slots the pacer's clock moved on since the cycle took its slot. The host may
        stop the loop between the two; the drive samples at the SYNC, so the cycle is moved to the slot it samples
        in, as a late wake-up is, and the SYNC counts the slots between (docs/timing.md, "A SYNC later than its
        slot"). A stop's later SYNCs in the same cycle are not asked."""
        pacer = self._pacer
        if not self._sync_armed or pacer is None:
            return 0
        self._sync_armed = False
        extra = slots_behind((self._now() if now is None else now) - pacer.t0, self.dt, self._k)
        if extra <= 0:
            return 0
        pacer.missed += extra - 1 if self._woke_missed else extra  # slots k .. k+extra-1 got no cycle of their own
        self._woke_missed = False
        self.skipped += extra
        self.late_syncs += 1
        self._k += extra
        self._elapsed += extra
        self.slot += extra
        self._stamp = self.slot
        return extra

    def _setup_thread(self) -> None:
        self.granted.update(self._host.take(self.dt, gil_switch=self.gil_switch, gc_control=self.gc_control,
                                            cpu=self.cpu, realtime=self.realtime))

    def _collect(self, pacer: Pacer, k: int) -> None:
        """A young-generation collection, only when at least half a cycle is left before the next."""
        slack = pacer.t0 + k * self.dt - self._now()
        if slack < 0.5 * self.dt:
            return
        # ENABLING counts as enabled: its drive may already be in Operation Enabled, its RPDO deadline running
        powered = any(rt.state is not AxisState.OFF for rt in self._rts)
        if not self.collect_while_enabled and powered:
            return
        t0 = self._now()
        # young every 0.1 s, middle every 10 s; once a minute what survived those: scanned when no axis is
        # enabled (what a program beside the loop leaves in cycles must not grow without bound), frozen while
        # one is: a full collection's time grows with the heap (20-30 ms in a soak after a few minutes, past
        # every deadline), a freeze takes none. Frozen objects are collected again at close (host.py).
        if k % 60_000 == 0:
            if powered:
                gc.collect(1)
                gc.freeze()
            else:
                gc.collect(2)
        else:
            gc.collect(1 if k % 10_000 == 0 else 0)
        took = self._now() - t0
        self.gc_runs += 1
        if took > self.gc_worst:
            self.gc_worst = took

    def cpu_share(self) -> float | None:
        """The share of one CPU the loop's thread has used since it started (its CPU clock over the monotonic
        one; its spin included); None before, after, or in lockstep."""
        mark = self._cpu_mark
        if mark is None or not self.running:
            return None
        clk, c0, t0 = mark
        try:
            used = time.clock_gettime(clk) - c0
        except OSError:  # the thread ended meanwhile
            return None
        return used / max(time.perf_counter() - t0, 1e-9)

    def bound_of(self, rt: AxisRuntime | str) -> float:
        """The longest gap between two cycles that an axis rides out (s; inf: not watched)."""
        if self.stall_s is not None:
            return self.stall_s
        d = self.deadlines[rt if isinstance(rt, str) else rt.name]
        return d if d > 0 else math.inf

    @staticmethod
    def _watched(rt: AxisRuntime) -> bool:
        """Is the drive (possibly) in Operation Enabled? In servo, and while enabling from Ready To Switch On
        on: the enable's controlwords are written in a cycle, the drive enters Operation Enabled at the next
        SYNC, and the loop reads it a cycle later; a stall in between leaves a powered drive unwatched."""
        return rt.state is AxisState.SERVO or (
            rt.state is AxisState.ENABLING
            and rt.ch.axis.power in (PowerState.READY_TO_SWITCH_ON, PowerState.SWITCHED_ON,
                                     PowerState.OPERATION_ENABLED))

    def _on_stall(self, gap: float) -> None:
        """A gap past an enabled axis's deadline is a fault (drivectl's own clock; the drive's catches the
        same from its side); a shorter one is a missed cycle, counted, not a fault."""
        self._stalled = False
        over = [rt for rt in self._rts if self._watched(rt) and gap > self.bound_of(rt)]
        if not over:
            return
        self.stalls += 1
        servo = min(over, key=self.bound_of)
        fault = Fault(FaultKind.LOOP_STALLED, servo.name, servo.servo_k,
                      f"axis {servo.name}: the servo loop stalled: no cycle for {gap * 1e3:.1f} ms "
                      f"(bound {self.bound_of(servo) * 1e3:g} ms){self._steal.note()}")
        with self.io_lock:
            self._fault(fault, StopReason.FAULT)

    def _watchdog_main(self) -> None:
        """When the loop thread does not come back within the stall bound, quick-stop the enabled axes
        from here (best effort: the loop thread may hold the bus); the loop verifies when it resumes."""
        marks = 0
        while not self._closed.wait(self._watch_s / 2):
            marks += 1
            if marks * self._watch_s / 2 >= 1.0:  # the steal time's mark, about once a second
                marks = 0
                self._steal.mark()
            last = self._last_cycle_t
            if last is None or self._closing or self._stalled:
                continue
            if self._now() - last > 2 * self._watch_s:
                self._stalled = True
                for rt in self._rts:
                    if self._watched(rt):
                        quietly(rt.ch.axis.quick_stop)
                        quietly(rt.ch.axis.write, 0.0)

    # -- what the user's side reads ----------------------------------------------------------------------
    def status(self) -> dict[str, Any]:
        n = max(self.slots if self.clock == "wall" else self.cycle, 1)
        out: dict[str, Any] = {
            "clock": "wall clock, paced" if self.clock == "wall" else "lockstep (simulated time)",
            "cycle_s": self.dt,
            "cycles": self.cycle,
            "missed_deadlines": self.missed,  # cycles that started over half a period late, skipped ones included
            "missed_fraction": self.missed / n,  # of the cycle slots since the start
            "skipped_cycles": self.skipped,
            "late_syncs": self.late_syncs,  # of those, cycles whose SYNC went out a slot or more after their slot
            "worst_late_ms": self.worst_late * 1e3,
            "stalls": self.stalls,
            "stall_bound_ms": self._first_bound * 1e3,
            "latency_ms": self.latency.percentiles_ms(),  # the wall clock's lateness of every cycle
            "deadline_ms": {name: d * 1e3 for name, d in self.deadlines.items()},
            "gc_collections": self.gc_runs,
            "gc_worst_ms": self.gc_worst * 1e3,
            "cpu_share": self.cpu_share(),
            "granted": dict(self.granted),
            "faults": len(self.faults),
            "command_errors": len(self.command_errors),
            "axes": {},
        }
        for rt in self._rts:
            ax = rt.ch.axis
            a = {"state": rt.state.value, "power": ax.power.value, "position_m": rt.position,
                 "velocity_m_s": rt.velocity, "reference_m": rt.reference, "following_error_m": rt.following_error,
                 "effort": rt.effort, "effort_unit": ax.effort_unit, "clipped_cycles": rt.ch.clipped,
                 "home_offset_m": rt.offset, "move": rt.handle.kind if rt.handle else None}
            if rt.fault is not None:
                a["fault"] = f"{rt.fault.kind}: {rt.fault.detail}"
            if rt.read_error:
                a["read_error"] = rt.read_error
            out["axes"][rt.name] = a
        return out


_ENABLED = (PowerState.OPERATION_ENABLED, PowerState.QUICK_STOP_ACTIVE)


def drive_error(axis: Axis) -> tuple[int, str] | None:
    """The drive's 0x603F (code, text), read by SDO where the axis can, else its last EMCY."""
    code = drive_error_code(axis)
    if code is None:
        return None
    return int(code), error_text(int(code))


__all__ = ["AxisRuntime", "AxisState", "CHANNELS", "Capture", "CLOCKS", "Limits", "Move", "MotionFault",
           "ProfileRun", "ServoLoop", "Trigger", "SAFE_STATES", "Controller", "drive_error"]

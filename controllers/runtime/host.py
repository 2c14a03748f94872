"""The process-wide measures a wall-clock loop takes for its thread: the garbage collector, the GIL, the
BLAS thread pool and the priority of the process's other threads.

Both are the process's, not a loop's: the first wall-clock loop takes them, the last one gives them back.
"""

from __future__ import annotations

import errno
import gc
import os
import sys
import threading
from collections.abc import Callable

# the collector is the process's: the first wall-clock loop takes it, the last one gives it back
_gc_lock = threading.Lock()
_gc_holders = 0
_gc_was_enabled = True


def take_gc() -> None:
    global _gc_holders, _gc_was_enabled
    with _gc_lock:
        if _gc_holders == 0:
            _gc_was_enabled = gc.isenabled()
            gc.collect()
            gc.freeze()  # what exists now is never scanned again: young collections stay short
            gc.disable()
        _gc_holders += 1


def release_gc() -> None:
    global _gc_holders
    with _gc_lock:
        _gc_holders -= 1
        if _gc_holders == 0:
            gc.unfreeze()  # back to normal collection: what was frozen may be collected again
            if _gc_was_enabled:
                gc.enable()


# the interpreter's switch interval is the process's too. Python hands the GIL to a waiting thread only
# after the holder has run for this long (5 ms by default): a program plotting beside the loop would
# hold the loop's thread off for up to five cycles. The first wall-clock loop shortens it, the last
# one restores it.
_switch_holders = 0
_switch_was = 0.005


def take_switch(interval: float) -> float:
    global _switch_holders, _switch_was
    with _gc_lock:
        if _switch_holders == 0:
            _switch_was = sys.getswitchinterval()
            sys.setswitchinterval(min(_switch_was, interval))
        _switch_holders += 1
        return _switch_was


def release_switch() -> None:
    global _switch_holders
    with _gc_lock:
        _switch_holders -= 1
        if _switch_holders == 0:
            sys.setswitchinterval(_switch_was)


# BLAS (OpenBLAS under numpy) is the process's as well. The cycle's products are a few elements; a BLAS
# worker left spinning after each burned about 10 us of CPU per cycle on the other core, the one a
# program beside the loop (or the emulated drives across processes) runs on. The first wall-clock loop
# limits BLAS to the calling thread (threadpoolctl), the last one restores what was set.
_blas_holders = 0
_blas_limit = None


def take_blas() -> None:
    global _blas_holders, _blas_limit
    with _gc_lock:
        if _blas_holders == 0:
            from threadpoolctl import threadpool_limits

            _blas_limit = threadpool_limits(limits=1, user_api="blas")
        _blas_holders += 1


def release_blas() -> None:
    global _blas_holders, _blas_limit
    with _gc_lock:
        _blas_holders -= 1
        if _blas_holders == 0 and _blas_limit is not None:
            _blas_limit.restore_original_limits()
            _blas_limit = None


# The loop's thread runs at SCHED_FIFO, but it shares the GIL, and the bus lock, with the process's other
# threads (the program's, a console's, the loop's watchdog). When one of them asks for the GIL, the loop
# hands it over within the switch interval and then waits until that thread has actually taken it: if
# the thread is of the normal class and a program beside the loop has its CPU, the loop waits a whole
# scheduler slice (measured: 11-54 ms late wake-ups every few seconds at load 10, while cyclictest saw at
# most 2 ms). The first wall-clock loop puts the process's other threads in the real-time class too, below
# the loop, the last one puts back what it changed; where the OS refuses
# the real-time class, the top of the normal class (nice -20). Linux's calls take a thread id. Processes
# started from those threads do not inherit the class (SCHED_RESET_ON_FORK).
OTHER_THREADS_FIFO = 10
OTHER_THREADS_NICE = -20
_others_holders = 0
_others_was: dict[int, tuple[int, int, int]] = {}  # tid -> (policy, rt priority, nice)


def _thread_ids() -> list[int]:
    try:
        return [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return []


def _raise_thread(tid: int) -> str:
    """Raise one normal-class thread: "fifo", "nice", or "" (it ended, or nothing was permitted)."""
    was = (os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority, os.getpriority(os.PRIO_PROCESS, tid))
    try:
        # reset on fork: a program the session's process starts (a shell command, a test's subprocess) gets
        # the normal class, not ours
        os.sched_setscheduler(tid, os.SCHED_FIFO | getattr(os, "SCHED_RESET_ON_FORK", 0),
                              os.sched_param(OTHER_THREADS_FIFO))
        _others_was[tid] = was
        return "fifo"
    except OSError as exc:
        if exc.errno not in (errno.EPERM, errno.EACCES):
            raise
    try:
        os.setpriority(os.PRIO_PROCESS, tid, OTHER_THREADS_NICE)
        _others_was[tid] = was
        return "nice"
    except OSError as exc:
        if exc.errno not in (errno.EPERM, errno.EACCES):
            raise
    return ""


def take_others(loop_tid: int) -> str:
    """Put every other normal-class thread of the process at SCHED_FIFO 10 (else nice -20); returns what
    was granted."""
    global _others_holders
    with _gc_lock:
        _others_holders += 1
        if _others_holders > 1:
            return "the process's other threads raised by the first loop"
        got = set()
        for tid in _thread_ids():
            if tid == loop_tid:
                continue
            try:
                if os.sched_getscheduler(tid) != os.SCHED_OTHER:
                    continue  # a real-time thread (another loop's) keeps its class
                got.add(_raise_thread(tid))
            except OSError:
                pass  # ESRCH: the thread ended meanwhile
        if "fifo" in got and got <= {"fifo"}:
            return (f"the process's other threads at SCHED_FIFO {OTHER_THREADS_FIFO}, below the loop: one holding the "
                    "GIL or the bus lock is not descheduled by a program beside the loop")
        if got - {""}:
            return (f"the process's other threads at nice {OTHER_THREADS_NICE} (SCHED_FIFO not granted): a program "
                    "beside the loop may still hold the GIL off it for a scheduler slice")
        return ("the process's other threads at their priority (not permitted): a program beside the loop may hold "
                "the GIL off it for a scheduler slice")


def release_others() -> None:
    global _others_holders
    with _gc_lock:
        _others_holders -= 1
        if _others_holders == 0:
            for tid, (policy, prio, nice) in _others_was.items():
                try:
                    os.sched_setscheduler(tid, policy, os.sched_param(prio))
                    os.setpriority(os.PRIO_PROCESS, tid, nice)
                except OSError:
                    pass  # ended meanwhile
            _others_was.clear()


class HostMeasures:
    """What one wall-clock loop holds of the process while it runs, taken on the loop's own thread (its
    affinity and scheduling class are the thread's) and given back, all of it, at close."""

    def __init__(self) -> None:
        self._release: list[Callable[[], None]] = []  # what to call at close, in the order taken

    def take(self, dt: float, *, gil_switch: bool, gc_control: bool, cpu: int | None,
             realtime: bool) -> dict[str, str]:
        """Take the measures asked for; returns what was granted, as ``status()["granted"]`` shows it."""
        granted: dict[str, str] = {}
        if gil_switch:
            was = take_switch(dt / 10)
            self._release.append(release_switch)
            granted["gil"] = (f"switch interval {sys.getswitchinterval() * 1e3:g} ms (was {was * 1e3:g} ms): "
                              "a thread beside the loop gives up the GIL within a tenth of a cycle")
        take_blas()
        self._release.append(release_blas)
        granted["blas"] = "one BLAS thread (the loop's own): no BLAS worker spinning on the other core"
        if gc_control:
            take_gc()
            self._release.append(release_gc)
            granted["gc"] = "frozen heap, automatic collection off, young generation collected in the slack"
        if cpu is not None and hasattr(os, "sched_setaffinity"):
            try:
                os.sched_setaffinity(0, {cpu})  # 0: the calling thread (Linux)
                granted["cpu"] = f"pinned to CPU {cpu}"
            except OSError as exc:
                granted["cpu"] = f"not pinned ({exc.strerror})"
        if realtime and hasattr(os, "sched_setscheduler"):
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(50))
                granted["priority"] = "SCHED_FIFO 50"
            except OSError as exc:
                granted["priority"] = f"SCHED_FIFO not granted ({exc.strerror}); normal priority"
            granted["others"] = take_others(threading.get_native_id())
            self._release.append(release_others)
        return granted

    def release(self) -> None:
        """Give back everything taken (the process's measures are counted: the last loop restores them)."""
        while self._release:
            self._release.pop()()

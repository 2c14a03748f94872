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
# threads (the program's, a console's, the trace writer). A program beside the loop at the same nice
# level takes the CPU from such a thread while it holds the GIL, and the loop then waits a whole CFS
# slice (several ms) for it: a priority inversion. The first wall-clock loop raises the process's other
# threads to the top of the normal class (threads they start inherit it), the last one puts back what it
# changed. Linux's setpriority takes a thread id for PRIO_PROCESS.
OTHER_THREADS_NICE = -20
_nice_holders = 0
_nice_was: dict[int, int] = {}


def _thread_ids() -> list[int]:
    try:
        return [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return []


def take_nice(loop_tid: int) -> str:
    """Raise every other normal-class thread of the process to nice -20; returns what was granted."""
    global _nice_holders
    with _gc_lock:
        _nice_holders += 1
        if _nice_holders > 1:
            return f"the process's other threads at nice {OTHER_THREADS_NICE} (by the first loop)"
        refused = ""
        for tid in _thread_ids():
            if tid == loop_tid:
                continue
            try:
                if os.sched_getscheduler(tid) != os.SCHED_OTHER:
                    continue  # a real-time thread (another loop's) keeps its class
                was = os.getpriority(os.PRIO_PROCESS, tid)
                if was > OTHER_THREADS_NICE:
                    os.setpriority(os.PRIO_PROCESS, tid, OTHER_THREADS_NICE)
                    _nice_was[tid] = was
            except OSError as exc:
                if exc.errno in (errno.EPERM, errno.EACCES):
                    refused = exc.strerror or "not permitted"
                # ESRCH: the thread ended meanwhile
        if refused and not _nice_was:
            return f"the process's other threads at their nice level ({refused}: a program beside the loop " \
                   "may hold the GIL off it while descheduled)"
        return (f"the process's other threads at nice {OTHER_THREADS_NICE}: one holding the GIL or the bus "
                "lock is not descheduled by a program beside the loop")


def release_nice() -> None:
    global _nice_holders
    with _gc_lock:
        _nice_holders -= 1
        if _nice_holders == 0:
            for tid, was in _nice_was.items():
                try:
                    os.setpriority(os.PRIO_PROCESS, tid, was)
                except OSError:
                    pass  # ended meanwhile
            _nice_was.clear()

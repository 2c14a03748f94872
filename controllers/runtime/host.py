"""The process-wide measures a wall-clock loop takes for its thread: the garbage collector, the GIL, the
BLAS thread pool, the priority of the process's other threads and transparent huge pages.

They are the process's, not a loop's: the first wall-clock loop takes each, the last one gives it back
(:class:`Shared`, one count per measure).
"""

from __future__ import annotations

import errno
import gc
import os
import sys
import threading
from collections.abc import Callable

_lock = threading.Lock()

#: a measure applied: how to undo it, and what was granted (as ``status()["granted"]`` shows it)
Applied = tuple[Callable[[], None], str]


class Shared:
    """A setting of the whole process: the first holder applies it, the last one undoes it."""

    def __init__(self, apply: Callable[..., Applied]):
        self._apply = apply
        self._holders = 0
        self._undo: Callable[[], None] | None = None
        self._said = ""

    def take(self, *args: object) -> str:
        """Hold the measure (applied with ``args`` by the first holder); returns what was granted."""
        with _lock:
            if self._holders == 0:
                self._undo, self._said = self._apply(*args)
            self._holders += 1
            return self._said

    def release(self) -> None:
        with _lock:
            self._holders -= 1
            if self._holders == 0 and self._undo is not None:
                self._undo()
                self._undo = None


def _collector() -> Applied:
    was_enabled = gc.isenabled()
    gc.collect()
    gc.freeze()  # what exists now is never scanned again: young collections stay short
    gc.disable()

    def undo() -> None:
        gc.unfreeze()  # back to normal collection: what was frozen may be collected again
        if was_enabled:
            gc.enable()

    return undo, "frozen heap, automatic collection off, young generation collected in the slack"


# Python hands the GIL to a waiting thread only after the holder has run for the switch interval (5 ms by
# default): a program plotting beside the loop would hold the loop's thread off for up to five cycles.
def _switch_interval(interval: float) -> Applied:
    was = sys.getswitchinterval()
    sys.setswitchinterval(min(was, interval))
    return (lambda: sys.setswitchinterval(was),
            f"switch interval {sys.getswitchinterval() * 1e3:g} ms (was {was * 1e3:g} ms): a thread beside the "
            "loop gives up the GIL within a tenth of a cycle")


# BLAS (OpenBLAS under numpy): the cycle's products are a few elements; a BLAS worker left spinning after
# each burned about 10 us of CPU per cycle on the other core, the one a program beside the loop (or the
# emulated drives across processes) runs on. Limited to the calling thread (threadpoolctl).
def _one_blas_thread() -> Applied:
    from threadpoolctl import threadpool_limits

    limit = threadpool_limits(limits=1, user_api="blas")
    return limit.restore_original_limits, "one BLAS thread (the loop's own): no BLAS worker spinning on the other core"


# The loop's thread runs at SCHED_FIFO, but it shares the GIL, and the bus lock, with the process's other
# threads (the program's, a console's, the loop's watchdog). When one of them asks for the GIL, the loop
# hands it over within the switch interval and then waits until that thread has actually taken it: if
# the thread is of the normal class and a program beside the loop has its CPU, the loop waits a whole
# scheduler slice (measured: 11-54 ms late wake-ups every few seconds at load 10, while cyclictest saw at
# most 2 ms). So the process's other threads go in the real-time class too, below the loop; where the OS
# refuses it, the top of the normal class (nice -20). Linux's calls take a thread id. Processes started
# from those threads do not inherit the class (SCHED_RESET_ON_FORK).
OTHER_THREADS_FIFO = 10
OTHER_THREADS_NICE = -20


def _thread_ids() -> list[int]:
    try:
        return [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return []


def _raise_thread(tid: int) -> tuple[str, tuple[int, int, int] | None]:
    """Raise one normal-class thread: ("fifo" | "nice" | "", what it was, to put back)."""
    was = (os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority, os.getpriority(os.PRIO_PROCESS, tid))
    try:
        os.sched_setscheduler(tid, os.SCHED_FIFO | getattr(os, "SCHED_RESET_ON_FORK", 0),
                              os.sched_param(OTHER_THREADS_FIFO))
        return "fifo", was
    except OSError as exc:
        if exc.errno not in (errno.EPERM, errno.EACCES):
            raise
    try:
        os.setpriority(os.PRIO_PROCESS, tid, OTHER_THREADS_NICE)
        return "nice", was
    except OSError as exc:
        if exc.errno not in (errno.EPERM, errno.EACCES):
            raise
    return "", None


def _other_threads(loop_tid: int) -> Applied:
    changed: dict[int, tuple[int, int, int]] = {}
    got = set()
    lock = threading.Lock()

    def take(tid: int) -> None:
        try:
            if os.sched_getscheduler(tid) != os.SCHED_OTHER:
                return  # a real-time thread (another loop's) keeps its class
            how, was = _raise_thread(tid)
        except OSError:
            return  # ESRCH: the thread ended meanwhile
        with lock:
            got.add(how)
            if was is not None:
                changed[tid] = was

    for tid in _thread_ids():
        if tid != loop_tid:
            take(tid)

    # threads started later (a program's poller, a console's server) hold the GIL just the same: each is
    # raised as it starts, on its own first call (threading's profile hook, then the thread's own profile)
    previous = threading.getprofile()

    def on_start(frame: object, event: str, arg: object) -> object:
        sys.setprofile(previous)
        take(threading.get_native_id())
        return previous(frame, event, arg) if previous is not None else None

    threading.setprofile(on_start)

    def undo() -> None:
        threading.setprofile(previous)
        with lock:
            put_back = list(changed.items())
        for tid, (policy, prio, nice) in put_back:
            try:
                os.sched_setscheduler(tid, policy, os.sched_param(prio))
                os.setpriority(os.PRIO_PROCESS, tid, nice)
            except OSError:
                pass  # ended meanwhile

    if got == {"fifo"}:
        said = (f"the process's other threads at SCHED_FIFO {OTHER_THREADS_FIFO}, below the loop: one holding the GIL "
                "or the bus lock is not descheduled by a program beside the loop")
    elif "nice" in got or "fifo" in got:
        said = (f"the process's other threads at SCHED_FIFO {OTHER_THREADS_FIFO} or nice {OTHER_THREADS_NICE} (the "
                "real-time class not granted to all): a program beside the loop may hold the GIL off it")
    else:
        said = ("the process's other threads at their priority (not permitted): a program beside the loop may hold "
                "the GIL off it for a scheduler slice")
    return undo, said


# Transparent huge pages: the kernel's khugepaged collapses a process's pages into huge ones, holding the
# process's memory map and its CPU for milliseconds, on a kernel that is not fully preemptible without
# yielding to a real-time thread (measured with perf sched: the loop's thread runnable, and held off, for
# 5.5 ms while khugepaged ran on its CPU). The process opts out (prctl PR_SET_THP_DISABLE); what
# khugepaged does for other processes is the host's (docs/timing.md, doctor reports the mode).
_PR_SET_THP_DISABLE, _PR_GET_THP_DISABLE = 41, 42


def _no_huge_pages() -> Applied:
    import ctypes

    try:
        libc = ctypes.CDLL(None, use_errno=True)
        was = libc.prctl(_PR_GET_THP_DISABLE, 0, 0, 0, 0)
        if was < 0 or libc.prctl(_PR_SET_THP_DISABLE, 1, 0, 0, 0) != 0:
            raise OSError(ctypes.get_errno(), os.strerror(ctypes.get_errno()))
    except (OSError, AttributeError) as exc:
        return (lambda: None), f"transparent huge pages as the host has them (prctl refused: {exc})"
    return (lambda: libc.prctl(_PR_SET_THP_DISABLE, was, 0, 0, 0)), \
        "transparent huge pages off for this process: khugepaged does not collapse its memory under the loop"


COLLECTOR = Shared(_collector)
SWITCH_INTERVAL = Shared(_switch_interval)
ONE_BLAS_THREAD = Shared(_one_blas_thread)
OTHER_THREADS = Shared(_other_threads)
NO_HUGE_PAGES = Shared(_no_huge_pages)


class HostMeasures:
    """What one wall-clock loop holds of the process while it runs, taken on the loop's own thread (its
    affinity and scheduling class are the thread's) and given back, all of it, at close."""

    def __init__(self) -> None:
        self._held: list[Shared] = []  # in the order taken

    def _hold(self, measure: Shared, *args: object) -> str:
        said = measure.take(*args)
        self._held.append(measure)
        return said

    def take(self, dt: float, *, gil_switch: bool, gc_control: bool, cpu: int | None,
             realtime: bool) -> dict[str, str]:
        """Take the measures asked for; returns what was granted, as ``status()["granted"]`` shows it."""
        granted: dict[str, str] = {}
        if gil_switch:
            granted["gil"] = self._hold(SWITCH_INTERVAL, dt / 10)
        granted["blas"] = self._hold(ONE_BLAS_THREAD)
        if sys.platform.startswith("linux"):
            granted["thp"] = self._hold(NO_HUGE_PAGES)
        if gc_control:
            granted["gc"] = self._hold(COLLECTOR)
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
            granted["others"] = self._hold(OTHER_THREADS, threading.get_native_id())
        return granted

    def release(self) -> None:
        """Give back everything taken (counted per measure: the last loop restores the process's settings)."""
        while self._held:
            self._held.pop().release()


# Steal time: on a virtual machine, the time the hypervisor ran something else while a vCPU of this guest was
# ready to run (/proc/stat's eighth field per CPU, in USER_HZ ticks). A gap of the loop that the guest's own
# scheduler cannot explain (cyclictest at real-time priority sees it too) shows up here: measured on the
# 2-core VM of docs/timing.md, exactly 100 ms taken from one vCPU now and then.
def steal_s() -> dict[str, float] | None:
    """Each CPU's steal time since boot (s, ``{"cpu0": ...}``); None where the kernel does not say."""
    try:
        tick = 1.0 / os.sysconf("SC_CLK_TCK")
        with open("/proc/stat") as f:
            return {p[0]: int(p[8]) * tick for p in (line.split() for line in f)
                    if p[0].startswith("cpu") and p[0] != "cpu" and len(p) > 8}
    except (OSError, ValueError, IndexError):
        return None


class StealWatch:
    """The host's steal time since a mark: :meth:`mark` now and then (off the cycle's path), :meth:`since`
    when a gap is found. A ``/proc/stat`` read costs some tens of us: never per cycle."""

    def __init__(self, read: Callable[[], dict[str, float] | None] = steal_s):
        self._read = read
        self._mark = read()

    def mark(self) -> None:
        self._mark = self._read()

    def since(self) -> tuple[str, float] | None:
        """The CPU whose steal time rose most since the mark, and by how much (s); None: unknown or none."""
        now, was = self._read(), self._mark
        if not now or not was:
            return None
        cpu, rise = max(((c, now[c] - was.get(c, now[c])) for c in now), key=lambda cr: cr[1])
        return (cpu, rise) if rise > 0 else None

    def note(self) -> str:
        """A clause for a stall's message: what the hypervisor took meanwhile, or nothing."""
        got = self.since()
        if got is None:
            return ""
        cpu, rise = got
        return (f"; the host's steal time on {cpu} rose by {rise * 1e3:.0f} ms since about a second before "
                "(the hypervisor ran something else on this VM's CPU: docs/timing.md)")

"""The servo loop's own process: ``python -m drivectl.session_child`` (started by session_process.py).

It builds the machine exactly as ``drivectl.connect(loop="thread")`` does (session.open_here: the same
ServoLoop, the same cycle code on either clock), with its status and rings in shared memory
(controllers/runtime/shared.py), and serves the Machine's, the axes' and the handles' methods to the user's
process through a ``multiprocessing.managers`` server on a Unix socket (one thread per connection of the
user's side, authenticated with a key given on the control pipe). It does nothing else: no user code,
no console, no plotting.

What it takes of the OS, beside the loop's own measures (controllers/runtime/host.py): all of its memory
locked (``mlockall``, where granted), no garbage collection while an axis is enabled, and it dies with
its parent: ``PR_SET_PDEATHSIG`` (SIGTERM, on Linux, when the parent's connecting thread is its main
thread) and the control pipe's end of file both close the machine (every axis disabled, verified, with
a bound of 3 s), then the process exits. A parent killed by SIGKILL thus leaves no process behind, and
an axis whose disable is not confirmed in time is stopped by its drive's own RPDO deadline and
heartbeat once the bus is silent.
"""

from __future__ import annotations

import ctypes
import gc
import os
import shutil
import signal
import sys
import threading
from multiprocessing.connection import Connection
from multiprocessing.managers import BaseManager
from typing import Any

_PR_SET_PDEATHSIG = 1
_MCL_CURRENT, _MCL_FUTURE, _MCL_ONFAULT = 1, 2, 4
#: how long the close at the parent's death may take before the process exits regardless (s)
DEATH_CLOSE_S = 3.0


def _libc() -> Any:
    return ctypes.CDLL(None, use_errno=True)


def die_with_parent(parent: int) -> str:
    """PR_SET_PDEATHSIG: SIGTERM when the parent (its thread that started us) ends; what was granted."""
    if not sys.platform.startswith("linux"):
        return "the control pipe's end only (no PR_SET_PDEATHSIG off Linux)"
    try:
        if _libc().prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0) != 0:
            raise OSError(ctypes.get_errno(), os.strerror(ctypes.get_errno()))
    except (OSError, AttributeError) as exc:
        return f"the control pipe's end only (prctl refused: {exc})"
    if os.getppid() != parent:  # the parent ended before the prctl took hold
        os._exit(0)
    return "PR_SET_PDEATHSIG (SIGTERM) and the control pipe's end"


def lock_memory() -> str:
    """mlockall(MCL_CURRENT | MCL_FUTURE | MCL_ONFAULT): no page of this process that was touched is paged
    out under the loop. On fault: a page is locked when first used, so the threads' reserved stacks and
    the allocators' reserves cost nothing (locked whole, they made the process 570 MB resident)."""
    libc = _libc()
    try:
        if libc.mlockall(_MCL_CURRENT | _MCL_FUTURE | _MCL_ONFAULT) == 0:
            return "the loop's process locked in memory (mlockall, current and future, each page from its first use)"
        if libc.mlockall(_MCL_CURRENT | _MCL_FUTURE) == 0:  # a kernel before 4.4: no MCL_ONFAULT
            return "all of the loop's process locked in memory (mlockall, current and future)"
        err = ctypes.get_errno()
        raise OSError(err, os.strerror(err))
    except (OSError, AttributeError) as exc:
        return f"not locked (mlockall refused: {exc}); raise RLIMIT_MEMLOCK or grant CAP_IPC_LOCK"


class Served:
    """What the user's process calls: the machine's, the axes' and the handles' methods by name. Handles
    (Move, Capture) stay here under a number; the user's side holds the number."""

    def __init__(self, machine: Any, granted: dict[str, str]):
        self.m = machine
        self.granted = granted
        self._handles: dict[int, Any] = {}
        self._ids: dict[int, int] = {}  # id() of a kept handle -> its number
        self._next = 0
        self._lock = threading.Lock()

    # -- handles ----------------------------------------------------------------------------------------
    def _keep(self, obj: Any) -> Any:
        from drivectl.controllers.runtime.capture import Capture
        from drivectl.controllers.runtime.handles import Move

        if isinstance(obj, list):
            return [self._keep(o) for o in obj]
        if isinstance(obj, Move | Capture):
            with self._lock:
                hid = self._ids.get(id(obj))  # the same handle again (a jog's renewal): the same number
                if hid is None:
                    self._next += 1
                    hid = self._ids[id(obj)] = self._next
                    self._handles[hid] = obj
            if isinstance(obj, Move):
                return ("move", hid, obj.axis, obj.kind, obj.target, self.move_state(hid))
            return ("capture", hid, obj.axis, obj.channels, obj.trigger, obj.pre, obj.post, obj.dt, obj.meta)
        return obj

    def kept(self) -> int:
        """How many handles are kept for the user's side (a long session's handles must not pile up)."""
        return len(self._handles)

    def forget(self, ids: list[int]) -> None:
        with self._lock:
            for i in ids:
                obj = self._handles.pop(i, None)
                if obj is not None:
                    self._ids.pop(id(obj), None)

    # -- the machine and its axes --------------------------------------------------------------------------
    def info(self) -> dict[str, Any]:
        m = self.m
        loop = m.loop
        axes = {}
        for name, ax in m.axes.items():
            hw = m.hardware.axes[name]
            axes[name] = {"limits": ax.limits, "motion_limits": ax.motion_limits,
                          "node_id": getattr(hw, "node_id", None),
                          "identity_answered": getattr(hw, "identity_answered", None),
                          "effort_unit": hw.effort_unit, "jog_deadman": loop.axes[name].motion.jog_deadman}
        return {"pid": os.getpid(), "clock": loop.clock, "dt": loop.dt, "bus": m.bus, "config": m.config,
                "deadlines": dict(loop.deadlines), "axes": axes, "shm": m.shared.name,
                "layout": m.shared.layout}

    def call(self, method: str, args: tuple, kw: dict[str, Any], forget: list[int]) -> Any:
        if forget:
            self.forget(forget)
        if method == "step":
            self.m.loop.step(*args)
            return None
        return self._keep(getattr(self.m, method)(*args, **kw))

    def axis_call(self, axis: str, method: str, args: tuple, kw: dict[str, Any], forget: list[int]) -> Any:
        if forget:
            self.forget(forget)
        ax = self.m.axes[axis]
        out = self._keep(getattr(ax, method)(*args, **kw))
        if method == "enable" and ax.timing_warning:
            return ("warned", ax.timing_warning)
        return out

    def axis_get(self, axis: str, attr: str) -> Any:
        return getattr(self.m.axes[axis], attr)

    def status(self) -> dict[str, Any]:
        out = self.m.status()
        out["granted"].update(self.granted)
        out["loop"] = "process"
        out["loop_pid"] = os.getpid()
        return out

    def latency(self) -> Any:
        return self.m.loop.latency

    def faults(self) -> list[Any]:
        return list(self.m.loop.faults)

    # -- handles: a move, a capture ------------------------------------------------------------------------
    def move_state(self, hid: int) -> dict[str, Any]:
        h = self._handles[hid]
        return {"status": str(h.status), "detail": h.detail, "fault": h.fault, "position": h.position,
                "following_error": h.following_error, "settled": h.settled, "cycles": h.cycles, "done": h.done,
                "target": h.target, "path": h.path, "record_error": h.record_error}

    def move_wait(self, hid: int, timeout: float | None) -> dict[str, Any]:
        self._handles[hid].wait(timeout)
        return self.move_state(hid)

    def move_trace(self, hid: int) -> Any:
        return self._handles[hid].trace  # one pickled block: the run's record, whole

    def capture_state(self, hid: int) -> tuple[str, str, int | None]:
        c = self._handles[hid]
        return c.state, c.detail, c.trigger_slot

    def capture_wait(self, hid: int, timeout: float | None) -> Any:
        """The trace once it filled: its samples out of the ring in one block, never cycle by cycle."""
        c = self._handles[hid]
        tr = c.wait(timeout)
        return tr, c.state, c.detail

    def capture_result(self, hid: int) -> Any:
        c = self._handles[hid]
        return c.result(), c.state, c.detail


class _Manager(BaseManager):
    pass


def main() -> int:
    """The child's whole life: read the spec, build, serve, close at the parent's end."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a Ctrl-C is the user's program's to handle (it stops the axes)
    fd_in, fd_out = int(sys.argv[1]), int(sys.argv[2])
    control, reply = Connection(fd_in, writable=False), Connection(fd_out, readable=False)
    spec = control.recv()
    granted = {"process": die_with_parent(spec["parent"]) if spec["pdeathsig"] else
               "the control pipe's end (the parent's connecting thread is not its main thread: no PR_SET_PDEATHSIG)"}
    granted["memory"] = lock_memory()
    ended = threading.Event()

    def on_term(signum: int, frame: object) -> None:  # noqa: ARG001 - the parent ended (PDEATHSIG) or a kill
        ended.set()

    signal.signal(signal.SIGTERM, on_term)
    import warnings

    from drivectl.session import TimingWarning, open_here

    warnings.simplefilter("ignore", TimingWarning)  # the user's process warns, with enable's text (session_process)

    try:
        machine = open_here(spec["config"], spec["names"], shared=True, **spec["opts"])
    except BaseException as exc:  # noqa: BLE001 - the user's side raises it as it would in-process
        try:
            reply.send(("error", exc))
        except Exception:  # noqa: BLE001 - not picklable: its type and text
            reply.send(("error", RuntimeError(f"{type(exc).__name__}: {exc}")))
        return 1
    if spec["opts"]["clock"] == "wall":
        granted["gc"] = ("frozen heap, automatic collection off; none at all while an axis is enabled or "
                         "enabling, young generation in the slack otherwise (the loop's own process)")
    served = Served(machine, granted)
    _Manager.register("served", callable=lambda: served)
    server = _Manager(address=spec["address"], authkey=spec["authkey"]).get_server()
    server.stop_event = threading.Event()  # serve_forever's (its main-thread wait is ours: the parent watch below)
    threading.Thread(target=server.accepter, name="drivectl-loop-server", daemon=True).start()
    reply.send(("ready", served.info()))
    gc.collect()
    gc.freeze()  # what was built is never scanned again

    def watch_pipe() -> None:
        try:
            control.recv_bytes()  # the parent sends nothing more: this returns at its end (EOF) or its "close"
        except (EOFError, OSError):
            pass
        ended.set()

    threading.Thread(target=watch_pipe, name="drivectl-parent-watch", daemon=True).start()
    while not ended.wait(1.0):
        pass
    # the parent closed the machine, ended, or was killed: close what is left (idempotent), bounded
    closer = threading.Thread(target=_close, args=(machine,), name="drivectl-loop-close", daemon=True)
    closer.start()
    closer.join(DEATH_CLOSE_S)
    machine.shared.unlink()
    shutil.rmtree(os.path.dirname(spec["address"]), ignore_errors=True)  # the socket's folder (a killed parent's too)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


def _close(machine: Any) -> None:
    try:
        machine.close()
    except BaseException as exc:  # noqa: BLE001 - the drives' own watchdogs stop what the close could not
        print(f"drivectl: the loop's process: close failed: {exc}", file=sys.stderr)


if __name__ == "__main__":
    sys.exit(main())

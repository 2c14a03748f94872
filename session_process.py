"""``drivectl.connect(loop="process")``: the servo loop in a process of its own, the API in the user's.

The loop's process (session_child.py) builds the machine as ``connect(loop="thread")`` does and serves it;
this module holds the user's side: :class:`ProcessMachine`, :class:`ProcessAxis`, :class:`ProcessMove` and
:class:`ProcessCapture`, with the public names and behaviour of session.py's Machine, AxisControl, Move
and Capture. How each kind of thing crosses:

* commands (enable, move_to, jog, stop, run, home, capture, close, ...) and waits: one call each through
  a ``multiprocessing.managers`` connection (a Unix socket; each thread of this process has its own
  connection, so a console's threads do not queue behind a waiting shell). The exceptions raised there
  (AxisError, LimitError, MotionFault, CaptureError, HomingError, TimeoutError) are raised here, the same
  types with the same messages.
* status, positions, states: read from the shared-memory block the loop writes every cycle
  (controllers/runtime/shared.py), no call and no per-cycle work here; the rarely changing rest (fault
  texts, latency percentiles, what the OS granted) by a call, when the block says it changed or once a
  second.
* captures and a run's record: the trace, whole, in one pickled block when it completed; the scope reads
  the rings in shared memory where the loop writes them.
* faults: a fault ends the moves under way there; their handles raise MotionFault here.

A KeyboardInterrupt while a call is under way stops every axis (a controlled stop, as in-process) and
drops that thread's connection, whose reply would come late.
"""

from __future__ import annotations

import math
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import warnings
import weakref
from multiprocessing.connection import Connection
from multiprocessing.managers import BaseManager
from pathlib import Path
from types import SimpleNamespace
from typing import Any

from drivectl.controllers.runtime.capture import CHANNELS, Capture, CaptureError, Ring, Trigger
from drivectl.controllers.runtime.loop import AxisState
from drivectl.controllers.runtime.shared import LOOP_FIELDS, POWERS, STATES, SharedView, decode_axis
from drivectl.driver.axis import AxisError
from drivectl.driver.cia402 import PowerState

#: how long the loop's process may take to build the machine (boot the drives) before connect gives up (s)
START_TIMEOUT_S = 60.0
#: how old the slow part of status() may be (s)
SLOW_STATUS_S = 1.0
_STATE_ENUM = {s.value: s for s in AxisState}


class _Client(BaseManager):
    pass


_Client.register("served")


class LoopGone(AxisError):
    """The loop's process ended (killed, crashed): the drives' own watchdogs stop the axes."""


# -- the machine ---------------------------------------------------------------------------------------------
class ProcessMachine:
    """A connected machine whose loop runs in a process of its own (see the module docstring)."""

    def __init__(self, proc: subprocess.Popen, control: Connection, served: Any, info: dict[str, Any],
                 folder: str):
        self._proc = proc
        self._control = control
        self._served = served
        self._folder = folder
        self._info = info
        self._forget: list[int] = []
        #: the handles this side holds (weakly: one dropped here is forgotten there with the next call)
        self._moves: weakref.WeakValueDictionary[int, ProcessMove] = weakref.WeakValueDictionary()
        self._closed = False
        self._slow: dict[str, Any] | None = None
        self._slow_key: Any = None
        self._slow_t = 0.0
        self._slow_lock = threading.Lock()
        self.pid: int = info["pid"]
        self.config = info["config"]
        self.bus = info["bus"]
        self.view = SharedView(info["shm"], info["layout"])
        self.axes: dict[str, ProcessAxis] = {n: ProcessAxis(self, n, a) for n, a in info["axes"].items()}
        self.loop = LoopView(self)
        self.hardware = SimpleNamespace(bus=self.bus, axes={n: SimpleNamespace(
            node_id=a["node_id"], identity_answered=a["identity_answered"], effort_unit=a["effort_unit"])
            for n, a in info["axes"].items()})
        self.unconfirmed: list[str] = []

    # -- calls into the loop's process ---------------------------------------------------------------------
    def _call(self, method: str, *args: Any) -> Any:
        forget, self._forget = self._forget, []
        try:
            return self._served._callmethod(method, args + ((forget,) if method in ("call", "axis_call") else ()))
        except (EOFError, ConnectionError, FileNotFoundError) as exc:
            raise self._gone(exc) from None
        except BaseException as exc:
            if not isinstance(exc, Exception):  # interrupted mid-call: its reply must not answer the next one
                conn = getattr(self._served._tls, "connection", None)
                if conn is not None:
                    del self._served._tls.connection
                    conn.close()
            raise

    def _gone(self, exc: BaseException) -> LoopGone:
        code = self._proc.poll()
        how = f"exit code {code}" if code is not None else f"{type(exc).__name__}"
        return LoopGone(f"the servo loop's process (pid {self.pid}) ended ({how}); the drives' own watchdogs "
                        "(RPDO deadline, heartbeat) stop the axes: they may still be powered until then")

    def _machine(self, method: str, *args: Any, **kw: Any) -> Any:
        return self._wrap(self._call("call", method, args, kw))

    def _wrap(self, out: Any) -> Any:
        if isinstance(out, list):
            return [self._wrap(o) for o in out]
        if isinstance(out, tuple) and out and out[0] == "move":
            _, hid, axis, kind, target, state = out
            h = self._moves.get(hid)
            if h is None:  # the same handle there is the same object here (a jog's renewal returns it)
                h = self._moves[hid] = ProcessMove(self, hid, axis, kind, target, state)
            return h
        if isinstance(out, tuple) and out and out[0] == "capture":
            return ProcessCapture(self, *out[1:])
        return out

    def _dropped(self, hid: int) -> None:
        self._moves.pop(hid, None)
        self._forget.append(hid)

    # -- the Machine API -------------------------------------------------------------------------------------
    @property
    def clock(self) -> str:
        return self._info["clock"]

    def advance(self, seconds: float) -> None:
        """Let ``seconds`` pass: lockstep runs the cycles (there), wall clock sleeps (here)."""
        if self.clock == "lockstep":
            self._machine("advance", seconds)
        else:
            threading.Event().wait(seconds)

    def run_until(self, done: Any, timeout: float | None) -> bool:
        """Until ``done()`` (evaluated here): lockstep steps the loop one cycle per check, wall polls."""
        if self.clock == "lockstep":
            dt = self.loop.dt
            limit = int(math.ceil(timeout / dt)) if timeout is not None else int(3600 / dt)
            for _ in range(limit):
                if done():
                    return True
                self._call("call", "step", (1,), {})
            return bool(done())
        end = None if timeout is None else time.monotonic() + timeout
        try:
            while not done():
                if self._proc.poll() is not None:
                    return bool(done())
                if end is not None and time.monotonic() >= end:
                    return False
                time.sleep(min(0.002, self.loop.dt * 2))
        except KeyboardInterrupt:
            self.stop_all("interrupted (KeyboardInterrupt)")
            raise
        return True

    def stop_all(self, why: str = "stopped") -> list[ProcessMove]:
        return self._machine("stop_all", why)

    def status(self) -> dict[str, Any]:
        """As session.Machine.status(): the counters and each axis from the shared block (as of the last
        cycle), the texts and percentiles from the loop's process (at most SLOW_STATUS_S old)."""
        blk = self.view.read()
        lf = dict(zip(LOOP_FIELDS, blk[:len(LOOP_FIELDS)].tolist(), strict=True))
        rows = {n: self.view.axis_row(blk, n) for n in self.axes}
        key = (lf["faults"], lf["command_errors"], tuple((r["state"], r["faulted"]) for r in rows.values()))
        slow = self._slow_status(key)
        wall = self.clock == "wall"
        n = max(int(lf["slots"] if wall else lf["cycle"]), 1)
        out = dict(slow)
        out.update({"cycles": int(lf["cycle"]), "missed_deadlines": int(lf["missed"]),
                    "missed_fraction": lf["missed"] / n, "skipped_cycles": int(lf["skipped"]),
                    "worst_late_ms": lf["worst_late"] * 1e3, "stalls": int(lf["stalls"]),
                    "gc_collections": int(lf["gc_runs"]), "gc_worst_ms": lf["gc_worst"] * 1e3,
                    "faults": int(lf["faults"]), "command_errors": int(lf["command_errors"])})
        axes = {}
        for name, row in rows.items():
            a = dict(slow["axes"].get(name, {}))
            a.update(decode_axis(row))
            if not row["faulted"]:
                a.pop("fault", None)
            axes[name] = a
        out["axes"] = axes
        return out

    def _slow_status(self, key: Any) -> dict[str, Any]:
        with self._slow_lock:
            now = time.monotonic()
            if self._slow is None or key != self._slow_key or now - self._slow_t > SLOW_STATUS_S:
                self._slow = self._call("status")
                self._slow_key, self._slow_t = key, now
            return self._slow

    def close(self) -> dict[str, str]:
        """Disable every axis (verified, there), stop the loop, close the bus; then the loop's process ends."""
        if self._closed:
            return {}
        self._closed = True
        states: dict[str, str] = {}
        try:
            states = self._machine("close")  # the loop's process names an axis that did not confirm (stderr)
        except LoopGone as exc:
            print(f"drivectl: {exc}", file=sys.stderr)
        finally:
            self._end()
        self.unconfirmed = [n for n, st in states.items() if st == PowerState.OPERATION_ENABLED.value]
        return states

    def _end(self) -> None:
        try:
            self._control.close()  # the end of file: the loop's process exits (it has closed the machine)
        except OSError:
            pass
        try:
            self._proc.wait(10)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait(5)
        self.view.close()
        shutil.rmtree(self._folder, ignore_errors=True)

    def __enter__(self) -> ProcessMachine:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<drivectl machine on {self.bus}: {', '.join(self.axes)} ({self.clock}, loop in process {self.pid})>"


# -- an axis --------------------------------------------------------------------------------------------------
class ProcessAxis:
    """``machine.axes["x"]``: session.AxisControl's API, the loop in its own process."""

    def __init__(self, machine: ProcessMachine, name: str, info: dict[str, Any]):
        self._m = machine
        self.name = name
        self._info = info
        self.timing_warning = ""

    def _row(self, field: str) -> float:
        return self._m.view.axis_value(self.name, field)

    def _do(self, method: str, *args: Any, **kw: Any) -> Any:
        return self._m._wrap(self._m._call("axis_call", self.name, method, args, kw))

    # -- what it reports (the shared block: as of the last cycle) --------------------------------------------
    @property
    def position(self) -> float:
        return self._row("position")

    @property
    def velocity(self) -> float:
        return self._row("velocity")

    @property
    def following_error(self) -> float:
        return self._row("following_error")

    @property
    def power(self) -> PowerState:
        return POWERS[int(self._row("power"))]

    @property
    def state(self) -> str:
        return STATES[int(self._row("state"))]

    @property
    def enabled(self) -> bool:
        return self.state == AxisState.SERVO.value

    @property
    def error(self) -> tuple[int, str] | None:
        return self._m._call("axis_get", self.name, "error")

    @property
    def fault(self) -> Any:
        return self._m._call("axis_get", self.name, "fault") if self._row("faulted") else None

    @property
    def limits(self) -> Any:
        return self._info["limits"]

    @property
    def motion_limits(self) -> Any:
        return self._info["motion_limits"]

    # -- commands (carried out there, the same checks and the same errors) -----------------------------------
    def enable(self, timeout: float = 1.0) -> None:
        out = self._do("enable", timeout)
        if isinstance(out, tuple) and out[:1] == ("warned",):
            from drivectl.session import TimingWarning

            self.timing_warning = out[1]
            warnings.warn(self.timing_warning, TimingWarning, stacklevel=2)

    def disable(self, timeout: float = 1.0) -> None:
        self._do("disable", timeout)

    def fault_reset(self, timeout: float = 1.0) -> None:
        self._do("fault_reset", timeout)

    def move_to(self, position: float, *, speed: float | None = None) -> ProcessMove:
        return self._do("move_to", position, speed=speed)

    def move_by(self, distance: float, *, speed: float | None = None) -> ProcessMove:
        return self._do("move_by", distance, speed=speed)

    def jog(self, velocity: float) -> ProcessMove:
        return self._do("jog", velocity)

    def stop(self, why: str = "stopped") -> ProcessMove:
        return self._do("stop", why)

    def run(self, profile: Any, *, relative: bool = False, approach: bool = False,
            record: str | Path | None = None) -> ProcessMove:
        # a relative folder is this process's: the loop's process may stand elsewhere (same files)
        return self._do("run", profile, relative=relative, approach=approach,
                        record=None if record is None else os.path.abspath(record))

    def home(self) -> ProcessMove:
        return self._do("home")

    def set_position(self, position: float) -> None:
        self._do("set_position", position)

    def capture(self, channels: Any = ("reference", "position", "following_error", "effort"),
                trigger: str | Trigger | None = "now", pre: float = 0.1, post: float = 0.5) -> ProcessCapture:
        return self._do("capture", tuple(channels), trigger, pre, post)

    def __repr__(self) -> str:
        return f"<axis {self.name}: {self.state}, {self.power.value}, {self.position * 1e3:.6f} mm>"


# -- handles --------------------------------------------------------------------------------------------------
class ProcessMove:
    """A handle on a command given to the loop (session's Move): ``wait()`` for its end."""

    _FINAL = ("done", "stopped", "fault")

    def __init__(self, machine: ProcessMachine, hid: int, axis: str, kind: str, target: float | None,
                 state: dict[str, Any]):
        self._m = machine
        self._hid = hid
        self.axis = axis
        self.kind = kind
        self._state = state
        self._trace: Any = None
        self._final = bool(state["done"])

    def __del__(self) -> None:
        try:
            self._m._dropped(self._hid)
        except Exception:  # noqa: BLE001 - at interpreter exit: nothing to tell
            pass

    def _now(self) -> dict[str, Any]:
        if not self._final:
            self._state = self._m._call("move_state", self._hid)
            self._final = bool(self._state["done"])
        return self._state

    @property
    def done(self) -> bool:
        return bool(self._now()["done"])

    def __getattr__(self, name: str) -> Any:
        if name in ("status", "detail", "fault", "position", "following_error", "settled", "cycles", "target",
                    "path", "record_error"):
            return self._now()[name]
        raise AttributeError(name)

    @property
    def trace(self) -> Any:
        """A run's record (trace v1), once it ended: one block from the loop's process."""
        if self._trace is None and self.kind == "run" and self.done:
            self._trace = self._m._call("move_trace", self._hid)
        return self._trace

    def wait(self, timeout: float | None = None) -> ProcessMove:
        """As Move.wait: MotionFault when it ended in a fault, TimeoutError when it has not ended."""
        try:
            self._state = self._m._call("move_wait", self._hid, timeout)
            self._final = True
        except KeyboardInterrupt:
            self._m.stop_all("interrupted (KeyboardInterrupt)")
            raise
        except Exception:
            self._final = False
            self._now()  # the handle as it ended (a fault) or stands (a timeout)
            raise
        return self

    def close_record(self) -> None:
        """A streamed run's file is closed in the loop's process, by its wait."""

    def __repr__(self) -> str:
        st = self._now()
        where = f" at {st['position'] * 1e3:.6f} mm" if st["position"] is not None else ""
        return f"<Move {self.kind} axis {self.axis}: {st['status']}{where}>"


class ProcessCapture:
    """A capture armed on one axis (session's Capture): ``wait()`` gives its trace, in one block."""

    #: draw the PNG in a child process: no need, the loop is not in this one (a caller may still ask)
    plot_apart = False

    def __init__(self, machine: ProcessMachine, hid: int, axis: str, channels: tuple[str, ...], trigger: Trigger,
                 pre: int, post: int, dt: float, meta: dict[str, str]):
        self._m = machine
        self._hid = hid
        self.axis, self.channels, self.trigger, self.pre, self.post, self.dt, self.meta = (
            axis, channels, trigger, pre, post, dt, meta)
        self._local: Capture | None = None  # the completed capture, here (its trace, its writing)
        self._state = ("armed", "", None)

    def __del__(self) -> None:
        try:
            self._m._forget.append(self._hid)
        except Exception:  # noqa: BLE001 - at interpreter exit
            pass

    def _completed(self, got: tuple[Any, str, str]) -> Capture:
        tr, state, detail = got
        cap = Capture(self.axis, self.channels, self.trigger, self.pre, self.post, self.dt, self.meta)
        cap.trace, cap.state, cap.detail = tr, state, detail
        cap._done.set()
        self._local = cap
        return cap

    def _now(self) -> tuple[str, str, int | None]:
        if self._local is None:
            self._state = self._m._call("capture_state", self._hid)
        return self._state if self._local is None else (self._local.state, self._local.detail, None)

    @property
    def state(self) -> str:
        return self._now()[0]

    @property
    def detail(self) -> str:
        return self._now()[1]

    @property
    def trigger_slot(self) -> int | None:
        return self._now()[2]

    @property
    def done(self) -> bool:
        return self.state in ("done", "cancelled")

    @property
    def trace(self) -> Any:
        return self._local.trace if self._local is not None else None

    def wait(self, timeout: float | None = None) -> Any:
        if self._local is None:
            self._completed(self._m._call("capture_wait", self._hid, timeout))
        return self._local.result()  # type: ignore[union-attr]

    def result(self) -> Any:
        if self._local is None:
            self._completed(self._m._call("capture_result", self._hid))
        return self._local.result()  # type: ignore[union-attr]

    def write(self, path: str | Path, plot: bool = True) -> list[Path]:
        """The trace and its PNG, written here (the loop is not in this process: drawn in place)."""
        self.result()
        self._local.plot_apart = self.plot_apart  # type: ignore[union-attr]
        return self._local.write(path, plot)  # type: ignore[union-attr]

    def _trigger_text(self) -> str:
        self.result()
        return self._local._trigger_text()  # type: ignore[union-attr]


# -- the loop, as the console, the live view and the benches read it -----------------------------------------
class RingView(Ring):
    """An axis's capture ring, read in the shared segment (its write index from the block)."""

    def __init__(self, machine: ProcessMachine, name: str):
        data, slot = machine.view.ring_arrays[name]
        self._v, self._name = machine.view, name
        super().__init__(data.shape[1], data, slot)

    @property  # type: ignore[override]
    def next(self) -> int:
        return int(self._v.axis_value(self._name, "ring_next"))

    @next.setter
    def next(self, value: int) -> None:  # Ring.__init__'s; the loop's process writes it
        pass

    @property  # type: ignore[override]
    def count(self) -> int:
        return int(self._v.axis_value(self._name, "ring_count"))

    @count.setter
    def count(self, value: int) -> None:
        pass

    def push(self, *args: Any) -> None:
        raise RuntimeError("the ring is written by the loop's process")


class _Handle:
    def __init__(self, kind: str):
        self.kind = kind
        self.done = False


class AxisView:
    """``machine.loop.axes[name]``: what the console and the live view read of an axis runtime."""

    def __init__(self, machine: ProcessMachine, name: str):
        self._m = machine
        self.name = name
        self.ring = RingView(machine, name)
        self.motion = machine.axes[name].motion_limits
        self.traj = _Traj(self)

    def _row(self) -> dict[str, Any]:
        v = self._m.view
        return v.axis_row(v.read(), self.name)

    def __getattr__(self, name: str) -> Any:
        fields = {"position": "position", "velocity": "velocity", "reference": "reference",
                  "following_error": "following_error", "effort": "effort", "offset": "offset"}
        if name in fields:
            return self._row()[fields[name]]
        raise AttributeError(name)

    @property
    def state(self) -> AxisState:
        return _STATE_ENUM[STATES[int(self._row()["state"])]]

    @property
    def handle(self) -> _Handle | None:
        move = decode_axis(self._row())["move"]
        return None if move is None else _Handle(move)

    @property
    def arrived(self) -> bool:
        return bool(self._row()["arrived"])


class _Traj:
    """``rt.traj.arrived``: the reference at rest (the block)."""

    def __init__(self, axis: AxisView):
        self._axis = axis

    @property
    def arrived(self) -> bool:
        return self._axis.arrived


class LoopView:
    """``machine.loop``: the counters from the shared block; ``step`` and ``latency`` by a call."""

    def __init__(self, machine: ProcessMachine):
        self._m = machine
        info = machine._info
        self.dt: float = info["dt"]
        self.clock: str = info["clock"]
        self.deadlines: dict[str, float] = info["deadlines"]
        self.axes = {n: AxisView(machine, n) for n in info["axes"]}
        self.error: BaseException | None = None

    def _field(self, name: str) -> int:
        v = self._m.view
        return int(v.loop_field(v.read(), name))

    @property
    def cycle(self) -> int:
        return self._field("cycle")

    @property
    def slot(self) -> int:
        return self._field("slot")

    @property
    def slots(self) -> int:
        return self._field("slots")

    @property
    def latency(self) -> Any:
        """The loop's LatencyRecord, as of now (a copy from the loop's process)."""
        return self._m._call("latency")

    @property
    def faults(self) -> list[Any]:
        """The faults the loop met (kind, axis, detail, safe state; ``at``: CLOCK_MONOTONIC, shared by the
        processes), a copy from the loop's process."""
        return self._m._call("faults")

    @property
    def running(self) -> bool:
        return self._m._proc.poll() is None

    def step(self, cycles: int = 1) -> None:
        self._m._call("call", "step", (cycles,), {})

    def run_until(self, done: Any, timeout: float | None) -> bool:
        return self._m.run_until(done, timeout)

    def status(self) -> dict[str, Any]:
        return self._m.status()


# -- starting the loop's process ------------------------------------------------------------------------------
def _child_env() -> dict[str, str]:
    """This process's environment, and one BLAS thread: the loop's cycle products are a few elements (host.py
    limits BLAS to the loop's thread; here no worker is even started)."""
    return {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def connect_process(cfg: Any, names: list[str], opts: dict[str, Any]) -> ProcessMachine:
    """Start the loop's process for ``cfg`` and return the user's side of it (session.connect's)."""
    opts = dict(opts)
    if opts.get("fault_dir") is not None:  # a relative folder is this process's
        opts["fault_dir"] = os.path.abspath(opts["fault_dir"])
    if opts.get("faults") is not None:
        opts["faults"] = list(opts["faults"])
    folder = tempfile.mkdtemp(prefix="drivectl-loop-")  # mode 0700: the socket is the user's own
    address = os.path.join(folder, "loop.sock")
    authkey = os.urandom(32)
    ctl_r, ctl_w = os.pipe()
    rep_r, rep_w = os.pipe()
    try:
        proc = subprocess.Popen([sys.executable, "-m", "drivectl.session_child", str(ctl_r), str(rep_w)],
                                pass_fds=(ctl_r, rep_w), stdin=subprocess.DEVNULL, env=_child_env(),
                                start_new_session=True)  # a Ctrl-C at the terminal is this process's to handle
    except BaseException:
        for fd in (ctl_r, ctl_w, rep_r, rep_w):
            os.close(fd)
        shutil.rmtree(folder, ignore_errors=True)
        raise
    os.close(ctl_r)
    os.close(rep_w)
    control, reply = Connection(ctl_w, readable=False), Connection(rep_r, writable=False)
    try:
        control.send({"config": cfg, "names": names, "opts": opts, "address": address, "authkey": authkey,
                      "parent": os.getpid(), "pdeathsig": threading.current_thread() is threading.main_thread()})
        if not reply.poll(START_TIMEOUT_S):
            raise AxisError(f"the servo loop's process did not start within {START_TIMEOUT_S:g} s")
        try:
            what, got = reply.recv()
        except EOFError:
            raise AxisError(f"the servo loop's process ended while starting (exit code {proc.wait(5)})") from None
        if what == "error":
            raise got
        client = _Client(address=address, authkey=authkey)
        client.connect()
        served = client.served()
    except BaseException:
        control.close()
        reply.close()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
        shutil.rmtree(folder, ignore_errors=True)
        raise
    reply.close()
    return ProcessMachine(proc, control, served, got, folder)


__all__ = ["ProcessMachine", "ProcessAxis", "ProcessMove", "ProcessCapture", "LoopGone", "CaptureError",
           "CHANNELS", "connect_process"]

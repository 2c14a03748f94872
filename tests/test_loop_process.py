"""Issue 39 point 1: the servo loop in a process of its own (session_child.py, session_process.py).

The loop's process runs the same ServoLoop as connect(loop="thread"); with the lockstep clock forwarded
(advance, waits, run_until) a move, a run and a capture through the process boundary give the in-process
trace bit for bit. Faults raised there arrive here as the same exceptions with the same messages; a parent
killed by SIGKILL leaves no loop process behind."""

from __future__ import annotations

import os
import subprocess
import sys
import time
import tomllib

import numpy as np
import pytest

import drivectl
from drivectl.controllers.runtime.capture import CaptureError
from drivectl.controllers.runtime.loop import MotionFault
from drivectl.controllers.runtime.servo import LimitError
from drivectl.driver.axis import AxisError
from drivectl.driver.cia402 import PowerState
from drivectl.machine.config import DEFAULT_CONFIG_TOML, ConfigError, parse_config
from drivectl.profiles.ptp import PointToPoint
from drivectl.session import Machine
from drivectl.session_process import ProcessMachine


def config(**top):
    data = tomllib.loads(DEFAULT_CONFIG_TOML)
    data["axes"]["x"]["controller"] = "pid-dob"
    data["axes"]["x"]["controller_settings"] = {}
    data.update(top)
    return parse_config(data, "<test>")


def session(m) -> dict:
    """A move, a profile run and a capture on x, lockstep: everything they recorded."""
    x = m.axes["x"]
    x.enable()
    m.advance(0.1)
    cap = x.capture(channels=("reference", "position", "following_error", "effort", "velocity", "torque",
                              "statusword"), trigger="move", pre=0.05, post=0.3)
    move = x.move_to(0.005).wait(5)
    run = x.run(PointToPoint(0.0, 0.003, 0.05, 0.5, 20.0, hold_until=0.3), relative=True).wait(5)
    m.advance(0.05)
    st = m.status()
    tr_cap, tr_run = cap.wait(1), run.trace
    return {"capture": tr_cap.columns, "run": tr_run.columns, "move": (move.status, move.position, move.cycles),
            "position": x.position, "following_error": x.following_error, "cycles": st["cycles"],
            "axis": {k: v for k, v in st["axes"]["x"].items()}, "capture_meta": tr_cap.meta["capture_trigger"]}


def test_lockstep_through_the_process_gives_the_in_process_trace_bit_for_bit(tmp_path):
    with drivectl.connect(config(), axes=["x"], fault_dir=tmp_path, loop="thread") as here:
        assert isinstance(here, Machine)
        a = session(here)
    with drivectl.connect(config(), axes=["x"], fault_dir=tmp_path, loop="process") as there:
        assert isinstance(there, ProcessMachine) and there.pid != os.getpid()
        assert there.clock == "lockstep"
        b = session(there)
    for what in ("capture", "run"):
        assert set(a[what]) == set(b[what])
        for col in a[what]:
            assert np.array_equal(np.asarray(a[what][col]), np.asarray(b[what][col])), (what, col)
    assert len(a["capture"]["time_s"]) == 50 + 1 + 300
    for key in ("move", "position", "following_error", "cycles", "axis", "capture_meta"):
        assert a[key] == b[key], key
    assert there.axes["x"].power is PowerState.SWITCH_ON_DISABLED  # verified there on the way out


def test_faults_and_refusals_in_the_loop_process_arrive_with_their_messages(tmp_path):
    said = {}
    for where in ("thread", "process"):
        got = said[where] = []
        with drivectl.connect(config(), axes=["x"], fault_dir=tmp_path / where, faults=["emcy-fault@0.3"],
                              loop=where) as m:
            x = m.axes["x"]
            with pytest.raises(AxisError) as e0:
                x.move_to(0.01)  # not enabled
            got.append(str(e0.value))
            x.enable()
            with pytest.raises(LimitError) as e1:
                x.move_to(1.0)
            got.append(str(e1.value))
            with pytest.raises(CaptureError) as e2:
                x.capture(pre=10, post=1)
            got.append(str(e2.value))
            h = x.move_to(0.05)
            with pytest.raises(MotionFault, match="drive fault") as e3:
                h.wait(2)
            got.append(str(e3.value))
            assert e3.value.fault.kind == "drive fault" and e3.value.fault.axis == "x"
            assert h.status == "fault" and h.fault is not None
            assert x.state == "off" and x.fault is not None and x.fault.kind == "drive fault"
            st = m.status()
            got.append(st["axes"]["x"]["fault"])
            assert st["faults"] == 1
            with pytest.raises(AxisError, match="fault_reset first") as e4:
                x.enable()
            got.append(str(e4.value))
            m.advance(0.5)  # the stop's end: the axis at rest
            x.fault_reset()
            x.enable()
            assert x.move_to(0.001).wait(5).status == "done"
    assert said["thread"] == said["process"]


def test_handles_dropped_here_are_forgotten_there(tmp_path):
    import gc

    with drivectl.connect(config(), axes=["x"], fault_dir=tmp_path, loop="process") as m:
        x = m.axes["x"]
        x.enable()
        for i in range(20):
            x.move_to(0.001 * (i % 3)).wait(5)
        gc.collect()
        kept = x.stop()  # the next call tells the loop's process which handles this side dropped
        assert m._call("kept") == 1 and kept.wait(5).status == "done"


def test_the_wall_clock_loop_process_moves_an_axis_and_says_what_it_was_granted(tmp_path, monkeypatch):
    """Outcome only, no timing asserted (a 50 ms RPDO deadline, as tests/test_session.py's threaded one)."""
    from drivectl.machine import live_status

    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    cfg = config()
    object.__setattr__(cfg.axis("x"), "rpdo_timeout_ms", 50)
    with drivectl.connect(cfg, axes=["x"], clock="wall", fault_dir=tmp_path, stall_s=1.0) as m:  # the default
        assert isinstance(m, ProcessMachine)
        x = m.axes["x"]
        x.enable()
        assert x.move_to(0.002).wait(timeout=20).status == "done"
        st = m.status()
        assert st["clock"].startswith("wall") and st["cycles"] > 100 and st["loop"] == "process"
        assert {"gc", "others", "memory", "process", "priority"} <= set(st["granted"])
        assert "none at all while an axis is enabled" in st["granted"]["gc"]
        assert m.loop.cycle >= st["cycles"] and m.loop.axes["x"].ring.count > 0
        published = live_status.read(cfg.bus)  # `drivectl status` elsewhere reads the loop's process
        assert published["pid"] == m.pid
    assert x.power is PowerState.SWITCH_ON_DISABLED
    assert m._proc.poll() == 0  # the loop's process ended with the close


def test_the_loop_key_of_the_configuration(tmp_path):
    with pytest.raises(ConfigError, match=r"^<test>: loop: expected one of process, thread, got 'sideways'$"):
        config(loop="sideways")
    with drivectl.connect(config(loop="thread"), axes=["x"], clock="wall", fault_dir=tmp_path, stall_s=1.0) as m:
        assert isinstance(m, Machine)  # the wall clock's loop a thread of this process, as the file says
    with pytest.raises(ValueError, match="connect: loop: expected one of process, thread, got 'elsewhere'"):
        drivectl.connect(config(), loop="elsewhere")


PARENT = """
import sys, time
import drivectl
m = drivectl.connect(axes=["x"], clock="wall", fault_dir=sys.argv[1], stall_s=1.0)
print(m.pid, flush=True)
time.sleep(600)
"""


def _gone(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] in ("Z", "X")  # a zombie: ended, not yet reaped
    except FileNotFoundError:
        return True


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc and PR_SET_PDEATHSIG")
def test_a_parent_killed_by_sigkill_leaves_no_loop_process(tmp_path):
    parent = subprocess.Popen([sys.executable, "-c", PARENT, str(tmp_path)], stdout=subprocess.PIPE, text=True)
    try:
        child = int(parent.stdout.readline())
        assert not _gone(child)
        parent.kill()  # SIGKILL: no close, no atexit
        parent.wait(30)
        deadline = time.monotonic() + 60  # generous: polling for an end, not timing it
        while not _gone(child) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert _gone(child), f"the loop's process {child} outlived its parent"
    finally:
        if parent.poll() is None:
            parent.kill()


def test_the_shell_through_the_loop_process_says_what_it_says_in_process(monkeypatch, capsys):
    import io

    from drivectl.tools.cli.main import main

    script = "enable x\nmove x 2mm\njog x 5mm/s 0.2s\nmove-by x -1mm\nstatus x\nwait 0.1s\nexit\n"
    said = {}
    for where in ("thread", "process"):
        monkeypatch.setattr(sys, "stdin", io.StringIO(script))
        rc = main(["shell", "--axis", "x", "--loop", where])
        out = capsys.readouterr()
        assert rc == 0, out.err
        said[where] = [ln for ln in out.out.splitlines() if ln]
        assert "closed: x Switch On Disabled" in out.err
    assert said["thread"] == said["process"] and len(said["process"]) == 7  # status: the axis, the loop


def test_the_scope_and_the_live_view_read_the_rings_in_shared_memory(tmp_path):
    from drivectl.tools.cli.live import sample
    from drivectl.tools.ui.stream import ScopeFeed

    got = {}
    for where in ("thread", "process"):
        with drivectl.connect(config(), axes=["x"], fault_dir=tmp_path, loop=where) as m:
            feed = ScopeFeed(m)
            feed.subscribe("x", ["reference", "position", "effort"], 1.0)
            m.axes["x"].enable()
            m.axes["x"].move_to(0.002)
            m.advance(0.3)
            first = feed.poll()
            m.advance(0.05)
            got[where] = (first, feed.poll(), sample(m, ("position", "following_error", "effort")))
    assert got["thread"] == got["process"]
    assert len(got["process"][1]["t"]) == 50  # only what came since the last poll


def test_a_loop_process_that_dies_is_said_so_and_the_close_does_not_hang(tmp_path, capsys):
    import signal

    from drivectl.session_process import LoopGone

    m = drivectl.connect(config(), axes=["x"], fault_dir=tmp_path, loop="process")
    x = m.axes["x"]
    os.kill(m.pid, signal.SIGKILL)
    m._proc.wait(30)
    with pytest.raises(LoopGone, match=r"the servo loop's process \(pid \d+\) ended \(exit code -9\); the drives' own"):
        x.enable()
    assert m.close() == {}
    assert "ended (exit code -9)" in capsys.readouterr().err

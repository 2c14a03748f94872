"""Issue 15 points 2-5: the resident loop and the Python API, against the emulated drives.

Lockstep clock (simulated time, deterministic) unless a test says otherwise; every connect() opens its
own virtual channel (machine/build.py: unique_virtual_channel)."""

from __future__ import annotations

import signal
import threading
import tomllib

import numpy as np
import pytest
from helpers import enabled_wall_loop

import drivectl
from drivectl.controllers.runtime.capture import CaptureError
from drivectl.controllers.runtime.loop import MotionFault
from drivectl.controllers.runtime.servo import LimitError
from drivectl.driver.axis import AxisError
from drivectl.driver.cia402 import PowerState
from drivectl.machine.config import DEFAULT_CONFIG_TOML, parse_config
from drivectl.profiles.ptp import PointToPoint
from drivectl.tracefile.format import Trace


def config(controller: str = "pid-dob", **motion: float):
    """The embedded machine with x under a controller with integral action (asmc holds ~4 um off
    against the x plant's Coulomb friction: no integrator), optional [axes.x.motion] keys."""
    data = tomllib.loads(DEFAULT_CONFIG_TOML)
    data["axes"]["x"]["controller"] = controller
    data["axes"]["x"]["controller_settings"] = {}
    if motion:
        data["axes"]["x"]["motion"] = motion
    return parse_config(data, "<test>")


@pytest.fixture
def machine(tmp_path):
    with drivectl.connect(config(), axes=["x"], fault_dir=tmp_path) as m:
        yield m


def test_enable_holds_position_and_status(machine):
    x = machine.axes["x"]
    assert x.power is PowerState.SWITCH_ON_DISABLED and x.state == "off"
    x.enable()
    assert x.power is PowerState.OPERATION_ENABLED and x.state == "servo"
    start = x.position
    machine.advance(0.5)
    assert abs(x.position - start) < 1e-6  # held under its controller
    st = machine.status()
    assert st["clock"].startswith("lockstep") and st["cycles"] > 500
    assert st["missed_deadlines"] == 0 and st["axes"]["x"]["state"] == "servo"


@pytest.mark.parametrize("target", [0.02, -0.015])
def test_move_to_and_move_by_end_within_1um(machine, target):
    x = machine.axes["x"]
    x.enable()
    h = x.move_to(target).wait(timeout=5)
    assert h.status == "done" and h.settled, h.detail
    machine.advance(0.2)
    assert abs(x.position - target) < 1e-6
    h = x.move_by(0.004).wait(timeout=5)
    assert h.settled
    machine.advance(0.2)
    assert abs(x.position - (target + 0.004)) < 1e-6


def test_jog_stops_by_itself_unless_renewed(machine):
    x = machine.axes["x"]
    x.enable()
    j = x.jog(0.01)
    machine.advance(0.15)
    assert x.velocity == pytest.approx(0.01, rel=0.05)
    machine.advance(0.5)  # not renewed: the dead man (0.2 s) stopped it
    assert j.done and j.status == "stopped"
    assert abs(x.velocity) < 1e-4
    travelled = x.position
    assert 0.0018 < travelled < 0.0025  # 0.2 s at 10 mm/s, plus the braking
    # renewed every 0.1 s for 1 s: it keeps moving the whole time
    j = x.jog(-0.01)
    for _ in range(10):
        machine.advance(0.1)
        assert x.velocity == pytest.approx(-0.01, rel=0.05)
        assert x.jog(-0.01) is j
    assert not j.done
    x.stop().wait(1)
    machine.advance(0.1)
    assert j.status == "stopped" and abs(x.velocity) < 1e-4
    assert x.position == pytest.approx(travelled - 0.0100, abs=0.0006)


def test_jog_stops_in_front_of_the_soft_limit(tmp_path):
    with drivectl.connect(config(max_velocity_m_s=0.2), axes=["x"], fault_dir=tmp_path) as m:
        x = m.axes["x"]
        x.enable()
        j = x.jog(0.2)
        for _ in range(12):
            m.advance(0.1)
            x.jog(0.2)
        lo, hi = x.limits.position
        assert j.done and x.state == "servo"  # stopped at the limit, no fault
        assert hi - 0.0011 < x.position < hi
        held = x.jog(0.01)  # the button still held at the limit: nothing moves, nothing raises
        assert held.done and "at the soft limit already" in held.detail
        x.jog(-0.01)  # away from it is fine
        m.advance(0.1)
        assert x.velocity < 0


def test_an_axis_enabled_outside_its_soft_limits_is_held_and_may_only_go_back_in(tmp_path):
    data = tomllib.loads(DEFAULT_CONFIG_TOML)
    data["axes"]["x"]["limits"]["position_m"] = [0.001, 0.1]  # x stands at 0: 1 mm below its lower limit
    with drivectl.connect(parse_config(data, "<test>"), axes=["x"], fault_dir=tmp_path) as m:
        x = m.axes["x"]
        x.enable()
        m.advance(0.5)
        assert x.state == "servo" and x.power is PowerState.OPERATION_ENABLED  # held, no soft-limit fault
        assert x.jog(-0.01).detail.startswith("at the soft limit already")  # further out: nothing moves
        with pytest.raises(LimitError, match="outside the soft limits"):
            x.move_to(-0.002)
        x.jog(0.01)  # inward: allowed, and the ratchet follows it in
        m.advance(0.05)
        assert x.velocity > 0 and x.state == "servo" and x.position < 0.001
        x.move_to(0.005).wait(5.0)  # a move's target must be inside, as always
        assert x.state == "servo" and x.position == pytest.approx(0.005, abs=1e-5)


def test_outside_the_soft_limits_only_a_step_further_out_is_a_fault():
    from types import SimpleNamespace

    from drivectl.controllers.runtime.cycle import OUTSIDE_SLACK_M, _further_out

    lim = (0.001, 0.1)
    ch = SimpleNamespace(outside_mark=None)
    assert _further_out(ch, 0.0005, lim, taken=False)  # left the limits while checked: a fault at once
    assert not _further_out(ch, 0.0, lim, taken=True) and ch.outside_mark == 0.0  # taken up outside: held
    assert not _further_out(ch, 0.0004, lim, taken=False) and ch.outside_mark == 0.0004  # inward: the ratchet
    assert not _further_out(ch, 0.0004 - OUTSIDE_SLACK_M * 0.9, lim, taken=False)  # standing, within the slack
    assert _further_out(ch, 0.0004 - OUTSIDE_SLACK_M * 1.1, lim, taken=False)  # running away outward
    ch = SimpleNamespace(outside_mark=None)
    assert not _further_out(ch, 0.2, lim, taken=True)  # above the upper limit: the same, mirrored
    assert _further_out(ch, 0.2 + OUTSIDE_SLACK_M * 1.1, lim, taken=False)


def test_a_jog_renewed_while_its_dead_man_stop_is_under_way_moves_on(machine):
    x = machine.axes["x"]
    x.enable()
    j = x.jog(0.02)
    machine.advance(0.215)  # 0.2 s: the dead man began the stop (about 40 ms long); the axis decelerates
    assert 0 < x.velocity < 0.02 and not j.done
    assert x.jog(0.02) is j
    machine.advance(0.15)
    assert x.velocity == pytest.approx(0.02, rel=0.05)


def test_moves_outside_the_limits_are_refused_before_anything_moves(machine):
    x = machine.axes["x"]
    with pytest.raises(AxisError, match="not enabled"):
        x.move_to(0.01)
    x.enable()
    with pytest.raises(LimitError, match=r"outside the soft limits \[-0.1, 0.1\]"):
        x.move_to(0.5)
    with pytest.raises(LimitError, match="max_velocity"):
        x.jog(5.0)
    machine.advance(0.1)
    assert abs(x.position) < 1e-6


def test_stop_is_controlled_and_the_axis_holds(machine):
    x = machine.axes["x"]
    x.enable()
    h = x.move_to(0.05)
    machine.advance(0.3)
    s = x.stop().wait(1)
    assert h.status == "stopped" and s.status == "done"
    assert 0.005 < x.position < 0.05 and abs(x.velocity) < 1e-4
    here = x.position
    machine.advance(0.3)
    assert abs(x.position - here) < 2e-6


def test_relative_run_of_a_profile(machine):
    x = machine.axes["x"]
    x.enable()
    x.move_to(0.01).wait(5)
    prof = PointToPoint(0.0, 0.005, 0.05, 0.5, 20.0, hold_until=0.4)
    with pytest.raises(LimitError, match="starts at"):
        x.run(prof)  # absolute: the axis is not at the start
    with pytest.raises(LimitError, match=r"velocity 0.44\d+ exceeds the axis's max_velocity_m_s 0.1"):
        x.run(PointToPoint(0.0, 0.05, 0.5, 5.0, 200.0), relative=True)
    h = x.run(prof, relative=True, record=machine.loop.fault_dir).wait(5)
    assert h.status == "done"
    tr = h.trace
    streamed = Trace.read(h.path)
    assert streamed.meta["stop"] == "done" and np.allclose(streamed.pos, tr.pos, rtol=0, atol=1e-9)
    assert isinstance(tr, Trace) and len(tr) == round(0.4 / 0.001) + 1
    assert tr.ref[0] == pytest.approx(0.01, abs=1e-9) and tr.ref[-1] == pytest.approx(0.015, abs=1e-9)
    assert np.max(np.abs(tr.error)) < 50e-6
    machine.advance(0.2)
    assert abs(x.position - 0.015) < 1e-6


def test_absolute_run_with_approach(machine):
    x = machine.axes["x"]
    x.enable()
    prof = PointToPoint(0.01, 0.0, 0.05, 0.5, 20.0, hold_until=0.3)
    h = x.run(prof, approach=True).wait(5)
    assert h.status == "done" and h.trace.ref[0] == pytest.approx(0.01)
    assert abs(h.trace.pos[0] - 0.01) < 5e-6  # the approach ended at the start


def test_capture_on_a_move_start(machine, tmp_path):
    x = machine.axes["x"]
    x.enable()
    cap = x.capture(channels=("reference", "position", "following_error", "velocity", "torque", "statusword"),
                    trigger="move", pre=0.05, post=0.2)
    machine.advance(0.1)
    assert not cap.done  # armed: no move yet
    x.move_to(0.005)
    tr = cap.wait(1)
    assert len(tr) == 50 + 1 + 200
    assert tr.time[50] == 0.0 and tr.time[0] == pytest.approx(-0.05)
    assert np.all(tr.ref[:50] == 0.0) and tr.ref[50] >= 0.0 and tr.ref[-1] > 0.0
    assert {"following_error_m", "vel_m_s", "torque_actual", "statusword"} <= set(tr.columns)
    assert np.all(tr.columns["statusword"][:] == tr.columns["statusword"][0])
    paths = cap.write(tmp_path / "cap.csv")
    assert Trace.read(paths[0]).meta["capture_trigger"] == "move" and paths[1].suffix == ".png"
    with pytest.raises(CaptureError, match="longer than the ring"):
        x.capture(pre=10, post=1)


def test_level_trigger_capture(machine):
    x = machine.axes["x"]
    x.enable()
    cap = x.capture(trigger="position>0.002", pre=0.01, post=0.01)
    x.move_to(0.004).wait(5)
    tr = cap.wait(1)
    assert tr.pos[9] < 0.002 <= tr.pos[10]


def test_capture_around_an_injected_fault_and_the_fault_ring_on_disk(tmp_path):
    with drivectl.connect(config(), axes=["x"], fault_dir=tmp_path, faults=["emcy-fault@0.3"]) as m:
        x = m.axes["x"]
        cap = x.capture(trigger="fault", pre=0.2)
        x.enable()
        h = x.move_to(0.05)
        with pytest.raises(MotionFault, match="drive fault") as exc:
            h.wait(2)
        assert exc.value.fault.kind == "drive fault"
        assert exc.value.fault.safe_state["x"] in ("Fault", "Switch On Disabled")
        assert x.state == "off" and x.fault is not None
        tr = cap.wait(1)  # the post-trigger samples (0.5 s by default) follow the fault: the stop, and after
        # 0.2 s before, 0.5 s after; the detecting cycle has no sample of x (its drive was in Fault)
        assert len(tr) == 700 and tr.time[0] == pytest.approx(-0.2) and tr.time[200] == 0.0
        assert tr.time[-1] == pytest.approx(0.5)
        assert tr.ref[200] > 0 and "drive fault" in tr.meta["capture_detail"]
        assert tr.meta["capture_post_samples"] == "500"
        assert abs(tr.pos[-1] - tr.pos[-100]) < 1e-6  # it shows the axis brought to rest
        files = m.loop.flush()
        assert len(files) == 1 and files[0].name.startswith("x-fault-")  # the armed capture, on disk
        assert len(Trace.read(files[0])) == 700
        with pytest.raises(AxisError, match="fault_reset first"):
            x.enable()
        x.fault_reset()
        x.enable()
        x.move_to(0.001).wait(5)


def test_ctrl_c_during_a_move_stops_it_and_the_context_disables(tmp_path):
    m = drivectl.connect(config(), axes=["x"], fault_dir=tmp_path)
    x = m.axes["x"]
    inner = m.loop.axes["x"].ch.controller
    calls = {"n": 0}
    step = inner.step

    def step_with_signal(ref, fb):
        calls["n"] += 1
        if calls["n"] == 200:
            signal.raise_signal(signal.SIGINT)  # as if Ctrl-C came in the middle of the cycle
        return step(ref, fb)

    inner.step = step_with_signal
    with pytest.raises(KeyboardInterrupt):
        with m:
            x.enable()
            h = x.move_to(0.05)
            h.wait(5)
    assert h.status == "stopped" and "SIGINT" in h.detail
    assert x.power is PowerState.SWITCH_ON_DISABLED
    assert abs(x.position) < 0.05  # it did not finish the move


def test_an_exception_inside_the_context_disables_every_axis(tmp_path):
    with pytest.raises(ZeroDivisionError):
        with drivectl.connect(config(), axes=["x", "y"], fault_dir=tmp_path) as m:
            for ax in m.axes.values():
                ax.enable()
            m.axes["x"].move_to(0.01)
            m.advance(0.05)
            raise ZeroDivisionError("a bug in the user's program")
    assert all(ax.power is PowerState.SWITCH_ON_DISABLED for ax in m.axes.values())
    assert m.hardware.axes["x"].network.bus is None  # the bus is shut down


def test_wall_clock_loop_moves_and_counts_deadlines(tmp_path, monkeypatch):
    """The threaded loop on the wall clock (loop="thread"; tests/test_loop_process.py has the loop's own process):
    outcome only (no timing asserted). The drive's RPDO deadline runs
    on the wall clock too; 50 ms here so that a loaded test machine's hiccups are not this test's subject."""
    import os

    from drivectl.machine import live_status

    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    cfg = config()
    object.__setattr__(cfg.axis("x"), "rpdo_timeout_ms", 50)
    was = (os.sched_getscheduler(0), os.getpriority(os.PRIO_PROCESS, 0))
    with drivectl.connect(cfg, axes=["x"], clock="wall", fault_dir=tmp_path, stall_s=1.0, loop="thread") as m:
        x = m.axes["x"]
        x.enable()
        h = x.move_to(0.002).wait(timeout=20)
        assert h.status == "done"
        st = m.status()
        assert st["clock"].startswith("wall") and st["cycles"] > 100
        assert {"missed_deadlines", "worst_late_ms", "stalls", "gc_collections"} <= set(st)
        assert "gc" in st["granted"] and "others" in st["granted"]
        assert "paced on the wall clock" in st["bus"]
        published = live_status.read(cfg.bus)  # written as the loop starts, for `drivectl status` elsewhere
        assert published["pid"] == os.getpid() and "x" in published["axes"] and "p99_99" in published["latency_ms"]
        if st["granted"]["others"].startswith("the process's other threads at SCHED_FIFO"):
            policy = os.sched_getscheduler(0)  # this (the program's) thread, below the loop, not to its children
            assert policy & ~os.SCHED_RESET_ON_FORK == os.SCHED_FIFO and policy & os.SCHED_RESET_ON_FORK
            # a thread the program starts later (a poller, a console's server) is raised as it starts
            seen: list[int] = []
            t = threading.Thread(target=lambda: seen.append(os.sched_getscheduler(0) & ~os.SCHED_RESET_ON_FORK))
            t.start()
            t.join()
            assert seen == [os.SCHED_FIFO]
    assert x.power is PowerState.SWITCH_ON_DISABLED
    assert threading.getprofile() is None  # the hook that raised new threads is gone with the last loop
    assert live_status.read(cfg.bus) is None  # removed at close
    # the last loop put back what it changed (controllers/runtime/host.py)
    assert (os.sched_getscheduler(0), os.getpriority(os.PRIO_PROCESS, 0)) == was


def homing_config(method: str, **homing):
    data = tomllib.loads(DEFAULT_CONFIG_TOML)
    x = data["axes"]["x"]
    x["controller"], x["controller_settings"] = "pid-dob", {}
    x["homing"] = {"method": method, **homing}
    # the emulated drive: home switch active at and below -12 mm, mechanical stop at -30 mm
    x["emulator"] = {"home_switch_m": -0.012, "limit_switches_m": [-0.095, 0.095], "hard_stops_m": [-0.03, 0.12]}
    return parse_config(data, "<test>")


def test_home_here_sets_the_coordinates(tmp_path):
    with drivectl.connect(homing_config("here", position_m=0.05), axes=["x"], fault_dir=tmp_path,
                          start={"x": 0.003}) as m:
        x = m.axes["x"]
        x.enable()
        h = x.home().wait(1)
        assert h.status == "done"
        assert x.position == pytest.approx(0.05, abs=1e-6)
        x.move_by(0.01).wait(5)
        m.advance(0.2)
        assert x.position == pytest.approx(0.06, abs=1e-6)
        assert m.hardware.drives["x"].drive.position == pytest.approx(0.013, abs=2e-6)  # the drive's own


def test_home_on_the_home_switch_from_0x60FD(tmp_path):
    with drivectl.connect(homing_config("switch", position_m=0.0, speed_m_s=0.02), axes=["x"],
                          fault_dir=tmp_path, start={"x": 0.01}) as m:
        x = m.axes["x"]
        assert m.hardware.drives["x"].drive.digital_inputs() == 0
        x.enable()
        h = x.home().wait(1)
        assert h.status == "done", h.detail
        m.advance(0.2)
        drive = m.hardware.drives["x"].drive
        # home (0.0) is the switch's edge at -12 mm of the drive, to a creep cycle (1 mm/s x 1 ms)
        assert drive.position == pytest.approx(-0.012, abs=3e-6)
        assert x.position == pytest.approx(0.0, abs=3e-6)
        x.move_by(0.001).wait(5)
        assert drive.digital_inputs() & 4 == 0  # off the cam
        x.move_by(-0.002).wait(5)
        assert drive.digital_inputs() & 4 == 4  # on it
        # the soft limits hold again after homing
        with pytest.raises(LimitError):
            x.move_to(0.2)


def test_home_against_the_hard_stop_by_following_error(tmp_path):
    with drivectl.connect(homing_config("hard-stop", position_m=-0.02, speed_m_s=0.005, hard_stop_effort=300.0),
                          axes=["x"], fault_dir=tmp_path, start={"x": -0.025}) as m:
        x = m.axes["x"]
        x.enable()
        h = x.home().wait(1)
        assert h.status == "done", h.detail
        m.advance(0.2)
        drive = m.hardware.drives["x"].drive
        # the stop (-30 mm of the drive) is -20 mm of the axis; it backed off 1 mm
        assert x.position == pytest.approx(-0.019, abs=2e-6)
        assert drive.position == pytest.approx(-0.029, abs=1e-5)
        assert x.state == "servo" and x.limits.following_error == 0.001  # limits restored


def test_homing_switch_not_found_is_one_error(tmp_path):
    with drivectl.connect(homing_config("switch", direction="positive", max_travel_m=0.01), axes=["x"],
                          fault_dir=tmp_path) as m:
        x = m.axes["x"]
        x.enable()
        with pytest.raises(Exception, match="home switch not found within 10 mm"):
            x.home().wait(1)
        assert x.state == "servo"


def test_approach_plans_a_visible_move_to_the_profile_start_and_the_run_follows():
    from drivectl.controllers.registry import make_controller
    from drivectl.controllers.runtime.approach import plan_approach, where_axes_stand
    from drivectl.controllers.runtime.servo import Channel, plan_run, run_channels
    from drivectl.plant_emulator.models import load_plant
    from drivectl.plant_emulator.sim_axis import SimAxis
    from drivectl.tools.cli.approach import consent

    cfg = config()
    spec = load_plant("rigid-x")
    axis = SimAxis(spec.build(0.001), initial_position=0.03)
    ctrl = make_controller("pid-dob", 0.001, {}, plant=spec, axis="x")
    prof = PointToPoint(0.0, 0.005, 0.05, 0.5, 20.0, hold_until=0.3)
    ch = Channel(axis, ctrl, prof, cfg.axis("x").limits)
    approach, moves = plan_approach([ch], where_axes_stand([ch]), {"x": cfg.axis("x").motion})
    assert moves == ["approach: axis x from 30.000 mm to its profile's start 0.000 mm (30.000 mm, 0.42 s at up "
                     "to 100 mm/s)"]
    with pytest.raises(LimitError, match="--no-approach; nothing moved"):
        consent(False, moves)
    with pytest.raises(LimitError, match="use --approach"):
        consent(None, moves)  # no terminal here: refused, naming the flag
    assert axis.power is PowerState.SWITCH_ON_DISABLED
    consent(True, moves)
    plan = plan_run([ch])
    first = run_channels(approach, disable_at_end=False)
    assert first.ok and abs(first.trace.pos[-1]) < 5e-6
    res = run_channels(plan)
    assert res.ok and abs(res.trace.pos[0]) < 5e-6 and abs(res.trace.pos[-1] - 0.005) < 5e-6


def test_a_stalled_wall_clock_loop_is_a_fault_and_stops_the_axis():
    """The stall is injected through the loop's clock (a jump of 10 s between two cycles), so the
    outcome does not depend on how busy the machine is."""

    from drivectl.controllers.registry import make_controller
    from drivectl.controllers.runtime.loop import AxisState
    from drivectl.controllers.runtime.servo import Channel
    from drivectl.plant_emulator.models import load_plant
    from drivectl.plant_emulator.sim_axis import SimAxis

    spec = load_plant("rigid-x")
    axis = SimAxis(spec.build(0.001), name="x")
    ch = Channel(axis, make_controller("pid-dob", 0.001, {}, plant=spec, axis="x"), None, config().axis("x").limits)
    loop, jump = enabled_wall_loop(ch, stall_s=5.0)
    try:
        rt = loop.axes["x"]
        jump["s"] = 10.0  # the next cycle starts 10 s after the last one, as far as the loop can tell
        assert loop.run_until(lambda: loop.faults, 10.0)
        fault = loop.faults[0]
        assert fault.kind == "servo loop stalled" and "no cycle for 100" in fault.detail
        assert fault.safe_state["x"] in ("Switch On Disabled", "Quick Stop Active")
        assert rt.state is AxisState.OFF and loop.status()["stalls"] == 1
    finally:
        loop.close()
    assert axis.power is PowerState.SWITCH_ON_DISABLED


def test_a_controller_that_raises_stops_every_axis_instead_of_killing_the_loop(machine):
    x = machine.axes["x"]
    x.enable()
    h = x.move_to(0.01)
    machine.advance(0.05)

    def broken(ref, fb):
        raise FloatingPointError("nan in the state")

    machine.loop.axes["x"].ch.controller.step = broken
    with pytest.raises(MotionFault, match="FloatingPointError"):
        h.wait(1)
    assert x.state == "off" and x.power in (PowerState.SWITCH_ON_DISABLED, PowerState.QUICK_STOP_ACTIVE)
    machine.advance(0.05)  # the loop goes on cycling the (disabled) axis
    assert machine.status()["faults"] == 1


def test_the_last_seconds_before_any_fault_are_on_disk_without_asking(tmp_path):
    with drivectl.connect(config(), axes=["x", "y"], fault_dir=tmp_path, faults=["y/emcy-fault@0.4"],
                          ring_s=0.25) as m:
        for ax in m.axes.values():
            ax.enable()
        h = m.axes["x"].move_to(0.02)
        with pytest.raises(MotionFault):
            h.wait(2)
        files = sorted(m.loop.flush())
    assert [f.name.split("-fault-")[0] for f in files] == ["x", "y"]  # every axis, the ring's last 0.25 s
    tr = Trace.read(files[0])
    assert len(tr) == 250 and tr.time[-1] == 0.0 and tr.pos[-1] > 0.0
    assert "emcy" in tr.meta["capture_detail"] or "drive fault" in tr.meta["capture_detail"]
    assert {"following_error_m", "torque_actual", "statusword"} <= set(tr.columns)


def test_a_drive_that_does_not_confirm_the_disable_is_named_on_close(tmp_path, capsys):
    m = drivectl.connect(config(), axes=["x"], fault_dir=tmp_path)
    with m:
        m.axes["x"].enable()
        m.loop.axes["x"].ch.axis.disable = lambda: None  # the command never reaches the drive
    assert m.unconfirmed == ["x"]
    err = capsys.readouterr().err
    assert "axis x: the drive last reported Operation Enabled after the disable: it may still be powered" in err


def test_identify_refuses_an_axis_away_from_its_start_without_approach(monkeypatch):
    """identify opens the axis where its identification profile starts; a drive standing elsewhere
    (as across processes) is shown the approach and, with --no-approach, refused before it moves."""
    from drivectl.machine import build as machine_module
    from drivectl.machine.config import load_config
    from drivectl.tools.commissioning.commands import identify_axis

    opened = []
    real = machine_module.open_machine

    def elsewhere(cfg, names, **kw):
        kw["start"] = {n: p + 0.005 for n, p in kw["start"].items()}  # 5 mm off
        opened.append(real(cfg, names, **kw))
        return opened[-1]

    monkeypatch.setattr(machine_module, "open_machine", elsewhere)
    with pytest.raises(LimitError, match=r"to its profile's start .*--no-approach; nothing moved"):
        identify_axis(load_config(None), "x", approach=False)
    assert opened and opened[0].drives["x"].drive.power is PowerState.SWITCH_ON_DISABLED


def test_a_resident_run_gives_the_controller_the_preview_a_trace_gives(tmp_path):
    # z under mbc: its feed-forward needs the reference ahead of the transport delay (Controller.prepare in
    # a one-shot trace). The resident loop's run must give it the same preview: without it mbc extrapolates
    # the reference (0.65 um max, 0.14 um rms here against the trace's 0.50 / 0.073)
    from drivectl.controllers.registry import make_controller
    from drivectl.controllers.runtime.servo import run
    from drivectl.machine.build import open_machine
    from drivectl.machine.config import load_config
    from drivectl.plant_emulator.models import load_plant

    cfg = load_config()
    assert cfg.axis("z").controller == "mbc"
    prof = PointToPoint(0.0, 0.065, 0.1, 1.0, 40.0, hold_until=1.0)  # paper 000's move, a shorter hold
    with open_machine(cfg, ["z"], start={"z": 0.0}) as m:
        ctrl = make_controller("mbc", cfg.cycle_s, {}, plant=load_plant("two-mass"), axis="z")
        one_shot = run(m.axes["z"], ctrl, prof, limits=cfg.axis("z").limits).trace.error
    with drivectl.connect(cfg, axes=["z"], start={"z": 0.0}, fault_dir=tmp_path) as machine:
        z = machine.axes["z"]
        z.enable()
        machine.advance(0.1)
        h = z.run(prof).wait(10)
        # a relative run: the preview follows the shifted reference (0.65 / 0.14 um if it did not)
        back = z.run(PointToPoint(0.0, -0.03, 0.1, 1.0, 40.0, hold_until=1.0), relative=True).wait(10)
    assert h.status == "done" and back.status == "done"
    resident = h.trace.error
    assert len(resident) == len(one_shot)
    rms = {k: float(np.sqrt(np.mean(e**2))) for k, e in (("resident", resident), ("one_shot", one_shot),
                                                          ("relative", back.trace.error))}
    assert rms["resident"] < 1.25 * rms["one_shot"] and rms["relative"] < 1.25 * rms["one_shot"]
    assert np.max(np.abs(resident)) < np.max(np.abs(one_shot)) + 0.1e-6


def test_the_wall_clock_loop_runs_blas_on_one_thread_and_gives_the_pool_back():
    """Issue 29: no BLAS worker spinning beside the loop while it runs; what was set before comes back."""
    from threadpoolctl import threadpool_info

    from drivectl.controllers.registry import make_controller
    from drivectl.controllers.runtime.servo import Channel
    from drivectl.plant_emulator.models import load_plant
    from drivectl.plant_emulator.sim_axis import SimAxis

    def blas_threads() -> dict[str, int]:  # by library: the loop's imports may load another one (scipy's)
        return {p["filepath"]: p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"}

    before = blas_threads()
    spec = load_plant("rigid-x")
    axis = SimAxis(spec.build(0.001), name="x")
    ch = Channel(axis, make_controller("pid-dob", 0.001, {}, plant=spec, axis="x"), None, config().axis("x").limits)
    loop, _jump = enabled_wall_loop(ch)
    try:
        during = blas_threads()
        assert during and set(during.values()) == {1} and "blas" in loop.granted
    finally:
        loop.close()
    after = blas_threads()
    assert {f: after[f] for f in before} == before

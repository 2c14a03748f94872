"""SIGINT/SIGTERM end a run at a cycle boundary: the handler never raises into the cycle (a
KeyboardInterrupt raised inside a CAN queue's lock once hung the quick stop with the drive enabled)."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import threading

import pytest
from helpers import PdController, SineProfile

from drivectl.controllers.registry import make_controller
from drivectl.controllers.runtime.interrupt import StopRequest, stop_on_signals
from drivectl.controllers.runtime.servo import Channel, Limits, StopReason, run, run_channels
from drivectl.driver.cia402 import PowerState
from drivectl.machine.build import open_machine
from drivectl.machine.config import load_config
from drivectl.plant_emulator.models import load_plant
from drivectl.plant_emulator.sim_axis import SimAxis
from drivectl.profiles.library import load_profile

DT = 0.001


class _SignalAt(PdController):
    """Raises a real signal from inside the cycle (as if it arrived there) and finishes the step."""

    def __init__(self, dt: float, at: int, signum: int = signal.SIGINT):
        super().__init__(dt)
        self.at, self.signum, self.calls, self.finished = at, signum, 0, []

    def step(self, reference, feedback):
        self.calls += 1
        if self.calls == self.at:
            signal.raise_signal(self.signum)  # the Python handler runs at the next bytecode, right here
            self.finished.append(self.calls)  # with the old raising handler this line never ran
        return super().step(reference, feedback)


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_inside_a_cycle_lets_the_cycle_finish_then_stops(signum):
    axis = SimAxis(load_plant("rigid-x").build(DT))
    ctrl = _SignalAt(DT, 300, signum)
    before = signal.getsignal(signum)
    res = run(axis, ctrl, SineProfile(0.01, 1.0, 1.0))
    assert ctrl.finished == [300]
    assert res.stop is StopReason.INTERRUPTED and signal.Signals(signum).name in res.detail
    assert len(res.trace) == 300  # the cycle the signal arrived in is recorded whole
    assert ctrl.calls == 300  # and no further cycle ran
    assert axis.power is PowerState.SWITCH_ON_DISABLED
    meta = res.trace.meta
    assert meta["fault_kind"] == "interrupted" and meta["safe_state"] == "Switch On Disabled"
    # docs/faults.md's bound: seen at the next cycle boundary (cycle 300), torque off one cycle later
    assert meta["fault_cycle"] == "300" and meta["safe_after_cycles"] == "1"
    assert signal.getsignal(signum) is before  # the run's own handler is gone again


def test_a_signal_inside_a_canopen_send_does_not_tear_the_frame():
    """On the emulated CiA 402 drive: the signal arrives inside the master's RPDO send; that frame
    still goes out, the drive sees the cycle, and the quick stop reaches it."""
    cfg = load_config(None)
    prof = load_profile("short-move")
    m = open_machine(cfg, ["x"], start={"x": prof.start_position})
    with m:
        axis, drive = m.axes["x"], m.drives["x"]
        ac = cfg.axis("x")
        inner = make_controller(ac.controller, cfg.cycle_s, ac.controller_settings, plant=m.specs["x"], axis="x")
        send = axis.network.send_message
        armed, sent_after = [False], []

        def send_with_signal(can_id, data, remote=False):
            if armed[0]:
                armed[0] = False
                signal.raise_signal(signal.SIGTERM)
                sent_after.append(can_id)
            return send(can_id, data, remote)

        class Arming(type(inner)):
            calls = 0

            def step(self, reference, feedback):
                Arming.calls += 1
                if Arming.calls == 200:
                    armed[0] = True  # the next frame the master sends is this cycle's RPDO
                return super().step(reference, feedback)

        inner.__class__ = Arming
        axis.network.send_message = send_with_signal
        syncs0 = drive.drive.syncs
        res = run_channels([Channel(axis, inner, prof, ac.limits)])
        assert sent_after, "the signal was never raised"
        assert res.stop is StopReason.INTERRUPTED and "SIGTERM" in res.detail
        assert len(res.trace) == 200
        assert drive.drive.power is PowerState.SWITCH_ON_DISABLED  # the drive's own state, not the master's
        assert drive.drive.syncs > syncs0 + 200


def test_a_signal_before_the_run_enables_nothing():
    axis = SimAxis(load_plant("rigid-x").build(DT))
    request = StopRequest()
    request.handle(signal.SIGINT)
    res = run_channels([Channel(axis, PdController(DT), SineProfile(0.01, 1.0, 1.0), Limits())],
                       stop_request=request)
    assert res.stop is StopReason.INTERRUPTED and not res.enabled and len(res.trace) == 0
    assert "before the axes were enabled" in res.detail
    assert axis.power is PowerState.SWITCH_ON_DISABLED and axis.drive.syncs == 0  # not one cycle ran


def test_a_run_in_another_thread_needs_no_signal_handlers():
    """Handlers can only be set from the main thread: a run elsewhere must not try."""
    out = []
    axis = SimAxis(load_plant("rigid-x").build(DT))
    worker = threading.Thread(target=lambda: out.append(run(axis, PdController(DT), SineProfile(0.01, 1.0, 0.2))))
    worker.start()
    worker.join()
    assert out and out[0].ok, out


def test_handlers_are_restored_after_the_block_even_on_error():
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    with pytest.raises(RuntimeError), stop_on_signals() as request:
        assert signal.getsignal(signal.SIGINT) == request.handle
        raise RuntimeError("boom")
    assert {s: signal.getsignal(s) for s in before} == before


def test_second_signal_says_stopping_third_kills():
    code = textwrap.dedent("""
        import signal, sys
        from drivectl.controllers.runtime.interrupt import stop_on_signals
        with stop_on_signals() as request:
            for n in (1, 2, 3):
                signal.raise_signal(signal.SIGINT)
                print(n, request.name, request.count, flush=True)
        print("not reached", flush=True)
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == -signal.SIGINT, proc.stderr
    assert proc.stdout.splitlines() == ["1 SIGINT 1", "2 SIGINT 2"]
    assert proc.stderr.count("signal once more to kill at once") == 1


def test_identify_interrupted_during_set_up_moves_nothing_and_exits_130(tmp_path, capsys, monkeypatch):
    """The command routes the signals for its whole length: a signal after the bus is set up and
    before the identification run is seen by the run before it enables anything (a run's own routing
    would have missed it, and the run would have gone ahead)."""
    from drivectl.controllers.runtime import servo
    from drivectl.tools.cli.main import main

    real_run, calls = servo.run, []

    def run_after_a_signal(*args, **kwargs):
        calls.append(1)
        if len(calls) == 1:
            signal.raise_signal(signal.SIGINT)
        return real_run(*args, **kwargs)

    monkeypatch.setattr(servo, "run", run_after_a_signal)
    before = signal.getsignal(signal.SIGINT)
    rc = main(["identify", "--axis", "x", "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert rc == 130, err
    assert len(calls) == 1
    assert err.count("\n") == 1 and "interrupted (SIGINT) before the axes were enabled" in err
    assert list(tmp_path.iterdir()) == []  # no identified plant written
    assert signal.getsignal(signal.SIGINT) is before


def test_ctrl_c_in_offline_work_is_one_line_and_130(tmp_path, capsys, monkeypatch):
    """Where no drive is involved (tune's search, explain, plot) Ctrl-C ends the work at once."""
    from drivectl.tools.cli import main as cli

    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "cmd_plot", interrupted)
    rc = cli.main(["plot", str(tmp_path / "x.csv")])
    err = capsys.readouterr().err
    assert rc == 130 and err == "drivectl: plot: interrupted\n"

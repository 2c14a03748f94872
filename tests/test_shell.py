"""drivectl shell driven through standard input (a script), on the emulated drives in lockstep."""

from __future__ import annotations

import io
import os
import signal
import subprocess
import sys

import pytest

from drivectl.tools.cli.main import main
from drivectl.tools.cli.quantity import QuantityError, parse_quantity
from drivectl.tracefile.format import Trace


def shell(monkeypatch, capsys, script: str, *args: str) -> tuple[int, list[str], str]:
    monkeypatch.setattr(sys, "stdin", io.StringIO(script))
    rc = main(["shell", "--axis", "x", *args])
    cap = capsys.readouterr()
    return rc, [ln for ln in cap.out.splitlines() if ln], cap.err


def position_mm(line: str) -> float:
    return float(line.split(" at ")[1].split(" mm")[0])


def test_quantities_take_only_their_units():
    assert parse_quantity("20mm", "position") == pytest.approx(0.02)
    assert parse_quantity("-5 mm/s", "velocity") == pytest.approx(-0.005)
    assert parse_quantity("250ms", "time") == pytest.approx(0.25)
    for bad, kind in (("20", "position"), ("5mm/s", "position"), ("5mm", "velocity"), ("nan mm", "position"),
                      ("", "time")):
        with pytest.raises(QuantityError):
            parse_quantity(bad, kind)


def test_script_enable_move_jog_and_exit_disables(monkeypatch, capsys, tmp_path):
    rc, out, err = shell(monkeypatch, capsys, "enable x\nmove x 20mm\nmove-by x -5mm\njog x 5mm/s 0.3s\n"
                         "status x\nexit\n", "--out", str(tmp_path))
    assert rc == 0, (out, err)
    assert out[0] == "x: Operation Enabled, holding 0.0000 mm"
    assert out[1].startswith("x: move to 20.0000 mm done")
    assert abs(position_mm(out[1]) - 20.0) < 0.01
    assert out[2].startswith("x: move by -5.0000 mm done")
    assert abs(position_mm(out[2]) - 15.0) < 0.01
    # 0.3 s at 5 mm/s, renewed inside the dead-man interval, then a controlled stop: about 1.5 mm further
    jog_end = float(out[3].split("stopped at ")[1].split(" mm")[0])
    assert out[3].startswith("x: jogged 0.300 s at 5.000 mm/s") and 16.0 < jog_end < 17.0
    assert out[4].startswith("x: servo, Operation Enabled")
    assert "missed deadlines 0" in out[5]
    assert "closed: x Switch On Disabled" in err  # what the drive reported when the session closed


def test_a_failing_command_is_one_line_and_the_session_goes_on(monkeypatch, capsys, tmp_path):
    rc, out, _ = shell(monkeypatch, capsys, "move x 20mm\nbogus 1\nenable x\nmove x 20\nmove q 1mm\n"
                       "move x 0.5m\njog x 1m/s\nmove x 2mm speed=fast\nmove x 2mm\n", "--out", str(tmp_path))
    assert rc == 1  # a script with a failed command says so in its exit code
    errors = [ln for ln in out if ln.startswith("error: ")]
    assert errors == [
        "error: axis x: move_to: not enabled (enable() first)",
        "error: bogus: unknown command (help lists them)",
        "error: position: '20' needs a unit (m, mm, um, µm, nm), e.g. 20mm",
        "error: axis 'q': not on this machine (axes: x)",
        errors[4],
        errors[5],
        errors[6],
    ]
    assert "outside the soft limits" in errors[4] and "nothing moved" in errors[4]
    assert "jog: |velocity| must be <=" in errors[5]
    assert errors[6].startswith("error: speed: 'fast' is not a number")
    assert out[-1].startswith("x: move to 2.0000 mm done")  # it still works after every refusal


def test_enable_disable_and_stop_take_several_axes_and_extra_words_are_refused(monkeypatch, capsys, tmp_path):
    monkeypatch.setattr(sys, "stdin", io.StringIO(
        "enable x y q\nstatus\nenable x y\nmove x 1mm 2mm\njog y 1mm/s 0.1s\nstop x y\ndisable y x\n"))
    rc = main(["shell", "--axis", "x,y", "--out", str(tmp_path)])
    out = [ln for ln in capsys.readouterr().out.splitlines() if ln]
    assert rc == 1
    # a bad name among several: refused before any axis is enabled
    assert out[0] == "error: axis 'q': not on this machine (axes: x, y)"
    assert out[1].startswith("x: off, Switch On Disabled") and out[2].startswith("y: off, Switch On Disabled")
    enabled = [ln for ln in out if ", holding " in ln]
    assert [ln.split(":")[0] for ln in enabled] == ["x", "y"]
    assert "error: usage: move AXIS POSITION [speed=V] [timeout=T] [&]" in out  # not silently a move to 1 mm
    assert [ln.split(":")[0] for ln in out if ": stop " in ln] == ["x", "y"]
    assert [ln for ln in out if "(the drive reports it)" in ln] == [
        "y: Switch On Disabled (the drive reports it)", "x: Switch On Disabled (the drive reports it)"]


def test_capture_around_a_move_is_written_with_its_plot(monkeypatch, capsys, tmp_path):
    cap = tmp_path / "cap.csv"
    rc, out, _ = shell(monkeypatch, capsys, f"enable x\ncapture x trigger=move pre=20ms post=100ms out={cap}\n"
                       "wait 50ms\nmove x 1mm\nwait 50ms\n", "--out", str(tmp_path))
    assert rc == 0, out
    assert out[1] == f"x: capture armed (trigger move) -> {cap}"
    # under mbc (x's default) the move is done in 96 ms, inside the capture's 100 ms after the trigger
    assert out[3].startswith("x: move to 1.0000 mm done") and out[4] == "waited 0.05 s"
    assert out[5] == f"wrote {cap}, {cap.with_suffix('.png')}"
    tr = Trace.read(cap)
    assert len(tr) == 20 + 1 + 100 and tr.meta["capture_trigger"] == "move"


def test_relative_run_and_plot(monkeypatch, capsys, tmp_path):
    rc, out, _ = shell(monkeypatch, capsys, "enable x\nmove x 5mm\nrun x short-move relative\nplot\n",
                       "--out", str(tmp_path))
    assert rc == 0, out
    run_line = next(ln for ln in out if ln.startswith("x: run short-move"))
    assert " done in " in run_line
    written = next(ln for ln in out if ln.startswith("wrote ") and ln.endswith(".csv"))
    tr = Trace.read(written.split(" ", 1)[1])
    assert tr.ref[0] == pytest.approx(0.005, abs=1e-7)  # the profile shifted to where the axis stood
    assert out[-1].startswith("wrote ") and out[-1].endswith(".png")


def test_ctrl_c_during_a_move_stops_the_axis_and_keeps_the_session(tmp_path):
    script = "enable x\nmove x 90mm speed=1mm/s &\nwait 100s\nstatus x\nexit\n"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "drivectl.tools.cli.main", "shell", "--axis", "x", "--out",
                             str(tmp_path)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)
    assert proc.stdin is not None and proc.stdout is not None
    proc.stdin.write(script)
    proc.stdin.close()
    proc.stdin = None  # written whole: communicate() below only reads
    first = proc.stdout.readline()
    assert first.startswith("x: Operation Enabled"), first
    assert proc.stdout.readline().startswith("x: move to 90.0000 mm started")
    proc.send_signal(signal.SIGINT)  # the 90 s (simulated) move is under way, the wait about to run it
    rest, err = proc.communicate(timeout=120)
    lines = rest.splitlines()
    assert proc.returncode == 1, (rest, err)
    assert lines[0].startswith("interrupted: x servo at "), lines
    stopped_at = float(lines[0].split(" at ")[1].split(" mm")[0])
    assert 0 <= stopped_at < 90  # a controlled stop long before the target
    assert lines[1] == "waited 100 s" or lines[1].startswith("x: servo")  # the session went on
    assert lines[-2].startswith("x: servo, Operation Enabled")  # holding where it stopped
    assert float(lines[-2].split("position ")[1].split(" mm")[0]) == pytest.approx(stopped_at, abs=0.01)
    assert "closed: x Switch On Disabled" in err


class CtrlCBeforeLine(io.StringIO):
    """A script whose reading is interrupted once (Ctrl-C at the prompt) before its line number ``at``."""

    def __init__(self, text: str, at: int) -> None:
        super().__init__(text)
        self.at = at
        self.lines_read = 0

    def readline(self, *args) -> str:
        if self.lines_read == self.at:
            self.at = -1
            raise KeyboardInterrupt
        self.lines_read += 1
        return super().readline(*args)


def test_ctrl_c_between_commands_stops_a_move_given_with_and(monkeypatch, capsys, tmp_path):
    # the move goes on between commands (on the wall clock, while the user types): Ctrl-C there stops it
    script = "enable x\nmove x 90mm speed=1mm/s &\nwait 1s\nwait 2s\nstatus x\nexit\n"
    monkeypatch.setattr(sys, "stdin", CtrlCBeforeLine(script, at=3))
    rc = main(["shell", "--axis", "x", "--out", str(tmp_path)])
    out = [ln for ln in capsys.readouterr().out.splitlines() if ln]
    assert rc == 1, out
    assert out[2] == "waited 1 s"
    assert out[3].startswith("interrupted: x servo at "), out
    stopped_at = position_mm(out[3])
    assert 0.9 < stopped_at < 1.2  # 1 s at 1 mm/s, then the controlled stop
    assert out[4] == "waited 2 s"
    assert out[5].startswith("x: servo, Operation Enabled")
    assert float(out[5].split("position ")[1].split(" mm")[0]) == pytest.approx(stopped_at, abs=0.01)
    # with nothing under way it only says how to leave
    monkeypatch.setattr(sys, "stdin", CtrlCBeforeLine("enable x\nstatus x\nexit\n", at=1))
    rc = main(["shell", "--axis", "x", "--out", str(tmp_path)])
    out = [ln for ln in capsys.readouterr().out.splitlines() if ln]
    assert rc == 0 and out[1] == "^C (exit leaves the session)", out


def test_shell_refuses_a_bad_axis_flag_before_connecting(monkeypatch, capsys):
    monkeypatch.setattr(sys, "stdin", io.StringIO("enable x\n"))
    rc = main(["shell", "--axis", "x,x"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "--axis" in err[0]


def test_live_view_is_quiet_when_output_is_not_a_terminal():
    from drivectl.tools.cli.live import QuietView, open_live_view

    assert isinstance(open_live_view(object(), io.StringIO()), QuietView)


def test_the_live_window_draws_what_it_is_fed(tmp_path):
    pytest.importorskip("matplotlib")
    import multiprocessing as mp

    import matplotlib

    matplotlib.use("Agg")
    from drivectl.tools.cli.live import window_main

    q = mp.get_context("spawn").Queue()
    for k in range(5):
        q.put((k * 0.05, [[0.001 * k, 1e-3 * k, 2.0]]))
    q.put(None)
    window_main(q, ["x"], ("position", "following_error", "effort"), max_frames=3)  # the end marker ends it


def test_live_channels_are_chosen_and_checked(monkeypatch, capsys, tmp_path):
    rc, out, _ = shell(monkeypatch, capsys, "live on channels=position,effort\nlive on channels=torque\n"
                       "live off\n", "--out", str(tmp_path))
    assert rc == 1
    assert out[0] == "live view on (none (output is not a terminal)): position, effort"
    assert out[1].startswith("error: live: channel 'torque': expected one of position, reference")
    assert out[2] == "live view off"


def test_the_status_line_shows_the_chosen_channels(tmp_path):
    import drivectl
    from drivectl.tools.cli.live import StatusLine

    buf = io.StringIO()
    with drivectl.connect(axes=["x"], fault_dir=tmp_path) as m:
        m.axes["x"].enable()
        m.axes["x"].move_to(0.002).wait(5)
        StatusLine(m, buf, ("position", "following_error")).refresh()
    line = buf.getvalue().split("\x1b[2K")[-1]
    assert line.startswith("x: position 2 mm following_error ")


def test_the_status_line_fits_one_row_of_the_terminal(tmp_path, monkeypatch):
    """Wider than the terminal, it would wrap, and the carriage return would rewrite only its last row: each
    refresh would leave a row behind (seen with x, y and z in a 160-column terminal)."""
    import drivectl
    from drivectl.tools.cli.live import StatusLine

    buf = io.StringIO()
    with drivectl.connect(fault_dir=tmp_path) as m:
        view = StatusLine(m, buf, ("position", "following_error", "effort"))
        monkeypatch.setenv("COLUMNS", "60")
        view.refresh()
        narrow = buf.getvalue().split("\x1b[2K")[-1]
        monkeypatch.setenv("COLUMNS", "400")
        view.refresh()
        wide = buf.getvalue().split("\x1b[2K")[-1]
    assert len(narrow) == 59 and narrow.endswith("~") and narrow.startswith("x: position ")
    assert "z: position" in wide and not wide.endswith("~")  # room enough: the whole line


def test_a_result_starts_on_a_line_of_its_own_after_the_status_line(tmp_path):
    """The status line is rewritten in place while a command waits; the command's result must erase it first
    (was: "... max 0.78 msx: move to 10.0000 mm done" on one line in a terminal)."""
    import drivectl
    from drivectl.tools.cli.live import StatusLine
    from drivectl.tools.cli.shell import Shell

    buf = io.StringIO()
    with drivectl.connect(axes=["x"], fault_dir=tmp_path) as m:
        live = StatusLine(m, buf, ("position",))
        sh = Shell(m, out=tmp_path, stdin=io.StringIO(), stdout=buf, interactive=False, live=live)
        live.refresh()
        sh.say("x: done")
        live.refresh()
        sh.say("x: again")
    text = buf.getvalue()
    assert text.count("x: position") == 2
    for result in ("x: done\n", "x: again\n"):
        before = text[:text.index(result)]
        assert before.endswith("\r\x1b[2K"), repr(before[-60:])  # the status line erased just before it


def test_a_capture_pending_at_the_end_fills_or_is_named(monkeypatch, capsys, tmp_path):
    # triggered by the move but 300 ms of post-trigger samples still to come when the script ends: filled
    cap = tmp_path / "late.csv"
    never = tmp_path / "never.csv"
    rc, out, _ = shell(monkeypatch, capsys, f"enable x\ncapture x trigger=move pre=10ms post=300ms out={cap}\n"
                       f"capture x trigger=position>1 out={never}\nwait 20ms\nmove x 1mm\n", "--out", str(tmp_path))
    assert f"wrote {cap}, {cap.with_suffix('.png')}" in out
    assert len(Trace.read(cap)) == 10 + 1 + 300
    # a level never crossed: said, not silently dropped, and the script's exit code says it failed
    assert out[-1] == (f"error: capture on axis x: not triggered when the session ended; nothing written "
                       f"to {never}")
    assert rc == 1 and not never.exists()

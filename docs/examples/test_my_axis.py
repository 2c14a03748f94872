"""A user's CI check of an axis, against drivectl's emulated drives (copy it next to your own tests).

Run it with ``pytest docs/examples/test_my_axis.py``. With ``DRIVECTL_CONFIG`` pointing at your
machine's configuration the same test commands your machine (the clock is then the wall clock on a
real bus: the loop runs in its own thread at 1 kHz)."""

import pytest

import drivectl


@pytest.fixture
def machine(tmp_path):
    # the embedded emulated machine (or $DRIVECTL_CONFIG); lockstep: simulated time, deterministic
    with drivectl.connect(axes=["x"], fault_dir=tmp_path) as m:
        yield m  # leaving the block disables the axes, also when the test fails


def test_x_moves_20_mm_and_holds(machine):
    x = machine.axes["x"]
    x.enable()
    move = x.move_to(0.020).wait(timeout=5)  # raises MotionFault if the move ends in a fault
    assert move.status == "done"
    machine.advance(0.2)  # let it hold a while
    assert abs(x.position - 0.020) < 10e-6
    assert machine.status()["missed_deadlines"] == 0


def test_x_jog_stops_when_not_renewed(machine):
    x = machine.axes["x"]
    x.enable()
    x.jog(0.005)  # m/s; renew within 0.2 s or it stops by itself
    machine.advance(1.0)
    assert abs(x.velocity) < 1e-4
    assert 0.0009 < x.position < 0.0015


def test_a_scope_capture_of_a_move(machine, tmp_path):
    x = machine.axes["x"]
    x.enable()
    cap = x.capture(channels=("reference", "position", "following_error", "torque"), trigger="move",
                    pre=0.02, post=0.3)
    x.move_by(0.005)
    trace = cap.wait(timeout=2)
    cap.write(tmp_path / "x-move.csv")  # trace v1 + PNG
    assert max(abs(trace.columns["following_error_m"])) < 50e-6

"""SimAxis time model, the trace file v1, metrics and the servo loop's safety."""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers import PdController, SineProfile

from drivectl.controllers.runtime.servo import LimitError, Limits, StopReason, run
from drivectl.driver.axis import Axis, AxisError
from drivectl.driver.cia402 import PowerState
from drivectl.driver.units import DEFAULT_RESOLUTION_M, EffortScale, Encoder
from drivectl.plant_emulator.models import load_plant
from drivectl.plant_emulator.sim_axis import SimAxis
from drivectl.tracefile import metrics
from drivectl.tracefile.format import REQUIRED, Trace, TraceError

DT = 0.001


def _axis(**kw) -> SimAxis:
    return SimAxis(load_plant("rigid-x").build(DT), **kw)


def test_sim_axis_implements_the_protocol():
    assert isinstance(_axis(), Axis)


@pytest.mark.parametrize("transport", [True, False])
def test_transport_delay_rule(transport):
    """The effort written after sample k acts from t(k+1) to t(k+2) (one cycle later) with the
    transport delay, from t(k) without: compare against the bare plant."""
    axis = _axis(transport_delay=transport, resolution=None, enabled=True)
    plant = load_plant("rigid-x").build(DT)
    state = plant.initial_state()
    efforts = [0.0, 300.0, 300.0, -50.0, 120.0, 0.0, 0.0]
    applied = [0.0] + efforts[:-1] if transport else efforts
    for k, u in enumerate(efforts):
        fb = axis.read()
        assert fb.time == pytest.approx(k * DT)
        assert fb.position == plant.position(state)
        axis.write(u)
        plant.step(state, applied[k])


def test_quantisation_to_encoder_counts():
    axis = _axis(enabled=True)
    axis.read()
    axis.write(500.0)
    positions = []
    for _ in range(50):
        fb = axis.read()
        positions.append(fb.position)
        counts = fb.position / DEFAULT_RESOLUTION_M
        assert abs(counts - round(counts)) < 1e-6
    assert positions[-1] > 0


def test_power_states_are_reached_through_the_cycle_like_a_cia402_drive():
    axis = _axis(resolution=None)
    assert axis.power is PowerState.SWITCH_ON_DISABLED
    axis.read()
    axis.write(1000.0)
    for _ in range(10):
        axis.read()
    assert axis.state.s == [0.0, 0.0]  # disabled: no torque whatever is written
    axis.enable()  # non-blocking: Shutdown, then Enable Operation, one SYNC each
    states = []
    for _ in range(3):
        axis.write(1000.0)
        axis.read()
        states.append(axis.power)
    assert states == [PowerState.READY_TO_SWITCH_ON, PowerState.OPERATION_ENABLED, PowerState.OPERATION_ENABLED]
    axis.write(1000.0)
    axis.read()  # the setpoint written while enabled acts one cycle later
    assert axis.state.s[1] > 0
    axis.quick_stop()
    axis.write(1000.0)  # ignored: quick stop zeroes the setpoint
    axis.read()
    assert axis.power is PowerState.QUICK_STOP_ACTIVE
    v = axis.state.s[1]
    axis.read()
    assert axis.state.s[1] < v  # friction decelerates; no drive effort
    assert axis.power is PowerState.SWITCH_ON_DISABLED  # quick stop option 2: then disabled


def test_fault_and_reset_edge():
    axis = _axis(resolution=None, enabled=True)
    axis.read()
    axis.drive.fault(0x7305)
    assert axis.power is PowerState.FAULT_REACTION_ACTIVE
    axis.read()
    assert axis.power is PowerState.FAULT and axis.drive.error_code == 0x7305
    with pytest.raises(AxisError, match="0x7305"):
        axis.enable()
    axis.fault_reset()  # a rising edge of controlword bit 7 (sent with each cycle's setpoint)
    for _ in range(3):
        axis.write(0.0)
        axis.read()
    assert axis.power is PowerState.SWITCH_ON_DISABLED and axis.drive.error_code == 0
    axis.enable()
    for _ in range(3):
        axis.write(0.0)
        axis.read()
    assert axis.power is PowerState.OPERATION_ENABLED


def test_force_noise_is_seeded():
    def run_once(seed):
        axis = _axis(force_noise=5.0, seed=seed, enabled=True, resolution=None)
        axis.read()
        out = []
        for _ in range(200):
            axis.write(60.0)
            out.append(axis.read().position)
        return out

    assert run_once(1) == run_once(1)
    assert run_once(1) != run_once(2)


def test_units_round_trip():
    enc = Encoder()
    assert enc.from_counts(enc.to_counts(0.0123456)) == pytest.approx(0.0123456, abs=DEFAULT_RESOLUTION_M / 2)
    scale = EffortScale(rated=1000.0)
    assert scale.to_permille(500.0) == 500 and scale.from_permille(-250) == -250.0
    with pytest.raises(ValueError, match="resolution"):
        Encoder(0.0)
    # 0x6076 holds the rated effort in thousandths as UNSIGNED32: the largest that fits passes, more does not
    assert EffortScale(rated=EffortScale.MAX_RATED).rated_thousandths == 0xFFFF_FFFF
    with pytest.raises(ValueError, match="0x6076"):
        EffortScale(rated=EffortScale.MAX_RATED * 1.001)


# -- trace file --------------------------------------------------------------------------------------
def _trace() -> Trace:
    res = run(_axis(), PdController(DT), SineProfile(0.01, 1.0, 0.5), meta={"plant": "rigid-x"})
    return res.trace


def test_trace_round_trip(tmp_path):
    tr = _trace()
    path = tr.write(tmp_path / "x.csv")
    text = path.read_text().splitlines()
    assert text[0] == "# drivectl trace v1"
    assert "# axis: x" in text and "# effort_unit: N" in text and "# dt_s: 0.001" in text
    header = next(line for line in text if not line.startswith("#"))
    assert header.split(",")[:4] == list(REQUIRED)
    back = Trace.read(path)
    assert back.meta["plant"] == "rigid-x"
    np.testing.assert_allclose(back.pos, tr.pos, atol=1e-9)
    np.testing.assert_allclose(back.effort, tr.effort, atol=1e-6)
    assert len(back) == len(tr) == 501
    assert not list(tmp_path.glob(".*tmp"))  # no temporary left behind


def test_third_party_csv_with_four_columns_reads(tmp_path):
    p = tmp_path / "other.csv"
    p.write_text("time_s,ref_m,pos_m,effort,current_A\n0,0,0,1,0.1\n0.001,0.0001,0,2,0.2\n0.002,0.0002,0.0001,3,0.3\n")
    tr = Trace.read(p)
    assert tr.dt == pytest.approx(0.001) and tr.columns["current_A"][2] == 0.3


@pytest.mark.parametrize(
    "body, fragment",
    [
        ("time_s,ref_m,pos_m\n0,0,0\n", "missing column(s) effort"),
        ("# only metadata\n", "no column row"),
        ("time_s,ref_m,pos_m,effort\n", "no data rows"),
        ("time_s,ref_m,pos_m,effort\n0,0,0,0\n0.001,0,zz,0\n", "garbled"),
        ("time_s,ref_m,pos_m,effort\n0,0,0,0\n0.001,0,0\n", "garbled"),
        ("time_s,ref_m,pos_m,effort\n0,0,0,0\n0.001,0,nan,0\n", "column pos_m: not a finite number"),
        ("time_s,ref_m,pos_m,effort\n0,0,0,0\n0,0,0,0\n", "time_s: not increasing"),
    ],
)
def test_bad_traces_get_one_line_naming_the_file(tmp_path, body, fragment):
    p = tmp_path / "bad.csv"
    p.write_text(body)
    with pytest.raises(TraceError) as info:
        Trace.read(p)
    assert str(info.value).startswith(str(p)) and fragment in str(info.value) and "\n" not in str(info.value)


def test_atomic_write_keeps_old_file_when_writing_fails(tmp_path, monkeypatch):
    tr = _trace()
    path = tr.write(tmp_path / "x.csv")
    before = path.read_text()

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr("os.fsync", boom)
    with pytest.raises(OSError):
        tr.head(10).write(path)
    assert path.read_text() == before
    assert not list(tmp_path.glob(".*tmp"))


# -- metrics -----------------------------------------------------------------------------------------
def test_metrics_on_known_signals():
    ref = np.zeros(4)
    pos = np.array([1e-6, -3e-6, 0.0, 2e-6])
    e = metrics.tracking_error(ref, pos)
    assert e["max"] == pytest.approx(3e-6) and e["mean"] == pytest.approx(1.5e-6)
    assert e["rms"] == pytest.approx(math.sqrt((1 + 9 + 4) / 4) * 1e-6)
    f = np.array([1.0, 3.0, 1.0, 3.0])
    assert metrics.chattering_sigma(f) == pytest.approx(1.0)
    assert metrics.effort_roughness(f) == pytest.approx(2.0)
    w = metrics.mechanical_work(np.array([10.0, -10.0]), np.array([1.0, 1.0]), 0.5)
    assert w == {"positive": 5.0, "net": 0.0}
    el = metrics.ElectricalModel(force_constant=10.0, resistance=2.0, standby_power=1.0)
    # P = max(fv, 0) + R (f/K)^2 + P0 = 10 + 2 + 1 and 0 + 2 + 1 -> (13 + 3) * 0.5
    assert el.energy(np.array([10.0, -10.0]), np.array([1.0, 1.0]), 0.5) == pytest.approx(8.0)


def test_summary_of_a_trace():
    s = metrics.summarize(_trace())
    assert {"max_um", "mean_um", "rms_um", "energy_J", "sigma", "du_rms", "electrical_J"} <= set(s)
    assert s["max_um"] >= s["rms_um"] >= s["mean_um"] > 0
    assert s["energy_J"] > 0


# -- servo loop safety ---------------------------------------------------------------------------------
def test_profile_outside_soft_limits_is_refused_before_moving():
    axis = _axis()
    with pytest.raises(LimitError, match="outside the soft limits"):
        run(axis, PdController(DT), SineProfile(0.02, 1.0, 1.0), limits=Limits(position=(-0.01, 0.01)))
    assert axis.state.s == [0.0, 0.0] and axis.power is PowerState.SWITCH_ON_DISABLED


def test_following_error_ends_in_quick_stop_with_trace_kept():
    axis = _axis()
    weak = PdController(DT, kp=1e4, kd=0.0)  # cannot follow: error grows beyond the window
    res = run(axis, weak, SineProfile(0.01, 2.0, 2.0), limits=Limits(following_error=100e-6, following_time=0.005))
    assert res.stop is StopReason.FOLLOWING_ERROR
    assert axis.power is PowerState.SWITCH_ON_DISABLED
    tr = res.trace
    assert tr.meta["stop"] == "following error" and "window" in tr.meta["stop_detail"]
    assert 1 < len(tr) < 2001
    over = np.abs(tr.error) > 100e-6
    first = int(np.argmax(over))
    assert len(tr) - 1 - first == 5  # five cycles outside the window allowed, stopped on the sixth


def test_axis_not_at_the_profile_start_is_refused():
    axis = _axis(initial_position=0.01)
    res = run(axis, PdController(DT), SineProfile(0.01, 1.0, 1.0), limits=Limits(following_error=1e-3))
    assert res.stop is StopReason.FOLLOWING_ERROR and "nothing moved" in res.detail
    assert len(res.trace) == 1


def test_effort_is_clipped_to_the_limit_and_counted():
    res = run(_axis(), PdController(DT), SineProfile(0.01, 1.0, 1.0), limits=Limits(max_effort=200.0))
    assert np.abs(res.trace.effort).max() <= 200.0
    assert int(res.trace.meta["effort_clipped_cycles"]) > 0


def test_interrupt_quick_stops_and_keeps_the_trace():
    class Interrupting(PdController):
        calls = 0

        def step(self, reference, feedback):
            Interrupting.calls += 1
            if Interrupting.calls == 300:
                raise KeyboardInterrupt
            return super().step(reference, feedback)

    axis = _axis()
    res = run(axis, Interrupting(DT), SineProfile(0.01, 1.0, 1.0))
    assert res.stop is StopReason.INTERRUPTED and len(res.trace) == 299
    assert axis.power is PowerState.SWITCH_ON_DISABLED


def test_contour_error_of_a_circle_is_the_radial_deviation():
    t = np.linspace(0, 2 * np.pi, 2000)
    rx, ry = 0.04 * np.cos(t), 0.04 * np.sin(t)
    # measured: 5 um outside the circle and 3 mrad late along it; tangential lag is no contour error
    px, py = 0.040005 * np.cos(t - 0.003), 0.040005 * np.sin(t - 0.003)
    ce = metrics.contour_error(rx, ry, px, py)
    assert np.median(ce) == pytest.approx(5e-6, rel=0.01)
    assert np.abs(rx - px).max() > 1e-4  # the per-axis errors are far larger

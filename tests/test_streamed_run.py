"""Issue 18 point 5 in the servo loop: a run streams its trace as it goes (servo.Recording through
tools/trace_stream.TraceWriter), so a killed master leaves every row up to its last flush."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

from drivectl.tracefile.format import Trace


def test_sigkill_mid_run_leaves_a_readable_partial_trace(tmp_path):
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "drivectl", "trace", "--axis", "x", "--duration", "600",
                             "--out", str(out), "--quiet", "--no-plot"], stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        line = proc.stderr.readline()
        assert line.startswith("trace: axis x"), line + proc.stderr.read()
        deadline = time.monotonic() + 60
        partial = None
        while time.monotonic() < deadline:  # until the writer has flushed a few thousand rows
            found = list(out.glob("x-*.csv.partial"))
            if found and found[0].stat().st_size > 200_000:
                partial = found[0]
                break
            time.sleep(0.05)
        assert partial is not None, "no streamed rows appeared"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.communicate(timeout=30)
    tr = Trace.read(partial)
    assert tr.meta["trace_complete"] == "false"
    assert len(tr) > 2000 and tr.meta["axis"] == "x"
    assert (abs(tr.time[1:] - tr.time[:-1] - 0.001) < 1e-9).all()  # every row whole, in order
    assert not (out / "x.csv").exists()  # AXIS.csv points at completed traces only


def test_a_completed_run_streams_to_a_new_name_and_x_csv_is_the_latest(tmp_path, capsys):
    from drivectl.tools.cli.main import main

    out = tmp_path / "out"
    wrote = []
    for _ in range(2):
        assert main(["trace", "--axis", "x", "--duration", "0.2", "--out", str(out), "--quiet", "--no-plot"]) == 0
        wrote += [ln.split(" ", 1)[1] for ln in capsys.readouterr().out.splitlines() if ln.startswith("wrote ")]
    runs = sorted(p for p in out.glob("x-*.csv"))
    assert len(runs) == 2 and not list(out.glob("*.partial"))
    latest = Trace.read(out / "x.csv")
    assert latest.meta["recording"] == "streamed" and latest.meta["stop"] == "completed"
    assert len(latest) == 201 and latest.meta.get("trace_complete", "true") == "true"
    assert len(wrote) == 2 and os.path.samefile(out / "x.csv", wrote[1])


def test_references_sampled_chunk_by_chunk_equal_the_profile_and_keep_false_streams_only(tmp_path):
    """The run samples its references REF_CHUNK cycles at a time (bounded memory): across the chunk
    boundaries the reference is the profile's, bit for bit; keep=False holds nothing in memory and the
    result's trace is the streamed file read back."""
    import numpy as np
    from helpers import PdController, SineProfile

    from drivectl.controllers.runtime.servo import REF_CHUNK, Channel, Limits, plan_run, run_channels
    from drivectl.plant_emulator.models import load_plant
    from drivectl.plant_emulator.sim_axis import SimAxis

    prof = SineProfile(0.001, 0.5, 2 * REF_CHUNK * 0.001 + 0.5)
    traces = []
    for keep in (True, False):
        ch = Channel(SimAxis(load_plant("rigid-x").build(0.001)), PdController(0.001), prof, Limits())
        plan = plan_run([ch], keep=keep)
        assert len(plan.refs[0][0]) == REF_CHUNK
        res = run_channels(plan, stream=tmp_path / str(keep))
        assert res.ok and res.cycles > 2 * REF_CHUNK
        traces.append(res.trace)
    ref = prof.sample(np.arange(res.cycles) * 0.001)[0]
    assert np.array_equal(traces[0].ref, ref)
    assert traces[1].meta["recording"] == "streamed"
    assert np.allclose(traces[1].ref, ref, rtol=0, atol=1e-9) and np.allclose(traces[1].pos, traces[0].pos, atol=1e-9)


def test_a_streamed_run_has_no_one_hour_cap_and_its_limit_check_is_windowed():
    import numpy as np
    import pytest
    from helpers import PdController, SineProfile

    from drivectl.controllers.runtime.servo import REF_CHUNK, Channel, LimitError, Limits, plan_run
    from drivectl.plant_emulator.models import load_plant
    from drivectl.plant_emulator.sim_axis import SimAxis

    def channel(profile):
        return Channel(SimAxis(load_plant("rigid-x").build(0.001)), PdController(0.001), profile,
                       Limits(position=(-0.1, 0.1)))

    two_hours = SineProfile(0.01, 0.5, 7200.0)
    plan = plan_run([channel(two_hours)], keep=False)  # planned: checked whole, sampled one chunk
    assert plan.cycles == 7_200_001 and len(plan.refs[0][0]) == REF_CHUNK
    with pytest.raises(LimitError, match="more than a run records .3600000 cycles"):
        plan_run([channel(two_hours)], keep=True)  # held in memory: capped

    class LeavesAt700(SineProfile):
        def sample(self, t):
            p, v, a, j = super().sample(t)
            return np.where(np.asarray(t) >= 700.0, 0.5, p), v, a, j

    with pytest.raises(LimitError, match=r"position 0.500000 m at t=700.000 s is outside the soft limits"):
        plan_run([channel(LeavesAt700(0.01, 0.5, 1000.0))], keep=False)  # in the second window

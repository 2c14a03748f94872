"""Issue 15 across processes: the session API and `trace --approach` against `drivectl emulate` in
another process (socketcand on loopback). Outcomes only: no timing is asserted."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

import drivectl
from drivectl.driver.cia402 import PowerState
from drivectl.machine.config import load_config
from drivectl.tracefile.format import Trace

CONFIG = """
cycle_s = 0.001
[bus]
{bus}
[axes.x]
node_id = 1
rated_effort = 100.0
plant = "rigid-x"
controller = "pid-dob"
profile = "short-move"
[axes.x.limits]
position_m = [-0.1, 0.1]
following_error_m = 0.002
"""


@pytest.fixture
def emulator(tmp_path):
    cfg = tmp_path / "emu.toml"
    cfg.write_text(CONFIG.format(bus='interface = "virtual"'))
    proc = subprocess.Popen([sys.executable, "-m", "drivectl", "--config", str(cfg), "emulate", "--axis", "x",
                             "--socketcand"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    line = proc.stdout.readline()
    assert line.startswith("emulating x"), line + proc.stderr.read()
    port = int(re.search(r"127\.0\.0\.1:(\d+)", line).group(1))
    master = tmp_path / "master.toml"
    master.write_text(CONFIG.format(bus=f'interface = "socketcand"\nchannel = "can0"\nhost = "127.0.0.1"\n'
                                        f"port = {port}"))
    try:
        yield master
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=30)


def test_api_moves_an_axis_in_another_process(emulator, tmp_path):
    """Lockstep clock across the process boundary: each cycle waits for the drive's TPDOs, so the
    outcome does not depend on how loaded the machine is (on the wall clock, the default on this bus,
    a master held up for 300 ms loses the drive to its heartbeat consumer, as it should)."""
    with drivectl.connect(load_config(emulator), fault_dir=tmp_path, clock="lockstep") as m:
        x = m.axes["x"]
        x.enable()
        h = x.move_to(0.003).wait(timeout=30)
        assert h.status == "done", h.detail
        m.advance(0.3)
        assert abs(x.position - 0.003) < 5e-6
        assert m.status()["cycles"] > 100
    assert x.power is PowerState.SWITCH_ON_DISABLED  # verified from the drive's report on the way out


def test_trace_approaches_the_profile_start_or_refuses(emulator, tmp_path):
    base = [sys.executable, "-m", "drivectl", "--config", str(emulator), "trace", "--axis", "x", "--profile",
            "circle", "--duration", "0.3", "--quiet", "--no-plot", "--out", str(tmp_path / "out")]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    refused = subprocess.run([*base, "--no-approach"], capture_output=True, text=True, timeout=120, env=env)
    assert refused.returncode == 2, refused.stderr
    assert "approach: axis x from 0.000 mm to its profile's start 40.000 mm" in refused.stderr
    assert refused.stderr.strip().splitlines()[-1].startswith("drivectl: axis x from 0.000 mm")
    assert "--no-approach; nothing moved" in refused.stderr
    done = subprocess.run([*base, "--approach"], capture_output=True, text=True, timeout=120, env=env)
    assert done.returncode == 0, done.stderr
    tr = Trace.read(Path(tmp_path / "out" / "x.csv"))
    assert tr.meta["profile"] == "circle" and abs(tr.pos[0] - 0.04) < 20e-6  # it started where the circle does


def test_shell_script_moves_an_axis_in_another_process(emulator, tmp_path):
    """drivectl shell driven through stdin against the emulator in another process (lockstep clock,
    as above: outcomes only)."""
    script = "enable x\nmove x 3mm\nstatus x\nexit\n"
    done = subprocess.run([sys.executable, "-m", "drivectl", "--config", str(emulator), "shell", "--clock",
                           "lockstep", "--out", str(tmp_path / "out")], input=script, capture_output=True,
                          text=True, timeout=120, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    out = done.stdout.splitlines()
    assert done.returncode == 0, (done.stdout, done.stderr)
    assert out[0].startswith("x: Operation Enabled")
    assert out[1].startswith("x: move to 3.0000 mm done")
    assert abs(float(out[1].split(" at ")[1].split(" mm")[0]) - 3.0) < 0.005
    assert out[2].startswith("x: servo, Operation Enabled")
    assert "closed: x Switch On Disabled" in done.stderr  # the drive's report on the way out

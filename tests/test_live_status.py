"""The running loop's timing published for `drivectl status` in another process (machine/live_status.py)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

from drivectl.machine import live_status
from drivectl.machine.config import BusConfig


def test_published_read_back_and_removed(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    bus = BusConfig(interface="socketcand", channel="can0", host="127.0.0.1", port=4711)
    pub = live_status.Publisher(live_status.path_for(bus), lambda: {"cycles": 7, "latency_ms": {"max": 1.5}})
    pub._write()
    got = live_status.read(bus)
    assert got["cycles"] == 7 and got["pid"] == os.getpid() and got["latency_ms"] == {"max": 1.5}
    assert oct(live_status.path_for(bus).stat().st_mode & 0o777) == "0o600"
    assert live_status.path_for(bus).parent == tmp_path / "drivectl"
    assert live_status.read(bus, now=got["written"] + live_status.STALE_S + 1) is None  # stale
    assert live_status.read(BusConfig(interface="socketcand", channel="can0", port=4712)) is None  # another bus
    pub.close()
    assert not live_status.path_for(bus).exists()


def test_a_file_whose_writer_is_gone_is_not_read(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    bus = BusConfig(interface="socketcan", channel="can1")
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    path = live_status.path_for(bus)
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps({"pid": int(gone.stdout), "written": 1e12, "cycles": 1}))
    assert live_status.read(bus) is None
    path.write_text("{half")
    assert live_status.read(bus) is None


def test_summary_keeps_timing_and_states_only():
    st = {"clock": "wall clock, paced", "cycles": 10, "latency_ms": {"p50": 0.0}, "deadline_ms": {"x": 17.0},
          "granted": {"gc": "..."}, "axes": {"x": {"state": "servo", "power": "Operation Enabled", "position_m": 0.1}}}
    out = live_status.summary(st)
    assert "granted" not in out and out["axes"] == {"x": {"state": "servo", "power": "Operation Enabled",
                                                         "fault": None}}

"""Issue 19 point 2: the emulated drive against canopen's own master (RemoteNode, BaseNode402, PdoMap,
its NMT master and EMCY consumer), every check of `drivectl conformance`: in-process (the drive served
on its own thread and clock) and across processes over socketcand and SLCAN (`drivectl emulate`)."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys

import pytest

from drivectl.tools.cli.main import main
from drivectl.tools.conformance.suite import CHECKS, FAIL, PASS

CONFIG = """
cycle_s = 0.001
[bus]
{bus}
[axes.x]
node_id = 3
rated_effort = 100.0
plant = "rigid-x"
controller = "asmc"
profile = "short-move"
"""


def _run(tmp_path, bus: str, *flags: str, capsys) -> dict:
    cfg = tmp_path / "machine.toml"
    cfg.write_text(CONFIG.format(bus=bus))
    rc = main(["--config", str(cfg), "conformance", "--json", *flags])
    out = json.loads(capsys.readouterr().out)
    bad = [r for r in out["rows"] if r["result"] == FAIL]
    assert rc == 0 and not bad, bad
    return out


def test_every_check_passes_in_process(tmp_path, capsys):
    out = _run(tmp_path, 'interface = "virtual"', capsys=capsys)
    assert [r["result"] for r in out["rows"]] == [PASS] * len(CHECKS)
    assert len(CHECKS) >= 25


@pytest.mark.parametrize("transport", ["socketcand", "slcan"])
def test_every_check_passes_across_processes(tmp_path, capsys, transport):
    emu_cfg = tmp_path / "emu.toml"
    emu_cfg.write_text(CONFIG.format(bus='interface = "virtual"'))
    proc = subprocess.Popen([sys.executable, "-m", "drivectl", "--config", str(emu_cfg), "emulate",
                             f"--{transport}"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        line = proc.stdout.readline()
        if transport == "slcan":
            tty = re.search(r"(/dev/\S+)", line).group(1)
            bus = f'interface = "slcan"\nchannel = "{tty}"'
        else:
            port = re.search(r"127\.0\.0\.1:(\d+)", line).group(1)
            bus = f'interface = "socketcand"\nchannel = "can0"\nhost = "127.0.0.1"\nport = {port}'
        out = _run(tmp_path, bus, "--allow-enable", capsys=capsys)
    finally:
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert out["passed"] == len(CHECKS)  # the emulated drive is recognised by 0x1018: torque checks run too


def test_a_non_conforming_node_fails_its_rows(tmp_path, capsys, monkeypatch):
    """The checks can fail: a drive that answers SDO in Stopped (as canopen's LocalNode does) is caught."""
    from drivectl.plant_emulator.node402 import EmulatedDrive

    monkeypatch.setattr(EmulatedDrive, "_sdo_allowed", lambda self: True)
    cfg = tmp_path / "machine.toml"
    cfg.write_text(CONFIG.format(bus='interface = "virtual"'))
    rc = main(["--config", str(cfg), "conformance", "--json", "--only", "Stopped"])
    out = json.loads(capsys.readouterr().out)
    assert rc == 1 and out["failed"] == 1 and "answered an SDO upload in Stopped" in out["rows"][0]["detail"]


def test_an_emcy_in_stopped_fails_its_row(tmp_path, capsys, monkeypatch):
    from drivectl.plant_emulator.node402 import EmulatedDrive

    original = EmulatedDrive._on_sync

    def sync_emcy_in_any_state(self, can_id, data, timestamp):  # a drive that reports in Stopped too
        if len(data) > 1:
            self.node.emcy.send(0x8240, 0x11)
            return
        original(self, can_id, data, timestamp)

    monkeypatch.setattr(EmulatedDrive, "_on_sync", sync_emcy_in_any_state)
    cfg = tmp_path / "machine.toml"
    cfg.write_text(CONFIG.format(bus='interface = "virtual"'))
    rc = main(["--config", str(cfg), "conformance", "--json", "--only", "no EMCY"])
    out = json.loads(capsys.readouterr().out)
    assert rc == 1 and "sent in Stopped" in out["rows"][0]["detail"]

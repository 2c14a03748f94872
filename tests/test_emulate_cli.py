"""`drivectl emulate`'s own values (one line naming the flag, exit 2, before any bus opens) and its bus log
(every frame, sent and received, on one clock). Issue 18 point 8 and its CLI list."""

from __future__ import annotations

import csv
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import can
import canopen
import pytest

from drivectl.driver.network import BusLog, attach_bus_log, close_threaded, open_bus, threaded_network
from drivectl.driver.network import unique_virtual_channel as channel_name
from drivectl.tools.cli.main import main

GUARD = 10.0


def emulate(capsys: pytest.CaptureFixture[str], *flags: str) -> tuple[int, list[str]]:
    rc = main(["emulate", "--axis", "x", *flags])
    captured = capsys.readouterr()
    return rc, captured.err.splitlines()


@pytest.mark.parametrize("flags, expected", [
    (["--socketcand", "70000"], "drivectl: emulate: --socketcand 70000: expected a TCP port 0..65535"),
    (["--socketcand", "-1"], "drivectl: emulate: --socketcand -1: expected a TCP port"),
    (["--interface", "socketcan", "--channel", "drivectl-none0"],
     "drivectl: emulate: --interface socketcan --channel drivectl-none0: cannot open: "),
    (["--interface", "pcan", "--channel", "PCAN_USBBUS1"],
     "drivectl: emulate: --interface pcan --channel PCAN_USBBUS1: cannot open: "),
    (["--slcan", "--noise", "-1"], "drivectl: emulate: --noise -1.0: expected"),
    (["--slcan", "--noise", "nan"], "drivectl: emulate: --noise nan: expected"),
    (["--slcan", "--idle-timeout", "-2"], "drivectl: emulate: --idle-timeout -2.0: expected"),
    (["--slcan", "--bus-log", "/nonexistent-folder/x.csv"], "--bus-log /nonexistent-folder/x.csv: folder"),
    (["--slcan", "--bus-log", "frames.xyz"], "--bus-log frames.xyz: unknown log format"),
])
def test_bad_emulate_values_are_one_line_exit_2(capsys, flags, expected):
    rc, lines = emulate(capsys, *flags)
    assert rc == 2 and len(lines) == 1 and lines[0].startswith("drivectl: emulate: ") and expected in lines[0], lines


def test_bad_axis_list_and_busy_port(capsys):
    rc, lines = main(["emulate", "--axis", "x,x", "--slcan"]), capsys.readouterr().err.splitlines()
    assert rc == 2 and lines == ["drivectl: emulate: --axis x,x: axis x given twice"]
    rc, lines = main(["emulate", "--axis", ",", "--slcan"]), capsys.readouterr().err.splitlines()
    assert rc == 2 and len(lines) == 1 and "--axis ','" in lines[0]
    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = taken.getsockname()[1]
        rc, lines = emulate(capsys, "--socketcand", str(port))
    assert rc == 2 and len(lines) == 1
    assert lines[0].startswith(f"drivectl: emulate: --socketcand {port}: cannot listen on 127.0.0.1:{port}: ")


def test_bus_log_stamps_sent_and_received_frames_on_one_clock(tmp_path):
    """Received frames arrive stamped by other clocks (here 5.0 s, as an adapter's boot-relative counter
    would); sent frames had none (0.000000). Both get the host's clock when they pass."""
    path = tmp_path / "frames.csv"
    net = threaded_network(open_bus("virtual", channel_name("log")))
    t0 = time.time()
    log = attach_bus_log(net, str(path))
    assert isinstance(log, BusLog)
    net.send_message(0x080, b"")  # SYNC, sent: logged by the wrapped send
    log.on_message_received(can.Message(timestamp=5.0, arbitration_id=0x181, data=b"\x01", is_extended_id=False,
                                        is_rx=True))
    close_threaded(net)  # stops the notifier's listeners, the log among them
    t1 = time.time()
    rows = list(csv.DictReader(path.open()))
    assert [int(r["arbitration_id"], 16) for r in rows] == [0x080, 0x181]
    stamps = [float(r["timestamp"]) for r in rows]
    assert all(t0 <= t <= t1 for t in stamps) and stamps == sorted(stamps)


def test_emulate_bus_log_across_processes(tmp_path):
    """`drivectl emulate --socketcand --bus-log`: the master's SDO request (received) and the drive's
    boot-up and answer (sent) in one file, every stamp on the host's clock, in order."""
    path = tmp_path / "emu.csv"
    t0 = time.time()
    proc = subprocess.Popen([sys.executable, "-m", "drivectl", "emulate", "--axis", "x", "--socketcand",
                             "--bus-log", str(path)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        line = proc.stdout.readline()
        assert line.startswith("emulating x"), line + proc.stderr.read()
        port = int(line.rsplit(":", 1)[1])
        net = threaded_network(open_bus("socketcand", "can0", host="127.0.0.1", port=port))
        try:
            node = net.add_node(canopen.RemoteNode(1, canopen.objectdictionary.ObjectDictionary()))
            assert int.from_bytes(node.sdo.upload(0x1000, 0), "little") != 0  # device type, answered by the drive
        finally:
            close_threaded(net)
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=GUARD)
    t1 = time.time()
    rows = list(csv.DictReader(path.open()))
    ids = [int(r["arbitration_id"], 16) for r in rows]
    assert 0x701 in ids and 0x601 in ids and 0x581 in ids  # boot-up (sent), request (received), answer (sent)
    stamps = [float(r["timestamp"]) for r in rows]
    assert all(t0 <= t <= t1 for t in stamps), stamps
    assert stamps == sorted(stamps)


def test_bus_log_folder_is_checked_before_the_bus_opens(tmp_path, capsys):
    rc, lines = emulate(capsys, "--socketcand", "--bus-log", str(tmp_path / "missing" / "f.asc"))
    assert rc == 2 and len(lines) == 1 and "folder" in lines[0]
    assert not Path(tmp_path / "missing").exists()

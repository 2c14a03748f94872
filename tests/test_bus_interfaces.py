"""[bus] takes every interface python-can knows, with [bus.options] passed to ``can.Bus``; a bus that cannot
be opened (driver library missing, nothing listening, tty gone) is one line naming the interface and what
python-can said, exit 2, before anything moves. Issue 15 points 1 and 7, issue 18 point 8.

The CLI cases run the real entry point in-process; stderr must be exactly one ``drivectl: ...`` line.
"""

from __future__ import annotations

import re
import socket
import textwrap
import threading
from pathlib import Path
from typing import Any

import can
import pytest

from drivectl.driver import network, socketcand_client
from drivectl.driver.network import INTERFACES, BusOpenError, open_bus, unique_virtual_channel
from drivectl.machine.config import ConfigError, load_config
from drivectl.tools.cli.main import main

AXIS = '[axes.x]\nplant = "rigid-x"\ncontroller = "asmc"\nprofile = "circle"\n'
PCAN = '[bus]\ninterface = "pcan"\nchannel = "PCAN_USBBUS1"\nbitrate = 1000000\n[bus.options]\ndevice_id = 1\n'
KVASER = ('[bus]\ninterface = "kvaser"\nchannel = 0\nbitrate = 1000000\n[bus.options]\n'
          'exclusive = true\nfd = true\ndata_bitrate = 2000000\n')


def write_config(tmp_path: Path, bus: str) -> str:
    path = tmp_path / "machine.toml"
    path.write_text(bus + AXIS)
    return str(path)


def run_cli(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, list[str]]:
    rc = main(list(argv))
    err = capsys.readouterr().err
    return rc, err.splitlines()


def vendor_library_present(interface: str, channel: str | int) -> bool:
    try:
        open_bus(interface, channel).shutdown()
    except BusOpenError:
        return False
    return True


def test_every_python_can_interface_is_accepted(tmp_path):
    assert set(INTERFACES) == set(can.interfaces.VALID_INTERFACES)
    for name in ("pcan", "kvaser", "ixxat", "vector", "gs_usb", "socketcan", "slcan", "socketcand", "virtual"):
        cfg = load_config(write_config(tmp_path, f'[bus]\ninterface = "{name}"\nchannel = "0"\n'))
        assert cfg.bus.interface == name


@pytest.mark.parametrize("bus, interface, said", [
    (PCAN, "pcan", "pcanbasic"),  # python-can: OSError("pcanbasic library not found.")
    (KVASER, "kvaser", "canlib"),  # python-can logs "Kvaser canlib is unavailable." then raises NameError
])
def test_vendor_interface_without_its_library_is_one_line_exit_2(tmp_path, capsys, bus, interface, said):
    if vendor_library_present(interface, 0 if interface == "kvaser" else "PCAN_USBBUS1"):
        pytest.skip(f"{interface}'s library is installed here")
    config = write_config(tmp_path, bus)
    for command in (["status", "--axis", "x"], ["trace", "--axis", "x", "--no-plot", "--quiet",
                                                "--out", str(tmp_path / "out")]):
        rc, lines = run_cli(capsys, "--config", config, *command)
        assert rc == 2, lines
        assert len(lines) == 1 and lines[0].startswith(f"drivectl: bus {interface}:"), lines
        assert "cannot open" in lines[0] and said in lines[0].lower(), lines
        out = tmp_path / "out"
        assert not out.exists() or not any(out.iterdir())  # nothing ran, nothing written


def test_bus_options_reach_can_bus(tmp_path, monkeypatch):
    """[bus.options] arrive at can.Bus as keyword arguments, unchanged, beside bitrate (and host/port for
    socketcand); an option overrides a default drivectl sets (slcan's sleep_after_open)."""
    seen: list[dict[str, Any]] = []
    real_bus = can.Bus

    def recording_bus(**kwargs: Any) -> can.BusABC:
        seen.append(kwargs)
        return real_bus(interface="virtual", channel=unique_virtual_channel("opts"))

    monkeypatch.setattr(network.can, "Bus", recording_bus)
    cfg = load_config(write_config(tmp_path, PCAN))
    b = cfg.bus
    open_bus(b.interface, b.channel, b.bitrate, **b.open_kwargs()).shutdown()
    assert seen[-1] == {"interface": "pcan", "channel": "PCAN_USBBUS1", "bitrate": 1_000_000, "device_id": 1}
    cfg = load_config(write_config(tmp_path, KVASER))
    b = cfg.bus
    open_bus(b.interface, b.channel, b.bitrate, **b.open_kwargs()).shutdown()
    assert seen[-1] == {"interface": "kvaser", "channel": 0, "bitrate": 1_000_000, "exclusive": True, "fd": True,
                        "data_bitrate": 2_000_000}
    open_bus("slcan", "/dev/ttyX", 500_000, sleep_after_open=0.5).shutdown()
    assert seen[-1]["sleep_after_open"] == 0.5


def test_bus_options_act_on_the_real_interface():
    """Passed through for real: virtual's receive_own_messages, off by default here, on by option."""
    channel = unique_virtual_channel("own")
    for own in (False, True):
        bus = open_bus("virtual", channel, **({"receive_own_messages": True} if own else {}))
        try:
            bus.send(can.Message(arbitration_id=0x123, data=b"\x01", is_extended_id=False))
            got = bus.recv(0)
            assert (got is not None) == own
        finally:
            bus.shutdown()


@pytest.mark.parametrize("bus, key", [
    ('[bus]\ninterface = "pcan"\n[bus.options]\ndevice = { id = 1 }\n', "bus.options.device: expected a string"),
    ('[bus]\ninterface = "pcan"\n[bus.options]\nids = [1, 2]\n', "bus.options.ids: expected a string"),
    ('[bus]\ninterface = "pcan"\n[bus.options]\nbitrate = 500000\n', "bus.options.bitrate: set by [bus] itself"),
    ('[bus]\ninterface = "pcan"\n[bus.options]\nf_clock = nan\n', "bus.options.f_clock: expected"),
    ('[bus]\ninterface = "pcan"\noptions = 3\n', "bus.options: expected a table"),
    ('[bus]\ninterface = "virtual"\n[bus.options]\nreceive_own_messages = true\n', "bus.options: the virtual bus"),
    ('[bus]\ninterface = "peak"\n', "bus.interface: 'peak' is not an interface python-can knows"),
    ('[bus]\ninterface = "kvaser"\nchannel = -1\n', "bus.channel: expected"),
    ('[bus]\ninterface = "kvaser"\nchannel = true\n', "bus.channel: expected"),
])
def test_bad_bus_table_is_one_line_naming_the_key(tmp_path, capsys, bus, key):
    config = write_config(tmp_path, bus)
    with pytest.raises(ConfigError, match=f"machine.toml: {key}".replace("[", r"\[").replace("(", r"\(")):
        load_config(config)
    rc, lines = run_cli(capsys, "--config", config, "status", "--axis", "x")
    assert rc == 2 and len(lines) == 1 and key in lines[0], lines


def closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]  # closed on exit, never listened: connecting is refused


def test_no_emulator_listening_is_one_line_without_python_can_flood(tmp_path, capsys, caplog):
    """python-can's socketcand client retries connect() in a busy loop for 10 s, logging a warning each time
    (~880 000 lines); the probe in open_bus answers first, with one line."""
    port = closed_port()
    config = write_config(tmp_path, f'[bus]\ninterface = "socketcand"\nchannel = "can0"\nport = {port}\n')
    with caplog.at_level("DEBUG", logger="can"):
        rc, lines = run_cli(capsys, "--config", config, "status", "--axis", "x")
    assert rc == 2 and len(lines) == 1, lines
    assert f"bus socketcand 127.0.0.1:{port}" in lines[0] and "nothing listens there" in lines[0]
    assert not [r for r in caplog.records if r.name.startswith("can")]


def test_missing_slcan_tty_is_one_line(tmp_path, capsys):
    tty = tmp_path / "ttyGONE"
    config = write_config(tmp_path, f'[bus]\ninterface = "slcan"\nchannel = "{tty}"\n')
    rc, lines = run_cli(capsys, "--config", config, "scan")
    assert rc == 2 and len(lines) == 1, lines
    assert lines[0].startswith(f"drivectl: bus slcan:{tty}: cannot open:") and "could not open port" in lines[0]


@pytest.mark.parametrize("says, expected", [(b"", "no socketcand greeting"),
                                            (b"HTTP/1.1 400 Bad Request\r\n\r\n", "not a socketcand server")])
def test_a_server_that_is_not_socketcand_is_one_line(monkeypatch, says, expected):
    """Something listens but does not greet (or greets wrongly): one line within the handshake bound, where
    python-can's client would block in recv() for ever."""
    monkeypatch.setattr(socketcand_client, "SOCKETCAND_HANDSHAKE_S", 0.2)
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    done = threading.Event()

    def serve() -> None:
        conn, _ = listener.accept()
        with conn:
            if says:
                conn.sendall(says)
                conn.shutdown(socket.SHUT_WR)
            done.wait(5.0)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        with pytest.raises(BusOpenError, match=f"bus socketcand 127.0.0.1:{port} .*: cannot open: {expected}"):
            open_bus("socketcand", "can0", host="127.0.0.1", port=port)
    finally:
        done.set()
        thread.join(5.0)
        listener.close()


def test_the_adapter_examples_of_real_drive_md_load_and_fail_in_one_line(tmp_path, capsys):
    """docs/real-drive.md's PCAN and Kvaser tables are valid configuration, and on a machine without the
    vendor's library give exactly the one line the page shows."""
    page = (Path(__file__).resolve().parent.parent / "docs" / "real-drive.md").read_text()
    blocks = [textwrap.dedent(b) for b in re.findall(r"```toml\n(.*?)```", page, re.S)]
    shown = {b.split('interface = "')[1].split('"')[0]: b for b in blocks if "[bus]" in b}
    assert set(shown) >= {"pcan", "kvaser"}
    for interface, table in shown.items():
        config = write_config(tmp_path, table)
        assert load_config(config).bus.interface == interface
        if vendor_library_present(interface, load_config(config).bus.channel):
            continue
        rc, lines = run_cli(capsys, "--config", config, "scan")
        assert rc == 2 and len(lines) == 1, lines
        prefix = f"drivectl: bus {interface}:"
        assert lines[0].startswith(prefix) and lines[0].split(": cannot open: ")[0] in page.replace("`", " ")


def test_config_show_keeps_the_bus_options(tmp_path, capsys):
    config = write_config(tmp_path, KVASER)
    assert main(["--config", config, "config", "show"]) == 0
    shown = tmp_path / "shown.toml"
    shown.write_text(capsys.readouterr().out)
    assert load_config(shown).bus == load_config(config).bus  # channel 0 stays a number, options whole


def test_socketcand_server_going_away_is_one_warning_and_a_bus_error(caplog):
    """python-can's client read the server's EOF as "no frame" for ever (its notifier spinning) or, on a
    reset, printed a traceback from the notifier thread, and its send raised BrokenPipeError. Through
    open_bus: one warning, then a silent bus (the master's TPDO deadline sees it), sends a can.CanError."""
    from drivectl.plant_emulator.socketcand import SocketcandServerBus

    server = SocketcandServerBus(port=0)
    client = open_bus("socketcand", "can0", host="127.0.0.1", port=server.port)
    try:
        assert server.wait_for_client(5.0)
        server.send(can.Message(arbitration_id=0x181, data=b"\x01", is_extended_id=False))
        assert client.recv(5.0) is not None
        with caplog.at_level("WARNING"):
            server.shutdown()
            assert client.recv(0.2) is None  # the EOF (there at once: shutdown closed the socket), not a frame
            assert client.recv(0.01) is None  # and quiet afterwards
        lost = [r.getMessage() for r in caplog.records if "connection lost" in r.getMessage()]
        assert lost == [f"socketcand on can0@127.0.0.1:{server.port}: connection lost (the server closed it)"]
        with pytest.raises(can.CanOperationError, match="connection lost"):
            client.send(can.Message(arbitration_id=0x201, data=b"\x00", is_extended_id=False))
    finally:
        client.shutdown()
        server.shutdown()


def test_socketcand_server_without_the_channel_is_one_line_naming_it():
    from drivectl.plant_emulator.socketcand import SocketcandServerBus

    server = SocketcandServerBus(port=0, channel="can0")
    try:
        with pytest.raises(BusOpenError, match=r"bus socketcand 127.0.0.1:\d+ \(can1\): cannot open: the server has no "
                                               r"bus named 'can1' \(bus.channel\)"):
            open_bus("socketcand", "can1", host="127.0.0.1", port=server.port)
    finally:
        server.shutdown()

"""The emulator-side CAN adapters for masters in other processes: SLCAN over a pty and a socketcand server,
each driven by python-can's own client for that interface (what a master process would use).

Synchronisation is by blocking calls only (recv, wait_for_open, wait_for_client); their timeouts are
failure guards, never delays. Run this module directly to print the round-trip rate of each transport.
"""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Callable, Iterator

import can
import canopen
import pytest
import serial

from drivectl.plant_emulator.node402 import EMULATED_DRIVE_EDS
from drivectl.plant_emulator.slcan import SlcanAdapterBus
from drivectl.plant_emulator.socketcand import SocketcandServerBus

GUARD = 5.0  # seconds; only reached when something is broken
VENDOR_ID = 0x00D71C70  # [1018sub1] of the emulated drive's EDS


def open_slcan_client(adapter: SlcanAdapterBus) -> can.BusABC:
    client = can.Bus(interface="slcan", channel=adapter.tty_path, sleep_after_open=0, bitrate=1_000_000)
    # the client writes "O" without awaiting the answer; frames the adapter sends before it sees "O" are lost
    assert adapter.wait_for_open(GUARD)
    return client


def open_socketcand_client(server: SocketcandServerBus) -> can.BusABC:
    # the constructor returns after the raw-mode "< ok >", i.e. once the server is in raw mode
    return can.Bus(interface="socketcand", host="127.0.0.1", port=server.port, channel="can0")


def recv(bus: can.BusABC) -> can.Message:
    msg = bus.recv(GUARD)
    assert msg is not None, f"nothing received on {bus.channel_info} within {GUARD} s"
    return msg


def assert_frame(msg: can.Message, can_id: int, data: bytes, *, extended: bool = False) -> None:
    assert (msg.arbitration_id, msg.is_extended_id, msg.dlc, bytes(msg.data)) == (can_id, extended, len(data), data)
    assert not msg.is_remote_frame and not msg.is_error_frame


def ping_pong(client: can.BusABC, adapter: can.BusABC, n: int) -> float:
    """n round trips (client -> adapter, adapter echoes with id+1 -> client), in order; returns seconds."""
    t0 = time.perf_counter()
    for i in range(n):
        payload = i.to_bytes(4, "little") + bytes([i & 0xFF, 0xA5])
        client.send(can.Message(arbitration_id=0x181, data=payload, is_extended_id=False))
        got = recv(adapter)
        assert_frame(got, 0x181, payload)
        adapter.send(can.Message(arbitration_id=0x182, data=got.data, is_extended_id=False))
        assert_frame(recv(client), 0x182, payload)
    return time.perf_counter() - t0


# ---------------------------------------------------------------------------------------------- SLCAN


@pytest.fixture
def slcan_adapter() -> Iterator[SlcanAdapterBus]:
    adapter = SlcanAdapterBus.open_pty()
    yield adapter
    adapter.shutdown()


@pytest.fixture
def slcan_pair(slcan_adapter: SlcanAdapterBus) -> Iterator[tuple[SlcanAdapterBus, can.BusABC]]:
    client = open_slcan_client(slcan_adapter)
    yield slcan_adapter, client
    client.shutdown()


def test_slcan_client_frame_reaches_adapter(slcan_pair):
    adapter, client = slcan_pair
    assert adapter.bitrate == 1_000_000  # the client's S8
    client.send(can.Message(arbitration_id=0x123, data=b"\x01\x02\xfe", is_extended_id=False))
    assert_frame(recv(adapter), 0x123, b"\x01\x02\xfe")
    client.send(can.Message(arbitration_id=0x7FF, data=b"", is_extended_id=False))
    assert_frame(recv(adapter), 0x7FF, b"")


def test_slcan_adapter_frame_reaches_client(slcan_pair):
    adapter, client = slcan_pair
    adapter.send(can.Message(arbitration_id=0x705, data=b"\x00", is_extended_id=False))
    adapter.send(can.Message(arbitration_id=0x285, data=bytes(range(8)), is_extended_id=False))
    assert_frame(recv(client), 0x705, b"\x00")
    assert_frame(recv(client), 0x285, bytes(range(8)))


def test_slcan_extended_and_remote_frames(slcan_pair):
    adapter, client = slcan_pair
    client.send(can.Message(arbitration_id=0x1ABCDEF0, data=b"\xde\xad", is_extended_id=True))
    assert_frame(recv(adapter), 0x1ABCDEF0, b"\xde\xad", extended=True)
    adapter.send(can.Message(arbitration_id=0x00000123, data=b"\xbe\xef\x00", is_extended_id=True))
    assert_frame(recv(client), 0x123, b"\xbe\xef\x00", extended=True)
    client.send(can.Message(arbitration_id=0x705, is_remote_frame=True, dlc=1, is_extended_id=False))
    rtr = recv(adapter)
    assert (rtr.arbitration_id, rtr.is_remote_frame, rtr.dlc, rtr.is_extended_id) == (0x705, True, 1, False)
    adapter.send(can.Message(arbitration_id=0x1FFFFFFF, is_remote_frame=True, dlc=8, is_extended_id=True))
    rtr = recv(client)
    assert (rtr.arbitration_id, rtr.is_remote_frame, rtr.dlc, rtr.is_extended_id) == (0x1FFFFFFF, True, 8, True)
    # CAN FD lines (d/D/b/B, CANable 2.0 dialect) pass too, though the emulated drives are classic CAN
    client.send(can.Message(arbitration_id=0x321, data=bytes(range(12)), is_fd=True, bitrate_switch=True))
    fd = recv(adapter)
    assert (fd.arbitration_id, fd.is_fd, fd.bitrate_switch, bytes(fd.data)) == (0x321, True, True, bytes(range(12)))
    adapter.send(can.Message(arbitration_id=0x10000, is_extended_id=True, data=bytes(range(20)), is_fd=True))
    fd = recv(client)
    assert (fd.arbitration_id, fd.is_extended_id, fd.is_fd, fd.bitrate_switch) == (0x10000, True, True, False)
    assert bytes(fd.data) == bytes(range(20))


def test_slcan_500_round_trips_in_order(slcan_pair):
    adapter, client = slcan_pair
    ping_pong(client, adapter, 500)


def test_slcan_client_close_and_reopen(slcan_adapter):
    first = open_slcan_client(slcan_adapter)
    first.send(can.Message(arbitration_id=0x101, data=b"\x01", is_extended_id=False))
    assert_frame(recv(slcan_adapter), 0x101, b"\x01")
    first.shutdown()  # sends "C"
    assert slcan_adapter.wait_for_close(GUARD)
    # like a real adapter off the bus: a frame while the channel is closed is dropped, not delivered later
    slcan_adapter.send(can.Message(arbitration_id=0x666, data=b"\x66", is_extended_id=False))

    second = open_slcan_client(slcan_adapter)
    try:
        slcan_adapter.send(can.Message(arbitration_id=0x102, data=b"\x02", is_extended_id=False))
        assert_frame(recv(second), 0x102, b"\x02")
        second.send(can.Message(arbitration_id=0x103, data=b"\x03", is_extended_id=False))
        assert_frame(recv(slcan_adapter), 0x103, b"\x03")
        assert second.get_version(GUARD) == (1, 0)
        assert second.get_serial_number(GUARD) == "DCTL"
    finally:
        second.shutdown()


def test_slcan_reopen_after_client_vanished_while_adapter_kept_sending(slcan_adapter):
    """A client that dies without "C" leaves the channel open; frames then pile up until the adapter
    overruns, possibly with the pty holding half a line. The next client must get a clean stream."""
    dead = serial.Serial(slcan_adapter.tty_path, timeout=GUARD)
    dead.write(b"O\r")
    assert dead.read(1) == b"\r"
    dead.close()
    flood = can.Message(arbitration_id=0x1BD, data=b"\xbd" * 8, is_extended_id=False)  # "B"/"D": FD markers
    for _ in range(20_000):
        slcan_adapter.send(flood)
        if slcan_adapter.overruns:
            break
    assert slcan_adapter.overruns  # the pty and the adapter's own buffer are full

    client = open_slcan_client(slcan_adapter)
    try:
        slcan_adapter.send(can.Message(arbitration_id=0x123, data=b"\x01", is_extended_id=False))
        assert_frame(recv(client), 0x123, b"\x01")  # nothing stale or truncated before it
    finally:
        client.shutdown()


def test_slcan_lawicel_answers_and_partial_lines(slcan_adapter):
    """The adapter's replies byte for byte, seen through a bare serial port, and commands split across writes."""
    port = serial.Serial(slcan_adapter.tty_path, timeout=GUARD)

    def reply() -> bytes:  # up to and including CR (good) or BEL (error)
        answer = b""
        while not answer.endswith((b"\r", b"\a")):
            byte = port.read(1)
            assert byte, f"no complete answer within {GUARD} s, got {answer!r}"
            answer += byte
        return answer

    def ask(command: bytes) -> bytes:
        port.write(command)
        return reply()

    try:
        assert ask(b"t1231AA\r") == b"\a"  # channel closed: cannot transmit
        assert ask(b"C\r") == b"\a"  # already closed
        assert ask(b"S6\r") == b"\r"
        assert ask(b"V\r") == b"V0100\r"
        assert ask(b"N\r") == b"NDCTL\r"
        assert ask(b"F\r") == b"\a"  # status only while open
        assert ask(b"O\r") == b"\r"
        assert slcan_adapter.bitrate == 500_000
        assert ask(b"O\r") == b"\a"  # already open
        assert ask(b"S8\r") == b"\a"  # bitrate only while closed
        assert ask(b"F\r") == b"F00\r"
        assert ask(b"t1232AABB\r") == b"z\r"
        assert_frame(recv(slcan_adapter), 0x123, b"\xaa\xbb")
        assert ask(b"T12345678110\r") == b"Z\r"
        assert_frame(recv(slcan_adapter), 0x12345678, b"\x10", extended=True)
        assert ask(b"t8001AA\r") == b"\a"  # id beyond 11 bits
        assert ask(b"t1232AA\r") == b"\a"  # data shorter than the DLC
        assert ask(b"Q\r") == b"\a"  # unknown
        for piece in (b"t7", b"0", b"51", b"0", b"5\r"):  # one command over five writes
            port.write(piece)
            port.flush()
        assert reply() == b"z\r"
        assert_frame(recv(slcan_adapter), 0x705, b"\x05")
        port.write(b"t0010\rt0021EE\r")  # two commands in one write
        assert reply() + reply() == b"z\rz\r"
        assert_frame(recv(slcan_adapter), 0x001, b"")
        assert_frame(recv(slcan_adapter), 0x002, b"\xee")
        slcan_adapter.send(can.Message(arbitration_id=0x1A5, data=b"\x0f\xa0", is_extended_id=False))
        assert reply() == b"t1A520FA0\r"
        assert ask(b"C\r") == b"\r"
    finally:
        port.close()


# ---------------------------------------------------------------------------------------------- socketcand


@pytest.fixture
def socketcand_server() -> Iterator[SocketcandServerBus]:
    server = SocketcandServerBus(port=0)
    yield server
    server.shutdown()


@pytest.fixture
def socketcand_pair(socketcand_server: SocketcandServerBus) -> Iterator[tuple[SocketcandServerBus, can.BusABC]]:
    client = open_socketcand_client(socketcand_server)
    yield socketcand_server, client
    client.shutdown()


def test_socketcand_binds_loopback_only(socketcand_server):
    assert socketcand_server.port > 0
    assert socketcand_server.address == ("127.0.0.1", socketcand_server.port)


def test_socketcand_frames_both_ways(socketcand_pair):
    server, client = socketcand_pair
    assert server.is_client_connected
    client.send(can.Message(arbitration_id=0x605, data=b"\x40\x18\x10\x01\x00\x00\x00\x00", is_extended_id=False))
    assert_frame(recv(server), 0x605, b"\x40\x18\x10\x01\x00\x00\x00\x00")
    client.send(can.Message(arbitration_id=0x1ABCDEF0, data=b"\x0a", is_extended_id=True))
    assert_frame(recv(server), 0x1ABCDEF0, b"\x0a", extended=True)
    client.send(can.Message(arbitration_id=0x000, data=b"", is_extended_id=False))
    assert_frame(recv(server), 0x000, b"")
    server.send(can.Message(arbitration_id=0x585, data=b"\x43\x18\x10\x01\x70\x1c\xd7\x00", is_extended_id=False))
    assert_frame(recv(client), 0x585, b"\x43\x18\x10\x01\x70\x1c\xd7\x00")
    server.send(can.Message(arbitration_id=0x00000123, data=b"", is_extended_id=True))
    assert_frame(recv(client), 0x123, b"", extended=True)


def test_socketcand_500_round_trips_in_order(socketcand_pair):
    server, client = socketcand_pair
    ping_pong(client, server, 500)


def test_socketcand_reconnect_after_client_shutdown(socketcand_server):
    first = open_socketcand_client(socketcand_server)
    first.send(can.Message(arbitration_id=0x101, data=b"\x01", is_extended_id=False))
    assert_frame(recv(socketcand_server), 0x101, b"\x01")
    first.shutdown()
    second = open_socketcand_client(socketcand_server)  # may arrive before the server saw the first one leave
    try:
        second.send(can.Message(arbitration_id=0x102, data=b"\x02", is_extended_id=False))
        assert_frame(recv(socketcand_server), 0x102, b"\x02")
        socketcand_server.send(can.Message(arbitration_id=0x103, data=b"\x03", is_extended_id=False))
        assert_frame(recv(second), 0x103, b"\x03")
        assert socketcand_server.clients_served == 2
    finally:
        second.shutdown()


def test_socketcand_client_connects_while_server_keeps_sending(socketcand_server):
    """python-can's handshake reads "< ok >" with one recv(256) compared for equality: frames must not
    share that read, however busy the emulator side is while the master connects."""
    stop = threading.Event()

    def chatter() -> None:
        while not stop.is_set():
            socketcand_server.send(can.Message(arbitration_id=0x701, data=b"\x05", is_extended_id=False))

    thread = threading.Thread(target=chatter, daemon=True)
    thread.start()
    try:
        for _ in range(3):  # each connection hits the chatter at a different point of its handshake
            client = open_socketcand_client(socketcand_server)
            try:
                assert_frame(recv(client), 0x701, b"\x05")  # held frames follow once the hold-off ends
            finally:
                client.shutdown()
    finally:
        stop.set()
        thread.join(GUARD)


def raw_mode_socket(server: SocketcandServerBus, **sockopts: int) -> socket.socket:
    """A bare client through the handshake into raw mode (socket options set before connecting)."""
    sock = socket.socket()
    for opt, value in sockopts.items():
        sock.setsockopt(socket.SOL_SOCKET, getattr(socket, opt), value)
    sock.settimeout(GUARD)
    sock.connect(("127.0.0.1", server.port))
    for command in (b"", b"< open can0 >", b"< rawmode >"):
        if command:
            sock.sendall(command)
        reply = b""
        while not reply.endswith(b">"):
            chunk = sock.recv(1)
            assert chunk, "server closed the connection"
            reply += chunk
        assert reply == (b"< hi >" if not command else b"< ok >"), reply
    return sock


def read_until_closed(sock: socket.socket) -> bytes:
    reply = b""
    while chunk := sock.recv(4096):  # the server closes it; GUARD (the socket's timeout) only if broken
        reply += chunk
    return reply


def test_socketcand_serves_several_clients_as_one_bus():
    """Every client in raw mode gets what the emulator sends; a client's frame reaches the emulator and the
    other clients, not itself (socketcand's raw sockets do not receive their own frames)."""
    server = SocketcandServerBus(port=0)
    a, b = open_socketcand_client(server), open_socketcand_client(server)
    try:
        assert server.wait_for_client(GUARD, count=2)
        server.send(can.Message(arbitration_id=0x181, data=b"\x01", is_extended_id=False))
        assert_frame(recv(a), 0x181, b"\x01")
        assert_frame(recv(b), 0x181, b"\x01")
        a.send(can.Message(arbitration_id=0x201, data=b"\x0f\x00", is_extended_id=False))
        assert_frame(recv(server), 0x201, b"\x0f\x00")
        assert_frame(recv(b), 0x201, b"\x0f\x00")
        b.send(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False))
        assert_frame(recv(server), 0x080, b"")
        assert_frame(recv(a), 0x080, b"")  # a's own 0x201 never came back to it: this is the next frame
        assert server.clients_served == 2
    finally:
        a.shutdown()
        b.shutdown()
        server.shutdown()


def test_socketcand_idle_connection_does_not_hold_the_server():
    """An idle TCP client (nc, a stuck tool) once held the only slot for ever, so `status` died with a
    traceback. Now a master is served beside it, and the idle one is closed after the handshake timeout."""
    server = SocketcandServerBus(port=0, handshake_timeout=0.3)
    idle = socket.create_connection(("127.0.0.1", server.port), timeout=GUARD)
    try:
        master = open_socketcand_client(server)
        try:
            master.send(can.Message(arbitration_id=0x101, data=b"\x01", is_extended_id=False))
            assert_frame(recv(server), 0x101, b"\x01")
        finally:
            master.shutdown()
        assert read_until_closed(idle) == b"< hi >< error handshake timeout >"
    finally:
        idle.close()
        server.shutdown()


def test_socketcand_clients_are_capped_and_a_client_that_stops_reading_is_closed():
    """At most max_clients connections; a raw client on a quiet bus stays (a resident master between
    runs); one that takes none of the frames waiting for it for idle_timeout is closed (dead or hung)."""
    server = SocketcandServerBus(port=0, idle_timeout=0.3, max_clients=2, raw_hold_off=0)
    quiet = raw_mode_socket(server)
    stalled = raw_mode_socket(server, SO_RCVBUF=4096)
    try:
        with socket.create_connection(("127.0.0.1", server.port), timeout=GUARD) as third:
            assert read_until_closed(third) == b"< error too many clients >"
        time.sleep(0.5)  # longer than idle_timeout on a quiet bus: nobody is closed
        assert server.raw_clients == 2
        port = stalled.getsockname()[1]
        mine = next(c for c in server._clients if c.peer.endswith(f":{port}"))
        mine.sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
        quiet.close()  # (it would read; here it leaves)
        frames = 0
        while not mine.dropped and frames < 100_000:  # until its kernel buffers and then its queue are full
            server.send(can.Message(arbitration_id=0x181, data=b"\x01", is_extended_id=False))
            frames += 1
        assert mine.dropped, "the stalled client's queue never filled"
        deadline = time.monotonic() + GUARD
        while mine in server._clients and time.monotonic() < deadline:
            time.sleep(0.01)
        assert mine not in server._clients
        master = open_socketcand_client(server)  # the slots are free again
        master.shutdown()
    finally:
        quiet.close()
        stalled.close()
        server.shutdown()


def test_socketcand_client_that_stops_reading_loses_frames_alone():
    """Each client's queue is bounded: one that stops reading overflows its own buffer (frames dropped and
    counted), while the others get every frame, in order, and the emulator never blocks."""
    server = SocketcandServerBus(port=0, raw_hold_off=0)
    stalled = raw_mode_socket(server, SO_RCVBUF=4096)
    good = open_socketcand_client(server)
    n = 20000
    got: list[int] = []

    def reader() -> None:
        while len(got) < n:
            msg = good.recv(GUARD)
            if msg is None:
                return
            got.append(int.from_bytes(msg.data, "little"))

    try:
        assert server.wait_for_client(GUARD, count=2)
        port = stalled.getsockname()[1]
        mine = next(c for c in server._clients if c.peer.endswith(f":{port}"))
        mine.sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)  # no autotuning: overflow at once
        thread = threading.Thread(target=reader)
        thread.start()
        for i in range(n):
            server.send(can.Message(arbitration_id=0x181, data=i.to_bytes(4, "little"), is_extended_id=False))
        thread.join(3 * GUARD)
        assert got == list(range(n))
        others = [c for c in server._clients if c is not mine]
        assert mine.dropped > 0 and server.overruns == mine.dropped and [c.dropped for c in others] == [0]
        assert len(mine.out) <= 256 * 1024  # its queue stayed within its bound
    finally:
        stalled.close()
        good.shutdown()
        server.shutdown()


def test_socketcand_wire_format_and_split_commands():
    """The server's text byte for byte through a bare socket, with commands split and merged across writes."""
    server = SocketcandServerBus(port=0, channel="can0", raw_hold_off=0)
    sock = socket.create_connection(("127.0.0.1", server.port), timeout=GUARD)
    try:

        def read_element() -> str:
            text = b""
            while not text.endswith(b">"):
                chunk = sock.recv(1)
                assert chunk, "server closed the connection"
                text += chunk
            return text.decode()

        assert read_element() == "< hi >"
        sock.sendall(b"< open ")
        sock.sendall(b"can0 >")
        assert read_element() == "< ok >"
        sock.sendall(b"< rawmode >")
        assert read_element() == "< ok >"
        assert server.wait_for_client(GUARD)
        sock.sendall(b"< send 123 2 1 a >< send 1FFFFFFF 0 >< send 12 9 1 2 3 4 5 6 7 8 9 >< send 7ff 1 ab")
        sock.sendall(b" >< echo >")
        assert_frame(recv(server), 0x123, b"\x01\x0a")
        assert_frame(recv(server), 0x1FFFFFFF, b"", extended=True)
        assert_frame(recv(server), 0x7FF, b"\xab")  # the 9-byte send was dropped as socketcand drops it
        assert read_element() == "< echo >"
        server.send(can.Message(arbitration_id=0x1A5, data=b"\x0f\xa0", is_extended_id=False, timestamp=12.5))
        assert read_element() == "< frame 1A5 12.500000 0FA0 >"
        server.send(can.Message(arbitration_id=0x10, data=b"", is_extended_id=True, timestamp=3.0))
        assert read_element() == "< frame 00000010 3.000000  >"
    finally:
        sock.close()
        server.shutdown()
    refused = SocketcandServerBus(port=0, channel="can0")
    sock = socket.create_connection(("127.0.0.1", refused.port), timeout=GUARD)
    try:
        assert sock.recv(256) == b"< hi >"
        sock.sendall(b"< open can1 >")
        reply = b""
        while chunk := sock.recv(256):  # socketcand answers an unknown bus with an error and hangs up
            reply += chunk
        assert reply == b"< error could not open bus >"
    finally:
        sock.close()
        refused.shutdown()


# ---------------------------------------------------------------------------------------------- canopen


Transport = tuple[can.BusABC, Callable[[], can.BusABC]]


@pytest.fixture(params=["slcan", "socketcand"])
def transport(request) -> Iterator[Transport]:
    if request.param == "slcan":
        adapter: can.BusABC = SlcanAdapterBus.open_pty()
        yield adapter, lambda: open_slcan_client(adapter)
    else:
        adapter = SocketcandServerBus(port=0)
        yield adapter, lambda: open_socketcand_client(adapter)
    adapter.shutdown()  # idempotent: the emulator side's network may have shut it down already


def test_canopen_sdo_upload_over_transport(transport):
    adapter, open_client = transport
    emulator = canopen.Network(adapter)
    emulator.NOTIFIER_CYCLE = 0.05  # the notifier thread notices shutdown within this
    emulator.add_node(canopen.LocalNode(5, canopen.import_od(str(EMULATED_DRIVE_EDS), 5)))
    emulator.connect()
    master = canopen.Network(open_client())
    master.NOTIFIER_CYCLE = 0.05
    try:
        master.connect()
        drive = master.add_node(canopen.RemoteNode(5, canopen.import_od(str(EMULATED_DRIVE_EDS), 5)))
        assert int.from_bytes(drive.sdo.upload(0x1018, 1), "little") == VENDOR_ID
        assert drive.sdo[0x1018][1].raw == VENDOR_ID
    finally:
        master.disconnect()  # notifier first, then the bus (canopen's order)
        emulator.disconnect()


# ---------------------------------------------------------------------------------------------- rates


def measure_round_trip_rates(n: int = 2000) -> dict[str, float]:
    """Round trips per second of the ping-pong over each transport (one frame each way per trip)."""
    rates: dict[str, float] = {}
    adapter = SlcanAdapterBus.open_pty()
    client = open_slcan_client(adapter)
    try:
        ping_pong(client, adapter, 50)  # warm-up
        rates["slcan"] = n / ping_pong(client, adapter, n)
    finally:
        client.shutdown()
        adapter.shutdown()
    server = SocketcandServerBus(port=0)
    client = open_socketcand_client(server)
    try:
        ping_pong(client, server, 50)
        rates["socketcand"] = n / ping_pong(client, server, n)
    finally:
        client.shutdown()
        server.shutdown()
    return rates


if __name__ == "__main__":
    for name, rate in measure_round_trip_rates().items():
        print(f"{name:>10}: {rate:8.0f} round trips/s ({2 * rate:8.0f} frames/s, {1e6 / rate:6.0f} us per trip)")


@pytest.mark.parametrize("make, label", [(SlcanAdapterBus.open_pty, "slcan adapter"),
                                         (lambda: SocketcandServerBus(port=0), "socketcand server")])
def test_shutdown_wakes_a_blocked_recv_and_stops_the_io_thread(make, label):
    """Both device-side buses share one shutdown path (served_bus.py): a reader blocked in recv is
    woken with an error naming the bus, the I/O thread ends, send refuses, a second shutdown is a no-op."""
    bus = make()
    errors: list[BaseException] = []

    def reader() -> None:
        try:
            bus.recv(timeout=GUARD)
        except can.CanOperationError as exc:
            errors.append(exc)

    t = threading.Thread(target=reader)
    t.start()
    io_thread = bus._thread
    assert io_thread is not None and io_thread.is_alive()
    bus.shutdown()
    t.join(GUARD)
    assert not t.is_alive() and [str(e) for e in errors] == [f"{label} is shut down"]
    assert not io_thread.is_alive()
    with pytest.raises(can.CanOperationError, match=f"{label} is shut down"):
        bus.send(can.Message(arbitration_id=0x123, data=b"\x01", is_extended_id=False))
    bus.shutdown()


def test_served_bus_receive_queue_is_bounded_and_shutdown_still_wakes(monkeypatch):
    """A client flooding faster than the emulator reads loses frames (counted), it does not grow memory;
    shutting down with the queue full still wakes a reader."""
    from drivectl.plant_emulator import served_bus

    monkeypatch.setattr(served_bus, "RX_QUEUE_FRAMES", 10)
    server = SocketcandServerBus(port=0)
    client = open_socketcand_client(server)
    try:
        for i in range(50):
            client.send(can.Message(arbitration_id=0x100 + i, data=b"", is_extended_id=False))
        deadline = time.monotonic() + GUARD
        while server._rx.qsize() + server.rx_overruns < 50 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert (server._rx.qsize(), server.rx_overruns) == (10, 40)
        assert [recv(server).arbitration_id for _ in range(10)] == list(range(0x100, 0x10A))  # the first kept
        for i in range(20):  # full again: the shutdown's sentinel must still get in
            client.send(can.Message(arbitration_id=0x200 + i, data=b"", is_extended_id=False))
        while server._rx.qsize() < 10 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert server._rx.full()
    finally:
        client.shutdown()
        server.shutdown()
    with pytest.raises(can.CanOperationError, match="shut down"):
        for _ in range(11):  # what was queued, then the sentinel
            server.recv(GUARD)

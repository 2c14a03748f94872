"""The server side of the socketcand protocol on 127.0.0.1, as a python-can bus.

The emulator process plays socketcand: a master in another process connects with python-can's own
client, ``can.Bus(interface="socketcand", host="127.0.0.1", port=bus.port, channel="can0")``, and the
emulator's canopen Network sits on this bus like on any python-can bus.

Matched against python-can 4.6.1 ``can/interfaces/socketcand/socketcand.py`` (``SocketCanDaemonBus``)
and socketcand's ``state_nobus.c``/``state_raw.c``/``socketcand.c``:

* the client connects, ``_expect_msg("< hi >")``, sends ``< open CHANNEL >`` and expects ``< ok >``,
  sends ``< rawmode >`` and expects ``< ok >``. ``_expect_msg`` is ONE ``recv(256)`` compared for
  equality, so each of these answers must arrive alone: nothing may follow ``< ok >`` before the client
  has read it. Hence the raw-mode hold-off (``raw_hold_off``), a guard against a race that testing
  (a sender flooding during the handshake, in and across processes) never produced but nothing excludes;
* it transmits ``< send ID LEN b0 b1 ... >`` (``convert_can_message_to_ascii_message``: ID 3 or 8 hex
  digits, LEN ``{:X}``, bytes ``{:x}`` without padding); socketcand reads LEN as decimal (``%hhu``),
  requires exactly LEN bytes, and marks the id extended iff its text has 8 digits; the same here;
* it parses ``< frame ID SECONDS.USECONDS DATA >`` with ``split(" ", 3)`` and ``bytearray.fromhex(parts[2])``,
  so DATA must be contiguous hex (socketcand's ``%02X`` per byte, no spaces) and an empty frame is
  ``< frame 123 1.000000  >``; extended iff the id is not 3 characters long; ``< error ID TS >`` becomes
  an error frame. Any other ``< error ... >`` text (socketcand's ``< error unknown command >``) would
  make the client's ``int(parts[0], 16)`` raise inside its ``recv``, so in raw mode protocol errors are
  logged here, never answered.

Served: several clients at once, as socketcand serves each its own raw socket on one bus: a frame the
emulator sends reaches every client in raw mode, and a frame a client sends reaches the emulator and every
other client in raw mode (not itself: socketcand's sockets do not receive their own frames). One background
thread accepts, does the handshakes and reads; frames clients send are queued (bounded) for
``_recv_internal``. Nothing one client does can block another or grow memory without bound:

* each client's output is a bounded buffer (``_MAX_PENDING`` bytes): a client that stops reading loses
  frames (counted in :attr:`overruns`, logged once per client), the others do not wait for it;
* a connection that has not reached raw mode within ``handshake_timeout`` is told ``< error ... >`` and
  closed (an idle client, e.g. ``nc`` left open, must not hold a slot for ever);
* a client in raw mode that took none of the frames waiting for it for ``idle_timeout`` seconds (its
  kernel buffers full, then its own queue) is dead or hung: it is closed (None: never). A client on a
  quiet bus is not idle in this sense and stays: a resident master between runs sends nothing for minutes;
* at most ``max_clients`` connections at once; the next is told ``< error too many clients >``.

Frames sent while no client is in raw mode are dropped, as a bus that nobody listens to would.
"""

from __future__ import annotations

import logging
import select
import socket
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import can
from can.util import CAN_FD_DLC, len2dlc

from drivectl.plant_emulator.served_bus import ServedBus

log = logging.getLogger(__name__)

HOST = "127.0.0.1"  # loopback only: the protocol has no authentication
_MAX_PENDING = 256 * 1024  # bytes queued for a client that stopped reading; beyond, frames are dropped
_MAX_HELD = 1024  # frames kept during the raw-mode hold-off
_MAX_COMMAND = 512  # socketcand's MAXLEN is 4096 but no legal command is longer than an fdsend (~220)
_CANFD_BRS = 0x01
_CANFD_ESI = 0x02


@dataclass
class _Client:
    sock: socket.socket
    peer: str
    since: float  # monotonic time of the connection: the handshake deadline counts from it
    state: str = "nobus"  # socketcand's STATE_NO_BUS -> "bcm" after open -> "raw" after rawmode
    inbuf: str = ""
    out: bytearray = field(default_factory=bytearray)
    hold_until: float | None = None  # monotonic deadline of the raw-mode hold-off, None when released
    held: list[bytes] = field(default_factory=list)
    closing: bool = False  # close once `out` is flushed (after an error answer)
    waiting_since: float | None = None  # monotonic time since when `out` waits and the client took none of it
    dropped: int = 0  # frames lost because it did not read


class SocketcandServerBus(ServedBus):
    """socketcand server on 127.0.0.1:``port`` (0: ephemeral, read :attr:`port`).

    ``channel``: the bus name clients must open; None accepts any name (python-can's client always sends
    one). ``raw_hold_off``: after answering ``< rawmode >``, frames for the client are held until it
    sends something or this many seconds pass, so no frame shares a TCP read with that ``< ok >``.
    ``max_clients``, ``handshake_timeout``, ``idle_timeout``: see the module's docstring.
    """

    label = "socketcand server"

    def __init__(
        self,
        port: int = 0,
        *,
        channel: str | None = None,
        raw_hold_off: float = 0.25,
        max_clients: int = 8,
        handshake_timeout: float = 5.0,
        idle_timeout: float | None = 30.0,
        can_filters: can.typechecking.CanFilters | None = None,
        **kwargs: Any,
    ) -> None:
        if not 0 <= port <= 65535:
            raise ValueError(f"socketcand server: port {port} is not a TCP port (0..65535)")
        self._channel_name = channel
        self.raw_hold_off = raw_hold_off
        self.max_clients = max_clients
        self.handshake_timeout = handshake_timeout
        self.idle_timeout = idle_timeout
        self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            # a fixed port can be rebound at once after the emulator restarts (TIME_WAIT)
            self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._listener.bind((HOST, port))
            self._listener.listen(8)
            self._listener.setblocking(False)
        except BaseException:
            self._listener.close()
            raise
        self.port: int = self._listener.getsockname()[1]
        self.channel_info = f"socketcand server on {HOST}:{self.port}"
        self.clients_served = 0  # clients that reached raw mode, for diagnostics and tests
        self.overruns = 0  # frames dropped for clients that did not read them

        self._lock = threading.Lock()  # guards _clients and each client's out/held/hold_until, every socket write
        self._client_ready = threading.Condition(self._lock)
        self._clients: list[_Client] = []  # replaced (never mutated) under _lock, so it can be iterated freely
        self._init_io()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        super().__init__(channel=channel or "socketcand", can_filters=can_filters, **kwargs)
        self._start_io(self._serve, f"socketcand-server :{self.port}")

    # ------------------------------------------------------------------ public

    @property
    def address(self) -> tuple[str, int]:
        """The listening address, always (``"127.0.0.1"``, :attr:`port`)."""
        host, port = self._listener.getsockname()[:2]
        return host, port

    @property
    def raw_clients(self) -> int:
        """How many clients are in raw mode (frames sent now reach them)."""
        return sum(1 for c in self._clients if c.state == "raw" and not c.closing)

    @property
    def is_client_connected(self) -> bool:
        """True while at least one client is in raw mode."""
        return self.raw_clients > 0

    def wait_for_client(self, timeout: float | None = None, count: int = 1) -> bool:
        """Block until ``count`` clients are in raw mode; False on timeout."""
        with self._client_ready:
            return self._client_ready.wait_for(lambda: self.raw_clients >= count, timeout=timeout)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Hand ``msg`` to every client in raw mode; dropped without one. Never blocks (``timeout`` unused):
        bytes a socket does not take now are flushed by the server thread."""
        self._check_open()
        line = _format(msg)
        if line is None:
            return
        with self._lock:
            for client in self._clients:
                self._deliver_locked(client, line)

    def _close_io(self) -> None:
        with self._lock:
            clients, self._clients = self._clients, []
        for client in clients:
            client.sock.close()
        self._listener.close()
        self._wake_r.close()
        self._wake_w.close()

    # ------------------------------------------------------------------ output (callers hold _lock)

    def _deliver_locked(self, client: _Client, line: bytes) -> None:
        if client.state != "raw" or client.closing:
            return
        if client.hold_until is not None:
            if time.monotonic() < client.hold_until:
                if len(client.held) < _MAX_HELD:
                    client.held.append(line)
                else:
                    self._overrun_locked(client)
                return
            self._release_hold_locked(client)
        self._queue_locked(client, line)

    def _queue_locked(self, client: _Client, data: bytes) -> None:
        if len(client.out) + len(data) > _MAX_PENDING:
            self._overrun_locked(client)
            return
        was_idle = not client.out
        client.out += data
        self._flush_locked(client)
        if client.out and was_idle:
            self._wake()  # the server thread starts waiting for writability

    def _overrun_locked(self, client: _Client) -> None:
        self.overruns += 1
        client.dropped += 1
        if client.dropped == 1:
            log.warning("socketcand server :%d: client %s does not read: frames for it are dropped (others "
                        "unaffected)", self.port, client.peer)

    def _flush_locked(self, client: _Client) -> None:
        took = False
        while client.out:
            try:
                n = client.sock.send(client.out)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                client.out.clear()  # peer gone; the server thread sees the EOF/error on its next read
                break
            del client.out[:n]
            took = True
        if not client.out:
            client.waiting_since = None
        elif took or client.waiting_since is None:
            client.waiting_since = time.monotonic()  # the kernel's buffers are full: it is not reading now

    def _release_hold_locked(self, client: _Client) -> None:
        client.hold_until = None
        held, client.held = client.held, []
        for line in held:
            self._queue_locked(client, line)

    def _answer(self, client: _Client, text: str) -> None:
        with self._lock:
            self._queue_locked(client, text.encode("ascii"))

    def _wake(self) -> None:
        try:
            self._wake_w.send(b"x")
        except OSError:
            pass  # buffer full: the thread is awake anyway; closed: shutting down

    # ------------------------------------------------------------------ server thread

    def _serve(self) -> None:
        try:
            while not self._stopping:
                self._serve_once()
        except Exception:
            if not self._stopping:
                log.exception("socketcand server: thread died")

    def _deadline(self, client: _Client) -> float | None:
        """When the server thread must next look at ``client`` without any I/O on it."""
        if client.closing:
            return client.since + 2 * self.handshake_timeout  # told an error and not reading it: dropped then
        if client.state != "raw":
            return client.since + self.handshake_timeout
        stalled = client.waiting_since + self.idle_timeout if self.idle_timeout and client.waiting_since else None
        times = [t for t in (client.hold_until, stalled) if t is not None]
        return min(times) if times else None

    def _serve_once(self) -> None:
        clients = self._clients  # only this thread adds or removes clients
        rlist: list[socket.socket] = [self._wake_r, self._listener]
        wlist: list[socket.socket] = []
        deadlines: list[float] = []
        with self._lock:
            for client in clients:
                rlist.append(client.sock)
                if client.out:
                    wlist.append(client.sock)
                deadline = self._deadline(client)
                if deadline is not None:
                    deadlines.append(deadline)
        timeout = max(0.0, min(deadlines) - time.monotonic()) if deadlines else None
        readable, writable, _ = select.select(rlist, wlist, [], timeout)
        if self._stopping:
            return
        if self._wake_r in readable:
            try:
                self._wake_r.recv(4096)
            except BlockingIOError:
                pass
        for client in clients:
            if client.sock in writable:
                with self._lock:
                    self._flush_locked(client)
                    if client.closing and not client.out:
                        self._drop_locked(client, "closed after error")
            if client.sock in readable and client in self._clients:
                self._read_client(client)
        if self._listener in readable:
            self._accept()
        now = time.monotonic()
        with self._lock:
            for client in self._clients:
                if client.closing:
                    if now >= client.since + 2 * self.handshake_timeout:
                        self._drop_locked(client, "did not take its error answer")
                    continue
                if client.state != "raw":
                    if now >= client.since + self.handshake_timeout:
                        self._close_with_error_locked(client, "< error handshake timeout >",
                                                      f"no raw mode within {self.handshake_timeout:g} s")
                    continue
                if client.hold_until is not None and now >= client.hold_until:
                    self._release_hold_locked(client)
                if self.idle_timeout and client.waiting_since and now >= client.waiting_since + self.idle_timeout:
                    self._drop_locked(client, f"took none of its frames for {self.idle_timeout:g} s")

    def _accept(self) -> None:
        try:
            sock, addr = self._listener.accept()
        except (BlockingIOError, InterruptedError):
            return
        if len(self._clients) >= self.max_clients:
            log.warning("socketcand server :%d: %s refused: %d clients connected", self.port, addr, self.max_clients)
            _reject(sock, "< error too many clients >")
            return
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # as socketcand: small frames, no Nagle
        sock.setblocking(False)
        try:
            host, port = sock.getpeername()[:2]
            peer = f"{host}:{port}"
        except OSError:
            sock.close()
            return
        now = time.monotonic()
        client = _Client(sock=sock, peer=peer, since=now)
        with self._lock:
            self._clients = [*self._clients, client]
        log.info("socketcand server :%d: client %s connected", self.port, peer)
        self._answer(client, "< hi >")

    def _close_with_error_locked(self, client: _Client, text: str, why: str) -> None:
        client.out.clear()  # the error is the last thing it reads
        self._queue_locked(client, text.encode("ascii"))
        client.closing = True
        if not client.out:
            self._drop_locked(client, why)
        else:
            log.info("socketcand server :%d: closing client %s (%s)", self.port, client.peer, why)

    def _drop_locked(self, client: _Client, why: str) -> None:
        if client in self._clients:
            self._clients = [c for c in self._clients if c is not client]
        client.sock.close()
        log.info("socketcand server :%d: client %s gone (%s)", self.port, client.peer, why)

    def _read_client(self, client: _Client) -> None:
        try:
            data = client.sock.recv(65536)
            if data and hasattr(socket, "TCP_QUICKACK"):
                # Linux re-enables delayed ACKs after each read; the cycle is request/response, so ACK now
                client.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_QUICKACK, 1)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            data, why = b"", str(exc)
        else:
            why = "disconnected"
        if not data:
            with self._lock:
                self._drop_locked(client, why)
            return
        if client.closing:
            return  # told an error, closing: nothing it says counts any more
        if client.state == "raw" and client.hold_until is not None:
            # the client wrote after reading its raw-mode `< ok >`: frames can no longer share that read
            with self._lock:
                self._release_hold_locked(client)
        client.inbuf += data.decode("ascii", errors="replace")
        while True:
            start = client.inbuf.find("<")
            if start < 0:
                client.inbuf = ""  # no element can start in this text
                return
            end = client.inbuf.find(">", start)
            if end < 0:
                client.inbuf = client.inbuf[start:]
                if len(client.inbuf) > _MAX_COMMAND:
                    log.warning("socketcand server: unterminated command from %s discarded", client.peer)
                    client.inbuf = ""
                return
            command = client.inbuf[start : end + 1]
            client.inbuf = client.inbuf[end + 1 :]
            self._command(client, command)
            if client not in self._clients or client.closing:
                return

    def _command(self, client: _Client, command: str) -> None:
        words = command[1:-1].split()
        verb = words[0] if words else ""
        if client.state == "nobus":
            if verb == "open" and len(words) == 2:
                if self._channel_name is not None and words[1] != self._channel_name:
                    # socketcand: unknown bus -> error, then the connection ends
                    with self._lock:
                        self._close_with_error_locked(client, "< error could not open bus >",
                                                      f"asked for bus {words[1]!r}")
                    return
                client.state = "bcm"
                self._answer(client, "< ok >")
            else:
                self._answer(client, "< error unknown command >")
            return
        if command == "< rawmode >" and client.state != "raw":
            with self._client_ready:
                client.state = "raw"
                client.hold_until = time.monotonic() + self.raw_hold_off if self.raw_hold_off > 0 else None
                self.clients_served += 1
                self._queue_locked(client, b"< ok >")
                self._client_ready.notify_all()
            return
        if command == "< bcmmode >" and client.state != "bcm":
            with self._lock:
                client.state = "bcm"
                client.held.clear()
                client.hold_until = None
                self._queue_locked(client, b"< ok >")
            return
        if command == "< echo >":
            self._answer(client, "< echo >")
            return
        if verb in ("send", "fdsend"):
            msg = _parse_send(words)
            if msg is None:
                log.warning("socketcand server: syntax error in %r from %s", command, client.peer)  # as socketcand
                return
            msg.channel = self.channel_info
            self._put_rx(msg)
            line = _format(msg)  # the other clients are on the same bus: they see it too
            if line is not None and len(self._clients) > 1:
                with self._lock:
                    for other in self._clients:
                        if other is not client:
                            self._deliver_locked(other, line)
            return
        if client.state == "raw":
            log.warning(
                "socketcand server: unknown command %r from %s (not answered in raw mode)", command, client.peer
            )
        else:
            self._answer(client, "< error unknown command >")


def _reject(sock: socket.socket, text: str) -> None:
    try:
        sock.setblocking(False)
        sock.send(text.encode("ascii"))
    except OSError:
        pass
    sock.close()


def _format(msg: can.Message) -> bytes | None:
    """One socketcand raw-mode element for ``msg``, or None for what socketcand does not forward (RTR)."""
    ts = msg.timestamp if msg.timestamp > 0 else time.time()
    stamp = f"{ts:.6f}"  # socketcand: %ld.%06ld of the receive time
    if msg.is_error_frame:
        return f"< error {msg.arbitration_id & 0x1FFFFFFF:03X} {stamp} >".encode("ascii")
    if msg.is_remote_frame:
        return None  # socketcand's state_raw.c: "TODO implement"
    if msg.is_extended_id:
        ident = f"{msg.arbitration_id & 0x1FFFFFFF:08X}"
    else:
        ident = f"{msg.arbitration_id & 0x7FF:03X}"
    if msg.is_fd:
        flags = (_CANFD_BRS if msg.bitrate_switch else 0) | (_CANFD_ESI if msg.error_state_indicator else 0)
        data = bytes(msg.data).ljust(CAN_FD_DLC[len2dlc(len(msg.data))], b"\0")  # a valid CAN FD length
        return f"< fdframe {ident} {flags:02X} {stamp} {data.hex().upper()} >".encode("ascii")
    return f"< frame {ident} {stamp} {bytes(msg.data[:8]).hex().upper()} >".encode("ascii")


def _parse_send(words: list[str]) -> can.Message | None:
    """``send ID LEN b..`` or ``fdsend ID FLAGS LEN b..`` as socketcand's sscanf reads them; None if malformed."""
    fd = words[0] == "fdsend"
    head = 4 if fd else 3
    if len(words) < head:
        return None
    ident, length_text = words[1], words[head - 1]
    if not (_is_hex(ident) and length_text.isdigit()) or len(ident) > 8:
        return None
    length, max_len = int(length_text), (64 if fd else 8)
    payload = words[head:]
    if length > max_len or len(payload) != length or not all(len(b) <= 2 and _is_hex(b) for b in payload):
        return None
    if fd and length not in CAN_FD_DLC:
        return None
    extended = len(ident) == 8  # socketcand: element_length(buf, 2) == 8
    can_id = int(ident, 16)
    if can_id > (0x1FFFFFFF if extended else 0x7FF):
        return None
    flags = 0
    if fd:
        if not (len(words[2]) <= 2 and _is_hex(words[2])):
            return None
        flags = int(words[2], 16)
    return can.Message(
        arbitration_id=can_id,
        is_extended_id=extended,
        is_fd=fd,
        bitrate_switch=bool(flags & _CANFD_BRS),
        error_state_indicator=bool(flags & _CANFD_ESI),
        dlc=length,
        data=bytes(int(b, 16) for b in payload),
        timestamp=time.time(),
        is_rx=True,
    )


def _is_hex(text: str) -> bool:
    return bool(text) and all(c in "0123456789abcdefABCDEF" for c in text)

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

Served: one client at a time. A background thread accepts, does the handshake and reads; frames the
client sends are queued for ``_recv_internal``. A connection arriving while a client is served waits
up to ``busy_timeout`` for it to leave (a client that reconnects right after its shutdown may be seen
before the old connection's EOF), then is told ``< error ... >`` and closed. After a disconnect the
server accepts the next client. Frames sent while no client is in raw mode are dropped, as a bus that
nobody listens to would.
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
    state: str = "nobus"  # socketcand's STATE_NO_BUS -> "bcm" after open -> "raw" after rawmode
    inbuf: str = ""
    out: bytearray = field(default_factory=bytearray)
    hold_until: float | None = None  # monotonic deadline of the raw-mode hold-off, None when released
    held: list[bytes] = field(default_factory=list)
    closing: bool = False  # close once `out` is flushed (after an error answer)


class SocketcandServerBus(ServedBus):
    """socketcand server on 127.0.0.1:``port`` (0: ephemeral, read :attr:`port`).

    ``channel``: the bus name clients must open; None accepts any name (python-can's client always sends
    one). ``raw_hold_off``: after answering ``< rawmode >``, frames for the client are held until it
    sends something or this many seconds pass, so no frame shares a TCP read with that ``< ok >``.
    """

    label = "socketcand server"

    def __init__(
        self,
        port: int = 0,
        *,
        channel: str | None = None,
        raw_hold_off: float = 0.25,
        busy_timeout: float = 2.0,
        can_filters: can.typechecking.CanFilters | None = None,
        **kwargs: Any,
    ) -> None:
        self._channel_name = channel
        self.raw_hold_off = raw_hold_off
        self.busy_timeout = busy_timeout
        self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            # a fixed port can be rebound at once after the emulator restarts (TIME_WAIT)
            self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._listener.bind((HOST, port))
            self._listener.listen(4)
            self._listener.setblocking(False)
        except BaseException:
            self._listener.close()
            raise
        self.port: int = self._listener.getsockname()[1]
        self.channel_info = f"socketcand server on {HOST}:{self.port}"
        self.clients_served = 0  # clients that reached raw mode, for diagnostics and tests
        self.overruns = 0

        self._lock = threading.Lock()  # guards _client (its out/held/hold_until) and every socket write
        self._client_ready = threading.Condition(self._lock)
        self._client: _Client | None = None
        self._waiting: tuple[socket.socket, float] | None = None
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
    def is_client_connected(self) -> bool:
        """True while a client is in raw mode (frames sent now reach it)."""
        with self._lock:
            return self._client is not None and self._client.state == "raw"

    def wait_for_client(self, timeout: float | None = None) -> bool:
        """Block until a client is in raw mode; False on timeout."""
        with self._client_ready:
            return self._client_ready.wait_for(
                lambda: self._client is not None and self._client.state == "raw", timeout=timeout
            )

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Hand ``msg`` to the client in raw mode; dropped without one. Never blocks (``timeout`` unused):
        bytes the socket does not take now are flushed by the server thread."""
        self._check_open()
        line = _format(msg)
        if line is None:
            return
        with self._lock:
            client = self._client
            if client is None or client.state != "raw" or client.closing:
                return
            if client.hold_until is not None:
                if time.monotonic() < client.hold_until:
                    if len(client.held) < _MAX_HELD:
                        client.held.append(line)
                    else:
                        self.overruns += 1
                    return
                self._release_hold_locked(client)
            self._queue_locked(client, line)

    def _close_io(self) -> None:
        with self._lock:
            if self._client is not None:
                self._client.sock.close()
                self._client = None
        if self._waiting is not None:
            self._waiting[0].close()
            self._waiting = None
        self._listener.close()
        self._wake_r.close()
        self._wake_w.close()

    # ------------------------------------------------------------------ output (callers hold _lock)

    def _queue_locked(self, client: _Client, data: bytes) -> None:
        if len(client.out) + len(data) > _MAX_PENDING:
            self.overruns += 1
            return
        was_idle = not client.out
        client.out += data
        self._flush_locked(client)
        if client.out and was_idle:
            self._wake()  # the server thread starts waiting for writability

    def _flush_locked(self, client: _Client) -> None:
        while client.out:
            try:
                n = client.sock.send(client.out)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                client.out.clear()  # peer gone; the server thread sees the EOF/error on its next read
                return
            del client.out[:n]

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

    def _serve_once(self) -> None:
        now = time.monotonic()
        client = self._client  # only this thread replaces it
        rlist: list[socket.socket] = [self._wake_r, self._listener]
        wlist: list[socket.socket] = []
        deadlines: list[float] = []
        if client is not None:
            rlist.append(client.sock)
            with self._lock:
                if client.out:
                    wlist.append(client.sock)
                if client.hold_until is not None:
                    deadlines.append(client.hold_until)
        if self._waiting is not None:
            deadlines.append(self._waiting[1])
        timeout = max(0.0, min(deadlines) - now) if deadlines else None
        readable, writable, _ = select.select(rlist, wlist, [], timeout)
        if self._stopping:
            return
        if self._wake_r in readable:
            try:
                self._wake_r.recv(4096)
            except BlockingIOError:
                pass
        if client is not None and client.sock in writable:
            with self._lock:
                self._flush_locked(client)
                if client.closing and not client.out:
                    self._drop_locked(client, "closed after error")
        if client is not None and client.sock in readable and self._client is client:
            self._read_client(client)
        if self._listener in readable:
            self._accept()
        now = time.monotonic()
        if self._waiting is not None:
            if self._client is None:
                sock, _ = self._waiting
                self._waiting = None
                self._start(sock)
            elif now >= self._waiting[1]:
                sock, _ = self._waiting
                self._waiting = None
                _reject(sock, "< error another client is connected >")
        client = self._client
        if client is not None:
            with self._lock:
                if client.hold_until is not None and now >= client.hold_until:
                    self._release_hold_locked(client)

    def _accept(self) -> None:
        try:
            sock, addr = self._listener.accept()
        except (BlockingIOError, InterruptedError):
            return
        if self._client is None:
            self._start(sock)
        elif self._waiting is None:
            self._waiting = (sock, time.monotonic() + self.busy_timeout)
        else:
            _reject(sock, "< error another client is connected >")

    def _start(self, sock: socket.socket) -> None:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # as socketcand: small frames, no Nagle
        sock.setblocking(False)
        try:
            host, port = sock.getpeername()[:2]
            peer = f"{host}:{port}"
        except OSError:
            sock.close()
            return
        client = _Client(sock=sock, peer=peer)
        with self._lock:
            self._client = client
        log.info("socketcand server :%d: client %s connected", self.port, peer)
        self._answer(client, "< hi >")

    def _drop_locked(self, client: _Client, why: str) -> None:
        if self._client is client:
            self._client = None
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
            if self._client is not client or client.closing:
                return

    def _command(self, client: _Client, command: str) -> None:
        words = command[1:-1].split()
        verb = words[0] if words else ""
        if client.state == "nobus":
            if verb == "open" and len(words) == 2:
                if self._channel_name is not None and words[1] != self._channel_name:
                    # socketcand: unknown bus -> error, then the connection ends
                    self._answer(client, "< error could not open bus >")
                    with self._lock:
                        client.closing = True
                        if not client.out:
                            self._drop_locked(client, f"asked for bus {words[1]!r}")
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
            self._rx.put(msg)
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

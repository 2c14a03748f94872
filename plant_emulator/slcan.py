"""The adapter (device) side of SLCAN (LAWICEL ASCII) over a pseudo-terminal, as a python-can bus.

The emulator process plays the USB-CAN adapter: a master in another process opens the pty's slave end
with python-can's own client, ``can.Bus(interface="slcan", channel=bus.tty_path, sleep_after_open=0,
bitrate=1000000)`` (without ``sleep_after_open=0`` every open costs the client 2 s), and the
emulator's canopen Network sits on this bus like on any python-can bus.

Matched against python-can 4.6.1 ``can/interfaces/slcan.py`` (``slcanBus``):

* on open the client writes ``C``, ``S8`` (bitrate), an empty line (``_write(dbitrate_code)`` with
  ``""``), ``O`` without reading any answer; its ``_read`` returns every chunk ending in ``\\r`` or
  BEL and ``_recv_internal`` turns only chunks starting with t/T/x/r/R/d/D/b/B into messages, so the
  acknowledgements a real LAWICEL adapter sends (``\\r``, BEL, ``z\\r``/``Z\\r`` after a transmitted
  frame) are read and dropped there, costing one loop turn in ``BusABC.recv``;
* it transmits ``tIIIL<data>``, ``TIIIIIIIIL<data>``, ``rIIIL``, ``RIIIIIIIIL`` and (FD) ``d/D/b/B``
  with upper-case hex, each ending in ``\\r``; it parses classic data as ``int(string[4])`` (decimal
  DLC) and ignores anything after the data, so LAWICEL's optional 4-digit timestamp (``Z1``) is safe;
* ``get_version`` sends ``V`` and reads ``Vhhss``; ``get_serial_number`` sends ``N`` and reads
  ``Nxxxx``; ``shutdown`` sends ``C``.

Answers follow the LAWICEL CANUSB manual: ``\\r`` for a good command, BEL for a bad or ill-timed one
(``O``/``L``/``S``/``s`` only while closed, ``C``/``F``/transmit only while open), ``z\\r`` after a
standard and ``Z\\r`` after an extended transmit. Frames sent by the emulator before the client opened
the channel are dropped, as a real adapter that is not on the bus would never have seen them.

I/O runs in one background thread (select on the pty master and a wake-up pipe): commands are
answered, and ``O`` takes effect, even when nobody is calling ``recv`` yet; received frames are
queued for ``_recv_internal``.
"""

from __future__ import annotations

import errno
import fcntl
import logging
import os
import select
import struct
import termios
import threading
import time
import tty
from typing import Any

import can
from can.util import CAN_FD_DLC, len2dlc

from drivectl.plant_emulator.served_bus import ServedBus

log = logging.getLogger(__name__)

_OK = b"\r"
_ERROR = b"\a"
# LAWICEL S0..S8 (and the S9 = 83.3 kbit/s python-can also knows); the emulated bus has no bit timing,
# the value is only kept for inspection.
_BITRATES = {
    "0": 10_000,
    "1": 20_000,
    "2": 50_000,
    "3": 100_000,
    "4": 125_000,
    "5": 250_000,
    "6": 500_000,
    "7": 750_000,
    "8": 1_000_000,
    "9": 83_300,
}
_HEX = frozenset("0123456789abcdefABCDEF")
# Bytes not yet taken by the pty are kept whole-line; past this the adapter overruns like a real one
# whose host stops reading: new frames are dropped and the F status flag reports a data overrun.
_MAX_PENDING = 64 * 1024
_FLAG_DATA_OVERRUN = 0x08
_READ_CHUNK = 4096
_MAX_LINE = 256  # longest legal command is an FD frame, 10 + 128 + 4 chars


class SlcanAdapterBus(ServedBus):
    """The SLCAN adapter: frames the client transmits come out of ``recv``, ``send`` goes to the client.

    Build it with :meth:`open_pty`; hand :attr:`tty_path` to the client. ``ack_frames`` sends LAWICEL's
    ``z\\r``/``Z\\r`` after each frame the client transmits (CANable firmware sends nothing; python-can
    accepts both).
    """

    label = "slcan adapter"

    def __init__(
        self,
        master_fd: int,
        slave_fd: int,
        *,
        ack_frames: bool = True,
        hw_version: int = 1,
        sw_version: int = 0,
        serial_number: str = "DCTL",
        can_filters: can.typechecking.CanFilters | None = None,
        **kwargs: Any,
    ) -> None:
        if not (0 <= hw_version <= 99 and 0 <= sw_version <= 99):
            raise ValueError("hw_version and sw_version are two decimal digits each (python-can parses int())")
        self._master = master_fd
        # Held open for the bus's lifetime so the tty never hangs up (no EIO on the master) while no client
        # has it open, e.g. between a client's shutdown and the next open.
        self._slave = slave_fd
        self.tty_path = os.ttyname(slave_fd)
        self.channel_info = f"slcan adapter on {self.tty_path}"
        self.ack_frames = ack_frames
        self._version = f"{hw_version:02d}{sw_version:02d}"
        self._serial = serial_number
        os.set_blocking(master_fd, False)
        # Packet mode: a master read then also reports the client's tcflush(TCIFLUSH) (pyserial does one on
        # every open), which tells us to drop output queued for a previous client; see _read_master.
        fcntl.ioctl(master_fd, termios.TIOCPKT, struct.pack("i", 1))

        # Adapter state, touched only by the I/O thread except `_open` (read by send) and the flags.
        self._open = False
        self._open_changed = threading.Condition()
        self._listen_only = False
        self._timestamps = False
        self._status_flags = 0
        self.bitrate: int | None = None
        self.btr: str | None = None
        self.overruns = 0

        self._init_io()
        self._wlock = threading.Lock()  # guards _pending and every write to the master
        self._pending = bytearray()
        self._inbuf = bytearray()
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        super().__init__(channel=self.tty_path, can_filters=can_filters, **kwargs)
        self._start_io(self._io_loop, f"slcan-adapter {self.tty_path}")

    @classmethod
    def open_pty(cls, **kwargs: Any) -> SlcanAdapterBus:
        """A new pty pair; the adapter owns the master end, clients open :attr:`tty_path`."""
        master_fd, slave_fd = os.openpty()
        try:
            # On Linux the master's termios are the pair's: raw means no echo of what we write back to us
            # and no CR->NL mapping of the protocol's line terminator, before any client configures it.
            tty.setraw(master_fd)
            return cls(master_fd, slave_fd, **kwargs)
        except BaseException:
            os.close(master_fd)
            os.close(slave_fd)
            raise

    # ------------------------------------------------------------------ python-can template

    @property
    def is_channel_open(self) -> bool:
        """True between the client's ``O`` (or ``L``) and its ``C``."""
        return self._open

    def wait_for_open(self, timeout: float | None = None) -> bool:
        """Block until a client has opened the channel; False on timeout.

        python-can's client writes ``O`` without waiting for the answer, so right after ``can.Bus(...)``
        returns the adapter may not have processed it yet; frames sent before are dropped.
        """
        with self._open_changed:
            return self._open_changed.wait_for(lambda: self._open, timeout=timeout)

    def wait_for_close(self, timeout: float | None = None) -> bool:
        """Block until the channel is closed (the client's ``C``, sent by its ``shutdown``); False on timeout."""
        with self._open_changed:
            return self._open_changed.wait_for(lambda: not self._open, timeout=timeout)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Hand ``msg`` to the client (the adapter received it from the bus).

        Never blocks: dropped while the channel is closed, and on overrun (client not reading), as by a
        real adapter; ``timeout`` is therefore unused.
        """
        self._check_open()
        if not self._open:
            return
        line = self._format(msg)
        if line is None:
            return
        with self._wlock:
            if len(self._pending) + len(line) > _MAX_PENDING:
                self.overruns += 1
                self._status_flags |= _FLAG_DATA_OVERRUN
                return
            self._write_locked(line)

    def _close_io(self) -> None:
        with self._wlock:
            for fd in (self._master, self._slave, self._wake_r, self._wake_w):
                try:
                    os.close(fd)
                except OSError:
                    pass

    # ------------------------------------------------------------------ output

    def _write_locked(self, data: bytes) -> None:
        """Append to the pending bytes and push what the pty takes now (caller holds ``_wlock``)."""
        was_idle = not self._pending
        self._pending += data
        self._flush_locked()
        if self._pending and was_idle:
            self._wake()  # the I/O thread starts waiting for writability

    def _flush_locked(self) -> None:
        while self._pending:
            try:
                n = os.write(self._master, self._pending)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                if self._stopping:
                    return
                log.warning("slcan adapter: write to %s failed: %s", self.tty_path, exc)
                self._pending.clear()
                return
            del self._pending[:n]

    def _reply(self, data: bytes) -> None:
        with self._wlock:
            self._write_locked(data)

    def _wake(self) -> None:
        try:
            os.write(self._wake_w, b"x")
        except (BlockingIOError, OSError):
            pass  # pipe full: the thread is awake anyway; closed: shutting down

    def _format(self, msg: can.Message) -> bytes | None:
        if msg.is_error_frame:
            return None  # LAWICEL has no error-frame line
        if msg.is_extended_id:
            ident = f"{msg.arbitration_id & 0x1FFFFFFF:08X}"
        else:
            ident = f"{msg.arbitration_id & 0x7FF:03X}"
        ext = msg.is_extended_id
        if msg.is_remote_frame:
            text = f"{'R' if ext else 'r'}{ident}{min(msg.dlc, 8):d}"
        elif msg.is_fd:
            kind = ("B" if ext else "b") if msg.bitrate_switch else ("D" if ext else "d")
            dlc = len2dlc(len(msg.data))
            data = bytes(msg.data).ljust(CAN_FD_DLC[dlc], b"\0")  # the DLC code fixes the length; pad as CAN FD does
            text = f"{kind}{ident}{dlc:X}{data.hex().upper()}"
        else:
            data = bytes(msg.data[:8])
            text = f"{'T' if ext else 't'}{ident}{len(data):d}{data.hex().upper()}"
        if self._timestamps:
            # LAWICEL: milliseconds modulo 60000, 4 hex digits after the data
            text += f"{int(time.monotonic() * 1000) % 60000:04X}"
        return text.encode("ascii") + _OK

    # ------------------------------------------------------------------ input

    def _io_loop(self) -> None:
        try:
            while not self._stopping:
                with self._wlock:
                    want_write = bool(self._pending)
                rlist = [self._master, self._wake_r]
                readable, writable, _ = select.select(rlist, [self._master] if want_write else [], [])
                if self._stopping:
                    break
                if self._wake_r in readable:
                    try:
                        os.read(self._wake_r, 4096)
                    except BlockingIOError:
                        pass
                # Reading first: a flush notice must be seen before the freed space is filled again.
                if self._master in readable:
                    self._read_master()
                if writable:
                    with self._wlock:
                        self._flush_locked()
        except Exception:
            if not self._stopping:
                log.exception("slcan adapter: I/O thread died")

    def _read_master(self) -> None:
        try:
            chunk = os.read(self._master, _READ_CHUNK + 1)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            # EIO cannot happen while we hold the slave open; anything else is logged, not fatal.
            if exc.errno != errno.EIO:
                log.warning("slcan adapter: read from %s failed: %s", self.tty_path, exc)
            return
        if not chunk:
            return
        if chunk[0] != 0:
            # TIOCPKT status byte. FLUSHREAD: the client discarded its input queue (a new client opening,
            # or python-can's flush()). Whatever we still hold was meant for that queue; part of its first
            # line may already have been written and discarded, so delivering the rest would hand the client
            # a truncated line (python-can's parser raises on e.g. "BD..."). Drop it all: the stream restarts
            # on a line boundary.
            if chunk[0] & termios.TIOCPKT_FLUSHREAD:
                with self._wlock:
                    self._pending.clear()
            return
        self._inbuf += chunk[1:]  # packet mode: data comes after a 0 byte
        while True:
            end = self._inbuf.find(b"\r")
            if end < 0:
                if len(self._inbuf) > _MAX_LINE:  # garbage without terminator: resynchronise
                    self._inbuf.clear()
                return
            line = bytes(self._inbuf[:end])
            del self._inbuf[: end + 1]
            self._command(line.replace(b"\n", b"").decode("ascii", errors="replace"))

    def _command(self, line: str) -> None:
        if not line:
            # python-can sends a bare "\r" for "no FD data bitrate"; LAWICEL also uses CRs to flush a
            # half-typed command. Answering nothing keeps the client's input clean.
            return
        cmd = line[0]
        if cmd in "tTrRdDbB":
            self._client_frame(line)
            return
        reply = self._control(cmd, line[1:])
        self._reply(reply)

    def _control(self, cmd: str, arg: str) -> bytes:
        closed = not self._open
        if cmd in "OL" and not arg:
            if not closed:
                return _ERROR
            with self._open_changed:
                self._open, self._listen_only = True, cmd == "L"
                self._open_changed.notify_all()
            self._status_flags = 0
            return _OK
        if cmd == "C" and not arg:
            if closed:
                return _ERROR
            with self._open_changed:
                self._open = False
                self._open_changed.notify_all()
            return _OK
        if cmd == "S" and arg in _BITRATES:
            if not closed:
                return _ERROR
            self.bitrate, self.btr = _BITRATES[arg], None
            return _OK
        if cmd == "s" and len(arg) == 4 and set(arg) <= _HEX:
            if not closed:
                return _ERROR
            self.bitrate, self.btr = None, arg.upper()
            return _OK
        if cmd == "Y" and arg in ("2", "5"):  # CANable FD data bitrate: accepted, nothing to time
            return _OK if closed else _ERROR
        if cmd == "V" and not arg:
            return f"V{self._version}".encode() + _OK
        if cmd == "v" and not arg:
            return f"v{self._version}".encode() + _OK
        if cmd == "N" and not arg:
            return f"N{self._serial}".encode("ascii", errors="replace") + _OK
        if cmd == "F" and not arg:
            if closed:
                return _ERROR
            with self._wlock:  # send() sets the overrun bit from another thread
                flags, self._status_flags = self._status_flags, 0  # LAWICEL clears the flags on read
            return f"F{flags:02X}".encode() + _OK
        if cmd == "Z" and arg in ("0", "1"):
            if not closed:
                return _ERROR
            self._timestamps = arg == "1"
            return _OK
        if cmd in "Mm" and len(arg) == 8 and set(arg) <= _HEX:
            # SJA1000 acceptance code/mask: accepted so tools that set them work; the emulated bus
            # forwards everything (python-can filters on the client side anyway).
            return _OK if closed else _ERROR
        if cmd in "XWQ" and arg in ("0", "1", "2"):  # CAN232 auto-poll / filter mode / auto-start
            return _OK
        # P/A (polling) are only valid with auto-poll off, which this adapter never is; the rest is unknown.
        return _ERROR

    def _client_frame(self, line: str) -> None:
        msg = _parse_frame(line)
        ok = msg is not None and self._open and not self._listen_only
        if ok:
            assert msg is not None
            msg.channel = self.tty_path
            self._put_rx(msg)
        if not ok:
            self._reply(_ERROR)
        elif self.ack_frames:
            self._reply(b"Z\r" if line[0] in "TRDB" else b"z\r")


def _parse_frame(line: str) -> can.Message | None:
    """A t/T/r/R/d/D/b/B transmit command, or None if malformed (the adapter then answers BEL)."""
    kind = line[0]
    extended = kind in "TRDB"
    id_len = 8 if extended else 3
    ident, rest = line[1 : 1 + id_len], line[1 + id_len :]
    if len(ident) != id_len or not set(ident) <= _HEX or not rest:
        return None
    can_id = int(ident, 16)
    if can_id > (0x1FFFFFFF if extended else 0x7FF):
        return None
    fd = kind in "dDbB"
    dlc_char, payload = rest[0], rest[1:]
    if fd:
        if dlc_char not in _HEX:
            return None
        length = CAN_FD_DLC[int(dlc_char, 16)]
    else:
        if not dlc_char.isdigit() or int(dlc_char) > 8:
            return None
        length = int(dlc_char)
    if kind in "rR":
        if payload:
            return None
        return can.Message(
            arbitration_id=can_id,
            is_extended_id=extended,
            is_remote_frame=True,
            dlc=length,
            timestamp=time.time(),
            is_rx=True,
        )
    # The client may append nothing but the data: exact length, all hex.
    if len(payload) != 2 * length or not set(payload) <= _HEX:
        return None
    return can.Message(
        arbitration_id=can_id,
        is_extended_id=extended,
        is_fd=fd,
        bitrate_switch=kind in "bB",
        dlc=length,
        data=bytes.fromhex(payload),
        timestamp=time.time(),
        is_rx=True,
    )

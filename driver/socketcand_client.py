"""python-can's socketcand client, made safe to point at an emulator that is not there or goes away.

python-can 4.6's ``SocketCanDaemonBus`` (``can/interfaces/socketcand/socketcand.py``), as a master uses it:

* with nothing listening, its ``connect_to_server`` retries ``connect()`` in a busy loop for 10 s and logs
  a warning per attempt (~880 000 lines): :func:`probe_socketcand` connects once first and reads the
  ``< hi >`` greeting against a deadline, so a closed port or a stranger is one line;
* its handshake reads with blocking ``recv()`` on a socket without a timeout: a server that accepts and
  says nothing would hang the master for ever; :meth:`SocketcandClientBus.connect` bounds it;
* when the server closes the connection its receive path returns nothing for ever (EOF is read as "no
  frame", so the notifier thread spins), or, on a reset, logs the traceback and raises in the notifier
  thread; its ``send`` raises ``BrokenPipeError``, which is not a ``can.CanError``. Here a lost connection
  is logged once, receiving then waits as on a silent bus (the master sees its TPDOs stop: a fault it
  handles), and sending raises ``can.CanOperationError`` (a bus error the axis reports).
"""

from __future__ import annotations

import logging
import select
import socket
import threading
import time
from typing import Any

import can
from can.interfaces.socketcand import SocketCanDaemonBus

log = logging.getLogger(__name__)

#: seconds a socketcand server has to accept and greet, and to finish the handshake
SOCKETCAND_HANDSHAKE_S = 3.0
_DEFAULT_TIMEOUT_LOCK = threading.Lock()


def probe_socketcand(where: str, host: str, port: int, error: type[Exception]) -> None:
    """Check that a socketcand server listens and greets: one connection, one ``< hi >`` read with a
    deadline, then closed. Raises ``error`` with one line starting with ``where``."""
    try:
        with socket.create_connection((host, port), timeout=SOCKETCAND_HANDSHAKE_S) as probe:
            greeting = b""
            deadline = time.monotonic() + SOCKETCAND_HANDSHAKE_S
            while not greeting.endswith(b">") and len(greeting) < 64:
                probe.settimeout(max(0.001, deadline - time.monotonic()))
                chunk = probe.recv(64)
                if not chunk:
                    break
                greeting += chunk
    except ConnectionRefusedError:
        raise error(f"{where}: cannot open: nothing listens there (connection refused); start the "
                    f"emulator (drivectl emulate --socketcand {port}) or socketcand first") from None
    except TimeoutError:
        raise error(f"{where}: cannot open: no socketcand greeting within {SOCKETCAND_HANDSHAKE_S:g} s") from None
    except OSError as exc:
        raise error(f"{where}: cannot open: {exc.strerror or exc}") from None
    if greeting.strip() != b"< hi >":
        text = greeting.decode("ascii", "replace").strip() or "the connection closed"
        raise error(f"{where}: cannot open: not a socketcand server (it said {text!r}, expected '< hi >')")


class SocketcandClientBus(SocketCanDaemonBus):
    """python-can's socketcand client with a bounded handshake and a lost connection made one clear error
    (see the module's docstring). Open it with :meth:`connect`."""

    _lost: str | None = None

    @classmethod
    def connect(cls, channel: str | int, **kwargs: Any) -> SocketcandClientBus:
        # the client's socket is created inside its constructor: the default timeout is set around it (so
        # the handshake's blocking reads end), then the socket is made blocking again (receiving selects
        # with its own timeout)
        with _DEFAULT_TIMEOUT_LOCK:
            before = socket.getdefaulttimeout()
            socket.setdefaulttimeout(SOCKETCAND_HANDSHAKE_S)
            try:
                bus = cls(channel=channel, **kwargs)
            except can.CanError as exc:
                said = str(exc)
                if "could not open bus" in said:  # socketcand's answer to `< open NAME >` for a bus it lacks
                    raise can.CanInitializationError(f"the server has no bus named {channel!r} (bus.channel): "
                                                     f"{said}") from None
                raise
            finally:
                socket.setdefaulttimeout(before)
        bus._sock.settimeout(None)
        return bus

    @property
    def _sock(self) -> socket.socket:
        return self._SocketCanDaemonBus__socket  # type: ignore[attr-defined]  # python-can's own socket

    def _lose(self, why: str) -> str:
        if self._lost is None:
            self._lost = f"{self.channel_info}: connection lost ({why})"
            log.warning("%s", self._lost)
        return self._lost

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self._lost is not None:
            if timeout:
                time.sleep(timeout)  # a silent bus: the notifier polls at its own pace, no spinning
            return None, False
        if self._SocketCanDaemonBus__message_buffer:  # type: ignore[attr-defined]  # frames already parsed
            return super()._recv_internal(0)
        try:
            ready, _, _ = select.select([self._sock], [], [], timeout)
            if not ready:
                return None, False
            if not self._sock.recv(1, socket.MSG_PEEK):
                self._lose("the server closed it")
                return None, False
        except OSError as exc:
            self._lose(exc.strerror or str(exc))
            return None, False
        return super()._recv_internal(0)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self._lost is not None:
            raise can.CanOperationError(self._lost)
        try:
            super().send(msg, timeout)
        except OSError as exc:
            raise can.CanOperationError(self._lose(exc.strerror or str(exc))) from None

"""CAN buses and canopen networks: opened by python-can's own interface names, pumped in lockstep.

``virtual`` (python-can's in-process bus) runs in lockstep: every frame a network sends is
delivered, on the sending thread, to every network of the same :class:`Lockstep` until the bus is
quiet; a reply (an SDO response, the TPDOs answering a SYNC) is therefore already received when the
send returns. No notifier thread, so the order of frames never depends on timing and the same run
gives the same trace bit for bit. Other interfaces (slcan, socketcand, socketcan) cross a process
boundary: their networks are driven by a python-can Notifier as usual.
"""

from __future__ import annotations

import itertools
import logging
import os
import time
from typing import Any

import can
import canopen

from drivectl.driver.frame_guard import FrameGuard

log = logging.getLogger("drivectl.frames")

#: python-can interfaces the drivers know how to open
INTERFACES = ("virtual", "slcan", "socketcand", "socketcan")

_channel_counter = itertools.count()


def unique_virtual_channel(prefix: str = "drivectl") -> str:
    """A channel name no other bus of this process uses (virtual channels are process-global)."""
    return f"{prefix}-{os.getpid()}-{next(_channel_counter)}"


def open_bus(interface: str, channel: str, bitrate: int | None = None, **kwargs: Any) -> can.BusABC:
    """A python-can bus by interface name, with the settings each needs here."""
    if interface not in INTERFACES:
        raise ValueError(f"bus: interface: expected one of {', '.join(INTERFACES)}, got {interface!r}")
    if interface == "slcan":
        kwargs.setdefault("sleep_after_open", 0)  # else each open costs 2 s
    if bitrate is not None and interface != "virtual":
        kwargs["bitrate"] = bitrate
    if interface == "virtual":
        kwargs.setdefault("receive_own_messages", False)
    if interface == "socketcand":
        kwargs.setdefault("tcp_tune", True)  # TCP_NODELAY + QUICKACK: else Nagle and delayed ACKs cost ~40 ms a cycle
    return can.Bus(interface=interface, channel=channel, **kwargs)


class Lockstep:
    """Networks in one process that deliver each other's frames on the sending thread."""

    def __init__(self) -> None:
        self.networks: list[LockstepNetwork] = []
        self._settling = False

    def settle(self) -> None:
        """Deliver every pending frame to its network until all buses are quiet."""
        if self._settling:
            return  # a callback sent a frame: the outer settle delivers it
        self._settling = True
        try:
            busy = True
            while busy:
                busy = False
                for net in self.networks:
                    if net.pump():
                        busy = True
        finally:
            self._settling = False


class LockstepNetwork(canopen.Network):
    """A canopen Network without a notifier thread: frames are pumped by :class:`Lockstep`."""

    def __init__(self, bus: can.BusABC, lockstep: Lockstep):
        super().__init__(bus)
        self.lockstep = lockstep
        lockstep.networks.append(self)
        self._recv = bus.recv
        self.log: can.Listener | None = None
        self.recv_error: can.CanError | None = None
        #: every received frame is checked before canopen's dispatch (driver/frame_guard.py)
        self.frame_guard = FrameGuard()
        self.handler_errors = 0

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        super().send_message(can_id, data, remote)
        if self.log is not None:
            self.log.on_message_received(_logged(can_id, data, remote, rx=False))
        self.lockstep.settle()
        if self.recv_error is not None:
            exc, self.recv_error = self.recv_error, None
            raise exc

    def pump(self) -> bool:
        """Deliver the frames waiting on this network's bus; True if there were any. A bus that raises
        on receive keeps the error for its own next send (another node's send must not fail for it)."""
        got = False
        recv = self._recv
        notify = self.notify
        log = self.log
        while True:
            try:
                msg = recv(0)
            except can.CanError as exc:
                self.recv_error = exc
                return False
            if msg is None:
                break
            got = True
            if log is not None:
                log.on_message_received(msg)
            if not msg.is_error_frame and self.frame_guard.accept(msg.arbitration_id, msg.data, msg.is_remote_frame):
                try:
                    notify(msg.arbitration_id, msg.data, msg.timestamp)
                except Exception as exc:  # noqa: BLE001 - as canopen's MessageListener: one frame's handler
                    # must not end the pump (in lockstep that would be the sender's cycle); counted, logged
                    self.handler_errors += 1
                    _log_handler_error(msg.arbitration_id, exc, self.handler_errors)
        return got

    def disconnect(self) -> None:
        if self.log is not None:
            self.log.stop()
            self.log = None
        if self in self.lockstep.networks:
            self.lockstep.networks.remove(self)
        if self.bus is not None:
            self.bus.shutdown()
        self.bus = None


class GuardedListener(canopen.network.MessageListener):
    """canopen's MessageListener with the frame checks of driver/frame_guard.py before its dispatch."""

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame:
            return
        net = self.network
        if net.frame_guard.accept(msg.arbitration_id, msg.data, msg.is_remote_frame):
            try:
                net.notify(msg.arbitration_id, msg.data, msg.timestamp)
            except Exception as exc:  # noqa: BLE001 - the notifier thread must go on
                net.handler_errors = getattr(net, "handler_errors", 0) + 1
                _log_handler_error(msg.arbitration_id, exc, net.handler_errors)


def _log_handler_error(can_id: int, exc: Exception, count: int) -> None:
    if count == 1 or count % 1000 == 0:  # rate-limited: a flood of one bad frame is one line per 1000
        log.warning("frame 0x%03X: its handler raised %s: %s (%d so far; frame dropped)", can_id,
                    type(exc).__name__, exc, count)


def threaded_network(bus: can.BusABC) -> canopen.Network:
    """A canopen Network driven by a python-can Notifier (for buses that cross processes); every frame
    checked by a :class:`FrameGuard` before canopen's dispatch."""
    net = canopen.Network(bus)
    net.frame_guard = FrameGuard()
    net.handler_errors = 0
    net.listeners = [GuardedListener(net)]
    net.NOTIFIER_CYCLE = 0.05  # teardown waits up to one cycle; canopen's default is 1 s
    net.notifier = can.Notifier(bus, net.listeners, net.NOTIFIER_CYCLE)
    return net


def _logged(can_id: int, data: bytes, remote: bool, rx: bool) -> can.Message:
    return can.Message(timestamp=time.time(), arbitration_id=can_id, data=bytes(data), is_remote_frame=remote,
                       is_extended_id=can_id > 0x7FF, is_rx=rx)


def attach_bus_log(network: LockstepNetwork, path: str) -> can.Listener:
    """Record every frame the network sends and receives (on a bus: every frame) through python-can's
    Logger, the format chosen by the file's suffix (.asc, .blf, .log, .csv, .trc)."""
    try:
        logger = can.Logger(path)
    except ValueError as exc:
        raise ValueError(f"--bus-log {path}: {exc}") from None
    network.log = logger
    return logger


def close_threaded(net: canopen.Network) -> None:
    """Stop the notifier (its listeners, a bus log among them, are stopped too), then the bus."""
    if net.notifier is not None:
        net.notifier.stop(1.0)
        for listener in net.notifier.listeners:
            if isinstance(listener, can.Listener) and not isinstance(listener, canopen.network.MessageListener):
                listener.stop()
        net.notifier = None
    if net.bus is not None:
        net.bus.shutdown()
        net.bus = None

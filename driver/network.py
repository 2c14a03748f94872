"""CAN buses and canopen networks: opened by python-can's own interface names, pumped in lockstep.

``virtual`` (the in-process bus) runs in lockstep: every frame a network sends is delivered, on the
sending thread, to every network of the same :class:`Lockstep` until the bus is quiet; a reply (an SDO
response, the TPDOs answering a SYNC) is therefore already received when the send returns. No
notifier thread, so the order of frames never depends on timing and the same run gives the same trace
bit for bit. Unpaced, the networks' buses are the Lockstep's own (:meth:`Lockstep.bus`,
driver/lockstep_bus.py: frames handed over without copies); a run paced on the wall clock keeps
python-can's virtual bus (:func:`open_bus`). Other interfaces (slcan, socketcand, socketcan) cross a process
boundary: their networks are driven by a python-can Notifier as usual.
"""

from __future__ import annotations

import itertools
import logging
import os
import time
from collections.abc import Callable
from typing import Any

import can
import canopen

from drivectl.driver.axis import AxisConfigError
from drivectl.driver.frame_guard import FrameGuard
from drivectl.driver.lockstep_bus import LockstepBus, LockstepLink
from drivectl.driver.socketcand_client import SocketcandClientBus, probe_socketcand

log = logging.getLogger("drivectl.frames")

#: the interfaces opened with settings of their own here (the rest: python-can's defaults and [bus.options])
SPECIAL_INTERFACES = ("virtual", "slcan", "socketcand", "socketcan")
#: every interface name python-can knows (PCAN, Kvaser, IXXAT, Vector, gs_usb, ...): open_bus takes them all
INTERFACES: tuple[str, ...] = tuple(sorted(can.interfaces.VALID_INTERFACES))
#: keys a [bus.options] table may not set: they have keys of their own in [bus]
RESERVED_OPTIONS = frozenset({"interface", "bustype", "channel", "bitrate", "host", "port", "can_filters"})

_channel_counter = itertools.count()


class BusOpenError(AxisConfigError):
    """The bus could not be opened (driver library or device missing, nothing listening): bad input, one
    line naming the interface and what python-can said, raised before anything moved."""


def unique_virtual_channel(prefix: str = "drivectl") -> str:
    """A channel name no other bus of this process uses (virtual channels are process-global)."""
    return f"{prefix}-{os.getpid()}-{next(_channel_counter)}"


def open_bus(interface: str, channel: str | int, bitrate: int | None = None, **kwargs: Any) -> can.BusABC:
    """A python-can bus by interface name, with the settings each needs here; ``kwargs`` (the [bus.options]
    table, host/port for socketcand) go to ``can.Bus`` as they are and win over the defaults set here.

    Any failure to open is one :class:`BusOpenError` line: python-can's own message (and what it logged
    while trying: Kvaser's "canlib is unavailable" comes only as a log record), never its traceback."""
    if interface not in INTERFACES:
        raise BusOpenError(f"bus.interface: {interface!r} is not an interface python-can knows "
                           f"(one of {', '.join(INTERFACES)})")
    if interface == "slcan":
        kwargs.setdefault("sleep_after_open", 0)  # else each open costs 2 s
    if bitrate is not None and interface != "virtual":
        kwargs["bitrate"] = bitrate
    if interface == "virtual":
        kwargs.setdefault("receive_own_messages", False)
    where = f"bus {interface}:{channel}"
    if interface == "socketcand":
        kwargs.setdefault("tcp_tune", True)  # TCP_NODELAY + QUICKACK: else Nagle and delayed ACKs cost ~40 ms a cycle
        host, port = kwargs.get("host", "127.0.0.1"), kwargs.get("port", 29536)
        where = f"bus socketcand {host}:{port} ({channel})"
        probe_socketcand(where, host, port, BusOpenError)
    with _CanLogCapture() as captured:
        try:
            bus = _construct(interface, channel, kwargs)
        except Exception as exc:  # noqa: BLE001 - python-can raises anything here (Kvaser without canlib: NameError)
            said = _what_python_can_said(interface, exc, captured.records)
            raise BusOpenError(f"{where}: cannot open: {said}") from None
    captured.replay()
    return bus


def _construct(interface: str, channel: str | int, kwargs: dict[str, Any]) -> can.BusABC:
    if interface == "socketcand":
        return SocketcandClientBus.connect(channel, **kwargs)
    return can.Bus(interface=interface, channel=channel, **kwargs)


class _CanLogCapture(logging.Handler):
    """Holds python-can's log records while a bus opens: on failure they complete the one-line error,
    on success the distinct ones are replayed once (never a flood: at most a few records are kept)."""

    KEEP = 8

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []
        self.dropped = 0
        self._logger = logging.getLogger("can")

    def emit(self, record: logging.LogRecord) -> None:
        if record.levelno < logging.WARNING:
            return
        if len(self.records) < self.KEEP and all(r.getMessage() != record.getMessage() for r in self.records):
            self.records.append(record)
        else:
            self.dropped += 1

    def __enter__(self) -> _CanLogCapture:
        self._propagate = self._logger.propagate
        self._logger.addHandler(self)
        self._logger.propagate = False
        return self

    def __exit__(self, *exc: object) -> None:
        self._logger.removeHandler(self)
        self._logger.propagate = self._propagate

    def replay(self) -> None:
        for record in self.records:
            logging.getLogger(record.name).handle(record)


#: what python-can logged when an interface's module loaded without its library: it says so only once,
#: at import, and the next open fails with nothing but a NameError
_LOAD_NOTES: dict[str, str] = {}


def _what_python_can_said(interface: str, exc: BaseException, records: list[logging.LogRecord]) -> str:
    said = " ".join(str(exc).split()) or type(exc).__name__
    logged = [m for m in (" ".join(r.getMessage().split()) for r in records) if m and m not in said]
    if isinstance(exc, NameError | AttributeError):
        # python-can's vendor modules load without their library (logging that it is missing) and fail
        # on its first call: the log record is what says why
        said = f"{type(exc).__name__}: {said}"
        if logged:
            _LOAD_NOTES[interface] = logged[0].rstrip(".")
        why = _LOAD_NOTES.get(interface, "its driver library did not load")
        said = f"{why} (python-can then failed: {said})"
    return said if len(said) <= 400 else said[:397] + "..."


class Lockstep:
    """Networks in one process that deliver each other's frames on the sending thread."""

    def __init__(self) -> None:
        self.networks: list[LockstepNetwork] = []
        self._settling = False
        #: the devices' own clocks (emulated drives): advance(seconds) lets simulated time pass
        self.clocks: list[Callable[[float], None]] = []
        #: the devices' wall clocks (an emulated drive's ``wall_clock(now)``), served while a run is paced
        self.wall_clocks: list[Callable[[float | None], None]] = []
        self._wall: Callable[[], float] | None = None
        self._links: dict[str, LockstepLink] = {}
        #: asked once with the wall time the devices get just before the next delivery (a paced SYNC's slip:
        #: driver/sync_clock.SyncClock.tick), then cleared
        self.at_delivery: Callable[[float], None] | None = None

    def bus(self, channel: str) -> LockstepBus:
        """A new end of this lockstep's in-process bus ``channel`` (driver/lockstep_bus.py): the ends
        of one channel receive each other's frames, the same Message objects, without copies."""
        link = self._links.get(channel)
        if link is None:
            link = self._links[channel] = LockstepLink(channel)
        return link.open()

    def pace(self, wall: Callable[[], float] | None) -> None:
        """A run paced on the wall clock ``wall`` starts (None: it ended). While it lasts the devices run on
        that clock as they do across processes: each gets the wall time before every delivery (the time
        that passed while the master was silent, a late master's included, runs on the device) and after
        it (SYNC-locked at the frame's arrival); see plant_emulator/node402.EmulatedDrive.wall_clock."""
        if wall is self._wall:
            return  # several axes of one bus: once
        self._wall = wall
        if wall is None:
            for clock in list(self.wall_clocks):
                clock(None)
        else:
            self._serve_wall(wall)

    def advance(self, seconds: float) -> None:
        """Let ``seconds`` of simulated time pass on every device clock (a master waiting for a boot-up:
        in lockstep nothing else makes time go on), then deliver what that sent."""
        for clock in list(self.clocks):
            clock(seconds)
        self.settle()

    def settle(self) -> None:
        """Deliver every pending frame to its network until all buses are quiet."""
        if self._settling:
            return  # a callback sent a frame: the outer settle delivers it
        self._settling = True
        try:
            wall = self._wall
            if wall is not None:  # paced: the devices' clocks up to this frame, then to its arrival
                now = self._serve_wall(wall)
                hook, self.at_delivery = self.at_delivery, None
                if hook is not None:
                    hook(now)
                self._deliver()
                self._serve_wall(wall)
            self._deliver()
        finally:
            self._settling = False

    def _deliver(self) -> None:
        networks = self.networks
        busy = True
        while busy:
            busy = False
            for net in networks:
                inbox = net._inbox  # a lockstep bus with nothing waiting is skipped without a call
                if (inbox is None or inbox) and net.pump():
                    busy = True

    def _serve_wall(self, wall: Callable[[], float]) -> float:
        now = wall()
        for clock in self.wall_clocks:
            clock(now)
        return now

    @property
    def paced(self) -> bool:
        """A run paced on the wall clock is under way (:meth:`pace`)."""
        return self._wall is not None


#: canopen's NodeScanner records the node of these services (canopen/network.py NodeScanner.SERVICES)
_SCANNED = frozenset(canopen.network.NodeScanner.SERVICES)


class LockstepNetwork(canopen.Network):
    """A canopen Network without a notifier thread: frames are pumped by :class:`Lockstep`.

    Dispatch per COB-ID: once a subscribed COB-ID has gone through canopen's ``notify``, its frames go
    straight to canopen's own subscriber list for it (the live list, never a copy: a callback that
    subscribes or unsubscribes another on the same COB-ID mid-run is seen on the very next frame, as
    canopen sees it), then to the node scanner where canopen would call it. ``subscribe`` and
    ``unsubscribe`` drop the entry, so a list canopen replaces is looked up again."""

    def __init__(self, bus: can.BusABC, lockstep: Lockstep):
        #: COB-ID -> (canopen's live callback list for it, whether its node scanner looks at it); before
        #: canopen's constructor, which subscribes already
        self._dispatch: dict[int, tuple[list[Any], bool]] = {}
        super().__init__(bus)
        self.lockstep = lockstep
        lockstep.networks.append(self)
        self._recv = self._bus_recv = bus.recv
        #: a lockstep bus's inbox, peeked at before pumping (:meth:`LockstepBus.pending` without the call; None on
        #: other buses: always polled, e.g. a FaultyBus that raises on receive)
        self._inbox = bus.inbox if isinstance(bus, LockstepBus) else None
        self.log: BusLog | None = None
        self.recv_error: can.CanError | None = None
        #: every received frame is checked before canopen's dispatch (driver/frame_guard.py); None on an
        #: emulated drive's network (the drive checks its frames itself, with CiA 301's EMCY reactions)
        self.frame_guard: FrameGuard | None = FrameGuard()
        self.handler_errors = 0

    def subscribe(self, can_id: int, callback: Any) -> None:
        super().subscribe(can_id, callback)
        self._dispatch.pop(can_id, None)

    def unsubscribe(self, can_id: int, callback: Any = None) -> None:
        self._dispatch.pop(can_id, None)
        super().unsubscribe(can_id, callback)

    def _learn(self, can_id: int) -> None:
        callbacks = self.subscribers.get(can_id)
        if callbacks is not None:
            self._dispatch[can_id] = (callbacks, can_id & 0x7F != 0 and can_id & 0x780 in _SCANNED)

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        """canopen's ``Network.send_message`` (the override point it names for a custom backend): the same
        frame, a new :class:`can.Message` built as canopen builds it, sent under its ``send_lock``; its
        ``check()`` is left out (it raises what a notifier thread caught, and this network has none).
        Then every frame this caused is delivered (unless a delivery is already under way further up
        this thread's stack: that one goes on until the bus is quiet)."""
        bus = self.bus
        if not bus:
            raise RuntimeError("Not connected to CAN bus")
        # positional, in can.Message's own order (timestamp, arbitration_id, is_extended_id, is_remote_frame,
        # is_error_frame, channel, dlc, data): keywords cost a dict per frame (0.3 us of its 0.9)
        msg = can.Message(0.0, can_id, can_id > 0x7FF, remote, False, None, None, data)
        with self.send_lock:
            bus.send(msg)
        if self.log is not None:
            self.log.sent(can_id, data, remote)
        lockstep = self.lockstep
        if not lockstep._settling:
            lockstep.settle()
        if self.recv_error is not None:
            exc, self.recv_error = self.recv_error, None
            raise exc

    def pump(self) -> bool:
        """Deliver the frames waiting on this network's bus; True if there were any. A bus that raises
        on receive keeps the error for its own next send (another node's send must not fail for it).
        :meth:`Lockstep._deliver` calls it only when the bus has frames waiting (or cannot tell)."""
        got = False
        recv = self._recv
        dispatch = self._dispatch
        log = self.log
        # the lockstep bus's own inbox, popped here as its recv() pops it when it filters nothing (no call
        # per frame, no last poll that returns None); not when another receive was put in place of the
        # bus's (e.g. a test's frame injector) or the bus filters
        inbox = self._inbox
        if inbox is not None and (recv is not self._bus_recv or self.bus is None or self.bus._filters is not None):
            inbox = None
        guard = self.frame_guard
        while True:
            if inbox is not None:
                if not inbox:
                    break
                msg = inbox.popleft()
            else:
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
            if msg.is_remote_frame and (guard is None or msg.arbitration_id in self.__dict__.get(
                    "remote_subscribers", {})):
                deliver_remote(self, msg.arbitration_id)  # an emulated drive's RTR handler, never as data
            elif not msg.is_error_frame and (guard is None or guard.accept(msg.arbitration_id, msg.data,
                                                                           msg.is_remote_frame)):
                can_id = msg.arbitration_id
                try:
                    route = dispatch.get(can_id)
                    if route is None:
                        self.notify(can_id, msg.data, msg.timestamp)
                        self._learn(can_id)
                    else:  # what canopen's notify does, without looking the COB-ID up again
                        data, timestamp = msg.data, msg.timestamp
                        for callback in route[0]:
                            callback(can_id, data, timestamp)
                        if route[1]:
                            self.scanner.on_message_received(can_id)
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


def deliver_remote(network: canopen.Network, can_id: int) -> None:
    """A remote frame (RTR) to the callbacks in ``network.remote_subscribers`` (canopen's notify() has no
    RTR bit, so a remote frame handed to it would look like an empty data frame)."""
    for callback in list(network.__dict__.get("remote_subscribers", {}).get(can_id, ())):
        callback(can_id)


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


class BusLog(can.Listener):
    """A python-can Logger (format by the file's suffix: .asc, .blf, .log, .csv, .trc) that stamps every
    frame, sent or received, with one clock: the host's ``time.time()`` when this process sends or receives
    it. Received frames arrive stamped by whoever received them first (the kernel, an adapter's own
    counter, PCAN's boot-relative clock, the socketcand server's text), so they are restamped here."""

    def __init__(self, path: str) -> None:
        try:
            self.logger = can.Logger(path)
        except ValueError as exc:
            raise ValueError(f"--bus-log {path}: {exc}") from None
        self.path = path
        self._stopped = False

    def on_message_received(self, msg: can.Message) -> None:
        self.logger.on_message_received(can.Message(
            timestamp=time.time(), arbitration_id=msg.arbitration_id, is_extended_id=msg.is_extended_id,
            is_remote_frame=msg.is_remote_frame, is_error_frame=msg.is_error_frame, channel=msg.channel,
            dlc=msg.dlc, data=msg.data, is_fd=msg.is_fd, is_rx=msg.is_rx, bitrate_switch=msg.bitrate_switch,
            error_state_indicator=msg.error_state_indicator, check=False))

    def sent(self, can_id: int, data: bytes, remote: bool = False) -> None:
        """A frame this process sent (python-can buses do not echo them)."""
        self.logger.on_message_received(_logged(can_id, data, remote, rx=False))

    def stop(self) -> None:
        if not self._stopped:  # the notifier stops its listeners and close_threaded does too
            self._stopped = True
            self.logger.stop()


def _logged(can_id: int, data: bytes, remote: bool, rx: bool) -> can.Message:
    return can.Message(timestamp=time.time(), arbitration_id=can_id, data=bytes(data), is_remote_frame=remote,
                       is_extended_id=can_id > 0x7FF, is_rx=rx)


def log_sent_frames(network: canopen.Network, log: BusLog) -> None:
    """Wrap ``network.send_message`` so that every frame it sends is logged after it went out."""
    send = network.send_message

    def send_and_log(can_id: int, data: bytes, remote: bool = False) -> None:
        send(can_id, data, remote)
        log.sent(can_id, data, remote)

    network.send_message = send_and_log  # type: ignore[method-assign]


def attach_bus_log(network: canopen.Network, path: str) -> BusLog:
    """Record every frame the network sends and receives (on a bus: every frame) on one clock
    (:class:`BusLog`). A lockstep network logs in its own send/pump; a threaded one gets the log as a
    notifier listener (stopped by :func:`close_threaded`) and its sends wrapped."""
    log = BusLog(path)
    if isinstance(network, LockstepNetwork):
        network.log = log
    else:
        network.notifier.add_listener(log)
        log_sent_frames(network, log)
    return log


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

"""The in-process bus of a lockstep run: frames handed from one end to the others without copies.

python-can's ``virtual`` bus is made for threads: each send deep-copies the frame once per receiver
and puts it on a thread-safe queue, and each ``recv(0)`` on an empty queue raises and catches
``queue.Empty`` and reads the clock. A lockstep run (driver/network.py :class:`Lockstep`) has one
thread and delivers every frame on the sender's call, so none of that is needed: half of its cycle
went there. :class:`LockstepBus` is a ``can.BusABC`` whose ``send`` stamps the frame (timestamp,
channel, direction, as the virtual bus stamps its copies) and appends the same :class:`can.Message`
to a deque of every other end of the link; ``recv`` pops one, or returns None at once.

The contract (docs/lockstep-bus.md): **nobody modifies a Message after sending it** (canopen builds a
new one per ``send_message``; every sender in drivectl does the same), and the receivers only read
it. Frames stay real ``can.Message`` objects, one per frame, delivered in the order they were sent;
wrappers (FaultyBus, the bus log, the frame guard) see exactly what they saw on the virtual bus.

Single thread only: no locks. Paced runs, other interfaces and cross-process runs keep python-can's
buses (driver/network.py :func:`open_bus`).
"""

from __future__ import annotations

import time
from collections import deque

import can


class LockstepLink:
    """The wire: the ends attached to one lockstep channel."""

    def __init__(self, channel: str) -> None:
        self.channel = channel
        self.ends: list[LockstepBus] = []

    def open(self) -> LockstepBus:
        """A new end on this link (it receives every frame any other end sends from now on)."""
        return LockstepBus(self)


class LockstepBus(can.BusABC):
    """One end of a :class:`LockstepLink`: ``send`` hands the frame itself to every other end."""

    def __init__(self, link: LockstepLink) -> None:
        self.link = link
        #: the frames waiting here, oldest first (read only by :meth:`recv`; the lockstep pump peeks at it)
        self.inbox: deque[can.Message] = deque()
        self._peers: tuple[deque[can.Message], ...] = ()
        super().__init__(channel=link.channel)
        self.channel_info = f"lockstep bus channel {link.channel}"
        link.ends.append(self)
        self._relink()

    def _relink(self) -> None:
        # every end's peer inboxes, computed when an end comes or goes (never per frame)
        for end in self.link.ends:
            end._peers = tuple(e.inbox for e in self.link.ends if e is not end)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Stamp ``msg`` as the virtual bus stamps what it delivers (time.time(), the channel, received)
        and append it to every other end's inbox. The caller must not modify ``msg`` afterwards."""
        if self._is_shutdown:
            raise can.CanOperationError("Cannot operate on a closed bus")
        msg.timestamp = time.time()
        msg.channel = self.link.channel
        msg.is_rx = True  # as every receiver sees it (nobody receives its own frames here)
        for inbox in self._peers:
            inbox.append(msg)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """The oldest frame waiting, or None at once: in lockstep nothing can arrive while waiting
        (every frame is sent on the one thread), so ``timeout`` never blocks."""
        inbox = self.inbox
        filters = self._filters
        while inbox:
            msg = inbox.popleft()
            if filters is None or self._matches_filters(msg):
                return msg
        if self._is_shutdown:
            raise can.CanOperationError("Cannot operate on a closed bus")
        return None

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        inbox = self.inbox
        return (inbox.popleft() if inbox else None), False

    def pending(self) -> int:
        """How many frames wait here (a peek: the pump skips an end with none)."""
        return len(self.inbox)

    def shutdown(self) -> None:
        if self._is_shutdown:
            return
        super().shutdown()
        if self in self.link.ends:
            self.link.ends.remove(self)
            self._relink()
        self._peers = ()
        self.inbox.clear()

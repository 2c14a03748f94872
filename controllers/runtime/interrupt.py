"""Ctrl-C and SIGTERM as a request the servo loop reads at a cycle boundary.

Python's default SIGINT handler raises KeyboardInterrupt at whatever bytecode runs. In the servo
loop that can be inside ``queue.Queue.get`` with the queue's lock held (python-can's virtual bus, the
SLCAN reader), after which the quick stop itself blocks on that lock for ever with the drive enabled:
1 Ctrl-C in 60 hung that way under load. So the handler only records the signal; the loop checks it
once per cycle, between whole frames, and stops the axis from there. A second signal says that the
stop is under way; a third restores the default action and kills the process at once (the drive's
own watchdogs, RPDO deadline and master heartbeat 0x1016, then stop the axis).
"""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager

#: the signals that stop a run safely: Ctrl-C and the service manager's stop
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)

_active: StopRequest | None = None  # the request the signals go to now, if any


class StopRequest:
    """Set by a signal handler, read once per cycle: ``signum`` is 0 until the first signal."""

    __slots__ = ("signum", "count")

    def __init__(self) -> None:
        self.signum = 0
        self.count = 0

    @property
    def name(self) -> str:
        """The first signal's name (``SIGINT``), or "" when none came."""
        return signal.Signals(self.signum).name if self.signum else ""

    def handle(self, signum: int, frame: object = None) -> None:  # noqa: ARG002 - signal handler signature
        """The signal handler: never raises, so nothing in flight is torn in half."""
        self.count += 1
        if self.count == 1:
            self.signum = signum
        elif self.count == 2:
            # os.write, not print: a handler may run inside a print to the same stream
            os.write(2, b"drivectl: stopping the axis safely; signal once more to kill at once\n")
        else:
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)


@contextmanager
def stop_on_signals(request: StopRequest | None = None,
                    signums: Sequence[int] = STOP_SIGNALS) -> Iterator[StopRequest]:
    """Route ``signums`` into ``request`` inside the block, then restore the previous handlers.

    With ``request=None`` an enclosing block's request is reused (a run inside a command that routes
    the signals already sees a signal that came between two runs), else a new one is made. Outside
    the main thread handlers cannot be set, and no signal is delivered there either: the request is
    yielded as it is."""
    global _active
    if request is None and _active is not None:
        yield _active
        return
    request = StopRequest() if request is None else request
    if threading.current_thread() is not threading.main_thread():
        yield request
        return
    previous = {s: signal.signal(s, request.handle) for s in signums}
    outer, _active = _active, request
    try:
        yield request
    finally:
        _active = outer
        for s, handler in previous.items():
            signal.signal(s, signal.SIG_DFL if handler is None else handler)


def exit_code(request: StopRequest) -> int:
    """The shell's code for a command ended by the request's signal: 130 SIGINT, 143 SIGTERM."""
    return 128 + request.signum

"""Who sends the SYNC: the master's loop (one frame per cycle, as late as the loop), or the transport's own
periodic transmit, off the Python thread.

On SocketCAN python-can's ``send_periodic`` hands the frame to the kernel's broadcast manager (BCM): a
kernel hrtimer sends it, so the SYNC period does not inherit the loop's wake-up jitter, its GIL waits or
its garbage collection. Some adapters' drivers do the same in their firmware (python-can's native cyclic
tasks). Where python-can would only start a Python thread (``ThreadBasedCyclicSendTask``) that is no better
than the loop, so the loop keeps sending it (see :func:`start_periodic_sync`).

While the transport sends the SYNC, the master counts the SYNCs it sees on the bus (a frame the kernel
sent reaches the other sockets of the interface as any frame does) and each cycle waits for the next one
instead of sending it: the loop then runs on the SYNC's clock and uses that SYNC's TPDOs. A SYNC that
comes less than half a period after the last one is a second producer on the bus (ROGUE_SYNC). The
kernel's timer and the loop's ``perf_counter`` are both CLOCK_MONOTONIC, so a loop paced from the moment
the periodic transmit started stays in phase with it.
"""

from __future__ import annotations

import threading
from typing import Any

import can

#: how long a cycle waits for the transport's next SYNC before the SYNC is taken as lost, in periods
#: (the drives' own SYNC-loss watchdog is the safety net; this only keeps the loop from hanging)
SYNC_WAIT_PERIODS = 20


class PeriodicSync:
    """The SYNC sent by the transport (``task``), counted as it appears on the bus."""

    def __init__(self, task: Any, dt: float):
        self.task = task
        self.dt = dt
        self.seen = 0
        self.last_ts: float | None = None
        self.rogue = False
        self._event = threading.Event()
        self._lock = threading.Lock()

    def on_sync(self, can_id: int, data: bytes, timestamp: float) -> None:
        """Subscriber of the SYNC COB-ID (the notifier thread)."""
        with self._lock:
            if self.last_ts is not None and timestamp - self.last_ts < 0.5 * self.dt:
                self.rogue = True  # two producers: ours and another
            self.last_ts = timestamp
            self.seen += 1
        self._event.set()

    def wait_beyond(self, cycle: int) -> int:
        """Block until more than ``cycle`` SYNCs were seen; the count seen (``cycle`` itself if none came
        within :data:`SYNC_WAIT_PERIODS` periods)."""
        while self.seen <= cycle:
            self._event.clear()
            if self.seen > cycle:
                break
            if not self._event.wait(SYNC_WAIT_PERIODS * self.dt):
                return self.seen
        return self.seen

    def stop(self) -> None:
        self.task.stop()


def start_periodic_sync(bus: can.BusABC, cob_id: int, dt: float) -> tuple[PeriodicSync | None, str]:
    """Start the SYNC as the transport's periodic transmit where it runs off the Python thread; returns
    (the sync, "") or (None, why the loop keeps sending it)."""
    msg = can.Message(arbitration_id=cob_id, data=b"", is_extended_id=False)
    try:
        task = bus.send_periodic(msg, dt, store_task=False)
    except (can.CanError, NotImplementedError, OSError, ValueError) as exc:
        return None, f"{type(bus).__name__}: no periodic transmit ({exc})"
    if isinstance(task, can.broadcastmanager.ThreadBasedCyclicSendTask):
        task.stop()  # python-can's fallback is a Python thread: no steadier than the loop itself
        return None, f"{type(bus).__name__}: periodic transmit would be a Python thread"
    return PeriodicSync(task, dt), ""

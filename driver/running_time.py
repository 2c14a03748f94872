"""Waits for a peer's answer that count only the time this process was running.

A timeout on the wall clock blames the peer for time in which the waiter itself did not run: a host or a
VM that stalls the whole process (a loaded machine, a niced or software-emulated VM) lets a wall-clock
wait expire while the answer already sits in the socket, unread because the notifier thread did not run
either. Here a wait is cut into short slices, and a slice that overran its length by far was time this
process was not scheduled: it counts as its nominal length only, so the peer always gets ``timeout``
seconds of the waiter's own running time. A truly silent peer is still given up on, after at most
``timeout / SLICE_S`` slices. Only for answers without a real-time deadline (SDO, boot-up, the TPDOs of
a run not paced on the wall clock); a paced run's deadlines stay on the wall clock.
"""

from __future__ import annotations

import queue
import struct
import threading
import time
from collections.abc import Callable
from typing import Any

from canopen.sdo.client import SdoClient
from canopen.sdo.constants import RESPONSE_ABORTED
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

#: the slice a wait is cut into (s)
SLICE_S = 0.02
#: a slice that took longer than this factor times its length (plus a scheduler tick) was a stall
STALL_FACTOR = 3.0
_TICK_S = 0.004


def _counted(step: float, took: float) -> float:
    """The time a slice of ``step`` s that took ``took`` s counts for."""
    return step if took > STALL_FACTOR * step + _TICK_S else took


def wait_running(event: threading.Event, timeout: float, clock: Callable[[], float] = time.monotonic,
                 wall_limit: float | None = None) -> bool:
    """``event.wait(timeout)`` with ``timeout`` in this process's running time; whether the event is set.
    ``wall_limit``: never wait longer than this on the wall clock either (the peer's own watchdog runs on its
    wall clock), except for one more slice after a stall: what arrived while this process did not run is
    taken before giving up."""
    counted = 0.0
    start = clock()
    stalled = False
    while True:
        step = min(SLICE_S, timeout - counted)
        if step <= 0:
            return event.is_set()
        if wall_limit is not None and clock() - start >= wall_limit:
            if not stalled:
                return event.is_set()
            step = SLICE_S  # the grace slice
        t0 = clock()
        if event.wait(step):
            return True
        took = clock() - t0
        stalled = took > STALL_FACTOR * step + _TICK_S
        counted += step if stalled else took


def get_running(q: queue.Queue, timeout: float, clock: Callable[[], float] = time.monotonic) -> Any:
    """``q.get(timeout=timeout)`` with ``timeout`` in this process's running time (raises queue.Empty)."""
    counted = 0.0
    while True:
        step = min(SLICE_S, timeout - counted)
        if step <= 0:
            return q.get_nowait()
        t0 = clock()
        try:
            return q.get(timeout=step)
        except queue.Empty:
            counted += _counted(step, clock() - t0)


class RunningTimeSdoClient(SdoClient):
    """canopen's SDO client, waiting ``RESPONSE_TIMEOUT`` of this process's running time for each answer."""

    def read_response(self) -> bytes:
        try:
            response = get_running(self.responses, self.RESPONSE_TIMEOUT)
        except queue.Empty:
            raise SdoCommunicationError("No SDO response received") from None
        (res_command,) = struct.unpack_from("B", response)
        if res_command == RESPONSE_ABORTED:
            (abort_code,) = struct.unpack_from("<L", response, 4)
            raise SdoAbortedError(abort_code)
        return response

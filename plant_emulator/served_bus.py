"""What the emulator's device-side buses share: SLCAN adapter (slcan.py) and socketcand server
(socketcand.py) each run one background I/O thread that talks the protocol and queues the frames
the client transmits; python-can's ``recv`` takes them from that queue."""

from __future__ import annotations

import logging
import queue
import threading

import can

log = logging.getLogger(__name__)

#: frames a client may have sent that the emulator has not read yet (10 s of a busy 1 kHz two-axis bus)
RX_QUEUE_FRAMES = 65536


class _Shutdown:
    """Queue sentinel: wakes a blocked ``_recv_internal`` when the bus shuts down."""


class ServedBus(can.BusABC):
    """The python-can template (``send`` / ``_recv_internal`` / ``shutdown``) around an I/O thread.

    A subclass sets :attr:`label`, calls :meth:`_init_io` before starting its thread with
    :meth:`_start_io`, puts received frames with ``self._rx.put``, ends its loop when ``_stopping``
    is set, and implements :meth:`_wake` (interrupt the thread's select) and :meth:`_close_io`.
    """

    label = "served bus"  # as errors name it: "slcan adapter", "socketcand server"

    def _init_io(self) -> None:
        # queue.Queue, not SimpleQueue: CPython 3.11's SimpleQueue.get(timeout) can block for ever when a
        # signal interrupts it just before its deadline. Bounded: a client that floods faster than the
        # emulator reads loses frames (counted), it does not grow memory.
        self._rx: queue.Queue[can.Message | _Shutdown] = queue.Queue(maxsize=RX_QUEUE_FRAMES)
        self.rx_overruns = 0
        self._stopping = False
        self._thread: threading.Thread | None = None

    def _put_rx(self, msg: can.Message) -> None:
        """Queue a frame the client transmitted (I/O thread); dropped and counted when the queue is full."""
        try:
            self._rx.put_nowait(msg)
        except queue.Full:
            self.rx_overruns += 1
            if self.rx_overruns == 1:
                log.warning("%s: receive queue full (%d frames): frames dropped", self.label, RX_QUEUE_FRAMES)

    def _start_io(self, target: object, name: str) -> None:
        self._thread = threading.Thread(target=target, name=name, daemon=True)
        self._thread.start()

    def _check_open(self) -> None:
        if self._is_shutdown:
            raise can.CanOperationError(f"{self.label} is shut down")

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        try:
            item = self._rx.get(timeout=timeout)
        except queue.Empty:
            return None, False
        if isinstance(item, _Shutdown):
            self._rx.put(item)  # for any other waiter
            raise can.CanOperationError(f"{self.label} is shut down")
        return item, False

    def shutdown(self) -> None:
        if self._is_shutdown:
            return
        super().shutdown()
        self._stopping = True
        self._wake()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        while True:  # the sentinel must get in, also into a full queue
            try:
                self._rx.put_nowait(_Shutdown())
                break
            except queue.Full:
                try:
                    self._rx.get_nowait()
                except queue.Empty:
                    pass
        self._close_io()

    def _wake(self) -> None:
        raise NotImplementedError

    def _close_io(self) -> None:
        raise NotImplementedError

"""Who sends the SYNC (driver/sync_source.py): the transport's periodic transmit where it runs off the Python
thread, else the loop. The kernel's own (SocketCAN) is exercised in tests/test_socketcan.py and measured by
bench/sync_jitter.py; here the choice and the master's counting, on python-can's virtual bus."""

from __future__ import annotations

import can
import canopen
import pytest

from drivectl.driver.cia301 import HEARTBEAT_BASE, MASTER_NODE_ID, SYNC_COB_ID
from drivectl.driver.network import unique_virtual_channel
from drivectl.driver.sync_clock import SyncClock
from drivectl.driver.sync_source import PeriodicSync, start_periodic_sync


class _Task:
    stopped = False

    def stop(self) -> None:
        self.stopped = True


class _Sent(canopen.Network):
    def __init__(self) -> None:
        super().__init__()
        self.frames: list[int] = []
        self.bus = object()

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        self.frames.append(can_id)


def test_a_periodic_transmit_that_would_be_a_python_thread_leaves_the_sync_to_the_loop():
    bus = can.Bus(interface="virtual", channel=unique_virtual_channel())
    try:
        periodic, why = start_periodic_sync(bus, SYNC_COB_ID, 0.001)
        assert periodic is None and "Python thread" in why
        assert not [t for t in getattr(bus, "_periodic_tasks", []) if getattr(t, "thread", None)
                    and t.thread.is_alive()]
    finally:
        bus.shutdown()


def test_the_clock_counts_the_transports_syncs_and_a_late_loop_takes_the_latest():
    net = _Sent()
    clock = SyncClock(net, heartbeat_cycles=3)
    clock.tick()  # the loop's own SYNC (and the first heartbeat)
    assert net.frames == [SYNC_COB_ID, HEARTBEAT_BASE + MASTER_NODE_ID] and clock.cycle == 1
    p = clock.periodic = PeriodicSync(_Task(), 0.001)
    clock._periodic_base = clock.cycle
    p.on_sync(SYNC_COB_ID, b"", 10.000)
    clock.tick()
    assert clock.cycle == 2 and net.frames[2:] == []  # waited for the transport's SYNC, sent none
    for n in range(3):  # the loop slept through three SYNCs: it resumes at the latest, no burst
        p.on_sync(SYNC_COB_ID, b"", 10.001 + n * 0.001)
    clock.tick()
    assert clock.cycle == 5 and not p.rogue
    assert net.frames[2:] == [HEARTBEAT_BASE + MASTER_NODE_ID]  # cycle 4's heartbeat, skipped cycles or not
    p.on_sync(SYNC_COB_ID, b"", 10.0032)  # 0.2 periods after the last: a second producer
    assert p.rogue


def test_no_sync_from_the_transport_is_an_error_not_a_hang(monkeypatch):
    import drivectl.driver.sync_source as ss

    monkeypatch.setattr(ss, "SYNC_WAIT_PERIODS", 1)
    clock = SyncClock(_Sent())
    clock.periodic = PeriodicSync(_Task(), 0.001)
    with pytest.raises(can.CanOperationError, match="no SYNC from the periodic transmit"):
        clock.tick()

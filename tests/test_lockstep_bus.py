"""The lockstep bus (driver/lockstep_bus.py): frames handed to the other ends without copies, in order,
stamped as python-can's virtual bus stamps them; used by unpaced lockstep runs only."""

from __future__ import annotations

import can
import pytest

from drivectl.driver.lockstep_bus import LockstepBus, LockstepLink
from drivectl.driver.network import Lockstep, LockstepNetwork
from drivectl.machine.build import open_machine
from drivectl.machine.config import load_config


def test_send_hands_the_same_message_to_every_other_end_stamped_and_in_order():
    link = LockstepLink("t-lockstep-1")
    a, b, c = link.open(), link.open(), link.open()
    try:
        first = can.Message(arbitration_id=0x80, data=b"", is_extended_id=False)
        second = can.Message(arbitration_id=0x181, data=bytes([1, 2, 3]), is_extended_id=False)
        a.send(first)
        a.send(second)
        assert first.timestamp > 0 and first.channel == "t-lockstep-1" and first.is_rx
        assert a.pending() == 0 and b.pending() == 2 and c.pending() == 2  # nobody receives its own frames
        assert b.recv(0) is first and b.recv(0) is second  # the object itself: no copy
        assert c.recv(0) is first and c.recv(0) is second
        assert b.recv(0) is None and b.recv(5.0) is None  # returns at once: nothing can arrive in lockstep
    finally:
        for bus in (a, b, c):
            bus.shutdown()


def test_shutdown_detaches_the_end_and_a_closed_end_refuses():
    link = LockstepLink("t-lockstep-2")
    a, b = link.open(), link.open()
    b.shutdown()
    a.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))  # reaches no one, no error
    assert link.ends == [a]
    with pytest.raises(can.CanOperationError):
        b.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
    with pytest.raises(can.CanOperationError):
        b.recv(0)
    a.shutdown()


def test_filters_apply_as_on_any_python_can_bus():
    link = LockstepLink("t-lockstep-3")
    a = link.open()
    b = LockstepBus(link)
    b.set_filters([{"can_id": 0x181, "can_mask": 0x7FF}])
    try:
        a.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
        a.send(can.Message(arbitration_id=0x181, data=b"\x01", is_extended_id=False))
        msg = b.recv(0)
        assert msg is not None and msg.arbitration_id == 0x181 and b.recv(0) is None
    finally:
        a.shutdown()
        b.shutdown()


def test_networks_of_one_lockstep_deliver_on_the_senders_call():
    lockstep = Lockstep()
    one = LockstepNetwork(lockstep.bus("t-lockstep-4"), lockstep)
    two = LockstepNetwork(lockstep.bus("t-lockstep-4"), lockstep)
    got: list[tuple[int, bytes]] = []
    two.subscribe(0x601, lambda can_id, data, ts: got.append((can_id, bytes(data))))
    try:
        one.send_message(0x601, b"\x40\x00\x10\x00")
        assert got == [(0x601, b"\x40\x00\x10\x00")]
    finally:
        one.disconnect()
        two.disconnect()


@pytest.mark.parametrize("paced", [False, True])
def test_open_machine_uses_the_lockstep_bus_unless_paced(paced):
    cfg = load_config()
    with open_machine(cfg, ["x"], paced=paced) as m:
        net = m.axes["x"].network
        assert isinstance(net.bus, LockstepBus) is not paced
        assert isinstance(net.bus, can.BusABC)
        assert m.bus.startswith("virtual:")  # the configuration's interface, as the traces record it


def test_per_cob_id_dispatch_follows_canopens_live_subscriber_list():
    """A callback subscribed by another callback mid-run gets the very next frame (a snapshot of the list
    would miss it for one frame); an emptied and re-made list is looked up again."""
    lockstep = Lockstep()
    master = LockstepNetwork(lockstep.bus("t-lockstep-5"), lockstep)
    drive = LockstepNetwork(lockstep.bus("t-lockstep-5"), lockstep)
    seen: list[str] = []

    def late(can_id, data, ts):
        seen.append(f"late {data[0]}")

    def first(can_id, data, ts):
        seen.append(f"first {data[0]}")
        if data[0] == 1:
            drive.subscribe(0x201, late)  # canopen appends it to the list being iterated: this frame too

    drive.subscribe(0x201, first)
    try:
        for k in range(3):
            master.send_message(0x201, bytes([k]))
        assert seen == ["first 0", "first 1", "late 1", "first 2", "late 2"]
        drive.unsubscribe(0x201, first)
        drive.unsubscribe(0x201, late)  # canopen drops the emptied list
        drive.subscribe(0x201, late)  # and makes a new one
        master.send_message(0x201, bytes([3]))
        assert seen[-1] == "late 3" and len(seen) == 6
        assert drive.scanner.nodes == [] and master.scanner.nodes == []  # RPDOs: nothing for the scanner
        master.subscribe(0x181, lambda *a: None)
        drive.send_message(0x181, bytes([0]))  # a TPDO: canopen's scanner records its node, as before
        assert master.scanner.nodes == [1]
        master.scanner.reset()
        drive.send_message(0x181, bytes([0]))  # now through the per-COB-ID dispatch: the scanner still sees it
        assert master.scanner.nodes == [1]
    finally:
        master.disconnect()
        drive.disconnect()

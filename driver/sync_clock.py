"""The SYNC producer of one bus, shared by its axes (and the master's heartbeat producer)."""

from __future__ import annotations

import canopen

from drivectl.driver.cia301 import HEARTBEAT_BASE, MASTER_NODE_ID, SYNC_COB_ID, NmtState


class SyncClock:
    """The SYNC producer of one bus, shared by its axes; also the master's heartbeat producer
    (node ``MASTER_NODE_ID``, every ``heartbeat_cycles`` SYNCs), which the drives consume (0x1016)."""

    def __init__(self, network: canopen.Network, cob_id: int = SYNC_COB_ID, heartbeat_cycles: int = 100):
        self.network = network
        self.cob_id = cob_id
        self.cycle = 0
        self.heartbeat_cycles = heartbeat_cycles

    def tick(self) -> None:
        self.cycle += 1  # first: what answers this SYNC belongs to the new cycle
        self.network.send_message(self.cob_id, b"")
        # from the first SYNC on: a drive starts watching at the first heartbeat (CiA 301), so a master
        # that died before its first one would leave the drive unwatched
        if self.heartbeat_cycles and self.cycle % self.heartbeat_cycles == 1:
            self.network.send_message(HEARTBEAT_BASE + MASTER_NODE_ID, bytes([NmtState.OPERATIONAL]))

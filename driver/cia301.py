"""CiA 301 (CANopen application layer) numbers in one place: COB-IDs, NMT commands and states."""

from __future__ import annotations

from enum import IntEnum

NMT_COB_ID = 0x000
SYNC_COB_ID = 0x080
EMCY_BASE = 0x080
TPDO_BASE = (0x180, 0x280, 0x380, 0x480)
RPDO_BASE = (0x200, 0x300, 0x400, 0x500)
SDO_TX_BASE = 0x580  # server -> client
SDO_RX_BASE = 0x600  # client -> server
HEARTBEAT_BASE = 0x700
MASTER_NODE_ID = 0x7F  # drivectl's own heartbeat (0x77F), consumed by the drives
SDO_ABORT_VALUE_RANGE = 0x06090030  # value range of parameter exceeded


class NmtCommand(IntEnum):
    START = 0x01
    STOP = 0x02
    ENTER_PRE_OPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


class NmtState(IntEnum):
    """NMT states as the heartbeat reports them."""

    INITIALISING = 0x00  # the boot-up message carries 0
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F


#: Operational as a module constant for the per-cycle paths (a member read through its class goes through
#: EnumType's ``__getattr__`` hook on Python 3.11, some 0.3 us; driver/cia402.py POWER_OPERATION_ENABLED)
NMT_OPERATIONAL = NmtState.OPERATIONAL


NMT_TRANSITIONS = {
    NmtCommand.START: NmtState.OPERATIONAL,
    NmtCommand.STOP: NmtState.STOPPED,
    NmtCommand.ENTER_PRE_OPERATIONAL: NmtState.PRE_OPERATIONAL,
}

"""CiA 402 in one place: power states (more of the profile lands with the CANopen master)."""

from __future__ import annotations

from enum import Enum


class PowerState(Enum):
    """The power states of the CiA 402 drive state machine."""

    NOT_READY_TO_SWITCH_ON = "Not Ready To Switch On"
    SWITCH_ON_DISABLED = "Switch On Disabled"
    READY_TO_SWITCH_ON = "Ready To Switch On"
    SWITCHED_ON = "Switched On"
    OPERATION_ENABLED = "Operation Enabled"
    QUICK_STOP_ACTIVE = "Quick Stop Active"
    FAULT_REACTION_ACTIVE = "Fault Reaction Active"
    FAULT = "Fault"

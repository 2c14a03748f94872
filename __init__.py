"""drivectl: a drive controller for ball-screw feed axes (CiA 402 over CANopen, with a plant emulator)."""

__version__ = "0.1.0"

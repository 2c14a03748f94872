"""The Axis protocol: what every controller loop talks to (SimAxis, CanopenAxis).

Units are SI on this side of the seam: m, m/s, and the axis's effort unit (N or V). Counts and
per-mille exist only inside the transports.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import Protocol, runtime_checkable

from drivectl.driver.cia402 import PowerState


@dataclass(slots=True, frozen=True)
class Feedback:
    """One cycle's sample of the axis, taken at SYNC k (time ``time``)."""

    time: float  # s, simulated or bus time of the sample
    position: float  # m, as the encoder reports it (quantised at the transport)
    velocity: float  # m/s, as the drive reports it (0x606C on a CiA 402 drive)


#: what an axis may do last when neither the quick stop (RPDO, SDO) nor NMT Stop is confirmed (the
#: configuration's ``last_resort``): "nmt-reset" (NMT Reset Node: the drive restarts with its power
#: stage off) or "none"
LAST_RESORTS = ("nmt-reset", "none")


class FaultKind(Enum):
    """What the master detected; the value is what traces and messages say."""

    TPDO_TIMEOUT = "tpdo timeout"
    DRIVE_FAULT = "drive fault"
    DRIVE_STOPPED = "drive left Operation Enabled"
    HEARTBEAT_LOST = "heartbeat lost"
    UNEXPECTED_BOOT = "unexpected boot-up"
    BUS_ERROR = "bus error"
    IMPLAUSIBLE_POSITION = "implausible position"
    FOLLOWING_ERROR = "following error"
    SOFT_LIMIT = "soft position limit"
    ROGUE_RPDO = "rogue rpdo"
    ROGUE_SYNC = "rogue sync"
    FOREIGN_NMT = "foreign nmt"
    LOOP_STALLED = "servo loop stalled"  # the resident loop ran no cycle for longer than its bound
    RUN_CHECK = "run check"  # a [checks] fault threshold passed (controllers/runtime/run_checks.py)


class AxisError(RuntimeError):
    """An axis cannot do what was asked (not enabled, fault active, transport lost); ``kind`` says
    which fault was detected, when it was one."""

    def __init__(self, message: str, kind: FaultKind | None = None):
        super().__init__(message)
        self.kind = kind


class AxisConfigError(AxisError):
    """The drive or its description refused the configuration before anything moved (an EDS
    without an essential object, an SDO abort while configuring): bad input, not a fault."""


@runtime_checkable
class Axis(Protocol):
    """A feed axis driven by an effort setpoint once per cycle.

    ``read()`` returns the sample of the next cycle: the first call returns the sample at t = 0,
    every later call first lets the axis advance one cycle (SYNC) and then returns its sample.
    ``write(effort)`` sets the effort computed from that sample. ``enable``, ``disable``,
    ``quick_stop`` and ``fault_reset`` set the power state to reach; the drive gets there through the
    following cycles (``power`` tells where it is), never by blocking.
    """

    name: str
    dt: float
    effort_unit: str

    @property
    def power(self) -> PowerState:
        """The CiA 402 power state the drive last reported."""
        ...

    def read(self) -> Feedback: ...

    def write(self, effort: float) -> None: ...

    def enable(self) -> None: ...

    def disable(self) -> None: ...

    def quick_stop(self) -> None: ...

    def fault_reset(self) -> None: ...

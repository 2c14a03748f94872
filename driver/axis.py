"""The Axis: what every controller loop talks to (SimAxis, CanopenAxis), with its optional capabilities.

Units are SI on this side of the seam: m, m/s, and the axis's effort unit (N or V). Counts and
per-mille exist only inside the transports.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from enum import StrEnum
from typing import Any

from drivectl.driver.cia402 import PowerState
from drivectl.errors import EXIT_BAD_INPUT, DrivectlError


@dataclass(slots=True, frozen=True)
class Feedback:
    """One cycle's sample of the axis, taken at SYNC k (time ``time``)."""

    time: float  # s, simulated or bus time of the sample
    position: float  # m, as the encoder reports it (quantised at the transport)
    velocity: float  # m/s, as the drive reports it (0x606C on a CiA 402 drive)

    def __init__(self, time: float, position: float, velocity: float) -> None:
        # made every cycle: the slots are set through their descriptors, not by name through
        # object.__setattr__ as the generated frozen __init__ does (0.5 us against 0.76)
        _set_time(self, time)
        _set_position(self, position)
        _set_velocity(self, velocity)


_set_time, _set_position, _set_velocity = (Feedback.__dict__[k].__set__ for k in ("time", "position", "velocity"))


#: what an axis may do last when neither the quick stop (RPDO, SDO) nor NMT Stop is confirmed (the
#: configuration's ``last_resort``): "nmt-reset" (NMT Reset Node: the drive restarts with its power
#: stage off) or "none"
LAST_RESORTS = ("nmt-reset", "none")


class FaultKind(StrEnum):
    """What ended a run other than completion; the value (the member itself, a str) is what traces and
    messages say."""

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
    INTERRUPTED = "interrupted"  # SIGINT / SIGTERM: the operator stopped it (controllers/runtime/interrupt.py)
    AXIS_ERROR = "axis error"  # the axis failed without a detected kind (AxisError without one)
    LOOP_ERROR = "loop error"  # the resident loop itself raised


class AxisError(DrivectlError, RuntimeError):
    """An axis cannot do what was asked (not enabled, fault active, transport lost); ``kind`` says
    which fault was detected, when it was one."""

    def __init__(self, message: str, kind: FaultKind | None = None):
        super().__init__(message)
        self.kind = kind


class AxisConfigError(AxisError):
    """The drive or its description refused the configuration before anything moved (an EDS
    without an essential object, an SDO abort while configuring): bad input, not a fault."""

    exit_code = EXIT_BAD_INPUT


class Axis:
    """A feed axis driven by an effort setpoint once per cycle; every transport derives from it.

    ``read()`` returns the sample of the next cycle: the first call returns the sample at t = 0,
    every later call first lets the axis advance one cycle (SYNC) and then returns its sample.
    ``write(effort)`` sets the effort computed from that sample. ``enable``, ``disable``,
    ``quick_stop`` and ``fault_reset`` set the power state to reach; the drive gets there through the
    following cycles (``power`` tells where it is), never by blocking.

    The optional capabilities are declared here with the value of a transport that lacks them (SimAxis:
    no bus, its model always current), as python-can's ``BusABC`` declares its optional methods: callers
    read them directly and never probe an axis by name. A method a transport cannot serve raises
    ``NotImplementedError`` (the stop's escalation steps, the inputs by SDO).
    """

    name: str
    dt: float
    effort_unit: str
    #: the CiA 402 power state the drive last reported (an attribute or a property of the transport)
    power: PowerState

    # -- required ---------------------------------------------------------------------------------
    def read(self) -> Feedback:
        raise NotImplementedError

    def write(self, effort: float) -> None:
        raise NotImplementedError

    def stale(self) -> None:
        """The sample :meth:`read` just returned answered an earlier SYNC than this cycle's (the cycle found it:
        controllers/runtime/cycle.py ``bridge``): the cycle is bridged and counted as one without a sample. Only
        a transport that can lose samples (``lost_cycles``) is ever told."""
        self.lost_cycles += 1

    def enable(self) -> None:
        raise NotImplementedError

    def disable(self) -> None:
        raise NotImplementedError

    def quick_stop(self) -> None:
        raise NotImplementedError

    def fault_reset(self) -> None:
        raise NotImplementedError

    # -- reported beside the sample (read every cycle: plain attributes, no call) ---------------------
    #: the statusword (0x6041) of the last sample; 0 where the transport reports none
    statusword: int = 0
    #: 0x6077 in the effort unit; NaN where the drive reports none (not mapped)
    torque_actual: float = math.nan
    #: cycles in a row bridged without a fresh sample (the position extrapolated); 0 on a lossless transport
    lost_cycles: int = 0
    #: cycles bridged since the axis was opened; None on a transport that cannot lose a sample
    lost_total: int | None = None
    #: the last EMCY (error code, cycle); None: none received (or no bus)
    last_emcy: tuple[int, int] | None = None

    # -- the drive's state as confirmed ----------------------------------------------------------------
    #: the power state is what the drive last reported, not yet contradicted by a lost cycle
    state_fresh: bool = True
    #: where the last confirmed statusword came from: "TPDO" or "SDO"; "" without a transport
    state_source: str = ""
    #: a rogue producer or a foreign NMT command seen on this drive (FaultKind), else None
    foreign_kind: FaultKind | None = None
    #: what the boot chose and what the drive lacks, a line each (said when a run starts); none without a drive
    boot_notes: Sequence[str] = ()

    def enable_blocker(self) -> str:
        """Why the drive is not Operation Enabled, in the drive's own words (driver/enable_check.py); "" where
        nothing more is known than ``power``."""
        return ""

    def refresh_state(self) -> PowerState:
        """The power state asked of the drive again (by SDO on a bus); without a transport, ``power``."""
        return self.power

    def read_error_code(self) -> int | None:
        """The drive's 0x603F; None where it cannot be read."""
        return None

    def read_digital_inputs(self) -> int:
        """The drive's 0x60FD (its switches)."""
        raise NotImplementedError

    def drive_limits(self) -> dict[str, object]:
        """The limits the drive holds (0x6065/0x6066, 0x607D) in SI; none without a drive."""
        return {}

    #: after Operation Enabled a run holds the axis this long before its first reference sample (a holding
    #: brake's load taken over at rest: the configuration's ``enable_settle_ms``, controllers/runtime/servo.py)
    enable_settle_s: float = 0.0

    # -- the transport ---------------------------------------------------------------------------------
    #: the cycles advance in lockstep with the master (simulated time in this process)
    lockstep: bool = True
    #: CANopen node id and 0x1018 identity; None without a bus
    node_id: int | None = None
    identity: Any = None

    @property
    def counters(self) -> dict[str, int]:
        """The transport's event counts (cycles bridged, late and malformed frames); none without a bus."""
        return {}

    def pace(self, wall: Callable[[], float] | None) -> None:
        """A run paced on the wall clock ``wall`` starts (None: it ended); nothing to tell without drives
        of their own clock in this process."""

    def watch_sync(self, slip: Callable[[float | None], int] | None) -> None:
        """While a paced run lasts: ``slip(now)``, called just before the cycle's SYNC goes out (in-process with the
        wall time of its delivery; None: now), returns the slots the loop's clock moved on since the cycle took its
        slot; the SYNC then counts them as skipped (docs/timing.md,
        "A SYNC later than its slot"). Nothing to do without a SYNC."""

    def skip(self, slots: int) -> None:
        """The wall-clock loop woke late: ``slots`` cycle slots passed without a cycle of their own. The next
        ``read`` belongs to the slot it runs in, so its time and a velocity derived from two positions span
        the real interval (docs/timing.md). Nothing to do where the axis has no clock but the loop's calls."""

    # -- a stop's escalation beyond the quick stop by RPDO (controllers/runtime/safe_stop.py) -------------
    #: the configured last resort (LAST_RESORTS); None: the transport has none
    last_resort_action: str | None = None

    def sdo_quick_stop(self) -> None:
        """Quick stop by SDO (the controlword written outside the PDOs)."""
        raise NotImplementedError

    def abort_connection_option(self) -> int | None:
        """The drive's 0x6007 (what it does on a lost connection or NMT Stop)."""
        raise NotImplementedError

    def nmt_stop(self) -> None:
        """NMT Stop to this drive."""
        raise NotImplementedError

    def refresh_state_outside_operational(self) -> PowerState:
        """The statusword by SDO once the drive is out of NMT Operational."""
        raise NotImplementedError

    def last_resort(self) -> str | None:
        """Do the configured last resort; what was done (None: nothing)."""
        raise NotImplementedError

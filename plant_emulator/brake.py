"""The holding brake of an emulated drive: a feed axis carrying a load stands while its power stage is off.

Driven as CiA 402 drives drive their own (automatic) brake:

* power-on, and every state without torque: engaged, the motor side clamped (position held,
  velocity zero) whatever the disturbances;
* Enable Operation: the power stage comes on, the brake is told to release and the drive reports
  Operation Enabled once ``release_ms`` have passed (before that it still reports Switched On and
  applies no setpoint: a master that starts on Operation Enabled never pushes against the brake);
* leaving Operation Enabled (a disable command, a quick stop, a fault): the brake is told to engage
  while the power stage stays on, holding the axis at standstill for ``engage_ms`` (the drive's own
  standstill control, not the master's setpoint); only then is the power stage off and the new state
  reached. A quick stop and a fault report Quick Stop Active / Fault Reaction Active meanwhile, a
  disable command still Operation Enabled (the power stage is still on).

The brake clamps body 0 of the plant (the motor side, where a motor brake sits): on the two-mass
ball screw the table then stands within its spring's deflection under the load-side disturbance.
Configured per axis in ``[axes.NAME.emulator]`` (``brake_release_ms``, ``brake_engage_ms``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from drivectl.driver.cia402 import PowerState

#: the standstill control's time constant while the brake engages, in cycles: effort = -m v / (N dt), on
#: the drive's own velocity each cycle (no transport delay inside the drive): v falls by 1/N per cycle
STANDSTILL_CYCLES = 4.0


@dataclass(frozen=True)
class BrakeSpec:
    """Delays of a holding brake (ms of drive time)."""

    release_ms: float
    engage_ms: float


class HoldingBrake:
    """The brake's state, stepped once per drive cycle by :class:`~drivectl.plant_emulator.drive.DriveModel`."""

    def __init__(self, spec: BrakeSpec, dt: float, mass: float, position: float):
        self.release_cycles = max(1, math.ceil(spec.release_ms / 1000.0 / dt - 1e-9))
        self.engage_cycles = max(1, math.ceil(spec.engage_ms / 1000.0 / dt - 1e-9))
        self._gain = mass / (STANDSTILL_CYCLES * dt)
        self.engaged = True
        self.hold: float | None = position  # body 0's clamped position (None: taken at the next step)
        self._count = 0
        #: while engaging: the state the drive reaches once the brake holds (None: not engaging)
        self.target: PowerState | None = None

    @property
    def engaging(self) -> bool:
        return self.target is not None

    def gate(self, before: PowerState, after: PowerState) -> PowerState:
        """The state the drive reports this cycle, given the state the controlword (or a fault) asks for."""
        if self.target is not None:  # engaging: nothing changes the state until the brake holds
            if after in (PowerState.FAULT_REACTION_ACTIVE, PowerState.FAULT):
                self.target = PowerState.FAULT_REACTION_ACTIVE  # a fault while engaging: it ends in Fault
            self._count += 1
            if self._count < self.engage_cycles:
                return self._holding_state()
            target, self.target = self.target, None
            self.engaged, self.hold = True, None
            return target
        if after is PowerState.OPERATION_ENABLED and before is not PowerState.OPERATION_ENABLED and self.engaged:
            self._count += 1  # releasing: the power stage is on, the brake still holds
            if self._count < self.release_cycles:
                return before
            self._count, self.engaged, self.hold = 0, False, None
            return after
        if before is PowerState.OPERATION_ENABLED and after is not PowerState.OPERATION_ENABLED and not self.engaged:
            self.target, self._count = after, 1
            if self.engage_cycles > 1:
                return self._holding_state()
            self.target, self.engaged, self.hold = None, True, None
            return after
        if after is not PowerState.OPERATION_ENABLED:
            self._count = 0  # a release asked for and withdrawn starts again next time
        return after

    def drop(self) -> None:
        """The drive restarted (a reset, a brown-out): the coil loses power and the brake, spring-applied, engages
        at once, without the standstill control (the drive that would run it is booting)."""
        self.engaged, self.hold, self.target, self._count = True, None, None, 0

    def _holding_state(self) -> PowerState:
        t = self.target
        if t in (PowerState.QUICK_STOP_ACTIVE, PowerState.FAULT_REACTION_ACTIVE):
            return t
        return PowerState.OPERATION_ENABLED

    def effort(self, velocity0: float) -> float:
        """The drive's standstill control while the brake engages (the master's setpoint is not applied)."""
        return -self._gain * velocity0

    def before_step(self, s: list[float]) -> None:
        """Before a plant step: a brake that has just engaged holds body 0 where it is now."""
        if self.engaged and self.hold is None:
            self.hold = s[0]

    def clamp(self, s: list[float]) -> None:
        """After a plant step: an engaged brake holds body 0 where it engaged."""
        if self.engaged:
            s[0] = self.hold
            s[1] = 0.0

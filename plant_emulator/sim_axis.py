"""SimAxis: a plant (with effects) behind the Axis protocol, no bus. Fast batch runs and tests.

It plays the drive exactly as the CANopen path does, so a trace through SimAxis equals the trace
through the emulated drive:

* cyclic synchronous torque: the effort written after sample k is latched at SYNC k+1 and acts from
  t(k+1) to t(k+2) (``transport_delay=True``, the default); without it the effort acts at once,
  from t(k) to t(k+1), as the papers simulate;
* the position is quantised to whole encoder counts and the velocity to whole counts per second
  (0x6064 and 0x606C are integers on the bus);
* optionally the applied effort is quantised to per-mille of the rated effort (0x6071), and a
  seeded Gaussian force noise is added to what the plant feels (not to the trace's effort column).
"""

from __future__ import annotations

import random

from drivectl.driver.axis import AxisError, Feedback
from drivectl.driver.cia402 import PowerState
from drivectl.driver.units import DEFAULT_RESOLUTION_M, EffortScale, Encoder
from drivectl.plant_emulator.models import Plant, PlantState


class SimAxis:
    """The Axis protocol over a :class:`Plant`, in simulated time (one plant step per ``read``)."""

    def __init__(
        self,
        plant: Plant,
        *,
        name: str = "x",
        transport_delay: bool = True,
        resolution: float | None = DEFAULT_RESOLUTION_M,
        effort_scale: EffortScale | None = None,
        force_noise: float = 0.0,
        seed: int = 0,
        initial_position: float = 0.0,
        enabled: bool = False,
    ):
        if force_noise < 0:
            raise ValueError(f"SimAxis {name}: force_noise: must be >= 0, got {force_noise!r}")
        self.name = name
        self.plant = plant
        self.dt = plant.dt
        self.effort_unit = plant.effort_unit
        self.transport_delay = transport_delay
        self.encoder = Encoder(resolution) if resolution else None
        self.effort_scale = effort_scale
        self.force_noise = float(force_noise)
        self._rng = random.Random(seed)
        self.state: PlantState = plant.initial_state(initial_position)
        self.power = PowerState.OPERATION_ENABLED if enabled else PowerState.SWITCH_ON_DISABLED
        self._started = False
        self._written = 0.0  # setpoint received during the current cycle
        self._latched = 0.0  # setpoint acting during the current cycle

    # -- cycle ---------------------------------------------------------------------------------
    def read(self) -> Feedback:
        """Advance one cycle (except at the first call) and sample the encoder."""
        if self._started:
            if not self.transport_delay:
                self._latched = self._applied(self._written)
            effort = self._latched
            if self.force_noise:
                effort += self._rng.gauss(0.0, self.force_noise)
            self.plant.step(self.state, effort)
            if self.transport_delay:
                self._latched = self._applied(self._written)
        self._started = True
        s = self.state.s
        enc = self.encoder
        if enc is None:
            return Feedback(self.state.t, s[-2], s[-1])
        return Feedback(self.state.t, enc.quantise(s[-2]), enc.quantise(s[-1]))

    def write(self, effort: float) -> None:
        self._written = effort

    def _applied(self, effort: float) -> float:
        """What the drive applies of a setpoint: nothing unless enabled; per-mille on the bus."""
        if self.power is not PowerState.OPERATION_ENABLED:
            return 0.0
        if self.effort_scale is not None:
            return self.effort_scale.from_permille(self.effort_scale.to_permille(effort))
        return effort

    # -- power state ---------------------------------------------------------------------------
    def enable(self) -> None:
        if self.power is PowerState.FAULT:
            raise AxisError(f"axis {self.name}: in Fault, fault_reset first")
        self.power = PowerState.OPERATION_ENABLED

    def disable(self) -> None:
        self.power = PowerState.SWITCH_ON_DISABLED
        self._written = self._latched = 0.0

    def quick_stop(self) -> None:
        """Zero torque at once (a CST drive's quick stop with the torque ramp set to 0)."""
        if self.power is PowerState.OPERATION_ENABLED:
            self.power = PowerState.QUICK_STOP_ACTIVE
        self._written = self._latched = 0.0

    def fault_reset(self) -> None:
        if self.power is PowerState.FAULT:
            self.power = PowerState.SWITCH_ON_DISABLED

    def close(self) -> None:
        """Nothing to release; present so every axis can be closed the same way."""

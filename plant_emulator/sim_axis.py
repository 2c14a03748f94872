"""SimAxis: a plant (with effects) behind the Axis protocol, no bus. Fast batch runs and tests.

It plays the drive exactly as the CANopen path does, so a trace through SimAxis equals the trace
through the emulated drive: the same :class:`~drivectl.plant_emulator.drive.DriveModel` (CiA 402
power states stepped once per cycle, the one-cycle transport delay of cyclic synchronous torque),
the same master state machine choosing the controlword, and the same transport-edge conversions:

* the position is quantised to whole encoder counts and the velocity to whole counts per second
  (0x6064 and 0x606C are integers on the bus);
* optionally the effort is quantised to per-mille of the rated effort (0x6071);
* an optional seeded Gaussian force noise is added to what the plant feels (not to the trace's
  effort column).
"""

from __future__ import annotations

import math

from drivectl.driver.axis import Axis, AxisError, Feedback
from drivectl.driver.cia402 import MasterStateMachine, PowerState, encode_statusword
from drivectl.driver.units import DEFAULT_RESOLUTION_M, EffortScale, Encoder
from drivectl.plant_emulator.drive import DriveModel
from drivectl.plant_emulator.models import Plant, PlantState


class SimAxis(Axis):
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
        io: object = None,
        derived_velocity: bool = False,
        torque_mapped: bool = True,
    ):
        self.name = name
        self.plant = plant
        self.dt = plant.dt
        self.effort_unit = plant.effort_unit
        self.encoder = Encoder(resolution) if resolution else None
        self.effort_scale = effort_scale
        self.torque_mapped = torque_mapped  # the minimal mapping carries no 0x6077: NaN, as on the bus
        power = PowerState.OPERATION_ENABLED if enabled else PowerState.SWITCH_ON_DISABLED
        self.drive = DriveModel(plant, transport_delay=transport_delay, force_noise=force_noise, seed=seed,
                                initial_position=initial_position, power=power, io=io)
        self.master = MasterStateMachine(power)
        self._controlword = self.master.controlword(power)  # chosen from the last statusword
        self._sent_controlword = self._controlword if enabled else 0  # what the last "RPDO" carried
        self._written = 0.0
        # the compact mapping carries no velocity: the master derives it from two positions, so do we
        self._prev_counts: int | None = (self.encoder.to_counts(self.drive.position)
                                         if derived_velocity and self.encoder is not None else None)

    @property
    def state(self) -> PlantState:
        return self.drive.state

    @property
    def power(self) -> PowerState:
        return self.drive.power

    @property
    def statusword(self) -> int:
        power = self.drive.power
        return encode_statusword(power, follows=power is PowerState.OPERATION_ENABLED)

    def read_digital_inputs(self) -> int:
        """0x60FD of the drive (its switches)."""
        return self.drive.digital_inputs()

    @property
    def torque_actual(self) -> float:
        """0x6077: the effort the drive applies now (NaN when the bus mapping would not carry it)."""
        return self.drive.applied if self.torque_mapped else math.nan

    def read_error_code(self) -> int:
        """0x603F of the drive."""
        return self.drive.error_code

    # -- cycle ---------------------------------------------------------------------------------
    def read(self) -> Feedback:
        """One SYNC: the drive takes what was sent during the last cycle and the plant advances;
        then the encoder is sampled and the next controlword chosen."""
        d = self.drive
        d.sync(self._sent_controlword, self._written)
        self._controlword = self.master.controlword(d.power)
        t = (d.syncs - 1) * self.dt
        enc = self.encoder
        if enc is None:
            return Feedback(t, d.position, d.velocity)
        if self._prev_counts is not None:
            counts = enc.to_counts(d.position)
            velocity = enc.velocity(counts, self._prev_counts, self.dt)
            self._prev_counts = counts
            return Feedback(t, enc.from_counts(counts), velocity)
        return Feedback(t, enc.quantise(d.position), enc.quantise(d.velocity))

    def write(self, effort: float) -> None:
        """The cycle's "RPDO": the effort and the controlword go to the drive together."""
        if self.effort_scale is not None:
            effort = self.effort_scale.from_permille(self.effort_scale.to_permille(effort))
        self._written = effort
        self._sent_controlword = self._controlword

    # -- power state: targets reached through the cycle, like a CiA 402 drive ------------------
    def enable(self) -> None:
        if self.drive.power is PowerState.FAULT:
            raise AxisError(f"axis {self.name}: in Fault (0x603F = 0x{self.drive.error_code:04X}), fault_reset first")
        self._target(PowerState.OPERATION_ENABLED)

    def disable(self) -> None:
        self._target(PowerState.SWITCH_ON_DISABLED)
        self._written = 0.0

    def quick_stop(self) -> None:
        self._target(PowerState.QUICK_STOP_ACTIVE)
        self._written = 0.0

    def fault_reset(self) -> None:
        self.master.request_fault_reset()
        self._target(PowerState.SWITCH_ON_DISABLED)

    def _target(self, target: PowerState) -> None:
        self.master.target = target
        self._controlword = self.master.controlword(self.drive.power)

    def close(self) -> None:
        """Nothing to release; present so every axis can be closed the same way."""

"""The drive itself: a CiA 402 power stage around a plant, stepped once per SYNC.

SimAxis (no bus) and the emulated CANopen drive (node402.py) both hold one of these, so a trace
through SimAxis equals the trace through the emulator by construction, not by parallel code.

At each SYNC the drive (cyclic synchronous torque):

1. steps the plant over the cycle that just ended with the effort latched at the previous SYNC
   (the one-cycle transport delay; ``transport_delay=False`` applies the new setpoint at once,
   as the papers simulate);
2. takes the controlword and the setpoint received during that cycle: the controlword moves the
   power state by the table of driver/cia402.py, the setpoint is latched if the drive is in
   Operation Enabled without halt (zero torque in every other state);
3. reports (the caller samples position, velocity and state).
"""

from __future__ import annotations

import math
import random
from typing import Any

from drivectl.driver.cia402 import (
    DRIVE_TRANSITIONS,
    HALT_BIT,
    POWER_OPERATION_ENABLED,
    Command,
    PowerState,
    decode_command,
)
from drivectl.plant_emulator.brake import HoldingBrake
from drivectl.plant_emulator.models import Plant, PlantState

#: quick stop option codes (0x605A) after which the drive drops to Switch On Disabled by itself
QUICK_STOP_TO_DISABLED = (0, 1, 2, 3, 4)


class DriveModel:
    """Power state, setpoint latching and the plant of one drive (simulated time only)."""

    def __init__(
        self,
        plant: Plant,
        *,
        transport_delay: bool = True,
        force_noise: float = 0.0,
        seed: int = 0,
        initial_position: float = 0.0,
        quick_stop_option: int = 2,
        power: PowerState = PowerState.SWITCH_ON_DISABLED,
        io: Any = None,
    ):
        if not (force_noise >= 0 and math.isfinite(force_noise)):
            raise ValueError(f"drive: force_noise: must be >= 0, got {force_noise!r}")
        self.plant = plant
        self.transport_delay = transport_delay
        self.force_noise = float(force_noise)
        self._rng = random.Random(seed)
        self.state: PlantState = plant.initial_state(initial_position)
        self.power = power
        self.quick_stop_option = quick_stop_option
        self.error_code = 0
        self.applied = 0.0  # effort acting during the current cycle
        self.syncs = 0
        self.free_steps = 0  # plant steps on the drive's own clock (no SYNC): a run that had any is not lockstep
        self._last_cw = 0
        # False while no mode is selected that this drive runs (0x6060 = 0, CiA 402: no torque then);
        # SimAxis has no 0x6060 and is always in cyclic synchronous torque
        self.mode_ok = True
        #: a safe torque off (STO) input active: the drive does not take Shutdown (stays Switch On Disabled)
        self.sto = False
        #: the DC link has voltage (False: statusword bit 4 clear, Enable Operation not taken)
        self.voltage = True
        #: switches and mechanical stops (controllers/runtime/homing.py EmulatorIO): 0x60FD and hard stops
        self.io = io
        #: the holding brake, when the axis has one (plant_emulator/brake.py): engaged at power-on
        spec = getattr(io, "brake", None)
        self.brake = None if spec is None else HoldingBrake(spec, plant.dt, plant.design.total_mass,
                                                            self.state.s[0])

    @property
    def position(self) -> float:
        return self.state.s[-2]

    @property
    def velocity(self) -> float:
        return self.state.s[-1]

    def sync(self, controlword: int, setpoint: float) -> None:
        """One SYNC: advance the plant one cycle (except at the first SYNC), then take the
        controlword and setpoint received since the previous SYNC."""
        if not self.transport_delay:
            self._take(controlword, setpoint)
        if self.syncs:
            effort = self.applied
            if self.force_noise:
                effort += self._rng.gauss(0.0, self.force_noise)
            self._step(effort)
        self.syncs += 1
        if self.transport_delay:
            self._take(controlword, setpoint)

    def _hard_stop(self, stops: tuple[float, float]) -> None:
        """A mechanical stop: the carriage does not pass it (an inelastic impact: velocity 0)."""
        s = self.state.s
        if s[-2] < stops[0] or s[-2] > stops[1]:
            s[-2] = stops[0] if s[-2] < stops[0] else stops[1]
            s[-1] = 0.0

    def digital_inputs(self) -> int:
        """0x60FD: limit and home switches at the current position (0 without switches)."""
        return self.io.inputs(self.position) if self.io is not None else 0

    def free_cycle(self, controlword: int, setpoint: float) -> None:
        """One cycle of the drive's own clock with no SYNC (the master silent, or an SDO-only master):
        the plant moves on under the effort applied, the controlword received since is taken."""
        if self.syncs or self.applied:
            self.free_steps += 1
            self._step(self.applied)
        self._take(controlword, setpoint)

    def _step(self, effort: float) -> None:
        brake = self.brake
        if brake is not None:
            if brake.engaging:
                effort = brake.effort(self.state.s[1])  # the drive's standstill control, not the setpoint
            brake.before_step(self.state.s)
        self.plant.step(self.state, effort)
        if brake is not None:
            brake.clamp(self.state.s)
        if self.io is not None and self.io.hard_stops is not None:
            self._hard_stop(self.io.hard_stops)

    @property
    def following(self) -> bool:
        """Statusword bit 12 in cyclic synchronous torque: the drive follows the target torque
        (Operation Enabled, no halt, a mode it runs)."""
        return (self.power is POWER_OPERATION_ENABLED and not self._last_cw & HALT_BIT and self.mode_ok
                and not (self.brake is not None and self.brake.engaging))

    def _take(self, controlword: int, setpoint: float) -> None:
        before = self.power
        self._apply_controlword(controlword)
        brake = self.brake
        if brake is not None:
            self.power = brake.gate(before, self.power)
        enabled = self.power is POWER_OPERATION_ENABLED and not controlword & HALT_BIT and self.mode_ok
        self.applied = setpoint if enabled and not (brake is not None and brake.engaging) else 0.0

    def _apply_controlword(self, cw: int) -> None:
        power = self.power
        if cw == self._last_cw and power is POWER_OPERATION_ENABLED:
            return  # steady operation: the same command keeps the same state
        rising_reset = bool(cw & Command.FAULT_RESET) and not self._last_cw & Command.FAULT_RESET
        self._last_cw = cw
        if power is PowerState.FAULT_REACTION_ACTIVE:
            self.power = PowerState.FAULT  # the reaction (zero torque) takes one cycle
            return
        if power is PowerState.FAULT:
            if rising_reset:
                self.power = PowerState.SWITCH_ON_DISABLED
                self.error_code = 0
            return
        if power is PowerState.NOT_READY_TO_SWITCH_ON:
            self.power = PowerState.SWITCH_ON_DISABLED
            return
        if power is PowerState.QUICK_STOP_ACTIVE and self.quick_stop_option in QUICK_STOP_TO_DISABLED:
            # torque mode: zero torque is reached at once, so the quick stop completes in one cycle
            # and the drive drops to Switch On Disabled (transition 12) whatever the master sends
            self.power = PowerState.SWITCH_ON_DISABLED
            return
        cmd = decode_command(cw)
        if cmd is not None:
            new = DRIVE_TRANSITIONS.get((power, cmd), power)
            if self.sto and power is PowerState.SWITCH_ON_DISABLED:
                new = power  # safe torque off: held in Switch On Disabled whatever the controlword
            elif not self.voltage and new is PowerState.OPERATION_ENABLED:
                new = PowerState.SWITCHED_ON if power is PowerState.READY_TO_SWITCH_ON else power
            self.power = new

    def disable_voltage(self, code: int) -> None:
        """Communication lost with 0x6007 = 2 or 3 (disable voltage, quick stop): zero torque now and Switch On
        Disabled, 0x603F = code. A brake engages first, as on a disable command (plant_emulator/brake.py): the
        power stage holds the axis at standstill meanwhile, so a vertical axis does not fall."""
        self.error_code = code
        before, self.power = self.power, PowerState.SWITCH_ON_DISABLED
        if self.brake is not None and before is PowerState.OPERATION_ENABLED:
            # the stop reaction reports Quick Stop Active while the brake engages (not Operation Enabled, as a
            # disable command's does): the master's safe stop sees a stopping drive and does not escalate to NMT
            self.power = self.brake.gate(before, PowerState.QUICK_STOP_ACTIVE)
        self.applied = 0.0

    def restart(self) -> None:
        """A reset of the drive (NMT reset node, a spontaneous one): the power stage restarts in Switch On
        Disabled with no error, and the brake engages at once (:meth:`HoldingBrake.drop`)."""
        self.power, self.applied, self.error_code = PowerState.SWITCH_ON_DISABLED, 0.0, 0
        if self.brake is not None:
            self.brake.drop()

    def fault(self, code: int) -> None:
        """Enter Fault Reaction Active (zero torque now), Fault at the next SYNC; 0x603F = code."""
        self.error_code = code
        before, self.power = self.power, PowerState.FAULT_REACTION_ACTIVE
        if self.brake is not None:
            self.power = self.brake.gate(before, self.power)
        self.applied = 0.0

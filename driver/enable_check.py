"""Why a drive does not enable, read from what it reports (statusword, 0x603F or its EMCY, 0x6061).

"Transition timed out" is the most common question in the trackers of CANopen masters; the drive usually
says why, in its statusword and error code:

* Fault (bit 3): the fault code, from 0x603F, else the last EMCY;
* Ready to Switch On or Switched On with bit 4 (voltage enabled) clear, Enable Operation not taken: the
  power stage has no voltage (DC link, main contactor);
* Switch On Disabled after Shutdown commands, no fault: something outside the controlword holds it there,
  a safe torque off (STO) input or a hardware enable (CiA 402 has no bit of its own for it);
* 0x6061 not the mode drivectl set: the mode was not accepted.
"""

from __future__ import annotations

from drivectl.driver import cia402
from drivectl.driver.cia402 import PowerState

VOLTAGE_ENABLED = 0x0010  # statusword bit 4


def enable_blocker(statusword: int, *, error_code: int | None, emcy_code: int | None, mode_display: int | None,
                   mode: int | None) -> str:
    """The reason a drive is not Operation Enabled, in one phrase (from what it reported after the attempt)."""
    state = cia402.decode_statusword(statusword)
    sw = f"statusword 0x{statusword:04X}"
    if state in (PowerState.FAULT, PowerState.FAULT_REACTION_ACTIVE):
        if error_code:
            return f"in Fault: 0x603F = 0x{error_code:04X} ({cia402.error_text(error_code)}); {sw}"
        if emcy_code:
            return f"in Fault: EMCY 0x{emcy_code:04X} ({cia402.error_text(emcy_code)}); {sw}"
        return f"in Fault, no error code given; {sw}"
    if mode is not None and mode_display is not None and mode_display != mode:
        return f"mode not accepted: 0x6061 = {mode_display}, drivectl set 0x6060 = {mode}; {sw}"
    if state in (PowerState.READY_TO_SWITCH_ON, PowerState.SWITCHED_ON) and not statusword & VOLTAGE_ENABLED:
        return (f"voltage not enabled: {state.value} with statusword bit 4 clear (no DC link voltage: main power "
                f"or contactor off); {sw}")
    if state is PowerState.SWITCH_ON_DISABLED:
        return (f"held in Switch On Disabled without a fault: safe torque off (STO) or a hardware enable input is "
                f"active (the drive does not take Shutdown); {sw}")
    if state is PowerState.QUICK_STOP_ACTIVE:
        return f"in Quick Stop Active; {sw}"
    if state is PowerState.NOT_READY_TO_SWITCH_ON:
        return f"Not Ready To Switch On (still initialising, or a self-test failed); {sw}"
    return f"{state.value}: Enable Operation not taken; {sw}"

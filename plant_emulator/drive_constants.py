"""The emulated drive's constants: EMCY codes, timings, the EDS it answers with by default, the power
states that run or fault."""

from __future__ import annotations

from pathlib import Path

from drivectl.driver import cia402

#: CiA 402 digital inputs (bit 0 negative limit, 1 positive limit, 2 home switch)
DIGITAL_INPUTS = 0x60FD

#: EMCY / 0x603F codes (CiA 301 table 21)
RPDO_TIMEOUT_ERROR = 0x8250
RPDO_SHORT_ERROR = 0x8210  # PDO not processed due to length error
RPDO_LONG_ERROR = 0x8220  # PDO length exceeded
SYNC_LENGTH_ERROR = 0x8240  # unexpected SYNC data length
COMMUNICATION_ERROR = 0x8100  # communication, generic: NMT took the drive out of Operational while enabled
ERROR_RESET = 0x0000

#: default boot-up delay (ms of drive time); SYNC-loss window of a served drive (ms of wall time) when
#: no master heartbeat is consumed (else the consumer's time, 0x1016)
BOOT_DELAY_MS = 50.0
SYNC_LOSS_MS = 300.0
#: the SYNC-loss window of an in-process drive while the master's run is paced on the wall clock (cycles):
#: a master paced in real time leaves about one cycle between SYNCs, so a longer gap is the master running late
PACED_SYNC_LOSS_CYCLES = 2

EMULATED_DRIVE_EDS = Path(__file__).resolve().parent.parent / "driver" / "eds" / "drivectl-emulated-drive.eds"

RUNNING = (cia402.PowerState.OPERATION_ENABLED, cia402.PowerState.QUICK_STOP_ACTIVE)
FAULTED = (cia402.PowerState.FAULT, cia402.PowerState.FAULT_REACTION_ACTIVE)

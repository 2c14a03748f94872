"""The PDO mappings the master knows (full, compact, minimal): which objects each PDO carries, and how the
minimal mapping's event-driven controlword is repeated (machine/bus_budget.py counts their bits)."""

from __future__ import annotations

from drivectl.driver import cia402

#: the mapping drivectl configures: RPDO1 controlword + target torque; TPDO1 statusword + position;
#: TPDO2 velocity + torque actual (48 bits each, synchronous, transmission type 1)
RPDO_ENTRIES = ((cia402.CONTROLWORD, 0), (cia402.TARGET_TORQUE, 0))
#: the compact mapping (``bus.pdo_mapping = "compact"``, machine/bus_budget.py): one 8-byte TPDO with statusword,
#: position and torque actual; the velocity derived on the host from two positions (as SimAxis does)
COMPACT_TPDO_ENTRIES = (((cia402.STATUSWORD, 0), (cia402.POSITION_ACTUAL, 0), (cia402.TORQUE_ACTUAL, 0)),)
#: the minimal mapping (``bus.pdo_mapping = "minimal"``): TPDO1 statusword + position (velocity derived on the
#: host, torque actual not mapped: read 0x6077 by SDO where a tool needs it); RPDO1 the target torque alone,
#: synchronous; RPDO2 the controlword, event-driven (transmission type 255): sent in the cycles where the
#: controlword changes (CiA 301 practice), resent while a transition is pending and every CW_REFRESH_CYCLES, so
#: it costs the bus almost nothing in steady state
MINIMAL_TPDO_ENTRIES = (((cia402.STATUSWORD, 0), (cia402.POSITION_ACTUAL, 0)),)
MINIMAL_RPDO_ENTRIES = (((cia402.TARGET_TORQUE, 0),), ((cia402.CONTROLWORD, 0),))
#: the minimal mapping's RPDO2 is sent again each cycle, up to this many cycles after a change, while the drive
#: has not reported the state it asks for (the cycles a run waits for a transition: controllers/runtime/servo.py
#: STATE_CHANGE_CYCLES), so one lost frame costs a transition one cycle, not the transition
CW_RESEND_CYCLES = 20
#: ... and every this many cycles in any case (0.1 s at 1 kHz; 63 bits per 100 cycles: 0.06 % of 1 Mbit/s per
#: axis), so a lost frame that changed no power state (the halt bit) heals too
CW_REFRESH_CYCLES = 100
#: the PDO mappings the master knows (machine/bus_budget.py counts their bits)
MAPPINGS = ("full", "compact", "minimal")
TPDO_ENTRIES = (
    ((cia402.STATUSWORD, 0), (cia402.POSITION_ACTUAL, 0)),
    ((cia402.VELOCITY_ACTUAL, 0), (cia402.TORQUE_ACTUAL, 0)),
)

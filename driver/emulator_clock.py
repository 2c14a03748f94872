"""How a master tells drivectl's emulated drive in another process which clock it runs on (docs/timing.md,
"The emulated drive's clock (0x5FFF)").

A real drive runs on its own clock, whatever the master does. The emulated drive has none of its own: it steps
its plant at the SYNCs it receives, so it must know what the time between two SYNCs is. One object, answered by
`drivectl emulate`'s drives whatever EDS they impersonate and by no real drive, says it:

* ``EMULATOR_OBJECT`` (0x5FFF, manufacturer segment) sub 1, UNSIGNED32 read-only: ``EMULATOR_MARK``,
  drivectl's vendor number. Only read, never written, to find out whether a node is the emulator: a read of an
  object a drive lacks is aborted and changes nothing;
* sub 2, UNSIGNED8 read-write, written only to a node that answered sub 1 so, the master's clock:

  - ``CLOCK_OWN`` (0, at power-on and after a reset): SYNC-locked, one cycle per SYNC; after the SYNC-loss
    window (the heartbeat consumer time, 300 ms) on its own clock;
  - ``CLOCK_LOCKSTEP`` (1): time is the SYNC count and nothing else: one cycle per SYNC however long the master
    takes, never its own clock; its RPDO deadline and heartbeat consumer count SYNCs (a master that stops
    sending them stops time: nothing moves, nothing is missed);
  - ``CLOCK_SLOTS`` (2): a master on the wall clock whose SYNC carries its slot count (the CiA 301 SYNC counter
    byte, ``slot % SLOT_COUNTER_SPAN + 1``, counting the slots a late wake-up skipped as well): a SYNC whose
    counter jumped by n first runs the n - 1 cycles of the gap, the setpoint held, as a real drive's plant moves
    on while a late master is silent (its RPDO deadline counting them). The master sends the counter only while
    every drive it runs answered drivectl's mark: a real drive sees the plain SYNC.

"""

from __future__ import annotations

EMULATOR_OBJECT = 0x5FFF
MARK_SUB = 1
CLOCK_SUB = 2
#: 0x5FFF:1 of drivectl's emulated drive (its [DeviceInfo] VendorNumber)
EMULATOR_MARK = 0x00D71C70
CLOCK_OWN, CLOCK_LOCKSTEP, CLOCK_SLOTS = 0, 1, 2
CLOCK_NAMES = {CLOCK_OWN: "own", CLOCK_LOCKSTEP: "lockstep", CLOCK_SLOTS: "slots"}
#: the SYNC counter's values (CiA 301: 1..240 at most): the slot count modulo this, plus one
SLOT_COUNTER_SPAN = 240

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
    sending them stops time: nothing moves, nothing is missed).

A master on the wall clock leaves it at 0: it then steps one cycle per SYNC also where a late master skipped
slots (an open problem, docs/timing.md: the receive stamps cannot tell a late master from the emulator's own
late process).
"""

from __future__ import annotations

EMULATOR_OBJECT = 0x5FFF
MARK_SUB = 1
CLOCK_SUB = 2
#: 0x5FFF:1 of drivectl's emulated drive (its [DeviceInfo] VendorNumber)
EMULATOR_MARK = 0x00D71C70
CLOCK_OWN, CLOCK_LOCKSTEP = 0, 1
CLOCK_NAMES = {CLOCK_OWN: "own", CLOCK_LOCKSTEP: "lockstep"}

"""The process-wide measures a wall-clock loop takes for its thread: the garbage collector and the GIL.

Both are the process's, not a loop's: the first wall-clock loop takes them, the last one gives them back.
"""

from __future__ import annotations

import gc
import sys
import threading

# the collector is the process's: the first wall-clock loop takes it, the last one gives it back
_gc_lock = threading.Lock()
_gc_holders = 0
_gc_was_enabled = True


def take_gc() -> None:
    global _gc_holders, _gc_was_enabled
    with _gc_lock:
        if _gc_holders == 0:
            _gc_was_enabled = gc.isenabled()
            gc.collect()
            gc.freeze()  # what exists now is never scanned again: young collections stay short
            gc.disable()
        _gc_holders += 1


def release_gc() -> None:
    global _gc_holders
    with _gc_lock:
        _gc_holders -= 1
        if _gc_holders == 0:
            gc.unfreeze()  # back to normal collection: what was frozen may be collected again
            if _gc_was_enabled:
                gc.enable()


# the interpreter's switch interval is the process's too. Python hands the GIL to a waiting thread only
# after the holder has run for this long (5 ms by default): a program plotting beside the loop would
# hold the loop's thread off for up to five cycles. The first wall-clock loop shortens it, the last
# one restores it.
_switch_holders = 0
_switch_was = 0.005


def take_switch(interval: float) -> float:
    global _switch_holders, _switch_was
    with _gc_lock:
        if _switch_holders == 0:
            _switch_was = sys.getswitchinterval()
            sys.setswitchinterval(min(_switch_was, interval))
        _switch_holders += 1
        return _switch_was


def release_switch() -> None:
    global _switch_holders
    with _gc_lock:
        _switch_holders -= 1
        if _switch_holders == 0:
            sys.setswitchinterval(_switch_was)

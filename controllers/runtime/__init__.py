"""The runtime that drives the control laws: the resident loop, the servo cycle, moves, capture, homing,
run checks, the safe stop and interrupts.
"""

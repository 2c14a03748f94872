"""The machine: its configuration file (axes, buses, plants, controllers) and the assembly of axes from it.

Above the runtime (it names controllers, homing, motion limits) and below the commands and the session,
which both open a machine from it.
"""

"""Small test doubles shared by the tests (a PD controller and a sine reference)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from drivectl.controllers.base import Controller, Settings, param
from drivectl.profiles.base import Reference


@dataclass
class PdSettings(Settings):
    kp: float = param(3.0e6, lo=0.0)
    kd: float = param(1.0e4, lo=0.0)
    mass: float = param(88.08, lo=0.0)
    fc: float = param(46.7, lo=0.0)
    c: float = param(499.0, lo=0.0)


class PdController(Controller):
    """PD with model feed-forward; a stand-in that depends on nothing under test."""

    name = "test-pd"
    SettingsClass = PdSettings

    def reset(self) -> None:
        pass

    def step(self, reference, feedback):
        s = self.settings
        rv = reference.velocity
        ff = s.mass * reference.acceleration + s.c * rv + (s.fc if rv > 0 else -s.fc if rv < 0 else 0.0)
        return ff + s.kp * (reference.position - feedback.position) + s.kd * (rv - feedback.velocity)


@dataclass
class SineProfile:
    amplitude: float = 0.01
    freq: float = 0.5
    duration: float = 2.0

    @property
    def start_position(self) -> float:
        return 0.0

    def sample(self, t):
        w = 2 * math.pi * self.freq
        a = self.amplitude
        return a * np.sin(w * t), a * w * np.cos(w * t), -a * w * w * np.sin(w * t), -a * w**3 * np.cos(w * t)

    def at(self, t: float) -> Reference:
        p, v, acc, j = (float(x) for x in self.sample(np.array(t)))
        return Reference(p, v, acc, j)


class SimWallClock:
    """A simulated wall clock for paced runs (controllers/servo.Pacer(now=, sleep=)): time passes only by
    the pacer's waits, a microsecond per reading (so its spin ends) and what a test injects. Nothing sleeps."""

    def __init__(self, t0: float = 0.0) -> None:
        self.t = t0

    def now(self) -> float:
        self.t += 1e-6
        return self.t

    def sleep(self, s: float) -> None:
        self.t += s


def enabled_wall_loop(ch, **kw):
    """A resident loop on the wall clock (controllers/runtime/loop.py) over ``ch``, its clock the monotonic one plus a
    jump a test sets (``jump["s"]``: a stall as far as the loop can tell, whatever the machine's load), started
    and with the axis enabled and in servo. Returns (loop, jump); the caller closes the loop."""
    import time

    from drivectl.controllers.runtime.loop import AxisState, ServoLoop

    jump = {"s": 0.0}
    loop = ServoLoop([ch], clock="wall", now=lambda: time.perf_counter() + jump["s"], **kw)
    loop.start()
    rt = loop.axes[ch.axis.name]
    rt.state = AxisState.ENABLING
    loop.submit(ch.axis.enable)
    assert loop.run_until(lambda: rt.state is AxisState.SERVO, 10.0)
    return loop, jump


def reset_fault(axis, cycles: int = 4) -> None:
    """A fault reset by the master, then ``cycles`` cycles (read, zero effort) for the edge and its check."""
    axis.fault_reset()
    for _ in range(cycles):
        axis.read()
        axis.write(0.0)


def default_config_with(axis: str, cycle_s: float | None = None, **settings: object):
    """The embedded machine's configuration with ``settings`` added to ``axis``'s controller settings (and the
    cycle ``cycle_s``), parsed as a file would be."""
    import tomllib

    from drivectl.machine.config import DEFAULT_CONFIG_TOML, parse_config

    data = tomllib.loads(DEFAULT_CONFIG_TOML)
    if cycle_s is not None:
        data["cycle_s"] = cycle_s
    data["axes"][axis]["controller_settings"] = {**data["axes"][axis].get("controller_settings", {}), **settings}
    return parse_config(data, "<test>")

"""The socketcan backend on a kernel vcan interface: runs where vcan0 exists, skips cleanly elsewhere
(this development machine's kernel has no SocketCAN). Set DRIVECTL_SOCKETCAN to another channel to
use it."""

from __future__ import annotations

import os
import threading

import can
import canopen
import numpy as np
import pytest

from drivectl.controllers.registry import make_controller
from drivectl.controllers.runtime.servo import run
from drivectl.machine.build import open_machine
from drivectl.machine.config import BusConfig, load_config
from drivectl.plant_emulator.models import load_plant
from drivectl.plant_emulator.node402 import EmulatedDrive
from drivectl.profiles.ptp import PointToPoint

CHANNEL = os.environ.get("DRIVECTL_SOCKETCAN", "vcan0")


def _vcan_or_skip() -> can.BusABC:
    try:
        return can.Bus(interface="socketcan", channel=CHANNEL)
    except Exception as exc:  # noqa: BLE001 - any failure to open means: no SocketCAN here
        pytest.skip(f"no SocketCAN interface {CHANNEL} on this machine ({type(exc).__name__}: {exc})")


def test_trace_over_socketcan_equals_simulation():
    bus = _vcan_or_skip()
    cfg = load_config()
    ac = cfg.axis("x")
    net = canopen.Network(bus)
    drive = EmulatedDrive(net, ac.node_id, load_plant("rigid-x").build(cfg.cycle_s), rated_effort=ac.rated_effort)
    stop = threading.Event()

    def pump() -> None:  # the emulator's own receive loop, as `drivectl emulate` runs it
        while not stop.is_set():
            msg = bus.recv(0.05)
            if msg is not None and not msg.is_error_frame:
                net.notify(msg.arbitration_id, msg.data, msg.timestamp)

    thread = threading.Thread(target=pump, daemon=True)
    thread.start()
    drive.boot()
    profile = PointToPoint(0.0, 0.01, 0.05, 0.5, 20.0, hold_until=0.4)
    traces = []
    try:
        remote = type(cfg)(cfg.source, cfg.cycle_s, cfg.axes, BusConfig("socketcan", CHANNEL))
        for c, sim in ((remote, False), (cfg, True)):
            with open_machine(c, ["x"], sim=sim) as m:
                ctrl = make_controller("asmc", cfg.cycle_s, {"law": 14}, plant=m.specs["x"])
                res = run(m.axes["x"], ctrl, profile)
                assert res.ok, res.detail
                traces.append(res.trace)
    finally:
        stop.set()
        thread.join(2)
        bus.shutdown()
    assert np.array_equal(traces[0].pos, traces[1].pos)
    assert np.array_equal(traces[0].effort, traces[1].effort)

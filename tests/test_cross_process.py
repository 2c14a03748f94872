"""The emulator in another process (`drivectl emulate`), the master here: over SLCAN on a pty and
socketcand on loopback. The plant advances one cycle per SYNC on both sides of the process boundary,
so the trace equals the SimAxis trace bit for bit."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from drivectl.controllers.registry import make_controller
from drivectl.controllers.runtime.servo import run
from drivectl.machine.build import open_machine
from drivectl.machine.config import load_config
from drivectl.profiles.ptp import PointToPoint
from drivectl.tools.explain.core import explain
from drivectl.tracefile.format import Trace

AXIS_X = """
cycle_s = 0.001
[bus]
{bus}
[axes.x]
node_id = 1
rated_effort = 100.0
plant = "rigid-x"
controller = "asmc"
profile = "{profile}"
[axes.x.controller_settings]
law = 14
[axes.x.limits]
position_m = [-0.1, 0.1]
following_error_m = 0.002
"""


class Emulator:
    """`drivectl emulate` in a subprocess; the first line of its output names where it listens."""

    def __init__(self, tmp_path: Path, *flags: str, profile: str = "short-move"):
        cfg = tmp_path / "emu.toml"
        cfg.write_text(AXIS_X.format(bus='interface = "virtual"', profile=profile))
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "drivectl", "--config", str(cfg), "emulate", "--axis", "x", *flags],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        self.line = self.proc.stdout.readline()
        assert self.line.startswith("emulating x"), self.line + self.proc.stderr.read()

    def stop(self) -> str:
        self.proc.send_signal(signal.SIGTERM)
        _, err = self.proc.communicate(timeout=30)
        return err


def _config(tmp_path: Path, bus: str, profile: str = "short-move"):
    p = tmp_path / "master.toml"
    p.write_text(AXIS_X.format(bus=bus, profile=profile))
    return load_config(p)


def _trace(cfg, sim: bool, profile):
    # lockstep across processes: the same trace however loaded the host (as fast as the drive answers, a master
    # held up past the drive's SYNC-loss window saw it run on its own clock and stop: 0x8250, at load 12)
    with open_machine(cfg, ["x"], sim=sim, lockstep=not sim) as m:
        ctrl = make_controller("asmc", cfg.cycle_s, {"law": 14}, plant=m.specs["x"])
        res = run(m.axes["x"], ctrl, profile, limits=cfg.axis("x").limits)
        assert res.ok, res.detail
        return res.trace


@pytest.mark.parametrize("transport", ["slcan", "socketcand"])
def test_trace_across_processes_equals_simulation(tmp_path, transport):
    emu = Emulator(tmp_path, "--slcan" if transport == "slcan" else "--socketcand")
    try:
        if transport == "slcan":
            tty = re.search(r"(/dev/\S+)", emu.line).group(1)
            bus = f'interface = "slcan"\nchannel = "{tty}"'
        else:
            port = int(re.search(r"127\.0\.0\.1:(\d+)", emu.line).group(1))
            bus = f'interface = "socketcand"\nchannel = "can0"\nhost = "127.0.0.1"\nport = {port}'
        cfg = _config(tmp_path, bus)
        profile = PointToPoint(0.0, 0.01, 0.05, 0.5, 20.0, hold_until=0.5)
        remote = _trace(cfg, False, profile)
    finally:
        err = emu.stop()
    local = _trace(cfg, True, profile)
    assert np.array_equal(remote.pos, local.pos)
    assert np.array_equal(remote.effort, local.effort)
    assert "emulator stopped after" in err


def test_emulate_effect_trace_explain_end_to_end(tmp_path):
    """Issue 6 point 7: emulate with a hidden effect, trace the axis on it, explain names it."""
    emu = Emulator(tmp_path, "--slcan", "--effect", "periodic:amplitude=12,period=0.01", profile="circle")
    try:
        tty = re.search(r"(/dev/\S+)", emu.line).group(1)
        cfg = _config(tmp_path, f'interface = "slcan"\nchannel = "{tty}"', profile="circle")
        from drivectl.profiles.library import load_profile

        tr = _trace(cfg, False, load_profile("circle", axis="x"))
    finally:
        emu.stop()
    from drivectl.plant_emulator.models import load_plant

    res = explain(tr, load_plant("rigid-x"))
    assert res.effect == "periodic"
    assert res.params["amplitude"] == pytest.approx(12.0, rel=0.25)
    assert res.params["period"] == pytest.approx(0.01, rel=0.25)
    assert res.gap_after < 0.2 * res.gap_before


@pytest.mark.parametrize("how", [signal.SIGKILL, signal.SIGSTOP], ids=["killed", "hung"])
def test_killed_or_hung_master_the_drive_stops_on_its_own(tmp_path, how):
    """Issue 7 point 5 (second half): SIGKILL the master mid-trace; the emulated drive consumes the
    master's heartbeat (0x1016, 300 ms) and stops per 0x6007 (quick stop) by itself. SIGSTOP stands
    for a master that hangs with its port open (as a deadlock would): the same reaction."""
    emu = Emulator(tmp_path, "--slcan", profile="circle")
    master = None
    try:
        tty = re.search(r"(/dev/\S+)", emu.line).group(1)
        cfg_path = tmp_path / "master.toml"
        cfg_path.write_text(AXIS_X.format(bus=f'interface = "slcan"\nchannel = "{tty}"', profile="circle"))
        master = subprocess.Popen(
            [sys.executable, "-m", "drivectl", "--config", str(cfg_path), "trace", "--axis", "x", "--duration", "600",
             "--out", str(tmp_path), "--quiet", "--no-plot"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        line = master.stderr.readline()
        assert line.startswith("trace: axis x"), line
        master.send_signal(how)
        reaction = emu.proc.stderr.readline()  # printed by the emulator when it reacts
    finally:
        if master is not None:
            master.kill()  # a stopped process dies on SIGKILL too
            master.communicate(timeout=30)
        err = emu.stop()
    # the drive's clock runs on once the SYNCs stop: its RPDO deadline (2 cycles of drive time) or the
    # heartbeat consumer (300 ms), whichever runs out first, stops it
    assert re.search(r"master lost \(.*\): drive stopped \(Switch On Disabled, 0x603F = 0x(8250|8130)\)",
                     reaction), reaction + err


def test_scan_and_status_across_processes_read_the_nmt_state_from_the_drive(tmp_path, capsys):
    """Issue 18 leftover: across processes scan never sees the boot-up and the drive sends no heartbeat
    (0x1017 = 0 by default), so it said "unknown". It now asks the drive for one heartbeat (0x1017 set for a
    moment, then written back) and reports what the drive said; its 0x1017 is as it was found."""
    import json

    from drivectl.tools.cli.main import main

    emu = Emulator(tmp_path, "--socketcand")
    try:
        port = int(re.search(r"127\.0\.0\.1:(\d+)", emu.line).group(1))
        cfg = tmp_path / "master.toml"
        cfg.write_text(AXIS_X.format(bus=f'interface = "socketcand"\nchannel = "can0"\nhost = "127.0.0.1"\n'
                                         f'port = {port}', profile="short-move"))
        assert main(["--config", str(cfg), "scan", "--json"]) == 0
        nodes = json.loads(capsys.readouterr().out)["nodes"]
        assert [(n["node"], n["nmt"]) for n in nodes] == [(1, "PRE-OPERATIONAL")]
        assert main(["--config", str(cfg), "status", "--axis", "x", "--json"]) == 0
        assert json.loads(capsys.readouterr().out)["x"]["nmt"] == "PRE-OPERATIONAL"
        from drivectl.driver.network import close_threaded, open_bus, threaded_network

        net = threaded_network(open_bus("socketcand", "can0", host="127.0.0.1", port=port))
        try:
            node = net.add_node(1)
            assert node.sdo.upload(0x1017, 0) == b"\x00\x00"  # written back: no heartbeat left on
        finally:
            close_threaded(net)
    finally:
        emu.stop()



def test_an_axis_that_does_not_send_the_sync_waits_for_its_own_tpdos():
    """Several axes share one SYNC: only the first to read in a cycle sends it (and clears its TPDO event).
    The others found their event still set from their previous cycle, so across processes they did not
    wait for this cycle's TPDOs and bridged the cycle as lost whenever those came after the first axis's
    (at load, four in a row faulted y and z with "no TPDO"). Here y's TPDOs are held back and handed over
    only once y waits, as from a drive in another process: y must wait for them, not find the event set."""
    import threading

    from drivectl.machine.config import load_config as load

    with open_machine(load(None), ["x", "y"]) as m:
        x, y = m.axes["x"], m.axes["y"]
        for ax in (x, y):
            ax.connect()
        x.read(), y.read()
        held: list[tuple[int, bytes]] = []
        set_on_entry: list[bool] = []

        class Arrival(threading.Event):
            def wait(self, timeout: float | None = None) -> bool:
                set_on_entry.append(self.is_set())
                for (cob, data), cb in zip(held, late, strict=True):  # the drive's frames come in meanwhile
                    cb(cob, data, 0.0)
                return super().wait(timeout)

        y.lockstep = False  # frames come from elsewhere now: the event is what wakes y
        y._arrived = Arrival()
        y._arrived.set()  # as its previous cycle leaves it
        late = [y._tpdo_callback(i) for i in range(len(y._tpdo_cob))]
        for cob in y._tpdo_cob:  # the lockstep drive's answers to y are held, not delivered
            y.network.subscribers[cob][:] = [lambda cob, data, ts: held.append((cob, bytes(data)))]
        lost = y.lost_total
        x.read()  # sends the SYNC; the drives answer
        fb = y.read()
        assert set_on_entry == [False], "y found its TPDO event set from its previous cycle"
        assert y.lost_total == lost and y.state_fresh and fb is not None


def test_paced_tpdo_waits_share_one_budget_and_the_deadline_bounds_bridging():
    """On the wall clock across processes a cycle's TPDO waits end together, half the drive's deadline after
    the SYNC (three axes waiting one after the other no longer add up), and a cycle bridged for want of its
    TPDOs counts against the axis's deadline (docs/timing.md), not against the 3 of a lossless bus."""
    import threading

    from drivectl.machine.config import load_config as load

    with open_machine(load(None), ["x", "y"]) as m:
        x, y = m.axes["x"], m.axes["y"]
        for ax in (x, y):
            ax.connect()
        x.read(), y.read()
        now = [100.0]
        waits: list[float] = []

        class Arrival(threading.Event):
            def wait(self, timeout: float | None = None) -> bool:
                waits.append(timeout)
                return False  # nothing came

        for ax in (x, y):
            ax.lockstep = False
            ax._arrived = Arrival()
            ax.pace(lambda: now[0])
        assert y.rpdo_timeout_ms == 18 and y._lost_limit == 17 and y._tpdo_budget == pytest.approx(0.009)
        for cob in x._tpdo_cob + y._tpdo_cob:  # the drives' answers never reach the masters
            x.network.subscribers[cob][:] = []
        x.read()  # SYNC at t = 100 s; x waits its budget (8.5 ms), then the clock has moved on by it
        now[0] += 0.0085
        y.read()  # y's budget ends 9 ms after the same SYNC: 0.5 ms left, not another 9 ms
        assert waits == [pytest.approx(0.0085), pytest.approx(0.0005)]
        for ax in (x, y):
            ax.pace(None)
        assert y._lost_limit == y.max_lost_cycles == 3


def test_every_axis_waits_for_its_own_tpdos_across_processes(tmp_path):
    """Several axes share one SYNC: only the first to read in a cycle sends it. Each of the others used to
    find its TPDO event still set from its previous cycle, so across processes it did not wait for this
    cycle's TPDOs and bridged the cycle as lost whenever they came after the first axis's (at load, four
    in a row faulted y and z with "no TPDO"). Unpaced, the master waits for every drive: no cycle of any
    axis may be bridged."""
    import dataclasses

    import drivectl
    from drivectl.machine.config import DEFAULT_CONFIG_TOML

    cfg_path = tmp_path / "emu.toml"
    cfg_path.write_text(DEFAULT_CONFIG_TOML)
    emu = subprocess.Popen([sys.executable, "-m", "drivectl", "--config", str(cfg_path), "emulate", "--socketcand"],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                           env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        line = emu.stdout.readline()
        assert line.startswith("emulating"), line + emu.stderr.read()
        port = int(re.search(r"127\.0\.0\.1:(\d+)", line).group(1))
        cfg = load_config(cfg_path)
        cfg = dataclasses.replace(cfg, bus=dataclasses.replace(cfg.bus, interface="socketcand", channel="can0",
                                                               host="127.0.0.1", port=port))
        with drivectl.connect(cfg, clock="lockstep") as m:
            for ax in m.axes.values():
                ax.enable()
            m.loop.step(300)
            lost = {n: rt.ch.axis.lost_total for n, rt in m.loop.axes.items()}
            states = {n: ax.state for n, ax in m.axes.items()}
        assert lost == {n: 0 for n in lost}, lost
        assert set(states.values()) == {"servo"}, states
    finally:
        emu.send_signal(signal.SIGTERM)
        emu.communicate(timeout=30)


def _emulate_default(tmp_path, *flags: str):
    """`drivectl emulate` of the embedded machine's x in another process: (process, config for a master on it)."""
    from drivectl.machine.config import DEFAULT_CONFIG_TOML

    emu_cfg = tmp_path / "emu.toml"
    emu_cfg.write_text(DEFAULT_CONFIG_TOML)
    proc = subprocess.Popen([sys.executable, "-m", "drivectl", "--config", str(emu_cfg), "emulate", "--axis", "x",
                             "--socketcand", *flags], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    line = proc.stdout.readline()
    assert line.startswith("emulating"), line + proc.stderr.read()
    port = int(re.search(r"127\.0\.0\.1:(\d+)", line).group(1))
    master = tmp_path / "master.toml"
    master.write_text(DEFAULT_CONFIG_TOML.replace('interface = "virtual"', 'interface = "socketcand"', 1).replace(
        'channel = "drivectl"', 'channel = "can0"\nhost = "127.0.0.1"\n' f"port = {port}", 1))
    return proc, master


def test_trace_clock_lockstep_across_processes_is_the_simulation_bit_for_bit(tmp_path):
    """Issue 39 point 5: `drivectl trace --clock lockstep` against `drivectl emulate` in another process: the
    master waits for every SYNC's TPDOs (never bridges), the emulated drive, told so (0x5FFF:2), steps one cycle
    per SYNC however long the master takes: the trace is `trace --sim`'s, every column, bit for bit."""
    from drivectl.tools.cli.main import main

    emu, master = _emulate_default(tmp_path)
    base = ["--config", str(master), "trace", "--axis", "x", "--duration", "1.0", "--no-plot", "--quiet"]
    try:
        assert main([*base, "--clock", "lockstep", "--out", str(tmp_path / "bus")]) == 0
    finally:
        emu.send_signal(signal.SIGTERM)
        err = emu.communicate(timeout=30)[1]
    assert main([*base, "--sim", "--out", str(tmp_path / "sim")]) == 0
    files = [next((tmp_path / d).glob("x-*.csv")) for d in ("bus", "sim")]
    bus, sim = (Trace.read(f) for f in files)
    assert len(bus.pos) == len(sim.pos) == 1001
    assert np.array_equal(bus.pos, sim.pos) and np.array_equal(bus.effort, sim.effort)
    rows = [[line for line in f.read_text().splitlines() if not line.startswith("#")] for f in files]
    assert rows[0][0] == "time_s,ref_m,pos_m,effort,vel_m_s" and rows[0] == rows[1]  # every column as written
    assert bus.meta["tpdo_lost_cycles"] == "0" and "lockstep across processes" in bus.meta["bus"]
    assert "emulator stopped after" in err


def test_clock_lockstep_refuses_a_node_that_is_not_the_emulated_drive():
    """A real drive is never driven in lockstep: a node that does not answer drivectl's emulator object (0x5FFF:1)
    is refused at connect, one line, before anything is configured or moves."""
    from drivectl.driver.axis import AxisConfigError
    from drivectl.driver.emulator_clock import EMULATOR_OBJECT
    from drivectl.machine.config import load_config as load

    with open_machine(load(None), ["x"]) as m:
        ax, drive = m.axes["x"], m.drives["x"]
        del drive.od[EMULATOR_OBJECT]  # a drive that is not drivectl's emulator has no such object
        ax.lockstep_peer = True
        with pytest.raises(AxisConfigError) as exc:
            ax.connect()
        msg = str(exc.value)
        assert "\n" not in msg and msg.startswith("axis x: node 1: clock lockstep: the node is not drivectl's emulated")
        assert "--paced" in msg


def test_clock_lockstep_a_drive_that_stops_answering_is_one_error_not_a_hang():
    """Lockstep across processes waits for every SYNC's TPDOs, however long the drive takes, up to a generous
    bound of this process's running time; past it, one error (a TPDO timeout), never a hang, and the stop after it
    bridges as any run does."""
    from drivectl.driver.axis import AxisError, FaultKind
    from drivectl.machine.config import load_config as load

    with open_machine(load(None), ["x"]) as m:
        ax = m.axes["x"]
        ax.read()
        ax.lockstep, ax.lockstep_peer, ax.lockstep_wait = False, True, 0.05  # frames from elsewhere, waited for
        ax._tpdo_handlers = [ax._tpdo_callback(i) for i in range(len(ax._tpdo_cob))]
        for cob in ax._tpdo_cob:  # the drive's answers never reach the master
            ax.network.subscribers[cob][:] = []
        with pytest.raises(AxisError) as exc:
            ax.read()
        assert exc.value.kind is FaultKind.TPDO_TIMEOUT and "no TPDO for SYNC" in str(exc.value)
        assert "within 0.05 s (clock lockstep across processes" in str(exc.value)
        ax.read()  # the stop's cycles: bridged, no second wait
        assert ax.lost_cycles == 1


@pytest.mark.parametrize("lockstep", [True, False], ids=["lockstep", "as-fast-as-it-answers"])
def test_clock_lockstep_waits_out_a_drive_stopped_for_half_a_second(tmp_path, lockstep):
    """The emulator's process stopped for 0.5 s mid-run (SIGSTOP, as a starved host or VM stops it): in lockstep
    the master waits for that SYNC's TPDOs and the trace is still the simulation's bit for bit; without it the
    master gives up on each SYNC's TPDOs after 150 ms and bridges the cycle (or faults past 3 in a row): the trace
    is then not the simulation's."""
    import threading

    from drivectl.machine.build import axis_profile
    from drivectl.machine.config import load_config as load

    def stop_the_drive_at(axis, cycle: int, pid: int) -> None:  # the drive's process stopped once, at ``cycle``
        write, k = axis.write, [0]

        def counted(effort: float) -> None:
            k[0] += 1
            if k[0] == cycle:
                os.kill(pid, signal.SIGSTOP)
                threading.Timer(0.5, os.kill, (pid, signal.SIGCONT)).start()
            write(effort)

        axis.write = counted

    emu, master = _emulate_default(tmp_path)
    profile = axis_profile(load(None), "x")  # where the emulator puts x: its configured profile's start
    traces = []
    try:
        for cfg, sim in ((load(master), False), (load(None), True)):
            with open_machine(cfg, ["x"], sim=sim, lockstep=lockstep and not sim,
                              start={"x": profile.start_position}) as m:
                ac = cfg.axis("x")
                law = make_controller(ac.controller, cfg.cycle_s, ac.controller_settings, plant=m.specs["x"], axis="x")
                if not sim:
                    stop_the_drive_at(m.axes["x"], 300, emu.pid)
                traces.append(run(m.axes["x"], law, profile, limits=ac.limits, duration=0.6))
    finally:
        emu.send_signal(signal.SIGCONT)
        emu.send_signal(signal.SIGTERM)
        emu.communicate(timeout=30)
    remote, local = traces
    assert local.ok
    if lockstep:
        assert remote.ok, remote.detail
        assert np.array_equal(remote.trace.pos, local.trace.pos) and np.array_equal(remote.trace.effort,
                                                                                    local.trace.effort)
    else:  # bridged (extrapolated) cycles, or a TPDO timeout: not the simulation's trace
        assert int(remote.trace.meta["tpdo_lost_cycles"]) > 0 or "no TPDO for" in remote.detail
        assert not np.array_equal(remote.trace.pos, local.trace.pos[:len(remote.trace.pos)])

"""Cycle rates of the servo loop over CANopen, beside a bare python-can ping-pong in the same run.

* lockstep 1 axis / 2 axes: the servo loop on the emulated machine (virtual bus, lockstep, the
  lockstep bus of docs/lockstep-bus.md): SYNC, TPDOs, controller, RPDO and the plant, cycles per wall
  second (target >= 25 000 for one axis, and >= 0.25 of the same run's ping-pong: `ratio_1axis_pingpong`);
* trace x: `drivectl trace --axis x --no-plot` in this process, the run's cycles per wall second of its
  run (streaming the trace to disk as it goes; target >= 22 000): `trace_x_cps`;
* ping-pong: two python-can virtual buses, one frame each way per cycle, nothing else: the ceiling
  the bus library sets;
* paced: the same one-axis loop held to 1 kHz on the wall clock for --paced-seconds: missed-deadline
  fraction (target < 0.5 %) and worst lateness;
* slcan / socketcand across processes: `drivectl emulate --slcan | --socketcand` in a subprocess, the
  master here, a 2 s trace (the emulator pumps its own bus; the master waits for each cycle's TPDOs).

    python bench/loop_rate.py [--json] [--seconds 3] [--paced-seconds 10]
"""

from __future__ import annotations

import argparse
import json
import time

import can

from drivectl.controllers.registry import make_controller
from drivectl.controllers.runtime.servo import Channel, run_channels
from drivectl.driver.network import unique_virtual_channel
from drivectl.machine.build import open_machine
from drivectl.machine.config import load_config
from drivectl.profiles.library import load_profile


def lockstep_cps(names: list[str], seconds: float, pace: bool = False) -> tuple[float, dict]:
    cfg = load_config()
    profiles = {n: load_profile(cfg.axis(n).profile, axis=n) for n in names}
    with open_machine(cfg, names, start={n: p.start_position for n, p in profiles.items()}, paced=pace) as m:
        channels = [Channel(m.axes[n], make_controller(cfg.axis(n).controller, cfg.cycle_s,
                                                       cfg.axis(n).controller_settings, plant=m.specs[n], axis=n),
                            profiles[n], cfg.axis(n).limits) for n in names]
        t0 = time.perf_counter()
        res = run_channels(channels, duration=seconds, pace=pace)
        wall = time.perf_counter() - t0
    return res.cycles / wall, res.trace.meta


def cross_process_cps(transport: str, seconds: float) -> float:
    """`drivectl emulate` in another process, the master here; cycles per second of a trace."""
    import os
    import re
    import signal
    import subprocess
    import sys
    import tempfile
    from pathlib import Path

    from drivectl.machine.config import load_config as load
    from drivectl.profiles.ptp import PointToPoint

    body = ('cycle_s = 0.001\n[bus]\n{bus}\n[axes.x]\nnode_id = 1\nrated_effort = 100.0\nplant = "rigid-x"\n'
            'controller = "asmc"\nprofile = "short-move"\n')
    with tempfile.TemporaryDirectory() as tmp:
        emu_cfg = Path(tmp) / "emu.toml"
        emu_cfg.write_text(body.format(bus='interface = "virtual"'))
        flag = "--slcan" if transport == "slcan" else "--socketcand"
        proc = subprocess.Popen([sys.executable, "-m", "drivectl", "--config", str(emu_cfg), "emulate", flag],
                                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                                env={**os.environ, "PYTHONUNBUFFERED": "1"})
        try:
            line = proc.stdout.readline()
            if transport == "slcan":
                tty = re.search(r"(/dev/\S+)", line).group(1)
                bus = f'interface = "slcan"\nchannel = "{tty}"'
            else:
                port = re.search(r"127\.0\.0\.1:(\d+)", line).group(1)
                bus = f'interface = "socketcand"\nchannel = "can0"\nport = {port}'
            master_cfg = Path(tmp) / "master.toml"
            master_cfg.write_text(body.format(bus=bus))
            cfg = load(master_cfg)
            with open_machine(cfg, ["x"]) as m:
                ctrl = make_controller("asmc", cfg.cycle_s, {"law": 14}, plant=m.specs["x"])
                prof = PointToPoint(0.0, 0.01, 0.05, 0.5, 20.0, hold_until=seconds)
                t0 = time.perf_counter()
                res = run_channels([Channel(m.axes["x"], ctrl, prof)], duration=seconds)
                wall = time.perf_counter() - t0
        finally:
            proc.send_signal(signal.SIGTERM)
            proc.wait(30)
    return res.cycles / wall


def trace_cps() -> float:
    """`drivectl trace --axis x --no-plot`, run here: cycles per wall second of its recorded run (the
    call of run_channels that streams to --out; opening, configuring and the summary are not counted)."""
    import contextlib
    import io
    import tempfile

    from drivectl.controllers.runtime import servo
    from drivectl.tools.cli.main import main as cli

    timed: list[tuple[int, float]] = []
    run = servo.run_channels

    def timed_run(*args, **kwargs):
        t0 = time.perf_counter()
        res = run(*args, **kwargs)
        if kwargs.get("stream") is not None:
            timed.append((res.cycles, time.perf_counter() - t0))
        return res

    servo.run_channels = timed_run
    try:
        # its summary and messages would break --json's one object on stdout
        with tempfile.TemporaryDirectory() as tmp, contextlib.redirect_stdout(io.StringIO()), \
                contextlib.redirect_stderr(io.StringIO()):
            rc = cli(["trace", "--axis", "x", "--no-plot", "--quiet", "--out", tmp])
    finally:
        servo.run_channels = run
    if rc != 0 or len(timed) != 1:
        raise SystemExit(f"bench: drivectl trace --axis x --no-plot failed (exit {rc})")
    cycles, wall = timed[0]
    return cycles / wall


def pingpong_cps(cycles: int) -> float:
    ch = unique_virtual_channel("pingpong")
    a = can.Bus(interface="virtual", channel=ch)
    b = can.Bus(interface="virtual", channel=ch)
    ping = can.Message(arbitration_id=0x80, data=b"", is_extended_id=False)
    pong = can.Message(arbitration_id=0x181, data=bytes(6), is_extended_id=False)
    t0 = time.perf_counter()
    for _ in range(cycles):
        a.send(ping)
        b.recv(0)
        b.send(pong)
        a.recv(0)
    wall = time.perf_counter() - t0
    a.shutdown()
    b.shutdown()
    return cycles / wall


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print exactly one JSON object")
    ap.add_argument("--seconds", type=float, default=3.0, help="simulated seconds per lockstep run")
    ap.add_argument("--paced-seconds", type=float, default=10.0)
    args = ap.parse_args()
    one, _ = lockstep_cps(["x"], args.seconds)
    two, _ = lockstep_cps(["x", "y"], args.seconds)
    pp = pingpong_cps(20000)
    trace_x = trace_cps()
    slcan = cross_process_cps("slcan", 2.0)
    socketcand = cross_process_cps("socketcand", 2.0)
    _, meta = lockstep_cps(["x"], args.paced_seconds, pace=True)
    missed = float(meta["missed_fraction"])
    worst = float(meta["worst_late_ms"])
    out = {"lockstep_1axis_cps": round(one), "lockstep_2axis_cps": round(two), "pingpong_cps": round(pp),
           "slcan_cps": round(slcan), "socketcand_cps": round(socketcand), "paced_missed_fraction": missed,
           "paced_worst_late_ms": round(worst, 3), "trace_x_cps": round(trace_x),
           "ratio_1axis_pingpong": round(one / pp, 3)}
    if args.json:
        print(json.dumps(out))
        return
    print(f"{'loop':<44} {'cycles/s':>10} {'target':>10}")
    print(f"{'lockstep, 1 axis (virtual bus, emulated drive)':<44} {one:>10.0f} {'>= 25000':>10}")
    print(f"{'lockstep, 2 axes (one SYNC, two drives)':<44} {two:>10.0f} {'':>10}")
    print(f"{'drivectl trace --axis x --no-plot (streamed)':<44} {trace_x:>10.0f} {'>= 22000':>10}")
    print(f"{'python-can ping-pong (1 frame each way)':<44} {pp:>10.0f} {'':>10}")
    print(f"{'slcan (pty) across processes':<44} {slcan:>10.0f} {'':>10}")
    print(f"{'socketcand (127.0.0.1) across processes':<44} {socketcand:>10.0f} {'':>10}")
    print(f"\npaced 1 kHz, {args.paced_seconds:g} s, one axis: missed {missed * 100:.3f} % of deadlines "
          f"(target < 0.5 %), worst lateness {worst:.3f} ms")
    if meta.get("stop") != "completed":  # the drive's RPDO deadline runs on the wall clock too: a late master stops
        print(f"  the paced run stopped after {meta.get('cycles')} cycles: {meta.get('stop_detail', meta.get('stop'))}")
    print(f"ratio lockstep 1 axis / ping-pong: {one / pp:.3f} (target >= 0.25; the loop adds SYNC, 2 TPDOs, "
          "controller, plant)")


if __name__ == "__main__":
    main()

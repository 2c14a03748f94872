"""The SYNC period's jitter on a SocketCAN interface, sent by the resident loop against sent by the kernel
(driver/sync_source.py: python-can's send_periodic, the broadcast manager).

An emulated drive runs in another process (`drivectl emulate --interface socketcan`), the resident loop here
(`drivectl.connect(clock="wall")`, axis x connected, not enabled: SYNC, TPDOs, RPDO every cycle) for
--seconds, once with ``bus.sync = "loop"`` and once with ``"auto"``. A third socket on the interface records
every SYNC with the kernel's receive timestamp; the table gives the period's deviation from cycle_s and
the loop's own missed cycles. Needs a kernel CAN interface: on this project's machines run it in the VM,

    ../shared/vcan-vm/run -- .venv/bin/python bench/sync_jitter.py --cycle-s 0.01 [--json]

(the loop runs 20-60x slower there than on a host: a 10 ms cycle; on a host with vcan0, 0.001). ``--bare``: the
SYNC alone (a Python thread sleeping to absolute deadlines against python-can's send_periodic), where the
resident loop cannot run (its start bound is wall-clock).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import can
import numpy as np

import drivectl
from drivectl.driver.cia301 import SYNC_COB_ID
from drivectl.machine.config import DEFAULT_CONFIG_TOML


def _config(path: Path, channel: str, cycle_s: float, sync: str) -> None:
    text = DEFAULT_CONFIG_TOML.replace("cycle_s = 0.001", f"cycle_s = {cycle_s}", 1).replace(
        'interface = "virtual"', f'interface = "socketcan"\nsync = "{sync}"', 1).replace(
        'channel = "drivectl"', f'channel = "{channel}"', 1).replace(
        "rpdo_timeout_ms = 2 ", f"rpdo_timeout_ms = {max(2, round(2 * cycle_s * 1000))} ", 1)
    path.write_text(text)


def _record(channel: str, stop: threading.Event, out: list[float]) -> None:
    """Every SYNC's kernel receive time. can-utils' candump where it is installed: a Python reader on a slow
    host (the VM) falls behind at 1 kHz, its socket buffer overflows and dropped SYNCs read as long periods."""
    if shutil.which("candump"):
        _record_candump(channel, stop, out)
        return
    bus = can.Bus(interface="socketcan", channel=channel, can_filters=[{"can_id": SYNC_COB_ID, "can_mask": 0x7FF}])
    try:
        while not stop.is_set():
            msg = bus.recv(0.05)
            if msg is not None and msg.arbitration_id == SYNC_COB_ID:
                out.append(msg.timestamp)  # the kernel's receive time (SO_TIMESTAMP), not when Python read it
    finally:
        bus.shutdown()


def _record_candump(channel: str, stop: threading.Event, out: list[float]) -> None:
    # -L: "(1700000000.123456) vcan0 080#": the kernel's timestamp of each frame, the filter in the kernel
    proc = subprocess.Popen(["candump", "-L", f"{channel},{SYNC_COB_ID:03X}:7FF"], stdout=subprocess.PIPE, text=True)
    reader = threading.Thread(target=lambda: out.extend(float(line[1:line.index(")")]) for line in proc.stdout
                                                        if line.startswith("(")), daemon=True)
    reader.start()
    stop.wait()
    proc.terminate()
    reader.join(5)


def measure(channel: str, cycle_s: float, seconds: float, sync: str) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        cfg = Path(tmp) / "m.toml"
        _config(cfg, channel, cycle_s, sync)
        emu = subprocess.Popen([sys.executable, "-m", "drivectl", "--config", str(cfg), "emulate", "--interface",
                                "socketcan", "--channel", channel, "--axis", "x"], stdout=subprocess.PIPE, text=True)
        try:
            for line in emu.stdout:
                if line.startswith("point a master"):
                    break
            stamps: list[float] = []
            stop = threading.Event()
            rec = threading.Thread(target=_record, args=(channel, stop, stamps), daemon=True)
            with drivectl.connect(str(cfg), axes=["x"], clock="wall", fault_dir=None,
                                  loop="thread") as m:  # it reads the axis object: in this process
                clock = m.axes["x"]._rt.ch.axis.clock
                time.sleep(0.5)  # the loop settles
                rec.start()
                time.sleep(seconds)
                stop.set()
                rec.join(2)
                status = m.status()
                source, note = clock.sync_source, clock.sync_note
        finally:
            emu.terminate()
            emu.wait(10)
    periods = np.diff(np.asarray(stamps))
    dev = (periods - cycle_s) * 1e6
    return {"sync": sync, "sent_by": source, "note": note, "periods": int(len(periods)),
            "mean_period_us": float(np.mean(periods) * 1e6) if len(periods) else None,
            "jitter_std_us": float(np.std(dev)) if len(dev) else None,
            "jitter_p50_us": float(np.percentile(np.abs(dev), 50)) if len(dev) else None,
            "jitter_p99_us": float(np.percentile(np.abs(dev), 99)) if len(dev) else None,
            "jitter_max_us": float(np.max(np.abs(dev))) if len(dev) else None,
            "loop_missed": status.get("missed_deadlines"), "loop_cycles": status.get("cycles"),
            "loop_worst_late_ms": status.get("worst_late_ms")}


def _stats(stamps: list[float], cycle_s: float) -> dict:
    periods = np.diff(np.asarray(stamps))
    dev = np.abs(periods - cycle_s) * 1e6
    if not len(dev):
        return {"periods": 0, "mean_period_us": None, "jitter_std_us": None, "jitter_p50_us": None,
                "jitter_p99_us": None, "jitter_max_us": None}
    return {"periods": int(len(periods)), "mean_period_us": float(np.mean(periods) * 1e6),
            "jitter_std_us": float(np.std(periods * 1e6)), "jitter_p50_us": float(np.percentile(dev, 50)),
            "jitter_p99_us": float(np.percentile(dev, 99)), "jitter_max_us": float(np.max(dev))}


def measure_bare(channel: str, cycle_s: float, seconds: float, sync: str) -> dict:
    """The SYNC alone, no drive and no resident loop: a Python thread sleeping to absolute deadlines
    (``sync="loop"``, what a Python loop can do at best) or python-can's ``send_periodic`` (the kernel's
    broadcast manager)."""
    stamps: list[float] = []
    stop = threading.Event()
    rec = threading.Thread(target=_record, args=(channel, stop, stamps), daemon=True)
    rec.start()
    time.sleep(0.2)
    bus = can.Bus(interface="socketcan", channel=channel)
    msg = can.Message(arbitration_id=SYNC_COB_ID, data=b"", is_extended_id=False)
    try:
        if sync == "loop":
            end = time.monotonic() + seconds
            t = time.monotonic()
            while t < end:
                bus.send(msg)
                t += cycle_s
                delay = t - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            source = "python"
        else:
            task = bus.send_periodic(msg, cycle_s)
            time.sleep(seconds)
            task.stop()
            source = type(task).__name__
    finally:
        time.sleep(0.2)
        stop.set()
        rec.join(2)
        bus.shutdown()
    return {"sync": sync, "sent_by": source, "note": "bare: no drive, no resident loop", **_stats(stamps, cycle_s),
            "loop_missed": None, "loop_cycles": None, "loop_worst_late_ms": None}


def _host() -> str:
    """The kernel, and the machine's vendor where it says it is a VM (figures from a software-emulated CPU are
    no host's figures)."""
    try:
        vendor = Path("/sys/class/dmi/id/sys_vendor").read_text().strip()
    except OSError:
        vendor = "?"
    return f"{os.uname().release} ({vendor})"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--channel", default=os.environ.get("DRIVECTL_SOCKETCAN", "vcan0"))
    ap.add_argument("--cycle-s", type=float, default=0.001)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--bare", action="store_true",
                    help="the SYNC alone: a Python thread against send_periodic, no drive and no resident loop")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    how = measure_bare if args.bare else measure
    rows = [how(args.channel, args.cycle_s, args.seconds, s) for s in ("loop", "auto")]
    out = {"cycle_s": args.cycle_s, "seconds": args.seconds, "load": os.getloadavg()[0], "host": _host(),
           "bare": args.bare,
           "loop": rows[0], "transport": rows[1]}
    if args.json:
        print(json.dumps(out))
        return
    print(f"SYNC period on {args.channel}, cycle {args.cycle_s * 1e3:g} ms, {args.seconds:g} s each, "
          f"load {out['load']:.2f}, kernel {out['host']}")
    print("period error |T - cycle_s|, from the kernel's receive timestamps of every SYNC")
    print(f"{'sync':6s} {'sent by':10s} {'periods':>8s} {'mean us':>10s} {'p50 us':>9s} {'p99 us':>9s} "
          f"{'max us':>10s} {'std us':>9s} {'missed':>7s} {'late ms':>8s}")
    for r in rows:
        print(f"{r['sync']:6s} {r['sent_by']:10s} {r['periods']:8d} {r['mean_period_us'] or 0:10.1f} "
              f"{r['jitter_p50_us'] or 0:9.1f} {r['jitter_p99_us'] or 0:9.1f} {r['jitter_max_us'] or 0:10.1f} "
              f"{r['jitter_std_us'] or 0:9.1f} "
              f"{str(r['loop_missed']):>7s} {str(r['loop_worst_late_ms']):>8s}")
        if r["note"]:
            print(f"       ({r['note']})")


if __name__ == "__main__":
    main()

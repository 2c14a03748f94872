"""The soak: 10 minutes of simulated time, two axes in lockstep, random faults, recoveries, re-enables.

Axes x and y of the embedded machine (emulated CiA 402 drives on the virtual bus, CANopen masters)
run back-to-back random moves; before most moves a random fault is armed on a random axis (every
kind that leaves the master alive). Every fault that fired must be found in the traces (read back
from disk), memory must stay flat (tracemalloc after a warm-up of 10 %, at ten points after it and
at the end, each after a full garbage collection; the least-squares slope says what 100 more moves
would add), and no move may hang (a faulthandler guard dumps the stacks and exits after 120 s of wall time in one move).
tracemalloc slows the loop several times: 10 simulated minutes take 15-20 minutes here.

    python bench/soak.py [--minutes 10] [--seed 1] [--json]

``--wall`` (issue 25 point 8, the timing model of docs/timing.md): N minutes on the wall clock instead,
``drivectl.connect(clock="wall")`` with x, y and z enabled beside one CPU-bound process, a random mix of
moves, jogs, stops and captures, status polled at 20 Hz; in-process, or with ``--across`` against
``drivectl emulate --socketcand`` in another process. At the end the process is stopped for 0.5 s
(SIGSTOP, SIGCONT from a helper process): the axes must fault within their deadline plus 2 cycles after it
resumes (a real stall is still caught). ``--json`` prints exactly {"minutes", "faults", "missed_fraction",
"worst_late_ms", "latency_p99_99_ms", "moves_done", "moves_failed", "hogs"} (the deliberate stall excluded;
"hogs": how many CPU-bound processes ran beside it, `--hog N`, default 1).
Target: 0 faults over 30 minutes, both ways.

    python bench/soak.py --wall [--across] [--hog N] [--cycle-s 0.002|doctor] [--minutes 30] [--loop process|thread]
        [--json]

``--cycle-s doctor``: first ``drivectl doctor --json`` probes 10 s (across: 60 s) at 1 ms on the same set-up
(across: against an emulator of its own) beside the same hogs, and the soak runs at the cycle it recommends
(docs/timing.md, "The cycle doctor recommends"); the stderr line "cycle ..." says which it was.

``--cyclictest``: cyclictest (rt-tests) runs beside the soak, one real-time thread per CPU at 1 kHz
(``cyclictest -m -p 49 -i 1000 -t N -a -q --spike=10000``), and the stderr line "host stops" lists every wake-up
it saw 10 ms late or more, with how many faults came at one (docs/soaks.md: the host stops this VM now and
then, past the axes' deadlines; this says which faults were those). Needs root for its priority.

``--loop``: where the master's loop runs (``connect(loop=...)``, default process: issue 39 point 1); the
0.5 s SIGSTOP then stops the loop's process. The line on stderr names it.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from drivectl.tools.conformance.soak import run_soak

#: where the wall soak's moves go (m, around each axis's start; inside every axis's soft limits)
SPAN_M = 0.008
#: a rise of the host's steal time in one second this large is a gap no deadline of the machine rides out (s)
STEAL_RISE_S = 0.05


def _burn() -> None:
    while True:
        pass


def _emulator(tmp: Path, config: Path, log: Path):
    """``drivectl emulate --socketcand`` in another process, its stderr (what the drives say of a master they
    lost) kept in ``log``: (process, port)."""
    with log.open("w") as err:  # the child holds its own descriptor
        proc = subprocess.Popen([sys.executable, "-m", "drivectl", "--config", str(config), "emulate", "--socketcand"],
                                stdout=subprocess.PIPE, stderr=err, text=True,
                                env={**os.environ, "PYTHONUNBUFFERED": "1"})
    line = proc.stdout.readline()
    if not line.startswith("emulating"):
        proc.wait(timeout=30)
        raise RuntimeError(f"emulate did not start: {line}{log.read_text()}")
    return proc, int(re.search(r"127\.0\.0\.1:(\d+)", line).group(1))


def drive_lines(log: Path) -> list[str]:
    """The emulated drives' own words on the masters they lost (``drivectl emulate``'s stderr)."""
    return [ln.strip() for ln in log.read_text().splitlines() if "master lost" in ln] if log.exists() else []


def _steal_sampler(stop: threading.Event, rises: list, total: list) -> None:
    """Once a second, the host's steal time per vCPU (controllers/runtime/host.py): every rise of
    STEAL_RISE_S or more in one second, with its monotonic time (a fault near one is the hypervisor's)."""
    from drivectl.controllers.runtime.host import steal_s

    was = steal_s()
    while was is not None and not stop.wait(1.0):
        now = steal_s()
        total[0] += sum(now[c] - was.get(c, now[c]) for c in now)
        rises.extend((time.monotonic(), c, now[c] - was[c]) for c in now if now[c] - was.get(c, now[c]) >= STEAL_RISE_S)
        was = now


def steal_line(r: dict) -> str:
    """The host's steal time over the soak, and which faults came within 2 s of a rise."""
    rises, at = r["_steal_rises"], r["_fault_at"]
    near = sum(any(abs(t - f) <= 2.0 for t, _, _ in rises) for f in at)
    return (f"host: steal time {r['_steal_total_s'] * 1e3:.0f} ms over the soak, {len(rises)} rises of "
            f"{STEAL_RISE_S * 1e3:g} ms or more in one second (largest "
            f"{max((d for _, _, d in rises), default=0.0) * 1e3:.0f} ms); faults within 2 s of one: "
            f"{near} of {len(at)}")


#: cyclictest's spike threshold (us): below every axis's deadline, above the host's ordinary late wake-ups
SPIKE_US = 10_000
#: a fault this close after the end of a host stop (s), or during it, was that stop's
STOP_SLACK_S = 0.010
_SPIKE = re.compile(r"^T:\s*(\d+)\s+Spike:\s*(\d+):\s*TS:\s*(\d+)", re.M)


def _cyclictest(cpus: int):
    """cyclictest beside the soak, one real-time thread per CPU; its spikes are printed as they come."""
    return subprocess.Popen(["cyclictest", "-m", "-p", "49", "-i", "1000", "-t", str(cpus), "-a", "-q",
                             f"--spike={SPIKE_US}"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def cyclictest_spikes(text: str) -> list[tuple[int, float, float]]:
    """cyclictest's spikes: (thread, how late in s, when it woke in s of CLOCK_MONOTONIC), each once (it prints
    them as they come and again at its end)."""
    seen = {(int(t), int(lat), int(ts)) for t, lat, ts in _SPIKE.findall(text)}
    return sorted(((t, lat * 1e-6, ts * 1e-6) for t, lat, ts in seen), key=lambda s: s[2])


def at_host_stops(fault_at: list[float], spikes: list[tuple[int, float, float]]) -> int:
    """How many faults came during a stop cyclictest saw, or within STOP_SLACK_S after it ended (its wake-up)."""
    return sum(any(ts - late <= f <= ts + STOP_SLACK_S for _, late, ts in spikes) for f in fault_at)


def host_stops_line(r: dict) -> str:
    """The host's stops cyclictest saw beside the soak, and which faults came at one."""
    spikes, at = r["_spikes"], r["_fault_at"]
    if r.get("_cyclictest_error"):
        return f"host stops: cyclictest failed: {r['_cyclictest_error']}"
    if spikes is None:
        return "host stops: cyclictest did not run (--cyclictest)"
    worst = max((late for _, late, _ in spikes), default=0.0)
    listed = ", ".join(f"{late * 1e3:.1f} ms on CPU {t} at {ts:.3f} s" for t, late, ts in spikes[:12])
    return (f"host stops: cyclictest saw {len(spikes)} wake-up(s) {SPIKE_US / 1e3:g} ms late or more (worst "
            f"{worst * 1e3:.1f} ms){': ' + listed if listed else ''}; faults at one: {at_host_stops(at, spikes)} "
            f"of {len(at)}")


def wall_soak(minutes: float, *, across: bool, seed: int = 1, stall_s: float = 0.5, quiet: bool = False,
              cycle_s: float | None = 0.001, hogs: int = 1, loop: str = "process", cyclictest: bool = False) -> dict:
    """The wall-clock soak (see the module text); returns its figures and the stall's outcome.
    ``cycle_s`` None: the cycle ``drivectl doctor`` recommends on the same set-up beside the same hogs.
    ``cyclictest``: run it beside the soak (after doctor's probe, to the end)."""
    import multiprocessing

    import drivectl
    from drivectl.controllers.runtime.handles import MotionFault
    from drivectl.driver.axis import AxisError
    from drivectl.machine.config import load_config

    rng = random.Random(seed)
    emu = None
    tmp = Path(tempfile.mkdtemp(prefix="soak-wall-"))
    config = tmp / "machine.toml"  # the embedded machine at this cycle, for both ends
    burners = [multiprocessing.get_context("spawn").Process(target=_burn, daemon=True) for _ in range(hogs)]
    for burner in burners:  # first: doctor's probe runs beside them too
        burner.start()
    doctor = None
    if cycle_s is None:  # the cycle doctor recommends for this set-up, beside the same hogs
        doctor = _doctor_cycle(tmp, across, PROBE_S[across])
        cycle_s = doctor["recommended_cycle_s"]
    config.write_text(_config_text(cycle_s))
    if across:  # the emulator runs the embedded machine; the master reaches it over socketcand
        emu, port = _emulator(tmp, config, tmp / "emulator.log")
        config = tmp / "master.toml"
        config.write_text(_config_text(cycle_s, port))
    cfg = load_config(config)
    polls, done, failed, fault_lines, refusals, fault_at = [0], 0, 0, [], [0], []
    rises, stolen, stop_steal = [], [0.0], threading.Event()
    ct = _cyclictest(os.cpu_count() or 1) if cyclictest else None  # here: the finally below ends it
    threading.Thread(target=_steal_sampler, args=(stop_steal, rises, stolen), daemon=True).start()
    try:
        with drivectl.connect(cfg, clock="wall", fault_dir=tmp, loop=loop) as m:
            names = list(m.axes)
            for ax in m.axes.values():
                ax.enable()
            home = {n: ax.position for n, ax in m.axes.items()}
            stop_poll = threading.Event()

            def poll() -> None:  # the status at 20 Hz, as a UI would
                while not stop_poll.wait(0.05):
                    m.status()
                    polls[0] += 1

            poller = threading.Thread(target=poll, daemon=True)
            poller.start()
            st0 = m.status()
            t_end = time.monotonic() + 60.0 * minutes
            while time.monotonic() < t_end:
                name = rng.choice(names)
                ax = m.axes[name]
                what = rng.choice(("move", "move", "jog", "stop", "capture"))
                try:
                    if ax.state != "servo":  # a fault: say so, reset, go on (enable may refuse: the host is late)
                        if ax.fault is not None:
                            at = "" if getattr(ax.fault, "at", None) is None else f" (monotonic {ax.fault.at:.3f} s)"
                            fault_lines.append(f"{name}: {ax.fault.kind}: {ax.fault.detail}{at}")
                            if getattr(ax.fault, "at", None) is not None:
                                fault_at.append(ax.fault.at)
                        ax.fault_reset(2.0)
                        try:
                            ax.enable(2.0)
                        except AxisError as exc:
                            refusals[0] += 1
                            fault_lines.append(f"{name}: {exc}")
                            time.sleep(1.0)
                        continue
                    if what == "move":
                        ax.move_to(home[name] + rng.uniform(-SPAN_M, SPAN_M)).wait(20.0)
                    elif what == "jog":
                        v = rng.choice((-1, 1)) * rng.uniform(0.002, 0.01)
                        for _ in range(rng.randint(1, 6)):
                            if abs(ax.position - home[name]) > SPAN_M:
                                break
                            ax.jog(v)
                            time.sleep(0.1)
                        ax.stop().wait(10.0)
                    elif what == "stop":
                        h = ax.move_to(home[name] + rng.uniform(-SPAN_M, SPAN_M))
                        time.sleep(rng.uniform(0.01, 0.3))
                        ax.stop().wait(10.0)
                        h.wait(1.0) if not h.done else None
                    else:
                        ax.capture(trigger="now", pre=0.2, post=0.2).wait(5.0)
                    done += 1
                except (MotionFault, TimeoutError, AxisError) as exc:
                    failed += 1
                    fault_lines.append(f"{name} {what}: {exc}")
            st = m.status()
            stop_poll.set()
            poller.join(1.0)
            holds = _holds(m)
            stall = _stall(m, stall_s)
    finally:
        stop_steal.set()
        for burner in burners:
            burner.terminate()
        if emu is not None:
            emu.send_signal(signal.SIGTERM)
            emu.communicate(timeout=30)
        ct_out = None
        if ct is not None:
            ct.send_signal(signal.SIGINT)
            ct_out = ct.communicate(timeout=30)[0]
    slots = max(st["cycles"] - st0["cycles"] + st["skipped_cycles"] - st0["skipped_cycles"], 1)
    return {"minutes": minutes, "hogs": hogs, "faults": st["faults"] - st0["faults"],
            "missed_fraction": (st["missed_deadlines"] - st0["missed_deadlines"]) / slots,
            "worst_late_ms": st["worst_late_ms"], "latency_p99_99_ms": st["latency_ms"]["p99_99"],
            "moves_done": done, "moves_failed": failed, "_refusals": refusals[0], "_stall": stall,
            "_status": st, "_polls": polls[0], "_faults": fault_lines,
            "_steal_rises": rises, "_steal_total_s": stolen[0], "_fault_at": fault_at, "_cycle_s": cycle_s,
            "_doctor": doctor, "_drive_lines": drive_lines(tmp / "emulator.log"), "_holds": holds,
            "_spikes": None if ct_out is None else cyclictest_spikes(ct_out),
            "_cyclictest_error": None if ct_out is None or "Max:" in ct_out else (ct_out.strip() or "no output")[-300:]}


def _holds(m, rest_s: float = 0.5, hold_s: float = 1.0) -> dict:
    """Every axis at rest at the end: the error's peak to peak (m) over ``hold_s`` after ``rest_s``, and whether
    the effort sat at its limit (a limit cycle inside the following-error window faults nothing: y's at 2 ms
    before docs/standstill.md "The cycle"). Axes not in servo are left out."""
    from drivectl.controllers.runtime.capture import CaptureError
    from drivectl.tools.commissioning.cycle_check import rest_figures

    time.sleep(rest_s)
    caps = {n: ax.capture(trigger="now", pre=0.0, post=hold_s) for n, ax in m.axes.items() if ax.state == "servo"}
    out = {}
    for n, cap in caps.items():
        try:
            tr = cap.wait(hold_s + 5.0)
        except (TimeoutError, CaptureError) as exc:  # a fault ended it: the fault lines say which
            out[n] = {"error": str(exc)}
            continue
        pp, _, at_limit = rest_figures(tr.error, tr.effort, m.axes[n].limits.max_effort)
        out[n] = {"peak_to_peak_m": pp, "at_limit": at_limit}
    return out


def holds_line(holds: dict) -> str:
    parts = []
    for n, h in holds.items():
        if "error" in h:
            parts.append(f"{n} not captured ({h['error']})")
        else:
            parts.append(f"{n} {h['peak_to_peak_m'] * 1e6:.2f} um p-p" + (", the effort AT ITS LIMIT (a limit cycle)"
                                                                         if h["at_limit"] else ""))
    return f"hold at the end ({len(holds)} axes at rest, 1 s): " + ("; ".join(parts) or "no axis in servo")


def _config_text(cycle_s: float, port: int | None = None) -> str:
    """The embedded machine at ``cycle_s``; with ``port``, its master on socketcand at that loopback port."""
    from drivectl.machine.config import DEFAULT_CONFIG_TOML

    text = DEFAULT_CONFIG_TOML.replace("cycle_s = 0.001", f"cycle_s = {cycle_s!r}", 1)
    if port is not None:
        text = re.sub(r'(?m)^interface = "virtual".*$', 'interface = "socketcand"', text, count=1)
        text = re.sub(r'(?m)^channel = "drivectl".*$', f'channel = "can0"\nhost = "127.0.0.1"\nport = {port}',
                      text, count=1)
    return text


# doctor's probe enables no axis; across processes it wavers between cycles in 10 s (docs/timing.md, "The
# cycle doctor recommends": run it 60 s or more there)
PROBE_S = {False: 10.0, True: 60.0}


def _doctor_cycle(tmp: Path, across: bool, seconds: float) -> dict:
    """``drivectl doctor --json`` at 1 ms on this soak's set-up (across: against an emulator of its own, which
    then ends): its JSON, whose "recommended_cycle_s" the soak then runs at."""
    probe_cfg = tmp / "doctor.toml"
    probe_cfg.write_text(_config_text(0.001))
    emu = None
    try:
        if across:
            emu, port = _emulator(tmp, probe_cfg, tmp / "emulator-doctor.log")
            probe_cfg.write_text(_config_text(0.001, port))
        out = subprocess.run([sys.executable, "-m", "drivectl", "--config", str(probe_cfg), "doctor", "--seconds",
                              str(seconds), "--json"], capture_output=True, text=True, timeout=seconds + 120)
    finally:
        if emu is not None:
            emu.send_signal(signal.SIGTERM)
            emu.communicate(timeout=30)
    try:
        return {**json.loads(out.stdout), "_seconds": seconds}
    except json.JSONDecodeError as exc:
        raise RuntimeError(f"doctor gave no JSON (exit {out.returncode}): {out.stderr.strip()[-400:]}") from exc


def _stall(m, seconds: float) -> dict:
    """Stop this process for ``seconds`` (SIGSTOP, then SIGCONT from a helper process) with every axis
    enabled; how long after it resumed the loop faulted an axis (the detection time against the resume)."""
    from drivectl.driver.axis import AxisError

    loop = m.loop
    pid = getattr(m, "pid", os.getpid())  # the loop's own process, else this one
    for ax in m.axes.values():
        if ax.state != "servo":
            try:
                ax.fault_reset(2.0)
                ax.enable(2.0)
            except AxisError as exc:  # the host too late for the deadline: refused, and said why
                return {"fault": None, "axis": None, "ms_after_resume": None, "deadline_ms": None,
                        "within": False, "safe": {}, "refused": str(exc)}
    n0 = len(loop.faults)
    # the helper stops this process, resumes it and prints when it resumed it (CLOCK_MONOTONIC, shared by the
    # processes): the fault's own detection time, against that, is how long the loop took to catch the stall
    helper = subprocess.Popen([sys.executable, "-c", (
        "import os, signal, sys, time\n"
        f"pid, s = {pid}, {seconds}\n"
        "time.sleep(0.2); os.kill(pid, signal.SIGSTOP); time.sleep(s)\n"
        "t = time.monotonic(); os.kill(pid, signal.SIGCONT); print(t)")], stdout=subprocess.PIPE, text=True)
    resumed = float(helper.communicate()[0])
    m.run_until(lambda: len(loop.faults) > n0, 2.0)
    time.sleep(0.1)
    fault = loop.faults[n0] if len(loop.faults) > n0 else None
    after_ms = None if fault is None or fault.at is None else (fault.at - resumed) * 1e3
    deadline_ms = loop.deadlines.get(fault.axis) * 1e3 if fault else None
    return {"fault": None if fault is None else f"{fault.kind}: {fault.detail}", "axis": fault and fault.axis,
            "ms_after_resume": after_ms, "deadline_ms": deadline_ms,
            "within": after_ms is not None and after_ms <= deadline_ms + 2 * loop.dt * 1e3,
            "safe": {n: ax.power.value for n, ax in m.axes.items()}}


def stall_line(stall: dict) -> str:
    if stall.get("refused"):
        return f"stall of 0.5 s (SIGSTOP): not tried, no axis could be enabled: {stall['refused']}"
    if stall["fault"] is None:
        return "stall of 0.5 s (SIGSTOP): NOT caught"
    within = "within" if stall["within"] else "NOT within"
    return (f"stall of 0.5 s (SIGSTOP): {stall['fault']}; axis {stall['axis']} faulted "
            f"{stall['ms_after_resume']:.1f} ms after the process resumed ({within} its deadline "
            f"{stall['deadline_ms']:g} ms + 2 cycles); end states as the drives reported them {stall['safe']}")


def cycle_line(r: dict) -> str:
    """The cycle the soak ran at, and whose choice it was."""
    d = r["_doctor"]
    if d is None:
        return f"cycle {r['_cycle_s'] * 1e3:g} ms (--cycle-s)"
    lat = d["latency_ms"]
    return (f"cycle {r['_cycle_s'] * 1e3:g} ms, recommended by drivectl doctor ({d['_seconds']:g} s probe at 1 ms "
            f"beside the hogs: verdict {d['verdict']}, p99.99 {lat['p99_99']:.2f} ms, max {lat['max']:.2f} ms, "
            f"{d.get('late_share', 0.0) * 100:.2f} % of its cycles over half a cycle late, "
            f"{d.get('missed_fraction', 0.0) * 100:.2f} % of its slots missed, the loop's thread "
            f"{(d.get('cpu_share') or 0.0) * 100:.0f} % of a CPU)")


def loop_line(st: dict) -> str:
    """The loop's own record at the end (before the stall): what a fault may be laid at."""
    return ("loop: lateness " + ", ".join(f"{q} {v:.2f}" for q, v in st["latency_ms"].items()) + " ms; skipped "
            f"{st['skipped_cycles']} slots ({st.get('late_syncs', 0)} at a SYNC later than its slot); "
            f"stalls {st['stalls']}; collections {st['gc_collections']}, worst "
            f"{st['gc_worst_ms']:.2f} ms; the loop's thread {(st.get('cpu_share') or 0.0) * 100:.0f} % of a CPU; "
            "deadlines " + ", ".join(f"{n} {v:g}" for n, v in st["deadline_ms"].items())
            + " ms")


def _interrupted(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0, help="simulated minutes (default 10)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json", action="store_true", help="print exactly one JSON object")
    ap.add_argument("--wall", action="store_true", help="on the wall clock, x, y and z, beside a CPU-bound process")
    ap.add_argument("--across", action="store_true", help="--wall against drivectl emulate --socketcand")
    ap.add_argument("--cycle-s", default="0.001",
                    help="--wall: the servo cycle in s (default 0.001; longer: the way out where a host cannot keep "
                    "it), or 'doctor': the cycle drivectl doctor recommends on the same set-up beside the hogs")
    ap.add_argument("--hog", type=int, default=1, help="--wall: CPU-bound processes beside the soak (default 1)")
    ap.add_argument("--cyclictest", action="store_true",
                    help="--wall: cyclictest beside the soak; which faults came at the host's stops (needs root)")
    ap.add_argument("--loop", choices=("process", "thread"), default="process",
                    help="--wall: the loop in its own process (default) or a thread of this one")
    args = ap.parse_args()
    # a SIGTERM (or a SIGINT where a background start ignores it) ends the soak as Ctrl-C does: through the
    # cleanup, so the emulator and the hogs end with it instead of running on as orphans
    signal.signal(signal.SIGTERM, _interrupted)
    if args.cyclictest and not args.wall:
        ap.error("--cyclictest: only with --wall (the lockstep soak runs on simulated time)")
    if args.wall:
        if args.hog < 0:
            ap.error(f"--hog: must be 0 or more, got {args.hog}")
        cycle_s = None
        if args.cycle_s != "doctor":
            try:
                cycle_s = float(args.cycle_s)
            except ValueError:
                ap.error(f"--cycle-s: expected seconds or 'doctor', got {args.cycle_s!r}")
            if not (0.0005 <= cycle_s <= 0.01):
                ap.error(f"--cycle-s: must be within 0.0005..0.01 s, got {args.cycle_s}")
        if args.cyclictest and shutil.which("cyclictest") is None:
            ap.error("--cyclictest: no cyclictest on PATH (Debian: apt-get install rt-tests)")
        r = wall_soak(args.minutes, across=args.across, seed=args.seed, quiet=args.json, cycle_s=cycle_s,
                      hogs=args.hog, loop=args.loop, cyclictest=args.cyclictest)
        if args.json:
            print(json.dumps({k: v for k, v in r.items() if not k.startswith("_")}))
            for line in list(dict.fromkeys(r["_faults"]))[:20]:  # what went wrong, beside the one object
                print(f"  {line}", file=sys.stderr)
            for line in r["_drive_lines"][:20]:
                print(f"  emulated drive: {line}", file=sys.stderr)
            print(holds_line(r["_holds"]), file=sys.stderr)
            print(stall_line(r["_stall"]), file=sys.stderr)
            print(f"({args.loop} loop) " + loop_line(r["_status"]), file=sys.stderr)
            print(steal_line(r), file=sys.stderr)
            print(host_stops_line(r), file=sys.stderr)
            print(cycle_line(r), file=sys.stderr)
            return
        st, stall = r["_status"], r["_stall"]
        print(f"wall soak, {'across processes (socketcand)' if args.across else 'in-process'}, the loop in "
              f"{'its own process' if args.loop == 'process' else 'a thread of the program'}: "
              f"{r['minutes']:g} min at cycle {r['_cycle_s'] * 1e3:g} ms, x y z enabled "
              f"beside {args.hog} CPU-bound process(es); "
              "load average "
              f"{' '.join(f'{v:.2f}' for v in os.getloadavg())}")
        print(f"faults {r['faults']}, moves done {r['moves_done']}, failed {r['moves_failed']}, enables refused "
              f"{r['_refusals']} (the host too late for the deadline), status polls {r['_polls']}")
        print(f"missed {r['missed_fraction'] * 100:.3f} % of the slots, worst late {r['worst_late_ms']:.2f} ms; "
              "lateness " + ", ".join(f"{q} {v:.3f} ms" for q, v in st["latency_ms"].items()))
        print("deadlines " + ", ".join(f"{n} {v:g} ms" for n, v in st["deadline_ms"].items()))
        for line in list(dict.fromkeys(r["_faults"]))[:10]:
            print(f"  {line}")
        for line in r["_drive_lines"][:10]:
            print(f"  emulated drive: {line}")
        print(holds_line(r["_holds"]))
        print(stall_line(stall))
        print(loop_line(st))
        print(steal_line(r))
        print(host_stops_line(r))
        print(cycle_line(r))
        return
    r = run_soak(60.0 * args.minutes, seed=args.seed, progress=not args.json)
    out = {
        "simulated_s": round(r.simulated_s, 3),
        "moves": r.moves,
        "faults_injected": sum(r.injected.values()),
        "faults_accounted": sum(r.accounted.values()),
        "unaccounted": r.unaccounted,
        "memory_warm_kib": round(r.memory_warm_kib, 1),
        "memory_end_kib": round(r.memory_end_kib, 1),
        "memory_growth_kib": round(r.memory_growth_kib, 1),
        "memory_slope_kib_per_100_moves": round(r.memory_slope_kib_per_100_moves, 2),
        "worst_move_wall_s": round(r.worst_move_wall_s, 3),
        "wall_s": round(r.wall_s, 1),
    }
    if args.json:
        print(json.dumps(out))
        return
    print(f"simulated {r.simulated_s:.1f} s in {r.moves} moves, {r.wall_s:.0f} s wall "
          f"(worst move {r.worst_move_wall_s:.2f} s wall: no hang)")
    print(f"{'fault':<28} {'injected':>9} {'accounted':>10}")
    for case in sorted(r.injected):
        print(f"{case:<28} {r.injected[case]:>9} {r.accounted[case]:>10}")
    print(f"{'all':<28} {sum(r.injected.values()):>9} {sum(r.accounted.values()):>10}   recoveries {r.recoveries}")
    for line in r.unaccounted:
        print(f"  NOT ACCOUNTED: {line}")
    print(f"memory (tracemalloc): {r.memory_warm_kib:.0f} KiB after warm-up, {r.memory_end_kib:.0f} KiB at the end "
          f"({r.memory_growth_kib:+.0f} KiB), peak {r.memory_peak_kib:.0f} KiB")
    print("memory samples (moves: KiB, after a full collection): "
          + ", ".join(f"{m}: {k:.0f}" for m, k in r.memory_samples))
    print(f"slope {r.memory_slope_kib_per_100_moves:+.1f} KiB per 100 moves")


if __name__ == "__main__":
    main()

"""Standing still (issue 26): how well every shipped controller holds a resting axis, on every axis.

In lockstep on the embedded machine (``drivectl.connect(clock="lockstep")``: the emulated CiA 402 drives
over the virtual bus), each axis under each controller is enabled and given, one after the other, the
commands a user gives: ``move_by`` +5 mm and -3 mm, a jog at 10 mm/s released after 0.3 s (the dead man
stops it), a stop 0.15 s into a 20 mm move, ``home()`` and a relative ``run()`` of the axis's profile.
After each command has ended, the following error (reference minus the encoder reading) is taken from
0.3 s on for 5 s (the session's ring): its largest magnitude and its peak-to-peak.

Cases: ``exact`` (the plant the controller believes); on x and y also ``stribeck`` (the plant with an unmodelled
Stribeck effect, excess_force 15 N, velocity 2 mm/s; the controller believes rigid-x) and ``noise`` (a
2 N Gaussian force noise on the plant). Targets (the defaults, every case: issue 26 point 2 for the exact
plant, issue 38 point 6 for all): <= 0.5 um and peak-to-peak <= 0.5 um.

``--json`` prints exactly one object: ``worst_hold_um``, ``worst_peak_to_peak_um`` (exact plant),
``worst_stribeck_um``, ``worst_stribeck_peak_to_peak_um``, ``worst_noise_um``, ``worst_noise_peak_to_peak_um``
(x and y), each over the default controllers, and ``rows`` (one per
run: axis, controller, default, case, command, max_um, peak_to_peak_um, status).

``--move-cost``: mbc's cost per cycle of a session move with the move's preview against the extrapolation
fallback (issue 26 point 4), on SimAxis; wall-clock figures, disturbed by other load.

Usage: .venv/bin/python bench/standstill.py [--json] [--defaults] [--axes x,y,z] [--controllers mbc,asmc]
       [--cycle-s 0.002] [--move-cost]
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent.parent))

from drivectl.controllers.registry import CONTROLLERS  # noqa: E402

SETTLE_S = 0.3
HOLD_S = 5.0
STRIBECK = ("stribeck", {"excess_force": 15.0, "velocity": 0.002})
NOISE = 2.0
CASES = {"exact": ((), 0.0), "stribeck": ((STRIBECK,), 0.0), "noise": ((), NOISE)}
COMMANDS = ("move_by +5 mm", "move_by -3 mm", "jog released", "stop mid-move", "home()", "run relative")


def hold_figures(machine, name: str) -> tuple[float, float]:
    """Let SETTLE_S + HOLD_S pass; the last HOLD_S of following error: (max |e|, peak-to-peak), um."""
    machine.advance(SETTLE_S + HOLD_S)
    rt = machine.axes[name]._rt
    fe = rt.ring.window(int(round(HOLD_S / machine.loop.dt)))[0][2]
    return float(np.max(np.abs(fe)) * 1e6), float((np.max(fe) - np.min(fe)) * 1e6)


def command(machine, name: str, what: str) -> None:
    """Give ``what`` to axis ``name`` and wait until it ended."""
    from drivectl.machine.build import axis_profile

    a = machine.axes[name]
    if what == "move_by +5 mm":
        a.move_by(0.005).wait(10)
    elif what == "move_by -3 mm":
        a.move_by(-0.003).wait(10)
    elif what == "jog released":
        h = a.jog(0.01)
        machine.advance(0.3)
        h.wait(10)
    elif what == "stop mid-move":
        a.move_by(0.02)
        machine.advance(0.15)
        a.stop().wait(10)
    elif what == "home()":
        a.home().wait(30)
    elif what == "run relative":
        a.run(axis_profile(machine.config, name), relative=True).wait(60)
    else:
        raise ValueError(what)


def session_rows(cfg, name: str, controller: str, case: str, default: bool) -> list[dict]:
    import drivectl

    effects, noise = CASES[case]
    ac = cfg.axis(name)
    settings = ac.controller_settings if default else {}
    c = replace(cfg, axes={name: replace(ac, controller=controller, controller_settings=settings)})
    rows = []
    base = {"axis": name, "controller": controller, "default": default, "case": case}
    try:
        m = drivectl.connect(c, axes=[name], clock="lockstep", ring_s=SETTLE_S + HOLD_S + 0.5, fault_dir=None,
                             effects=effects, noise=noise)
    except Exception as exc:  # a controller that does not apply to this axis's model
        return [{**base, "command": "connect", "max_um": None, "peak_to_peak_um": None,
                 "status": f"not applicable: {str(exc).splitlines()[0]}"}]
    with m:
        m.axes[name].enable()
        for what in COMMANDS:
            try:
                command(m, name, what)
                hmax, pp = hold_figures(m, name)
                rows.append({**base, "command": what, "max_um": round(hmax, 3), "peak_to_peak_um": round(pp, 3),
                             "status": "ok"})
            except Exception as exc:
                rows.append({**base, "command": what, "max_um": None, "peak_to_peak_um": None,
                             "status": f"{type(exc).__name__}: {str(exc).splitlines()[0]}"})
                break
    return rows


def move_cost(name: str, planned: bool) -> dict:
    """mbc's cost per cycle of a 5 mm move_by on SimAxis (no bus: the law alone), with the move's preview
    installed (planned) or without (the extrapolation fallback): mean and median us per step over the
    move's cycles, and how many of them ran on the table."""
    import time

    import drivectl
    from drivectl.machine.config import load_config

    cfg = load_config()
    ac = cfg.axis(name)
    cfg = replace(cfg, axes={name: replace(ac, controller="mbc", controller_settings={})})
    with drivectl.connect(cfg, axes=[name], sim=True, clock="lockstep", fault_dir=None) as m:
        a = m.axes[name]
        a.enable()
        m.advance(0.1)
        if not planned:
            a._plan = lambda *args: None  # the session as it was: no plan for a move
        c = a._rt.ch.controller
        inner = c.step
        costs, table = [], []

        def timed(reference, feedback):
            tab, k = c._table, c._k
            table.append(tab is not None and k < len(tab[0]) and abs(reference.position - tab[0][k]) <= 1e-12)
            t0 = time.perf_counter()
            u = inner(reference, feedback)
            costs.append(time.perf_counter() - t0)
            return u

        c.step = timed
        h = a.move_by(0.005)
        m.run_until(lambda: a._rt.traj.arrived, 5)
        moving = len(costs)
        h.wait(5)
    us = np.asarray(costs[:moving]) * 1e6
    return {"axis": name, "planned": planned, "cycles": moving, "table_rows": int(sum(table[:moving])),
            "mean_us": round(float(us.mean()), 1), "median_us": round(float(np.median(us)), 1)}


def worst(rows: list[dict], case: str, key: str) -> float | None:
    sel = [r for r in rows if r["default"] and r["case"] == case]
    if not sel:
        return None
    if any(r[key] is None for r in sel):
        return None  # a run that did not complete: no figure (its row says why)
    return max(r[key] for r in sel)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print exactly one JSON object")
    ap.add_argument("--defaults", action="store_true", help="only each axis's default controller")
    ap.add_argument("--axes", default="x,y,z")
    ap.add_argument("--cycle-s", type=float, default=None,
                    help="the servo cycle (default: the embedded machine's, 1 ms); a controller tuned at one "
                    "cycle may not hold at another")
    ap.add_argument("--controllers", default=",".join(CONTROLLERS))
    ap.add_argument("--move-cost", action="store_true", help="only mbc's per-cycle cost of a move, with and "
                    "without the move's preview (issue 26 point 4)")
    args = ap.parse_args(argv)
    if args.move_cost:
        for name in ("x", "z"):
            for planned in (False, True):
                r = move_cost(name, planned)
                print(f"{name} mbc move_by 5 mm {'with its preview   ' if planned else 'extrapolated (old)'}: "
                      f"{r['cycles']} cycles, {r['table_rows']} on the table, step {r['mean_us']} us mean, "
                      f"{r['median_us']} us median", flush=True)
        return 0
    from drivectl.machine.config import load_config

    cfg = load_config()
    if args.cycle_s is not None:
        if not args.cycle_s > 0:
            ap.error(f"--cycle-s: must be > 0 s, got {args.cycle_s!r}")
        cfg = replace(cfg, cycle_s=args.cycle_s)
    rows: list[dict] = []
    for name in args.axes.split(","):
        ac = cfg.axis(name)
        names = [ac.controller] if args.defaults else [ac.controller] + [
            c for c in args.controllers.split(",") if c != ac.controller]
        for controller in names:
            for case in ("exact", "stribeck", "noise") if name in ("x", "y") else ("exact",):
                new = session_rows(cfg, name, controller, case, controller == ac.controller)
                rows += new
                if not args.json:
                    for r in new:
                        mx = "-" if r["max_um"] is None else f"{r['max_um']:8.3f}"
                        pp = "-" if r["peak_to_peak_um"] is None else f"{r['peak_to_peak_um']:8.3f}"
                        print(f"{name}  {controller:10s}{'*' if r['default'] else ' '} {case:9s} {r['command']:14s} "
                              f"max {mx} um  p-p {pp} um  {r['status']}", flush=True)
    out = {"worst_hold_um": worst(rows, "exact", "max_um"),
           "worst_peak_to_peak_um": worst(rows, "exact", "peak_to_peak_um"),
           "worst_stribeck_um": worst(rows, "stribeck", "max_um"),
           "worst_stribeck_peak_to_peak_um": worst(rows, "stribeck", "peak_to_peak_um"),
           "worst_noise_um": worst(rows, "noise", "max_um"),
           "worst_noise_peak_to_peak_um": worst(rows, "noise", "peak_to_peak_um"),
           "rows": rows}
    if args.json:
        print(json.dumps(out))
    else:
        print(f"defaults (*): worst hold {out['worst_hold_um']} um, peak-to-peak {out['worst_peak_to_peak_um']} um"
              f"; x, y stribeck {out['worst_stribeck_um']} um, p-p {out['worst_stribeck_peak_to_peak_um']} um; "
              f"noise {out['worst_noise_um']} um, p-p {out['worst_noise_peak_to_peak_um']} um (targets 0.5 um, "
              "0.5 um p-p in every case)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

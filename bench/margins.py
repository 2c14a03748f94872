"""Stability margins measured on the embedded machine's emulated drives against python-control.

`drivectl bode --loop open`'s measurement (tools/commissioning/margins.py) on axes x (rigid-x) and z
(two-mass), each under its default controller (mbc) and under gains `tune --target` found on the model:
x under pid for gm=8dB,pm=45deg,ms=2; z under mbc for gm=3dB,pm=20deg,ms=4 (what its observer-based loop
can meet on every corner: at gm=8dB `tune` refuses, binding gm). Each measured gain margin, phase margin
and Ms is compared with python-control's ``stability_margins`` on the discrete loop (the law's linear form
at 1 kHz, the one-cycle transport delay, the zero-order hold, the plant from its parameters), its
crossovers restricted to the excited band and chosen as python-control chooses; :func:`reference_margins`
is also what tests/test_margins.py checks against.

    python bench/margins.py [--json] [--seconds S]

``--json`` prints exactly {"cases", "worst_gm_err_db", "worst_pm_err_deg", "worst_ms_rel_err", "seconds"}:
cases measured, the largest |measured - reference| of each margin (Ms relative), wall seconds of the
whole bench (the tune searches included).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from typing import Any

import numpy as np

#: (axis, controller, targets of `tune --target`, None: the axis's default gains)
CASES: list[tuple[str, str, str | None]] = [("x", "mbc", None), ("z", "mbc", None),
                                             ("x", "pid", "gm=8dB,pm=45deg,ms=2"), ("z", "mbc", "gm=3dB,pm=20deg,ms=4")]


def plant_ss(spec: Any, direction: float) -> Any:
    """The plant's linear part from its parameters (effort -> table position and velocity), continuous, as
    python-control's state space; on a rigid axis the viscous coefficient of the direction it slides in."""
    import control as ct

    p = spec.params
    if spec.model == "rigid":
        m = p["mass"]
        c = p["c_pos"] if direction > 0 else p["c_neg"] if direction < 0 else 0.5 * (p["c_pos"] + p["c_neg"])
        a, b = np.array([[0.0, 1.0], [0.0, -c / m]]), np.array([[0.0], [1.0 / m]])
        out = np.eye(2)
    else:
        m1, m2, k, n, b1, b2 = (p[x] for x in ("m1", "m2", "k", "n", "b1", "b2"))
        a = np.array([[0, 1, 0, 0], [-k / m1, -(n + b1) / m1, k / m1, n / m1], [0, 0, 0, 1],
                      [k / m2, n / m2, -k / m2, -(n + b2) / m2]], dtype=float)
        b = np.array([[0.0], [1.0 / m1], [0.0], [0.0]])
        out = np.array([[0.0, 0, 1, 0], [0, 0, 0, 1]])
    return ct.ss(a, b, out, np.zeros((2, 1)))


def reference_margins(law: Any, spec: Any, dt: float, direction: float, band: tuple[float, float]
                      ) -> dict[str, float | None]:
    """python-control's margins of L = -K(z) z^-1 P_zoh(z), in the band. Evaluated as frequency data on a
    dense grid: the polynomial method of python-control 0.10 misplaces the pid-dob loop's phase crossovers
    (poles near z = 1 in a 9th-order polynomial: -3.5 dB at 6.6 Hz where the loop has |L| = 26 dB)."""
    import control as ct

    plant = ct.c2d(plant_ss(spec, direction), dt, "zoh")
    delay = ct.ss([[0.0]], [[1.0]], [[1.0]], [[0.0]], dt)  # the one-cycle transport delay
    form = law.linear_form()
    k = ct.ss(form.A, form.B, form.C.reshape(1, -1), form.D.reshape(1, 2), dt)
    loop = -(k * plant * delay)
    w = 2 * math.pi * np.logspace(math.log10(0.5), math.log10(0.4999 / dt), 8000)
    gm, pm, sm, wpc, wgc, _ = ct.stability_margins(ct.frd(loop, w), returnall=True)
    fpc, fgc = wpc / (2 * math.pi), wgc / (2 * math.pi)
    g = 20 * np.log10(gm[(fpc >= band[0]) & (fpc <= band[1])])
    p = pm[(fgc >= band[0]) & (fgc <= band[1])]
    return {"gm_db": float(g[np.argmin(np.abs(g))]) if len(g) else None,
            "pm_deg": float(p[np.argmin(np.abs(p))]) if len(p) else None, "ms": float(1 / np.min(sm))}


def compare(res: Any, law: Any, spec: Any, dt: float) -> dict[str, float | None]:
    """Measured minus reference for one open-loop result (None where either is not measurable)."""
    m = res.margins
    ref = reference_margins(law, spec, dt, math.copysign(1.0, res.bias_velocity) if res.bias_velocity else 0.0,
                            (float(res.freqs[0]), float(res.freqs[-1])))

    def diff(a: float | None, b: float | None) -> float | None:
        return None if a is None or b is None else a - b

    return {"gm_err_db": diff(m.gm_db.value, ref["gm_db"]), "pm_err_deg": diff(m.pm_deg.value, ref["pm_deg"]),
            "ms_rel_err": None if m.ms.value is None else m.ms.value / ref["ms"] - 1,
            **{f"ref_{k}": v for k, v in ref.items()}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print exactly one JSON object")
    ap.add_argument("--seconds", type=float, default=10.0, help="excitation per case, s (default 10)")
    args = ap.parse_args()

    from drivectl.controllers.registry import make_controller
    from drivectl.machine.config import load_config
    from drivectl.plant_emulator.models import load_plant
    from drivectl.tools.commissioning.margins import measure_open_loop
    from drivectl.tools.commissioning.tune_margins import parse_targets, tune_to_targets

    t0 = time.perf_counter()
    cfg = load_config(None)
    rows = []
    for axis, name, targets in CASES:
        ac = cfg.axis(axis)
        spec = load_plant(ac.plant)
        settings = dict(ac.controller_settings) if name == ac.controller else {}
        if targets:
            tuned = tune_to_targets(cfg, axis, parse_targets(targets), controller=name, candidates=32, verify=False)
            settings = tuned.settings
        law = make_controller(name, cfg.cycle_s, settings, plant=spec, axis=axis)
        res = measure_open_loop(cfg, axis, controller=law, seconds=args.seconds)
        if not res.ok:
            raise SystemExit(f"bench/margins.py: {axis} {name}: the run stopped: {res.detail}")
        law.reset()
        rows.append((axis, name, targets, res, compare(res, law, spec, cfg.cycle_s)))
    wall = time.perf_counter() - t0

    def worst(key: str) -> float | None:
        vals = [abs(r[4][key]) for r in rows if r[4][key] is not None]
        return max(vals) if vals else None

    out = {"cases": len(rows), "worst_gm_err_db": worst("gm_err_db"), "worst_pm_err_deg": worst("pm_err_deg"),
           "worst_ms_rel_err": worst("ms_rel_err"), "seconds": wall}
    if args.json:
        print(json.dumps(out))
        return
    head = (f"{'axis':<5} {'controller':<36} {'gm dB':>8} {'ref':>8} {'pm deg':>8} {'ref':>8} {'Ms':>7} {'ref':>7} "
            f"{'bw Hz':>7} {'coh min':>8}")
    print(head)
    print("-" * len(head))
    for axis, name, targets, res, c in rows:
        m = res.margins
        label = f"{name} ({'tuned ' + targets if targets else 'default'})"

        def f(v: float | None, fmt: str) -> str:
            return "-" if v is None else format(v, fmt)

        print(f"{axis:<5} {label:<36} {f(m.gm_db.value, '.2f'):>8} {f(c['ref_gm_db'], '.2f'):>8} "
              f"{f(m.pm_deg.value, '.2f'):>8} {f(c['ref_pm_deg'], '.2f'):>8} {f(m.ms.value, '.3f'):>7} "
              f"{f(c['ref_ms'], '.3f'):>7} {f(m.bandwidth_hz.value, '.1f'):>7} {f(m.coherence_min, '.3f'):>8}")
    print(f"worst |error|: gm {out['worst_gm_err_db']:.3f} dB (<= 1), pm {out['worst_pm_err_deg']:.3f} deg (<= 3), "
          f"Ms {100 * out['worst_ms_rel_err']:.2f} % (<= 5 %); {wall:.1f} s")


if __name__ == "__main__":
    main()

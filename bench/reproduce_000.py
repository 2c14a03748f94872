"""Reproduce paper 000's comparison: TDE + SMC, TDE + VPRL, TDE + PID-NFTSM on its seed-000 run.

The scenario, as the paper simulates it (section 4.1):

* plant ``two-mass`` (eq 1, Table 1; effort in V; d1 = d2 = 0.1 sin(pi t) already in the plant file),
  integrated exactly (zero-order hold) at 1 kHz;
* ``SimAxis(plant, transport_delay=False, resolution=None)``: the effort acts in the cycle it is
  computed for and the controller sees the exact sampled table position and velocity (the paper's
  simulation has neither a fieldbus delay nor an encoder);
* reference: jerk-limited 0 -> 65 mm, vmax 0.1 m/s, amax 1 m/s^2, jmax 40 m/s^3. The move itself
  takes 0.775 s; the paper's "total motion time 2.5 s" is read as the move plus holding to 2.5 s;
* controllers at dt = Delta t = 1 ms with the paper's gains (the defaults of their settings).

What the paper does not give, and is chosen here (each default sits in the controller's settings, with
the reason next to it; this script prints them and how much the result moves with them):

* m~ (``m_tilde``, V s^2/m) and a low-pass on the x2'' estimate (``accel_filter_hz``, first order).
  The paper tunes "the remaining parameters ... for each algorithm under the condition of stability"
  (section 4.1), so they are chosen per controller:
  - SMC and VPRL (the baselines): no filter, as the paper shows their control voltage chattering, and
    the same m~ = 0.06 for both so that they differ only in the reaching law; 0.06 is 0.75-0.8 of the
    m~ at which the unfiltered TDE loses the 89.2 Hz mode (0.075-0.08), i.e. ~2-2.5 dB of gain margin.
  - PID-NFTSM: unfiltered it limit-cycles at every m~; a 40 Hz first-order low-pass (2.2x below the
    mode) and m~ = 0.15, the geometric centre of the window that is then bounded (0.1-0.25) and of
    the one that is smooth (0.12-0.2).
* PID-NFTSM's s1' in eq (11): the backward difference of s1 (see controllers/pid_nftsm.py).

    python bench/reproduce_000.py            # tables
    python bench/reproduce_000.py --json     # one JSON object: the three results and their settings

Exit status 1 when the reproduction criteria (order PID-NFTSM < VPRL < SMC, each max error within 25 %
of the paper's) fail.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from drivectl.controllers.base import Controller
from drivectl.controllers.pid_nftsm import TdePidNftsm
from drivectl.controllers.runtime.servo import run
from drivectl.controllers.tde_smc import TdeSmc
from drivectl.controllers.vprl import TdeVprl
from drivectl.plant_emulator.models import load_plant
from drivectl.plant_emulator.sim_axis import SimAxis
from drivectl.profiles.ptp import PointToPoint
from drivectl.tracefile.metrics import tracking_error

DT = 0.001  # s, the paper's Delta t and sampling period
DURATION = 2.5  # s, "total motion time"
HOLD_FROM = 1.5  # s, the settled hold used to tell a smooth loop from a limit cycle
TOLERANCE = 0.25  # reproduction criterion: each max error within 25 % of the paper's

#: key, class, the paper's maximum tracking error (um, section 4.2 / abstract)
CONTROLLERS: tuple[tuple[str, type[Controller], float], ...] = (
    ("smc", TdeSmc, 68.2),
    ("vprl", TdeVprl, 28.4),
    ("pid_nftsm", TdePidNftsm, 13.8),
)


@dataclass
class Outcome:
    """One run of the seed-000 scenario."""

    max_um: float
    rms_um: float
    completed: bool  # False: the run left the 5 mm following-error window (diverged)
    du_hold_mv: float  # RMS of the effort's cycle-to-cycle change while holding, mV (chattering)
    du_mv: float  # the same over the whole run


def seed000_profile() -> PointToPoint:
    return PointToPoint(0.0, 0.065, 0.1, 1.0, 40.0, hold_until=DURATION)


def run_seed000(cls: type[Controller], profile: PointToPoint | None = None, **settings: Any) -> Outcome:
    """``cls`` with the paper's gains (overridden by ``settings``) on the seed-000 scenario."""
    plant = load_plant("two-mass").build(DT)
    axis = SimAxis(plant, transport_delay=False, resolution=None, enabled=True)  # the paper starts enabled at t = 0
    res = run(axis, cls(DT, **settings), profile or seed000_profile(), duration=DURATION)
    tr = res.trace
    err = tracking_error(tr.ref, tr.pos)
    du = np.diff(tr.effort)
    hold = du[int(HOLD_FROM / DT) :]
    return Outcome(
        max_um=err["max"] * 1e6,
        rms_um=err["rms"] * 1e6,
        completed=res.ok,
        du_hold_mv=float(np.sqrt(np.mean(hold**2))) * 1e3 if res.ok else math.nan,
        du_mv=float(np.sqrt(np.mean(du**2))) * 1e3,
    )


def chosen(cls: type[Controller]) -> dict[str, Any]:
    s = cls.SettingsClass()
    return {"m_tilde": s.m_tilde, "accel_filter_hz": s.accel_filter_hz}


def _cell(o: Outcome) -> str:
    if not o.completed:
        return "diverged"
    return f"{o.max_um:.1f}"


def _filter_text(hz: float) -> str:
    return "off" if hz == 0 else f"{hz:g} Hz"


def main_results(profile: PointToPoint) -> dict[str, tuple[Outcome, dict[str, Any], float]]:
    out = {}
    for key, cls, paper in CONTROLLERS:
        ch = chosen(cls)
        out[key] = (run_seed000(cls, profile), ch, paper)
    return out


def criteria(results: dict[str, tuple[Outcome, dict[str, Any], float]]) -> list[tuple[str, bool]]:
    m = {k: v[0].max_um if v[0].completed else math.inf for k, v in results.items()}
    checks = [("order PID-NFTSM < VPRL < SMC", m["pid_nftsm"] < m["vprl"] < m["smc"])]
    for key, (o, _, paper) in results.items():
        lo, hi = paper * (1 - TOLERANCE), paper * (1 + TOLERANCE)
        checks.append((f"{key}: {lo:.1f} <= max <= {hi:.1f} um", o.completed and lo <= o.max_um <= hi))
    return checks


CHOICES = """\
Choices (unstated in the paper; its section 4.1 tunes "the remaining parameters" per algorithm for
stability), each made in the controller's settings, where the reason is written down:
  smc, vprl  m~ 0.06, no filter. The two baselines share one TDE, so they differ only in their
             reaching law. Unfiltered, the TDE loses the 89.2 Hz mode at m~ 0.075-0.08 (tables
             below): 0.06 keeps ~2-2.5 dB. Unfiltered because the paper shows their voltage chattering.
  pid-nftsm  first-order 40 Hz low-pass on the x2'' estimate (unfiltered it limit-cycles at any m~);
             m~ 0.15, the geometric centre of the m~ window bounded with it (0.1-0.25; < 100 um) and
             of the one smooth with it (0.12-0.2; hold-phase effort change < 10 mV per cycle).
             s1' of eq (11) = backward difference of s1 (controllers/pid_nftsm.py says why).
"""

M_POINTS = {
    "smc": (0.045, 0.05, 0.055, 0.06, 0.065, 0.07, 0.075, 0.08),
    "vprl": (0.045, 0.05, 0.055, 0.06, 0.065, 0.07, 0.075, 0.08),
    "pid_nftsm": (0.075, 0.1, 0.125, 0.15, 0.175, 0.2, 0.225, 0.25, 0.275),
}
F_POINTS = {
    "smc": (0.0, 30.0, 40.0, 60.0, 100.0),
    "vprl": (0.0, 30.0, 40.0, 60.0, 100.0),
    "pid_nftsm": (0.0, 30.0, 35.0, 40.0, 50.0, 60.0, 80.0),
}


def _neighbours(points: tuple[float, ...], value: float) -> list[int]:
    """Indices of the points either side of ``value`` in ``points`` (which contains it)."""
    i = points.index(value)
    return [j for j in (i - 1, i + 1) if 0 <= j < len(points)]


def _spread(outcomes: list[Outcome]) -> str:
    if any(not o.completed for o in outcomes):
        return "diverges"
    vals = [o.max_um for o in outcomes]
    if len(vals) == 1:
        return f"{vals[0]:.1f} um"
    return f"{min(vals):.1f}..{max(vals):.1f} um"


def _sweep_rows(labels: list[str], outcomes: list[Outcome]) -> None:
    def cell(o: Outcome, attr: str) -> str:
        return "div." if not o.completed else f"{getattr(o, attr):.1f}"

    print("    " + f"{'':<5}" + "".join(f"{label:>8}" for label in labels))
    print("    " + f"{'max':<5}" + "".join(f"{cell(o, 'max_um'):>8}" for o in outcomes))
    print("    " + f"{'hold':<5}" + "".join(f"{cell(o, 'du_hold_mv'):>8}" for o in outcomes))


def print_tables(profile: PointToPoint) -> bool:
    t0 = time.perf_counter()
    results = main_results(profile)
    print("Paper 000 reproduction: two-mass (Table 1, d1 = d2 = 0.1 sin(pi t)), no transport delay, exact")
    print(
        f"sensor, 1 kHz; 0 -> 65 mm, 0.1 m/s, 1 m/s^2, 40 m/s^3 (move {profile.move_time:.3f} s), held to "
        f"{DURATION} s"
    )
    print()
    head = (
        f"{'controller':<10} {'max um':>8} {'RMS um':>7} {'paper um':>8} {'ratio':>6} "
        f"{'m~ V s^2/m':>10} {'x2 filter':>10} {'du RMS mV':>9}"
    )
    print(head)
    print("-" * len(head))
    for key, (o, ch, paper) in results.items():
        print(
            f"{key:<10} {_cell(o):>8} {o.rms_um:>7.2f} {paper:>8.1f} {o.max_um / paper:>6.2f} "
            f"{ch['m_tilde']:>10.3g} {_filter_text(ch['accel_filter_hz']):>10} {o.du_mv:>9.1f}"
        )
    print(
        "x2 filter: first-order low-pass on the x2'' estimate of eq (21). du RMS: RMS of the effort's change"
    )
    print("per cycle over the run, the chattering of the paper's Figs 6-8.")
    print()
    ok = True
    for text, passed in criteria(results):
        ok &= passed
        print(f"  [{'ok' if passed else 'FAIL'}] {text}")
    print()
    print(CHOICES)

    print("Sensitivity. max: max error, um ('div.': left the 5 mm window); hold: RMS effort change per cycle")
    print("while holding (t >= 1.5 s), mV: ~1-5 smooth, tens = chattering or a limit cycle. * = chosen.")
    by_m: dict[str, list[Outcome]] = {}
    by_f: dict[str, list[Outcome]] = {}
    for key, cls, _ in CONTROLLERS:
        ch = chosen(cls)
        by_m[key] = [
            run_seed000(cls, profile, m_tilde=m, accel_filter_hz=ch["accel_filter_hz"]) for m in M_POINTS[key]
        ]
        by_f[key] = [
            run_seed000(cls, profile, m_tilde=ch["m_tilde"], accel_filter_hz=f) for f in F_POINTS[key]
        ]
        print(f"  {key}, filter {_filter_text(ch['accel_filter_hz'])}, varying m~ (V s^2/m):")
        _sweep_rows([f"{m:g}{'*' if m == ch['m_tilde'] else ''}" for m in M_POINTS[key]], by_m[key])
        print(f"  {key}, m~ {ch['m_tilde']:g}, varying the filter cut-off (Hz):")
        _sweep_rows([f"{f:g}{'*' if f == ch['accel_filter_hz'] else ''}" for f in F_POINTS[key]], by_f[key])
    print("  (cut-off 0 = no filter)")
    print()
    print("How sensitive each figure is (the neighbouring points above):")
    for key, cls, _ in CONTROLLERS:
        ch = chosen(cls)
        mi = _neighbours(M_POINTS[key], ch["m_tilde"])
        fi = _neighbours(F_POINTS[key], ch["accel_filter_hz"])
        m_lo, m_hi = M_POINTS[key][mi[0]], M_POINTS[key][mi[-1]]
        print(
            f"  {key:<10} {results[key][0].max_um:.1f} um; m~ {m_lo:g}..{m_hi:g}: "
            f"{_spread([by_m[key][i] for i in mi])}; cut-off "
            f"{', '.join(_filter_text(F_POINTS[key][i]) for i in fi)}: {_spread([by_f[key][i] for i in fi])}"
        )
    print("  smc is chattering-dominated and not monotonic in m~: its figure is only good to a factor ~2;")
    print("  pid-nftsm falls roughly as 1/m~ inside its window: 13.8 um is what the window's centre gives.")
    print()
    print("Cross-checks")
    o = run_seed000(TdePidNftsm, profile, s1_derivative="estimate")
    print(f"  pid-nftsm, s1' from the TDE's filtered x2'' estimate instead of the difference: {_cell(o)}")
    cells = [
        f"{key} {_cell(run_seed000(cls, profile, accel_source='velocity'))}" for key, cls, _ in CONTROLLERS
    ]
    print("  x2'' from the first difference of the measured velocity (max um): " + ", ".join(cells))
    for m, f in ((0.06, 0.0), (0.15, 40.0)):
        cells = [
            f"{key} {_cell(run_seed000(cls, profile, m_tilde=m, accel_filter_hz=f))}"
            for key, cls, _ in CONTROLLERS
        ]
        print(f"  all three at m~ {m:g}, filter {_filter_text(f)} (max um): " + ", ".join(cells))
    print(
        "  -> neither shared setting gives the paper's order: unfiltered at m~ 0.06 PID-NFTSM diverges (its"
    )
    print("     ~100 rad/s PID-surface loop needs a faster TDE); at m~ 0.15 / 40 Hz SMC beats VPRL.")
    print(f"({time.perf_counter() - t0:.1f} s)")
    return ok


def json_results(profile: PointToPoint) -> tuple[dict[str, Any], bool]:
    results = main_results(profile)
    out = {}
    # exactly the keys; the choices of m~ and filter are printed with the text table
    for key, (o, _ch, _) in results.items():
        out[key] = {
            "max_um": round(o.max_um, 3) if o.completed else None,
            "rms_um": round(o.rms_um, 3) if o.completed else None,
        }
    return out, all(passed for _, passed in criteria(results))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object with the three results")
    args = ap.parse_args(argv)
    profile = seed000_profile()
    if args.json:
        out, ok = json_results(profile)
        print(json.dumps(out))
    else:
        ok = print_tables(profile)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

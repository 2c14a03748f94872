"""What `drivectl explain` tells: the report, the evidence by location, the plot and the files it writes."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from drivectl.plant_emulator.models import PlantSpec
from drivectl.tools.explain.data import Prepared, simulate_windows

if TYPE_CHECKING:  # the result type lives with explain(); only annotations need it here
    from drivectl.tools.explain.core import ExplainResult

#: the remainder is called noise up to this many times the floor; above, the model still misses something
MISSING_FACTOR = 2.0

SIGNATURES = {
    "none": "the nominal plant already explains the data: no effect shrinks the gap significantly above its floor",
    "stribeck": "extra friction at low speed: the axis breaks away later and decelerates harder near standstill",
    "backlash": "lost motion when the force reverses: the table stands while the screw crosses the gap",
    "periodic": "a force that repeats with position (lead error, runout): the residual is a sine of q",
    "mass": "the residual follows the acceleration: the moving mass differs from the model's",
    "viscous": "the residual grows with speed: the viscous friction differs from the model's",
    "coulomb": "a constant friction per direction of motion that differs from the model's",
    "delay": "the measured motion lags the effort: the drive applies it later than the transport delay",
    "offset": "a constant force: the residual has one sign in both directions of motion",
    "spring": "a force proportional to position: the residual grows with q",
    "resonance": "the table follows the force through a lightly damped mode: ringing at one frequency",
    "saturation": "the acceleration stops following the command when |effort| is large: the drive clips it",
}

UNITS = {"excess_force": "effort", "velocity": "m/s", "width": "m", "amplitude": "effort", "period": "m",
         "mass": "kg", "scale": "", "scale_neg": "", "delay": "s", "force": "effort", "stiffness": "effort/m",
         "frequency": "Hz", "damping": "", "limit": "effort", "phase": "rad", "force_pos": "effort",
         "force_neg": "effort"}


def locate(prep: Prepared, nominal: PlantSpec) -> dict[str, Any]:
    """Where the nominal model disagrees: the gap by speed, by direction, near reversals, by |effort|."""
    win = prep.windows
    err = simulate_windows(prep, nominal) - win.measured
    rows = win.start[:, None] + np.arange(1, win.length + 1)[None, :]
    v = prep.vel[rows]
    u = np.abs(prep.applied[rows])
    vmax = float(np.max(np.abs(prep.vel))) or 1.0
    out: dict[str, Any] = {}

    def rms(mask: np.ndarray) -> float:
        return float(np.sqrt(np.mean(err[mask] ** 2))) if mask.any() else math.nan

    out["gap_by_speed_m"] = {
        "standstill": rms(np.abs(v) < 1e-4),
        "slow (<10% vmax)": rms((np.abs(v) >= 1e-4) & (np.abs(v) < 0.1 * vmax)),
        "fast (>=10% vmax)": rms(np.abs(v) >= 0.1 * vmax),
    }
    out["gap_by_direction_m"] = {"+": rms(v > 1e-4), "-": rms(v < -1e-4)}
    sgn = np.sign(prep.vel)
    flips = np.flatnonzero((sgn[1:] * sgn[:-1] < 0) | ((sgn[1:] != 0) & (sgn[:-1] == 0))) + 1
    near = np.zeros(len(prep.vel), dtype=bool)
    span = int(round(0.05 / prep.dt))
    for k in flips:
        near[max(0, k - span):k + span] = True
    rev = near[rows]
    out["gap_near_starts_and_reversals_m"] = rms(rev)
    out["gap_elsewhere_m"] = rms(~rev)
    out["gap_at_high_effort_m"] = rms(u > 0.8 * float(np.max(u)))
    return out


def _fmt_params(params: dict[str, float], unit: str, indent: str = "  ") -> list[str]:
    return [f"{indent}{k} = {val:.6g} {UNITS.get(k, '').replace('effort', unit)}".rstrip() for k, val in params.items()]


def format_report(res: ExplainResult, prep: Prepared) -> str:
    ev = res.evidence
    unit = prep.effort_unit
    um = 1e6
    lines = [f"explain {prep.source} against plant {prep.spec.name}", ""]
    if not res.effects:
        lines.append("effect: none")
        lines.append(f"  {SIGNATURES['none']}")
    for i, e in enumerate(res.effects):
        lines.append(f"effect {i + 1}: {e['effect']}   (gap after it: {e['gap_after'] * um:.3f} um)")
        lines.append(f"  {SIGNATURES[e['effect']]}")
        lines += _fmt_params({**e["params"], **e.get("extra", {})}, unit)
    shrink = 1 - res.gap_after / res.gap_before if res.gap_before > 0 else 0.0
    lines.append("")
    lines.append(f"gap before: {res.gap_before * um:.3f} um   after: {res.gap_after * um:.3f} um   "
                 f"(shrink {100 * shrink:.1f} %)")
    lines.append(f"gap metric: {res.gap_metric}")
    dropped = ev.get("windows_dropped") or {}
    drop = "; ".join(f"{n} left out ({why})" for why, n in dropped.items())
    lines.append(f"  {ev['windows']} windows of {ev['window_s'] * 1e3:.0f} ms{'; ' + drop if drop else ''}; "
                 f"start velocity from {ev['velocity_from']}; transport delay {ev['transport_delay_cycles']} cycle(s)")
    lines.append(f"  floor (the data's own noise, estimated from the trace): {ev['floor_m'] * um:.3f} um")
    lines.append("")
    lines.append("where the nominal model disagrees (RMS position error of the windows, um):")
    for k, val in ev["gap_by_speed_m"].items():
        lines.append(f"  speed {k:<18} {val * um:9.3f}")
    for k, val in ev["gap_by_direction_m"].items():
        lines.append(f"  moving {k:<17} {val * um:9.3f}")
    lines.append(f"  near starts/reversals    {ev['gap_near_starts_and_reversals_m'] * um:9.3f}")
    lines.append(f"  elsewhere                {ev['gap_elsewhere_m'] * um:9.3f}")
    lines.append(f"  at |effort| > 80 % peak  {ev['gap_at_high_effort_m'] * um:9.3f}")
    for r, rnd in enumerate(ev["rounds"]):
        lines.append("")
        base = "the nominal plant" if r == 0 else "the model with " + ", ".join(rnd["model"])
        lines.append(f"round {r + 1}: candidates on top of {base} (gap {rnd['gap_m'] * um:.3f} um); the best is "
                     f"named when its robust gain (the two best windows counted as the third), less "
                     f"{ev['param_charge']:g} floor^2 "
                     f"per parameter, is at least {ev['margin']:g} floor^2:")
        lines.append(f"  {'candidate':<11} {'gap um':>9} {'shrink':>7} {'robust gain':>12} {'better':>6} "
                     f"{'worse':>5}  params")
        for c in rnd["candidates"]:
            ps = ", ".join(f"{k}={v:.4g}" for k, v in c["params"].items())
            lines.append(f"  {c['key']:<11} {c['gap_m'] * um:9.3f} {100 * c['shrink']:6.1f}% "
                         f"{c['robust_gain_floor2']:9.2f} fl2 {c['improved']:>6} {c['worse']:>5}  ({ps})")
        lines.append(f"  -> {rnd['decision']}")
    for name, why in ev["refused"].items():
        lines.append(f"  {name}: not tried ({why})")
    lines.append("")
    ratio = res.gap_after / ev["floor_m"] if ev["floor_m"] > 0 else math.inf
    if ratio > MISSING_FACTOR:
        lines.append(f"{res.gap_after * um:.1f} um unexplained, {ratio:.1f} times the floor: "
                     "the model still misses something")
    else:
        lines.append(f"{res.gap_after * um:.1f} um unexplained, {ratio:.1f} times the floor: what remains is the "
                     "data's own noise")
    return "\n".join(lines) + "\n"


def stitched(prep: Prepared, sim: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows and values of a windowed simulation laid end to end, for plotting."""
    win = prep.windows
    rows = (win.start[:, None] + np.arange(1, win.length + 1)[None, :]).ravel()
    return rows, sim.ravel()


def write_outputs(res: ExplainResult, prep: Prepared, out: Path, stem: str) -> list[Path]:
    from drivectl.tracefile.format import atomic_write_text

    out.mkdir(parents=True, exist_ok=True)
    files = []
    toml_path = out / f"{stem}.plant.toml"
    named = ", ".join(e["effect"] for e in res.effects) or "none"
    comment = (f"augmented by drivectl explain from {prep.source}\n"
               f"effects {named}; gap {res.gap_before * 1e6:.3f} um -> {res.gap_after * 1e6:.3f} um")
    atomic_write_text(toml_path, res.augmented.to_toml(comment=comment))
    files.append(toml_path)
    rep = out / f"{stem}.report.txt"
    atomic_write_text(rep, res.report)
    files.append(rep)
    files.append(plot_explain(res, prep, out / f"{stem}.png"))
    return files


#: a fixed place: "best" counts every plotted point under each candidate place, ~0.5 s of a 25 s record's plot
LEGEND_LOC = "upper right"


def plot_explain(res: ExplainResult, prep: Prepared, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    nominal = prep.spec
    sim0 = simulate_windows(prep, nominal)
    rows, s0 = stitched(prep, sim0)
    fig, axes = plt.subplots(3, 1, figsize=(10, 10))
    ax = axes[0]
    t = prep.t
    ax.plot(t, prep.pos * 1e3, "k-", lw=1.0, label="measured")
    ax.plot(t[rows], s0 * 1e3, ".", ms=1.0, color="tab:red", label="nominal (windowed)")
    e0 = (s0 - prep.pos[rows]) * 1e6
    named = " + ".join(e["effect"] for e in res.effects)
    if res.effects:
        _, s1 = stitched(prep, simulate_windows(prep, res.augmented))
        ax.plot(t[rows], s1 * 1e3, ".", ms=1.0, color="tab:green", label=f"with {named}")
        e1 = (s1 - prep.pos[rows]) * 1e6
    else:
        e1 = None
    ax.set_xlabel("time (s)")
    ax.set_ylabel("position (mm)")
    ax.set_title(f"explain: {named or 'none'}; gap {res.gap_before * 1e6:.2f} -> {res.gap_after * 1e6:.2f} um")
    ax.legend(loc=LEGEND_LOC, markerscale=8)
    for ax, x, label in ((axes[1], prep.vel[rows] * 1e3, "velocity (mm/s)"),
                         (axes[2], prep.pos[rows] * 1e3, "position (mm)")):
        ax.plot(x, e0, ".", ms=1.0, color="tab:red", label="nominal")
        if e1 is not None:
            ax.plot(x, e1, ".", ms=1.0, color="tab:green", label=f"with {named}")
        ax.set_xlabel(label)
        ax.set_ylabel("sim - measured (um)")
        ax.legend(loc=LEGEND_LOC, markerscale=8)
    # fixed margins: tight_layout measured every label and legend first (0.3 s of a 10 s trace's plot)
    fig.subplots_adjust(left=0.08, right=0.98, bottom=0.05, top=0.96, hspace=0.28)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path

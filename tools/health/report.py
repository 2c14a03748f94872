"""``drivectl health report``: per axis and effect, the fitted parameter over the runs, the run at which
it began to change (tools/health/trend.py), its slope and when it crosses its limit; alarms; a fleet
table ranking every axis by its worst alarm; a figure with one panel per effect (docs/health.md).

An alarm is a change found in a parameter whose effect explains what changed: on the runs from the
onset on, that effect's fit closes the gap between the model and the run (the fit's ``gap``) by a
tenth at least (``EXPLAINS``) and about as well as the best of the changed effects does (within
``NAMING_FACTOR``). A wear moves the single fits
of several effects (viscous friction grown also raises the Coulomb fit, which absorbs part of it);
those changes are shown as following the named effect, not as alarms of their own.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np

from drivectl.errors import InputError
from drivectl.tools.health.deps import need
from drivectl.tools.health.trend import Change, find_change, runs_to_limit

#: a crossing further than this many runs away is said as such, without a date (centuries of shifts)
FAR_RUNS = 100_000
#: an effect is named (an alarm) when its gap score is within this factor of the best changed effect's
NAMING_FACTOR = 1.25
#: ... and its fit closes at least a tenth of the model's gap on the runs since the onset: the parameters
#: of an effect that is not there (a period without an amplitude) wander, and explain nothing
EXPLAINS = 0.9


@dataclass
class Trend:
    """One parameter of one effect over an axis's fitted runs."""

    effect: str
    param: str
    runs: list[int]  # run_index of each point
    times: list[datetime]
    values: list[float | None]
    uncertainties: list[float | None]
    gaps: list[float | None]
    change: Change | None = None
    #: the median, over the runs from the onset on, of this effect's gap over the run's model gap
    gap_score: float = math.inf
    limit: float | None = None
    #: runs after the last until the slope reaches the limit (0: past it), None: not towards it / no limit
    runs_to_limit: float | None = None
    cross_utc: datetime | None = None
    alarm: bool = False

    @property
    def key(self) -> str:
        return f"{self.effect}.{self.param}"

    @property
    def onset_run(self) -> int | None:
        return self.runs[self._known()[self.change.onset]] if self.change is not None else None

    def _known(self) -> list[int]:
        return [i for i, v in enumerate(self.values) if v is not None and math.isfinite(v)]


@dataclass
class AxisReport:
    machine: str
    axis: str
    runs: int
    fitted: int
    started: list[datetime]  # every run's start, run_index order
    trends: list[Trend] = field(default_factory=list)

    @property
    def alarms(self) -> list[Trend]:
        """The alarms (effects that explain the change about equally well): the effect with the fewest
        parameters first (of two that explain it alike, the simpler), then the strongest change."""
        size: dict[str, int] = {}
        for t in self.trends:
            size[t.effect] = size.get(t.effect, 0) + 1
        return sorted((t for t in self.trends if t.alarm), key=lambda t: (size[t.effect], *_alarm_order(t)))

    @property
    def following(self) -> list[Trend]:
        """Changes that are not alarms: parameters of effects that followed the named one."""
        return [t for t in self.trends if t.change is not None and not t.alarm]

    def to_json(self) -> dict[str, Any]:
        """The object ``--json`` prints: exactly machine, axis, runs, alarms, trends (docs/health.md)."""
        return {
            "machine": self.machine,
            "axis": self.axis,
            "runs": self.runs,
            "alarms": [_alarm_json(t) for t in self.alarms],
            "trends": {t.key: [[r, v, u] for r, v, u in zip(t.runs, t.values, t.uncertainties, strict=True)]
                       for t in self.trends},
        }


def _alarm_order(t: Trend) -> tuple[float, float]:
    c = t.change
    return (-(c.statistic / c.threshold) if c is not None else 0.0, t.gap_score)


def _alarm_json(t: Trend) -> dict[str, Any]:
    c = t.change
    assert c is not None
    onset = t.onset_run
    when = t.times[t.runs.index(onset)]
    return {"effect": t.effect, "param": t.param, "onset_run": onset, "onset_utc": _utc(when),
            "first_value": c.first_value, "last_value": c.last_value,
            "slope_per_100_runs": c.slope_per_run * 100.0}


def _utc(t: datetime) -> str:
    return t.strftime("%Y-%m-%dT%H:%M:%SZ")


# ------------------------------------------------------------------------------------------------
# Reading the store
# ------------------------------------------------------------------------------------------------
def open_catalog(root: Path) -> Any:
    """The store's catalog, read-only (an ingest may be writing it)."""
    from drivectl.tools.health.store import CATALOG

    duckdb = need("duckdb")
    path = Path(root).expanduser() / CATALOG
    if not path.is_file():
        raise InputError(f"--store {root}: no health store there (no {CATALOG}; drivectl health ingest makes one)")
    try:
        return duckdb.connect(str(path), read_only=True)
    except duckdb.Error as exc:
        raise InputError(f"--store {root}: {CATALOG}: {str(exc).splitlines()[0]}") from None


def axes_in(con: Any, machine: str | None = None, axis: str | None = None) -> list[tuple[str, str]]:
    """(machine, axis) of every axis in the store, filtered."""
    q = "SELECT DISTINCT machine, axis FROM runs WHERE (? IS NULL OR machine = ?) AND (? IS NULL OR axis = ?) " \
        "ORDER BY machine, axis"
    return [tuple(r) for r in con.execute(q, [machine, machine, axis, axis]).fetchall()]


def axis_report(con: Any, machine: str, axis: str, limits: dict[str, float] | None = None) -> AxisReport:
    """The report of one axis from the catalog ``con``; ``limits``: "effect.param" -> SI value."""
    runs = con.execute("SELECT run_index, sha256, started_utc FROM runs_ordered WHERE machine = ? AND axis = ? "
                       "ORDER BY run_index", [machine, axis]).fetchall()
    rows = con.execute(
        "SELECT f.effect, f.parameter, r.run_index, r.started_utc, f.value, f.uncertainty, f.gap "
        "FROM fits f JOIN runs_ordered r ON f.run = r.sha256 WHERE r.machine = ? AND r.axis = ? "
        "ORDER BY f.effect, f.parameter, r.run_index", [machine, axis]).fetchall()
    fitted = {r[2] for r in rows}
    series: dict[tuple[str, str], Trend] = {}
    for effect, param, run, when, value, unc, gap in rows:
        t = series.setdefault((effect, param), Trend(effect, param, [], [], [], [], []))
        t.runs.append(int(run))
        t.times.append(when)
        t.values.append(_finite(value))
        t.uncertainties.append(_finite(unc))
        t.gaps.append(_finite(gap))
    rep = AxisReport(machine, axis, len(runs), len(fitted), [r[2] for r in runs], list(series.values()))
    _analyse(rep, limits or {})
    return rep


def _finite(v: Any) -> float | None:
    return float(v) if v is not None and math.isfinite(v) else None


# ------------------------------------------------------------------------------------------------
# The analysis
# ------------------------------------------------------------------------------------------------
def _model_gaps(trends: list[Trend]) -> dict[int, float]:
    """Per run, the gap of the model alone, as near as the fits say: the median of the effects' gaps
    (most effects, fitted where they are not, land on the model)."""
    per_run: dict[int, list[float]] = {}
    seen: set[tuple[str, int]] = set()
    for t in trends:
        for r, g in zip(t.runs, t.gaps, strict=True):
            if g is not None and (t.effect, r) not in seen:  # one gap per effect and run
                seen.add((t.effect, r))
                per_run.setdefault(r, []).append(g)
    return {r: float(np.median(g)) for r, g in per_run.items()}


def _analyse(rep: AxisReport, limits: dict[str, float]) -> None:
    ref = _model_gaps(rep.trends)
    interval = _run_interval(rep.started)
    for t in rep.trends:
        known = t._known()
        if not known:
            continue
        x = np.array([t.values[i] for i in known])
        u = np.array([t.uncertainties[i] if t.uncertainties[i] is not None else np.nan for i in known])
        t.change = find_change(x, u)
        t.limit = limits.get(t.key)
        if t.change is None:
            continue
        after = [known[j] for j in range(t.change.onset, len(known))]
        ratios = [t.gaps[i] / ref[t.runs[i]] for i in after
                  if t.gaps[i] is not None and ref.get(t.runs[i], 0.0) > 0.0]
        t.gap_score = float(np.median(ratios)) if ratios else math.inf
        if t.limit is not None:
            t.runs_to_limit = runs_to_limit(t.change.last_value, t.change.slope_per_run, t.limit,
                                            t.change.first_value)
            if t.runs_to_limit is not None and interval is not None and t.runs_to_limit <= FAR_RUNS:
                t.cross_utc = rep.started[-1] + interval * t.runs_to_limit
    changed = [t for t in rep.trends if t.change is not None and math.isfinite(t.gap_score)]
    if changed:
        best = min(t.gap_score for t in changed)
        for t in changed:
            # the effect explains what changed: its fit closes the gap on the runs since the onset (below
            # the model's), about as well as the best changed effect's does
            t.alarm = t.gap_score <= EXPLAINS and t.gap_score <= NAMING_FACTOR * best


def _run_interval(started: list[datetime]) -> timedelta | None:
    """The median time between runs (a shift), for a crossing's date."""
    if len(started) < 2:
        return None
    steps = np.diff(np.array([s.timestamp() for s in started]))
    return timedelta(seconds=float(np.median(steps)))


def worst(rep: AxisReport) -> Trend | None:
    """The axis's worst alarm: past its limit, else the soonest crossing, else the first named."""
    alarms = rep.alarms
    if not alarms:
        return None
    return min(alarms, key=lambda t: (t.runs_to_limit is None, t.runs_to_limit or 0.0, alarms.index(t)))


def fleet(reports: list[AxisReport]) -> list[AxisReport]:
    """Every axis, the worst first: axes with alarms (past a limit, then the soonest crossing, then by
    the change's strength), then the quiet ones."""
    def rank(rep: AxisReport) -> tuple:
        w = worst(rep)
        if w is None:
            return (1, 0.0, 0.0, rep.machine, rep.axis)
        c = w.change
        return (0, w.runs_to_limit if w.runs_to_limit is not None else math.inf,
                -(c.statistic / c.threshold) if c else 0.0, rep.machine, rep.axis)

    return sorted(reports, key=rank)


# ------------------------------------------------------------------------------------------------
# Output
# ------------------------------------------------------------------------------------------------
def _num(v: float | None) -> str:
    return "-" if v is None else f"{v:.4g}"


def _crossing(t: Trend) -> str:
    if t.limit is None:
        return "no limit"
    if t.runs_to_limit is None:
        return f"limit {_num(t.limit)}: not towards it"
    if t.runs_to_limit == 0.0:
        return f"past its limit {_num(t.limit)}"
    if t.runs_to_limit > FAR_RUNS:
        return f"limit {_num(t.limit)}: more than {FAR_RUNS} runs away"
    when = f" ({_utc(t.cross_utc)})" if t.cross_utc is not None else ""
    return f"limit {_num(t.limit)} in {t.runs_to_limit:.0f} runs{when}"


def axis_text(rep: AxisReport) -> str:
    """The report of one axis, for a person."""
    head = f"{rep.machine}/{rep.axis}: {rep.runs} runs"
    if rep.fitted < rep.runs:
        head += f", {rep.runs - rep.fitted} not analysed yet (drivectl health analyze)"
    lines = [head]
    if not rep.trends:
        lines.append("  no fits yet")
        return "\n".join(lines)
    alarms = rep.alarms
    if not alarms:
        lines.append("  no alarm: no parameter changed beyond its run-to-run noise")
    for t in alarms:
        c = t.change
        assert c is not None
        lines.append(f"  ALARM {t.key}: changed at run {t.onset_run} ({_utc(t.times[t.runs.index(t.onset_run)])}), "
                     f"{_num(c.first_value)} -> {_num(c.last_value)}, {c.slope_per_run * 100:+.4g} per 100 runs; "
                     f"{_crossing(t)}")
    follow = rep.following
    if follow:
        lines.append("  also moved (following the alarm's effect): " + ", ".join(
            f"{t.key} from run {t.onset_run}" for t in follow))
    lines.append(f"  {'parameter':24s} {'first':>10s} {'last':>10s} {'noise':>10s}  change")
    for t in rep.trends:
        vals = [v for v in t.values if v is not None]
        if not vals:
            lines.append(f"  {t.key:24s} {'-':>10s} {'-':>10s} {'-':>10s}  unknown (no value)")
            continue
        c = t.change
        what = "none" if c is None else f"{c.shape} at run {t.onset_run} ({c.statistic:.3g} > {c.threshold:.3g})"
        from drivectl.tools.health.trend import noise_sigma

        sigma = c.sigma if c is not None else noise_sigma(np.array(vals))
        lines.append(f"  {t.key:24s} {_num(vals[0]):>10s} {_num(vals[-1]):>10s} {_num(sigma):>10s}  {what}")
    return "\n".join(lines)


def fleet_text(reports: list[AxisReport]) -> str:
    """Every axis in the store ranked by its worst alarm."""
    lines = [f"{'machine':16s} {'axis':6s} {'runs':>5s}  worst alarm"]
    for rep in fleet(reports):
        w = worst(rep)
        if w is None:
            what = "none" if rep.fitted else "none (not analysed yet)"
        else:
            c = w.change
            assert c is not None
            what = (f"{w.key} from run {w.onset_run}: {_num(c.first_value)} -> {_num(c.last_value)}; "
                    f"{_crossing(w)}")
        lines.append(f"{rep.machine:16s} {rep.axis:6s} {rep.runs:5d}  {what}")
    return "\n".join(lines)


def plot(rep: AxisReport, path: str | Path) -> Path:
    """One panel per effect: its parameters against time, the band (the fits' uncertainty where
    known, else the run-to-run noise), the onset marked, the limit dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from drivectl.tools.health.trend import noise_sigma

    effects: dict[str, list[Trend]] = {}
    for t in rep.trends:
        effects.setdefault(t.effect, []).append(t)
    n = max(1, len(effects))
    cols = 3 if n > 4 else 1
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(5.2 * cols, 2.3 * rows), squeeze=False, sharex=True)
    for ax in axes.flat[n:]:
        ax.set_visible(False)
    colors = ("tab:blue", "tab:orange")
    for ax, (effect, trends) in zip(axes.flat, effects.items(), strict=False):
        alarm = any(t.alarm for t in trends)
        for j, t in enumerate(trends[:2]):
            a = ax if j == 0 else ax.twinx()
            known = t._known()
            if not known:
                continue
            x = [t.times[i] for i in known]
            y = np.array([t.values[i] for i in known])
            u = np.array([t.uncertainties[i] if t.uncertainties[i] is not None else np.nan for i in known])
            band = np.where(np.isfinite(u), u, t.change.sigma if t.change else noise_sigma(y))
            a.fill_between(x, y - band, y + band, color=colors[j], alpha=0.2, lw=0)
            a.plot(x, y, ".-", color=colors[j], lw=1, ms=3, label=t.param)
            a.set_ylabel(t.param, color=colors[j], fontsize=8)
            a.tick_params(labelsize=7)
            if t.limit is not None:
                a.axhline(t.limit, color=colors[j], ls="--", lw=0.8)
            if t.change is not None:
                when = t.times[t.runs.index(t.onset_run)]
                a.axvline(when, color="red" if t.alarm else "grey", lw=1.2 if t.alarm else 0.8,
                          ls="-" if t.alarm else ":")
        ax.set_title(f"{effect}" + ("  ALARM" if alarm else ""), fontsize=9, color="red" if alarm else "black")
    for ax in axes[-1]:
        ax.tick_params(axis="x", labelrotation=30, labelsize=7)
    fig.suptitle(f"{rep.machine}/{rep.axis}: {rep.runs} runs (red line: onset of an alarm; dashed: limit)",
                 fontsize=10)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path

"""Every figure of merit of a run, in one place: tracking error, energy, chattering.

All functions take plain arrays (or a Trace through :func:`summarize`), SI units in, SI units out;
the ``*_um`` keys of :func:`summarize` are micrometres for people.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivectl.tracefile.format import Trace


def tracking_error(ref: np.ndarray, pos: np.ndarray) -> dict[str, float]:
    """Max, mean and RMS of |r - q| in m (mean of the absolute error, as paper 004's Table 5)."""
    e = np.abs(np.asarray(ref, dtype=float) - np.asarray(pos, dtype=float))
    if e.size == 0:
        return {"max": float("nan"), "mean": float("nan"), "rms": float("nan")}
    return {"max": float(e.max()), "mean": float(e.mean()), "rms": float(np.sqrt(np.mean(e * e)))}


def velocity_of(trace: Trace) -> np.ndarray:
    """Measured velocity: the drive's column when recorded, else the central difference of pos."""
    if "vel_m_s" in trace.columns:
        return trace.columns["vel_m_s"]
    if len(trace) < 2:
        return np.zeros(len(trace))
    return np.gradient(trace.pos, trace.time)


def mechanical_work(effort: np.ndarray, velocity: np.ndarray, dt: float) -> dict[str, float]:
    """Work of the effort on the axis: ``positive`` = sum max(f v, 0) dt (what a drive that
    cannot regenerate must supply), ``net`` = sum f v dt. J when the effort is in N."""
    p = np.asarray(effort, dtype=float) * np.asarray(velocity, dtype=float)
    return {"positive": float(np.sum(np.maximum(p, 0.0)) * dt), "net": float(np.sum(p) * dt)}


@dataclass(frozen=True)
class ElectricalModel:
    """A stated model of what a servo drive draws for an axial force f at speed v:

    P = max(f v, 0) + R (f / K_f)^2 + P_standby

    motoring power (braking power is burnt in a resistor, not recovered) plus copper loss of the
    current f / K_f, plus standby. Defaults: a 400 W AC servo (0.64 N m/A, 1.5 ohm per phase pair)
    on a 10 mm lead screw, K_f = 0.64 * 2 pi / 0.010 = 402 N/A; standby 0 (paper 004's power meter
    includes ~95 W of standby, see bench/reproduce_004.py).
    """

    force_constant: float = 402.0  # N/A
    resistance: float = 1.5  # ohm
    standby_power: float = 0.0  # W

    def energy(self, effort: np.ndarray, velocity: np.ndarray, dt: float) -> float:
        f = np.asarray(effort, dtype=float)
        p = np.maximum(f * np.asarray(velocity, dtype=float), 0.0)
        p += self.resistance * (f / self.force_constant) ** 2 + self.standby_power
        return float(np.sum(p) * dt)


def chattering_sigma(effort: np.ndarray) -> float:
    """Paper 004 eq (26): standard deviation of the control signal about its mean."""
    f = np.asarray(effort, dtype=float)
    return float(np.sqrt(np.mean((f - f.mean()) ** 2))) if f.size else float("nan")


def effort_roughness(effort: np.ndarray) -> float:
    """RMS of the effort's first difference (per cycle): high-frequency chattering."""
    f = np.asarray(effort, dtype=float)
    return float(np.sqrt(np.mean(np.diff(f) ** 2))) if f.size > 1 else 0.0


def summarize(trace: Trace, electrical: ElectricalModel | None = None) -> dict[str, float]:
    """The summary table of a trace: errors in um, energy in J (effort unit x m), sigma, roughness."""
    err = tracking_error(trace.ref, trace.pos)
    v = velocity_of(trace)
    dt = trace.dt
    work = mechanical_work(trace.effort, v, dt)
    out = {
        "max_um": err["max"] * 1e6,
        "mean_um": err["mean"] * 1e6,
        "rms_um": err["rms"] * 1e6,
        "energy_J": work["positive"],
        "work_net_J": work["net"],
        "sigma": chattering_sigma(trace.effort),
        "du_rms": effort_roughness(trace.effort),
        "duration_s": float(trace.time[-1] - trace.time[0]) if len(trace) else 0.0,
    }
    if trace.effort_unit in ("N", ""):
        out["electrical_J"] = (electrical or ElectricalModel()).energy(trace.effort, v, dt)
    return out


def contour_error(ref_x: np.ndarray, ref_y: np.ndarray, pos_x: np.ndarray, pos_y: np.ndarray,
                  window: int = 50) -> np.ndarray:
    """Distance from each measured (x, y) to the reference path, m (the contour error of a two-axis
    move: what the part sees, unlike the per-axis tracking errors). The path is the reference
    polyline; each sample looks for its nearest segment within +-``window`` samples of its own time,
    so a path that crosses itself is not confused."""
    rx, ry = np.asarray(ref_x, float), np.asarray(ref_y, float)
    px, py = np.asarray(pos_x, float), np.asarray(pos_y, float)
    n = len(rx)
    if n < 2:
        return np.hypot(px - rx, py - ry)
    best = np.full(n, np.inf)
    idx = np.arange(n)
    for off in range(-window, window):
        j = np.clip(idx + off, 0, n - 2)
        ax, ay = rx[j], ry[j]
        dx, dy = rx[j + 1] - ax, ry[j + 1] - ay
        seg2 = dx * dx + dy * dy
        with np.errstate(invalid="ignore", divide="ignore"):
            u = np.where(seg2 > 0, ((px - ax) * dx + (py - ay) * dy) / seg2, 0.0)
        u = np.clip(u, 0.0, 1.0)
        d = np.hypot(px - (ax + u * dx), py - (ay + u * dy))
        np.minimum(best, d, out=best)
    return best

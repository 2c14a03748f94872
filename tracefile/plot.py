"""Trace plots: reference and position, tracking error in um, effort (PNG, no screen needed)."""

from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from drivectl.tracefile.format import Trace


def plot_traces(traces: dict[str, Trace], path: str | Path, title: str = "") -> Path:
    """One column of three panels per axis; written atomically like the trace."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from drivectl.tracefile.format import atomic_write_bytes

    names = list(traces)
    contour = "x" in traces and "y" in traces and len(traces["x"]) == len(traces["y"])
    rows = 4 if contour else 3
    fig, axes = plt.subplots(rows, len(names), figsize=(6.5 * len(names), 2.5 * rows), squeeze=False)
    for j, name in enumerate(names):
        tr = traces[name]
        t = tr.time
        ax_p, ax_e, ax_u = axes[0][j], axes[1][j], axes[2][j]
        ax_p.plot(t, tr.ref * 1e3, label="reference", lw=1.0)
        ax_p.plot(t, tr.pos * 1e3, label="position", lw=1.0, ls="--")
        ax_p.set_ylabel("position [mm]")
        ax_p.legend(loc="best", fontsize=8)
        ax_p.set_title(f"axis {name}" + (f" - {tr.meta['controller']}" if "controller" in tr.meta else ""))
        ax_e.plot(t, tr.error * 1e6, lw=0.8, color="C3")
        ax_e.set_ylabel("error r - q [um]")
        ax_u.plot(t, tr.effort, lw=0.6, color="C2")
        ax_u.set_ylabel(f"effort [{tr.effort_unit or '?'}]")
        ax_u.set_xlabel("time [s]")
        for ax in (ax_p, ax_e, ax_u):
            ax.grid(True, alpha=0.3)
    if contour:
        from drivectl.tracefile.metrics import contour_error

        tx, ty = traces["x"], traces["y"]
        ce = contour_error(tx.ref, ty.ref, tx.pos, ty.pos)
        ax_xy, ax_ce = axes[3][0], axes[3][1]
        gain = 500.0
        ax_xy.plot(tx.ref * 1e3, ty.ref * 1e3, lw=1.0, label="reference")
        # the measured path with its deviation from the reference magnified, else it is invisible
        ax_xy.plot((tx.ref + gain * (tx.pos - tx.ref)) * 1e3, (ty.ref + gain * (ty.pos - ty.ref)) * 1e3,
                   lw=0.8, ls="--", label=f"measured, deviation x{gain:g}")
        ax_xy.set_aspect("equal", adjustable="datalim")
        ax_xy.set_xlabel("x [mm]")
        ax_xy.set_ylabel("y [mm]")
        ax_xy.legend(loc="best", fontsize=8)
        ax_xy.set_title("contour")
        ax_ce.plot(tx.time, ce * 1e6, lw=0.8, color="C4")
        ax_ce.set_xlabel("time [s]")
        ax_ce.set_ylabel("contour error [um]")
        ax_ce.set_title(f"contour error: max {ce.max() * 1e6:.2f} um, RMS {np.sqrt(np.mean(ce**2)) * 1e6:.2f} um")
        for ax in (ax_xy, ax_ce):
            ax.grid(True, alpha=0.3)
        for extra in axes[3][2:]:
            extra.set_visible(False)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    path = Path(path)
    atomic_write_bytes(path, buf.getvalue())
    return path


_apart: ProcessPoolExecutor | None = None


def plot_files_apart(files: dict[str, str | Path], path: str | Path, title: str = "") -> Path:
    """:func:`plot_traces` of trace files, drawn in a child process. Matplotlib renders in C holding the
    GIL for tens of milliseconds at a time, which a wall-clock servo loop in this process cannot wait
    for (bench/session.py: 3-5 % of its deadlines missed beside one plot a second, drawn here); waiting
    on the child releases the GIL. The child is started once and kept."""
    global _apart
    if _apart is None:
        import multiprocessing as mp

        _apart = ProcessPoolExecutor(1, mp_context=mp.get_context("spawn"))
    return _apart.submit(_plot_files, {k: str(v) for k, v in files.items()}, str(path), title).result()


def _plot_files(files: dict[str, str], path: str, title: str) -> Path:
    return plot_traces({k: Trace.read(p) for k, p in files.items()}, path, title)

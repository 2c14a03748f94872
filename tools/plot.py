"""Trace plots: reference and position, tracking error in um, effort (PNG, no screen needed)."""

from __future__ import annotations

from pathlib import Path

from drivectl.tools.trace import Trace


def plot_traces(traces: dict[str, Trace], path: str | Path, title: str = "") -> Path:
    """One column of three panels per axis; written atomically like the trace."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from drivectl.tools.trace import atomic_write_bytes

    names = list(traces)
    fig, axes = plt.subplots(3, len(names), figsize=(6.5 * len(names), 7.5), sharex="col", squeeze=False)
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

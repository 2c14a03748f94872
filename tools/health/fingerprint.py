"""The fingerprint run (docs/health.md): the axis's short health profile, run on a session like any
other profile (``AxisControl.run``: the resident loop's limits, following-error checks and fault
reactions), its trace streamed to a folder with ``# machine:`` and ``# started_utc:``, then kept in the
health store.

Refused, in one line and before anything moves, where the axis is not enabled or the profile would
leave its soft limits. The trace of a run that did not complete stays on disk and is not ingested: a
run that a fault or a stop cut short is not the fingerprint, and would be a false step in the trend.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from drivectl.driver.axis import AxisError
from drivectl.errors import InputError
from drivectl.profiles.base import Profile, ProfileError
from drivectl.tools.health.settings import DEFAULT_PROFILE

#: beyond the profile's duration, what a fingerprint run may take (the approach move to its start)
APPROACH_ALLOWANCE_S = 10.0


@dataclass
class FingerprintResult:
    """What a fingerprint run did: the handle's status (``done`` is a completed run), the trace written
    (None when nothing was recorded), and the store's outcome (None when not ingested)."""

    axis: str
    status: str
    trace: Path | None
    started_utc: str
    detail: str = ""
    ingest: Any = None

    @property
    def line(self) -> str:
        """One line for a person."""
        where = f"; trace {self.trace}" if self.trace else ""
        if self.ingest is not None:
            kept = {"added": "ingested", "present": "already in the store"}.get(self.ingest.status,
                                                                                  self.ingest.status)
            where += f" ({kept})"
        elif self.trace is not None:
            where += " (not ingested)"
        tail = f": {self.detail}" if self.detail else ""
        return f"health run {self.axis}: {self.status}{tail}{where}"


def fingerprint_profile(cfg: Any, axis: str) -> Profile:
    """The axis's fingerprint profile: ``[axes.NAME.health] profile``, else the library's
    ``fingerprint``; an error names the key that pointed there."""
    from drivectl.profiles.library import load_profile

    health = getattr(cfg.axis(axis), "health", None)
    name = health.profile if health is not None else DEFAULT_PROFILE
    source = health.profile_source if health is not None else "the default fingerprint profile"
    try:
        return load_profile(name, axis=axis)
    except ProfileError as exc:
        raise InputError(f"{source}: {exc}") from None


def check_fingerprint(ax: Any, profile: Profile, dt: float) -> None:
    """The refusals, before anything moves: the axis enabled (AxisError), every sample of the profile
    within the soft limits (LimitError naming the first one outside)."""
    if not ax.enabled:
        raise AxisError(f"axis {ax.name}: health run: not enabled (enable it first); nothing moved")
    n = int(math.ceil(profile.duration / dt)) + 1
    t = np.arange(n) * dt
    ax.limits.refuse_outside(f"axis {ax.name}: health run {getattr(profile, 'name', 'profile')}",
                             profile.sample(t)[0], t)


def run_fingerprint(machine: Any, axis: str, *, machine_name: str, out: str | Path,
                    store: str | Path | None = None, profile: Profile | None = None,
                    timeout: float | None = None, started: datetime | None = None) -> FingerprintResult:
    """Run the fingerprint of ``axis`` on ``machine`` (a :class:`drivectl.session.Machine` whose axis is
    enabled), record it into ``out`` (``AXIS-STAMP.csv``) and, completed, ingest it into ``store``
    (None: not ingested). ``started``: the run's ``# started_utc`` (default: now; a generated history
    gives its own, a shift apart). A fault ends the run as any run's does (the loop's fault reaction); the
    result says how it ended, and the trace keeps what was recorded."""
    from drivectl.controllers.runtime.loop import MotionFault
    from drivectl.tools.health.store import check_machine

    check_machine(machine_name)
    ax = machine.axes[axis]
    profile = profile if profile is not None else fingerprint_profile(machine.config, axis)
    check_fingerprint(ax, profile, machine.loop.dt)
    started = (started or datetime.now(UTC)).astimezone(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
    handle = ax.run(profile, approach=True, record=Path(out),
                    meta={"machine": machine_name, "started_utc": started, "health": "fingerprint"})
    detail = ""
    try:
        handle.wait(timeout if timeout is not None else profile.duration + APPROACH_ALLOWANCE_S)
    except MotionFault as exc:
        detail = str(exc)
    except TimeoutError as exc:  # the loop goes on: stop the run, as the shell's timeout does
        ax.stop("health run timed out").wait(5.0)
        handle.close_record()
        detail = str(exc)
    result = FingerprintResult(axis, str(handle.status), handle.path, started, detail or handle.record_error)
    if handle.status == "done" and handle.path is not None and store is not None:
        from drivectl.tools.health.store import Store

        with Store(store) as s:
            result.ingest = s.ingest(handle.path, machine_name, config=machine.config)
    return result


def default_machine_name(cfg: Any) -> str:
    """``--machine`` when not given: the configuration file's stem (``quench-3.toml``: quench-3), else
    ``emulated`` for the embedded configuration."""
    src = str(cfg.source)
    return "emulated" if src.startswith("<") else Path(src).stem

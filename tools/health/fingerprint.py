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


@dataclass
class Started:
    """A fingerprint run under way: its handle (the resident loop's), where it goes and when it began."""

    handle: Any
    axis: str
    machine_name: str
    started_utc: str
    store: Path | None
    config: Any


def start_fingerprint(machine: Any, axis: str, *, machine_name: str, out: str | Path,
                      store: str | Path | None = None, profile: Profile | None = None,
                      started: datetime | None = None) -> Started:
    """The refusals, then the run started (it approaches the profile's start first): the loop goes on
    with it while the caller waits (:func:`run_fingerprint`) or watches it (the console's Health page)."""
    from drivectl.tools.health.store import check_machine

    check_machine(machine_name)
    ax = machine.axes[axis]
    profile = profile if profile is not None else fingerprint_profile(machine.config, axis)
    check_fingerprint(ax, profile, machine.loop.dt)
    when = (started or datetime.now(UTC)).astimezone(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
    handle = ax.run(profile, approach=True, record=Path(out),
                    meta={"machine": machine_name, "started_utc": when, "health": "fingerprint"})
    return Started(handle, axis, machine_name, when, Path(store) if store is not None else None, machine.config)


def finish_fingerprint(run: Started, detail: str = "") -> FingerprintResult:
    """Once the run's handle is done: its trace closed (on this side, never in the cycle) and, completed,
    ingested."""
    handle = run.handle
    handle.close_record()
    result = FingerprintResult(run.axis, str(handle.status), handle.path, run.started_utc,
                               detail or handle.record_error or ("" if handle.status == "done" else handle.detail))
    if handle.status == "done" and handle.path is not None and run.store is not None:
        from drivectl.tools.health.store import Store

        with Store(run.store) as s:
            result.ingest = s.ingest(handle.path, run.machine_name, config=run.config)
    return result


def run_fingerprint(machine: Any, axis: str, *, machine_name: str, out: str | Path,
                    store: str | Path | None = None, profile: Profile | None = None,
                    timeout: float | None = None, started: datetime | None = None) -> FingerprintResult:
    """Run the fingerprint of ``axis`` on ``machine`` (a :class:`drivectl.session.Machine` whose axis is
    enabled), record it into ``out`` (``AXIS-STAMP.csv``) and, completed, ingest it into ``store``
    (None: not ingested). ``started``: the run's ``# started_utc`` (default: now; a generated history
    gives its own, a shift apart). A fault ends the run as any run's does (the loop's fault reaction);
    the result says how it ended, and the trace keeps what was recorded."""
    from drivectl.controllers.runtime.loop import MotionFault

    profile = profile if profile is not None else fingerprint_profile(machine.config, axis)
    run = start_fingerprint(machine, axis, machine_name=machine_name, out=out, store=store, profile=profile,
                            started=started)
    detail = ""
    try:
        run.handle.wait(timeout if timeout is not None else profile.duration + APPROACH_ALLOWANCE_S)
    except MotionFault as exc:
        detail = str(exc)
    except TimeoutError as exc:  # the loop goes on: stop the run, as the shell's timeout does
        machine.axes[axis].stop("health run timed out").wait(5.0)
        detail = str(exc)
    return finish_fingerprint(run, detail)


def default_machine_name(cfg: Any) -> str:
    """``--machine`` when not given: the configuration file's stem (``quench-3.toml``: quench-3), else
    ``emulated`` for the embedded configuration."""
    src = str(cfg.source)
    return "emulated" if src.startswith("<") else Path(src).stem

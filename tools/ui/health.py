"""The console's Health page (docs/health.md): the store's fleet table, the trend panels of one axis,
and the fingerprint run on the console's own machine.

The run goes where every console command goes (the conductor, ``AxisControl.run`` under the resident
loop); the page's status stream watches it, and once it ended its trace is closed and ingested in a
thread of its own, never in the conductor nor the cycle. The analysis of new runs is ``drivectl
health analyze`` in a child process: its fits take seconds of CPU per run and would otherwise compete
with a wall-clock loop in this process.
"""

from __future__ import annotations

import asyncio
import sys
import threading
from pathlib import Path
from typing import Any

#: longest analysis the console waits for (s)
ANALYZE_TIMEOUT_S = 3600.0


class HealthPanel:
    """The Health page's side of one console: the store, the machine's name in it, the run under way."""

    def __init__(self, console: Any, store: Path, machine_name: str):
        self.console = console
        self.store = Path(store)
        self.machine_name = machine_name
        self.running: Any = None  # tools/health/fingerprint.py Started
        self.last: dict[str, Any] | None = None  # the last run's outcome, for the page
        self._finishing = False
        self._lock = threading.Lock()

    # -- the run ----------------------------------------------------------------------------------------------
    def start_run(self, msg: dict[str, Any]) -> str:
        """On the conductor: the refusals (one line), then the run started."""
        from drivectl.tools.health.fingerprint import start_fingerprint

        ax = self.console.axis(msg.get("axis"))
        name = str(msg.get("machine") or self.machine_name)
        with self._lock:
            if self.running is not None:
                raise ValueError(f"health run: axis {self.running.axis}'s fingerprint is still running")
        run = start_fingerprint(self.console.m, ax.name, machine_name=name, out=self.console.out, store=self.store)
        with self._lock:
            self.running = run
            self.last = {"axis": ax.name, "state": "running", "line": f"health run {ax.name}: running"}
        return f"{ax.name}: fingerprint run started (machine {name}; the trace goes into the store)"

    def watch(self) -> None:
        """From the status stream: a run that ended is finished (trace closed, ingested) in a thread."""
        with self._lock:
            run = self.running
            if run is None or not run.handle.done or self._finishing:
                return
            self._finishing = True
        threading.Thread(target=self._finish, args=(run,), name="drivectl-ui-health", daemon=True).start()

    def _finish(self, run: Any) -> None:
        from drivectl.tools.health.fingerprint import finish_fingerprint

        try:
            res = finish_fingerprint(run)
            last = {"axis": run.axis, "state": res.status, "line": res.line,
                    "trace": res.trace.name if res.trace else None,
                    "ingest": res.ingest.status if res.ingest is not None else None}
        except Exception as exc:  # noqa: BLE001 - shown on the page; the console goes on
            last = {"axis": run.axis, "state": "failed", "line": f"health run {run.axis}: {exc}"}
        with self._lock:
            self.last, self.running, self._finishing = last, None, False

    def status(self) -> dict[str, Any]:
        with self._lock:
            return {"store": str(self.store), "machine": self.machine_name, "last": self.last,
                    "running": self.running is not None}

    # -- the store --------------------------------------------------------------------------------------------
    def fleet(self) -> dict[str, Any]:
        """Every axis of the store, ranked by its worst alarm."""
        from drivectl.tools.health.report import axes_in, axis_report, fleet, open_catalog, worst

        cfg = self.console.m.config
        if not (self.store / "catalog.duckdb").is_file():
            return {"store": str(self.store), "axes": [], "note": "no store yet: run a fingerprint"}
        con = open_catalog(self.store)
        try:
            reports = [axis_report(con, m, a, cfg.health_limits_of(a)) for m, a in axes_in(con)]
        finally:
            con.close()
        rows = []
        for rep in fleet(reports):
            w = worst(rep)
            rows.append({"machine": rep.machine, "axis": rep.axis, "runs": rep.runs, "fitted": rep.fitted,
                         "alarms": len(rep.alarms), "worst": None if w is None else {
                             "key": w.key, "onset_run": w.onset_run, "first_value": w.change.first_value,
                             "last_value": w.change.last_value, "runs_to_limit": w.runs_to_limit,
                             "limit": w.limit}})
        return {"store": str(self.store), "axes": rows}

    def axis(self, machine: str, axis: str) -> dict[str, Any]:
        """One axis's report (the ``--json`` object) and, per trend, what its panel draws."""
        import numpy as np

        from drivectl.tools.health.report import axis_report, open_catalog
        from drivectl.tools.health.trend import noise_sigma

        con = open_catalog(self.store)
        try:
            rep = axis_report(con, machine, axis, self.console.m.config.health_limits_of(axis))
        finally:
            con.close()
        panels: dict[str, list[dict[str, Any]]] = {}
        for t in rep.trends:
            vals = [v for v in t.values if v is not None]
            sigma = t.change.sigma if t.change is not None else (noise_sigma(np.array(vals)) if vals else None)
            panels.setdefault(t.effect, []).append({
                "param": t.param, "times": [x.strftime("%Y-%m-%dT%H:%M:%SZ") for x in t.times],
                "runs": t.runs, "values": t.values, "uncertainties": t.uncertainties, "sigma": sigma,
                "limit": t.limit, "alarm": t.alarm, "onset_run": t.onset_run,
                "onset_utc": (t.times[t.runs.index(t.onset_run)].strftime("%Y-%m-%dT%H:%M:%SZ")
                              if t.onset_run is not None else None)})
        return {"report": rep.to_json(), "panels": panels}

    async def analyze(self) -> dict[str, Any]:
        """``drivectl health analyze --store STORE`` in a child; its last line."""
        cfg = self.console.m.config
        args = [sys.executable, "-m", "drivectl.tools.cli.main"]
        if not str(cfg.source).startswith("<"):
            args += ["--config", str(cfg.source)]
        proc = await asyncio.create_subprocess_exec(*args, "health", "analyze", "--store", str(self.store),
                                                    stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
        try:
            stdout, stderr = await asyncio.wait_for(proc.communicate(), ANALYZE_TIMEOUT_S)
        except TimeoutError:
            proc.kill()
            raise ValueError(f"health analyze: no result within {ANALYZE_TIMEOUT_S:g} s") from None
        out = stdout.decode(errors="replace").strip().splitlines()
        err = stderr.decode(errors="replace").strip().splitlines()
        line = (out or err or [f"health analyze exited with {proc.returncode}"])[-1]
        return {"ok": proc.returncode == 0, "line": line, "errors": err[-20:]}

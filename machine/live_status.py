"""The running loop's timing, published for other processes: what `drivectl status` shows of a session
(the shell, the console, a program) that holds the bus.

A wall-clock session writes one small JSON file per bus about once a second, off the loop's thread, and
removes it when it closes: the lateness percentiles, missed cycles, stalls, each axis's deadline and
state. A reader takes the file only while its writer lives and it is fresh (docs/timing.md). The file is
the user's own (the runtime folder, mode 0600): nothing in it commands anything.
"""

from __future__ import annotations

import json
import os
import re
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

#: how often the session writes, and how old a file may be before a reader calls it stale (s)
PERIOD_S = 1.0
STALE_S = 5.0


def folder() -> Path:
    """Where the files live: $XDG_RUNTIME_DIR/drivectl, else the temporary folder's drivectl-UID."""
    base = os.environ.get("XDG_RUNTIME_DIR")
    if base and os.path.isdir(base):
        return Path(base) / "drivectl"
    return Path(tempfile.gettempdir()) / f"drivectl-{os.getuid()}"


def bus_key(bus: Any) -> str:
    """One name per bus a configuration describes (interface, channel, and host:port for socketcand)."""
    where = f"{bus.interface}-{bus.channel}"
    if bus.interface == "socketcand":
        where += f"-{bus.host}-{bus.port}"
    return re.sub(r"[^A-Za-z0-9_.-]", "_", where)


def path_for(bus: Any) -> Path:
    return folder() / f"loop-{bus_key(bus)}.json"


class Publisher:
    """Writes ``snapshot()`` to ``path`` every :data:`PERIOD_S` on a thread of its own, until :meth:`close`."""

    def __init__(self, path: Path, snapshot: Callable[[], dict[str, Any]]):
        self.path = path
        self._snapshot = snapshot
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._main, name="drivectl-status-file", daemon=True)
        self.error: str | None = None

    def start(self) -> None:
        self._thread.start()

    def _main(self) -> None:
        while True:
            try:
                self._write()
            except (OSError, TypeError, ValueError) as exc:  # a full disk or a read-only folder: the loop runs on
                self.error = str(exc)
            if self._stop.wait(PERIOD_S):
                return

    def _write(self) -> None:
        self.path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        doc = {"pid": os.getpid(), "written": time.time(), **self._snapshot()}
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w") as f:
            json.dump(doc, f)
        os.replace(tmp, self.path)  # a reader sees the old file or the new one, never half of one

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(2.0)
        try:
            doc = json.loads(self.path.read_text())
            if doc.get("pid") == os.getpid():  # ours: another session may have taken the bus since
                self.path.unlink()
        except (OSError, ValueError):
            pass


def read(bus: Any, *, now: float | None = None) -> dict[str, Any] | None:
    """The published status of the session on ``bus``: None when there is none, its writer is gone, or it
    is older than :data:`STALE_S`."""
    try:
        doc = json.loads(path_for(bus).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(doc, dict) or not isinstance(doc.get("pid"), int):
        return None
    try:
        os.kill(doc["pid"], 0)
    except ProcessLookupError:
        return None
    except PermissionError:
        pass  # alive, another user's
    age = (time.time() if now is None else now) - float(doc.get("written", 0.0))
    if age > STALE_S:
        return None
    doc["age_s"] = age
    return doc


def summary(st: dict[str, Any]) -> dict[str, Any]:
    """What is published of ``Machine.status()``: timing and each axis's state, not the whole status."""
    keys = ("clock", "bus", "cycle_s", "cycles", "missed_deadlines", "missed_fraction", "skipped_cycles",
            "worst_late_ms", "stalls", "latency_ms", "deadline_ms", "faults")
    out = {k: st[k] for k in keys if k in st}
    out["axes"] = {n: {"state": a["state"], "power": a["power"], "fault": a.get("fault")}
                   for n, a in st.get("axes", {}).items()}
    return out

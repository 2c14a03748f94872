"""The console's trace folder: the traces listed, one read for plotting with its summary, and explain
run on one.

Explain runs in a child process (``drivectl explain``): its fits take seconds of CPU and would
otherwise compete with a wall-clock loop in this process for the interpreter.
"""

from __future__ import annotations

import asyncio
import re
import sys
from pathlib import Path
from typing import Any

from drivectl.tracefile.format import MAGIC, Trace, TraceError
from drivectl.tracefile.metrics import summarize

#: the folder explain writes into, inside the console's output folder
EXPLAIN_DIR = "explain"
#: longest explain run the console waits for (s)
EXPLAIN_TIMEOUT_S = 600.0


def inside(folder: Path, name: str) -> Path:
    """``name`` as a file inside ``folder`` (one subfolder level at most); ValueError for anything else."""
    parts = Path(name).parts
    if not name or len(parts) > 2 or any(p in ("..", ".", "") or p.startswith(".") for p in parts) or \
            Path(name).is_absolute():
        raise ValueError(f"{name!r}: not a file of the trace folder")
    path = folder / name
    if not path.is_file():
        raise ValueError(f"{name!r}: no such file in {folder}")
    return path


def margin_figures(folder: Path) -> dict[str, dict[str, Any]]:
    """The open-loop figures `drivectl bode --loop open --out FOLDER` left, per axis: the PNG, its time, and
    the margins of its JSON beside it (tools/commissioning/margins.py ``write_open_loop``) when readable."""
    import json

    out: dict[str, dict[str, Any]] = {}
    if not folder.is_dir():
        return out
    for png in folder.glob("bode-open-*.png"):
        axis = png.stem[len("bode-open-"):]
        entry: dict[str, Any] = {"png": png.name, "mtime": png.stat().st_mtime, "margins": None}
        side = png.with_suffix(".json")
        try:
            entry["margins"] = json.loads(side.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            pass
        out[axis] = entry
    return out


def is_trace(path: Path) -> bool:
    try:
        with path.open(encoding="utf-8") as fh:
            return fh.readline().startswith(MAGIC)
    except (OSError, UnicodeDecodeError):
        return False


def listing(folder: Path) -> list[dict[str, Any]]:
    """The folder's trace files, newest first: name, size, time, and the PNG beside it if any."""
    if not folder.is_dir():
        return []
    out = []
    for p in folder.glob("*.csv"):
        if not is_trace(p):
            continue
        st = p.stat()
        png = p.with_suffix(".png")
        out.append({"name": p.name, "bytes": st.st_size, "mtime": st.st_mtime,
                    "png": png.name if png.is_file() else None})
    out.sort(key=lambda e: (-e["mtime"], e["name"]))
    return out


def load(folder: Path, name: str) -> dict[str, Any]:
    """A trace's columns (for the page to plot and decimate), metadata and summary."""
    path = inside(folder, name)
    try:
        tr = Trace.read(path)
    except TraceError as exc:
        raise ValueError(str(exc)) from None
    try:
        summary = summarize(tr) if len(tr) > 1 else {}
    except (ValueError, ZeroDivisionError) as exc:
        summary = {"error": str(exc)}
    return {"name": name, "meta": dict(tr.meta), "summary": summary, "rows": len(tr),
            "columns": {k: v.tolist() for k, v in tr.columns.items()}}


def default_plant(console: Any, trace_axis: str) -> str:
    """The plant the console's configuration gives the trace's axis ("" when it names none)."""
    try:
        return console.m.config.axis(trace_axis).plant
    except Exception:  # noqa: BLE001 - an axis not in this configuration: the person types a plant
        return ""


async def run_explain(console: Any, name: str, plant: str) -> dict[str, Any]:
    """``drivectl explain TRACE --plant P --out OUT/explain --quiet`` in a child; its report and PNG."""
    path = inside(console.out, name)
    if not plant:
        tr_axis = Trace.read(path, columns=("time_s",)).meta.get("axis", "") if is_trace(path) else ""
        plant = default_plant(console, tr_axis)
    if not plant or not re.fullmatch(r"[\w.\-/ ]+", plant):
        raise ValueError(f"explain: plant {plant!r}: give a built-in plant name or a plant TOML file")
    out = console.out / EXPLAIN_DIR
    out.mkdir(parents=True, exist_ok=True)
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "drivectl.tools.cli.main", "explain", str(path), "--plant", plant, "--out", str(out),
        "--quiet", stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
    try:
        stdout, stderr = await asyncio.wait_for(proc.communicate(), EXPLAIN_TIMEOUT_S)
    except TimeoutError:
        proc.kill()
        raise ValueError(f"explain: no result within {EXPLAIN_TIMEOUT_S:g} s") from None
    text = stdout.decode(errors="replace")
    if proc.returncode != 0:
        raise ValueError((stderr.decode(errors="replace").strip() or text.strip() or
                          f"explain exited with {proc.returncode}").splitlines()[-1])
    report = "\n".join(line for line in text.splitlines() if not line.startswith("wrote "))
    files = [Path(line[len("wrote "):]) for line in text.splitlines() if line.startswith("wrote ")]
    png = next((f for f in files if f.suffix == ".png"), None)
    return {"name": name, "plant": plant, "report": report,
            "png": f"{EXPLAIN_DIR}/{png.name}" if png is not None else None,
            "files": [f.name for f in files]}

"""The trace file, format v1: the one result type of every run (simulation, emulator, real drive).

```
# drivectl trace v1
# axis: x
# plant: rigid-x
# effort_unit: N
# dt_s: 0.001
time_s,ref_m,pos_m,effort
0.000000,0.000000000,0.000000000,0.000000
```
``#`` lines before the column row are metadata (``key: value``). Required columns: ``time_s``,
``ref_m``, ``pos_m`` (measured), ``effort`` (commanded, in ``effort_unit``); any others may follow.
A CSV from another recorder reads once it has the four columns. Writes are atomic (temporary file in
the same folder, then rename), so a reader never sees half a trace.
"""

from __future__ import annotations

import io
import math
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

MAGIC = "# drivectl trace v1"
REQUIRED = ("time_s", "ref_m", "pos_m", "effort")
_FORMATS = {"time_s": "%.6f", "ref_m": "%.9f", "pos_m": "%.9f", "effort": "%.6f"}


class TraceError(ValueError):
    """A trace file cannot be read or used; the message is one line naming the file."""


@dataclass
class Trace:
    """Columns (numpy arrays of equal length, the four required first) and metadata."""

    columns: dict[str, np.ndarray]
    meta: dict[str, str] = field(default_factory=dict)
    #: where the trace came from (its file), named in errors
    source: str = field(default="trace", compare=False, repr=False)

    def __post_init__(self) -> None:
        for name in REQUIRED:
            if name not in self.columns:
                raise TraceError(f"trace: missing column {name!r}")
        n = {len(v) for v in self.columns.values()}
        if len(n) > 1:
            raise TraceError(f"trace: columns of different lengths {sorted(n)}")

    @property
    def time(self) -> np.ndarray:
        return self.columns["time_s"]

    @property
    def ref(self) -> np.ndarray:
        return self.columns["ref_m"]

    @property
    def pos(self) -> np.ndarray:
        return self.columns["pos_m"]

    @property
    def effort(self) -> np.ndarray:
        return self.columns["effort"]

    @property
    def error(self) -> np.ndarray:
        """Tracking error r - q, m."""
        return self.ref - self.pos

    @property
    def dt(self) -> float:
        if "dt_s" in self.meta:
            return float(self.meta["dt_s"])
        if len(self.time) > 1:
            return float(np.median(np.diff(self.time)))
        raise TraceError(f"{self.source}: dt_s: not in the metadata, and fewer than two rows to tell it from")

    @property
    def effort_unit(self) -> str:
        return self.meta.get("effort_unit", "")

    def __len__(self) -> int:
        return len(self.time)

    def head(self, n: int) -> Trace:
        return Trace({k: v[:n] for k, v in self.columns.items()}, dict(self.meta), self.source)

    # ---------------------------------------------------------------------------------------------
    def to_text(self) -> str:
        out = io.StringIO()
        out.write(MAGIC + "\n")
        for key, value in self.meta.items():
            text = str(value).replace("\n", " ")
            out.write(f"# {key}: {text}\n")
        names = list(REQUIRED) + [k for k in self.columns if k not in REQUIRED]
        data = np.column_stack([np.asarray(self.columns[k], dtype=float) for k in names]) if len(self) else None
        out.write(",".join(names) + "\n")
        if data is not None:
            fmt = [_FORMATS.get(k, "%.9g") for k in names]
            np.savetxt(out, data, fmt=fmt, delimiter=",")
        return out.getvalue()

    def write(self, path: str | Path) -> Path:
        """Write atomically: a temporary file beside ``path``, then rename over it."""
        path = Path(path)
        atomic_write_text(path, self.to_text())
        return path

    @classmethod
    def read(cls, path: str | Path) -> Trace:
        path = Path(path)
        try:
            text = path.read_text()
        except FileNotFoundError:
            raise TraceError(f"{path}: no such trace file") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise TraceError(f"{path}: cannot read: {exc}") from None
        return cls.parse(text, source=str(path))

    @classmethod
    def parse(cls, text: str, source: str = "<trace>") -> Trace:
        meta: dict[str, str] = {}
        lines = text.splitlines()
        i = 0
        while i < len(lines) and (lines[i].startswith("#") or not lines[i].strip()):
            line = lines[i].lstrip("#").strip()
            if ":" in line and not line.startswith("drivectl trace"):
                key, _, value = line.partition(":")
                meta[key.strip()] = value.strip()
            i += 1
        if "dt_s" in meta:
            try:
                dt = float(meta["dt_s"])
            except ValueError:
                dt = math.nan
            if not (math.isfinite(dt) and dt > 0):
                raise TraceError(f"{source}: dt_s: expected a number > 0 (s), got {meta['dt_s']!r}")
        if i >= len(lines):
            raise TraceError(f"{source}: no column row (expected {','.join(REQUIRED)})")
        names = [c.strip() for c in lines[i].split(",")]
        missing = [c for c in REQUIRED if c not in names]
        if missing:
            raise TraceError(f"{source}: missing column(s) {', '.join(missing)} (have {', '.join(names)})")
        rows = [ln for ln in lines[i + 1 :] if ln.strip()]
        if not rows:
            raise TraceError(f"{source}: no data rows")
        try:
            data = np.loadtxt(io.StringIO("\n".join(rows)), delimiter=",", ndmin=2)
        except ValueError as exc:
            raise _garbled(source, names, rows, exc) from None
        if data.shape[1] != len(names):
            raise TraceError(f"{source}: rows have {data.shape[1]} fields, the column row {len(names)} "
                             f"({','.join(names)})")
        columns = {name: data[:, j].copy() for j, name in enumerate(names)}
        for name in REQUIRED:
            bad = ~np.isfinite(columns[name])
            if bad.any():
                row = int(np.argmax(bad))
                raise TraceError(f"{source}: column {name}: not a finite number at data row {row + 1}")
        t = columns["time_s"]
        if len(t) > 1 and np.any(np.diff(t) <= 0):
            row = int(np.argmax(np.diff(t) <= 0)) + 2
            raise TraceError(f"{source}: column time_s: not increasing at data row {row}")
        return cls(columns, meta, source)


def _garbled(source: str, names: list[str], rows: list[str], exc: ValueError) -> TraceError:
    """The first data row that numpy could not read, with the column at fault."""
    for r, row in enumerate(rows, 1):
        fields = row.split(",")
        if len(fields) < len(names):
            return TraceError(f"{source}: garbled data: data row {r} has {len(fields)} of {len(names)} fields, no "
                              f"column {', '.join(names[len(fields):])} (truncated?)")
        if len(fields) > len(names):
            return TraceError(f"{source}: garbled data: data row {r} has {len(fields)} fields, the column row "
                              f"{len(names)} ({','.join(names)})")
        for name, text in zip(names, fields, strict=True):
            try:
                float(text)
            except ValueError:
                return TraceError(f"{source}: garbled data: column {name}: {text.strip()!r} is not a number at "
                                  f"data row {r}")
    reason = str(exc).splitlines()[0].split("; use `usecols`")[0]  # numpy's hint is not for our users
    return TraceError(f"{source}: garbled data: {reason}")


def atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` so that the file is either the old one or the whole new one."""
    atomic_write_bytes(path, text.encode())


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to a temporary file beside ``path``, fsync, then rename over ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def format_value(value: object) -> str:
    """Metadata values as one line (floats with full precision)."""
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else str(value)
    return str(value)

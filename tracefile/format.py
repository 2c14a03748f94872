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
A CSV from another recorder reads once it has the four columns. The whole contract, with the streamed
form (``recording: streamed``, trailer metadata after the data, the end marker) is docs/trace-format.md.

:meth:`Trace.write` writes a whole trace atomically (temporary file in the same folder, then rename);
a run streams its trace with :class:`drivectl.tracefile.stream.TraceWriter`. :meth:`Trace.read`
refuses what it cannot read right (duplicate column names, time not increasing or not stepping by
``dt_s``, files whose columns would not fit the memory budget) and reads gzip and a UTF-8 BOM.
"""

from __future__ import annotations

import hashlib
import io
import math
import os
import secrets
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from drivectl.errors import InputError

MAGIC = "# drivectl trace v1"
REQUIRED = ("time_s", "ref_m", "pos_m", "effort")
FORMATS = {"time_s": "%.6f", "ref_m": "%.9f", "pos_m": "%.9f", "effort": "%.6f"}
#: header value of ``recording`` in a streamed trace, and its last line once complete (docs/trace-format.md)
STREAMED = "streamed"
END_MARKER = "# end of trace"
#: data rows parsed at once by the reader
CHUNK_ROWS = 65536
BUDGET_ENV = "DRIVECTL_TRACE_MAX_MB"


class TraceError(InputError):
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
            fmt = [FORMATS.get(k, "%.9g") for k in names]
            np.savetxt(out, data, fmt=fmt, delimiter=",")
        return out.getvalue()

    def write(self, path: str | Path) -> Path:
        """Write atomically: a temporary file beside ``path``, then rename over it."""
        path = Path(path)
        atomic_write_text(path, self.to_text())
        return path

    @classmethod
    def read(cls, path: str | Path, columns: Sequence[str] | None = None) -> Trace:
        """Read a trace file (plain or gzip, UTF-8 with or without BOM) in bounded memory: the data is
        parsed in chunks and kept as float64 columns; a file whose columns would need more than
        :func:`max_read_bytes` is refused with the figure. ``columns`` keeps only those columns (the four
        required are always kept). A streamed trace (docs/trace-format.md) without its end marker reads
        as far as it was flushed, with ``trace_complete: false`` in its metadata."""
        path = Path(path)
        try:
            raw = open(path, "rb")  # noqa: SIM115 - closed below, whatever the reader does
        except FileNotFoundError:
            raise TraceError(f"{path}: no such trace file") from None
        except OSError as exc:
            raise TraceError(f"{path}: cannot read: {exc.strerror or exc}") from None
        try:
            lines = 0  # an upper bound of the rows, for the budget and one allocation (plain files)
            if raw.peek(2)[:2] == b"\x1f\x8b":
                import gzip

                binary: Any = gzip.GzipFile(fileobj=raw)
            else:
                binary = raw
                while block := raw.read(1 << 22):
                    lines += block.count(b"\n")
                lines += 1
                raw.seek(0)
            text = io.TextIOWrapper(binary, encoding="utf-8-sig", newline=None)
            try:
                return cls._from_lines(text, str(path), max_rows=lines, keep=columns)
            except (OSError, EOFError, UnicodeDecodeError) as exc:
                raise TraceError(f"{path}: cannot read: {exc}") from None
        finally:
            raw.close()

    @classmethod
    def parse(cls, text: str, source: str = "<trace>") -> Trace:
        return cls._from_lines(io.StringIO(text.removeprefix("\ufeff")), source)

    @classmethod
    def _from_lines(cls, lines: Iterator[str] | io.TextIOBase, source: str, max_rows: int = 0,
                    keep: Sequence[str] | None = None) -> Trace:
        """Parse a trace from its lines; ``max_rows`` (when known: the file's line count) sizes the one
        allocation of the columns and checks the memory budget before any row is parsed."""
        meta: dict[str, str] = {}
        header_line = None
        for line in lines:
            if line.startswith("#") or not line.strip():
                _meta_line(line, meta)
                continue
            header_line = line
            break
        _check_dt_text(meta, source)
        if header_line is None:
            raise TraceError(f"{source}: no column row (expected {','.join(REQUIRED)})")
        names = [c.strip() for c in header_line.strip().split(",")]
        seen: dict[str, int] = {}
        for j, name in enumerate(names):
            if name in seen:
                raise TraceError(f"{source}: column {name!r} appears twice (columns {seen[name] + 1} and {j + 1}): "
                                 "which one is meant cannot be told")
            seen[name] = j
        missing = [c for c in REQUIRED if c not in names]
        if missing:
            raise TraceError(f"{source}: missing column(s) {', '.join(missing)} (have {', '.join(names)})")
        wanted = [j for j, n in enumerate(names) if keep is None or n in keep or n in REQUIRED or n == "lost"]
        streamed = meta.get("recording") == STREAMED
        budget = max_read_bytes()
        width = len(wanted)

        def over_budget(rows: int) -> TraceError:
            need = rows * width * 8
            return TraceError(f"{source}: {rows} rows x {width} columns need {need / 1e6:.0f} MB in memory, more "
                              f"than readers take ({budget / 1e6:.0f} MB; raise {BUDGET_ENV} or cut the trace "
                              "into parts)")

        if max_rows and max_rows * width * 8 > budget:
            raise over_budget(max_rows)
        # the columns, one row each of a single block: sized once from the line count, or grown by doubling
        store = np.empty((width, max_rows or CHUNK_ROWS))
        trailer: dict[str, str] = {}
        complete = False
        rows_done = 0
        held: str | None = None  # the last data line, parsed once we know whether it was cut off
        chunk: list[str] = []

        def flush_chunk() -> None:
            nonlocal rows_done, store
            if not chunk:
                return
            try:
                data = np.loadtxt(chunk, delimiter=",", ndmin=2)
            except ValueError as exc:
                raise _garbled(source, names, chunk, exc, rows_done) from None
            if data.shape[1] != len(names):
                raise TraceError(f"{source}: rows have {data.shape[1]} fields, the column row {len(names)} "
                                 f"({','.join(names)})")
            end = rows_done + len(data)
            if end > store.shape[1]:
                if end * width * 8 > budget:
                    raise over_budget(end)
                grown = np.empty((width, min(max(end, 2 * store.shape[1]), budget // (width * 8))))
                grown[:, :rows_done] = store[:, :rows_done]
                store = grown
            store[:, rows_done:end] = data[:, wanted].T
            rows_done = end
            chunk.clear()

        for line in lines:
            if held is not None:
                chunk.append(held)
                held = None
                if len(chunk) >= CHUNK_ROWS:
                    flush_chunk()
            if line.startswith("#"):
                if line.strip() == END_MARKER:
                    complete = True
                else:
                    _meta_line(line, trailer)
                continue
            if not line.strip():
                continue
            if complete or trailer:
                raise TraceError(f"{source}: data row after the trailer (data row {rows_done + len(chunk) + 1})")
            held = line
        if held is not None:
            if held.endswith("\n") or not streamed or complete:
                chunk.append(held)
            # else: a streamed trace cut mid-row by a kill: the row was never whole, drop it
        flush_chunk()
        if rows_done == 0:
            raise TraceError(f"{source}: no data rows")
        meta.update(trailer)
        if streamed:
            meta["trace_complete"] = "true" if complete else "false"
            if not complete:
                meta.setdefault("stop", "incomplete")
                meta.setdefault("stop_detail", "the recording ended without its trailer (the writer was killed "
                                "or is still running): rows up to its last flush")
        if rows_done < store.shape[1] // 2 and rows_done > CHUNK_ROWS:  # mostly unused: give it back
            store = store[:, :rows_done].copy()
        columns = {names[j]: store[slot, :rows_done] for slot, j in enumerate(wanted)}
        # a trace from a bus log (tools/buslog): no reference on the bus is ``# ref: none`` (ref_m NaN), and a
        # SYNC without its PDOs is a row flagged ``lost`` with NaN values, never interpolated
        lost = columns.get("lost")
        for name in REQUIRED:
            if name == "ref_m" and meta.get("ref") == "none":
                continue
            bad = ~np.isfinite(columns[name])
            if lost is not None and name != "time_s":
                bad &= lost == 0
            if bad.any():
                row = int(np.argmax(bad))
                raise TraceError(f"{source}: column {name}: not a finite number at data row {row + 1}")
        _check_time(columns["time_s"], meta, source)
        return cls(columns, meta, source)


def max_read_bytes() -> int:
    """The memory a reader may take for a trace's columns: ${BUDGET_ENV} MB, default 1024 MB."""
    try:
        mb = float(os.environ.get(BUDGET_ENV, "1024"))
    except ValueError:
        mb = 1024.0
    return int(mb * 1e6)


def _meta_line(line: str, meta: dict[str, str]) -> None:
    text = line.lstrip("#").strip()
    if ":" in text and not text.startswith("drivectl trace"):
        key, _, value = text.partition(":")
        meta[key.strip()] = value.strip()


def _check_dt_text(meta: dict[str, str], source: str) -> None:
    if "dt_s" in meta:
        try:
            dt = float(meta["dt_s"])
        except ValueError:
            dt = math.nan
        if not (math.isfinite(dt) and dt > 0):
            raise TraceError(f"{source}: dt_s: expected a number > 0 (s), got {meta['dt_s']!r}")


def _check_time(t: np.ndarray, meta: dict[str, str], source: str) -> None:
    """Time strictly increasing and, when dt_s is given, stepping by dt_s or a whole multiple of it (a slot the
    loop skipped has no row: docs/trace-format.md), most steps within 1 %, at least one a single dt_s (a dt_s
    wrong by a whole factor is still caught); checked in slices so that a long trace takes no second copy."""
    dt = float(meta["dt_s"]) if "dt_s" in meta else None
    matching = single = steps = 0
    step = 1 << 20
    for a in range(0, max(0, len(t) - 1), step):
        d = np.diff(t[a : a + step + 1])
        bad = d <= 0
        if bad.any():
            row = a + int(np.argmax(bad)) + 2
            raise TraceError(f"{source}: column time_s: not increasing at data row {row}")
        if dt is not None:
            k = np.maximum(np.rint(d / dt), 1.0)
            matching += int(np.count_nonzero(np.abs(d - k * dt) <= 0.01 * dt))
            single += int(np.count_nonzero(np.abs(d - dt) <= 0.01 * dt))
            steps += len(d)
    if dt is not None and steps and (matching * 2 < steps or single == 0):
        median = float(np.median(np.diff(t[: step + 1])))
        raise TraceError(f"{source}: dt_s: {dt:g} s in the metadata, but the time column steps {median:g} s "
                         f"(median; {steps - matching} of {steps} steps are not a whole number of dt_s within 1 %, "
                         f"{single} a single dt_s): one of them is wrong")


def _garbled(source: str, names: list[str], rows: list[str], exc: ValueError, offset: int = 0) -> TraceError:
    """The first data row that numpy could not read, with the column at fault (``offset``: data rows
    before ``rows``)."""
    for r, row in enumerate(rows, offset + 1):
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


def file_sha256(path: str | Path) -> str:
    """The sha256 of a file's bytes, read in blocks (a trace's or a log's identity in a store)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(1 << 20):
            h.update(block)
    return h.hexdigest()


def atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` so that the file is either the old one or the whole new one."""
    atomic_write_bytes(path, text.encode("utf-8", errors="backslashreplace"))  # a non-UTF-8 path in metadata


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to a temporary file beside ``path`` (``.NAME.PID.RANDOM.tmp``, mode 0666 less the
    umask, as any file the user makes), fsync, then rename over ``path``. A temporary left by a killed
    process is removed by :func:`drivectl.tracefile.stream.clean_stale` (its pid is gone)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.parent / f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp"
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
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

"""Streaming trace writer: a run's trace goes to disk as it is recorded, at constant memory.

The contract of the file is docs/trace-format.md (trace format v1, streamed). In short: the header and
the column row are written when the writer opens, the rows follow at most ``flush_s`` (100 ms) behind
the loop, and the metadata known only at the end (stop reason, fault, counters) is written as trailer
``# key: value`` lines after the data, closed by the end marker ``# end of trace``. While the run lasts
the file is ``AXIS-STAMP.csv.partial``; on :meth:`TraceWriter.close` it is renamed ``AXIS-STAMP.csv``
(never over an existing file) and ``AXIS.csv`` is pointed at it (a hard link: the latest trace under a
fixed name). A killed process leaves the ``.partial`` file with every row up to the last flush, which
every reader reads, marked ``trace_complete: false``.

API (for the loop that records; :mod:`drivectl.controllers.runtime.servo` or the resident loop)::

    w = TraceWriter(folder, "x", columns=("time_s", "ref_m", "pos_m", "effort", "vel_m_s"),
                    meta={"axis": "x", "effort_unit": "N", "dt_s": "0.001", ...})
    w.start()                       # opens the .partial file (O_EXCL, mode 0666 & ~umask) and the thread
    for k in ...:                   # the per-cycle path:
        w.append(t, ref, pos, u, v) #   one row into a preallocated block: no I/O, no allocation
    w.error                         # None, or why writing stopped (disk full): cheap to poll per cycle
    w.flush()                       # not in the cycle: wait until every row so far is on disk (tests, phases)
    path = w.close({"stop": "completed", "cycles": "2501"})   # trailer, fsync, rename; -> the final path

Threading: ``append`` is called from ONE thread (the loop). A daemon thread owned by the writer wakes
every ``flush_s`` (and whenever a block fills), formats the rows the loop has published since its last
wake-up and writes and flushes them (to the kernel: a SIGKILL of the process loses nothing flushed; the
file is fsynced on close). ``inline=True`` (a lockstep run, which has no deadline to keep) writes on the
loop's thread instead: each full block as it fills, and the rows so far whenever ``flush_s`` of wall
time passed since the last flush (looked at every 32 rows); the thread then only flushes what an idle
loop left, ``flush_s`` after the last flush. A writer thread taking the GIL in the middle of the loop's
cycle (numpy releases it in every dot) cost 3-5 us per cycle; the promise of the file is the same.
Rows live in a ring of ``blocks`` preallocated blocks of ``block_rows``
rows; a block goes back to the ring once written. If the disk stalls so long that the ring is full, the
loop does not wait: ``append`` takes a new block (counted as ``trace_spill_blocks`` in the trailer) and
memory grows only for the length of the stall. A write error (disk full, the folder gone) stops the
writing, never the loop: the rows written so far stay, :attr:`TraceWriter.error` tells it (cheap to
poll each cycle) and :meth:`close` raises :class:`TraceWriteError` after closing the file (it stays a
``.partial``: incomplete).

``close(trailer, complete=True)`` ends the record: the run ended, whatever its stop reason (a fault or
an interrupt is a complete record of a run that stopped). ``complete=False`` keeps the ``.partial``
name (a record known to be cut short). :meth:`abandon` closes without trailer (as a crash would).
"""

from __future__ import annotations

import collections
import errno
import os
import re
import shutil
import threading
import time
from collections.abc import Iterable, Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from drivectl.tracefile.format import END_MARKER, FORMATS, MAGIC, REQUIRED, STREAMED, TraceError

#: a name that is safe as a file name stem on every system we care about (axis names, run names)
_SAFE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_+-]{0,63}")
PARTIAL_SUFFIX = ".partial"
#: rough size of one formatted row per column (bytes), for the room check before a run
BYTES_PER_VALUE = 14


class TraceWriteError(TraceError):
    """The trace could not be written whole; one line naming the file."""


def safe_name(name: str) -> bool:
    """Whether ``name`` can be used as a file name stem: letters, digits, ``_ + -``, not starting with a
    sign, at most 64 characters (so ``../../escaped``, ``x/y``, ``.``, ``""`` are not)."""
    return bool(_SAFE_NAME.fullmatch(name))


def estimate_bytes(rows: int, columns: int) -> int:
    """What a trace of ``rows`` x ``columns`` takes on disk, roughly (for the room check)."""
    return rows * columns * BYTES_PER_VALUE + 4096


def check_output_folder(folder: str | Path, flag: str = "--out", need_bytes: int = 0) -> Path:
    """Refuse, before anything moves, an output folder the run could not write: not a folder, not
    writable, or with less room than ``need_bytes``. A missing folder is not made here (the writer makes
    it), but the place it would go must be writable.
    Raises TraceWriteError with one line naming ``flag`` and the folder."""
    path = Path(folder)
    try:
        str(path).encode("utf-8")
    except UnicodeEncodeError:
        raise TraceWriteError(f"{flag} {os.fsencode(path)!r}: not valid UTF-8 (the trace records its path as "
                              "text); rename it") from None
    if path.exists() and not path.is_dir():
        raise TraceWriteError(f"{flag} {path}: exists and is not a folder (give a folder; the trace is named "
                              "AXIS-STAMP.csv inside it)")
    # a missing folder is made by the writer; here only its nearest existing ancestor is probed, so a run
    # refused later (a bus that cannot open) leaves nothing behind, not even an empty folder
    where = path
    while not where.exists():
        if where.parent == where:
            break
        where = where.parent
    if not where.is_dir():
        raise TraceWriteError(f"{flag} {path}: cannot create the folder: {where} is not a folder")
    probe = where / f".drivectl-probe.{os.getpid()}.tmp"
    try:
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        try:
            os.write(fd, b"x")
        finally:
            os.close(fd)
            os.unlink(probe)
    except OSError as exc:
        why = exc.strerror or exc
        raise TraceWriteError(f"{flag} {path}: cannot write there: {why}" if where == path else
                              f"{flag} {path}: cannot create the folder: {where}: {why}") from None
    if need_bytes:
        free = shutil.disk_usage(where).free
        if free < need_bytes:
            raise TraceWriteError(f"{flag} {path}: {free / 1e6:.1f} MB free, the run needs about "
                                  f"{need_bytes / 1e6:.1f} MB")
    return path


def clean_stale(folder: str | Path) -> list[Path]:
    """Remove the temporaries of writes that died (``.NAME.PID.*.tmp`` of a process that is gone; the
    pid-less ones of older versions when over an hour old). Partial traces are records, never removed:
    returns those whose writer is gone (``AXIS-STAMP.csv.partial``), for the caller to mention."""
    folder = Path(folder)
    left = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return []
    now = time.time()
    for e in entries:
        name = e.name
        if name.startswith(".") and name.endswith(".tmp"):
            parts = name.split(".")
            pid = next((int(p) for p in parts if p.isdigit()), None)
            try:
                stale = (not _alive(pid)) if pid is not None else now - e.stat().st_mtime > 3600
                if stale:
                    os.unlink(e.path)
            except OSError:
                pass
        elif name.endswith(PARTIAL_SUFFIX) and name not in _OPEN_PARTIALS:
            left.append(Path(e.path))
    return sorted(left)


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


#: partial files this process is writing (clean_stale must not call them left over)
_OPEN_PARTIALS: set[str] = set()


class _Block:
    """``rows`` rows of ``cols`` values, flat and row after row in a Python list: a row goes in by one slice
    assignment (a numpy row took 0.6 us of the loop's cycle, the list 0.13) and the formatter takes a
    slice of it as it is."""

    __slots__ = ("rows", "start")

    def __init__(self, rows: int, cols: int):
        self.rows: list[float] = [0.0] * (rows * cols)
        self.start = 0


class TraceWriter:
    """One axis's trace, streamed to ``folder``; see the module docstring for the contract."""

    #: inline: rows between two looks at the wall clock (at 1 000 rows/s still within 32 ms of flush_s)
    INLINE_CHECK_ROWS = 32

    def __init__(self, folder: str | Path, axis: str, *, columns: Sequence[str] = REQUIRED,
                 meta: Mapping[str, object] | None = None, block_rows: int = 1024, blocks: int = 4,
                 flush_s: float = 0.1, latest: bool = True, stamp: str | None = None, inline: bool = False):
        if not safe_name(axis):
            raise TraceWriteError(f"trace: axis name {axis!r} is not safe as a file name (letters, digits, _ + -)")
        columns = tuple(columns)
        if columns[: len(REQUIRED)] != REQUIRED:
            raise ValueError(f"trace: the columns must start with {', '.join(REQUIRED)}, got {columns}")
        if len(set(columns)) != len(columns):
            raise ValueError(f"trace: column names repeat: {columns}")
        if not 0 < flush_s <= 0.1:
            raise ValueError(f"trace: flush_s: expected 0 < flush_s <= 0.1 s, got {flush_s}")
        self.folder = Path(folder)
        self.axis = axis
        self.columns = columns
        self.meta = {str(k): _one_line(v) for k, v in (meta or {}).items()}
        self.flush_s = flush_s
        self.latest = latest
        self._stamp = stamp
        self._row_format = ",".join(FORMATS.get(c, "%.9g") for c in columns) + "\n"
        self._width = len(columns)
        self._ring_rows = block_rows
        self._free: collections.deque[_Block] = collections.deque(_Block(block_rows, len(columns))
                                                                  for _ in range(max(2, blocks)))
        self._blocks: collections.deque[_Block] = collections.deque()
        self._cur = self._free.popleft()
        self._cur.start = 0
        self._blocks.append(self._cur)
        self._i = 0  # next row in the current block
        self._count = 0  # rows published to the writer thread (written by the loop only)
        self._written = 0  # rows written to the file (written by the thread only)
        self._flushed = 0  # rows flushed to the kernel (written by the thread only)
        self.spilled = 0  # blocks allocated because the ring was full (a stalled disk)
        self.error: str | None = None
        self.path: Path | None = None  # the final name
        self.partial: Path | None = None
        self._file = None
        self._wake = threading.Event()
        self._stop = False
        self._thread: threading.Thread | None = None
        self.inline = inline
        self._lock = threading.Lock()  # inline: the loop and the idle-flush thread both write
        self._last_flush = time.monotonic()
        #: the row count at which append next looks at the clock (inline only; never otherwise)
        self._check_at = self.INLINE_CHECK_ROWS if inline else 1 << 62

    # --------------------------------------------------------------------------------- lifecycle
    def start(self) -> TraceWriter:
        """Create the ``.partial`` file with the header and the column row, and start the thread."""
        self.folder.mkdir(parents=True, exist_ok=True)
        stamp = self._stamp or datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
        for n in range(1, 10_000):
            stem = f"{self.axis}-{stamp}" + (f"-{n}" if n > 1 else "")
            final = self.folder / f"{stem}.csv"
            partial = self.folder / f"{stem}.csv{PARTIAL_SUFFIX}"
            if final.exists():
                continue
            try:
                fd = os.open(partial, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)  # the umask applies
            except FileExistsError:
                continue
            break
        else:
            raise TraceWriteError(f"{self.folder}: no free name for a trace of axis {self.axis}")
        self.path, self.partial = final, partial
        _OPEN_PARTIALS.add(partial.name)
        self._file = os.fdopen(fd, "w", encoding="utf-8", errors="backslashreplace", newline="\n")
        head = [MAGIC, *(f"# {k}: {v}" for k, v in self.meta.items()), f"# recording: {STREAMED}",
                ",".join(self.columns)]
        try:
            self._file.write("\n".join(head) + "\n")
            self._file.flush()
        except OSError as exc:
            self._fail(exc)
            self._close_file()
            raise TraceWriteError(f"{partial}: cannot write: {self.error}") from None
        self._thread = threading.Thread(target=self._run, name=f"trace-{self.axis}", daemon=True)
        self._thread.start()
        return self

    def __enter__(self) -> TraceWriter:
        return self.start() if self._file is None else self

    def __exit__(self, *exc: object) -> None:
        if self._file is not None:
            if exc[0] is None:
                self.close()
            else:
                self.abandon()

    # --------------------------------------------------------------------------------- the cycle
    def append(self, *values: float) -> None:
        """One row (one value per column, in order). Called from the loop's thread only; no I/O."""
        i = self._i
        if i == self._ring_rows:
            self._next_block()
            i = 0
        width = self._width
        if len(values) != width:  # a slice assignment of another length would resize the block
            raise ValueError(f"trace: append: expected {width} values (one per column), got {len(values)}")
        j = i * width
        self._cur.rows[j:j + width] = values
        self._i = i + 1
        self._count = count = self._count + 1  # publishes the row: the thread reads rows below _count only
        if count >= self._check_at:
            self._check_at = count + self.INLINE_CHECK_ROWS
            if time.monotonic() - self._last_flush >= self.flush_s:
                self._drain_locked()

    def extend(self, data: np.ndarray) -> None:
        """Many rows at once (``data`` of shape (rows, columns)): the whole-trace path."""
        data = np.asarray(data, dtype=float)
        if data.ndim != 2 or data.shape[1] != len(self.columns):
            raise ValueError(f"trace: extend: expected shape (rows, {len(self.columns)}), got {data.shape}")
        done = 0
        while done < len(data):
            if self._i == self._ring_rows:
                self._next_block()
            take = min(self._ring_rows - self._i, len(data) - done)
            w = self._width
            self._cur.rows[self._i * w : (self._i + take) * w] = data[done : done + take].ravel().tolist()
            self._i += take
            self._count += take
            done += take
            if self._i == self._ring_rows:
                self._wake.set()
        # a bulk writer may outrun the thread: wait for the ring to drain rather than spill
        while len(self._blocks) > 2 and self.error is None and self._thread is not None:
            self._wake.set()
            time.sleep(0.001)

    def _next_block(self) -> None:
        try:
            block = self._free.popleft()
        except IndexError:  # the thread is behind by the whole ring: never wait in the cycle
            block = _Block(self._ring_rows, len(self.columns))
            self.spilled += 1
        block.start = self._count
        self._blocks.append(block)  # before any of its rows is published
        self._cur = block
        self._i = 0
        if self.inline:
            self._drain_locked()  # the full block, on the loop's thread
        else:
            self._wake.set()

    def flush(self, timeout: float = 5.0) -> bool:
        """Wait until every row appended so far is written and flushed (not for the cycle: a sync point
        for tests and for the end of a phase). False on timeout or after a write error."""
        target = self._count
        if self.inline and self._thread is not None:
            self._drain_locked()
        deadline = time.monotonic() + timeout
        while self._written < target or self._flushed < target:
            if self.error is not None or self._thread is None or time.monotonic() > deadline:
                return False
            self._wake.set()
            time.sleep(0.001)
        return self.error is None

    @property
    def rows(self) -> int:
        """Rows appended so far."""
        return self._count

    # --------------------------------------------------------------------------------- the thread
    def _run(self) -> None:
        while True:
            if self.inline:  # only what an idle loop left: flush_s after the loop's last flush
                self._wake.wait(max(0.001, self._last_flush + self.flush_s - time.monotonic()))
                self._wake.clear()
                if self._stop:
                    return
                if time.monotonic() - self._last_flush >= self.flush_s:
                    self._drain_locked()
                continue
            self._wake.wait(self.flush_s)
            self._wake.clear()
            stop = self._stop
            self._drain()
            if stop:
                return

    def _drain_locked(self) -> None:
        with self._lock:
            self._drain()

    def _drain(self) -> None:
        """Write every published row not yet written, recycle the written blocks."""
        n = self._count
        blocks = self._blocks
        while blocks:
            b = blocks[0]
            end = min(n, b.start + self._ring_rows)
            if self._written < end:
                if self.error is None:
                    w = self._width
                    values = tuple(b.rows[(self._written - b.start) * w : (end - b.start) * w])
                    try:
                        self._file.write((self._row_format * (end - self._written)) % values)
                    except (OSError, ValueError) as exc:
                        self._fail(exc)
                self._written = end
            if end == b.start + self._ring_rows and len(blocks) > 1:
                blocks.popleft()  # full and written: the loop has moved on to a later block
                if len(self._free) < 8:  # spill blocks beyond a small ring are let go
                    self._free.append(b)
                continue
            break
        if self.error is None:
            try:
                self._file.flush()
                self._flushed = self._written
            except (OSError, ValueError) as exc:
                self._fail(exc)
        self._last_flush = time.monotonic()

    def _fail(self, exc: BaseException) -> None:
        if self.error is None:
            reason = os.strerror(exc.errno) if isinstance(exc, OSError) and exc.errno else str(exc)
            self.error = f"{reason} after {self._written} rows"

    # --------------------------------------------------------------------------------- the end
    def _join(self) -> None:
        if self._thread is not None:
            self._stop = True
            self._wake.set()
            self._thread.join()
            self._thread = None

    def close(self, trailer: Mapping[str, object] | None = None, *, complete: bool = True) -> Path:
        """Write the remaining rows, the trailer and the end marker; fsync; rename the ``.partial`` file to
        its final name (``complete=True``) and point ``AXIS.csv`` at it. Returns the path written.
        Raises TraceWriteError (the file kept as ``.partial``) when a write failed."""
        if self._file is None:
            raise TraceWriteError(f"trace {self.axis}: not started")
        self._join()
        self._drain()
        tail = dict(trailer or {})
        if self.spilled:
            tail["trace_spill_blocks"] = self.spilled
        if self.error is None:
            lines = [f"# {k}: {_one_line(v)}" for k, v in tail.items()]
            if complete:
                lines.append(END_MARKER)
            try:
                if lines:
                    self._file.write("\n".join(lines) + "\n")
                self._file.flush()
                os.fsync(self._file.fileno())
            except OSError as exc:
                self._fail(exc)
        self._close_file()
        if self.error is not None:
            raise TraceWriteError(f"{self.partial}: trace incomplete: {self.error}; the rows written before are "
                                  "kept")
        if not complete:
            return self.partial
        return self._publish()

    def abandon(self) -> Path | None:
        """Stop writing without a trailer, as a crash would (what was written stays, ``.partial``)."""
        if self._file is None:
            return self.partial
        self._join()
        self._drain()
        self._close_file()
        return self.partial

    def _close_file(self) -> None:
        if self._file is not None:
            try:
                self._file.close()
            except OSError as exc:
                self._fail(exc)
            self._file = None
            if self.partial is not None:
                _OPEN_PARTIALS.discard(self.partial.name)

    def _publish(self) -> Path:
        """``.partial`` -> its final name without replacing anything, then AXIS.csv -> it."""
        assert self.partial is not None and self.path is not None
        final = self.path
        for n in range(2, 10_000):
            try:
                os.link(self.partial, final)
                os.unlink(self.partial)
                break
            except FileExistsError:
                final = final.with_name(f"{self.path.stem}-{n}.csv")
            except OSError as exc:
                if exc.errno not in (errno.EPERM, errno.EOPNOTSUPP, errno.EXDEV, errno.EMLINK):
                    raise TraceWriteError(f"{self.partial}: cannot rename: {exc.strerror}") from None
                if final.exists():  # no hard links here: a rename that checks first (not atomic; rare)
                    final = final.with_name(f"{self.path.stem}-{n}.csv")
                    continue
                os.rename(self.partial, final)
                break
        self.path = final
        if self.latest:
            point_latest(final, self.folder / f"{self.axis}.csv")
        return final


def point_latest(target: Path, latest: Path) -> None:
    """Make ``latest`` (AXIS.csv) the same file as ``target``: a hard link swapped in atomically (a copy
    where links are not supported). A plain ``latest`` that is no other trace's name (an older
    version's, or the user's) is first kept under a stamped name, so no run overwrites a trace."""
    try:
        st = latest.lstat()
    except FileNotFoundError:
        st = None
    if st is not None and latest.is_file() and not latest.is_symlink() and st.st_nlink == 1:
        stamp = datetime.fromtimestamp(st.st_mtime, UTC).strftime("%Y%m%dT%H%M%SZ")
        for n in range(1, 10_000):
            keep = latest.with_name(f"{latest.stem}-{stamp}" + (f"-{n}" if n > 1 else "") + ".csv")
            try:
                os.link(latest, keep)
                break
            except FileExistsError:
                continue
            except OSError:
                shutil.copy2(latest, keep)
                break
    tmp = latest.with_name(f".{latest.name}.{os.getpid()}.latest.tmp")
    try:
        try:
            os.link(target, tmp)
        except FileExistsError:
            os.unlink(tmp)
            os.link(target, tmp)
        except OSError:
            shutil.copyfile(target, tmp)
        os.replace(tmp, latest)
    finally:
        if tmp.exists():
            os.unlink(tmp)


def write_trace(folder: str | Path, trace: object, *, latest: bool = True) -> Path:
    """Write a whole in-memory Trace through the streaming writer: a new name per run, ``AXIS.csv``
    pointed at it, the umask respected. The metadata stays in the header (it is known)."""
    from drivectl.tracefile.format import Trace

    assert isinstance(trace, Trace)
    axis = trace.meta.get("axis", "trace")
    names = list(REQUIRED) + [k for k in trace.columns if k not in REQUIRED]
    w = TraceWriter(folder, axis, columns=names, meta=trace.meta, latest=latest).start()
    try:
        data = np.column_stack([np.asarray(trace.columns[k], dtype=float) for k in names]) if len(trace) else \
            np.empty((0, len(names)))
        step = 65536
        for i in range(0, len(data), step):
            w.extend(data[i : i + step])
    except BaseException:
        w.abandon()
        raise
    return w.close()


def _one_line(value: object) -> str:
    from drivectl.tracefile.format import format_value

    return format_value(value).replace("\r", " ").replace("\n", " ")


def column_names(names: Iterable[str]) -> tuple[str, ...]:
    """The required four first, then the others in their order."""
    names = list(names)
    return tuple(REQUIRED) + tuple(n for n in names if n not in REQUIRED)


def amend_trailer(path: str | Path, updates: Mapping[str, str]) -> None:
    """Rewrite the trailer of a streamed trace that is already closed (docs/trace-format.md: ``# key: value``
    lines after the data, then the end marker) with ``updates`` merged in: the verdict of :func:`assess`
    is known only after the run's writer closed its file. In place (``AXIS.csv`` is a hard link to the
    same file); only the trailer is rewritten, the rows stay as they are."""
    with open(path, "r+b") as f:
        size = f.seek(0, os.SEEK_END)
        tail_start = max(0, size - 65536)  # the trailer is a few lines; 64 KiB holds it many times over
        f.seek(tail_start)
        tail = f.read()
        lines = tail.split(b"\n")
        if lines and lines[-1] == b"":
            lines.pop()
        # walk back over the trailer (comment lines) to the last data row
        i = len(lines)
        while i > 0 and lines[i - 1].startswith(b"#"):
            i -= 1
        if i == 0 and tail_start > 0:
            raise ValueError(f"{path}: trailer longer than 64 KiB")
        if i == 0:
            return  # a file with no data row: nothing streamed, nothing to amend
        offset = tail_start + sum(len(line) + 1 for line in lines[:i])
        trailer: dict[str, str] = {}
        for line in lines[i:]:
            text = line.decode("utf-8", "replace").lstrip("#").strip()
            if text == END_MARKER.lstrip("#").strip() or ":" not in text:
                continue
            key, _, value = text.partition(":")
            trailer[key.strip()] = value.strip()
        ended = any(line.strip() == END_MARKER.encode() for line in lines[i:])
        trailer.update({k: " ".join(str(v).split()) for k, v in updates.items()})
        out = [f"# {k}: {v}" for k, v in trailer.items()] + ([END_MARKER] if ended else [])
        f.seek(offset)
        f.truncate()
        f.write(("\n".join(out) + "\n").encode())
        f.flush()
        os.fsync(f.fileno())

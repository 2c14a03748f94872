"""A CAN log as chunks of arrays: (timestamp, COB-ID, length, data), read in bounded memory.

Two readers give the same chunks (tests/test_buslog.py checks they are identical):

- the reference: python-can's :class:`can.LogReader` (every suffix it reads), its Messages packed into arrays;
- the fast path, for the formats where LogReader is the bottleneck (candump ``.log``, Vector ``.asc`` in hex,
  ``.blf``; measured in docs/guide/buslog.md): text cut into blocks of whole lines and parsed with numpy
  (tools/buslog/fast_text.py), BLF containers inflated and their objects' fields read with numpy
  (tools/buslog/fast_blf.py); never one Message per frame. A text block the
  fast parser does not recognise line for line (CAN FD, a remote or error frame, an odd line) is handed to
  python-can's own reader for that format, so nothing is guessed; a decimal ``.asc`` is read by LogReader.

A frame CANopen does not use here (extended or remote, an error frame, CAN FD) keeps its place with COB-ID
-1: it is counted, never decoded. A log that ends early (a killed recorder) is read as far as it goes and
:attr:`Reading.truncated` says where.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import can
import numpy as np

CHUNK_FRAMES = 65536


@dataclass(frozen=True)
class Frames:
    """One chunk of frames in log order."""

    t: np.ndarray  # float64, s, as python-can reads the log's stamps
    cob: np.ndarray  # int32 11-bit COB-ID; -1: a frame not read here (extended, remote, error, FD)
    dlc: np.ndarray  # uint8 data length in bytes
    data: np.ndarray  # uint8 (n, 8), zero past the length

    def __len__(self) -> int:
        return len(self.t)


@dataclass
class Reading:
    """What reading a log found: how many frames, by which reader, and whether it ended early."""

    path: Path
    reader: str = ""  # "numpy (candump .log)" / "python-can LogReader (.blf)" ...
    frames: int = 0
    truncated: str | None = None  # why the reading stopped before the log's end
    notes: list[str] = field(default_factory=list)


def _pack(t: list[float], cob: list[int], dlc: list[int], data: list[bytes]) -> Frames:
    raw = np.frombuffer(b"".join(data), np.uint8).reshape(-1, 8) if data else np.zeros((0, 8), np.uint8)
    return Frames(np.asarray(t, np.float64), np.asarray(cob, np.int32), np.asarray(dlc, np.uint8), raw)


def messages_to_frames(messages: Iterator[can.Message], reading: Reading, chunk: int = CHUNK_FRAMES,
                       ) -> Iterator[Frames]:
    """Pack python-can Messages into chunks (the reference path, and the fast path's fallback)."""
    t: list[float] = []
    cob: list[int] = []
    dlc: list[int] = []
    data: list[bytes] = []
    for msg in messages:
        reading.frames += 1
        t.append(msg.timestamp)
        plain = not (msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id or msg.is_fd)
        cob.append(msg.arbitration_id if plain else -1)
        payload = bytes(msg.data or b"")[:8] if plain else b""
        dlc.append(len(payload))
        data.append(payload.ljust(8, b"\0"))
        if len(t) >= chunk:
            yield _pack(t, cob, dlc, data)
            t, cob, dlc, data = [], [], [], []
    if t:
        yield _pack(t, cob, dlc, data)


def first_error_line(exc: BaseException) -> str:
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]


def guarded(messages: Iterator[can.Message], reading: Reading, path: Path) -> Iterator[can.Message]:
    """``messages`` until the reader fails: a failure after the first frame is a truncated log (the frames before
    it are kept and :attr:`Reading.truncated` says where), before it a file that is no log (one line)."""
    from drivectl.tools.buslog.convert import BusLogError

    before = reading.frames
    try:
        yield from messages
    except Exception as exc:  # the readers raise their parsers' own errors on garbage or a cut-off file
        if reading.frames == before == 0:
            raise BusLogError(f"{path}: not a readable {path.suffix} CAN log: {first_error_line(exc)}") from None
        reading.truncated = f"unreadable after frame {reading.frames} ({first_error_line(exc)})"


def read_reference(path: Path, reading: Reading, progress: object = None) -> Iterator[Frames]:
    """Chunks through python-can's LogReader (the reference reader, every suffix it knows)."""
    from drivectl.tools.buslog.convert import BusLogError

    reading.reader = f"python-can LogReader ({path.suffix.lower()})"
    try:
        reader = can.LogReader(str(path))
    except Exception as exc:
        raise BusLogError(f"{path}: not a readable {path.suffix} CAN log: {first_error_line(exc)}") from None
    with reader:
        for frames in messages_to_frames(guarded(iter(reader), reading, path), reading):
            if progress is not None:
                progress.update(len(frames))
            yield frames
        header_size = getattr(reader, "file_size", None)  # a BLF's header, written when the recorder closes it
        if isinstance(reader, can.BLFReader) and header_size != os.path.getsize(path) and not reading.truncated:
            reading.truncated = (f"the BLF header gives {header_size} bytes, the file has {os.path.getsize(path)} "
                                 f"(a recorder that did not close it; {reading.frames} frames read)")


def split(frames: Frames, chunk: int) -> Iterator[Frames]:
    for i in range(0, len(frames), chunk):
        yield Frames(frames.t[i : i + chunk], frames.cob[i : i + chunk], frames.dlc[i : i + chunk],
                     frames.data[i : i + chunk])


def fast_path_reads(path: Path) -> bool:
    """Whether a fast reader reads this log (a candump .log, a .asc in hex: tools/buslog/fast_text.py; a .blf:
    tools/buslog/fast_blf.py)."""
    suffix = path.suffix.lower()
    if suffix == ".log":
        with open(path, "rb") as f:
            first = f.read(1).lstrip()
        return first in (b"(", b"")
    if suffix == ".asc":
        from drivectl.tools.buslog.fast_text import asc_header

        return asc_header(path)[2]
    return suffix == ".blf"


def read_frames(path: Path, reading: Reading, *, fast: bool | None = None, progress: bool = False,
                ) -> Iterator[Frames]:
    """The frames of the log at ``path`` in chunks. ``fast``: None picks the numpy reader where it reads the
    format, True insists (where it cannot, the reference), False is python-can's LogReader. ``progress``: a
    tqdm bar on stderr (where stderr is a terminal)."""
    from tqdm import tqdm

    use_fast = fast is not False and fast_path_reads(path)
    size = os.path.getsize(path)
    bar = tqdm(total=size if use_fast else None, unit="B" if use_fast else " frames", unit_scale=True,
               desc=path.name, leave=False, disable=None if progress else True)
    try:
        if not use_fast:
            gen = read_reference(path, reading, bar)
        elif path.suffix.lower() == ".blf":
            from drivectl.tools.buslog.fast_blf import read_blf_fast

            gen = read_blf_fast(path, reading, bar)
        else:
            from drivectl.tools.buslog.fast_text import read_fast

            gen = read_fast(path, reading, bar)
        yield from gen
    finally:
        bar.close()

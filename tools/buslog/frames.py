"""A CAN log as chunks of arrays: (timestamp, COB-ID, length, data), read in bounded memory.

Two readers give the same chunks (tests/test_buslog.py checks they are identical):

- the reference: python-can's :class:`can.LogReader` (every suffix it reads), its Messages packed into arrays;
- the fast path, for the formats where LogReader is the bottleneck (candump ``.log``, Vector ``.asc`` in hex,
  ``.blf``; measured in docs/guide/buslog.md): text cut into blocks of whole lines and parsed with numpy, BLF
  containers inflated and their objects' fields read with numpy; never one Message per frame. A text block the
  fast parser does not recognise line for line (CAN FD, a remote or error frame, an odd line) is handed to
  python-can's own reader for that format, so nothing is guessed; a decimal ``.asc`` is read by LogReader.

A frame CANopen does not use here (extended or remote, an error frame, CAN FD) keeps its place with COB-ID
-1: it is counted, never decoded. A log that ends early (a killed recorder) is read as far as it goes and
:attr:`Reading.truncated` says where.
"""

from __future__ import annotations

import io
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import can
import numpy as np

CHUNK_FRAMES = 65536
_BLOCK_BYTES = 4 << 20
#: hex digit value of each byte, -1 for a byte that is no hex digit
_HEX = np.full(256, -1, np.int16)
for _c in b"0123456789":
    _HEX[_c] = _c - 48
for _c in b"abcdef":
    _HEX[_c] = _c - 87
    _HEX[_c - 32] = _c - 87


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


def _first_error_line(exc: BaseException) -> str:
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]


def _guarded(messages: Iterator[can.Message], reading: Reading, path: Path) -> Iterator[can.Message]:
    """``messages`` until the reader fails: a failure after the first frame is a truncated log (the frames before
    it are kept and :attr:`Reading.truncated` says where), before it a file that is no log (one line)."""
    from drivectl.tools.buslog.convert import BusLogError

    before = reading.frames
    try:
        yield from messages
    except Exception as exc:  # the readers raise their parsers' own errors on garbage or a cut-off file
        if reading.frames == before == 0:
            raise BusLogError(f"{path}: not a readable {path.suffix} CAN log: {_first_error_line(exc)}") from None
        reading.truncated = f"unreadable after frame {reading.frames} ({_first_error_line(exc)})"


def read_reference(path: Path, reading: Reading, progress: object = None) -> Iterator[Frames]:
    """Chunks through python-can's LogReader (the reference reader, every suffix it knows)."""
    from drivectl.tools.buslog.convert import BusLogError

    reading.reader = f"python-can LogReader ({path.suffix.lower()})"
    try:
        reader = can.LogReader(str(path))
    except Exception as exc:
        raise BusLogError(f"{path}: not a readable {path.suffix} CAN log: {_first_error_line(exc)}") from None
    with reader:
        for frames in messages_to_frames(_guarded(iter(reader), reading, path), reading):
            if progress is not None:
                progress.update(len(frames))
            yield frames
        header_size = getattr(reader, "file_size", None)  # a BLF's header, written when the recorder closes it
        if isinstance(reader, can.BLFReader) and header_size != os.path.getsize(path) and not reading.truncated:
            reading.truncated = (f"the BLF header gives {header_size} bytes, the file has {os.path.getsize(path)} "
                                 f"(a recorder that did not close it; {reading.frames} frames read)")


# -- the fast path: text formats parsed with numpy --------------------------------------------------------------
def _lines(block: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(start, end) of each line of ``block`` (end excludes the newline and a carriage return)."""
    nl = np.flatnonzero(block == 10)
    starts = np.empty(len(nl), np.int64)
    starts[0:1] = 0
    starts[1:] = nl[:-1] + 1
    ends = nl.copy()
    cr = ends > starts
    cr[cr] = block[ends[cr] - 1] == 13
    ends[cr] -= 1
    return starts, ends


def _rows(block: np.ndarray, starts: np.ndarray, width: int) -> np.ndarray | None:
    """(n, width) bytes from each start, rows copied whole (None where a row would run past the block)."""
    if int(starts.max()) + width > len(block):
        return None
    return np.lib.stride_tricks.as_strided(block, shape=(len(block) - width + 1, width), strides=(1, 1),
                                           writeable=False)[starts]


def _decimal(m: np.ndarray, a: int, b: int) -> np.ndarray | None:
    """The decimal numbers ``d+.d+`` in columns a..b of every row, as Python's float() reads them: an exact
    integer over an exact power of ten (IEEE division rounds it once, as float() rounds the text)."""
    first = m[0, a:b].tobytes()
    dot = first.find(b".")
    if dot < 1 or dot == len(first) - 1 or b - a - 1 > 16 or (m[:, a + dot] != 46).any():
        return None
    digits = np.concatenate([m[:, a : a + dot], m[:, a + dot + 1 : b]], axis=1).astype(np.int64) - 48
    if ((digits < 0) | (digits > 9)).any():
        return None
    weights = 10 ** np.arange(digits.shape[1] - 1, -1, -1, dtype=np.int64)
    return (digits @ weights) / float(10 ** (b - a - dot - 1))


def _candump_block(block: np.ndarray) -> Frames | None:
    """candump -L lines ``(stamp) iface ID#DATA [T|R]``; None where a line is not that (the caller falls back).

    A log has a handful of line shapes (one per ID length and data length), and lines of one length have their
    fields at the same columns: the lines of each length are gathered into one byte matrix, the columns of the
    first line's fields checked on every line, and each field parsed a column at a time."""
    starts, ends = _lines(block)
    length = ends - starts
    keep = length > 0
    starts, length = starts[keep], length[keep]
    n = len(starts)
    if not n:
        return None
    t = np.empty(n)
    cob = np.empty(n, np.int64)
    dlc = np.zeros(n, np.uint8)
    data = np.zeros((n, 8), np.uint8)
    order = np.argsort(length, kind="stable")
    bounds = np.flatnonzero(np.diff(length[order])) + 1
    for rows in np.split(order, bounds):
        width = int(length[rows[0]])
        if width > 96 or width < 8:
            return None
        m = _rows(block, starts[rows], width)
        if m is None:
            return None
        first = m[0].tobytes()
        c, h = first.find(b")"), first.find(b"#")
        d = first.find(b".", 0, c)
        s = first.rfind(b" ", 0, h)
        e = first.find(b" ", h)
        e = width if e < 0 else e
        if min(c, h, d, s) < 1 or not d < c < s < h or first[0] != 40:
            return None
        fixed = [(0, 40), (c, 41), (d, 46), (h, 35), (s, 32)] + ([(e, 32)] if e < width else [])
        if any((m[:, col] != ch).any() for col, ch in fixed):
            return None
        if (m[:, h + 1 : e] == 35).any():
            return None  # CAN FD (##)
        ts = _decimal(m, 1, c)
        if ts is None:
            return None
        t[rows] = ts
        nid = h - s - 1
        idn = _HEX[m[:, s + 1 : h]].astype(np.int64)
        if (idn < 0).any() or not 1 <= nid <= 8:
            return None
        cob[rows] = idn @ (16 ** np.arange(nid - 1, -1, -1, dtype=np.int64)) if nid <= 3 else -1
        nd = e - h - 1
        if nd > 0 and (m[:, h + 1] | 32 == ord("r")).any():
            if not (m[:, h + 1] | 32 == ord("r")).all():
                return None
            cob[rows] = -1  # remote frames
            continue
        if nd % 2 or nd > 16:
            return None
        nib = _HEX[m[:, h + 1 : e]]
        if (nib < 0).any():
            return None
        nib = nib.astype(np.uint8)
        data[rows, : nd // 2] = (nib[:, 0::2] << 4) | nib[:, 1::2]
        dlc[rows] = nd // 2
    return Frames(t, cob.astype(np.int32), dlc, data)


def _asc_block(block: np.ndarray) -> Frames | None:
    """Vector ASC lines in hex, ``stamp channel ID Rx|Tx d DLC b0 .. b7 [...]``: the lines of each length, whose
    tokens (checked on every line) stand at the same columns, parsed a column at a time. Lines python-can's
    reader skips (no stamp, or no Rx/Tx) are skipped; a remote, error or FD frame gives None (the caller
    falls back to python-can's reader for the block)."""
    import re

    starts, ends = _lines(block)
    length = ends - starts
    keep = length > 0
    starts, length = starts[keep], length[keep]
    n = len(starts)
    t = np.empty(n)
    cob = np.empty(n, np.int64)
    dlc = np.zeros(n, np.uint8)
    data = np.zeros((n, 8), np.uint8)
    frame = np.zeros(n, bool)
    order = np.argsort(length, kind="stable")
    bounds = np.flatnonzero(np.diff(length[order])) + 1
    for rows in np.split(order, bounds) if n else []:
        width = int(length[rows[0]])
        m = _rows(block, starts[rows], width)
        if m is None:
            return None
        first = m[0].tobytes()
        toks = [(x.start(), x.end()) for x in re.finditer(rb"[^ \t]+", first)]
        blank = np.ones(width, bool)
        for a, b in toks:
            blank[a:b] = False
        if not np.array_equal((m == 32) | (m == 9), np.broadcast_to(blank, m.shape)):
            return None  # lines of one length but other columns: python-can's reader for this block
        words = [first[a:b] for a, b in toks]
        stamped = bool(re.fullmatch(rb"\d+\.\d+", words[0])) if words else False
        if stamped and (m[:, toks[0][0]] < 48).any() | (m[:, toks[0][0]] > 57).any():
            return None
        if not stamped:
            if words and words[0][:1].isdigit():
                return None  # a stamp in some lines of the group and not in others
            continue  # a line python-can's reader skips (End TriggerBlock, comments)
        if len(words) > 1 and words[1].upper() == b"CANFD":
            return None
        if len(words) < 4 or not words[1].isdigit():
            if len(words) > 1 and words[1][:1].isdigit():
                return None
            continue  # "Start of measurement", statistics: skipped by python-can
        if words[2].lower().startswith(b"errorframe"):
            return None
        if words[3].lower() not in (b"rx", b"tx"):
            continue  # python-can's reader takes only Rx/Tx lines
        if len(words) < 6 or words[4][:1].lower() == b"r":
            return None  # a remote frame, or a line of another shape
        # on every line of the group: a channel of digits, Rx or Tx, a data frame ("d")
        a, b = toks[1]
        if ((m[:, a:b] < 48) | (m[:, a:b] > 57)).any():
            return None
        a, b = toks[3]
        if b - a != 2 or not (((m[:, a] | 32 == ord("r")) | (m[:, a] | 32 == ord("t"))) &
                              (m[:, a + 1] | 32 == ord("x"))).all():
            return None
        a, b = toks[4]
        if (m[:, a:b] != np.frombuffer(words[4], np.uint8)).any():
            return None
        ts = _decimal(m, *toks[0])
        if ts is None:
            return None
        a, b = toks[2]
        ext = words[2][-1:].lower() == b"x"
        idn = _HEX[m[:, a : b - 1 if ext else b]].astype(np.int64)
        if (idn < 0).any() or idn.shape[1] > 8:
            return None
        a5, b5 = toks[5]
        if b5 - a5 != 1:
            return None
        d = _HEX[m[:, a5]]
        if (d < 0).any() or (d != d[0]).any() or d[0] > 8 or len(toks) < 6 + d[0]:
            return None
        nd = int(d[0])
        for k in range(nd):
            a, b = toks[6 + k]
            if b - a != 2:
                return None
            v = _HEX[m[:, a:b]]
            if (v < 0).any():
                return None
            data[rows, k] = (v[:, 0] << 4) | v[:, 1]
        t[rows] = ts
        cob[rows] = -1 if ext else idn @ (16 ** np.arange(idn.shape[1] - 1, -1, -1, dtype=np.int64))
        dlc[rows] = nd
        frame[rows] = True
    return Frames(t[frame], cob[frame].astype(np.int32), dlc[frame], data[frame])


def _split(frames: Frames, chunk: int) -> Iterator[Frames]:
    for i in range(0, len(frames), chunk):
        yield Frames(frames.t[i : i + chunk], frames.cob[i : i + chunk], frames.dlc[i : i + chunk],
                     frames.data[i : i + chunk])


def _asc_header(path: Path) -> tuple[bytes, int, bool]:
    """(the header lines, their length in bytes, whether the fast path reads this .asc: base hex)."""
    with open(path, "rb") as f:
        head = f.read(1 << 16)
    lines = head.splitlines(keepends=True)
    out, hex_base = b"", True
    for line in lines:
        low = line.strip().lower()
        if low.startswith(b"base"):
            hex_base = low.split()[1:2] == [b"hex"]
        if low and (low[:1].isdigit()):
            break
        out += line
        if low.startswith(b"begin triggerblock"):
            break
    return out, len(out), hex_base


def read_fast(path: Path, reading: Reading, progress: object = None) -> Iterator[Frames]:
    """Chunks of a candump .log or a hex .asc parsed with numpy (see the module docstring)."""
    from drivectl.tools.buslog.convert import BusLogError

    asc = path.suffix.lower() == ".asc"
    reading.reader = f"numpy ({'Vector .asc' if asc else 'candump .log'})"
    header, skip, _ = _asc_header(path) if asc else (b"", 0, True)
    parse = _asc_block if asc else _candump_block
    reader_cls = can.ASCReader if asc else can.CanutilsLogReader
    fallback_blocks = 0
    tail_ok = not asc
    with open(path, "rb") as f:
        f.seek(skip)
        rest = b""
        while True:
            raw = f.read(_BLOCK_BYTES)
            if progress is not None:
                progress.update(len(raw))
            if not raw:
                text = rest
                rest = b""
            else:
                text = rest + raw
                cut = text.rfind(b"\n") + 1
                text, rest = text[:cut], text[cut:]
                if not text:
                    continue
            if not text:
                break
            if not text.endswith(b"\n"):
                text += b"\n"  # the last line of a log written without a final newline
                last_unterminated = True
            else:
                last_unterminated = False
            if asc and b"end triggerblock" in text[-64:].lower():
                tail_ok = True
            block = np.frombuffer(text, np.uint8)
            frames = parse(block)
            if frames is None:
                # python-can's own reader for this block (it needs the .asc header for base and stamps)
                fallback_blocks += 1
                src = io.StringIO((header + text).decode("utf-8", "replace")) if asc else \
                    io.StringIO(text.decode("utf-8", "replace"))
                try:
                    msgs = iter(reader_cls(src))
                    got = list(messages_to_frames(_guarded(msgs, reading, path), reading, chunk=1 << 30))
                except BusLogError:
                    raise
                for fr in got:
                    yield from _split(fr, CHUNK_FRAMES)
                if reading.truncated:
                    return
            else:
                reading.frames += len(frames)
                yield from _split(frames, CHUNK_FRAMES)
            if last_unterminated and raw == b"":
                reading.truncated = f"the last line has no end (cut off after frame {reading.frames})"
            if not raw:
                break
    if fallback_blocks:
        reading.notes.append(f"{fallback_blocks} block(s) read by python-can's reader (lines the fast parser "
                             "does not take)")
    if asc and not tail_ok and reading.frames:
        reading.truncated = f"no 'End TriggerBlock' (the recorder did not close the log; {reading.frames} frames)"


# -- the fast path for BLF: the objects walked in Python, their fields read with numpy --------------------------
_BLF_BASE = np.dtype([("sig", "S4"), ("header_size", "<u2"), ("header_version", "<u2"), ("obj_size", "<u4"),
                      ("obj_type", "<u4")])
_BLF_MSG = [("channel", "<u2"), ("msg_flags", "u1"), ("dlc", "u1"), ("id", "<u4"), ("data", "u1", (8,))]
#: a CAN message object with header version 1 (48 bytes) and 2 (56 bytes), as Vector's BLF lays them out
_BLF_V1 = np.dtype(_BLF_BASE.descr + [("flags", "<u4"), ("client", "<u2"), ("version", "<u2"), ("ts", "<u8")]
                   + _BLF_MSG)
_BLF_V2 = np.dtype(_BLF_BASE.descr + [("flags", "<u4"), ("ts_status", "u1"), ("pad", "u1"), ("version", "<u2"),
                                      ("ts", "<u8"), ("orig_ts", "<u8")] + _BLF_MSG)
_BLF_CAN = (1, 86)  # CAN_MESSAGE, CAN_MESSAGE2
_BLF_OTHER_FRAMES = (73, 100, 101)  # error frame, CAN FD, CAN FD 64: frames python-can reads, not decoded here
_BLF_CONTAINER = 10


def _blf_objects(data: bytes, start_ts: float) -> tuple[Frames, int]:
    """The frames of one container's objects (``data``: the container's bytes after the last one's tail), and
    where the first object that continues in the next container starts."""
    import struct

    unpack = struct.Struct("<4sHHLL").unpack_from
    pos, end = 0, len(data)
    at: list[int] = []
    kind: list[int] = []  # 1: CAN v1, 2: CAN v2, 0: another frame python-can reads
    while True:
        p = data.find(b"LOBJ", pos, pos + 8)
        if p < 0:
            if pos + 8 > end:
                break
            raise ValueError("BLF: could not find the next object")
        if p + 16 > end:
            break
        _, _, version, size, otype = unpack(data, p)
        if p + size > end:
            break  # it continues in the next container
        if version in (1, 2):
            if otype in _BLF_CAN:
                at.append(p)
                kind.append(version)
            elif otype in _BLF_OTHER_FRAMES:
                at.append(p)
                kind.append(0)
        pos = p + size
    buf = np.frombuffer(data, np.uint8)
    n = len(at)
    t = np.empty(n)
    cob = np.full(n, -1, np.int64)
    dlc = np.zeros(n, np.uint8)
    out = np.zeros((n, 8), np.uint8)
    ats, kinds = np.asarray(at, np.int64), np.asarray(kind, np.int8)
    for version, dtype in ((1, _BLF_V1), (2, _BLF_V2)):
        rows = np.flatnonzero(kinds == version)
        if not len(rows):
            continue
        m = _rows(buf, ats[rows], dtype.itemsize)
        if m is None:
            raise ValueError("BLF: an object runs past its container")
        rec = np.ascontiguousarray(m).view(dtype).ravel()
        # python-can: the stamp's integer times 1e-5 or 1e-9, exactly (Decimal), then float, plus the start:
        # an exact integer over an exact power of ten rounds the same
        t[rows] = rec["ts"].astype(np.float64) / np.where(rec["flags"] == 1, 1e5, 1e9) + start_ts
        plain = (rec["id"] & 0x80000000 == 0) & (rec["msg_flags"] & 0x80 == 0)
        cob[rows] = np.where(plain, rec["id"] & 0x1FFFFFFF, -1)
        n_data = np.minimum(rec["dlc"], 8)
        dlc[rows] = np.where(plain, n_data, 0)
        keep = np.arange(8)[None, :] < dlc[rows][:, None]
        out[rows] = np.where(keep, rec["data"], 0)
    other = np.flatnonzero(kinds == 0)
    for i in other.tolist():  # error and FD frames: rare; their stamps as python-can reads them
        p = at[i]  # both header versions: flags at +16, the stamp at +24
        flags = int.from_bytes(data[p + 16 : p + 20], "little")
        ts = int.from_bytes(data[p + 24 : p + 32], "little")
        t[i] = ts / (1e5 if flags == 1 else 1e9) + start_ts
    return Frames(t, cob.astype(np.int32), dlc, out), pos


def read_blf_fast(path: Path, reading: Reading, progress: object = None) -> Iterator[Frames]:
    """Chunks of a BLF: python-can's BLFReader reads the file header (start time, declared size), the containers
    are inflated one by one and their objects walked, the frames' fields read a column at a time."""
    import struct
    import zlib

    from drivectl.tools.buslog.convert import BusLogError

    reading.reader = "numpy (.blf)"
    try:
        header = can.BLFReader(str(path))
    except Exception as exc:
        raise BusLogError(f"{path}: not a readable {path.suffix} CAN log: {_first_error_line(exc)}") from None
    with header:
        f = header.file
        start_ts = header.start_timestamp
        declared = header.file_size
        unpack = struct.Struct("<4sHHLL").unpack
        tail = b""
        try:
            while True:
                head = f.read(16)
                if len(head) < 16:
                    break
                sig, _, _, size, otype = unpack(head)
                if sig != b"LOBJ":
                    raise ValueError("BLF: an object without its LOBJ signature")
                body = f.read(size - 16)
                f.read(size % 4)
                if progress is not None:
                    progress.update(size)
                if otype != _BLF_CONTAINER:
                    continue
                method = int.from_bytes(body[:2], "little")
                raw = body[16:]
                if method == 2:
                    raw = zlib.decompressobj().decompress(raw)
                elif method != 0:
                    continue
                data = tail + raw
                frames, used = _blf_objects(data, start_ts)
                tail = data[used:]
                if len(frames):
                    reading.frames += len(frames)
                    yield from _split(frames, CHUNK_FRAMES)
        except (ValueError, zlib.error, struct.error) as exc:
            if not reading.frames:
                raise BusLogError(f"{path}: not a readable {path.suffix} CAN log: {exc}") from None
            reading.truncated = f"unreadable after frame {reading.frames} ({exc})"
            return
    if declared != os.path.getsize(path):
        reading.truncated = (f"the BLF header gives {declared} bytes, the file has {os.path.getsize(path)} "
                             f"(a recorder that did not close it; {reading.frames} frames read)")


def fast_path_reads(path: Path) -> bool:
    """Whether a fast reader reads this log (a candump .log, a .asc in hex: :func:`read_fast`; a .blf:
    :func:`read_blf_fast`)."""
    suffix = path.suffix.lower()
    if suffix == ".log":
        with open(path, "rb") as f:
            first = f.read(1).lstrip()
        return first in (b"(", b"")
    if suffix == ".asc":
        return _asc_header(path)[2]
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
            gen = read_blf_fast(path, reading, bar)
        else:
            gen = read_fast(path, reading, bar)
        yield from gen
    finally:
        bar.close()

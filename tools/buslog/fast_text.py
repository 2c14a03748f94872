"""The fast reader of the text logs: candump ``.log`` and Vector ``.asc`` in hex, parsed with numpy.

The text is cut into blocks of whole lines. A log has a handful of line shapes (one per ID length and data
length), and lines of one length have their fields at the same columns: the lines of each length are gathered
into one byte matrix (rows copied whole), the columns of the first line's fields checked on every line, and each
field parsed a column at a time. A block with a line that is not of the shapes parsed here (CAN FD, a remote or
error frame, an odd line) is handed to python-can's own reader for that format (tools/buslog/frames.py, the
reference), so nothing is guessed. The chunks are those of :func:`~drivectl.tools.buslog.frames.read_frames`.
"""

from __future__ import annotations

import io
from collections.abc import Iterator
from pathlib import Path

import can
import numpy as np

from drivectl.tools.buslog.frames import (
    CHUNK_FRAMES,
    Frames,
    Reading,
    guarded,
    messages_to_frames,
    split,
)

_BLOCK_BYTES = 4 << 20
_HEX = np.full(256, -1, np.int16)
for _c in b"0123456789":
    _HEX[_c] = _c - 48
for _c in b"abcdef":
    _HEX[_c] = _c - 87
    _HEX[_c - 32] = _c - 87

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


def rows_of(block: np.ndarray, starts: np.ndarray, width: int) -> np.ndarray | None:
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
        m = rows_of(block, starts[rows], width)
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
        m = rows_of(block, starts[rows], width)
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


def asc_header(path: Path) -> tuple[bytes, int, bool]:
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
    header, skip, _ = asc_header(path) if asc else (b"", 0, True)
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
                    got = list(messages_to_frames(guarded(msgs, reading, path), reading, chunk=1 << 30))
                except BusLogError:
                    raise
                for fr in got:
                    yield from split(fr, CHUNK_FRAMES)
                if reading.truncated:
                    return
            else:
                reading.frames += len(frames)
                yield from split(frames, CHUNK_FRAMES)
            if last_unterminated and raw == b"":
                reading.truncated = f"the last line has no end (cut off after frame {reading.frames})"
            if not raw:
                break
    if fallback_blocks:
        reading.notes.append(f"{fallback_blocks} block(s) read by python-can's reader (lines the fast parser "
                             "does not take)")
    if asc and not tail_ok and reading.frames:
        reading.truncated = f"no 'End TriggerBlock' (the recorder did not close the log; {reading.frames} frames)"

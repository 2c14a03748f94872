"""The fast reader of BLF logs: python-can's BLFReader reads the file header, the containers are inflated one by
one, their objects walked in Python (a few hundred nanoseconds each) and the frames' fields read with numpy.
The same frames as python-can's reader, stamp for stamp (tests/test_buslog.py): the chunks of
:func:`~drivectl.tools.buslog.frames.read_frames`.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import can
import numpy as np

from drivectl.tools.buslog.fast_text import rows_of
from drivectl.tools.buslog.frames import CHUNK_FRAMES, Frames, Reading, first_error_line, split

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
        m = rows_of(buf, ats[rows], dtype.itemsize)
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
        raise BusLogError(f"{path}: not a readable {path.suffix} CAN log: {first_error_line(exc)}") from None
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
                    yield from split(frames, CHUNK_FRAMES)
        except (ValueError, zlib.error, struct.error) as exc:
            if not reading.frames:
                raise BusLogError(f"{path}: not a readable {path.suffix} CAN log: {exc}") from None
            reading.truncated = f"unreadable after frame {reading.frames} ({exc})"
            return
    if declared != os.path.getsize(path):
        reading.truncated = (f"the BLF header gives {declared} bytes, the file has {os.path.getsize(path)} "
                             f"(a recorder that did not close it; {reading.frames} frames read)")

"""Bus logs in at length (issue 35 point 8): a 10-minute three-axis log at 1 kHz turned into a trace.

The log is made here, in a temporary folder: the bring-up of the embedded three-axis machine as drivectl's own
``--bus-log`` recorded it (a short real run on the emulated drives: NMT, the SDO writes of 0x1006 and of every
PDO's configuration), then ``--seconds`` of cyclic traffic at 1 kHz generated in the same candump format: per
cycle a SYNC and, for each of the three nodes, the compact mapping the bring-up configured (three axes at
1 kHz do not fit the full one under the bus-load ceiling): TPDO1 (statusword + position + torque actual) and
RPDO1 (controlword + target torque), the position a sine: 7 frames a cycle, 4.2 M frames in 10 minutes.
``drivectl trace --from-log`` of axis x is then run on it in a fresh process (wall time after the imports, and
peak RSS of that process: ru_maxrss), and the trace's rows are checked against the cycles generated.

The table also measures each reader alone on the first ``--reader-frames`` frames of the same traffic written
in every format python-can writes (python-can's LogReader, and the numpy reader where it reads the format),
which is where the fast path was found to be needed (docs/guide/buslog.md).

    python bench/buslog.py [--seconds 600] [--reader-frames 200000] [--json]

``--json`` prints exactly one JSON object: {"frames", "seconds", "frames_per_s", "peak_rss_mb"} of the
conversion (frames: of the whole log; seconds: the conversion's wall time).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

NODES = (1, 2, 3)
CYCLE_S = 0.001
CHUNK_CYCLES = 20000

CHILD = """
import contextlib, io, resource, sys, time
from pathlib import Path
from drivectl.tools.buslog import log_to_trace
def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime
t0, c0 = time.perf_counter(), cpu()
path = log_to_trace(Path(sys.argv[1]), axis="x", out_dir=Path(sys.argv[2]))
dt, dc = time.perf_counter() - t0, cpu() - c0
rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # the conversion's peak, before the check reads
from drivectl.tracefile.format import Trace
tr = Trace.read(path, columns=("lost",))
print(dt, dc, rss, len(tr), tr.meta["frames"],
      tr.meta["lost_rows"], tr.meta["mapping_source"].split(" (")[0].replace(" ", "_"))
"""


def bring_up(work: Path) -> tuple[bytes, float]:
    """The bring-up of the three-axis machine as drivectl's --bus-log records it (up to the first SYNC), and its
    last stamp."""
    import contextlib
    import io

    from drivectl.tools.cli.main import main

    log = work / "bringup.log"
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        rc = main(["trace", "--axis", "x,y,z", "--duration", "0.01", "--no-plot", "--quiet", "--bus-log", str(log),
                   "--out", str(work / "run")])
    assert rc == 0, rc
    out, last = [], 0.0
    for line in log.read_bytes().splitlines(keepends=True):
        if b" 080#" in line:
            break
        out.append(line)
        last = float(line[1 : line.index(b")")])
    return b"".join(out), last


def _digits(values: np.ndarray, width: int) -> np.ndarray:
    """(n, width) ASCII decimal digits of non-negative int64 values, zero-padded."""
    out = np.empty((len(values), width), np.uint8)
    v = values.copy()
    for k in range(width - 1, -1, -1):
        out[:, k] = 48 + v % 10
        v //= 10
    return out


_HEXCH = np.frombuffer(b"0123456789ABCDEF", np.uint8)


def _hex(data: np.ndarray) -> np.ndarray:
    """(n, 2 m) ASCII hex of (n, m) bytes."""
    out = np.empty((len(data), data.shape[1] * 2), np.uint8)
    out[:, 0::2] = _HEXCH[data >> 4]
    out[:, 1::2] = _HEXCH[data & 15]
    return out


def _lines(stamp_us: np.ndarray, cob: int, payload: np.ndarray, flag: bytes) -> np.ndarray:
    """candump -L lines ``(s.us) vcan0 CCC#DATA F``, one row each, fixed width."""
    n = len(stamp_us)
    sec, us = stamp_us // 1_000_000, stamp_us % 1_000_000
    parts = [np.full((n, 1), ord("("), np.uint8), _digits(sec, 10), np.full((n, 1), ord("."), np.uint8),
             _digits(us, 6), np.frombuffer(b") vcan0 ", np.uint8)[None].repeat(n, 0),
             np.frombuffer(f"{cob:03X}#".encode(), np.uint8)[None].repeat(n, 0), _hex(payload),
             np.frombuffer(b" " + flag + b"\n", np.uint8)[None].repeat(n, 0)]
    return np.hstack(parts)


def cyclic(first: int, n: int, t0_us: int) -> tuple[bytes, int]:
    """``n`` cycles from cycle ``first`` as candump text, and the frame count."""
    k = np.arange(first, first + n, dtype=np.int64)
    base = t0_us + k * 1000
    blocks = [_lines(base, 0x080, np.zeros((n, 0), np.uint8), b"T")]
    for j, node in enumerate(NODES):
        ph = 2 * np.pi * (k * CYCLE_S) / (2.0 + j)
        pos = np.round(np.sin(ph) * 0.01 / 76.29e-9).astype("<i4")
        tq = np.round(np.sin(ph + 0.3) * 400).astype("<i2")
        tp1 = np.zeros((n, 8), np.uint8)  # the compact mapping the bring-up configured: statusword, position, torque
        tp1[:, 0:2] = np.frombuffer(np.full(n, 0x1237, "<u2").tobytes(), np.uint8).reshape(n, 2)
        tp1[:, 2:6] = pos.view(np.uint8).reshape(n, 4)
        tp1[:, 6:8] = tq.view(np.uint8).reshape(n, 2)
        rp1 = np.zeros((n, 4), np.uint8)
        rp1[:, 0:2] = np.frombuffer(np.full(n, 0x000F, "<u2").tobytes(), np.uint8).reshape(n, 2)
        rp1[:, 2:4] = (tq // 2).astype("<i2").view(np.uint8).reshape(n, 2)
        blocks += [_lines(base + 40 + 60 * j, 0x180 + node, tp1, b"R"),
                   _lines(base + 300 + 60 * j, 0x200 + node, rp1, b"T")]
    return np.hstack(blocks).tobytes(), n * (1 + 2 * len(NODES))


def make_log(work: Path, seconds: float) -> tuple[Path, int, int]:
    """The log: the recorded bring-up, then the generated cycles; (path, frames, cycles)."""
    head, last = bring_up(work)
    path = work / "machine.log"
    cycles = int(round(seconds / CYCLE_S))
    frames = head.count(b"\n")
    t0_us = int(round((last + 0.01) * 1e6))
    with open(path, "wb") as f:
        f.write(head)
        for first in range(0, cycles, CHUNK_CYCLES):
            text, n = cyclic(first, min(CHUNK_CYCLES, cycles - first), t0_us)
            f.write(text)
            frames += n
    return path, frames, cycles


def convert(path: Path, work: Path) -> dict:
    res = subprocess.run([sys.executable, "-c", CHILD, str(path), str(work / "conv")], check=False,
                         capture_output=True, text=True)
    if res.returncode:
        raise SystemExit(f"bench/buslog.py: the conversion failed: {res.stderr.strip().splitlines()[-1]}")
    dt, dc, rss, rows, frames, lost, source = res.stdout.split()
    return {"seconds": float(dt), "cpu_s": float(dc), "peak_rss_mb": float(rss), "rows": int(rows),
            "frames": int(frames), "lost": int(lost), "source": source}


def readers(path: Path, work: Path, n: int) -> list[tuple[str, str, float]]:
    """(format, reader, frames/s) of each reader alone on the first ``n`` frames of the log."""
    import can

    from drivectl.tools.buslog.frames import Reading, fast_path_reads, read_frames

    msgs = []
    with can.LogReader(str(path)) as r:
        for m in r:
            msgs.append(m)
            if len(msgs) >= n:
                break
    out = []
    for suffix in (".log", ".asc", ".blf", ".trc", ".csv"):
        p = work / f"slice{suffix}"
        with can.Logger(str(p)) as w:
            for m in msgs:
                w.on_message_received(m)
        for fast in (False, True):
            if fast and not fast_path_reads(p):
                continue
            reading = Reading(p)
            t = time.process_time()  # CPU time: the machine's load does not count
            for _ in read_frames(p, reading, fast=fast):
                pass
            dt = time.process_time() - t
            out.append((suffix, reading.reader, reading.frames / dt))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=600.0, help="cyclic traffic in s (default 600: 10 minutes)")
    ap.add_argument("--reader-frames", type=int, default=200000, help="frames for the per-format reader table")
    ap.add_argument("--json", action="store_true", help="exactly one JSON object")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="drivectl-bench-buslog-") as tmp:
        work = Path(tmp)
        path, frames, cycles = make_log(work, args.seconds)
        res = convert(path, work)
        assert res["frames"] == frames, (res["frames"], frames)
        assert res["rows"] == cycles and res["lost"] == 0, res
        rate = frames / res["seconds"]
        if args.json:
            print(json.dumps({"frames": frames, "seconds": round(res["seconds"], 3),
                              "frames_per_s": round(rate), "peak_rss_mb": round(res["peak_rss_mb"], 1)}))
            return 0
        size = path.stat().st_size / 1e6
        print(f"log: {frames} frames, {cycles} cycles of 3 axes, {size:.0f} MB candump .log")
        print(f"{'what':<44}{'value':>14}")
        print(f"{'conversion, axis x (s)':<44}{res['seconds']:>14.2f}")
        print(f"{'frames/s (target >= 300000)':<44}{rate:>14.0f}")
        print(f"{'CPU s of the conversion (both threads)':<44}{res['cpu_s']:>14.2f}")
        print(f"{'frames per CPU s (the load-independent rate)':<44}{frames / res['cpu_s']:>14.0f}")
        print(f"{'peak RSS MB (target < 300)':<44}{res['peak_rss_mb']:>14.1f}")
        print(f"{'rows (one per SYNC), lost':<44}{res['rows']:>8} {res['lost']:>5}")
        print(f"{'mapping from':<44}{res['source']:>14}")
        print()
        print(f"readers alone, first {args.reader_frames} frames (frames per CPU second):")
        print(f"{'format':<8}{'reader':<36}{'frames/s':>12}")
        for suffix, reader, fps in readers(path, work, args.reader_frames):
            print(f"{suffix:<8}{reader:<36}{fps:>12.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

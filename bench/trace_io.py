"""Trace I/O at length: the streaming writer's memory over a long run, and the readers' memory and time
on a big trace (issue 18 points 5 and 7).

1. Stream ``--rows`` rows (default 3.6 M: one hour at 1 kHz) of five columns through TraceWriter, the
   loop waiting for the writer every 1024 rows as a 1 kHz loop would never need to; the peak of Python
   allocations (tracemalloc, both threads) at 1/10 of the run and at its end: flat means constant
   memory for a run of any length.
2. A trace of ``--read-rows`` rows (default 10 M, the issue's case) written in bulk, then in fresh
   processes ``Trace.read`` and ``drivectl summary`` of it: wall time and peak RSS (ru_maxrss of the
   child), beside the size of its columns as float64.

    python bench/trace_io.py [--rows N] [--read-rows N] [--json]

``--json`` prints exactly one JSON object: rows, append_us, writer_peak_kib_tenth, writer_peak_kib_end,
read_rows, file_mb, columns_mb, read_s, read_peak_mb, summary_s, summary_peak_mb.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

COLS = ("time_s", "ref_m", "pos_m", "effort", "vel_m_s")

CHILD = """
import resource, sys, time
t0 = time.perf_counter()
if sys.argv[1] == "read":
    from drivectl.tracefile.format import Trace
    tr = Trace.read(sys.argv[2])
    assert len(tr) == int(sys.argv[3])
else:
    from drivectl.tools.cli.main import main
    import contextlib, io
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["summary", sys.argv[2]]) == 0
print(time.perf_counter() - t0, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
"""


def stream(folder: Path, rows: int) -> tuple[Path, float, int, int]:
    from drivectl.tracefile.stream import TraceWriter

    meta = {"axis": "x", "effort_unit": "N", "dt_s": 0.001}
    timing = TraceWriter(folder / "timing", "x", columns=COLS, meta=meta).start()  # untraced: the append's cost
    n = min(rows, 100_000)
    t0 = time.perf_counter()
    for k in range(n):
        timing.append(k * 0.001, 1e-6 * k, 1e-6 * k, 0.5, 0.001)
    spent = time.perf_counter() - t0
    timing.close()
    w = TraceWriter(folder, "x", columns=COLS, meta=meta).start()
    tracemalloc.start()
    tenth = 0
    for k in range(rows):
        w.append(k * 0.001, 1e-6 * k, 1e-6 * k, 0.5, 0.001)
        if k % 1024 == 1023:
            w.flush()
        if k == rows // 10:
            tenth = tracemalloc.get_traced_memory()[1]
    w.flush()
    end = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    path = w.close({"stop": "completed", "cycles": rows})
    return path, spent / n * 1e6, tenth, end


def bulk(folder: Path, rows: int) -> Path:
    import numpy as np

    from drivectl.tracefile.stream import TraceWriter

    w = TraceWriter(folder, "big", columns=COLS, meta={"axis": "big", "effort_unit": "N", "dt_s": 0.001},
                    block_rows=65536).start()
    step = 65536
    for a in range(0, rows, step):
        k = np.arange(a, min(rows, a + step), dtype=float)
        w.extend(np.column_stack([k * 0.001, np.sin(k * 1e-3) * 0.01, np.sin(k * 1e-3) * 0.01 + 1e-7,
                                  np.cos(k * 1e-3), np.cos(k * 1e-3) * 0.01]))
    return w.close({"stop": "completed", "cycles": rows})


def child(what: str, path: Path, rows: int) -> tuple[float, float]:
    out = subprocess.run([sys.executable, "-c", CHILD, what, str(path), str(rows)], capture_output=True, text=True,
                         check=True).stdout.split()
    return float(out[0]), float(out[1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=3_600_000)
    ap.add_argument("--read-rows", type=int, default=10_000_000)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        _, append_us, tenth, end = stream(Path(folder), args.rows)
        path = bulk(Path(folder), args.read_rows)
        read_s, read_mb = child("read", path, args.read_rows)
        summary_s, summary_mb = child("summary", path, args.read_rows)
        res = {"rows": args.rows, "append_us": round(append_us, 3), "writer_peak_kib_tenth": round(tenth / 1024, 1),
               "writer_peak_kib_end": round(end / 1024, 1), "read_rows": args.read_rows,
               "file_mb": round(path.stat().st_size / 1e6, 1),
               "columns_mb": round(args.read_rows * len(COLS) * 8 / 1e6, 1), "read_s": round(read_s, 2),
               "read_peak_mb": round(read_mb, 1), "summary_s": round(summary_s, 2),
               "summary_peak_mb": round(summary_mb, 1)}
    if args.json:
        print(json.dumps(res))
        return 0
    print(f"streamed {res['rows']} rows x {len(COLS)} columns; read {res['read_rows']} rows ({res['file_mb']} MB)")
    print(f"{'measure':<34} {'value':>12}")
    print("-" * 47)
    for label, key, unit in (("append, per row", "append_us", "us"),
                             ("writer peak at 1/10 of the run", "writer_peak_kib_tenth", "KiB"),
                             ("writer peak at the end", "writer_peak_kib_end", "KiB"),
                             ("columns as float64", "columns_mb", "MB"),
                             ("Trace.read: time", "read_s", "s"), ("Trace.read: peak RSS", "read_peak_mb", "MB"),
                             ("drivectl summary: time", "summary_s", "s"),
                             ("drivectl summary: peak RSS", "summary_peak_mb", "MB")):
        print(f"{label:<34} {res[key]:>9} {unit}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

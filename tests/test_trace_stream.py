"""Issue 18 points 5 and 7: the streamed trace (tracefile/stream.py, docs/trace-format.md) and the
readers that refuse what they cannot read right.

No sleeps decide anything here: the writer is synchronised with :meth:`TraceWriter.flush`, the killed
writer reports how far it flushed before the kill.
"""

from __future__ import annotations

import gzip
import os
import signal
import stat
import subprocess
import sys
import textwrap
import tracemalloc

import numpy as np
import pytest

from drivectl.tracefile.format import END_MARKER, Trace, TraceError
from drivectl.tracefile.stream import TraceWriteError, TraceWriter, clean_stale, safe_name, write_trace

COLS = ("time_s", "ref_m", "pos_m", "effort", "vel_m_s")
META = {"axis": "x", "effort_unit": "N", "dt_s": 0.001}


def _writer(folder, **kw) -> TraceWriter:
    return TraceWriter(folder, "x", columns=COLS, meta=META, **kw).start()


def _rows(w: TraceWriter, n: int, k0: int = 0) -> None:
    for k in range(k0, k0 + n):
        w.append(k * 0.001, 1e-6 * k, 1e-6 * k - 1e-7, 0.5 * k, 1e-3)


def test_streamed_trace_is_readable_while_partial_and_complete_after_close(tmp_path):
    w = _writer(tmp_path, block_rows=100)
    _rows(w, 1050)
    assert w.flush()
    assert w.partial.name.endswith(".csv.partial") and not w.path.exists()
    part = Trace.read(w.partial)
    assert len(part) == 1050 and part.meta["trace_complete"] == "false" and part.meta["stop"] == "incomplete"
    np.testing.assert_allclose(part.columns["effort"], 0.5 * np.arange(1050), atol=1e-6)
    _rows(w, 450, 1050)
    path = w.close({"stop": "completed", "cycles": 1500})
    assert path.name.startswith("x-") and not w.partial.exists()
    tr = Trace.read(path)
    assert len(tr) == 1500 and tr.meta["trace_complete"] == "true" and tr.meta["stop"] == "completed"
    assert tr.meta["cycles"] == "1500" and tr.meta["axis"] == "x" and list(tr.columns) == list(COLS)
    assert path.read_text().splitlines()[-1] == END_MARKER
    # AXIS.csv is the latest trace, the same file
    assert os.path.samefile(tmp_path / "x.csv", path)


def test_no_run_overwrites_an_earlier_trace(tmp_path):
    (tmp_path / "x.csv").write_text("# drivectl trace v1\ntime_s,ref_m,pos_m,effort\n0,0,0,0\n0.001,0,0,0\n")
    paths = []
    for i in range(3):
        w = _writer(tmp_path, stamp="20260101T000000Z")
        _rows(w, 10 + i)
        paths.append(w.close({"stop": "completed"}))
    assert len(set(paths)) == 3 and all(p.exists() for p in paths)
    assert [len(Trace.read(p)) for p in paths] == [10, 11, 12]
    assert os.path.samefile(tmp_path / "x.csv", paths[-1])
    # the plain x.csv of an earlier version was kept under a stamped name, not overwritten
    kept = [p for p in tmp_path.glob("x-*.csv") if p not in paths]
    assert len(kept) == 1 and len(Trace.read(kept[0])) == 2


@pytest.mark.parametrize("mask", [0o022, 0o002, 0o077])
def test_files_respect_the_umask(tmp_path, mask):
    old = os.umask(mask)
    try:
        w = _writer(tmp_path)
        _rows(w, 5)
        path = w.close()
        tr = Trace.read(path)
        atomic = tr.write(tmp_path / "atomic.csv")
    finally:
        os.umask(old)
    for p in (path, tmp_path / "x.csv", atomic):
        assert stat.S_IMODE(p.stat().st_mode) == 0o666 & ~mask, p


@pytest.mark.parametrize("name", ["../../escaped", "x/y", "", ".", "..", ".hidden", "a" * 65, "x\0", "é"])
def test_names_that_are_not_safe_file_names_are_refused(tmp_path, name):
    assert not safe_name(name)
    with pytest.raises(TraceWriteError, match="not safe as a file name"):
        TraceWriter(tmp_path / "out", name)
    assert not (tmp_path / "out").exists() and not (tmp_path.parent / "escaped").exists()


def test_stale_temporaries_are_cleaned_and_partials_kept(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    pid = int(dead.stdout)
    stale = tmp_path / f".x.csv.{pid}.abcd1234.tmp"
    mine = tmp_path / f".x.csv.{os.getpid()}.abcd1234.tmp"
    partial = tmp_path / "x-20260101T000000Z.csv.partial"
    for p in (stale, mine, partial):
        p.write_text("x")
    left = clean_stale(tmp_path)
    assert not stale.exists() and mine.exists() and partial.exists()
    assert left == [partial]


def test_a_write_error_stops_the_writing_not_the_loop(tmp_path):
    w = _writer(tmp_path, block_rows=64, blocks=2)
    _rows(w, 10)
    assert w.flush()
    w._file.close()
    w._file = open("/dev/full", "w")  # noqa: SIM115 - the kernel's own full disk: every write is ENOSPC
    _rows(w, 5000, 10)  # the loop goes on: no exception, no wait
    w._wake.set()
    assert not w.flush(timeout=2.0) and "No space left on device" in w.error
    with pytest.raises(TraceWriteError) as err:
        w.close({"stop": "completed"})
    assert "\n" not in str(err.value) and "trace incomplete" in str(err.value)
    assert len(w._blocks) <= 2  # memory did not grow with the rows that could not be written


KILLED = textwrap.dedent("""
    import sys, time
    from drivectl.tracefile.stream import TraceWriter
    w = TraceWriter(sys.argv[1], "x", columns=("time_s", "ref_m", "pos_m", "effort"),
                    meta={"axis": "x", "dt_s": 0.001, "effort_unit": "N"}, block_rows=256).start()
    for k in range(3000):
        w.append(k * 0.001, 0.0, 1e-6 * k, 1.0)
    assert w.flush()
    print(w.rows, flush=True)
    for k in range(3000, 3100):
        w.append(k * 0.001, 0.0, 1e-6 * k, 1.0)
    time.sleep(60)
""")


def test_a_sigkilled_writer_leaves_a_readable_partial_trace(tmp_path):
    proc = subprocess.Popen([sys.executable, "-c", KILLED, str(tmp_path)], stdout=subprocess.PIPE, text=True)
    try:
        flushed = int(proc.stdout.readline())
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert flushed == 3000
    (partial,) = tmp_path.glob("x-*.csv.partial")
    tr = Trace.read(partial)
    assert 3000 <= len(tr) <= 3100 and tr.meta["trace_complete"] == "false"
    np.testing.assert_allclose(tr.pos, 1e-6 * np.arange(len(tr)), atol=1e-12)
    # cut mid-row: the reader drops the row that was never whole
    text = partial.read_text()
    partial.write_text(text + "3.100000,0.0000")
    assert len(Trace.read(partial)) == len(tr)


def _streamed_peak(rows: int) -> int:
    import tempfile

    with tempfile.TemporaryDirectory() as folder:
        w = _writer(folder, block_rows=512)
        tracemalloc.start()
        tracemalloc.reset_peak()
        for k in range(rows):
            w.append(k * 0.001, 0.0, 0.0, 1.0, 0.0)
            if k % 1024 == 0:  # a real loop appends at 1 kHz: the thread keeps up (here: wait for it)
                assert w.flush()
        assert w.flush()
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        assert w.spilled == 0
        w.close()
    return peak


def test_memory_is_flat_over_a_long_streamed_run():
    """40k and 160k rows: the same peak (the ring, one formatted block), not 4x."""
    short, long = _streamed_peak(40_000), _streamed_peak(160_000)
    assert long < 1.5 * short + 64_000, (short, long)
    assert long < 1_000_000, long


# ------------------------------------------------------------------------------------------- readers
TRACE = ("# drivectl trace v1\n# axis: x\n# effort_unit: N\n# dt_s: 0.001\ntime_s,ref_m,pos_m,effort\n"
         + "".join(f"{k * 0.001:.6f},{k * 1e-6:.9f},{k * 1e-6:.9f},{k:.6f}\n" for k in range(20)))


def test_gzip_and_bom_read_as_the_plain_file(tmp_path):
    plain = tmp_path / "t.csv"
    plain.write_text(TRACE)
    gz = tmp_path / "t.csv.gz"
    gz.write_bytes(gzip.compress(TRACE.encode()))
    bom = tmp_path / "bom.csv"
    bom.write_bytes(b"\xef\xbb\xbf" + TRACE.replace("# drivectl trace v1\n# axis: x\n# effort_unit: N\n# dt_s: 0.001\n",
                                                     "").encode())
    a, b, c = Trace.read(plain), Trace.read(gz), Trace.read(bom)
    for t in (b, c):
        for k in REQUIRED_COLS:
            np.testing.assert_array_equal(a.columns[k], t.columns[k])
    assert b.meta["dt_s"] == "0.001"


REQUIRED_COLS = ("time_s", "ref_m", "pos_m", "effort")


@pytest.mark.parametrize(("text", "fragments"), [
    (TRACE.replace("time_s,ref_m,pos_m,effort", "time_s,ref_m,pos_m,effort,pos_m").replace("\n0.0", ",9\n0.0")
     .rstrip("\n") + ",9\n", ("'pos_m' appears twice", "columns 3 and 5")),
    (TRACE.replace("# dt_s: 0.001", "# dt_s: 1e-06"), ("dt_s", "1e-06", "0.001", "one of them is wrong")),
    (TRACE.replace("0.005000,", "0.004000,"), ("time_s", "not increasing", "data row 6")),
    (TRACE + "# stop: completed\n0.020000,0,0,0\n", ("data row after the trailer",)),
])
def test_readers_refuse_what_they_cannot_read_right(tmp_path, text, fragments):
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(TraceError) as err:
        Trace.read(p)
    msg = str(err.value)
    assert msg.startswith(str(p)) and "\n" not in msg
    for f in fragments:
        assert f in msg, msg


def test_a_trace_too_large_for_the_memory_budget_is_refused_with_the_figure(tmp_path, monkeypatch):
    tr = Trace.parse(TRACE)
    big = Trace({k: np.arange(200_000) * (0.001 if k == "time_s" else 1.0) for k in REQUIRED_COLS},
                dict(tr.meta))
    path = big.write(tmp_path / "big.csv")
    monkeypatch.setenv("DRIVECTL_TRACE_MAX_MB", "1")
    with pytest.raises(TraceError) as err:
        Trace.read(path)
    msg = str(err.value)
    assert "rows x 4 columns need" in msg and "MB in memory" in msg and "DRIVECTL_TRACE_MAX_MB" in msg, msg
    monkeypatch.setenv("DRIVECTL_TRACE_MAX_MB", "100")
    assert len(Trace.read(path)) == 200_000


def test_read_keeps_only_the_columns_asked_for(tmp_path):
    tr = Trace.parse(TRACE)
    tr.columns["extra"] = np.ones(len(tr))
    path = tr.write(tmp_path / "t.csv")
    assert list(Trace.read(path, columns=("pos_m",)).columns) == list(REQUIRED_COLS)


def test_write_trace_gives_a_new_file_per_call(tmp_path):
    tr = Trace.parse(TRACE)
    a, b = write_trace(tmp_path, tr), write_trace(tmp_path, tr)
    assert a != b and os.path.samefile(tmp_path / "x.csv", b)
    back = Trace.read(b)
    assert back.meta["trace_complete"] == "true" and len(back) == len(tr)
    np.testing.assert_array_equal(back.pos, tr.pos)


def test_inline_writer_writes_full_blocks_and_late_rows_on_the_loops_thread(tmp_path):
    """Unpaced runs (inline=True): a full block is on disk when the append that filled it returns, and
    the rows so far are flushed by the loop once flush_s of wall time passed since the last flush."""
    w = _writer(tmp_path, block_rows=256, inline=True)
    _rows(w, 3 * 256 + 10)
    assert w._flushed >= 3 * 256  # written by the appends themselves, no flush() asked
    assert len(Trace.read(w.partial)) >= 3 * 256
    w._last_flush -= 1.0  # as if the loop had run 1 s of wall time since
    _rows(w, TraceWriter.INLINE_CHECK_ROWS, 3 * 256 + 10)
    assert 3 * 256 + 10 < w._flushed <= w.rows  # past the last full block: flushed by the clock rule
    path = w.close({"stop": "completed"})
    tr = Trace.read(path)
    np.testing.assert_allclose(tr.columns["effort"], 0.5 * np.arange(w.rows), atol=1e-6)


KILLED_INLINE = textwrap.dedent("""
    import sys, time
    from drivectl.tracefile.stream import TraceWriter
    w = TraceWriter(sys.argv[1], "x", columns=("time_s", "ref_m", "pos_m", "effort"),
                    meta={"axis": "x", "dt_s": 0.001, "effort_unit": "N"}, block_rows=256, inline=True).start()
    for k in range(3000):
        w.append(k * 0.001, 0.0, 1e-6 * k, 1.0)
    print(w._flushed, flush=True)  # the full blocks, written by the appends
    deadline = time.monotonic() + 30
    while w._flushed < w.rows and time.monotonic() < deadline:  # the loop idles: the thread flushes the rest
        time.sleep(0.005)
    print(w._flushed, flush=True)
    time.sleep(60)
""")


def test_a_sigkilled_inline_writer_leaves_every_row_of_an_idle_loop(tmp_path):
    proc = subprocess.Popen([sys.executable, "-c", KILLED_INLINE, str(tmp_path)], stdout=subprocess.PIPE, text=True)
    try:
        by_loop = int(proc.stdout.readline())
        by_thread = int(proc.stdout.readline())
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert by_loop >= 11 * 256 and by_thread == 3000
    (partial,) = tmp_path.glob("x-*.csv.partial")
    tr = Trace.read(partial)
    assert len(tr) == 3000 and tr.meta["trace_complete"] == "false"
    np.testing.assert_allclose(tr.pos, 1e-6 * np.arange(3000), atol=1e-12)


def _timed(tmp_path, t, dt="0.001"):
    body = "".join(f"{x!r},0,0,0\n" for x in t)
    p = tmp_path / "gaps.csv"
    p.write_text(f"# drivectl trace v1\n# axis: x\n# effort_unit: N\n# dt_s: {dt}\ntime_s,ref_m,pos_m,effort\n{body}")
    return p


def test_skipped_slots_read_back_as_gaps_and_a_dt_wrong_by_a_whole_factor_is_still_refused(tmp_path):
    """A slot the wall-clock loop skipped has no row: its time is a gap of whole dt_s (most of a short
    capture taken just after enable may be gaps); a file that steps 2 ms everywhere but says 1 ms is wrong."""
    slots = [0, 1, 5, 6, 9, 17, 18, 30]                     # 5 of 7 steps are gaps
    t = Trace.read(_timed(tmp_path, [s * 0.001 for s in slots])).columns["time_s"]
    assert np.allclose(np.diff(t) / 0.001, np.diff(slots))
    with pytest.raises(TraceError, match="dt_s"):
        Trace.read(_timed(tmp_path, [s * 0.002 for s in range(20)]))
    with pytest.raises(TraceError, match="dt_s"):
        Trace.read(_timed(tmp_path, [s * 0.0015 for s in range(20)]))

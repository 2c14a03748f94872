"""Issue 18 point 4, the outputs: everything a run writes is checked before a bus opens (``--out`` a
folder we can write with room, the bus log's folder, a config path that can be recorded), and a run's
traces never overwrite an earlier one. Each refusal: exit 2, one line naming the flag, nothing written.
"""

from __future__ import annotations

import os
import shutil
from collections import namedtuple
from pathlib import Path

import pytest

from drivectl.machine.config import DEFAULT_CONFIG_TOML
from drivectl.tools.cli.main import main
from drivectl.tracefile.format import Trace

SIM = ["trace", "--axis", "x", "--duration", "0.02", "--no-plot", "--quiet", "--sim"]
BUS = ["trace", "--axis", "x", "--duration", "0.02", "--no-plot", "--quiet"]


def _refused(capsys, argv: list[str], *fragments: str) -> str:
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc == 2, err
    lines = err.rstrip("\n").split("\n")
    assert len(lines) == 1 and lines[0].startswith("drivectl: ") and "Traceback" not in err, err
    for f in fragments:
        assert f in lines[0], (f, lines[0])
    return lines[0]


def test_out_naming_a_file_is_refused_before_the_run(tmp_path, capsys):
    f = tmp_path / "x.csv"
    f.write_text("not a folder")
    _refused(capsys, [*BUS, "--out", str(f)], "--out", str(f), "not a folder")
    assert f.read_text() == "not a folder" and sorted(tmp_path.iterdir()) == [f]


def test_out_with_no_room_is_refused_before_the_run(tmp_path, capsys, monkeypatch):
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(10**9, 10**9 - 1000, 1000))
    out = tmp_path / "out"
    _refused(capsys, [*BUS, "--out", str(out)], "--out", str(out), "MB free", "the run needs about")
    assert not out.exists()  # refused before the run: not even the folder is made


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_out_read_only_is_refused_before_the_run(tmp_path, capsys):
    out = tmp_path / "ro"
    out.mkdir()
    out.chmod(0o555)
    try:
        _refused(capsys, [*BUS, "--out", str(out)], "--out", "cannot write there")
    finally:
        out.chmod(0o755)


def test_bus_log_into_a_missing_folder_is_refused_before_the_run(tmp_path, capsys):
    log = tmp_path / "missing" / "frames.asc"
    out = tmp_path / "out"
    _refused(capsys, [*BUS, "--bus-log", str(log), "--out", str(out)], "--bus-log", "does not exist")
    assert not out.exists() and not log.parent.exists()


def test_a_config_path_that_is_not_utf8_is_refused(tmp_path, capsys):
    bad = Path(os.fsdecode(bytes(tmp_path) + b"/machine-\xff.toml"))
    try:
        bad.write_text(DEFAULT_CONFIG_TOML)
    except (OSError, UnicodeEncodeError):
        pytest.skip("this file system does not take non-UTF-8 names")
    out = tmp_path / "out"
    _refused(capsys, ["--config", str(bad), *SIM, "--out", str(out)], "--config", "not valid UTF-8")
    assert not out.exists()


def test_each_run_writes_a_new_trace_and_axis_csv_names_the_latest(tmp_path, capsys):
    out = tmp_path / "out"
    for _ in range(2):
        assert main([*SIM, "--out", str(out)]) == 0
    runs = sorted(p for p in out.glob("x-*.csv"))
    assert len(runs) == 2, sorted(out.iterdir())
    assert os.path.samefile(out / "x.csv", runs[-1]) or os.path.samefile(out / "x.csv", runs[0])
    assert not list(out.glob("*.partial")) and not list(out.glob(".*"))
    tr = Trace.read(out / "x.csv")
    assert tr.meta["trace_complete"] == "true" and tr.meta["stop"] == "completed"
    assert f"wrote {runs[-1]}" in capsys.readouterr().out


def test_controller_override_keeps_the_settings_that_apply_and_names_the_dropped(tmp_path, capsys):
    cfg = tmp_path / "machine.toml"
    text = DEFAULT_CONFIG_TOML
    for a, b in (('controller = "mbc"              #', 'controller = "pid"              #'),
                 ("# law = 14                      # paper 004 gain law (11..14)", "kp = 2e5\nkd = 3e3")):
        assert text.count(a) >= 1
        text = text.replace(a, b, 1)
    cfg.write_text(text)
    rc = main(["--config", str(cfg), *SIM, "--controller", "pid-dob", "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert rc == 0, err
    tr = Trace.read(tmp_path / "out" / "x.csv")
    assert float(tr.meta["kp"]) == 2e5 and float(tr.meta["kd"]) == 3e3  # kept: pid-dob takes them too
    rc = main(["--config", str(cfg), *SIM, "--controller", "asmc", "--out", str(tmp_path / "out2")])
    err = capsys.readouterr().err
    assert rc == 0, err
    assert "--controller asmc: axes.x.controller_settings kd, kp dropped (not asmc settings)" in err, err


def test_a_trace_lost_after_the_run_is_one_line_and_exit_1(tmp_path, capsys, monkeypatch):
    """The disk fills between the checks and the end of the run: the run is reported, the loss named."""
    from drivectl.tracefile import stream as trace_stream

    def full(folder, trace, **kw):
        raise trace_stream.TraceWriteError(f"{folder}/x-1.csv.partial: trace incomplete: No space left on device "
                                           "after 0 rows; the rows written before are kept")

    def stream_full(self, trailer=None, *, complete=True):
        self.abandon()
        raise trace_stream.TraceWriteError(f"{self.partial}: trace incomplete: No space left on device")

    monkeypatch.setattr(trace_stream, "write_trace", full)
    # the run streams its trace (servo.Recording): the disk fills under the stream, then the rewrite fails too
    monkeypatch.setattr(trace_stream.TraceWriter, "close", stream_full)
    rc = main([*SIM, "--out", str(tmp_path / "out")])
    cap = capsys.readouterr()
    assert rc == 1
    assert "completed" in cap.out  # the summary of the run that happened
    lines = [ln for ln in cap.err.splitlines() if ln.startswith("drivectl: ")]
    assert len(lines) == 1 and "No space left on device" in lines[0]


def test_bode_out_naming_a_file_is_refused_before_the_measurement(tmp_path, capsys):
    f = tmp_path / "x.csv"
    f.write_text("not a folder")
    _refused(capsys, ["bode", "--axis", "x", "--sim", "--out", str(f)], "--out", "not a folder")
    assert f.read_text() == "not a folder"


def test_identify_out_naming_a_file_is_refused_before_the_runs(tmp_path, capsys):
    f = tmp_path / "x.csv"
    f.write_text("not a folder")
    _refused(capsys, ["identify", "--axis", "x", "--sim", "--out", str(f)], "--out", "not a folder")


def test_a_profile_path_that_is_not_utf8_is_recorded_escaped(tmp_path, capsys):
    """The trace records the profile's path as text: a name that is not UTF-8 is written escaped, not a
    traceback after the run."""
    profile = Path(os.fsdecode(bytes(tmp_path) + b"/move-\xff.toml"))
    try:
        profile.write_text('kind = "dwell"\nposition = 0.0\nduration = 0.02\n')
    except (OSError, UnicodeEncodeError):
        pytest.skip("this file system does not take non-UTF-8 names")
    out = tmp_path / "out"
    rc = main([*SIM, "--profile", str(profile), "--out", str(out)])
    assert rc == 0, capsys.readouterr().err
    tr = Trace.read(out / "x.csv")
    assert "move-\\udcff.toml" in tr.meta["profile"]

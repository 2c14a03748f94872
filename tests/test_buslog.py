"""Bus logs in (tools/buslog): a log recorded by drivectl's own --bus-log, in three of python-can's formats, turned
back into a trace equals the run's own trace row for row (position within one encoder count, effort within the
0x6071 quantisation); bad input is one line and exit 2."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from drivectl.machine.config import load_config
from drivectl.tools.buslog import is_bus_log
from drivectl.tools.cli.main import main
from drivectl.tracefile.format import Trace


def _aligned(from_log: Trace, run: Trace, resolution: float, effort_q: float) -> list[int]:
    """The SYNC offsets at which every row of the run's trace matches the converted one."""
    n = len(run)
    ok = []
    for k in range(len(from_log) - n + 1):
        pos = from_log.pos[k : k + n]
        eff = from_log.effort[k : k + n]
        if np.all(np.abs(pos - run.pos) <= resolution * 1.000001) and \
                np.all(np.abs(eff - run.effort) <= effort_q * 1.000001):
            ok.append(k)
    return ok


@pytest.mark.parametrize("suffix", [".asc", ".blf", ".log"])
def test_own_bus_log_converts_to_the_runs_trace(tmp_path: Path, suffix: str, capsys) -> None:
    log = tmp_path / f"x{suffix}"
    run_dir, conv_dir = tmp_path / "run", tmp_path / "conv"
    assert main(["trace", "--axis", "x", "--duration", "0.5", "--no-plot", "--quiet", "--bus-log", str(log),
                 "--out", str(run_dir)]) == 0
    assert is_bus_log(log)
    capsys.readouterr()
    assert main(["trace", "--from-log", str(log), "--axis", "x", "--out", str(conv_dir)]) == 0
    assert (conv_dir / "x.csv").exists() and len(list(conv_dir.glob("x-*.csv"))) == 1
    run, conv = Trace.read(run_dir / "x.csv"), Trace.read(conv_dir / "x.csv")
    ac = load_config().axis("x")
    assert conv.meta["ref"] == "none" and np.all(np.isnan(conv.ref))
    assert conv.meta["node"] == str(ac.node_id) and conv.meta["bus_log"] == str(log)
    assert len(conv.meta["bus_log_sha256"]) == 64 and conv.meta["dt_source"] == "0x1006 written in the log"
    assert conv.dt == pytest.approx(load_config().cycle_s)
    assert int(conv.meta["lost_rows"]) == 0 and not conv.columns["lost"].any()
    assert np.allclose(np.diff(conv.time), conv.dt)
    # the run starts after the bring-up's SYNCs: one offset (and only one) aligns every row
    offsets = _aligned(conv, run, ac.encoder_m_per_count, ac.rated_effort / 2000)
    assert len(offsets) == 1, offsets
    k = offsets[0]
    assert len(conv) >= k + len(run)
    assert np.abs(conv.pos[k : k + len(run)] - run.pos).max() <= ac.encoder_m_per_count * 1.000001
    # the velocity the drive mapped (0x606C) is the run's own column
    assert np.allclose(conv.columns["vel_m_s"][k : k + len(run)], run.columns["vel_m_s"], atol=1e-12)
    assert np.all(np.diff(conv.columns["frame_time_s"]) >= 0)
    capsys.readouterr()
    assert main(["decode", str(log)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert any("SDO write 0x1006:00 Communication cycle period = 1000 (0x3E8)" in s for s in lines)
    assert any("SDO write 0x6060:00 Modes of operation = 10" in s for s in lines)
    assert any("node 1: boot-up" in s for s in lines) and any("NMT reset node -> node 1" in s for s in lines)
    assert any("-> Operation Enabled" in s for s in lines)
    assert any(s.startswith(f"SYNC: {len(conv)} frames, period mean") for s in lines)
    assert "mapping of node 1: the log's own PDO configuration SDO writes (TPDO1, TPDO2, RPDO1)" in lines
    if suffix == ".asc":  # summary and explain take a trace without a reference (ref: none)
        from drivectl.plant_emulator.models import load_plant
        from drivectl.tools.explain.data import ExplainError, prepare

        # past the column checks (ref_m NaN accepted): 0.5 s is then too short to decide, said as such
        with pytest.raises(ExplainError, match="cannot decide: the axis moves in only"):
            prepare(conv, load_plant("rigid-x"), str(conv_dir / "x.csv"))
        capsys.readouterr()
        assert main(["summary", str(conv_dir / "x.csv")]) == 0
        row = capsys.readouterr().out.splitlines()[-1].split()
        assert row[1:4] == ["-", "-", "-"] and "nan" not in row


def test_lost_pdos_are_flagged_not_interpolated(tmp_path: Path, capsys) -> None:
    import can

    log = tmp_path / "x.asc"
    assert main(["trace", "--axis", "x", "--duration", "0.2", "--no-plot", "--quiet", "--bus-log", str(log),
                 "--out", str(tmp_path / "run")]) == 0
    cut = tmp_path / "cut.asc"
    dropped = syncs = 0
    with can.LogReader(str(log)) as reader, can.Logger(str(cut)) as writer:
        for msg in reader:
            syncs += msg.arbitration_id == 0x080
            if msg.arbitration_id == 0x181 and dropped < 3 and syncs > 100:  # TPDO1 of three SYNCs
                dropped += 1
                continue
            writer.on_message_received(msg)
    assert dropped == 3
    assert main(["trace", "--from-log", str(cut), "--axis", "x", "--out", str(tmp_path / "conv")]) == 0
    conv = Trace.read(tmp_path / "conv" / "x.csv")
    lost = conv.columns["lost"] == 1
    assert lost.sum() == 3 and conv.meta["lost_rows"] == "3"
    assert np.all(np.isnan(conv.pos[lost])) and np.all(np.isfinite(conv.pos[~lost]))


@pytest.mark.parametrize("content,name,what", [
    (b"not a log at all\n", "x.txt", "not a CAN log python-can reads"),
    (b"hello\n", "x.asc", "no CAN frames"),
    (None, "missing.blf", "no such log file"),
])
def test_bad_log_is_one_line_exit_2(tmp_path: Path, capsys, content, name, what) -> None:
    path = tmp_path / name
    if content is not None:
        path.write_bytes(content)
    assert main(["trace", "--from-log", str(path), "--axis", "x", "--out", str(tmp_path / "conv")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(path) in err and what in err, err
    assert not (tmp_path / "conv").exists() or not list((tmp_path / "conv").iterdir())


def test_log_without_the_nodes_pdos_exit_2(tmp_path: Path, capsys) -> None:
    log = tmp_path / "x.log"
    assert main(["trace", "--axis", "x", "--duration", "0.05", "--no-plot", "--quiet", "--bus-log", str(log),
                 "--out", str(tmp_path / "run")]) == 0
    capsys.readouterr()
    assert main(["trace", "--from-log", str(log), "--axis", "x", "--node", "9", "--out", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "no PDOs of node 9" in err and str(log) in err

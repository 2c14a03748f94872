"""Bus logs in (tools/buslog): a log recorded by drivectl's own --bus-log, in three of python-can's formats, turned
back into a trace equals the run's own trace row for row (position within one encoder count, effort within the
0x6071 quantisation); bad input is one line and exit 2."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from drivectl.machine.config import load_config
from drivectl.tools.buslog import BusLogError, is_bus_log
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


@pytest.mark.parametrize("suffix", [".asc", ".blf", ".log", ".trc", ".csv"])
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


# -- the two readers, the formats --------------------------------------------------------------------------------
def _table(path: Path) -> np.ndarray:
    tr = Trace.read(path)
    return np.column_stack([tr.columns[c] for c in tr.columns])


@pytest.mark.parametrize("suffix", [".trc", ".csv", ".mf4"])
def test_other_formats_convert_as_the_log_does(tmp_path: Path, suffix: str) -> None:
    """.trc and .csv from drivectl's own --bus-log; .mf4 written by python-can's MF4Writer where asammdf is
    importable: the same frames give the same trace, bit for bit, as the candump log they came from."""
    import can

    log = tmp_path / "x.log"
    assert main(["trace", "--axis", "x", "--duration", "0.1", "--no-plot", "--quiet", "--bus-log", str(log),
                 "--out", str(tmp_path / "run")]) == 0
    if suffix == ".mf4":
        pytest.importorskip("asammdf")
    other = tmp_path / f"x{suffix}"
    with can.LogReader(str(log)) as reader, can.Logger(str(other)) as writer:
        for msg in reader:
            writer.on_message_received(msg)
    from drivectl.tools.buslog import log_to_trace

    a = log_to_trace(log, axis="x", out_dir=tmp_path / "a")
    b = log_to_trace(other, axis="x", out_dir=tmp_path / "b")
    ta, tb = _table(a), _table(b)
    assert ta.shape == tb.shape and len(ta) > 90
    # the frames' own stamps go through each format's resolution (.trc keeps 0.1 ms); the rest is exact
    tra, trb = Trace.read(a), Trace.read(b)
    for col in ("pos_m", "effort", "vel_m_s", "torque_actual", "lost"):
        assert np.array_equal(tra.columns[col], trb.columns[col]), col
    assert np.allclose(tra.columns["frame_time_s"], trb.columns["frame_time_s"], atol=2e-4)


@pytest.mark.parametrize("suffix", [".log", ".asc", ".blf"])
def test_the_numpy_reader_gives_what_python_cans_reader_gives(tmp_path: Path, suffix: str) -> None:
    """The fast path (tools/buslog/frames.py) against python-can's LogReader, the reference: the same frames
    array for array, and the same trace bit for bit (stamps included)."""
    from drivectl.tools.buslog import log_to_trace
    from drivectl.tools.buslog.frames import Reading, read_frames

    log = tmp_path / f"x{suffix}"
    assert main(["trace", "--axis", "x", "--duration", "0.1", "--no-plot", "--quiet", "--bus-log", str(log),
                 "--out", str(tmp_path / "run")]) == 0
    got = {}
    for fast in (True, False):
        reading = Reading(log)
        chunks = list(read_frames(log, reading, fast=fast))
        got[fast] = [np.concatenate([getattr(c, k) for c in chunks]) for k in ("t", "cob", "dlc", "data")]
        assert ("numpy" in reading.reader) == fast and reading.truncated is None
    for a, b in zip(got[True], got[False], strict=True):
        assert a.dtype == b.dtype and np.array_equal(a, b)
    fast_t = log_to_trace(log, axis="x", out_dir=tmp_path / "f", fast=True)
    ref_t = log_to_trace(log, axis="x", out_dir=tmp_path / "r", fast=False)
    assert Trace.read(fast_t).meta["log_reader"].startswith("numpy")
    assert Trace.read(ref_t).meta["log_reader"].startswith("python-can")
    assert np.array_equal(_table(fast_t), _table(ref_t), equal_nan=True)


def test_numpy_reader_falls_back_on_lines_it_does_not_parse(tmp_path: Path) -> None:
    """Remote and extended frames, an FD frame and a CRLF line in a candump log: the block goes to python-can's
    reader, and the frames are the reference's."""
    from drivectl.tools.buslog.frames import Reading, read_frames

    log = tmp_path / "odd.log"
    log.write_bytes(b"(1.000000) can0 080#\n(1.000100) can0 181#3702A0860100\r\n(1.000200) can0 12345678#01\n"
                    b"(1.000300) can0 701#R\n(1.000400) can0 123##1001122\n(1.000500) can0 201#0F00E803\n")
    out = {}
    for fast in (True, False):
        reading = Reading(log)
        chunks = list(read_frames(log, reading, fast=fast))
        out[fast] = [np.concatenate([getattr(c, k) for c in chunks]) for k in ("t", "cob", "dlc", "data")]
    for a, b in zip(out[True], out[False], strict=True):
        assert np.array_equal(a, b)
    assert out[True][1].tolist() == [0x080, 0x181, -1, -1, -1, 0x201]


# -- the mapping from the log itself -----------------------------------------------------------------------------
def _canopen_master_log(tmp_path: Path, suffix: str = ".blf") -> tuple[Path, np.ndarray, np.ndarray]:
    """A log of canopen's own master (RemoteNode, PdoMap) driving the emulated drive in lockstep, with a mapping
    drivectl never configures: TPDO1 position + statusword, TPDO2 torque actual alone, RPDO2 target
    torque + controlword; RPDO1 disabled. Returns (log, the master's positions in counts and torques in per
    mille, one per SYNC once enabled)."""
    import canopen

    from drivectl.driver import cia402
    from drivectl.driver.network import Lockstep, LockstepNetwork, attach_bus_log, open_bus, unique_virtual_channel
    from drivectl.plant_emulator.models import load_plant
    from drivectl.plant_emulator.node402 import EMULATED_DRIVE_EDS, EmulatedDrive

    lockstep, channel = Lockstep(), unique_virtual_channel("buslog")
    emu = LockstepNetwork(open_bus("virtual", channel), lockstep)
    master = LockstepNetwork(open_bus("virtual", channel), lockstep)
    log = tmp_path / f"canopen{suffix}"
    bus_log = attach_bus_log(master, str(log))
    try:
        drive = EmulatedDrive(emu, 1, load_plant("rigid-x").build(0.001), rated_effort=100.0)
        node = canopen.BaseNode402(1, str(EMULATED_DRIVE_EDS))
        master.add_node(node)
        drive.boot()
        lockstep.advance(0.05)  # the drive's boot-up delay, in its own (simulated) time
        node.sdo[cia402.MODES_OF_OPERATION].raw = int(cia402.Mode.CYCLIC_SYNC_TORQUE)
        node.sdo[cia402.COMM_CYCLE_PERIOD].raw = 1000
        assert node.sdo[0x1008].raw == "drivectl emulated drive"  # a segmented upload
        with pytest.raises(canopen.SdoAbortedError):  # a segmented download of a read-only object: aborted
            node.sdo.download(0x1008, 0, b"another name, longer")
        for maps, wanted in ((node.tpdo, {1: [(0x6064, 0), (0x6041, 0)], 2: [(0x6077, 0)]}),
                             (node.rpdo, {2: [(0x6071, 0), (0x6040, 0)]})):
            maps.read()
            for k, pdo in maps.map.items():
                pdo.clear()
                for index, sub in wanted.get(k, []):
                    pdo.add_variable(index, sub)
                pdo.trans_type = 1
                pdo.enabled = k in wanted
                pdo.save()
        node.nmt.state = "OPERATIONAL"
        tpdo, rpdo = node.tpdo[1], node.rpdo[2]
        pos, tq = [], []
        for k in range(400):
            master.send_message(0x80, b"")  # SYNC: the drive steps its plant and answers at once (lockstep)
            cw = 0x06 if k < 3 else 0x0F
            torque = 0 if k < 6 else int(900 * np.sin(2 * np.pi * k / 200))  # 90 N: past the friction
            if k >= 6:
                pos.append(tpdo[0x6064].raw)
                tq.append(torque)
            rpdo[0x6040].raw = cw
            rpdo[0x6071].raw = torque
            rpdo.transmit()
        assert tpdo[0x6041].raw & 0x6F == 0x27  # Operation Enabled, as the drive reported it
        rpdo[0x6040].raw = 0x06  # shut down: the drive leaves Operation Enabled
        rpdo.transmit()
        master.send_message(0x80, b"")
        node.nmt.state = "PRE-OPERATIONAL"
    finally:
        bus_log.stop()
        master.disconnect()
        emu.disconnect()
    return log, np.asarray(pos), np.asarray(tq)


def test_a_log_of_canopens_own_master_with_its_own_mapping(tmp_path: Path, capsys) -> None:
    """Another master, another mapping: the mapping is replayed from the log's PDO configuration writes (the
    configuration's would read nothing of it), and the trace is the master's own view row for row."""
    log, pos, tq = _canopen_master_log(tmp_path)
    assert main(["trace", "--from-log", str(log), "--axis", "x", "--out", str(tmp_path / "c")]) == 0
    err = capsys.readouterr().err
    assert "mapping from the log's own PDO configuration SDO writes (TPDO1, TPDO2, RPDO2)" in err, err
    tr = Trace.read(tmp_path / "c" / "x.csv")
    ac = load_config().axis("x")
    assert tr.meta["dt_source"] == "0x1006 written in the log" and "vel_m_s" not in tr.columns
    assert "torque_actual" in tr.columns
    k = len(tr) - len(pos) - 1  # the rows once enabled; the last row is the shut-down
    assert k >= 0
    # to the trace format's 1 nm (pos_m is written %.9f), far within one encoder count
    assert np.abs(tr.pos[k : k + len(pos)] - pos * ac.encoder_m_per_count).max() <= 0.51e-9
    assert np.allclose(tr.effort[k : k + len(pos)], tq * ac.rated_effort / 1000.0, atol=1e-12)
    assert np.ptp(tr.pos) > 1e-5
    # the last SYNC got the drive's TPDOs but no RPDO (the master had sent its shut-down before it): lost
    assert np.flatnonzero(tr.columns["lost"]).tolist() == [len(tr) - 1] and np.isnan(tr.effort[-1])
    # decode reads the same mapping and names what canopen's master did
    assert main(["decode", str(log)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert any("SDO write 0x1A00:01 TPDO mapping parameter 1 / Mapping entry 1 = 1617166368 (0x60640020)" in s
               for s in out)
    assert any("-> Operation Enabled" in s for s in out) and any("Operation Enabled -> Ready To Switch On" in s
                                                                 for s in out)
    assert any(s.strip().split(" ", 1)[1].startswith("RPDO2 0x301: ") and "frames in second 0" in s for s in out)
    assert "mapping of node 1: the log's own PDO configuration SDO writes (TPDO1, TPDO2, RPDO2)" in out
    assert any(s.endswith("SDO read 0x1008:00 Manufacturer device name -> 'drivectl emulated drive' (segmented, 23 "
                          "bytes)") for s in out), out[:40]
    assert any("SDO abort 0x1008:00 Manufacturer device name by the drive: 0x0601000" in s for s in out)
    # with the mapping of the configuration instead (the log cut before the first SYNC: no writes), nothing of
    # this node's PDOs is what the configuration expects: refused in one line, nothing guessed
    import can

    cut = tmp_path / "late.blf"
    with can.LogReader(str(log)) as reader, can.Logger(str(cut)) as writer:
        started = False
        for msg in reader:
            started = started or msg.arbitration_id == 0x080
            if started:
                writer.on_message_received(msg)
    assert main(["trace", "--from-log", str(cut), "--axis", "x", "--out", str(tmp_path / "late")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "no PDOs of node 1 (COB-IDs 0x181, 0x281, 0x201)" in err


def test_pdo_of_the_wrong_length_is_counted_not_decoded(tmp_path: Path, capsys) -> None:
    import can

    log = tmp_path / "x.log"
    assert main(["trace", "--axis", "x", "--duration", "0.1", "--no-plot", "--quiet", "--bus-log", str(log),
                 "--out", str(tmp_path / "run")]) == 0
    bad = tmp_path / "bad.log"
    cut = 0
    with can.LogReader(str(log)) as reader, can.Logger(str(bad)) as writer:
        for msg in reader:
            if msg.arbitration_id == 0x181 and cut < 2 and msg.timestamp > 0:
                cut += 1
                msg = can.Message(timestamp=msg.timestamp, arbitration_id=0x181, data=msg.data[:5],
                                  is_extended_id=False, is_rx=msg.is_rx)
            writer.on_message_received(msg)
    capsys.readouterr()
    assert main(["trace", "--from-log", str(bad), "--axis", "x", "--out", str(tmp_path / "c")]) == 0
    tr = Trace.read(tmp_path / "c" / "x.csv")
    assert tr.meta["bad_length_pdos"] == "2" and tr.meta["bad_length_by_pdo"] == "TPDO1 2"
    capsys.readouterr()
    assert main(["decode", str(bad), "--json"]) == 0
    import json

    obj = json.loads(capsys.readouterr().out)
    assert obj["bad_length_pdos"] == {"TPDO1": 2}
    assert sum("5 bytes, the mapping has 6: not decoded" in e["text"] for e in obj["events"]) == 2
    # --all: one line per frame decoded, none for the two of the wrong length
    with can.LogReader(str(bad)) as reader:
        tpdo1 = sum(m.arbitration_id == 0x181 and len(m.data) == 6 for m in reader)
    assert main(["decode", str(bad), "--all"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert sum(" TPDO1 0x181: 0x6041 statusword " in s for s in lines) == tpdo1 > 50
    assert not any("frames in second" in s for s in lines)


def _fixed_eds(tmp_path: Path) -> Path:
    """The emulated drive's EDS with TPDO1 fixed as statusword + position + modes of operation display (7 bytes):
    a drive whose mapping a master cannot change (the log carries no writes of it)."""
    import canopen

    from drivectl.plant_emulator.node402 import EMULATED_DRIVE_EDS

    od = canopen.import_od(str(EMULATED_DRIVE_EDS), 1)
    rec = od[0x1A00]
    words = [0x60410010, 0x60640020, 0x60610008]
    rec[0].default, rec[0].default_raw, rec[0].access_type = len(words), None, "ro"
    for s, w in enumerate(words, 1):
        rec[s].default, rec[s].default_raw, rec[s].access_type = w, None, "ro"
    for s in rec.subindices:
        rec[s].access_type = "ro"
    path = tmp_path / "fixed.eds"
    canopen.export_od(od, str(path), doc_type="eds")
    return path


def _config(tmp_path: Path, eds: Path) -> Path:
    p = tmp_path / "machine.toml"
    p.write_text('cycle_s = 0.001\n[bus]\ninterface = "virtual"\nchannel = "drives"\n[axes.x]\nnode_id = 1\n'
                 f'eds = "{eds}"\nplant = "rigid-x"\ncontroller = "mbc"\nprofile = "short-move"\n'
                 "rated_effort = 100.0\n[axes.x.limits]\nposition_m = [-0.1, 0.1]\nmax_effort = 2000.0\n"
                 "following_error_m = 0.001\nfollowing_time_s = 0.01\n")
    return p


def _matches_run(conv: Trace, run: Trace, resolution: float, effort_q: float) -> None:
    offsets = _aligned(conv, run, resolution, effort_q)
    assert len(offsets) == 1, offsets


def test_a_fixed_mapping_from_the_eds_and_a_log_that_starts_after_the_bring_up(tmp_path: Path, capsys) -> None:
    """TPDO1 fixed in the EDS (7 bytes, not the default 6): the log carries no write of it, so it decodes by the
    EDS; then the same log cut after the bring-up (no PDO configuration writes at all, no 0x1006): the mapping of
    the configuration and its cycle, said so; the trace equals the run's rows it holds."""
    import can

    cfg = str(_config(tmp_path, _fixed_eds(tmp_path)))
    log = tmp_path / "x.asc"
    assert main(["--config", cfg, "trace", "--axis", "x", "--duration", "0.3", "--no-plot", "--quiet", "--bus-log",
                 str(log), "--out", str(tmp_path / "run")]) == 0
    run = Trace.read(tmp_path / "run" / "x.csv")
    capsys.readouterr()
    assert main(["--config", cfg, "trace", "--from-log", str(log), "--axis", "x", "--out", str(tmp_path / "c")]) == 0
    conv = Trace.read(tmp_path / "c" / "x.csv")
    assert ("TPDO1 COB-ID 0x181 type 1 (mapping: configuration, COB-ID and type: log): 0x6041 statusword + 0x6064 "
            "+ 0x6061") in conv.meta["mapping"]
    assert conv.meta["mapping_source"].startswith("the log's own PDO configuration SDO writes (TPDO2, RPDO1); the "
                                                  "mapping of TPDO1 from the configuration (full mapping planned on")
    _matches_run(conv, run, 76.29e-9, 0.05)
    # the log from its 50th SYNC on: the drive already configured, the master's writes not in it
    late = tmp_path / "late.asc"
    syncs = 0
    with can.LogReader(str(log)) as reader, can.Logger(str(late)) as writer:
        for msg in reader:
            syncs += msg.arbitration_id == 0x080
            if syncs >= 50:
                writer.on_message_received(msg)
    assert main(["--config", cfg, "trace", "--from-log", str(late), "--axis", "x", "--out", str(tmp_path / "l")]) == 0
    lt = Trace.read(tmp_path / "l" / "x.csv")
    assert lt.meta["mapping_source"].startswith("the configuration (full mapping planned on EDS")
    assert "the log carries no PDO configuration writes for node 1" in lt.meta["mapping_source"]
    assert lt.meta["dt_source"].endswith(": cycle") and lt.dt == pytest.approx(0.001)
    n = len(lt)
    assert n == len(conv) - 49 and np.array_equal(lt.pos, conv.pos[49:]) and np.array_equal(lt.effort, conv.effort[49:])


EDS_DIR = next((p / "shared" / "eds" for p in Path(__file__).resolve().parents if (p / "shared" / "eds").is_dir()),
               None)


@pytest.mark.skipif(EDS_DIR is None, reason="no shared/eds folder")
def test_real_drives_eds_logs_convert_as_their_runs(tmp_path: Path, capsys) -> None:
    """Each real drive's EDS in shared/eds that drivectl brings up: a run on the emulated drive impersonating it,
    recorded, converted by the mapping the log configured (or the EDS fixes), equals the run row for row. (None of
    the EDS files there fixes a mapping today; a drive that does decodes by its EDS, as the test above shows.)"""
    import canopen

    from drivectl.driver.pdo_plan import plan

    done = 0
    for eds in sorted(EDS_DIR.glob("*.eds")):
        try:
            plan(canopen.import_od(str(eds), 1), "full", 1, str(eds))
        except Exception:
            continue  # refused by drivectl (tests/test_drives.py covers that)
        cfg = str(_config(tmp_path, eds))
        log, out = tmp_path / f"{eds.stem}.blf", tmp_path / eds.stem
        if main(["--config", cfg, "trace", "--axis", "x", "--duration", "0.2", "--no-plot", "--quiet",
                 "--bus-log", str(log), "--out", str(out / "run")]) != 0:
            continue  # not brought up on the emulated drive (tests/test_drives.py says why)
        assert main(["--config", cfg, "trace", "--from-log", str(log), "--axis", "x", "--out", str(out / "c")]) == 0
        conv, run = Trace.read(out / "c" / "x.csv"), Trace.read(out / "run" / "x.csv")
        assert conv.meta["mapping_source"].startswith("the log's own PDO configuration SDO writes"), eds.name
        _matches_run(conv, run, 76.29e-9, 0.05)
        done += 1
    capsys.readouterr()
    assert done >= 1


def test_decode_names_an_emcy_and_the_fault_it_caused(tmp_path: Path, capsys) -> None:
    log = tmp_path / "fault.log"
    assert main(["trace", "--axis", "x", "--duration", "0.3", "--no-plot", "--quiet", "--fault", "emcy-fault@0.05",
                 "--bus-log", str(log), "--out", str(tmp_path / "run")]) == 3
    capsys.readouterr()
    assert main(["decode", str(log), "--json"]) == 0
    import json

    events = [e["text"] for e in json.loads(capsys.readouterr().out)["events"]]
    emcy = next(k for k, e in enumerate(events) if "EMCY 0x2310 continuous over-current (error register 0x01)" in e)
    assert any("-> Fault (statusword" in e for e in events[emcy:])


def _sdo_write(t: float, index: int, sub: int, value: int, size: int = 4) -> list:
    """An expedited SDO download to node 1 and the drive's confirmation, as can.Messages."""
    import can

    cmd = {1: 0x2F, 2: 0x2B, 4: 0x23}[size]
    req = bytes([cmd]) + index.to_bytes(2, "little") + bytes([sub]) + value.to_bytes(4, "little")
    ack = bytes([0x60]) + index.to_bytes(2, "little") + bytes([sub]) + bytes(4)
    return [can.Message(timestamp=t, arbitration_id=0x601, data=req, is_extended_id=False),
            can.Message(timestamp=t + 1e-4, arbitration_id=0x581, data=ack, is_extended_id=False)]


def test_a_reference_on_the_bus_becomes_ref_m(tmp_path: Path) -> None:
    """A master in cyclic synchronous position: its RPDO carries 0x607A (the reference) and 0x60B2 (a torque
    offset, the effort); no 0x6071. The mapping comes from the log's writes, the reference becomes ref_m."""
    import can
    import canopen
    from canopen.objectdictionary import INTEGER16, INTEGER32, ODVariable

    from drivectl.plant_emulator.node402 import EMULATED_DRIVE_EDS

    od = canopen.import_od(str(EMULATED_DRIVE_EDS), 1)
    for index, name, dtype in ((0x607A, "Target position", INTEGER32), (0x60B2, "Torque offset", INTEGER16)):
        var = ODVariable(name, index, 0)
        var.data_type, var.access_type, var.pdo_mappable = dtype, "rw", True
        od.add_object(var)
    eds = tmp_path / "csp.eds"
    canopen.export_od(od, str(eds), doc_type="eds")
    msgs = []
    for k, (index, sub, value, size) in enumerate([
            (0x1006, 0, 2000, 4), (0x1400, 1, 0x80000201, 4), (0x1600, 0, 0, 1), (0x1600, 1, 0x607A0020, 4),
            (0x1600, 2, 0x60B20010, 4), (0x1600, 0, 2, 1), (0x1400, 1, 0x201, 4), (0x1801, 1, 0x80000281, 4)]):
        msgs += _sdo_write(0.001 * k, index, sub, value, size)
    for k in range(60):
        t = 0.1 + 0.002 * k
        msgs.append(can.Message(timestamp=t, arbitration_id=0x080, data=b"", is_extended_id=False))
        msgs.append(can.Message(timestamp=t + 1e-4, arbitration_id=0x181, is_extended_id=False,
                                data=(0x1237).to_bytes(2, "little") + (10 * k).to_bytes(4, "little", signed=True)))
        msgs.append(can.Message(timestamp=t + 3e-4, arbitration_id=0x201, is_extended_id=False,
                                data=(10 * k + 5).to_bytes(4, "little", signed=True) + (-100).to_bytes(2, "little",
                                                                                                      signed=True)))
    log = tmp_path / "csp.log"
    with can.Logger(str(log)) as writer:
        for m in msgs:
            writer.on_message_received(m)
    from drivectl.tools.buslog import log_to_trace

    tr = Trace.read(log_to_trace(log, axis="x", out_dir=tmp_path / "c", eds=eds))
    res = 76.29e-9
    assert tr.meta["ref"] == "0x607A target position" and tr.meta["dt_source"] == "0x1006 written in the log"
    assert tr.dt == pytest.approx(0.002) and len(tr) == 60 and tr.meta["lost_rows"] == "0"
    assert tr.meta["mapping_source"].startswith("the log's own PDO configuration SDO writes (RPDO1); the mapping "
                                                "of TPDO1 from the configuration")
    assert np.allclose(tr.ref, (10 * np.arange(60) + 5) * res, atol=0.51e-9)  # ref_m and pos_m: %.9f in the file
    assert np.allclose(tr.pos, 10 * np.arange(60) * res, atol=0.51e-9)
    assert np.allclose(tr.effort, -100 * 100.0 / 1000, atol=1e-12)  # 0x60B2 through the rated effort
    # without the torque offset the master commands no effort: refused in one line, no trace half-made
    msgs2 = [m for m in msgs if not (m.arbitration_id == 0x601 and m.data[1:4] == b"\x00\x16\x02")]
    for m in msgs2:
        if m.arbitration_id == 0x601 and m.data[1:4] == b"\x00\x16\x00" and m.data[4] == 2:
            m.data[4] = 1  # one entry: 0x607A alone
        if m.arbitration_id == 0x201:
            m.data = m.data[:4]
            m.dlc = 4
    log2 = tmp_path / "csp-no-effort.log"
    with can.Logger(str(log2)) as writer:
        for m in msgs2:
            writer.on_message_received(m)
    with pytest.raises(BusLogError, match=r"csp-no-effort.log: node 1 has no commanded effort \(0x6071 or 0x60B2\) in "
                       r"its RPDOs: nothing to trace"):
        log_to_trace(log2, axis="x", out_dir=tmp_path / "c2", eds=eds)
    assert not (tmp_path / "c2").exists() or not list((tmp_path / "c2").iterdir())


def test_health_ingest_takes_a_bus_log(tmp_path: Path, capsys) -> None:
    pytest.importorskip("pyarrow")
    log = tmp_path / "x.log"
    assert main(["trace", "--axis", "x", "--duration", "0.05", "--no-plot", "--quiet", "--bus-log", str(log),
                 "--out", str(tmp_path / "run")]) == 0
    capsys.readouterr()
    assert main(["health", "ingest", str(log), "--machine", "m1", "--axis", "x", "--store", str(tmp_path / "s")]) == 0
    assert "1 added" in capsys.readouterr().out


# -- lost, late, truncated ---------------------------------------------------------------------------------------
def test_a_late_pdo_flags_its_row_and_is_not_moved(tmp_path: Path) -> None:
    """TPDO1 of one SYNC sent after the next SYNC: that row is lost (NaN position), the next row takes the
    later frame; nothing is interpolated."""
    import can

    log = tmp_path / "x.log"
    assert main(["trace", "--axis", "x", "--duration", "0.1", "--no-plot", "--quiet", "--bus-log", str(log),
                 "--out", str(tmp_path / "run")]) == 0
    late = tmp_path / "late.log"
    syncs, held = 0, None
    with can.LogReader(str(log)) as reader, can.Logger(str(late)) as writer:
        for msg in reader:
            if msg.arbitration_id == 0x080:
                syncs += 1
                writer.on_message_received(msg)
                if held is not None:
                    writer.on_message_received(held)
                    held = None
                continue
            if msg.arbitration_id == 0x181 and syncs == 40:
                held = msg
                continue
            writer.on_message_received(msg)
    from drivectl.tools.buslog import log_to_trace

    tr = Trace.read(log_to_trace(late, axis="x", out_dir=tmp_path / "c"))
    ref = Trace.read(log_to_trace(log, axis="x", out_dir=tmp_path / "r"))
    lost = np.flatnonzero(tr.columns["lost"])
    assert lost.tolist() == [39] and np.isnan(tr.pos[39]) and tr.meta["lost_rows"] == "1"
    assert np.array_equal(np.delete(tr.pos, [39, 40]), np.delete(ref.pos, [39, 40]))


@pytest.mark.parametrize("suffix", [".log", ".asc", ".blf"])
def test_a_truncated_log_is_read_as_far_as_it_goes_and_said(tmp_path: Path, suffix: str, capsys) -> None:
    log = tmp_path / f"x{suffix}"
    assert main(["trace", "--axis", "x", "--duration", "0.3", "--no-plot", "--quiet", "--bus-log", str(log),
                 "--out", str(tmp_path / "run")]) == 0
    data = log.read_bytes()
    cut = tmp_path / f"cut{suffix}"
    cut.write_bytes(data[: len(data) * 2 // 3 + 5])  # mid-line, mid-container: as a killed recorder leaves it
    capsys.readouterr()
    assert main(["trace", "--from-log", str(cut), "--axis", "x", "--out", str(tmp_path / "c")]) == 0
    err = capsys.readouterr().err
    assert f"{cut}: truncated: read as far as it goes" in err, err
    tr = Trace.read(tmp_path / "c" / "x.csv")
    full = Trace.read(log_to_trace_default(log, tmp_path / "f"))
    assert tr.meta["truncated"] and 50 < len(tr) < len(full)
    ok = ~tr.columns["lost"].astype(bool)
    assert np.array_equal(tr.pos[ok], full.pos[: len(tr)][ok])
    assert main(["decode", str(cut)]) == 0
    assert any("truncated: read as far as it goes" in s for s in capsys.readouterr().out.splitlines())


def log_to_trace_default(log: Path, out: Path) -> Path:
    from drivectl.tools.buslog import log_to_trace

    return log_to_trace(log, axis="x", out_dir=out)


# -- explain, replay ---------------------------------------------------------------------------------------------
def test_explain_on_a_log_names_the_effect_hidden_in_the_emulated_plant(tmp_path: Path, capsys) -> None:
    """The run hides viscous friction at 0.47 of the model's; explain takes the log itself (converted in the
    same step) and names it, with no reference on the bus."""
    import json

    log = tmp_path / "machine.blf"
    assert main(["trace", "--axis", "x", "--effect", "viscous:scale=0.47", "--duration", "1.2", "--no-plot", "--quiet",
                 "--bus-log", str(log), "--out", str(tmp_path / "run")]) == 0
    capsys.readouterr()
    assert main(["explain", str(log), "--axis", "x", "--plant", "rigid-x", "--quiet", "--json",
                 "--out", str(tmp_path / "ex")]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["effect"] == "viscous" and res["params"]["scale"] == pytest.approx(0.47, rel=0.05)
    assert (tmp_path / "ex" / "x.csv").exists()  # the converted trace beside the report


def test_replay_plays_the_drives_frames_with_their_timing(tmp_path: Path) -> None:
    import can

    from drivectl.driver.network import unique_virtual_channel

    log = tmp_path / "x.log"
    assert main(["trace", "--axis", "x", "--duration", "0.02", "--no-plot", "--quiet", "--bus-log", str(log),
                 "--out", str(tmp_path / "run")]) == 0
    with can.LogReader(str(log)) as reader:
        recorded = [m for m in reader if m.arbitration_id in (0x081, 0x181, 0x281, 0x381, 0x481, 0x581, 0x701)]
    channel = unique_virtual_channel("replay")
    rx = can.Bus(interface="virtual", channel=channel)
    try:
        # 1000 times as fast: MessageSync still orders and paces the frames, the test does not wait for them
        assert main(["replay", str(log), "--interface", "virtual", "--channel", channel, "--node", "1",
                     "--speed", "1000", "--loop", "2"]) == 0
        got = []
        while (m := rx.recv(timeout=0)) is not None:
            got.append(m)
    finally:
        rx.shutdown()
    assert len(got) == 2 * len(recorded)
    assert [(m.arbitration_id, bytes(m.data)) for m in got[: len(recorded)]] == \
        [(m.arbitration_id, bytes(m.data)) for m in recorded]
    assert main(["replay", str(log), "--interface", "virtual", "--channel", channel, "--speed", "0"]) == 2
    # --loop i ends on a stop request (a signal: read after every frame), not at the log's end
    import math

    from drivectl.tools.buslog.replay import replay

    tx = can.Bus(interface="virtual", channel=channel)
    try:
        asked = iter(range(10**9))
        sent = replay(log, tx, only=frozenset([0x181]), speed=1000, loops=math.inf, stop=lambda: next(asked) >= 250)
    finally:
        tx.shutdown()
    assert 0 < sent < 250 and sent > sum(m.arbitration_id == 0x181 for m in recorded)  # past one pass of the log

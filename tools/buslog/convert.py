"""A CANopen bus log to trace format v1: one row per SYNC (docs/trace-format.md, docs/guide/buslog.md).

The log is streamed through python-can's :class:`can.LogReader` (the reader by the file's suffix). The node's
PDOs are found by the mapping drivectl plans for the drive (driver/pdo_plan.py on the drive's EDS) and unpacked
with the same :class:`~drivectl.driver.pdo.PdoLayout` the master uses; counts and per mille become metres and
the effort unit through driver/units.py, as on the live bus. The frames between one SYNC and the next belong
to that SYNC's row: the TPDOs the drive sent for it and the RPDO the master answered with. A SYNC without all
of them is a row flagged ``lost`` (its missing values NaN, never interpolated).
"""

from __future__ import annotations

import math
import struct
from pathlib import Path
from typing import Any

import can
import canopen
import numpy as np

from drivectl.driver import cia402
from drivectl.driver.cia301 import SYNC_COB_ID
from drivectl.driver.pdo import PdoLayout
from drivectl.driver.pdo_plan import plan as plan_pdos
from drivectl.driver.units import EffortScale, Encoder
from drivectl.errors import InputError
from drivectl.tracefile.format import file_sha256

#: the suffixes can.LogReader reads (.mf4 where python-can's asammdf extra is installed)
LOG_SUFFIXES = (".asc", ".blf", ".log", ".trc", ".csv", ".mf4")
SDO_RX_BASE = 0x600  # client -> server (the master's requests)


class BusLogError(InputError):
    """A bus log that cannot be turned into a trace; one line naming the file."""


def is_bus_log(path: str | Path) -> bool:
    """Whether ``path`` is named as a CAN log python-can reads (by its suffix, as can.LogReader chooses). A .csv
    is both a python-can log and a drivectl trace: one that starts as a trace (``# drivectl trace``) is not a log."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".csv":
        try:
            with open(path, "rb") as f:
                return not f.read(64).lstrip(b"\xef\xbb\xbf").startswith(b"# drivectl trace")
        except OSError:
            return True  # unreadable: the log reader says so in one line
    return suffix in LOG_SUFFIXES


def check_log(log: Path) -> Path:
    """``log`` as a Path, or :class:`BusLogError` in one line when it is not a log python-can reads or is not
    there (decode and trace --from-log refuse the same way)."""
    log = Path(log)
    if not is_bus_log(log):
        raise BusLogError(f"{log}: not a CAN log python-can reads (suffix {log.suffix or 'none'}; expected one of "
                          f"{', '.join(LOG_SUFFIXES)})")
    if not log.is_file():
        raise BusLogError(f"{log}: no such log file")
    return log


def _mapping(cfg: Any) -> str:
    from drivectl.machine.bus_budget import resolve_mapping

    return resolve_mapping(cfg, 1)


def _effort_unit(cfg: Any, axis: str) -> str:
    """The axis's effort unit (N or V) as its plant in the configuration says."""
    from drivectl.machine.build import plant_specs

    return plant_specs(cfg, [axis])[axis].effort_unit


def log_to_trace(log: Path, *, axis: str, out_dir: Path, node: int | None = None, eds: Path | None = None,
                 config: Any = None) -> Path:
    """Convert the bus log ``log`` to a trace of ``axis`` in ``out_dir`` (``AXIS-STAMP.csv`` and ``AXIS.csv``);
    returns the file written. ``node`` and ``eds`` override the configuration's; ``config`` is a
    MachineConfig or a path (None: $DRIVECTL_CONFIG, else the embedded machine). Raises :class:`BusLogError`."""
    from drivectl.machine.config import MachineConfig, load_config
    from drivectl.tracefile.stream import TraceWriter

    log = check_log(log)
    cfg = config if isinstance(config, MachineConfig) else load_config(config)
    ac = cfg.axis(axis)
    node_id = ac.node_id if node is None else node
    if not 1 <= node_id <= 127:
        raise BusLogError(f"{log}: --node {node_id}: expected 1..127")
    eds_path = str(eds) if eds is not None else ac.eds
    try:
        od = canopen.import_od(eds_path, node_id)
    except Exception as exc:  # canopen raises many types for a bad file
        reason = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise BusLogError(f"{log}: EDS {eds_path}: cannot be read: {reason}") from None
    mapping = _mapping(cfg)
    pdo_plan = plan_pdos(od, mapping, node_id, f"{log}: EDS {eds_path}")
    tx = [(p.cob_id, PdoLayout.from_entries(od, p.entries)) for p in pdo_plan.tx]
    rx = [(p.cob_id, PdoLayout.from_entries(od, p.entries)) for p in pdo_plan.rx if p.trans_type <= 240]
    at = {e: (k, j) for k, (_, lay) in enumerate(tx + rx) for j, e in enumerate(lay.entries)}
    if (cia402.POSITION_ACTUAL, 0) not in at or (cia402.TARGET_TORQUE, 0) not in at:
        raise BusLogError(f"{log}: mapping {mapping} of {eds_path} carries no position 0x6064 or target torque 0x6071")
    slot_of = {cob: k for k, (cob, _) in enumerate(tx + rx)}
    layouts = [lay for _, lay in tx + rx]
    enc, scale = Encoder(ac.encoder_m_per_count), EffortScale(ac.rated_effort)
    vel_at = at.get((cia402.VELOCITY_ACTUAL, 0))
    tq_at = at.get((cia402.TORQUE_ACTUAL, 0))
    pos_at, eff_at = at[(cia402.POSITION_ACTUAL, 0)], at[(cia402.TARGET_TORQUE, 0)]
    sdo_cob = SDO_RX_BASE + node_id
    period_us: int | None = None

    rows: list[tuple[float, ...]] = []  # (frame time, pos, effort, vel, torque, lost)
    window: list[tuple[int, ...] | None] = [None] * len(layouts)
    sync_at: float | None = None
    frames = 0
    pdo_frames = 0
    bad_length = 0

    def close_window() -> None:
        lost = any(v is None for v in window)

        def value(where: tuple[int, int] | None, conv) -> float:
            if where is None:
                return math.nan
            raw = window[where[0]]
            return math.nan if raw is None else conv(raw[where[1]])

        rows.append((sync_at, value(pos_at, enc.from_counts), value(eff_at, scale.from_permille),
                     value(vel_at, enc.from_counts), value(tq_at, scale.from_permille), 1.0 if lost else 0.0))
        window[:] = [None] * len(layouts)

    try:
        with can.LogReader(str(log)) as reader:
            for msg in reader:
                frames += 1
                if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
                    continue
                cob = msg.arbitration_id
                if cob == SYNC_COB_ID:
                    if sync_at is not None:
                        close_window()
                    sync_at = msg.timestamp
                    continue
                k = slot_of.get(cob)
                if k is not None:
                    if sync_at is None:
                        continue  # before the first SYNC: no row to belong to
                    pdo_frames += 1
                    lay = layouts[k]
                    if len(msg.data) != lay.codec.size:
                        bad_length += 1  # not the mapping's length: never decoded by guess
                        continue
                    window[k] = lay.codec.unpack(bytes(msg.data))
                elif cob == sdo_cob and len(msg.data) == 8 and msg.data[0] & 0xE3 == 0x23:
                    # an expedited download with the size given: the 0x1006 the master wrote
                    index, sub = struct.unpack_from("<HB", msg.data, 1)
                    if index == cia402.COMM_CYCLE_PERIOD and sub == 0:
                        period_us = struct.unpack_from("<I", msg.data, 4)[0]
    except (ValueError, OSError, struct.error, EOFError) as exc:
        if not frames:
            reason = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
            raise BusLogError(f"{log}: not a readable {log.suffix} CAN log: {reason}") from None
        raise BusLogError(f"{log}: unreadable after frame {frames}: {exc}") from None
    except Exception as exc:  # python-can's readers raise their parsers' own errors on garbage
        reason = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise BusLogError(f"{log}: not a readable {log.suffix} CAN log: {reason}") from None
    if sync_at is not None:
        close_window()
    if not frames:
        raise BusLogError(f"{log}: no CAN frames in it (not a {log.suffix} log, or an empty one)")
    if not pdo_frames:
        raise BusLogError(f"{log}: no PDOs of node {node_id} (COB-IDs "
                          f"{', '.join(f'0x{c:03X}' for c in slot_of)}) after a SYNC, in {frames} frames")
    if period_us:
        dt, dt_source = period_us * 1e-6, "0x1006 written in the log"
    else:
        dt, dt_source = cfg.cycle_s, f"{cfg.source}: cycle"
    data = np.asarray(rows, dtype=float)
    n = len(data)
    stamps = data[:, 0]
    jitter = np.diff(stamps) - np.median(np.diff(stamps)) if n > 1 else np.zeros(1)
    columns = ["time_s", "ref_m", "pos_m", "effort"]
    extra = []
    if vel_at is not None:
        extra.append(("vel_m_s", 3))
    if tq_at is not None:
        extra.append(("torque_actual", 4))
    columns += [name for name, _ in extra] + ["frame_time_s", "lost"]
    meta = {
        "axis": axis, "effort_unit": _effort_unit(cfg, axis), "dt_s": dt, "dt_source": dt_source,
        "ref": "none", "source": "bus log", "bus_log": str(log), "bus_log_sha256": file_sha256(log),
        "node": node_id, "mapping": mapping, "mapping_source": f"{mapping} mapping planned on {eds_path} (not read "
        "from the log's SDO writes)", "encoder_m_per_count": enc.resolution, "rated_effort": scale.rated,
        "config": cfg.source,
    }
    table = np.empty((n, len(columns)))
    table[:, 0] = np.arange(n) * dt
    table[:, 1] = math.nan
    table[:, 2] = data[:, 1]
    table[:, 3] = data[:, 2]
    for c, (_, src) in enumerate(extra, 4):
        table[:, c] = data[:, src]
    table[:, -2] = stamps - stamps[0]
    table[:, -1] = data[:, 5]
    writer = TraceWriter(out_dir, axis, columns=columns, meta=meta).start()
    try:
        for i in range(0, n, 65536):
            writer.extend(table[i : i + 65536])
    except BaseException:
        writer.abandon()
        raise
    return writer.close({"frames": frames, "syncs": n, "lost_rows": int(data[:, 5].sum()),
                         "bad_length_pdos": bad_length, "frame_jitter_max_s": float(np.max(np.abs(jitter)))})

"""A CANopen bus log to trace format v1: one row per SYNC (docs/trace-format.md, docs/guide/buslog.md).

The log is read in chunks of arrays (tools/buslog/frames.py: numpy for candump .log and hex .asc, python-can's
LogReader for every other suffix) and walked once (tools/buslog/stream.py): the node's PDO configuration SDO
writes are replayed into its mapping (tools/buslog/mapping.py, the driver's own PdoLayout), and the PDOs are
unpacked a column at a time by the mapping in force when they were sent. Counts and per mille become metres
and the effort unit through driver/units.py, as on the live bus. The frames between one SYNC and the next
belong to that SYNC's row: the TPDOs the drive sent for it and the RPDO the master answered with. A SYNC
without every PDO the mapping sends at each SYNC (a lost one, or one that came after the next SYNC) is a row
flagged ``lost``, its missing values NaN, never interpolated. Rows are streamed to the trace writer as they
complete: memory does not grow with the log.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import canopen
import numpy as np

from drivectl.driver import cia402
from drivectl.driver.cia301 import SYNC_COB_ID
from drivectl.driver.units import EffortScale, Encoder
from drivectl.errors import InputError
from drivectl.tracefile.format import file_sha256

#: the suffixes can.LogReader reads (.mf4 where python-can's asammdf extra is installed)
LOG_SUFFIXES = (".asc", ".blf", ".log", ".trc", ".csv", ".mf4")
TORQUE_OFFSET = 0x60B2  # per mille of rated, the torque feed-forward a master may command instead of 0x6071
TARGET_POSITION = 0x607A  # counts (CSP's reference)
TARGET_VELOCITY = 0x60FF  # counts/s (CSV's reference)
#: the row's fields and the object each comes from
FIELDS = ("pos", "effort", "vel", "tq", "ref_pos", "ref_vel")
_OBJECT = {"pos": cia402.POSITION_ACTUAL, "vel": cia402.VELOCITY_ACTUAL, "tq": cia402.TORQUE_ACTUAL,
           "ref_pos": TARGET_POSITION, "ref_vel": TARGET_VELOCITY}
_F = {name: k for k, name in enumerate(FIELDS)}


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
    if log.suffix.lower() == ".mf4":
        try:
            import asammdf  # noqa: F401  (python-can's MF4 reader needs it)
        except ImportError:
            raise BusLogError(f"{log}: an .mf4 log needs python-can's asammdf extra (pip install asammdf)") from None
    return log


def load_od(log: Path, eds: str, node: int) -> canopen.ObjectDictionary:
    try:
        return canopen.import_od(eds, node)
    except Exception as exc:  # canopen raises many types for a bad file
        reason = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise BusLogError(f"{log}: EDS {eds}: cannot be read: {reason}") from None


def _effort_unit(cfg: Any, axis: str) -> str:
    """The axis's effort unit (N or V) as its plant in the configuration says."""
    from drivectl.machine.build import plant_specs

    return plant_specs(cfg, [axis])[axis].effort_unit


def _where(pdos: list) -> dict[str, tuple[int, int]]:
    """field -> (index of the PDO in ``pdos``, entry) for the fields the mapping carries; the effort is 0x6071,
    else 0x60B2."""
    out: dict[str, tuple[int, int]] = {}
    for k, a in enumerate(pdos):
        for j, (index, sub) in enumerate(a.layout.entries):
            if sub:
                continue
            for name, obj in _OBJECT.items():
                if index == obj and a.config.rx == name.startswith("ref"):
                    out.setdefault(name, (k, j))
            if a.config.rx and index == cia402.TARGET_TORQUE:
                out["effort"] = (k, j)
            elif a.config.rx and index == TORQUE_OFFSET:
                out.setdefault("effort", (k, j))
    return out


class _Rows:
    """Rows of one SYNC window each, completed chunk by chunk (the open window carried to the next chunk)."""

    def __init__(self) -> None:
        n = len(FIELDS)
        self.vals = np.full(n, math.nan)
        self.have = np.zeros(n, bool)
        self.expect = np.zeros(n, bool)
        self.stamp: float | None = None  # the open window's SYNC (None: no SYNC yet)
        self.bad_length: dict[str, int] = {}
        self.pdo_frames = 0

    def chunk(self, fr, segments) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(stamps, values, have, expect) of the windows this chunk completed."""
        is_sync = fr.cob == SYNC_COB_ID
        win = np.cumsum(is_sync)
        nsync = int(win[-1]) if len(win) else 0
        n = len(FIELDS)
        vals = np.full((nsync + 1, n), math.nan)
        have = np.zeros((nsync + 1, n), bool)
        expect = np.zeros((nsync + 1, n), bool)
        vals[0], have[0], expect[0] = self.vals, self.have, self.expect
        sync_idx = np.flatnonzero(is_sync)
        stamps = np.empty(nsync + 1)
        stamps[0] = math.nan if self.stamp is None else self.stamp
        stamps[1:] = fr.t[sync_idx]
        for a, b, pdos in segments:
            where = _where(pdos)
            exp = np.zeros(n, bool)
            for name, (k, _) in where.items():
                exp[_F[name]] = pdos[k].config.cyclic
            opened = win[sync_idx[(sync_idx >= a) & (sync_idx < b)]]
            expect[opened] = exp
            cob = fr.cob[a:b]
            for k, pdo in enumerate(pdos):
                idx = np.flatnonzero(cob == pdo.cob) + a
                if not len(idx):
                    continue
                self.pdo_frames += len(idx)
                size = pdo.layout.codec.size
                ok = fr.dlc[idx] == size
                if not ok.all():  # not the mapping's length: counted, never decoded by guess
                    name = pdo.config.name
                    self.bad_length[name] = self.bad_length.get(name, 0) + int((~ok).sum())
                    idx = idx[ok]
                w = win[idx]
                last = np.concatenate([w[1:] != w[:-1], [True]]) if len(w) else w.astype(bool)
                idx, w = idx[last], w[last]  # two of one PDO in a window (one came late): the later one
                rec = np.ascontiguousarray(fr.data[idx, :size]).view(pdo.dtype).ravel()
                for name, (kk, j) in where.items():
                    if kk == k:
                        vals[w, _F[name]] = rec[f"f{j}"]
                        have[w, _F[name]] = True
        self.vals, self.have, self.expect = vals[-1].copy(), have[-1].copy(), expect[-1].copy()
        self.stamp = float(stamps[-1]) if nsync or self.stamp is not None else None
        done = slice(0, nsync)
        keep = np.isfinite(stamps[done])  # the frames before the log's first SYNC belong to no row
        return stamps[done][keep], vals[done][keep], have[done][keep], expect[done][keep]

    def last(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The window still open at the end of the log."""
        if self.stamp is None:
            return np.zeros(0), np.zeros((0, len(FIELDS))), np.zeros((0, len(FIELDS)), bool), \
                np.zeros((0, len(FIELDS)), bool)
        return np.array([self.stamp]), self.vals[None], self.have[None], self.expect[None]


def log_to_trace(log: Path, *, axis: str, out_dir: Path, node: int | None = None, eds: Path | None = None,
                 config: Any = None, mapping_base: str = "configuration", fast: bool | None = None,
                 progress: bool = False) -> Path:
    """Convert the bus log ``log`` to a trace of ``axis`` in ``out_dir`` (``AXIS-STAMP.csv`` and ``AXIS.csv``);
    returns the file written. ``node`` and ``eds`` override the configuration's; ``config`` is a
    MachineConfig or a path (None: $DRIVECTL_CONFIG, else the embedded machine). ``mapping_base``: where the
    mapping comes from for the PDOs the log does not configure ("configuration" or "eds"). ``fast``: the
    reader (tools/buslog/frames.py read_frames). Raises :class:`BusLogError`; a truncated log gives the trace
    of what it holds, with ``truncated`` in its trailer."""
    from drivectl.machine.bus_budget import resolve_mapping
    from drivectl.machine.config import MachineConfig, load_config
    from drivectl.tools.buslog.frames import Reading
    from drivectl.tools.buslog.mapping import NodeMapping
    from drivectl.tools.buslog.stream import Jitter, Walk
    from drivectl.tracefile.stream import TraceWriter

    log = check_log(log)
    cfg = config if isinstance(config, MachineConfig) else load_config(config)
    ac = cfg.axis(axis)
    node_id = ac.node_id if node is None else node
    if not 1 <= node_id <= 127:
        raise BusLogError(f"{log}: --node {node_id}: expected 1..127")
    eds_path = str(eds) if eds is not None else ac.eds
    od = load_od(log, eds_path, node_id)
    mapping = resolve_mapping(cfg, 1)
    nm = NodeMapping(od, node_id, mapping, f"EDS {eds_path}", base=mapping_base)
    walk = Walk(node_id, nm)
    reading = Reading(log)
    enc, scale = Encoder(ac.encoder_m_per_count), EffortScale(ac.rated_effort)
    rows = _Rows()
    jitter = Jitter()
    writer: TraceWriter | None = None
    state: dict[str, Any] = {"n": 0, "t0": None, "lost": 0, "skipped": 0, "ref0": None, "ref_int": 0.0}
    cols: dict[str, Any] = {}

    def dt_now() -> tuple[float, str]:
        if walk.period_us:
            return walk.period_us * 1e-6, "0x1006 written in the log"
        return cfg.cycle_s, f"{cfg.source}: cycle"

    def open_writer(where: dict) -> TraceWriter:
        dt, dt_source = dt_now()
        columns = ["time_s", "ref_m", "pos_m", "effort"]
        extra = [("vel_m_s", "vel"), ("torque_actual", "tq")]
        extra = [(c, f) for c, f in extra if f in where]
        columns += [c for c, _ in extra] + ["frame_time_s", "lost"]
        cols.update(extra=extra, dt=dt, ref="ref_pos" if "ref_pos" in where else "ref_vel" if "ref_vel" in where
                    else None)
        ref_meta = {"ref_pos": "0x607A target position", "ref_vel": "0x60FF target velocity, integrated from "
                    "the first position"}.get(cols["ref"], "none")
        meta = {
            "axis": axis, "effort_unit": _effort_unit(cfg, axis), "dt_s": dt, "dt_source": dt_source,
            "ref": "none" if cols["ref"] is None else ref_meta, "source": "bus log", "bus_log": str(log),
            "bus_log_sha256": file_sha256(log), "node": node_id, "mapping": " | ".join(nm.describe()),
            "mapping_source": nm.source, "log_reader": reading.reader, "encoder_m_per_count": enc.resolution,
            "rated_effort": scale.rated, "config": cfg.source,
        }
        return TraceWriter(out_dir, axis, columns=columns, meta=meta).start()

    def emit(stamps, vals, have, expect) -> None:
        nonlocal writer
        if not len(stamps):
            return
        jitter.add(stamps, dt_now()[0])
        # lost: a PDO the mapping sends at every SYNC did not come for it, or the row has no position or no
        # effort (a trace needs both: docs/trace-format.md)
        lost = (expect & ~have).any(axis=1) | ~have[:, _F["pos"]] | ~have[:, _F["effort"]]
        if writer is None:
            good = np.flatnonzero(~lost)
            if not len(good):
                state["skipped"] += len(stamps)
                return
            first = int(good[0])
            state["skipped"] += first
            stamps, vals, lost = stamps[first:], vals[first:], lost[first:]
            writer = open_writer(_where(nm.active()))
            state["t0"] = float(stamps[0])
        n = len(stamps)
        dt = cols["dt"]
        table = np.empty((n, 6 + len(cols["extra"])))
        table[:, 0] = (state["n"] + np.arange(n)) * dt
        pos = vals[:, _F["pos"]] * enc.resolution
        if cols["ref"] == "ref_pos":
            table[:, 1] = vals[:, _F["ref_pos"]] * enc.resolution
        elif cols["ref"] == "ref_vel":
            if state["ref0"] is None:
                state["ref0"] = float(pos[0])
            step = np.nan_to_num(vals[:, _F["ref_vel"]]) * enc.resolution * dt
            integ = state["ref_int"] + np.cumsum(step) - step  # the reference at the row's SYNC
            state["ref_int"] = float(integ[-1] + step[-1])
            table[:, 1] = state["ref0"] + integ
        else:
            table[:, 1] = math.nan
        table[:, 2] = pos
        table[:, 3] = vals[:, _F["effort"]] * (scale.rated / 1000.0)
        for c, (_, f) in enumerate(cols["extra"], 4):
            table[:, c] = vals[:, _F[f]] * (enc.resolution if f == "vel" else scale.rated / 1000.0)
        table[:, -2] = stamps - state["t0"]
        table[:, -1] = lost
        writer.extend(table)
        state["n"] += n
        state["lost"] += int(lost.sum())

    try:
        for fr, segments in walk.chunks(log, reading, fast=fast, progress=progress):
            emit(*rows.chunk(fr, segments))
        emit(*rows.last())
    except BaseException:
        if writer is not None:
            writer.abandon()
        raise
    if not reading.frames:
        raise BusLogError(f"{log}: no CAN frames in it (not a {log.suffix} log, or an empty one)")
    if writer is None:
        where = _where(nm.active())
        if rows.pdo_frames and ("effort" not in where or "pos" not in where):
            what = "commanded effort (0x6071 or 0x60B2) in its RPDOs" if "effort" not in where else \
                "position 0x6064 in its TPDOs"
            raise BusLogError(f"{log}: node {node_id} has no {what}: nothing to trace (mapping from {nm.source})")
        cobs = ", ".join(f"0x{a.cob:03X}" for a in nm.active()) or "none valid"
        why = f"; {nm.errors[0]}" if nm.errors else ""
        raise BusLogError(f"{log}: no PDOs of node {node_id} (COB-IDs {cobs}) after a SYNC, in {reading.frames} "
                          f"frames{why}")
    trailer: dict[str, Any] = {"frames": reading.frames, "syncs": state["n"], "lost_rows": state["lost"],
                               "syncs_before_first_pdos": state["skipped"],
                               "bad_length_pdos": sum(rows.bad_length.values()),
                               "bad_length_by_pdo": ", ".join(f"{k} {v}" for k, v in rows.bad_length.items()) or
                               "none"}
    trailer.update(jitter.report(cols["dt"]))
    if reading.truncated:
        trailer["truncated"] = reading.truncated
    if nm.errors:
        trailer["mapping_notes"] = "; ".join(nm.errors)
    return writer.close(trailer)

"""``drivectl decode LOG``: a CANopen / CiA 402 reading of a bus log, one line per event (docs/guide/buslog.md).

NMT commands, boot-ups and heartbeat state changes; the node's SDO transfers (expedited and segmented, joined:
tools/buslog/sdo.py) with the object's name from the EDS (canopen's object dictionary), aborts by name; EMCY by
its error code's name (driver/cia402.py); CiA 402 power-state transitions from the statusword; the node's PDOs
decoded by the mapping in force (replayed from the log's own PDO configuration writes, tools/buslog/mapping.py),
summarised per second (``--all``: every frame); a PDO whose length is not the mapping's is counted, never
decoded; at the end the SYNC period's statistics and where the mapping came from. ``--json``: one object.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import canopen
import numpy as np
from canopen.sdo.exceptions import SdoAbortedError

from drivectl.driver import cia402
from drivectl.driver.cia301 import (
    EMCY_BASE,
    HEARTBEAT_BASE,
    NMT_COB_ID,
    SYNC_COB_ID,
    NmtCommand,
    NmtState,
)
from drivectl.driver.pdo_plan import OBJECT_NAMES
from drivectl.tools.buslog.convert import BusLogError, check_log, load_od
from drivectl.tools.buslog.sdo import Transfer

_POWER = list(cia402.PowerState)


def _name(od: canopen.ObjectDictionary, index: int, sub: int) -> str:
    try:
        obj = od[index]
    except KeyError:
        return "(not in the EDS)"
    if isinstance(obj, canopen.objectdictionary.ODVariable):
        return obj.name
    var = obj.subindices.get(sub)
    return f"{obj.name}" + (f" / {var.name}" if var is not None and var.name != obj.name else "")


def _nmt(code: int) -> str:
    try:
        return NmtCommand(code).name.lower().replace("_", " ")
    except ValueError:
        return f"command 0x{code:02X}"


def _state(code: int) -> str:
    try:
        return NmtState(code).name.lower().replace("_", "-")
    except ValueError:
        return f"state 0x{code:02X}"


def _value(od: Any, index: int, sub: int, raw: bytes) -> str:
    """A value as the object's type reads it (a string object as text), with the mode's name for 0x6060/1."""
    n = int.from_bytes(raw[:8], "little") if raw else 0
    try:
        var = od[index] if isinstance(od[index], canopen.objectdictionary.ODVariable) else od[index][sub]
        if var.data_type == canopen.objectdictionary.VISIBLE_STRING:
            return repr(raw.decode("latin-1"))
        if len(raw) <= 8 and var.data_type in (canopen.objectdictionary.INTEGER8, canopen.objectdictionary.INTEGER16,
                                               canopen.objectdictionary.INTEGER32):
            n = int.from_bytes(raw, "little", signed=True)
    except (KeyError, TypeError):
        if len(raw) > 8:
            return raw.hex(" ")
    if len(raw) > 8:
        return raw.hex(" ")
    text = f"{n} (0x{n & 0xFFFFFFFFFFFFFFFF:X})" if not -10 < n < 10 else str(n)
    if index in (cia402.MODES_OF_OPERATION, cia402.MODES_OF_OPERATION_DISPLAY):
        try:
            text += f" ({cia402.Mode(n).name.lower().replace('_', ' ').replace('sync', 'synchronous')})"
        except ValueError:
            pass
    return text


def _transfer(od: Any, tr: Transfer) -> str:
    where = f"0x{tr.index:04X}:{tr.sub:02X} {_name(od, tr.index, tr.sub)}"
    seg = f" (segmented, {len(tr.value)} bytes)" if tr.segmented else ""
    if tr.kind == "abort":
        reason = SdoAbortedError.CODES.get(tr.abort_code, "unknown abort code")
        return f"SDO abort {where} by the {'client' if tr.by_client else 'drive'}: 0x{tr.abort_code:08X} {reason}"
    if tr.kind == "write":
        return f"SDO write {where} = {_value(od, tr.index, tr.sub, tr.value)}{seg}"
    if tr.kind == "read":
        return f"SDO read {where} -> {_value(od, tr.index, tr.sub, tr.value)}{seg}"
    return f"SDO block transfer {where} (not joined)"


class _Decoder:
    def __init__(self, od: Any, node: int, every: bool) -> None:
        self.od, self.node, self.every = od, node, every
        self.heartbeat: dict[int, int] = {}
        self.power: int | None = None  # index into _POWER
        self.lines: list[tuple[float, str]] = []
        self.t0: float | None = None
        self.seconds: dict[tuple[str, int], list] = {}  # (pdo, second) -> [count, min, max, names]
        self.bad: dict[str, int] = {}
        self.pdo_frames = 0
        self.t_last: float | None = None  # the last frame's stamp (the log's last, partial second ends there)

    def stamp(self, t: float) -> str:
        return f"{t - (self.t0 or 0.0):12.6f}"

    def event(self, t: float, cob: int, data: bytes, done: Transfer | None) -> None:
        if cob == NMT_COB_ID and len(data) == 2:
            self.lines.append((t, f"NMT {_nmt(data[0])} -> {'all nodes' if data[1] == 0 else f'node {data[1]}'}"))
        elif HEARTBEAT_BASE < cob <= HEARTBEAT_BASE + 127 and len(data) == 1:
            who = cob - HEARTBEAT_BASE
            if data[0] == 0:
                self.lines.append((t, f"node {who}: boot-up"))
            elif self.heartbeat.get(who) != data[0]:
                self.lines.append((t, f"node {who}: heartbeat {_state(data[0])}"))
            self.heartbeat[who] = data[0]
        elif EMCY_BASE < cob <= EMCY_BASE + 127 and len(data) >= 3:
            code, reg = struct.unpack_from("<HB", data)
            text = "error reset (no error)" if code == 0 else cia402.error_text(code)
            self.lines.append((t, f"node {cob - EMCY_BASE}: EMCY 0x{code:04X} {text} (error register 0x{reg:02X}"
                                  f"{', data ' + data[3:].hex(' ') if any(data[3:]) else ''})"))
        elif done is not None:
            self.lines.append((t, _transfer(self.od, done)))

    def pdos(self, fr, segments) -> None:
        for a, b, pdos in segments:
            cob = fr.cob[a:b]
            for pdo in pdos:
                idx = np.flatnonzero(cob == pdo.cob) + a
                if not len(idx):
                    continue
                size = pdo.layout.codec.size
                ok = fr.dlc[idx] == size
                name = pdo.config.name
                if not ok.all():
                    self.bad[name] = self.bad.get(name, 0) + int((~ok).sum())
                    for i in idx[~ok][:3].tolist():
                        self.lines.append((float(fr.t[i]), f"{name} 0x{pdo.cob:03X}: {int(fr.dlc[i])} bytes, the "
                                           f"mapping has {size}: not decoded"))
                    idx = idx[ok]
                if not len(idx):
                    continue
                self.pdo_frames += len(idx)
                rec = np.ascontiguousarray(fr.data[idx, :size]).view(pdo.dtype).ravel()
                t = fr.t[idx]
                names = [f"0x{i:04X}" + (f" {OBJECT_NAMES[i]}" if i in OBJECT_NAMES else "")
                         for i, _ in pdo.layout.entries]
                if (cia402.STATUSWORD, 0) in pdo.layout.entries:
                    sw = rec[f"f{pdo.layout.entries.index((cia402.STATUSWORD, 0))}"]
                    self._power(t, sw)
                if self.every:
                    for k in range(len(idx)):
                        vals = ", ".join(f"{n} {int(rec[k][j])}" for j, n in enumerate(names))
                        self.lines.append((float(t[k]), f"{name} 0x{pdo.cob:03X}: {vals}"))
                    continue
                sec = np.floor(t - (self.t0 or 0.0)).astype(np.int64)
                cut = np.flatnonzero(np.diff(sec)) + 1
                for part in np.split(np.arange(len(idx)), cut):
                    s = int(sec[part[0]])
                    cols = [rec[f"f{j}"][part] for j in range(len(names))]
                    got = self.seconds.get((name, s))
                    lo = [int(c.min()) for c in cols]
                    hi = [int(c.max()) for c in cols]
                    if got is None:
                        self.seconds[(name, s)] = [len(part), lo, hi, names, pdo.cob]
                    else:
                        got[0] += len(part)
                        got[1] = [min(x, y) for x, y in zip(got[1], lo, strict=True)]
                        got[2] = [max(x, y) for x, y in zip(got[2], hi, strict=True)]

    def _power(self, t: np.ndarray, sw: np.ndarray) -> None:
        uniq, inv = np.unique(sw, return_inverse=True)
        state = np.array([_POWER.index(cia402.decode_statusword(int(v))) for v in uniq])[inv]
        prev = np.concatenate([[-1 if self.power is None else self.power], state[:-1]])
        for k in np.flatnonzero(state != prev).tolist():
            before = "(start)" if prev[k] < 0 else _POWER[prev[k]].value
            self.lines.append((float(t[k]), f"node {self.node}: CiA 402 {before} -> {_POWER[state[k]].value} "
                                            f"(statusword 0x{int(sw[k]):04X})"))
        self.power = int(state[-1])

    def flush(self, upto: float | None) -> Iterator[tuple[float, str]]:
        """The lines up to ``upto`` (None: all), the seconds completed before it summarised."""
        done = [k for k in self.seconds if upto is None or (self.t0 or 0.0) + k[1] + 1 <= upto]
        for key in done:
            count, lo, hi, names, cob = self.seconds.pop(key)
            span = ", ".join(f"{n} {a}" + (f"..{b}" if b != a else "") for n, a, b in zip(names, lo, hi, strict=True))
            end = (self.t0 or 0.0) + key[1] + 1 - 1e-9
            self.lines.append((end if upto is not None or self.t_last is None else min(end, self.t_last),
                               f"{key[0]} 0x{cob:03X}: {count} frames in second {key[1]}: {span}"))
        self.lines.sort(key=lambda x: x[0])
        if upto is None:
            out, self.lines = self.lines, []
        else:
            k = next((i for i, (t, _) in enumerate(self.lines) if t > upto), len(self.lines))
            out, self.lines = self.lines[:k], self.lines[k:]
        return iter(out)


def decode_lines(log: Path, *, node: int, eds: str, mapping: str, every: bool = False, base: str = "configuration",
                 summary: dict | None = None, fast: bool | None = None, progress: bool = False) -> Iterator[str]:
    """The events of ``log`` for ``node`` as lines (see the module docstring); ``summary`` (a dict) gets the
    figures of the end (frames, SYNC statistics, mapping source, bad lengths, truncation)."""
    from drivectl.tools.buslog.frames import Reading
    from drivectl.tools.buslog.mapping import NodeMapping
    from drivectl.tools.buslog.stream import Jitter, Walk

    log = check_log(log)
    od = load_od(log, eds, node)
    nm = NodeMapping(od, node, mapping, f"EDS {eds}", base=base)
    dec = _Decoder(od, node, every)
    walk = Walk(node, nm, on_event=dec.event)
    reading = Reading(log)
    jitter = Jitter()
    syncs = 0
    for fr, segments in walk.chunks(log, reading, fast=fast, progress=progress):
        if dec.t0 is None and len(fr):
            dec.t0 = float(fr.t[0])
        if len(fr):
            dec.t_last = float(fr.t[-1])
        st = fr.t[fr.cob == SYNC_COB_ID]
        syncs += len(st)
        jitter.add(st, (walk.period_us or 1000) * 1e-6)
        dec.pdos(fr, segments)
        for t, text in dec.flush(float(fr.t[-1]) if len(fr) else None):
            yield f"{dec.stamp(t)} {text}"
    for t, text in dec.flush(None):
        yield f"{dec.stamp(t)} {text}"
    if not reading.frames:
        raise BusLogError(f"{log}: no CAN frames in it (not a {log.suffix} log, or an empty one)")
    period = (walk.period_us or 0) * 1e-6
    stats = jitter.report(period or (jitter.sum / jitter.n if jitter.n else 0.0))
    if stats:
        yield (f"SYNC: {syncs} frames, period mean {stats['sync_period_mean_s'] * 1e3:.3f} ms, min "
               f"{stats['sync_period_min_s'] * 1e3:.3f}, max {stats['sync_period_max_s'] * 1e3:.3f}, std "
               f"{stats['sync_period_std_s'] * 1e3:.3f} ms; against "
               + (f"0x1006 = {walk.period_us} us (written in the log)" if period else "the mean (no 0x1006 in the log)")
               + f": jitter max {stats['frame_jitter_max_s'] * 1e3:.3f} ms, p99 {stats['frame_jitter_p99_s'] * 1e3:.3f}"
               " ms (the log's own timestamps)")
    else:
        yield f"SYNC: {syncs} frame(s)"
    yield f"mapping of node {node}: {nm.source}"
    for line in nm.describe():
        yield f"  {line}"
    for note in nm.errors:
        yield f"  note: {note}"
    if dec.bad:
        yield "PDOs not of the mapping's length (counted, not decoded): " + ", ".join(
            f"{k} {v}" for k, v in dec.bad.items())
    yield f"{reading.frames} frames read ({reading.reader}), {dec.pdo_frames} PDOs of node {node} decoded"
    if reading.truncated:
        yield f"{log}: truncated: read as far as it goes: {reading.truncated}"
    if summary is not None:
        summary.update({"log": str(log), "node": node, "frames": reading.frames, "reader": reading.reader,
                        "syncs": syncs, "sync": stats, "period_us_from_log": walk.period_us,
                        "mapping_source": nm.source, "mapping": nm.describe(), "bad_length_pdos": dec.bad,
                        "pdo_frames": dec.pdo_frames, "truncated": reading.truncated})


def add_decode_parser(sub: Any) -> None:
    d = sub.add_parser("decode", help="read a CAN log as CANopen / CiA 402: NMT, SDO, EMCY, PDOs, SYNC, states",
                       description="One line per event of a recorded CAN log (.asc .blf .log .trc .csv .mf4): NMT, "
                       "boot-up and heartbeat changes, SDO transfers named from the EDS (segmented ones joined), "
                       "aborts and EMCY by name, CiA 402 state transitions, the node's PDOs by the mapping the log "
                       "configured (else the configuration's) per second, the SYNC period's statistics "
                       "(docs/guide/buslog.md).")
    d.add_argument("log", metavar="LOG")
    d.add_argument("--axis", default="x", help="the axis whose node, EDS and mapping are used (default x)")
    d.add_argument("--node", type=int, metavar="N", help="the drive's node-ID (default: the axis's)")
    d.add_argument("--eds", metavar="FILE", help="the drive's EDS (default: the axis's)")
    d.add_argument("--all", action="store_true", help="every PDO frame, not a summary per second")
    d.add_argument("--mapping-from", choices=("configuration", "eds"), default="configuration",
                   help="for the PDOs the log does not configure: the configuration's planned mapping (default) or "
                   "the EDS's default values")
    d.add_argument("--json", action="store_true", help="exactly one JSON object on stdout")
    d.add_argument("--quiet", action="store_true", help="no progress bar")


def cmd_decode(args: Any) -> int:
    from drivectl.machine.bus_budget import resolve_mapping
    from drivectl.machine.config import load_config

    cfg = load_config(args.config)
    ac = cfg.axis(args.axis)
    node = ac.node_id if args.node is None else args.node
    if not 1 <= node <= 127:
        raise BusLogError(f"--node {node}: expected 1..127")
    summary: dict = {}
    lines = decode_lines(Path(args.log), node=node, eds=args.eds or ac.eds, mapping=resolve_mapping(cfg, 1),
                         every=args.all, base=args.mapping_from, summary=summary, progress=not args.quiet)
    if args.json:
        events = []
        for line in lines:
            head = line[:12].strip()
            try:
                events.append({"t": float(head), "text": line[13:]})
            except ValueError:
                pass  # the end's lines are in the summary
        print(json.dumps({**summary, "events": events}))
        return 0
    for line in lines:
        print(line)
    return 0

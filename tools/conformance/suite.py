"""`drivectl conformance`: CiA 301 / CiA 402 checks of one node, made by canopen's own master classes.

canopen's RemoteNode (SDO client, PdoMap, NMT master, EMCY consumer) and BaseNode402 play the third
party: a PLC programme or someone's Python master would use the drive the same way. Each check resets
the node (NMT reset node: canopen's ``send_command(0x81)``, the boot-up awaited by a listener
subscribed before the command),
does one thing, and judges what the node answered against the standard; a row per check: area, name,
pass / FAIL / skip, what was seen.

Against the emulated drive of a configuration on the virtual bus, the drive runs in-process on its own
thread and wall clock (:class:`ServedEmulator`, as ``drivectl emulate`` serves it); on any other bus
the checks talk to whatever answers at the node id (a real drive, or ``drivectl emulate`` in another
process). Checks that switch the power stage on (Operation Enabled with zero torque) run on a real
drive only with ``--allow-enable``; checks that apply torque run only on the emulated drive.
"""

from __future__ import annotations

import argparse
import json
import queue
import struct
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import can
import canopen
from canopen.profiles.p402 import BaseNode402

from drivectl.driver import cia402

PASS, FAIL, SKIP = "pass", "FAIL", "skip"
MASTER_ID = 0x7F
#: 0x1018 of drivectl's emulated drive (driver/eds/drivectl-emulated-drive.eds)
EMULATOR_VENDOR, EMULATOR_PRODUCT = 0x00D71C70, 0x00000402


class Skip(Exception):
    """The check does not apply to this node (said why)."""


class Failed(Exception):
    """The node answered against the standard (said what)."""


@dataclass
class Row:
    area: str
    name: str
    result: str
    detail: str


@dataclass
class Target:
    """The node under test and the master's handles on it."""

    network: canopen.Network
    node: BaseNode402
    od: canopen.ObjectDictionary
    emulated: bool  # the in-process emulated drive (checks that apply torque may run)
    allow_enable: bool

    @property
    def node_id(self) -> int:
        return self.node.id

    # -- helpers ----------------------------------------------------------------------------------------
    def frames(self, can_id: int) -> queue.Queue:
        """A queue that receives every frame on ``can_id`` from now on (until :meth:`forget`)."""
        q: queue.Queue = queue.Queue()

        def cb(cid: int, data: bytes, ts: float) -> None:
            q.put(bytes(data))

        self.network.subscribe(can_id, cb)
        q.callback = cb  # type: ignore[attr-defined]
        q.can_id = can_id  # type: ignore[attr-defined]
        return q

    def forget(self, q: queue.Queue) -> None:
        self.network.unsubscribe(q.can_id, q.callback)  # type: ignore[attr-defined]

    def raw_sdo(self, request: bytes, timeout: float = 0.3) -> bytes | None:
        """One raw 8-byte SDO request; the server's answer or None."""
        q = self.frames(0x580 + self.node_id)
        try:
            self.network.send_message(0x600 + self.node_id, request)
            try:
                return q.get(timeout=timeout)
            except queue.Empty:
                return None
        finally:
            self.forget(q)

    def expect_abort(self, what: str, action: Callable[[], Any], *codes: int) -> str:
        try:
            action()
        except canopen.SdoAbortedError as exc:
            if codes and exc.code not in codes:
                want = " or ".join(f"0x{c:08X}" for c in codes)
                raise Failed(f"{what}: abort 0x{exc.code:08X}, expected {want}") from None
            return f"{what}: abort 0x{exc.code:08X}"
        raise Failed(f"{what}: accepted (expected an abort)")

    def reset(self, command: int = 0x81, timeout: float = 2.0) -> float:
        """NMT reset node (or communication), the boot-up awaited; returns the seconds it took.

        canopen's documented ``send_command`` then ``wait_for_bootup()`` starts listening only when the
        wait is called, so a boot-up that arrives before it (the sending process held up by load for
        longer than the drive's boot-up delay) is missed, and the drive would be blamed for the master's
        race. The listener is subscribed before the command instead."""
        booted = threading.Event()

        def on_heartbeat(can_id: int, data: bytes, timestamp: float) -> None:
            if data[:1] == b"\x00":
                booted.set()

        cob = 0x700 + self.node_id
        self.network.subscribe(cob, on_heartbeat)
        try:
            t0 = time.monotonic()
            self.node.nmt.send_command(command)
            if not booted.wait(timeout):
                raise Failed(f"no boot-up within {timeout:g} s of NMT command 0x{command:02X}")
            took = time.monotonic() - t0
        finally:
            self.network.unsubscribe(cob, on_heartbeat)
        self.node.nmt.state = "PRE-OPERATIONAL"  # what canopen's master assumes after the boot-up
        return took

    def sync(self, n: int = 1, period: float = 0.002) -> None:
        for _ in range(n):
            self.network.send_message(0x80, b"")
            time.sleep(period)

    def need_enable(self) -> None:
        if not (self.emulated or self.allow_enable):
            raise Skip("switches the power stage on (zero torque): --allow-enable to run it on a real drive")

    def need_emulated(self) -> None:
        if not self.emulated:
            raise Skip("applies torque: run only against the emulated drive")

    def remap(self, tx: bool, n: int, entries: list[tuple[int, int]], trans_type: int = 1,
              event_timer: int | None = None, inhibit: int | None = None) -> canopen.pdo.PdoMap:
        """PDO n (1-based) mapped with canopen's PdoMap, every other PDO of that direction disabled."""
        maps = self.node.tpdo if tx else self.node.rpdo
        maps.read()
        chosen = None
        for k, pdo in maps.map.items():
            pdo.clear()
            if k == n:
                for index, sub in entries:
                    pdo.add_variable(index, sub)
                pdo.trans_type = trans_type
                if event_timer is not None:
                    pdo.event_timer = event_timer
                if inhibit is not None:
                    pdo.inhibit_time = inhibit
                pdo.enabled = True
                chosen = pdo
            else:
                pdo.enabled = False
            pdo.save()
        return chosen

    def operational(self) -> None:
        self.node.nmt.state = "OPERATIONAL"
        time.sleep(0.02)

    def enable(self, rpdo: canopen.pdo.PdoMap, torque: int = 0, extra: dict | None = None) -> int:
        """Shutdown, then enable operation, by RPDO and SYNC; the statusword (SDO) after."""
        for cw in (0x06, 0x0F):
            rpdo[0x6040].raw = cw
            rpdo[0x6071].raw = torque
            for key, value in (extra or {}).items():
                rpdo[key].raw = value
            rpdo.transmit()
            self.sync(3)
        return self.node.sdo[cia402.STATUSWORD].raw

    def emcy_codes(self, q: queue.Queue, wait: float) -> list[int]:
        end, codes = time.monotonic() + wait, []
        while time.monotonic() < end:
            try:
                data = q.get(timeout=max(0.0, end - time.monotonic()))
            except queue.Empty:
                break
            if len(data) >= 2:
                codes.append(struct.unpack_from("<H", data)[0])
        return codes


# -- the checks ----------------------------------------------------------------------------------------
CHECKS: list[tuple[str, str, Callable[[Target], str]]] = []


def check(area: str, name: str):
    def register(fn: Callable[[Target], str]) -> Callable[[Target], str]:
        CHECKS.append((area, name, fn))
        return fn
    return register


@check("NMT", "boot-up after reset node (send_command(0x81), then the boot-up)")
def _bootup(t: Target) -> str:
    return f"boot-up {1000 * t.reset(0x81):.0f} ms after the command"


@check("NMT", "heartbeat without SYNC (wait_for_heartbeat)")
def _heartbeat(t: Target) -> str:
    t.node.sdo[cia402.PRODUCER_HEARTBEAT_TIME].raw = 50
    state = t.node.nmt.wait_for_heartbeat(1.0)
    if state != "PRE-OPERATIONAL":
        raise Failed(f"heartbeat says {state}, expected PRE-OPERATIONAL")
    return "heartbeat PRE-OPERATIONAL every 50 ms"


@check("NMT", "Stopped: no SDO answer, heartbeat says STOPPED")
def _stopped(t: Target) -> str:
    t.node.sdo[cia402.PRODUCER_HEARTBEAT_TIME].raw = 50
    t.node.nmt.state = "STOPPED"
    state = t.node.nmt.wait_for_heartbeat(1.0)
    if state != "STOPPED":
        raise Failed(f"heartbeat says {state}")
    if t.raw_sdo(bytes([0x40, 0x00, 0x10, 0, 0, 0, 0, 0])) is not None:
        raise Failed("answered an SDO upload in Stopped")
    t.node.nmt.state = "PRE-OPERATIONAL"
    t.node.nmt.wait_for_heartbeat(1.0)
    t.node.sdo[cia402.DEVICE_TYPE].raw  # noqa: B018 - answers again
    return "silent to SDO in Stopped, answers again in Pre-operational"


@check("NMT", "Stopped: no EMCY (a SYNC of wrong length reported only outside Stopped)")
def _stopped_emcy(t: Target) -> str:
    emcy = t.frames(0x80 + t.node_id)
    try:
        t.node.nmt.state = "STOPPED"
        time.sleep(0.02)
        t.network.send_message(0x80, b"\x01\x02")
        stopped = t.emcy_codes(emcy, 0.15)
        t.node.nmt.state = "PRE-OPERATIONAL"
        time.sleep(0.02)
        t.network.send_message(0x80, b"\x01\x02")
        preop = t.emcy_codes(emcy, 0.15)
    finally:
        t.forget(emcy)
    if stopped:
        raise Failed(f"EMCY {[hex(c) for c in stopped]} sent in Stopped")
    if 0x8240 not in preop:
        raise Skip("the node reports no SYNC length error (EMCY 0x8240) in Pre-operational either: cannot tell")
    return "none in Stopped; 0x8240 in Pre-operational"


@check("NMT", "reset communication restores 0x1000-0x1FFF (0x1017)")
def _reset_comm(t: Target) -> str:
    default = t.od[cia402.PRODUCER_HEARTBEAT_TIME].default
    t.node.sdo[cia402.PRODUCER_HEARTBEAT_TIME].raw = 250
    t.reset(0x82)
    got = t.node.sdo[cia402.PRODUCER_HEARTBEAT_TIME].raw
    if got != default:
        raise Failed(f"0x1017 = {got} after reset communication, the EDS default is {default}")
    return f"0x1017 back to {default}"


@check("SDO", "every EDS object uploads with its size")
def _upload_all(t: Target) -> str:
    n = 0
    for obj in t.od.values():
        subs = [obj] if isinstance(obj, canopen.objectdictionary.ODVariable) else list(obj.values())
        for var in subs:
            if not var.readable or var.index < 0x1000:
                continue
            data = t.node.sdo.upload(var.index, var.subindex)
            if var.data_type in canopen.objectdictionary.NUMBER_TYPES and len(data) * 8 != len(var):
                raise Failed(f"0x{var.index:04X}:{var.subindex}: {len(data)} bytes, type needs {len(var) // 8}")
            n += 1
    return f"{n} uploads"


@check("SDO", "0x1008 device name (segmented upload)")
def _device_name(t: Target) -> str:
    if 0x1008 not in t.od:
        raise Skip("0x1008 not in the EDS")
    name = t.node.sdo.upload(0x1008, 0).decode(errors="replace")
    if name != str(t.od[0x1008].default):
        raise Failed(f"device name {name!r}, the EDS says {t.od[0x1008].default!r}")
    return repr(name)


@check("SDO", "EDS limits enforced")
def _limits(t: Target) -> str:
    seen = []
    for obj in t.od.values():
        subs = [obj] if isinstance(obj, canopen.objectdictionary.ODVariable) else list(obj.values())
        for var in subs:
            if not var.writable or var.data_type not in canopen.objectdictionary.INTEGER_TYPES:
                continue
            fmt = var.STRUCT_TYPES[var.data_type]
            lo_type = -(1 << (fmt.size * 8 - 1)) if var.data_type in canopen.objectdictionary.SIGNED_TYPES else 0
            hi_type = (1 << (fmt.size * 8 - (1 if var.data_type in canopen.objectdictionary.SIGNED_TYPES else 0))) - 1
            for bound, step, codes in ((var.max, 1, (0x06090031, 0x06090030)), (var.min, -1, (0x06090032, 0x06090030))):
                if bound is None or not lo_type <= bound + step <= hi_type:
                    continue
                where = f"0x{var.index:04X}:{var.subindex} = {bound + step}"
                seen.append(t.expect_abort(where, lambda v=var, x=bound + step, f=fmt: t.node.sdo.download(
                    v.index, v.subindex, f.pack(x)), *codes))  # (canopen's encode_raw warns out of range)
    if not seen:
        raise Skip("no writable object with limits in the EDS")
    return f"{len(seen)} out-of-range writes refused"


@check("SDO", "reserved values refused (0x1400:2 = 0xF1, 0x1005 bit 30)")
def _reserved(t: Target) -> str:
    a = t.expect_abort("0x1400:2 = 0xF1", lambda: t.node.sdo.download(0x1400, 2, b"\xf1"))
    b = t.expect_abort("0x1005 = 0x40000080", lambda: t.node.sdo.download(0x1005, 0, struct.pack("<I", 0x40000080)))
    return f"{a}; {b}"


@check("SDO", "non-existent sub-indices aborted (0x06090011)")
def _subindex(t: Target) -> str:
    highest = t.node.sdo[cia402.CONSUMER_HEARTBEAT_TIME][0].raw
    out = [t.expect_abort(f"upload 0x1016:{highest + 1}", lambda: t.node.sdo.upload(0x1016, highest + 1), 0x06090011),
           t.expect_abort("upload 0x1000:1", lambda: t.node.sdo.upload(0x1000, 1), 0x06090011),
           t.expect_abort("download 0x6040:1", lambda: t.node.sdo.download(0x6040, 1, b"\x06\x00"), 0x06090011)]
    return "; ".join(out)


@check("SDO", "expedited download without size indication")
def _no_size(t: Target) -> str:
    answer = t.raw_sdo(bytes([0x22, 0x17, 0x10, 0x00, 40, 0, 0, 0]))
    if answer is None or answer[0] != 0x60:
        raise Failed(f"answer {answer.hex(' ') if answer else 'none'}, expected 60 17 10 00")
    got = t.node.sdo[cia402.PRODUCER_HEARTBEAT_TIME].raw
    if got != 40:
        raise Failed(f"0x1017 reads {got} after writing 40")
    return "0x1017 = 40 written with e=1, s=0"


@check("SDO", "block upload: served right or refused 0x05040001")
def _block(t: Target) -> str:
    want = t.node.sdo[cia402.IDENTITY][1].raw
    try:
        with t.node.sdo.open(cia402.IDENTITY, 1, "rb", block_transfer=True) as f:
            got = int.from_bytes(f.read(), "little")
    except canopen.SdoAbortedError as exc:
        if exc.code != 0x05040001:
            raise Failed(f"abort 0x{exc.code:08X}") from None
        return "refused with 0x05040001 (no block transfer)"
    if got != want:
        raise Failed(f"block upload read 0x{got:08X}, expedited 0x{want:08X}")
    return "served"


@check("SDO", "upload segment with no transfer open aborted")
def _stray_segment(t: Target) -> str:
    answer = t.raw_sdo(bytes([0x60, 0, 0, 0, 0, 0, 0, 0]))
    if answer is None or answer[0] != 0x80:
        raise Failed(f"answer {answer.hex(' ') if answer else 'none'}, expected an abort")
    return f"abort 0x{struct.unpack_from('<I', answer, 4)[0]:08X}"


@check("SDO", "remote frame on the SDO COB-ID ignored")
def _sdo_rtr(t: Target) -> str:
    q = t.frames(0x580 + t.node_id)
    try:
        t.network.bus.send(can.Message(arbitration_id=0x600 + t.node_id, is_remote_frame=True, dlc=8,
                                       is_extended_id=False))
        time.sleep(0.05)
        if not q.empty():
            raise Failed("answered a remote frame")
    finally:
        t.forget(q)
    t.node.sdo[cia402.DEVICE_TYPE].raw  # noqa: B018 - still alive
    return "no answer, SDO still served"


def _mapping_write(t: Target, index: int, entries: list[int]) -> None:
    comm = index - 0x200
    cob = t.node.sdo[comm][1].raw
    t.node.sdo[comm][1].raw = cob | 0x80000000
    t.node.sdo[index][0].raw = 0
    for k, word in enumerate(entries, 1):
        t.node.sdo[index][k].raw = word
    t.node.sdo[index][0].raw = len(entries)


@check("PDO", "mapping checked (unmappable, missing object, > 64 bits, change while valid)")
def _mapping_checks(t: Target) -> str:
    out = [t.expect_abort("RPDO1 maps 0x6041 (read-only)", lambda: _mapping_write(t, 0x1600, [0x60410010]),
                          0x06040041),
           t.expect_abort("RPDO1 maps 0x2000", lambda: _mapping_write(t, 0x1600, [0x20000010]),
                          0x06020000, 0x06040041),
           t.expect_abort("TPDO1 maps 3 x 32 bits", lambda: _mapping_write(t, 0x1A00, [0x60640020] * 3), 0x06040042)]
    t.reset()
    out.append(t.expect_abort("TPDO1 entry written while valid", lambda: t.node.sdo.download(
        0x1A00, 1, struct.pack("<I", 0x60410010))))
    return "; ".join(out)


@check("PDO", "remap with PdoMap; the new layout at the next SYNC")
def _remap(t: Target) -> str:
    tpdo = t.remap(True, 1, [(cia402.POSITION_ACTUAL, 0), (cia402.STATUSWORD, 0)])
    t.operational()
    before = tpdo.timestamp
    t.sync()
    time.sleep(0.05)  # (PdoMap.wait_for_reception clears its flag inside the wait: a frame already in is missed)
    if tpdo.timestamp == before:
        raise Failed("no TPDO after SYNC")
    sw = tpdo[cia402.STATUSWORD].raw
    if cia402.decode_statusword(sw) is not cia402.PowerState.SWITCH_ON_DISABLED:
        raise Failed(f"statusword 0x{sw:04X} decoded from the new layout")
    return f"TPDO1 = 0x6064 + 0x6041, statusword 0x{sw:04X}"


@check("PDO", "transmission type 3: every third SYNC")
def _every_n(t: Target) -> str:
    t.remap(True, 1, [(cia402.STATUSWORD, 0)], trans_type=3)
    t.operational()
    q = t.frames(0x180 + t.node_id)
    try:
        t.sync(9)
        time.sleep(0.05)
        n = q.qsize()
    finally:
        t.forget(q)
    if n != 3:
        raise Failed(f"{n} frames in 9 SYNCs")
    return "3 frames in 9 SYNCs"


@check("PDO", "transmission type 255 with event timer, no SYNC")
def _event_timer(t: Target) -> str:
    t.remap(True, 1, [(cia402.STATUSWORD, 0)], trans_type=255, event_timer=20)
    q = t.frames(0x180 + t.node_id)
    try:
        t.operational()
        time.sleep(0.3)
        n = q.qsize()
    finally:
        t.forget(q)
    if not 8 <= n <= 17:
        raise Failed(f"{n} frames in 0.3 s with a 20 ms event timer")
    return f"{n} frames in 0.3 s (20 ms event timer)"


@check("PDO", "RTR on a TPDO answered")
def _rtr(t: Target) -> str:
    t.remap(True, 1, [(cia402.STATUSWORD, 0)], trans_type=1)
    t.operational()
    q = t.frames(0x180 + t.node_id)
    try:
        t.network.bus.send(can.Message(arbitration_id=0x180 + t.node_id, is_remote_frame=True, dlc=2,
                                       is_extended_id=False))
        time.sleep(0.02)
        t.sync()  # a synchronous TPDO answers at the next SYNC
        frame = q.get(timeout=0.5)
    except queue.Empty:
        raise Failed("no answer to the RTR") from None
    finally:
        t.forget(q)
    return f"answered [{frame.hex(' ')}]"


@check("PDO", "0x6060 through an RPDO: 0x6061 follows")
def _mode_rpdo(t: Target) -> str:
    rpdo = t.remap(False, 1, [(cia402.CONTROLWORD, 0), (cia402.MODES_OF_OPERATION, 0)])
    t.operational()
    want = int(cia402.Mode.CYCLIC_SYNC_TORQUE)
    rpdo[cia402.CONTROLWORD].raw = 0
    rpdo[cia402.MODES_OF_OPERATION].raw = want
    rpdo.transmit()
    t.sync(2)
    got = t.node.sdo[cia402.MODES_OF_OPERATION_DISPLAY].raw
    if got != want:
        raise Failed(f"0x6061 = {got} after 0x6060 = {want} by RPDO")
    return f"0x6061 = {got}"


@check("PDO", "short RPDO: EMCY 0x8210, then error reset 0x0000 (canopen's active list empties)")
def _short_rpdo(t: Target) -> str:
    t.remap(False, 1, [(cia402.CONTROLWORD, 0), (cia402.TARGET_TORQUE, 0)])
    t.operational()
    emcy = t.frames(0x80 + t.node_id)
    try:
        t.network.send_message(0x200 + t.node_id, b"\x00")
        first = t.emcy_codes(emcy, 0.2)
        reg = t.node.sdo[cia402.ERROR_REGISTER].raw
        t.network.send_message(0x200 + t.node_id, b"\x00\x00\x00\x00")
        second = t.emcy_codes(emcy, 0.2)
    finally:
        t.forget(emcy)
    if 0x8210 not in first:
        raise Failed(f"EMCY {[hex(c) for c in first]} after a 1-byte RPDO, expected 0x8210")
    if not reg & 0x10:
        raise Failed(f"0x1001 = 0x{reg:02X} while the length error is active (bit 4 expected)")
    if 0x0000 not in second or t.node.emcy.active:
        raise Failed(f"after a good RPDO: EMCY {[hex(c) for c in second]}, active {t.node.emcy.active}")
    return f"0x8210, 0x1001 = 0x{reg:02X}, then 0x0000"


@check("402", "transitions with BaseNode402 (state = ...)")
def _transitions(t: Target) -> str:
    t.need_enable()
    node = t.node
    t.remap(False, 1, [(cia402.CONTROLWORD, 0), (cia402.TARGET_TORQUE, 0)], trans_type=255)
    t.remap(True, 1, [(cia402.STATUSWORD, 0)], trans_type=255)
    node.setup_402_state_machine(read_pdos=True)
    node.sdo[cia402.MODES_OF_OPERATION].raw = int(cia402.Mode.CYCLIC_SYNC_TORQUE)
    t.operational()
    seen = []
    for state in ("READY TO SWITCH ON", "SWITCHED ON", "OPERATION ENABLED", "SWITCH ON DISABLED"):
        node.state = state
        seen.append(node.state)
    if seen[-2] != "OPERATION ENABLED":
        raise Failed(f"states {seen}")
    return " -> ".join(seen)


@check("402", "halt clears statusword bit 12")
def _halt(t: Target) -> str:
    t.need_enable()
    rpdo = t.remap(False, 1, [(cia402.CONTROLWORD, 0), (cia402.TARGET_TORQUE, 0)])
    t.node.sdo[cia402.MODES_OF_OPERATION].raw = int(cia402.Mode.CYCLIC_SYNC_TORQUE)
    t.operational()
    sw = t.enable(rpdo)
    if cia402.decode_statusword(sw) is not cia402.PowerState.OPERATION_ENABLED or not sw & 0x1000:
        raise Failed(f"enabled without halt: statusword 0x{sw:04X}")
    rpdo[cia402.CONTROLWORD].raw = 0x010F
    rpdo.transmit()
    t.sync(3)
    halted = t.node.sdo[cia402.STATUSWORD].raw
    rpdo[cia402.CONTROLWORD].raw = 0
    rpdo.transmit()
    t.sync(3)
    if halted & 0x1000:
        raise Failed(f"halted: statusword 0x{halted:04X} (bit 12 still set)")
    return f"0x{sw:04X} -> halt 0x{halted:04X}"


@check("402", "no mode (0x6060 = 0): no torque")
def _no_mode(t: Target) -> str:
    t.need_emulated()
    rpdo = t.remap(False, 1, [(cia402.CONTROLWORD, 0), (cia402.TARGET_TORQUE, 0)])
    t.node.sdo[cia402.MODES_OF_OPERATION].raw = 0
    t.operational()
    t.enable(rpdo, torque=200)
    torque = t.node.sdo[cia402.TORQUE_ACTUAL].raw
    rpdo[cia402.CONTROLWORD].raw = 0
    rpdo[cia402.TARGET_TORQUE].raw = 0
    rpdo.transmit()
    t.sync(2)
    if torque != 0:
        raise Failed(f"torque actual {torque} per mille with no mode selected")
    return "torque actual 0 with target 200 per mille"


@check("402", "leaving Operational while enabled: 0x6007 reaction, EMCY 0x8100")
def _leave_op(t: Target) -> str:
    t.need_enable()
    rpdo = t.remap(False, 1, [(cia402.CONTROLWORD, 0), (cia402.TARGET_TORQUE, 0)])
    t.node.sdo[cia402.MODES_OF_OPERATION].raw = int(cia402.Mode.CYCLIC_SYNC_TORQUE)
    t.operational()
    emcy = t.frames(0x80 + t.node_id)
    try:
        t.enable(rpdo)
        t.node.nmt.state = "PRE-OPERATIONAL"
        codes = t.emcy_codes(emcy, 0.2)
    finally:
        t.forget(emcy)
    state = cia402.decode_statusword(t.node.sdo[cia402.STATUSWORD].raw)
    option = t.node.sdo[cia402.ABORT_CONNECTION_OPTION].raw
    if option and state is cia402.PowerState.OPERATION_ENABLED:
        raise Failed(f"still Operation Enabled in Pre-operational (0x6007 = {option})")
    if option and not any(0x8100 <= c <= 0x81FF for c in codes):
        raise Failed(f"EMCY {[hex(c) for c in codes]}, expected a communication error (0x81xx)")
    return f"0x6007 = {option}: {state.value}, EMCY {', '.join(f'0x{c:04X}' for c in codes)}"


@check("301", "RPDO deadline (0x1400:5) stops an enabled drive")
def _deadline(t: Target) -> str:
    t.need_enable()
    rpdo = t.remap(False, 1, [(cia402.CONTROLWORD, 0), (cia402.TARGET_TORQUE, 0)])
    t.node.sdo[0x1400][5].raw = 20
    t.node.sdo[cia402.MODES_OF_OPERATION].raw = int(cia402.Mode.CYCLIC_SYNC_TORQUE)
    t.operational()
    emcy = t.frames(0x80 + t.node_id)
    try:
        t.enable(rpdo)
        t.sync(30, 0.004)  # SYNCs go on, the RPDOs stop
        codes = t.emcy_codes(emcy, 0.1)
    finally:
        t.forget(emcy)
    state = cia402.decode_statusword(t.node.sdo[cia402.STATUSWORD].raw)
    if state is cia402.PowerState.OPERATION_ENABLED or 0x8250 not in codes:
        raise Failed(f"{state.value}, EMCY {[hex(c) for c in codes]} 120 ms after the last RPDO (deadline 20 ms)")
    return f"{state.value}, EMCY 0x8250"


@check("301", "master heartbeat consumer (0x1016) stops an enabled drive")
def _consumer(t: Target) -> str:
    t.need_enable()
    rpdo = t.remap(False, 1, [(cia402.CONTROLWORD, 0), (cia402.TARGET_TORQUE, 0)], trans_type=255)
    t.node.sdo[cia402.CONSUMER_HEARTBEAT_TIME][1].raw = (MASTER_ID << 16) | 100
    t.node.sdo[cia402.MODES_OF_OPERATION].raw = int(cia402.Mode.CYCLIC_SYNC_TORQUE)
    t.operational()
    emcy = t.frames(0x80 + t.node_id)
    try:
        t.network.send_message(0x700 + MASTER_ID, bytes([0x05]))
        t.enable(rpdo)
        time.sleep(0.4)  # no more heartbeat, no SYNC
        codes = t.emcy_codes(emcy, 0.1)
    finally:
        t.forget(emcy)
    state = cia402.decode_statusword(t.node.sdo[cia402.STATUSWORD].raw)
    if state is cia402.PowerState.OPERATION_ENABLED or cia402.HEARTBEAT_LOST_ERROR not in codes:
        raise Failed(f"{state.value}, EMCY {[hex(c) for c in codes]} 400 ms after the last heartbeat (100 ms)")
    return f"{state.value}, EMCY 0x8130"


# -- running ----------------------------------------------------------------------------------------------
def run_checks(network: canopen.Network, node_id: int, eds: str, *, emulated: bool, allow_enable: bool = False,
               only: str | None = None, progress: Callable[[Row], None] | None = None) -> list[Row]:
    od = canopen.import_od(eds, node_id)
    node = BaseNode402(node_id, od)
    network.add_node(node)
    target = Target(network, node, od, emulated, allow_enable)
    try:  # drivectl's emulated drive in another process (drivectl emulate): the torque checks may run too
        target.reset()
        vendor, product = node.sdo[cia402.IDENTITY][1].raw, node.sdo[cia402.IDENTITY][2].raw
        target.emulated = emulated or (vendor, product) == (EMULATOR_VENDOR, EMULATOR_PRODUCT)
    except (canopen.SdoAbortedError, canopen.SdoCommunicationError, canopen.nmt.NmtError):
        pass  # the first check reports it
    rows = []
    try:
        for area, name, fn in CHECKS:
            if only and only not in f"{area} {name}":
                continue
            try:
                target.reset()
                detail, result = fn(target), PASS
            except Skip as exc:
                detail, result = str(exc), SKIP
            except Failed as exc:
                detail, result = str(exc), FAIL
            except (canopen.SdoAbortedError, canopen.SdoCommunicationError, canopen.nmt.NmtError,
                    RuntimeError, ValueError, AssertionError) as exc:
                detail, result = f"{type(exc).__name__}: {exc}", FAIL
            row = Row(area, name, result, detail)
            rows.append(row)
            if progress is not None:
                progress(row)
    finally:
        try:
            node.nmt.send_command(0x81)  # leave the node as it powered on
        except can.CanError:
            pass
        network.nodes.pop(node_id, None)
    return rows


class ServedEmulator:
    """An emulated drive on a virtual channel, served on its own thread with the wall clock, as
    ``drivectl emulate`` serves it across processes (frames first, then the drive's clock)."""

    def __init__(self, channel: str, make_drive: Callable[[canopen.Network], Any]):
        from drivectl.driver.network import open_bus

        self.bus = open_bus("virtual", channel)
        self.net = canopen.Network(self.bus)
        self.drive = make_drive(self.net)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="emulated-drive", daemon=True)
        self.drive.boot()
        self._thread.start()

    def _serve(self) -> None:
        from drivectl.plant_emulator.node402 import deliver

        while not self._stop.is_set():
            msg = self.bus.recv(0.002)
            if msg is not None:
                deliver(self.net, msg)
            self.drive.serve()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.drive.close()
        self.bus.shutdown()


def format_table(rows: list[Row]) -> str:
    w_area = max(4, *(len(r.area) for r in rows)) if rows else 4
    w_name = max(5, *(len(r.name) for r in rows)) if rows else 5
    lines = [f"{'area':<{w_area}}  {'check':<{w_name}}  {'result':<6}  detail", "-" * (w_area + w_name + 30)]
    lines += [f"{r.area:<{w_area}}  {r.name:<{w_name}}  {r.result:<6}  {r.detail}" for r in rows]
    counts = {k: sum(r.result == k for r in rows) for k in (PASS, FAIL, SKIP)}
    lines.append(f"{counts[PASS]} passed, {counts[FAIL]} failed, {counts[SKIP]} skipped of {len(rows)} checks")
    return "\n".join(lines)


def add_conformance_parser(sub: Any) -> None:
    p = sub.add_parser("conformance", help="CiA 301/402 conformance checks of a node, by canopen's own master",
                       description=__doc__.split("\n\n")[0])
    p.add_argument("--axis", default=None, help="the configured axis whose node to check (default: the first)")
    p.add_argument("--node", type=int, default=None, help="node id to check instead of an axis's (1..127)")
    p.add_argument("--eds", default=None, help="EDS of that node (default: the axis's)")
    p.add_argument("--allow-enable", action="store_true",
                   help="on a real drive, also run the checks that switch its power stage on (zero torque)")
    p.add_argument("--only", default=None, metavar="TEXT", help="run only the checks whose area or name contains TEXT")
    p.add_argument("--json", action="store_true", help="one JSON object instead of the table")


def cmd_conformance(args: argparse.Namespace) -> int:
    from drivectl.driver.network import close_threaded, open_bus, threaded_network, unique_virtual_channel
    from drivectl.machine.build import plant_specs
    from drivectl.machine.config import load_config

    cfg = load_config(args.config)
    name = args.axis or next(iter(cfg.axes))
    if name not in cfg.axes:
        print(f"drivectl: conformance: --axis {name}: not in {cfg.source} ({', '.join(cfg.axes)})", file=sys.stderr)
        return 2
    ac = cfg.axis(name)
    node_id = args.node if args.node is not None else ac.node_id
    if not 1 <= node_id <= 127:
        print(f"drivectl: conformance: --node {node_id}: expected 1..127", file=sys.stderr)
        return 2
    eds = args.eds or str(ac.eds)
    b = cfg.bus
    emulator = None
    if b.interface == "virtual":
        from drivectl.plant_emulator.node402 import EmulatedDrive

        channel = unique_virtual_channel(b.channel)
        spec = plant_specs(cfg, [name])[name]
        emulator = ServedEmulator(channel, lambda net: EmulatedDrive(
            net, node_id, spec.build(cfg.cycle_s), rated_effort=ac.rated_effort, resolution=ac.encoder_m_per_count))
        net = threaded_network(open_bus("virtual", channel))
        where = f"virtual:{channel} (emulated drive, served on its own clock)"
    else:
        kwargs = {"host": b.host, "port": b.port} if b.interface == "socketcand" else {}
        net = threaded_network(open_bus(b.interface, b.channel, b.bitrate, **kwargs))
        where = f"{b.interface}:{b.channel}"
    if not args.json:
        print(f"conformance: node {node_id} on {where}, EDS {eds}", file=sys.stderr, flush=True)
    try:
        rows = run_checks(net, node_id, eds, emulated=emulator is not None, allow_enable=args.allow_enable,
                          only=args.only,
                          progress=None if args.json else lambda r: print(f"  {r.result:<4} {r.area} {r.name}",
                                                                         file=sys.stderr, flush=True))
    finally:
        close_threaded(net)
        if emulator is not None:
            emulator.close()
    failed = sum(r.result == FAIL for r in rows)
    if args.json:
        print(json.dumps({"node": node_id, "bus": where, "rows": [r.__dict__ for r in rows],
                          "passed": sum(r.result == PASS for r in rows), "failed": failed}))
    else:
        print(format_table(rows))
    return 1 if failed else 0

"""The checks of `drivectl conformance`, in the order they run: NMT, SDO and PDO (CiA 301), then the
CiA 402 state machine and the heartbeat consumer. Each one does one thing to a freshly reset node and judges
the answer against the standard (the why of each is in its own text).
"""

from __future__ import annotations

import queue
import struct
import time
from collections.abc import Callable

import can
import canopen

from drivectl.driver import cia402
from drivectl.tools.conformance.target import MASTER_ID, Failed, Skip, Target

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

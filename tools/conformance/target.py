"""The node under test for `drivectl conformance` (:class:`Target`: canopen's master handles on it and
the helpers the checks share) and what a check may raise (:class:`Skip`, :class:`Failed`).
"""

from __future__ import annotations

import queue
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

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

"""Fault injection: what goes wrong on a real axis, on cue, in the emulated drive and on its bus.

A fault is written ``[AXIS/]KIND[:k=v,...][@TIME]`` (``drivectl emulate --fault``, ``drivectl trace
--fault``, :func:`parse_fault` in tests), e.g. ``y/emcy-fault:code=0x4310@2.5``. TIME is seconds of
drive time counted from the first SYNC at which the drive is in Operation Enabled (so ``@0.5`` lands
about 500 rows into a trace); the fault fires once. Without AXIS it goes to the first axis.

Drive-side kinds act inside :class:`~drivectl.plant_emulator.node402.EmulatedDrive` (its SYNC
handler asks the injector once per cycle); bus-side kinds act on the master's bus through
:class:`FaultyBus`, a python-can bus wrapping the real one (only where master and drive share a
process: the lockstep virtual bus). The master is never told what was injected: it has to find out.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import can

from drivectl.driver import cia402
from drivectl.driver.cia301 import NMT_COB_ID, RPDO_BASE, SYNC_COB_ID
from drivectl.errors import InputError


@dataclass(frozen=True)
class Kind:
    """One fault kind: its parameters (defaults), where it acts and what it models."""

    params: Mapping[str, float]
    where: str  # "drive" | "bus" | "config"
    text: str


#: the fault vocabulary (names are the ``--fault`` spelling)
KINDS: dict[str, Kind] = {
    "tpdo-lost": Kind({"cycles": 1}, "drive", "TPDO1 (statusword + position) not sent for `cycles` SYNCs"),
    "tpdo-late": Kind({"cycles": 1}, "drive",
                      "the TPDOs of `cycles` SYNCs go out after the master's deadline (with its next RPDO)"),
    "sync-no-response": Kind({"cycles": math.inf}, "drive",
                             "the drive answers no SYNC with its TPDOs (it still steps and takes RPDOs)"),
    "heartbeat-stop": Kind({}, "drive", "the drive stops producing its heartbeat (0x1017)"),
    "emcy-fault": Kind({"code": 0x2310}, "drive",
                       "the drive enters Fault with 0x603F = `code` and sends EMCY (default over-current)"),
    "node-reset": Kind({}, "drive", "the drive resets by itself: boot-up while operational, parameters lost"),
    "encoder-glitch": Kind({"jump": 5e-3}, "drive",
                           "the reported position jumps by `jump` m and stays offset (counts lost)"),
    "limit-switch": Kind({"position": math.nan}, "drive",
                         "the drive's own limit switch: at `position` m (default: where the axis is at TIME) the "
                         "drive enters Fault with 0x603F = 0x5441/0x5442 and sends EMCY"),
    "sdo-abort": Kind({"index": cia402.MODES_OF_OPERATION}, "config",
                      "the drive aborts the SDO download of object `index` while it is configured"),
    "bus-error": Kind({}, "bus", "the master's bus raises once on send (python-can CanOperationError)"),
    "bus-off": Kind({}, "bus", "the master's bus goes bus-off: every send and receive raises from then on"),
    "master-dead": Kind({}, "bus", "the master falls silent (its process died): nothing it sends reaches "
                        "the drives any more"),
    "rogue-rpdo": Kind({"effort": 30.0}, "drive",
                       "a second node sends this drive's RPDO1 (Enable Operation, `effort` in the effort unit) "
                       "after each of the master's, and every cycle the master sends none: it overrides the master"),
    "rogue-sync": Kind({}, "drive", "a second node sends a SYNC after each of the master's (the drive steps twice a "
                       "cycle)"),
    "foreign-nmt": Kind({"command": 0x02, "hidden": 0}, "drive",
                        "a second NMT master sends `command` (0x02 Stop, 0x80 Pre-operational, 0x82 Reset "
                        "Communication) to this drive; hidden=1: the master's bus does not see the command (only "
                        "the drive's heartbeat tells)"),
    "malformed-frame": Kind({"function": 0x180, "length": 2, "rtr": 0, "cycles": 1, "broadcast": 0}, "drive",
                            "for `cycles` SYNCs a frame of `length` data bytes (rtr=1: a remote frame) on function "
                            "code `function` + node id (0x180 TPDO1, 0x280 TPDO2: in place of the real one; 0x080 "
                            "EMCY, 0x580 SDO response, 0x700 heartbeat); broadcast=1: the function code alone "
                            "(0x080 SYNC, 0x000 NMT)"),
}

#: SDO abort code the drive answers an injected sdo-abort with (CiA 301: general error)
SDO_ABORT_GENERAL = 0x08000000


class FaultSpecError(InputError):
    """A ``--fault`` text cannot be used; the message is one line naming the field."""


@dataclass(frozen=True)
class FaultSpec:
    kind: str
    at: float = 0.0
    params: Mapping[str, float] = field(default_factory=dict)
    axis: str | None = None

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise FaultSpecError(f"fault: unknown kind {self.kind!r} (known: {', '.join(KINDS)})")
        known = KINDS[self.kind].params
        for key, value in self.params.items():
            if key not in known:
                raise FaultSpecError(f"fault {self.kind}: {key}: unknown parameter"
                                     + (f" (known: {', '.join(known)})" if known else " (it takes none)"))
            if not isinstance(value, (int, float)) or (math.isnan(value) and key != "position"):
                raise FaultSpecError(f"fault {self.kind}: {key}: expected a number, got {value!r}")
        jump = self.params.get("jump")
        if jump is not None and not (math.isfinite(jump) and abs(jump) <= 1.0):  # the drive's 32-bit counts
            raise FaultSpecError(f"fault {self.kind}: jump: expected a finite jump of at most 1 m, got {jump:g}")
        position = self.params.get("position")
        if position is not None and math.isinf(position):
            raise FaultSpecError(f"fault {self.kind}: position: expected a finite position in m, got {position:g}")
        for key in ("code", "index"):  # 16-bit objects of the drive (0x603F, an OD index)
            value = self.params.get(key)
            if value is not None and not (value == int(value) and 0 <= value <= 0xFFFF):
                raise FaultSpecError(f"fault {self.kind}: {key}: expected an integer 0..0xFFFF, got {value:g}")
        if "cycles" in self.params and not self.params["cycles"] >= 1:
            raise FaultSpecError(f"fault {self.kind}: cycles: must be >= 1, got {self.params['cycles']}")
        _check_frame_params(self)
        if not (math.isfinite(self.at) and self.at >= 0):
            raise FaultSpecError(f"fault {self.kind}: time: must be >= 0 s, got {self.at}")

    def param(self, key: str) -> float:
        return float(self.params.get(key, KINDS[self.kind].params[key]))

    @property
    def where(self) -> str:
        return KINDS[self.kind].where

    def __str__(self) -> str:
        args = ",".join(f"{k}={v:g}" for k, v in self.params.items())
        return f"{self.axis + '/' if self.axis else ''}{self.kind}{':' + args if args else ''}@{self.at:g}"


def _check_frame_params(spec: FaultSpec) -> None:
    """The frame-level kinds' parameters must describe a frame that can be sent."""
    p = spec.params
    if spec.kind == "foreign-nmt" and "command" in p and p["command"] not in (0x01, 0x02, 0x80, 0x81, 0x82):
        raise FaultSpecError(f"fault foreign-nmt: command: expected an NMT command (0x01, 0x02, 0x80, 0x81, 0x82), "
                             f"got {p['command']:g}")
    if spec.kind == "malformed-frame":
        if "length" in p and not (p["length"] == int(p["length"]) and 0 <= p["length"] <= 8):
            raise FaultSpecError(f"fault malformed-frame: length: must be 0..8 data bytes, got {p['length']:g}")
        if "function" in p and not (p["function"] == int(p["function"]) and 0 <= p["function"] <= 0x780
                                    and not int(p["function"]) & 0x7F):
            raise FaultSpecError("fault malformed-frame: function: expected a CANopen function code (a multiple of "
                                 f"0x80 up to 0x780), got {p['function']:g}")
    if spec.kind == "rogue-rpdo" and "effort" in p and not math.isfinite(p["effort"]):
        raise FaultSpecError(f"fault rogue-rpdo: effort: must be finite, got {p['effort']:g}")


def parse_fault(text: str, source: str = "--fault") -> FaultSpec:
    """``[AXIS/]KIND[:k=v,...][@TIME]`` -> FaultSpec (TIME defaults to 0); integers may be written 0x...."""
    body, _, when = text.strip().partition("@")
    axis, slash, body = body.rpartition("/")
    if slash and not axis.strip():
        raise FaultSpecError(f"{source} {text}: axis: empty before '/'")
    kind, _, args = body.partition(":")
    params: dict[str, float] = {}
    for item in filter(None, (a.strip() for a in args.split(","))):
        key, eq, value = item.partition("=")
        if not eq:
            raise FaultSpecError(f"{source} {text}: {item!r}: expected key=value")
        try:
            params[key.strip()] = float(int(value, 0)) if value.strip().lower().startswith("0x") else float(value)
        except ValueError:
            raise FaultSpecError(f"{source} {text}: {key.strip()}: expected a number, got {value!r}") from None
    try:
        at = float(when) if when.strip() else 0.0
    except ValueError:
        raise FaultSpecError(f"{source} {text}: time: expected seconds after @, got {when!r}") from None
    try:
        return FaultSpec(kind.strip(), at, params, axis.strip() or None)
    except FaultSpecError as exc:
        raise FaultSpecError(f"{source} {text}: {exc}") from None


class MasterDied(BaseException):  # noqa: N818 - not an error the master could handle: it is gone
    """Raised on the master's thread by :class:`FaultyBus` in "dead" mode: the master stops right
    there, as if its process had been killed (no handler runs, nothing more is sent)."""


class FaultyBus(can.BusABC):
    """The master's bus with injectable failures (python-can's two-method template around a real bus).

    ``fail("once")`` makes the next send raise; ``fail("off")`` every send and receive (bus-off);
    ``fail("dead")`` stops the master at its next send (:class:`MasterDied`).
    """

    def __init__(self, bus: can.BusABC):
        self.inner = bus
        self.mode = ""
        self.raised = 0
        super().__init__(channel=bus.channel_info)
        self.channel_info = f"faulty({bus.channel_info})"

    def fail(self, mode: str) -> None:
        if mode not in ("", "once", "off", "dead"):
            raise ValueError(f"FaultyBus: mode: expected once, off or dead, got {mode!r}")
        self.mode = mode

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        mode = self.mode
        if mode:
            if mode == "dead":
                if not self.raised:
                    self.raised += 1
                    raise MasterDied("the master died (injected)")
                return  # what a harness still sends after the "death" (closing) reaches no one
            if mode == "once":
                self.mode = ""
            self.raised += 1
            raise can.CanOperationError("bus error: transmit failed (injected)" if mode == "once"
                                        else "bus-off: the controller left the bus (injected)")
        self.inner.send(msg, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self.mode == "off":
            self.raised += 1
            raise can.CanOperationError("bus-off: the controller left the bus (injected)")
        return self.inner.recv(timeout), False

    def shutdown(self) -> None:
        super().shutdown()
        self.inner.shutdown()


@dataclass
class _Armed:
    spec: FaultSpec
    base: int | None = None  # drive SYNC count of the first Operation Enabled after arming
    start: float | None = None  # limit switch: the position the axis had when it was armed


class FaultInjector:
    """The faults armed on one emulated drive. The drive calls :meth:`on_sync` once per SYNC (after
    its plant step), asks :meth:`tpdo_action` before sending its TPDOs and :meth:`heartbeat_ok`
    before its heartbeat; everything an injected fault changes is in this object's flags."""

    def __init__(self, specs: Iterable[FaultSpec] = (), *, bus: FaultyBus | None = None):
        self.armed: list[_Armed] = []
        self.bus = bus
        self.position_offset = 0.0  # m added to the reported position (encoder glitch)
        self.heartbeat_stopped = False
        self.sdo_abort_index: int | None = None
        self.deaf = False  # master-dead without the master's bus: the emulator stops hearing it
        self.fired: list[tuple[FaultSpec, int]] = []  # (fault, drive SYNC count)
        self._lost = 0.0
        self._late = 0.0
        self._silent = 0.0
        self.held: list[tuple[int, bytes]] = []  # late TPDO frames waiting to go out
        self._frames: _FrameFaults | None = None  # rogue producers, foreign NMT, malformed frames
        for spec in specs:
            self.arm(spec)

    def arm(self, spec: FaultSpec) -> None:
        if spec.where == "bus" and self.bus is None and spec.kind != "master-dead":
            raise FaultSpecError(f"fault {spec.kind}: acts on the master's bus, which this emulator does not own "
                                 "(bus faults need the master in the same process: drivectl trace --fault)")
        if spec.where == "config":
            self.sdo_abort_index = int(spec.param("index"))
            self.fired.append((spec, 0))
            return
        self.armed.append(_Armed(spec))

    @property
    def pending(self) -> bool:
        return bool(self.armed)

    # -- per cycle ----------------------------------------------------------------------------------
    def on_sync(self, drive: Any, syncs: int, dt: float) -> None:
        """``drive`` is the EmulatedDrive; ``syncs`` its SYNC count. Fires what is due: TIME counts from
        the first SYNC in Operation Enabled after the fault was armed."""
        enabled = drive.drive.power is cia402.PowerState.OPERATION_ENABLED
        for armed in list(self.armed):
            spec = armed.spec
            if armed.base is None:
                if not enabled:
                    continue
                armed.base = syncs
            if syncs - armed.base < round(spec.at / dt):
                continue
            if spec.kind == "limit-switch" and not math.isnan(spec.param("position")):
                edge, pos = spec.param("position"), drive.drive.position
                if armed.start is None:
                    armed.start = pos  # the side of the switch the axis starts on
                if (pos - edge) * (armed.start - edge) > 0:
                    continue  # not reached yet
            self.armed.remove(armed)
            self.fired.append((spec, syncs))
            self._fire(spec, drive)

    def _fire(self, spec: FaultSpec, drive: Any) -> None:
        kind = spec.kind
        if kind == "tpdo-lost":
            self._lost = spec.param("cycles")
        elif kind == "tpdo-late":
            self._late = spec.param("cycles")
        elif kind == "sync-no-response":
            self._silent = spec.param("cycles")
        elif kind == "heartbeat-stop":
            self.heartbeat_stopped = True
        elif kind == "emcy-fault":
            drive.fault(int(spec.param("code")))
        elif kind == "limit-switch":
            code = 0x5441 if drive.drive.velocity >= 0 else 0x5442
            drive.fault(code, internal_limit=True)
        elif kind == "encoder-glitch":
            self.position_offset += spec.param("jump")
        elif kind == "node-reset":
            drive.reset(spontaneous=True)
        elif kind == "bus-error":
            self.bus.fail("once")
        elif kind == "bus-off":
            self.bus.fail("off")
        elif kind == "master-dead":
            if self.bus is not None:
                self.bus.fail("dead")
            else:
                self.deaf = True
        elif kind in ("rogue-rpdo", "rogue-sync", "foreign-nmt", "malformed-frame"):
            if self._frames is None:
                self._frames = _FrameFaults(drive)
            self._frames.fire(spec)

    def tpdo_action(self, n: int) -> str:
        """What to do with TPDO ``n`` (0-based) this cycle: "send", "drop" or "hold" (send late)."""
        if self._silent >= 1:
            return "drop"
        if self._late >= 1:
            return "hold"
        if n == 0 and self._lost >= 1:
            return "drop"
        if self._frames is not None and self._frames.replaces_tpdo(n):
            return "drop"  # a malformed frame goes out in its place
        return "send"

    def end_cycle(self) -> None:
        """After this SYNC's TPDOs: count down the lasting faults."""
        for name in ("_lost", "_late", "_silent"):
            value = getattr(self, name)
            if value >= 1:
                setattr(self, name, value - 1)

    def repair(self) -> None:
        """End every lasting fault (the drive repaired, the encoder referenced again); armed faults
        that have not fired yet stay armed."""
        self._lost = self._late = self._silent = 0.0
        self.heartbeat_stopped = False
        self.position_offset = 0.0
        self.held.clear()
        self.deaf = False
        if self._frames is not None:
            self._frames.stop()
            self._frames = None

    def release(self) -> list[tuple[int, bytes]]:
        frames, self.held = self.held, []
        return frames


class _FrameFaults:
    """Frames another node (or a broken one) puts on the drive's bus: a rogue RPDO or SYNC producer, a
    foreign NMT master, malformed frames. Each is sent on the bus (the master sees what any node would)
    and dispatched to the drive's own network too (a node on a real bus receives every other node's
    frames; a python-can bus does not receive its own). Hooks on the drive's network run after the
    drive's handlers, so a rogue RPDO lands after the master's and overrides it."""

    def __init__(self, drive: Any):
        self.drive = drive
        self.net = drive.network
        self.node_id = drive.node_id
        self.rogue_rpdo: bytes | None = None
        self.rogue_sync = False
        self.malformed: tuple[int, bytes, bool] | None = None  # (COB-ID, data, remote)
        self.malformed_cycles = 0.0
        self._master_rpdo = False  # the master's RPDO came since the last SYNC
        self._inside = False  # our own dispatch is under way: the hooks do not fire on it
        self.rpdo_cob = RPDO_BASE[0] + self.node_id
        self.net.subscribe(SYNC_COB_ID, self._on_sync)
        self.net.subscribe(self.rpdo_cob, self._on_rpdo)

    def fire(self, spec: FaultSpec) -> None:
        kind = spec.kind
        if kind == "rogue-rpdo":
            permille = self.drive.scale.to_permille(spec.param("effort"))
            self.rogue_rpdo = struct.pack("<Hh", int(cia402.Command.ENABLE_OPERATION), max(-32768, min(32767,
                                                                                                      permille)))
        elif kind == "rogue-sync":
            self.rogue_sync = True
        elif kind == "foreign-nmt":
            frame = bytes([int(spec.param("command")), self.node_id])
            if spec.param("hidden"):
                self._dispatch(NMT_COB_ID, frame)  # only the drive gets it
            else:
                self._emit(NMT_COB_ID, frame)
        elif kind == "malformed-frame":
            function, length = int(spec.param("function")), int(spec.param("length"))
            cob = function if function == 0 or spec.param("broadcast") else function + self.node_id
            self.malformed = (cob, bytes(length) if not spec.param("rtr") else b"", bool(spec.param("rtr")))
            self.malformed_cycles = spec.param("cycles")

    def replaces_tpdo(self, n: int) -> bool:
        if self.malformed is None or self.malformed_cycles < 1:
            return False
        return self.malformed[0] - self.node_id == (0x180, 0x280, 0x380, 0x480)[n]

    def _emit(self, cob: int, data: bytes, remote: bool = False) -> None:
        self.net.send_message(cob, data, remote)
        if not remote:
            self._dispatch(cob, data)

    def _dispatch(self, cob: int, data: bytes) -> None:
        self._inside = True
        try:
            self.net.notify(cob, data, 0.0)
        finally:
            self._inside = False

    def _on_rpdo(self, can_id: int, data: bytes, timestamp: float) -> None:
        if self._inside:
            return
        self._master_rpdo = True
        if self.rogue_rpdo is not None:
            self._emit(self.rpdo_cob, self.rogue_rpdo)  # right after the master's: the drive takes this one

    def _on_sync(self, can_id: int, data: bytes, timestamp: float) -> None:
        if self._inside:
            return
        if self.rogue_rpdo is not None and not self._master_rpdo:
            self._emit(self.rpdo_cob, self.rogue_rpdo)  # every cycle, whether the master sends or not
        self._master_rpdo = False
        if self.malformed is not None and self.malformed_cycles >= 1:
            cob, frame, remote = self.malformed
            self.net.send_message(cob, frame, remote)  # the master's to cope with (the drive ignores it)
            self.malformed_cycles -= 1
        if self.rogue_sync:
            self._emit(SYNC_COB_ID, b"")

    def stop(self) -> None:
        self.net.unsubscribe(SYNC_COB_ID, self._on_sync)
        self.net.unsubscribe(self.rpdo_cob, self._on_rpdo)

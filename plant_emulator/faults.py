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
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import can

from drivectl.driver import cia402


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
}

#: SDO abort code the drive answers an injected sdo-abort with (CiA 301: general error)
SDO_ABORT_GENERAL = 0x08000000


class FaultSpecError(ValueError):
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

    def tpdo_action(self, n: int) -> str:
        """What to do with TPDO ``n`` (0-based) this cycle: "send", "drop" or "hold" (send late)."""
        if self._silent >= 1:
            return "drop"
        if self._late >= 1:
            return "hold"
        if n == 0 and self._lost >= 1:
            return "drop"
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

    def release(self) -> list[tuple[int, bytes]]:
        frames, self.held = self.held, []
        return frames

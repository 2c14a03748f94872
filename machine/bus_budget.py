"""The bus budget: how much of the CAN bus the configured axes, PDO mapping and cycle take.

Per cycle the bus carries one SYNC and, per axis, the TPDOs drivectl maps (driver/canopen_axis.py) and
its RPDO. A classic CAN data frame with an 11-bit identifier and n data bytes is 47 + 8 n bits on the
wire (SOF, identifier, RTR, IDE, r0, DLC, data, CRC and its delimiter, ACK slot and delimiter, EOF, and
the 3-bit intermission); bit stuffing adds at most floor((34 + 8 n - 1) / 4) bits (the stuffed part runs
from SOF to the end of the CRC; one stuff bit per 4 bits in the worst case: Davis et al., "CAN
schedulability analysis refuted, revisited and revised", 2007).

Two figures per configuration: the nominal load (no stuff bits) and the bound (every frame stuffed in
the worst way). The ceiling (``bus.load_ceiling_pct``, default 70 %) applies to the nominal load, the
figure a bus analyser shows and the rule of thumb is about (room for SDO, EMCY, heartbeats and
retransmissions); the bound must stay under 100 %, or the cycle's frames might not fit the cycle at all.
Either over: the run is refused with one line naming the figure, before any drive is enabled.

Figures for 1 Mbit/s and 1 kHz (from this module; SYNC 47/55 bits; nominal bits per cycle, per cent):

=============================  ===========  ===========  ===========  ===========  ===========  ===========
mapping                        bits / axis  1 axis       2 axes       3 axes       4 axes       5 axes
=============================  ===========  ===========  ===========  ===========  ===========  ===========
full (TPDO 6+6, RPDO 4)         269 (325)   316  31.6 %  585  58.5 %  854  85.4 %  1123 112.3 % 1392 139.2 %
compact (TPDO 8, RPDO 4)        190 (230)   237  23.7 %  427  42.7 %  617  61.7 %  807  80.7 %   997  99.7 %
minimal (TPDO 6, RPDO 2 + ev.)  158 (190)   205  20.5 %  363  36.3 %  521  52.1 %  679  67.9 %   837  83.7 %
=============================  ===========  ===========  ===========  ===========  ===========  ===========

(worst-case stuffing: minimal 4 axes 815 bits, 81.5 %; compact 3 axes 74.5 %.)

``bus.pdo_mapping = "auto"`` (default) uses the first of full, compact and minimal that fits
(:func:`resolve_mapping`): at 1 kHz on 1 Mbit/s full for 1-2 axes, compact for 3, minimal for 4; five
do not fit (83.7 %): a 2 ms cycle or a second bus. The minimal mapping carries per cycle only what the
loop needs (statusword and position in, target torque out): its controlword travels in an event-driven
RPDO2 (transmission type 255, 2 data bytes, 63 bits) that the master sends in the cycles where the
controlword changes (enable, quick stop, the fault-reset edge, disable), again while the drive has not
reached the state it asks for and every 100 cycles (driver/canopen_axis.py CW_RESEND_CYCLES,
CW_REFRESH_CYCLES: 0.63 bits per cycle and axis), so it is counted as zero in steady state; torque
actual (0x6077) is not mapped (read by SDO where a tool needs it; the trace's
torque column is then empty, NaN). CiA 301 practice: an event-driven RPDO for what changes rarely.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from drivectl.machine.config import ConfigError, MachineConfig

#: data bytes of the frames drivectl sends or receives per cycle and axis, by mapping
MAPPINGS: dict[str, tuple[tuple[str, int], ...]] = {
    "full": (("TPDO1 statusword + position", 6), ("TPDO2 velocity + torque", 6), ("RPDO1 controlword + torque", 4)),
    "compact": (("TPDO1 statusword + position + torque", 8), ("RPDO1 controlword + torque", 4)),
    "minimal": (("TPDO1 statusword + position", 6), ("RPDO1 target torque", 2)),
}
#: frames sent only on an event, not counted in the steady-state load: (what, data bytes), by mapping
EVENT_FRAMES: dict[str, tuple[tuple[str, int], ...]] = {
    "minimal": (("RPDO2 controlword, event-driven (type 255): when it changes, while a transition is pending, "
                 "every 100 cycles", 2),),
}
#: what a mapping leaves out, said in the budget's lines
NOT_MAPPED: dict[str, str] = {
    "compact": "velocity derived on the host from two positions",
    "minimal": "velocity derived on the host; torque actual 0x6077 not mapped: read by SDO where a tool needs it",
}
#: the order "auto" tries them in: the first that fits under the ceiling
AUTO_ORDER = ("full", "compact", "minimal")
#: the mapping drivectl configures today (driver/canopen_axis.py RPDO_ENTRIES, TPDO_ENTRIES)
DEFAULT_MAPPING = "full"
DEFAULT_CEILING_PCT = 70.0


def frame_bits(data_bytes: int) -> tuple[int, int]:
    """(nominal bits, worst-case bits with stuffing) of a classic CAN data frame, 11-bit identifier."""
    if not 0 <= data_bytes <= 8:
        raise ValueError(f"CAN frame: 0..8 data bytes, got {data_bytes}")
    nominal = 47 + 8 * data_bytes
    return nominal, nominal + (34 + 8 * data_bytes - 1) // 4


@dataclass(frozen=True)
class BusLoad:
    axes: int
    mapping: str
    cycle_s: float
    bitrate: int
    bits_nominal: int  # per cycle
    bits_bound: int

    @property
    def nominal_pct(self) -> float:
        return 100.0 * self.bits_nominal / (self.bitrate * self.cycle_s)

    @property
    def bound_pct(self) -> float:
        return 100.0 * self.bits_bound / (self.bitrate * self.cycle_s)

    def text(self) -> str:
        return (f"bus load {self.nominal_pct:.1f} % of {self.bitrate / 1e6:g} Mbit/s ({self.bound_pct:.1f} % with "
                f"worst-case stuffing): {self.axes} {'axis' if self.axes == 1 else 'axes'}, {self.mapping} mapping, "
                f"{self.bits_nominal} bits ({self.bits_bound}) per {self.cycle_s * 1e3:g} ms cycle")


def bus_load(axes: int, cycle_s: float, bitrate: int, mapping: str = DEFAULT_MAPPING) -> BusLoad:
    sync = frame_bits(0)
    per_axis = [frame_bits(n) for _, n in MAPPINGS[mapping]]
    nominal = sync[0] + axes * sum(b[0] for b in per_axis)
    bound = sync[1] + axes * sum(b[1] for b in per_axis)
    return BusLoad(axes, mapping, cycle_s, bitrate, nominal, bound)


def axes_per_bus(cycle_s: float, bitrate: int, ceiling_pct: float = DEFAULT_CEILING_PCT,
                 mapping: str = DEFAULT_MAPPING) -> int:
    """The most axes whose load stays within the ceiling (nominal) and under 100 % (bound)."""
    n = 0
    while n < 127:
        load = bus_load(n + 1, cycle_s, bitrate, mapping)
        if load.nominal_pct > ceiling_pct or load.bound_pct >= 100.0:
            break
        n += 1
    return n


class BusLoadError(ConfigError):
    """The configured axes would load the bus past the ceiling: refused before anything is enabled."""


def resolve_mapping(cfg: MachineConfig, axes: int) -> str:
    """The mapping a run of ``axes`` axes uses: ``bus.pdo_mapping``, where "auto" (the default) is the first
    of full, compact and minimal that fits under the ceiling (the last one when none does: the run is then
    refused by :func:`check_bus_load`). The full mapping carries the drive's own velocity (0x606C), which
    the controllers were tuned on; compact and minimal derive it on the host from two positions (SimAxis
    the same, so --sim still equals the bus bit for bit)."""
    mapping = getattr(cfg.bus, "pdo_mapping", "auto")
    if mapping != "auto":
        return mapping
    ceiling = getattr(cfg.bus, "load_ceiling_pct", DEFAULT_CEILING_PCT)
    for candidate in AUTO_ORDER:
        load = bus_load(axes, cfg.cycle_s, cfg.bus.bitrate, candidate)
        if load.nominal_pct <= ceiling and load.bound_pct < 100.0:
            return candidate
    return AUTO_ORDER[-1]


def axis_frames(cfg: MachineConfig, name: str, mapping: str) -> tuple[tuple[str, int], ...]:
    """The cyclic frames (what, data bytes) of axis ``name`` under ``mapping``, as its drive's PDO plan makes them
    (driver/pdo_plan.py: a fixed mapping may carry more, a one-entry PDO split a group); the nominal mapping's
    where the EDS cannot be read (the axis then refuses it at connect, naming the file). A drive lacking an
    essential is refused here, in one line, before anything is configured."""
    od = _eds(cfg.axis(name).eds, cfg.axis(name).node_id)
    if od is None:
        return MAPPINGS[mapping]
    from drivectl.driver.pdo_plan import plan

    frames = plan(od, mapping, cfg.axis(name).node_id, f"axis {name}: EDS {cfg.axis(name).eds}").frames()
    return tuple((what, n) for what, n, cyclic in frames if cyclic)


_EDS_CACHE: dict[tuple[str, int, int], Any] = {}


def _eds(path: str, node_id: int) -> Any:
    import canopen

    try:
        key = (str(path), Path(path).stat().st_mtime_ns, node_id)
    except OSError:
        return None
    if key not in _EDS_CACHE:
        try:
            _EDS_CACHE[key] = canopen.import_od(str(path), node_id)
        except Exception:  # noqa: BLE001 - CanopenAxis names the file and the reason
            return None
    return _EDS_CACHE[key]


def machine_load(cfg: MachineConfig, names: Sequence[str] | None = None) -> BusLoad:
    """The load of the axes ``names`` (default all), each with the frames its drive's PDO plan makes."""
    names = list(names) if names is not None else list(cfg.axes)
    mapping = resolve_mapping(cfg, len(names))
    sync = frame_bits(0)
    nominal, bound = sync[0], sync[1]
    for name in names:
        for _, n in axis_frames(cfg, name, mapping):
            b = frame_bits(n)
            nominal, bound = nominal + b[0], bound + b[1]
    return BusLoad(len(names), mapping, cfg.cycle_s, cfg.bus.bitrate, nominal, bound)


def check_bus_load(cfg: MachineConfig, names: Sequence[str]) -> BusLoad:
    """The load of a run on the bus of ``cfg`` with the axes ``names``; raises :class:`BusLoadError` when
    over the ceiling (the virtual bus has no bitrate to exceed, but the same configuration would on a
    real one: it is refused there too, so that what runs in emulation runs on the machine)."""
    load = machine_load(cfg, names)
    ceiling = getattr(cfg.bus, "load_ceiling_pct", DEFAULT_CEILING_PCT)
    if load.nominal_pct > ceiling or load.bound_pct >= 100.0:
        fit = max(axes_per_bus(cfg.cycle_s, cfg.bus.bitrate, ceiling, m) for m in _mappings(cfg))
        raise BusLoadError(
            f"{cfg.source}: bus: {load.nominal_pct:.1f} % bus load ({load.bound_pct:.1f} % with worst-case "
            f"stuffing) for {load.axes} axes at {cfg.cycle_s * 1e3:g} ms on {cfg.bus.bitrate / 1e6:g} Mbit/s is over "
            f"the {ceiling:g} % ceiling (bus.load_ceiling_pct): {fit} axes fit; a longer cycle_s or a second bus")
    return load


def _mappings(cfg: MachineConfig) -> tuple[str, ...]:
    mapping = getattr(cfg.bus, "pdo_mapping", "auto")
    return AUTO_ORDER if mapping == "auto" else (mapping,)


def show_lines(cfg: MachineConfig) -> list[str]:
    """`config show`'s budget, as TOML comments (the output still loads back)."""
    load = machine_load(cfg)
    ceiling = getattr(cfg.bus, "load_ceiling_pct", DEFAULT_CEILING_PCT)
    lines = ["", "# bus budget (machine/bus_budget.py): per cycle one SYNC and per axis"]
    for what, n in MAPPINGS[load.mapping]:
        nom, bound = frame_bits(n)
        lines.append(f"#   {what}: {n} bytes, {nom} bits ({bound} with worst-case stuffing)")
    for what, n in EVENT_FRAMES.get(load.mapping, ()):
        nom, bound = frame_bits(n)
        lines.append(f"#   {what}: {n} bytes, {nom} bits ({bound}) when sent, counted as 0 in steady state")
    if load.mapping in NOT_MAPPED:
        lines.append(f"#   ({NOT_MAPPED[load.mapping]})")
    if getattr(cfg.bus, "pdo_mapping", "auto") == "auto":
        lines.append("#   (bus.pdo_mapping = \"auto\": the first of full, compact, minimal that fits under the "
                     "ceiling)")
    lines.append(f"# {load.text()}")
    lines.append(f"# ceiling {ceiling:g} % (bus.load_ceiling_pct): "
                 f"{max(axes_per_bus(cfg.cycle_s, cfg.bus.bitrate, ceiling, m) for m in _mappings(cfg))} axes fit at "
                 "this cycle and bitrate"
                 + ("" if load.nominal_pct <= ceiling and load.bound_pct < 100 else "; OVER: runs of all axes are "
                    "refused"))
    return lines

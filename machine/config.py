"""Machine configuration: the axes, their plants, controllers, profiles and limits.

An embedded default serves when no file is given (three emulated axes on the circle of paper 004's
eq (25): x = rigid-x under the model-based controller ``mbc``, which beats paper 004's ASMC there
(selectable), y = rigid-y under that ASMC with gain law 14; z = two-mass on paper 000's seed-000 move
under ``mbc``, which beats paper 000's PID-NFTSM there (selectable).
A file given with ``--config`` (or ``DRIVECTL_CONFIG``) has the same shape; every error names the file
and the key.
"""

from __future__ import annotations

import math
import os
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from drivectl.controllers.runtime.run_checks import RunChecks
from drivectl.controllers.runtime.servo import Limits
from drivectl.driver.axis import LAST_RESORTS
from drivectl.driver.units import DEFAULT_RESOLUTION_M, EffortScale
from drivectl.errors import InputError

DEFAULT_CONFIG_TOML = """\
# drivectl machine configuration (embedded default: emulated drives, no hardware)
cycle_s = 0.001                 # servo cycle = SYNC period
# loop = "process"              # the wall-clock servo loop: in a process of its own, or "thread" of the program's

[bus]
interface = "virtual"           # any python-can interface: virtual, slcan, socketcand, socketcan, pcan, kvaser, ...
channel = "drivectl"            # virtual: any name (unique per run); slcan: the tty; socketcan: can0; kvaser: 0
bitrate = 1000000
# host = "127.0.0.1"            # socketcand only (drivectl emulate --socketcand serves loopback)
# port = 29536
# [bus.options]                 # passed to can.Bus as they are, e.g. pcan: device_id = 1; kvaser: exclusive = true

[axes.x]
node_id = 1
rated_effort = 100.0         # N per 1000 per mille of 0x6071 (0x6076); 0.1 % = 0.1 N
plant = "rigid-x"               # built-in plant name or a plant TOML file (what the emulated drive plays)
# model = "rigid-x"             # the plant the controller believes (name or TOML file); default: the plant
controller = "mbc"              # mbc | asmc | pid-nftsm | smc | vprl | pid | pid-dob; paper 004: "asmc", law 14
profile = "circle"              # built-in profile name or a profile TOML file
encoder_m_per_count = 76.29e-9
max_lost_cycles = 3             # cycles in a row without TPDOs bridged (extrapolated) before it is a fault
# rpdo_timeout_ms = 6           # the drive's deadline on our RPDO (0x1400:05); default: from the axis's physics
                                # (docs/timing.md: x 17 ms, z 17 ms); 0 = off
last_resort = "nmt-reset"       # when neither quick stop (RPDO, SDO) nor NMT Stop is confirmed: nmt-reset | none
[axes.x.controller_settings]
# mbc (no settings) beats paper 004's ASMC here: the circle within 0.10 um against 0.14, standing within
# 0.06 um after a move against 4 um (paper 004's law has no integral action against the Coulomb friction;
# docs/standstill.md), with an unmodelled Stribeck effect and noise 11 um against 38 (bench/precision.py,
# docs/precision.md). Its du rms over
# the circle reads 1.33 against 1.04 N per cycle only because both flip the effort by the friction
# (93 N) at the reversals and mbc's second flip, ahead of the transport delay, is the run's last cycle
# (over 10.6 s: 1.30 against 1.37). `bode` measures it about a constant-velocity bias (the axis slides,
# never sticks): no mode, within 0.3 dB of the model to 100 Hz. For paper 004's ASMC set
# controller = "asmc" and uncomment:
# law = 14                      # paper 004 gain law (11..14)
[axes.x.limits]
# position_m / following_error_m / following_time_s left out: taken from the drive (0x607D, 0x6065/0x6066)
position_m = [-0.1, 0.1]        # soft limits
max_effort = 300.0              # N (3x rated), clipped here and by the drive (0x6072)
following_error_m = 0.001       # window
following_time_s = 0.01
max_speed_m_s = 2.0             # a position step faster than this between two samples is implausible
max_jump_m = 0.0005             # a second difference of the position beyond this is an encoder glitch

[axes.y]
node_id = 2
rated_effort = 100.0         # N per 1000 per mille of 0x6071 (0x6076); 0.1 % = 0.1 N
plant = "rigid-y"
controller = "asmc"
profile = "circle"
encoder_m_per_count = 76.29e-9
[axes.y.controller_settings]
law = 14
standstill_gain = 300.0         # N/(um s): integral action at rest, where the law alone stands off (docs/standstill.md)
[axes.y.limits]
position_m = [-0.1, 0.1]
max_effort = 300.0
following_error_m = 0.001
following_time_s = 0.01

[axes.z]
node_id = 3
rated_effort = 1.0           # V per 1000 per mille of 0x6071 (0x6076); 0.1 % = 0.001 V
plant = "two-mass"
controller = "mbc"              # paper 000: controller = "pid-nftsm" with the two settings below
profile = "seed-000"
encoder_m_per_count = 76.29e-9
# z has a holding brake: once the drive reports Operation Enabled (released) a run holds z this long
# before its first reference sample, the load the brake held taken over at rest (docs/precision.md)
enable_settle_ms = 100
[axes.z.emulator]
# the emulated drive's holding brake (plant_emulator/brake.py): z stands while its power stage is off
brake_release_ms = 50           # after Operation Enabled is asked for; the drive reports it once released
brake_engage_ms = 20            # the power stage holds the axis this long after leaving Operation Enabled
[axes.z.controller_settings]
# mbc: seed-000 within 0.7 um (PID-NFTSM 19.9 um), stable on every +-10 % corner (bench/precision.py).
# For paper 000's PID-NFTSM set controller = "pid-nftsm" and uncomment: the paper-scenario defaults
# (m~ 0.15, 40 Hz) assume no transport delay; with the one-cycle delay of cyclic synchronous torque the
# 40 Hz filter's lag destabilises the TDE loop. Measured on seed-000 with SimAxis: 150 Hz keeps m~
# 0.125-0.175 stable (30 / 20 / 15 um max error).
# m_tilde = 0.15
# accel_filter_hz = 150.0
[axes.z.limits]
position_m = [-0.01, 0.1]
max_effort = 5.0                # V
following_error_m = 0.001
following_time_s = 0.01

[checks]
# fractions of a run's cycles: past *_warn a completed run says "completed with warnings" (exit 4),
# past *_fault it is a fault (exit 3) that stops the run when it is passed: mid-run the fraction is of
# the cycles so far, but of at least fault_min_cycles (or the whole run if shorter)
missed_deadlines_warn = 0.005   # --paced: cycles that started more than half a cycle late
missed_deadlines_fault = 0.05
clipped_warn = 0.01             # cycles with the effort clipped at limits.max_effort
clipped_fault = 0.5
extrapolated_warn = 0.005       # cycles run on an extrapolated position (TPDO lost or malformed)
extrapolated_fault = 0.05
fault_min_cycles = 1000         # 1 s at 1 kHz: 5 % of it, 50 missed deadlines in the first second, stop a run

# [health]
# store = "health"              # drivectl health's store (docs/health.md); default: the user's data folder
# baseline_runs = 3             # an axis without axes.NAME.model: its baseline is the model of its first N runs
# [health.limits]               # where a wear trend becomes an alarm's deadline (defaults: docs/health.md)
# backlash.width = "20um"
# viscous.scale = 1.5
# [axes.x.health]
# profile = "fingerprint"       # drivectl health run's profile (library name, or a TOML file beside this one)
"""


#: where a wall-clock servo loop may run (session.connect's ``loop``, the configuration's ``loop``)
LOOPS = ("process", "thread")

#: the largest position count of the drive's INTEGER32 0x6064 / 0x607A
MAX_COUNTS = 2**31 - 1

DEFAULT_EDS = str(Path(__file__).resolve().parent.parent / "driver" / "eds" / "drivectl-emulated-drive.eds")


@dataclass(frozen=True)
class BusConfig:
    interface: str = "virtual"  # any of can.interfaces.VALID_INTERFACES
    channel: str | int = "drivectl"
    bitrate: int = 1_000_000
    host: str = "127.0.0.1"  # socketcand only
    port: int = 29536  # socketcand only
    options: dict[str, Any] = field(default_factory=dict)  # [bus.options]: keyword arguments for can.Bus
    load_ceiling_pct: float = 70.0  # the most of the bitrate the cyclic frames may take (machine/bus_budget.py)
    pdo_mapping: str = "auto"  # full | compact | minimal | auto: the first that fits the ceiling (bus_budget.py)
    #: who sends the SYNC of a wall-clock run: "auto" the transport's periodic transmit where it runs off the
    #: Python thread (SocketCAN's kernel, driver/sync_source.py), else the loop; "loop" always the loop
    sync: str = "auto"

    def open_kwargs(self) -> dict[str, Any]:
        """What :func:`drivectl.driver.network.open_bus` takes besides interface, channel and bitrate."""
        kwargs = dict(self.options)
        if self.interface == "socketcand":
            kwargs.update(host=self.host, port=self.port)
        return kwargs


class ConfigError(InputError):
    """The machine configuration is invalid; one line naming the file and the key."""


def parse_bus(bus_raw: dict[str, Any], src: str) -> BusConfig:
    """The [bus] table: any interface python-can knows, its options passed through to ``can.Bus``."""
    extra = set(bus_raw) - {"interface", "channel", "bitrate", "host", "port", "options", "load_ceiling_pct",
                            "pdo_mapping", "sync"}
    if extra:
        raise ConfigError(f"{src}: bus.{sorted(extra)[0]}: unknown key")
    from drivectl.driver.network import INTERFACES, RESERVED_OPTIONS

    interface = bus_raw.get("interface", "virtual")
    if interface not in INTERFACES:
        raise ConfigError(f"{src}: bus.interface: {interface!r} is not an interface python-can knows "
                          f"(one of {', '.join(INTERFACES)})")
    bitrate = bus_raw.get("bitrate", 1_000_000)
    if isinstance(bitrate, bool) or not isinstance(bitrate, int) or bitrate <= 0:
        raise ConfigError(f"{src}: bus.bitrate: expected a positive integer (bit/s), got {bitrate!r}")
    port = bus_raw.get("port", 29536)
    if isinstance(port, bool) or not isinstance(port, int) or not 0 < port < 65536:
        raise ConfigError(f"{src}: bus.port: expected a TCP port 1..65535, got {port!r}")
    channel = bus_raw.get("channel", "drivectl")
    if isinstance(channel, bool) or not (isinstance(channel, str) and channel or isinstance(channel, int)
                                         and channel >= 0):
        # an integer for the adapters python-can numbers (Kvaser, IXXAT, Vector, gs_usb: 0, 1, ...)
        raise ConfigError(f"{src}: bus.channel: expected a non-empty string or a channel number >= 0, "
                          f"got {channel!r}")
    options = bus_raw.get("options", {})
    if not isinstance(options, dict):
        raise ConfigError(f"{src}: bus.options: expected a table of keyword arguments for python-can's "
                          f"{interface} interface, got {options!r}")
    for key, value in options.items():
        if key in RESERVED_OPTIONS:
            raise ConfigError(f"{src}: bus.options.{key}: set by [bus] itself, not by its options")
        if not key.isidentifier():
            raise ConfigError(f"{src}: bus.options.{key}: not a keyword argument name")
        if not isinstance(value, str | int | float | bool) or isinstance(value, float) and not math.isfinite(value):
            raise ConfigError(f"{src}: bus.options.{key}: expected a string, number or boolean, got {value!r}")
    if options and interface == "virtual":
        raise ConfigError(f"{src}: bus.options: the virtual bus takes no options (it carries the in-process "
                          f"emulated drives in lockstep); remove them or choose the adapter's interface")
    ceiling = _number(src, "bus.load_ceiling_pct", bus_raw.get("load_ceiling_pct", 70.0), positive=True)
    if ceiling > 100:
        raise ConfigError(f"{src}: bus.load_ceiling_pct: a per cent of the bitrate, 0 < x <= 100, got {ceiling:g}")
    mapping = bus_raw.get("pdo_mapping", "auto")
    if mapping not in ("full", "compact", "minimal", "auto"):
        raise ConfigError(f"{src}: bus.pdo_mapping: expected \"auto\", \"full\", \"compact\" or \"minimal\", "
                          f"got {mapping!r}")
    sync = bus_raw.get("sync", "auto")
    if sync not in ("auto", "loop"):
        raise ConfigError(f"{src}: bus.sync: expected \"auto\" or \"loop\", got {sync!r}")
    return BusConfig(interface, channel, bitrate, _string(src, "bus.host", bus_raw.get("host", "127.0.0.1")), port,
                     dict(options), ceiling, mapping, sync)


@dataclass(frozen=True)
class AxisConfig:
    name: str
    plant: str
    controller: str
    profile: str
    controller_settings: dict[str, Any] = field(default_factory=dict)
    encoder_m_per_count: float = DEFAULT_RESOLUTION_M
    limits: Limits = field(default_factory=Limits)
    node_id: int = 1
    rated_effort: float = 100.0
    eds: str = DEFAULT_EDS
    max_lost_cycles: int = 3  # consecutive cycles without TPDOs bridged before it is a fault
    last_resort: str = "nmt-reset"  # the stop's last escalation (driver/canopen_axis.py LAST_RESORTS)
    rpdo_timeout_ms: int | None = None  # the drive's deadline on our RPDO (0x1400:05); None: from the physics
    #: limits the file left out: taken from the drive (0x6065/0x6066, 0x607D) when it has them
    limits_from_drive: frozenset[str] = frozenset()
    #: the plant the controller believes (built-in name or TOML file); None: the same as the plant
    model: str | None = None
    #: [axes.NAME.motion], [axes.NAME.homing], [axes.NAME.emulator] (the session's moves, homing and the
    #: emulated drive's switches: controllers/runtime/motion.py, controllers/runtime/homing.py)
    motion: Any = None
    homing: Any = None
    emulator: Any = None
    #: after the drive reports Operation Enabled (a holding brake released), the loop holds the axis at the
    #: run's start this long before the run's first reference sample: the load the brake held is taken
    #: over at rest, not in the motion (controllers/runtime/servo.py ``_settle``), s
    enable_settle_s: float = 0.0
    #: [axes.NAME] sdo_init: (index, sub-index, value) written before enable and read back (vendor objects)
    sdo_init: tuple[tuple[int, int, int], ...] = ()
    #: where rated_effort came from ("FILE: axes.NAME.rated_effort"), None: the built-in default (a drive without
    #: 0x6076 then refuses: the effort of 1000 per mille must come from the motor's data)
    rated_effort_source: str | None = field(default=None, compare=False)
    #: [axes.NAME] identity, vendor_id, product_code, revision: what the boot compares of 0x1018
    #: (driver/axis_boot.py IdentityCheck; the values the file leaves out come from the EDS's [DeviceInfo])
    identity: Any = None
    #: [axes.NAME.health]: the fingerprint run's profile and this axis's health limits
    #: (tools/health/settings.py AxisHealth)
    health: Any = None

    def limits_with(self, drive: Mapping[str, Any]) -> Limits:
        """The configured limits, completed by what the drive holds for the keys the file left out."""
        taken = {k: v for k, v in drive.items() if k in self.limits_from_drive}
        if "position" in taken and "position_source" in drive:
            taken["position_source"] = drive["position_source"]
        return replace(self.limits, **taken) if taken else self.limits


@dataclass(frozen=True)
class MachineConfig:
    source: str
    cycle_s: float
    axes: dict[str, AxisConfig]
    bus: BusConfig = field(default_factory=BusConfig)
    checks: RunChecks = field(default_factory=RunChecks)  # [checks]: when a completed run warns or faults
    #: [health] store: the health store's folder (drivectl health; relative to the file's folder)
    health_store: str | None = None
    #: [health.limits]: "effect.param" -> SI value, for every axis (tools/health/settings.py)
    health_limits: dict[str, float] = field(default_factory=dict)
    #: where the wall-clock servo loop runs: "process" (its own) or "thread" (the program's); None: the default
    loop: str | None = None
    #: [health] baseline_runs: an axis's first runs whose model is its baseline (None: the analysis's default)
    health_baseline_runs: int | None = None

    def health_limits_of(self, axis: str) -> dict[str, float]:
        """The health limits of ``axis``: the documented defaults, [health.limits], [axes.NAME.health.limits]."""
        from drivectl.tools.health.settings import axis_limits

        ac = self.axes.get(axis)
        return axis_limits(self.health_limits, ac.health if ac is not None else None)

    def axis(self, name: str) -> AxisConfig:
        if name not in self.axes:
            raise ConfigError(f"{self.source}: axes.{name}: no such axis (have {', '.join(self.axes)})")
        return self.axes[name]


def load_config(path: str | Path | None = None) -> MachineConfig:
    """The file at ``path``, else ``$DRIVECTL_CONFIG``, else the embedded default."""
    path = path or os.environ.get("DRIVECTL_CONFIG")
    if not path:
        return parse_config(tomllib.loads(DEFAULT_CONFIG_TOML), "<embedded default>")
    p = Path(path)
    try:
        str(p).encode("utf-8")
    except UnicodeEncodeError:
        raise ConfigError(f"--config {os.fsencode(p)!r}: the path is not valid UTF-8 (traces record it as "
                          "text); rename the file") from None
    try:
        data = tomllib.loads(p.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{p}: no such configuration file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{p}: cannot read: {exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None
    return parse_config(data, str(p))


def _number(src: str, key: str, value: Any, *, positive: bool = False, nonnegative: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ConfigError(f"{src}: {key}: expected a number, got {value!r}")
    if positive and value <= 0:
        raise ConfigError(f"{src}: {key}: must be > 0, got {value!r}")
    if nonnegative and value < 0:
        raise ConfigError(f"{src}: {key}: must be >= 0, got {value!r}")
    return float(value)


def _string(src: str, key: str, value: Any) -> str:
    if not isinstance(value, str) or not value:
        raise ConfigError(f"{src}: {key}: expected a non-empty string, got {value!r}")
    return value


def parse_config(data: dict[str, Any], src: str) -> MachineConfig:
    unknown = set(data) - {"cycle_s", "loop", "axes", "bus", "checks", "health"}
    if unknown:
        raise ConfigError(f"{src}: {sorted(unknown)[0]}: unknown key (expected cycle_s, loop, bus, axes, checks, "
                          "health)")
    loop = _choice(src, "loop", data["loop"], LOOPS) if "loop" in data else None
    checks = _checks(data.get("checks", {}), src)
    health_store, health_limits = _health(data.get("health", {}), src)
    baseline_runs = _health_baseline_runs(data.get("health", {}), src)
    bus_raw = data.get("bus", {})
    if not isinstance(bus_raw, dict):
        raise ConfigError(f"{src}: bus: expected a table")
    bus = parse_bus(bus_raw, src)
    cycle = _number(src, "cycle_s", data.get("cycle_s", 0.001), positive=True)
    axes_raw = data.get("axes")
    if not isinstance(axes_raw, dict) or not axes_raw:
        raise ConfigError(f"{src}: axes: expected at least one [axes.NAME] table")
    axes: dict[str, AxisConfig] = {}
    from drivectl.tracefile.stream import safe_name

    for name, raw in axes_raw.items():
        k = f"axes.{name}"
        if not safe_name(name):
            raise ConfigError(f"{src}: axes.{name!r}: an axis name names its trace files: letters, digits, _ + - "
                              "only, at most 64 characters")
        if not isinstance(raw, dict):
            raise ConfigError(f"{src}: {k}: expected a table")
        allowed = {"plant", "controller", "profile", "controller_settings", "encoder_m_per_count", "limits",
                   "node_id", "rated_effort", "eds", "max_lost_cycles", "rpdo_timeout_ms", "model", "motion",
                   "homing", "emulator", "last_resort", "sdo_init", "health",
                   "enable_settle_ms", "identity", "vendor_id", "product_code", "revision"}
        extra = set(raw) - allowed
        if extra:
            raise ConfigError(f"{src}: {k}.{sorted(extra)[0]}: unknown key")
        for req in ("plant", "controller", "profile"):
            if req not in raw:
                raise ConfigError(f"{src}: {k}.{req}: missing")
        from drivectl.controllers.registry import CONTROLLERS

        if isinstance(raw["controller"], str) and raw["controller"] not in CONTROLLERS:
            raise ConfigError(f"{src}: {k}.controller: unknown controller {raw['controller']!r} "
                              f"(known: {', '.join(CONTROLLERS)})")
        settings = raw.get("controller_settings", {})
        if not isinstance(settings, dict):
            raise ConfigError(f"{src}: {k}.controller_settings: expected a table")
        lim_raw = raw.get("limits", {})
        if not isinstance(lim_raw, dict):
            raise ConfigError(f"{src}: {k}.limits: expected a table")
        lim_extra = set(lim_raw) - {"position_m", "max_effort", "following_error_m", "following_time_s",
                                    "max_speed_m_s", "max_jump_m"}
        if lim_extra:
            raise ConfigError(f"{src}: {k}.limits.{sorted(lim_extra)[0]}: unknown key")
        position = lim_raw.get("position_m")
        if position is not None:
            if not (isinstance(position, list) and len(position) == 2):
                raise ConfigError(f"{src}: {k}.limits.position_m: expected [lower, upper] in m, got {position!r}")
            lo = _number(src, f"{k}.limits.position_m", position[0])
            hi = _number(src, f"{k}.limits.position_m", position[1])
            if not lo < hi:
                raise ConfigError(f"{src}: {k}.limits.position_m: lower {lo} must be below upper {hi}")
            position = (lo, hi)
        limits = Limits(
            position=position,
            position_source=f"{src}: {k}.limits.position_m" if position is not None else None,
            max_effort=_number(src, f"{k}.limits.max_effort", lim_raw.get("max_effort", math.inf), positive=True)
            if "max_effort" in lim_raw
            else math.inf,
            following_error=_number(
                src, f"{k}.limits.following_error_m", lim_raw.get("following_error_m", 5e-3), positive=True
            ),
            following_time=_number(src, f"{k}.limits.following_time_s", lim_raw.get("following_time_s", 0.0),
                                   nonnegative=True),
            max_speed=_number(src, f"{k}.limits.max_speed_m_s", lim_raw.get("max_speed_m_s", 2.0), positive=True),
            max_jump=_number(src, f"{k}.limits.max_jump_m", lim_raw.get("max_jump_m", Limits.max_jump), positive=True),
        )
        from_drive = {"position": "position_m", "following_error": "following_error_m",
                      "following_time": "following_time_s"}
        resolution = _number(src, f"{k}.encoder_m_per_count", raw.get("encoder_m_per_count", DEFAULT_RESOLUTION_M),
                             positive=True)
        if position is not None and max(abs(position[0]), abs(position[1])) / resolution > MAX_COUNTS:
            raise ConfigError(f"{src}: {k}.encoder_m_per_count: {resolution:g} m per count cannot reach the soft "
                              f"limits {list(position)} m in the drive's 32-bit position (0x6064)")
        rated = _number(src, f"{k}.rated_effort", raw.get("rated_effort", 100.0), positive=True)
        if rated > EffortScale.MAX_RATED:
            raise ConfigError(f"{src}: {k}.rated_effort: must be <= {EffortScale.MAX_RATED:g} (0x6076 holds it in "
                              f"thousandths, 32 bits), got {rated!r}")
        axes[name] = AxisConfig(
            name=name,
            plant=_string(src, f"{k}.plant", raw["plant"]),
            controller=_string(src, f"{k}.controller", raw["controller"]),
            profile=_string(src, f"{k}.profile", raw["profile"]),
            controller_settings=dict(settings),
            encoder_m_per_count=resolution,
            limits=limits,
            node_id=_node_id(src, f"{k}.node_id", raw.get("node_id", len(axes) + 1)),
            rated_effort=rated,
            eds=_string(src, f"{k}.eds", raw.get("eds", DEFAULT_EDS)),
            max_lost_cycles=_lost_cycles(src, f"{k}.max_lost_cycles", raw.get("max_lost_cycles", 3)),
            rpdo_timeout_ms=_count(src, f"{k}.rpdo_timeout_ms", raw["rpdo_timeout_ms"])
            if "rpdo_timeout_ms" in raw else None,
            limits_from_drive=frozenset(f for f, key in from_drive.items() if key not in lim_raw),
            model=_string(src, f"{k}.model", raw["model"]) if "model" in raw else None,
            **_session_tables(src, k, raw),
            last_resort=_choice(src, f"{k}.last_resort", raw.get("last_resort", "nmt-reset"), LAST_RESORTS),
            sdo_init=_sdo_init(src, f"{k}.sdo_init", raw.get("sdo_init", [])),
            enable_settle_s=_settle_ms(src, f"{k}.enable_settle_ms", raw.get("enable_settle_ms", 0)) / 1000.0,
            rated_effort_source=f"{src}: {k}.rated_effort" if "rated_effort" in raw else None,
            identity=_identity(src, k, raw),
            health=_axis_health(src, f"{k}.health", raw.get("health")),
        )
    owner: dict[int, str] = {}
    for name, ac in axes.items():
        if ac.node_id in owner:
            raise ConfigError(f"{src}: axes.{name}.node_id: {ac.node_id} is also axes.{owner[ac.node_id]}.node_id "
                              "(two axes share a node_id)")
        owner[ac.node_id] = name
    return MachineConfig(src, cycle, axes, bus, checks, health_store, health_limits, loop,
                         health_baseline_runs=baseline_runs)


def _health(raw: Any, src: str) -> tuple[str | None, dict[str, float]]:
    """[health] store = DIR: the health store (drivectl health), a path relative to the file's folder;
    [health.limits]: the trend limits of every axis (tools/health/settings.py)."""
    from drivectl.tools.health.settings import parse_limits

    if not isinstance(raw, dict):
        raise ConfigError(f"{src}: health: expected a table")
    extra = set(raw) - {"store", "limits", "baseline_runs"}
    if extra:
        raise ConfigError(f"{src}: health.{sorted(extra)[0]}: unknown key (known: store, limits, baseline_runs)")
    try:
        limits = parse_limits(src, "health.limits", raw.get("limits"))
    except InputError as exc:
        raise ConfigError(str(exc)) from None
    if "store" not in raw:
        return None, limits
    store = Path(_string(src, "health.store", raw["store"])).expanduser()
    if not store.is_absolute() and not src.startswith("<"):
        store = Path(src).parent / store
    return str(store), limits


def _axis_health(src: str, key: str, raw: Any) -> Any:
    """[axes.NAME.health]: its profile checked now (it loads: one line naming the key), a TOML file taken
    from the configuration file's folder when relative."""
    from drivectl.profiles.base import ProfileError
    from drivectl.profiles.library import load_profile
    from drivectl.tools.health.settings import parse_axis_health

    try:
        health = parse_axis_health(src, key, raw)
    except InputError as exc:
        raise ConfigError(str(exc)) from None
    profile = health.profile
    if profile.endswith(".toml") and not Path(profile).expanduser().is_absolute() and not src.startswith("<"):
        profile = str(Path(src).parent / Path(profile).expanduser())
    if profile != health.profile or raw is not None:
        try:
            load_profile(profile)
        except ProfileError as exc:
            raise ConfigError(f"{src}: {key}.profile: {exc}") from None
        health = replace(health, profile=profile)
    return health


def _health_baseline_runs(raw: dict[str, Any], src: str) -> int | None:
    """[health] baseline_runs = N (>= 1): the first runs of an axis whose model is its baseline."""
    value = raw.get("baseline_runs")
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ConfigError(f"{src}: health.baseline_runs: expected an integer >= 1, got {value!r}")
    return value


def _sdo_init(src: str, key: str, raw: Any) -> tuple[tuple[int, int, int], ...]:
    """[[index, sub, value], ...] or [[axes.NAME.sdo_init]] tables of index, sub, value: integers."""
    if not isinstance(raw, list):
        raise ConfigError(f"{src}: {key}: expected a list of [index, sub, value]")
    out = []
    for n, item in enumerate(raw):
        if isinstance(item, dict):
            extra = set(item) - {"index", "sub", "value"}
            if extra or "index" not in item or "value" not in item:
                raise ConfigError(f"{src}: {key}[{n}]: expected index, sub and value, got {sorted(item)}")
            item = [item["index"], item.get("sub", 0), item["value"]]
        if not (isinstance(item, list) and len(item) == 3 and all(isinstance(v, int) and not isinstance(v, bool)
                                                                  for v in item)):
            raise ConfigError(f"{src}: {key}[{n}]: expected [index, sub, value] (integers), got {item!r}")
        index, sub, value = item
        if not 0x1000 <= index <= 0xFFFF or not 0 <= sub <= 0xFF:
            raise ConfigError(f"{src}: {key}[{n}]: index 0x1000..0xFFFF and sub 0..255, got {index:#x}:{sub}")
        out.append((index, sub, value))
    return tuple(out)


def _identity(src: str, key: str, raw: dict[str, Any]) -> Any:
    """[axes.NAME] identity (one of IDENTITY_CHECKS) and the 32-bit vendor_id, product_code, revision."""
    from drivectl.driver.axis_boot import IDENTITY_CHECKS, IdentityCheck

    values = {}
    for name in ("vendor_id", "product_code", "revision"):
        if name in raw:
            v = raw[name]
            if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= 0xFFFFFFFF:
                raise ConfigError(f"{src}: {key}.{name}: expected a 32-bit unsigned integer (0x1018), got {v!r}")
            values[name] = v
    check = _choice(src, f"{key}.identity", raw.get("identity", "vendor+product"), IDENTITY_CHECKS)
    return IdentityCheck(check, source=src if src != "<embedded default>" else None, **values)


def _choice(src: str, key: str, value: Any, choices: tuple[str, ...]) -> str:
    if value not in choices:
        raise ConfigError(f"{src}: {key}: expected one of {', '.join(choices)}, got {value!r}")
    return value


def _checks(raw: Any, src: str) -> RunChecks:
    """[checks]: fractions of a run's cycles past which a completed run warns (exit 4) or a run faults (exit 3,
    mid-run: controllers/run_checks.RunGuard), and the fewest cycles a fault fraction is judged on mid-run."""
    if not isinstance(raw, dict):
        raise ConfigError(f"{src}: checks: expected a table")
    known = {f.name for f in fields(RunChecks)}
    extra = set(raw) - known
    if extra:
        raise ConfigError(f"{src}: checks.{sorted(extra)[0]}: unknown key (known: {', '.join(sorted(known))})")
    values = {key: _number(src, f"checks.{key}", value, nonnegative=True) for key, value in raw.items()}
    try:
        return RunChecks(**values)
    except ValueError as exc:
        raise ConfigError(f"{src}: {exc}") from None


def _session_tables(src: str, key: str, raw: dict[str, Any]) -> dict[str, Any]:
    """motion, homing and emulator tables of an axis, parsed by their own modules."""
    from drivectl.controllers.runtime.homing import parse_emulator_io, parse_homing
    from drivectl.controllers.runtime.motion import parse_motion

    try:
        return {"motion": parse_motion(src, f"{key}.motion", raw.get("motion")),
                "homing": parse_homing(src, f"{key}.homing", raw.get("homing")),
                "emulator": parse_emulator_io(src, f"{key}.emulator", raw.get("emulator"))}
    except ValueError as exc:
        raise ConfigError(str(exc)) from None


def _settle_ms(src: str, key: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not 0 <= value <= 10000:
        raise ConfigError(f"{src}: {key}: expected a time in ms (0..10000), got {value!r}")
    return float(value)


def _count(src: str, key: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 0xFFFF:
        raise ConfigError(f"{src}: {key}: expected an integer 0..65535, got {value!r}")
    return value


#: the most cycles in a row the master bridges without TPDOs: it extrapolates the position from the last
#: one received, which holds for a few cycles only (at 2 m/s and 1 g, 10 ms of a wrong guess is 50 um)
MAX_LOST_CYCLES = 10


def _lost_cycles(src: str, key: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= MAX_LOST_CYCLES:
        raise ConfigError(f"{src}: {key}: expected an integer 0..{MAX_LOST_CYCLES} (cycles bridged by extrapolating "
                          f"the position; more is driving blind), got {value!r}")
    return value


def _node_id(src: str, key: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 127:
        raise ConfigError(f"{src}: {key}: expected an integer node id 1..127, got {value!r}")
    return value

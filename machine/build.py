"""A machine's axes, ready to run: emulated drives on a bus with CANopen masters, or SimAxis.

``open_machine(cfg, ["x"])`` builds, for the virtual bus (the default), the emulated CiA 402 drives
of the configuration (plant + effects) on one in-process python-can virtual channel and a CanopenAxis
master for each, in lockstep; with ``sim=True`` the same plants behind SimAxis with no bus. Both
quantise the effort to per mille of the rated effort and the position to encoder counts, so the
two give the same trace bit for bit.

``faults=[...]`` (virtual bus only) arms fault injection: each drive gets a
:class:`~drivectl.plant_emulator.faults.FaultInjector` and the master's bus a
:class:`~drivectl.plant_emulator.faults.FaultyBus`, so tests, benches and ``drivectl trace --fault``
can break the axis on cue; :meth:`Machine.let_drives_run` lets the drives' own clocks run on when the
master has stopped sending (it died, its bus went off).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from drivectl.controllers.runtime.timing import Deadline, axis_deadline
from drivectl.driver.axis import Axis, AxisConfigError
from drivectl.driver.canopen_axis import CanopenAxis, SyncClock
from drivectl.driver.cia301 import HEARTBEAT_BASE, NmtState
from drivectl.driver.network import (
    Lockstep,
    LockstepNetwork,
    attach_bus_log,
    close_threaded,
    open_bus,
    threaded_network,
    unique_virtual_channel,
)
from drivectl.driver.units import EffortScale, Encoder
from drivectl.machine.config import MachineConfig
from drivectl.plant_emulator.drive_constants import RPDO_TIMEOUT_ERROR
from drivectl.plant_emulator.faults import FaultInjector, FaultSpec, FaultSpecError, FaultyBus
from drivectl.plant_emulator.models import PlantError, PlantSpec, load_plant
from drivectl.plant_emulator.node402 import EmulatedDrive
from drivectl.plant_emulator.sim_axis import SimAxis
from drivectl.profiles.base import Profile, ProfileError
from drivectl.profiles.library import load_profile


@dataclass
class Machine:
    """The axes of a run and what must be closed after it."""

    axes: dict[str, Axis]
    specs: dict[str, PlantSpec]
    bus: str
    drives: dict[str, EmulatedDrive] = field(default_factory=dict)
    injectors: dict[str, FaultInjector] = field(default_factory=dict)
    master_bus: FaultyBus | None = None
    #: each axis's deadline (controllers/runtime/timing.py): written to its drive as 0x1400:05
    deadlines: dict[str, Deadline] = field(default_factory=dict)
    _closers: list[Any] = field(default_factory=list)

    def let_drives_run(self, cycles: int, until_safe: bool = False) -> dict[str, int | None]:
        """Run the emulated drives' own clocks ``cycles`` cycles with nothing from the master (physical
        time goes on after the master stopped sending). Returns, per drive, the first of those cycles
        at which its torque was off (None: not within ``cycles``)."""
        from drivectl.controllers.runtime.servo import SAFE_STATES

        safe: dict[str, int | None] = {n: (0 if d.drive.power in SAFE_STATES else None) for n, d in self.drives.items()}
        for j in range(1, cycles + 1):
            if until_safe and all(v is not None for v in safe.values()):
                break
            for name, drive in self.drives.items():
                drive.idle()
                if safe[name] is None and drive.drive.power in SAFE_STATES:
                    safe[name] = j
        return safe

    def drive_account(self, name: str, code: int) -> str | None:
        """What the emulated drive of axis ``name`` says of the reaction behind its 0x603F ``code``: for its RPDO
        deadline, whose the time without a setpoint was (SYNCs without one, slots the master skipped, its own
        clock). None for any other code, and for a real drive, which does not say."""
        drive = self.drives.get(name)
        if drive is None or code != RPDO_TIMEOUT_ERROR:
            return None
        return drive.deadline_why or None

    def close(self) -> None:
        for closer in reversed(self._closers):
            try:
                closer()
            except Exception:  # noqa: BLE001 - close everything that can be closed
                pass
        self._closers.clear()

    def __enter__(self) -> Machine:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def machine_meta(cfg: MachineConfig, machine: Machine, plant: PlantSpec, model: PlantSpec, profile: str,
                 effects: Sequence[tuple[str, Mapping[str, float]]] = (),
                 faults: Sequence[object] = ()) -> dict[str, str]:
    """The machine's part of an axis's trace header (the rest: controllers/runtime/recording.py
    ``trace_header``): the plant emulated, the model the controller was designed on, the profile, the bus,
    the configuration file, and the effects added and faults injected, where there are any."""
    meta = {"plant": plant.name, "model": model.name, "profile": profile, "bus": machine.bus, "config": cfg.source}
    if effects:
        meta["effects"] = "; ".join(f"{n}:{','.join(f'{k}={v:g}' for k, v in p.items())}" for n, p in effects)
    if faults:
        meta["injected"] = "; ".join(str(f) for f in faults)
    return meta


def plant_specs(cfg: MachineConfig, names: Sequence[str], plant: str | None = None,
                effects: Sequence[tuple[str, dict[str, float]]] = ()) -> dict[str, PlantSpec]:
    specs = {}
    for name in names:
        if plant is not None:
            spec = load_plant(plant)
        else:
            try:
                spec = load_plant(cfg.axis(name).plant)
            except PlantError as exc:  # name the configuration key that pointed there
                raise PlantError(f"{cfg.source}: axes.{name}.plant: {exc}") from None
        for ename, eparams in effects:
            spec = spec.with_effect(ename, **eparams)
        specs[name] = spec
    return specs


def model_specs(cfg: MachineConfig, names: Sequence[str], model: str | None = None, plant: str | None = None,
                plants: Mapping[str, PlantSpec] | None = None) -> dict[str, PlantSpec]:
    """The plant each axis's controller believes (its *model*), beside the plant the drive plays.

    ``model`` (``--model``) wins, then the axis's ``model`` key, then the plant the run uses (``plant``,
    i.e. ``--plant``, else ``axes.NAME.plant``) -- so ``--plant`` alone still changes both, and a
    mismatched machine is ``--plant TRUE --model BELIEVED``. The model never carries the run's
    ``--effect`` effects: those are what the machine does and the controller does not know. An error
    names the flag or the configuration key; a model whose effort unit differs from the plant's
    (``plants``, when given) is refused.
    """
    out = {}
    for name in names:
        ac = cfg.axis(name)
        if model is not None:
            what, text = "--model", model
        elif ac.model is not None:
            what, text = f"{cfg.source}: axes.{name}.model", ac.model
        elif plant is not None:
            what, text = "--plant", plant
        else:
            what, text = f"{cfg.source}: axes.{name}.plant", ac.plant
        try:
            spec = load_plant(text)
        except PlantError as exc:
            raise PlantError(f"{what}: {exc}") from None
        if plants is not None and name in plants and plants[name].effort_unit != spec.effort_unit:
            raise PlantError(f"{what}: model {spec.name} has effort in {spec.effort_unit}, axis {name}'s plant "
                             f"{plants[name].name} in {plants[name].effort_unit}")
        out[name] = spec
    return out


def axis_model(cfg: MachineConfig, name: str) -> str:
    """The model axis ``name`` of ``cfg`` names: its ``model`` key, else its ``plant``."""
    ac = cfg.axis(name)
    return ac.model if ac.model is not None else ac.plant


def with_model(cfg: MachineConfig, name: str, model: str | None) -> MachineConfig:
    """``cfg`` with axis ``name``'s model set to ``model`` (``--model``; None leaves it), for tools that
    read the model from the configuration (tune's search runs on it)."""
    if model is None:
        return cfg
    from dataclasses import replace

    model_specs(cfg, [name], model)  # validated now: one line naming --model
    return replace(cfg, axes={**cfg.axes, name: replace(cfg.axis(name), model=model)})


def axis_profile(cfg: MachineConfig, name: str, profile: str | None = None) -> Profile:
    """The profile ``profile`` (``--profile``) or else the one ``cfg`` names for axis ``name``; an error in
    the latter names the configuration key that pointed there."""
    if profile is not None:
        return load_profile(profile, axis=name)
    try:
        return load_profile(cfg.axis(name).profile, axis=name)
    except ProfileError as exc:
        raise ProfileError(f"{cfg.source}: axes.{name}.profile: {exc}") from None


def open_machine(
    cfg: MachineConfig,
    names: Sequence[str],
    *,
    sim: bool = False,
    plant: str | None = None,
    effects: Sequence[tuple[str, dict[str, float]]] = (),
    start: dict[str, float] | None = None,
    noise: float = 0.0,
    seed: int = 0,
    bus_log: str | None = None,
    faults: Sequence[FaultSpec] | None = None,
    paced: bool = False,
    lockstep: bool = False,
) -> Machine:
    """The axes ``names`` of ``cfg``, each starting at ``start[name]`` (m); ``bus_log`` records every
    frame to a file (python-can Logger, format by suffix); ``faults`` arms fault injection (a spec
    without an axis goes to the first axis). On the virtual bus the drives and masters share the
    lockstep's own bus (driver/lockstep_bus.py); ``paced`` (a run on the wall clock) keeps python-can's
    virtual bus instead. ``lockstep`` on a bus to another process: every SYNC's TPDOs are waited for and
    drivectl's emulated drives step one cycle per SYNC whatever the wait (a node that is not one is refused,
    one line; docs/timing.md); in-process and with ``sim`` runs are lockstep anyway."""
    if paced and lockstep:
        raise ValueError("open_machine: paced and lockstep are two clocks: one of them")
    if faults is not None and (sim or cfg.bus.interface != "virtual"):
        raise FaultSpecError("--fault: faults are injected into the emulated drives of the virtual bus (not with "
                             "--sim or another bus; across processes use drivectl emulate --fault)")
    for spec in faults or ():
        if spec.axis is not None and spec.axis not in names:
            raise FaultSpecError(f"--fault {spec}: axis {spec.axis!r} is not in this run ({', '.join(names)})")
    start = start or {}
    specs = plant_specs(cfg, names, plant, effects)
    from drivectl.machine.bus_budget import check_bus_load, resolve_mapping

    mapping = resolve_mapping(cfg, len(names))  # --sim derives the velocity as the bus mapping makes the master do
    if not sim:
        check_bus_load(cfg, names)  # over the ceiling: refused here, before any drive is configured or enabled
    dt = cfg.cycle_s
    if sim:
        if bus_log:
            raise ValueError("--bus-log: there is no bus with --sim")
        axes: dict[str, Axis] = {}
        for i, name in enumerate(names):
            ac = cfg.axis(name)
            axes[name] = SimAxis(specs[name].build(dt), name=name, resolution=ac.encoder_m_per_count,
                                 effort_scale=EffortScale(ac.rated_effort), force_noise=noise, seed=seed + i,
                                 initial_position=start.get(name, 0.0), io=ac.emulator,
                                 derived_velocity=mapping != "full", torque_mapped=mapping != "minimal")
            axes[name].enable_settle_s = ac.enable_settle_s
        return Machine(axes, specs, "sim (SimAxis, no bus)", deadlines=axis_deadlines(cfg, names, specs))
    if cfg.bus.interface != "virtual":
        return _open_remote(cfg, names, specs, bus_log, lockstep)
    lockstep = Lockstep()
    channel = unique_virtual_channel(cfg.bus.channel)
    # the emulated drives step on the SYNCs they receive; paced, those come on the wall clock
    machine = Machine({}, specs, f"virtual:{channel} (emulated CiA 402 drives, "
                                 f"{'paced on the wall clock' if paced else 'lockstep'})")
    emu_net = LockstepNetwork(_lockstep_end(lockstep, channel, paced), lockstep)
    machine._closers.append(emu_net.disconnect)
    master_bus = _lockstep_end(lockstep, channel, paced)
    if faults is not None:
        master_bus = machine.master_bus = FaultyBus(master_bus)
    master_net = LockstepNetwork(master_bus, lockstep)
    machine._closers.append(master_net.disconnect)
    if bus_log:
        attach_bus_log(master_net, bus_log)
    try:
        for i, name in enumerate(names):
            ac = cfg.axis(name)
            injector = None
            if faults is not None:
                mine = [f for f in faults if (f.axis or names[0]) == name]
                injector = machine.injectors[name] = FaultInjector(mine, bus=machine.master_bus)
            drive = EmulatedDrive(emu_net, ac.node_id, specs[name].build(dt), rated_effort=ac.rated_effort,
                                  eds=readable_eds(name, ac.eds), resolution=ac.encoder_m_per_count,
                                  force_noise=noise, seed=seed + i,
                                  initial_position=start.get(name, 0.0), faults=injector,
                                  io=ac.emulator)
            machine.drives[name] = drive
            machine._closers.append(drive.close)
            drive.boot()
        _connect_masters(machine, master_net, cfg, names, specs)
    except BaseException:
        machine.close()
        raise
    return machine


def _lockstep_end(lockstep: Lockstep, channel: str, paced: bool) -> Any:
    """One end of the in-process bus: the lockstep's own (frames without copies), or python-can's virtual
    bus for a run paced on the wall clock."""
    return open_bus("virtual", channel) if paced else lockstep.bus(channel)


def readable_eds(name: str, eds: str) -> str:
    """``eds`` when canopen reads it; else the one line the master would say, before any drive exists (the emulated
    drive impersonates the axis's EDS)."""
    import canopen

    try:
        canopen.import_od(str(eds), 1)
    except Exception as exc:  # canopen raises many types for a bad file
        reason = (str(exc).strip().splitlines() or [type(exc).__name__])[0].rstrip(":")
        raise AxisConfigError(f"axis {name}: EDS {eds}: cannot be read: {reason}") from None
    return eds


def _connect_masters(machine: Machine, net: Any, cfg: MachineConfig, names: Sequence[str],
                     specs: dict[str, PlantSpec], lockstep: bool = False) -> None:
    """One CanopenAxis per axis on ``net``, sharing one SYNC clock; each booted and configured."""
    from drivectl.machine.bus_budget import resolve_mapping

    clock = SyncClock(net)
    clock.allow_periodic = cfg.bus.sync == "auto"
    machine.deadlines = axis_deadlines(cfg, names, specs)
    for name in names:
        ac = cfg.axis(name)
        axis = CanopenAxis(net, ac.node_id, name=name, dt=cfg.cycle_s, effort_unit=specs[name].effort_unit,
                           eds=ac.eds, encoder=Encoder(ac.encoder_m_per_count),
                           effort_scale=EffortScale(ac.rated_effort), clock=clock,
                           max_lost_cycles=ac.max_lost_cycles, rpdo_timeout_ms=machine.deadlines[name].ms,
                           max_effort=ac.limits.max_effort, last_resort=ac.last_resort,
                           mapping=resolve_mapping(cfg, len(names)),
                           rated_effort_source=ac.rated_effort_source,
                           sdo_init=ac.sdo_init, identity=ac.identity)
        axis.enable_settle_s = ac.enable_settle_s
        axis.lockstep_peer = lockstep
        axis.connect()
        machine.axes[name] = axis
        machine._closers.append(axis.close)


def axis_deadlines(cfg: MachineConfig, names: Sequence[str], specs: dict[str, PlantSpec]) -> dict[str, Deadline]:
    """Each axis's deadline (docs/timing.md): ``rpdo_timeout_ms`` where configured (0: the drive does not
    watch), else from its physics: the plant's mass, ``limits.max_effort`` and ``limits.following_error_m``."""
    out = {}
    for name in names:
        ac = cfg.axis(name)
        try:
            mass = specs[name].nominal_mass
        except Exception:  # noqa: BLE001 - a model without a mass: the deadline falls back to two cycles
            mass = None
        out[name] = axis_deadline(name, cfg.cycle_s, mass=mass, max_effort=ac.limits.max_effort,
                                  window=ac.limits.following_error, override_ms=ac.rpdo_timeout_ms)
    return out


def _open_remote(cfg: MachineConfig, names: Sequence[str], specs: dict[str, PlantSpec],
                 bus_log: str | None, lockstep: bool = False) -> Machine:
    """Masters on a bus that reaches drives in another process (slcan, socketcand, socketcan):
    a notifier thread receives, each cycle waits for its TPDOs against a deadline (``lockstep``: for them)."""
    b = cfg.bus
    bus = open_bus(b.interface, b.channel, b.bitrate, **b.open_kwargs())
    net = threaded_network(bus)
    machine = Machine({}, specs, f"{b.interface}:{b.channel}" + (" (lockstep across processes)" if lockstep else ""))
    machine._closers.append(lambda: close_threaded(net))
    if bus_log:
        attach_bus_log(net, bus_log)  # sent and received frames, on one clock
    try:
        _connect_masters(machine, net, cfg, names, specs, lockstep)
    except BaseException:
        machine.close()
        raise
    return machine


@dataclass
class BusSession:
    """A master network on the configured bus, without any axis configured on it (scan, status).

    On the virtual bus the machine's emulated drives are created in-process first (booted, as they
    would be on power-up); elsewhere the drives are whatever answers on the bus."""

    network: Any
    bus: str
    drives: dict[str, EmulatedDrive]
    lockstep: bool
    _closers: list[Any]
    #: node id -> NMT state of the latest boot-up or heartbeat seen since the session opened
    nmt_seen: dict[int, int] = field(default_factory=dict)

    def watch_nmt(self) -> None:
        for node_id in range(1, 128):
            self.network.subscribe(HEARTBEAT_BASE + node_id, self._on_heartbeat)

    def _on_heartbeat(self, can_id: int, data: bytes, timestamp: float) -> None:
        if data:
            # a boot-up (state byte 0) is followed by Pre-operational, where the node then sits
            self.nmt_seen[can_id - HEARTBEAT_BASE] = data[0] or int(NmtState.PRE_OPERATIONAL)

    def close(self) -> None:
        for closer in reversed(self._closers):
            try:
                closer()
            except Exception:  # noqa: BLE001
                pass
        self._closers.clear()

    def __enter__(self) -> BusSession:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_bus_session(cfg: MachineConfig, effects: Sequence[tuple[str, dict[str, float]]] = ()) -> BusSession:
    b = cfg.bus
    if b.interface == "virtual":
        lockstep = Lockstep()
        channel = unique_virtual_channel(b.channel)
        emu = LockstepNetwork(lockstep.bus(channel), lockstep)
        master = LockstepNetwork(lockstep.bus(channel), lockstep)
        session = BusSession(master, f"virtual:{channel} (emulated drives)", {}, True,
                             [emu.disconnect, master.disconnect])
        session.watch_nmt()
        specs = plant_specs(cfg, list(cfg.axes), None, effects)
        for name, ac in cfg.axes.items():
            drive = EmulatedDrive(emu, ac.node_id, specs[name].build(cfg.cycle_s), rated_effort=ac.rated_effort,
                                  eds=readable_eds(name, ac.eds), resolution=ac.encoder_m_per_count)
            session.drives[name] = drive
        for drive in session.drives.values():
            drive.boot()
        lockstep.advance(0.1)  # power-on: the drives take some tens of ms to boot
        return session
    net = threaded_network(open_bus(b.interface, b.channel, b.bitrate, **b.open_kwargs()))
    session = BusSession(net, f"{b.interface}:{b.channel}", {}, False, [lambda: close_threaded(net)])
    session.watch_nmt()
    return session

"""Commissioning commands: config show / init, scan, status, enable, disable, fault-reset, identify.

Each works on the configured bus: the embedded machine's emulated drives on the virtual bus, or a
real bus by configuration alone. A drive that does not answer, an SDO abort or a refused state
change is one line on stderr and exit code 1.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import canopen

from drivectl.driver import cia402
from drivectl.driver.cia301 import EMCY_BASE, NmtState
from drivectl.machine.config import DEFAULT_CONFIG_TOML, ConfigError, load_config

NMT_NAMES = {int(s): s.name.replace("_", "-") for s in NmtState}

#: the heartbeat period (ms) scan and status ask, for a moment, of a node that sends none (0x1017 = 0, the CiA
#: 301 default) and whose boot-up they did not see: its first heartbeat says the NMT state
PROBE_HEARTBEAT_MS = 50


def nmt_states(session: Any, nodes: dict[int, Any]) -> dict[int, str]:
    """The NMT state of each node (id -> its SDO client), as its own messages say: the boot-up or heartbeat
    seen since the session opened, else a heartbeat asked for: 0x1017 set to PROBE_HEARTBEAT_MS, the first
    heartbeat awaited (three periods), the old value written back (the node's configuration as found). A
    node that refuses, or sends nothing, is "unknown" with the reason (never a guess)."""
    seen = session.nmt_seen
    out: dict[int, str] = {}
    asked: dict[int, int] = {}  # node -> its 0x1017 before the probe
    for node_id, sdo in nodes.items():
        if node_id in seen:
            continue
        try:
            old = int.from_bytes(sdo.upload(cia402.PRODUCER_HEARTBEAT_TIME, 0), "little")
            if old:  # it sends heartbeats: one is due within its period
                asked[node_id] = -old
                continue
            sdo.download(cia402.PRODUCER_HEARTBEAT_TIME, 0, PROBE_HEARTBEAT_MS.to_bytes(2, "little"))
            asked[node_id] = 0
        except (canopen.SdoAbortedError, canopen.SdoCommunicationError) as exc:
            out[node_id] = f"unknown (no heartbeat; 0x1017 not settable: {exc})"
    if asked:
        wait_s = 3 * max([PROBE_HEARTBEAT_MS] + [-v for v in asked.values() if v < 0]) / 1000.0
        if session.lockstep:
            session.network.lockstep.advance(wait_s)  # the emulated drives' own clocks run that long
        else:
            until = time.monotonic() + wait_s
            while time.monotonic() < until and not all(n in seen for n in asked):
                time.sleep(0.01)
    for node_id, old in asked.items():
        if old == 0:
            try:
                nodes[node_id].download(cia402.PRODUCER_HEARTBEAT_TIME, 0, (0).to_bytes(2, "little"))
            except (canopen.SdoAbortedError, canopen.SdoCommunicationError) as exc:
                out[node_id] = f"heartbeat of {PROBE_HEARTBEAT_MS} ms left on: 0x1017 not restored to 0 ({exc})"
        if node_id not in seen and node_id not in out:
            out[node_id] = f"unknown (no heartbeat within {wait_s * 1000:.0f} ms{' of 0x1017 set' if old == 0 else ''})"
    for node_id in nodes:
        if node_id in seen:
            state = NMT_NAMES.get(seen[node_id], f"0x{seen[node_id]:02X}")
            out[node_id] = state if node_id not in out else f"{state}; {out[node_id]}"
    return out


def add_commission_parsers(sub: Any) -> None:
    c = sub.add_parser("config", help="show the resolved machine configuration, or write a starter file")
    csub = c.add_subparsers(dest="config_command", metavar="show|init")
    csub.required = True
    csub.add_parser("show", help="print the configuration in use (file, $DRIVECTL_CONFIG or embedded)")
    ci = csub.add_parser("init", help="write a commented starter configuration")
    ci.add_argument("file", nargs="?", default="drivectl.toml")
    ci.add_argument("--force", action="store_true", help="overwrite an existing file")
    ci.add_argument("--eds", metavar="FILE", help="a configuration whose axis is this drive (emulated by default: the "
                    "emulated drive impersonates the EDS); every choice commented")
    ci.add_argument("--axis", default="x", help="--eds: the axis's name (default x)")

    s = sub.add_parser("scan", help="list the CANopen nodes on the bus (identity, device name, NMT state)")
    s.add_argument("--json", action="store_true")

    st = sub.add_parser("status", help="NMT state, CiA 402 power state, mode, error code, position of an axis")
    st.add_argument("--axis", default=None, help="axis name (default: every axis of the configuration)")
    st.add_argument("--json", action="store_true")

    for name, what in (("enable", "bring an axis to Operation Enabled"),
                       ("disable", "bring an axis to Switch On Disabled"),
                       ("fault-reset", "reset a drive's fault (rising edge of controlword bit 7, verified)")):
        p = sub.add_parser(name, help=what)
        p.add_argument("--axis", default="x")

    i = sub.add_parser("identify", help="identify an axis's model: mass and friction of a rigid axis (PID + DOB "
                       "constant-velocity runs), masses, stiffness and damping of a two-mass one (closed-loop FRF fit)")
    i.add_argument("--axis", default="x")
    i.add_argument("--out", default="traces", metavar="DIR", help="where the identified model TOML goes")
    i.add_argument("--sim", action="store_true", help="SimAxis instead of the emulated drive on the bus")
    i.add_argument("--json", action="store_true")
    from drivectl.tools.cli.approach import add_approach_flags

    add_approach_flags(i)
    i.add_argument("--write-config", nargs="?", const="", metavar="FILE",
                   help="also point axes.AXIS.model at the identified model in FILE (default: the --config in "
                   "use), comments kept, the old file backed up as FILE.STAMP.bak")
    i.add_argument("--model", metavar="NAME|FILE", help="the model identification starts from and compares with "
                   "(default: the axis's model key, else its plant); its kind (rigid, two-mass) picks the method")
    i.add_argument("--plant", metavar="NAME|FILE", help="what the emulated drive plays (default: the axis's plant)")
    i.add_argument("--seconds", type=float, default=20.0,
                   help="two-mass: length of the multisine excitation, s (default 20)")
    i.add_argument("--friction", action="store_true",
                   help="two-mass: also constant-velocity runs for the friction (made anyway when the model has "
                   "Coulomb friction)")
    i.add_argument("--noise", type=float, default=0.0, metavar="EFFORT",
                   help="emulated drive: force noise std on the plant, effort unit (default 0)")


def cmd_config(args: argparse.Namespace) -> int:
    if args.config_command == "init":
        from drivectl.tracefile.format import atomic_write_text

        path = Path(args.file)
        if path.exists() and not args.force:
            print(f"drivectl: {path}: exists (use --force to overwrite)", file=sys.stderr)
            return 2
        text = DEFAULT_CONFIG_TOML
        if args.eds is not None:
            from drivectl.machine.eds_config import starter_config
            from drivectl.tracefile.stream import safe_name

            if not safe_name(args.axis):
                print(f"drivectl: --axis {args.axis!r}: an axis name names its trace files: letters, digits, _ + - "
                      "only", file=sys.stderr)
                return 2

            text = starter_config(args.eds, args.axis)  # a drive without an essential: one line, nothing written
        atomic_write_text(path, text)
        print(f"wrote {path} (use it with: drivectl --config {path} ...)")
        return 0
    from drivectl.machine.config_io import show_text

    cfg = load_config(args.config)
    print(show_text(cfg), end="")
    from drivectl.machine.bus_budget import show_lines

    print("\n".join(show_lines(cfg)))
    return 0


def _settle(session: Any, seconds: float) -> None:
    """Let answers arrive: immediate in lockstep, a short wait on a real bus."""
    if not session.lockstep:
        time.sleep(seconds)


def cmd_scan(args: argparse.Namespace) -> int:
    from drivectl.machine.build import open_bus_session

    cfg = load_config(args.config)
    with open_bus_session(cfg) as session:
        net = session.network
        net.scanner.reset()
        net.scanner.search()
        _settle(session, 0.3)
        rows = []
        for node_id in sorted(net.scanner.nodes):
            node = canopen.RemoteNode(node_id, canopen.ObjectDictionary())
            net.add_node(node)
            row: dict[str, Any] = {"node": node_id}
            try:
                row["vendor_id"] = int.from_bytes(node.sdo.upload(cia402.IDENTITY, 1), "little")
                row["product_code"] = int.from_bytes(node.sdo.upload(cia402.IDENTITY, 2), "little")
                row["revision"] = int.from_bytes(node.sdo.upload(cia402.IDENTITY, 3), "little")
                row["serial"] = int.from_bytes(node.sdo.upload(cia402.IDENTITY, 4), "little")
            except (canopen.SdoAbortedError, canopen.SdoCommunicationError) as exc:
                row["error"] = str(exc)
            try:
                row["device_name"] = node.sdo.upload(0x1008, 0).decode(errors="replace")
            except (canopen.SdoAbortedError, canopen.SdoCommunicationError):
                axis = next((n for n, a in cfg.axes.items() if a.node_id == node_id), None)
                row["device_name"] = (canopen.import_od(cfg.axes[axis].eds).device_information.product_name
                                      if axis else "?") + " (from the EDS)"
            rows.append(row)
        found = nmt_states(session, {r["node"]: net[r["node"]].sdo for r in rows})
        for row in rows:
            row["nmt"] = found[row["node"]]
        if args.json:
            print(json.dumps({"bus": session.bus, "nodes": rows}))
            return 0
        print(f"bus {session.bus}: {len(rows)} node(s)")
        print(f"{'node':>4}  {'vendor':>10}  {'product':>10}  {'rev':>10}  {'serial':>10}  {'NMT':<18} device")
        for r in rows:
            if "error" in r:
                print(f"{r['node']:>4}  SDO error: {r['error']}")
                continue
            print(f"{r['node']:>4}  0x{r['vendor_id']:08X}  0x{r['product_code']:08X}  0x{r['revision']:08X}  "
                  f"{r['serial']:>10}  {r['nmt']:<18} {r['device_name']}")
    return 0


def cmd_status(args: argparse.Namespace) -> int:
    from drivectl.driver.units import EffortScale
    from drivectl.machine.build import open_bus_session
    from drivectl.plant_emulator.models import load_plant

    cfg = load_config(args.config)
    names = [args.axis] if args.axis else list(cfg.axes)
    for n in names:
        cfg.axis(n)
    from drivectl.machine.build import axis_deadlines, plant_specs

    deadlines = axis_deadlines(cfg, names, plant_specs(cfg, names))
    from drivectl.machine import live_status

    live = live_status.read(cfg.bus)  # a session on this bus in another process: its loop's timing
    out = {}
    with open_bus_session(cfg) as session:
        net = session.network
        for name in names:
            ac = cfg.axis(name)
            emcy: list[bytes] = []
            net.subscribe(EMCY_BASE + ac.node_id, lambda cob, data, ts, e=emcy: e.append(bytes(data)))
            node = canopen.RemoteNode(ac.node_id, canopen.import_od(ac.eds, ac.node_id))
            net.add_node(node)
            try:
                sw = node.sdo[cia402.STATUSWORD].raw
                mode = node.sdo[cia402.MODES_OF_OPERATION_DISPLAY].raw
                code = node.sdo[cia402.ERROR_CODE].raw
                counts = node.sdo[cia402.POSITION_ACTUAL].raw
                max_torque = node.sdo[cia402.MAX_TORQUE].raw
                # the RPDO deadline the drive holds now (0x1400:05, where it has one: docs/timing.md)
                rpdo_deadline = node.sdo[cia402.RPDO_COMM][5].raw if 5 in node.sdo[cia402.RPDO_COMM] else None
            except (canopen.SdoAbortedError, canopen.SdoCommunicationError) as exc:
                print(f"drivectl: axis {name}: node {ac.node_id}: no answer to SDO ({exc})", file=sys.stderr)
                return 1
            _settle(session, 0.3)
            try:
                mode_text = cia402.Mode(mode).name
            except ValueError:
                mode_text = str(mode)
            unit = load_plant(ac.plant).effort_unit
            out[name] = {
                "node": ac.node_id,
                "nmt": nmt_states(session, {ac.node_id: node.sdo})[ac.node_id],
                "power_state": cia402.decode_statusword(sw).value,
                "statusword": f"0x{sw:04X}",
                "mode": mode_text,
                "error_code": f"0x{code:04X}",
                "error": cia402.error_text(code),
                "position_m": counts * ac.encoder_m_per_count,
                # the drive's own limit now, and what connecting writes there (limits.max_effort)
                "max_torque_permille": max_torque,
                "max_torque": EffortScale(ac.rated_effort).from_permille(max_torque),
                "max_effort": ac.limits.max_effort if math.isfinite(ac.limits.max_effort) else None,
                "effort_unit": unit,
                "last_emcy": emcy[-1].hex() if emcy else None,
                "rpdo_deadline_ms": rpdo_deadline,
                "deadline_ms": deadlines[name].ms,  # what connecting writes there
                "resident_loop": None if live is None else {
                    "pid": live["pid"], "age_s": live["age_s"], "cycles": live.get("cycles"),
                    "latency_ms": live.get("latency_ms"), "missed_fraction": live.get("missed_fraction"),
                    "worst_late_ms": live.get("worst_late_ms"), "stalls": live.get("stalls"),
                    "deadline_ms": live.get("deadline_ms", {}).get(name),
                    "state": live.get("axes", {}).get(name, {}).get("state")},
            }
    if args.json:
        print(json.dumps(out))
        return 0
    for name, s in out.items():
        print(f"axis {name} (node {s['node']}) on {session.bus}")
        print(f"  NMT          {s['nmt']}")
        print(f"  power state  {s['power_state']}  (statusword {s['statusword']})")
        print(f"  mode         {s['mode']}")
        print(f"  error        {s['error_code']}: {s['error']}")
        print(f"  position     {s['position_m'] * 1e3:.6f} mm")
        u = s["effort_unit"]
        limit = "unlimited: the drive's own is kept" if s["max_effort"] is None else \
            f"{s['max_effort']:g} {u} is written when an axis connects"
        print(f"  max torque   {s['max_torque']:g} {u} (0x6072 = {s['max_torque_permille']} per mille; "
              f"limits.max_effort {limit})")
        print(f"  last EMCY    {s['last_emcy'] or 'none'}")
        d = deadlines[name]
        now = "none" if s["rpdo_deadline_ms"] is None else f"{s['rpdo_deadline_ms']} ms"
        print(f"  deadline     0x1400:05 = {now}; connecting writes {d.ms} ms ({d.source}: {d.formula})")
        r = s["resident_loop"]
        if r is None:
            print("  loop         no session holds this bus (none published its loop: machine/live_status.py)")
        else:
            lat = r["latency_ms"] or {}
            if cfg.bus.interface == "virtual":  # an in-process bus: that session's drives are not the ones above
                print(f"  loop         session pid {r['pid']} runs this machine on its own in-process bus (its "
                      "emulated drives, not the ones above):")
            print(f"  loop         session pid {r['pid']} ({r['age_s']:.1f} s ago): axis {r['state']}, deadline "
                  f"{r['deadline_ms']} ms; {r['cycles']} cycles, missed {100 * (r['missed_fraction'] or 0):.3f} %, "
                  f"stalls {r['stalls']}")
            print("               lateness " + ", ".join(f"{q} {v:.2f}" for q, v in lat.items()) + " ms")
    return 0


def cmd_power(args: argparse.Namespace) -> int:
    """enable / disable / fault-reset: set the target, then cycle until the drive reports it."""
    from drivectl.controllers.runtime.servo import STATE_CHANGE_CYCLES
    from drivectl.driver.cia402 import PowerState
    from drivectl.machine.build import open_machine

    cfg = load_config(args.config)
    cfg.axis(args.axis)
    with open_machine(cfg, [args.axis]) as m:
        ax = m.axes[args.axis]
        ax.read()
        ax.write(0.0)
        want = {"enable": PowerState.OPERATION_ENABLED, "disable": PowerState.SWITCH_ON_DISABLED,
                "fault-reset": PowerState.SWITCH_ON_DISABLED}[args.command]
        {"enable": ax.enable, "disable": ax.disable, "fault-reset": ax.fault_reset}[args.command]()
        for _ in range(STATE_CHANGE_CYCLES):
            if ax.power is want:
                break
            ax.read()
            ax.write(0.0)
        if ax.power is not want:
            blocker = ax.enable_blocker() if want is PowerState.OPERATION_ENABLED else ""
            why = f": {blocker}" if blocker else ""
            print(f"drivectl: axis {args.axis}: still {ax.power.value} after {STATE_CHANGE_CYCLES} cycles "
                  f"(wanted {want.value}){why}", file=sys.stderr)
            return 1
        print(f"axis {args.axis}: {ax.power.value}")
    return 0


IDENTIFY_KEYS = {"m": "mass", "c_pos": "c_pos", "c_neg": "c_neg", "fc_pos": "fc_pos", "fc_neg": "fc_neg"}


def identify_axis(cfg: Any, name: str, *, sim: bool = False, model: str | None = None, plant: str | None = None,
                  noise: float = 0.0, approach: bool | None = None) -> dict[str, Any]:
    """Run the identification on axis ``name`` of ``cfg`` (emulated drive on the bus, or SimAxis);
    returns the identified parameters (keys of IDENTIFY_KEYS) and the model's, SI. An axis that is not
    at the identification profile's start is moved there first (controllers/runtime/approach.py; ``approach``: the
    ``--approach`` / ``--no-approach`` choice)."""
    from drivectl.controllers.pid import PidDob
    from drivectl.machine.build import model_specs, open_machine, plant_specs
    from drivectl.tools.commissioning.identify import identify_rigid

    cfg.axis(name)
    plants = plant_specs(cfg, [name], plant)
    model = model_specs(cfg, [name], model, plant, plants=plants)[name]
    if model.model != "rigid":
        raise ConfigError(f"{cfg.source}: axes.{name}: identify's constant-velocity runs fit a rigid axis, model "
                          f"{model.name} is {model.model}")
    machines = []

    def axis_factory(start: float):
        m = open_machine(cfg, [name], sim=sim, start={name: start}, plant=plant, noise=noise)
        machines.append(m)
        _approach(m.axes[name], start)
        return m.axes[name]

    def _approach(axis: Any, start: float) -> None:
        from drivectl.controllers.runtime.approach import plan_approach, where_axes_stand
        from drivectl.controllers.runtime.servo import Channel, LimitError, run_channels
        from drivectl.profiles.dwell import Dwell
        from drivectl.tools.cli.approach import consent

        ac = cfg.axis(name)
        ch = Channel(axis, controller_factory(cfg.cycle_s), Dwell(start, 1.0), ac.limits, {})
        plan, moves = plan_approach([ch], where_axes_stand([ch]), {name: ac.motion})
        if plan is None:
            return
        consent(approach, moves)
        res = run_channels(plan)  # ends disabled: the identification enables it again
        if not res.ok:
            raise LimitError(f"axis {name}: the approach to {start * 1e3:.3f} mm stopped: {res.detail}")

    def controller_factory(dt: float):
        # the loop's nominal mass is a rough guess on purpose: the result does not depend on it
        return PidDob.for_plant(dt, {"mass": 100.0}, axis=name if name in ("x", "y") else "x")

    try:
        out = identify_rigid(axis_factory, controller_factory=controller_factory)
    finally:
        for m in machines:
            m.close()
    return {"identified": {k: float(out[k]) for k in IDENTIFY_KEYS},
            "model": {k: model.params[v] for k, v in IDENTIFY_KEYS.items()}, "spec": model}


def cmd_identify(args: argparse.Namespace) -> int:
    from drivectl.plant_emulator.models import PlantSpec
    from drivectl.tracefile.format import atomic_write_text
    from drivectl.tracefile.stream import check_output_folder

    cfg = load_config(args.config)
    cfg.axis(args.axis)
    if getattr(args, "write_config", None) is not None:  # before anything moves
        from drivectl.machine.config_io import target_file

        args.write_config = str(target_file(args.write_config, args.config))
    from drivectl.machine.build import model_specs, plant_specs

    plants = plant_specs(cfg, [args.axis], getattr(args, "plant", None))
    believed = model_specs(cfg, [args.axis], getattr(args, "model", None), getattr(args, "plant", None),
                           plants=plants)[args.axis]
    check_output_folder(args.out, "--out", 1_000_000)  # the plant file goes there after the runs
    if believed.model == "two-mass":  # closed-loop FRF fit (tools/commissioning/identify_two_mass.py)
        from drivectl.tools.commissioning.identify_two_mass import cmd_identify_two_mass

        return cmd_identify_two_mass(args, cfg, believed, plants[args.axis], _merge_plant)
    t0 = time.perf_counter()
    result = identify_axis(cfg, args.axis, sim=args.sim, model=getattr(args, "model", None),
                           plant=getattr(args, "plant", None), noise=getattr(args, "noise", 0.0),
                           approach=getattr(args, "approach", None))
    keys = IDENTIFY_KEYS
    model = result["spec"]
    ident = result["identified"]
    current = model.params
    seconds = time.perf_counter() - t0
    spec = PlantSpec(name=f"{args.axis}-identified", model="rigid", effort_unit=model.effort_unit,
                     params={keys[k]: float(v) for k, v in ident.items()})
    path = Path(args.out) / f"{args.axis}-identified.toml"
    atomic_write_text(path, spec.to_toml(f"identified by drivectl identify --axis {args.axis} on "
                                          f"{'SimAxis' if args.sim else cfg.bus.interface}; load with --model {path} "
                                          "(or --plant)"))
    merged = _merge_plant(args, cfg, path)
    rel = {k: ident[k] / current[keys[k]] - 1.0 for k in keys}
    if args.json:
        print(json.dumps({"axis": args.axis, "identified": ident, "model": {k: current[keys[k]] for k in keys},
                          "rel_err": rel, "plant_file": str(path), "seconds": seconds}))
        return 0
    units = {"m": "kg", "c_pos": "N s/m", "c_neg": "N s/m", "fc_pos": "N", "fc_neg": "N"}
    print(f"axis {args.axis}: PID + DOB constant-velocity runs, 5-100 mm/s both ways ({seconds:.1f} s)")
    print(f"{'parameter':<16} {'identified':>10} {'model':>12} {'difference':>11}")
    for k in keys:
        print(f"{k + ' (' + units[k] + ')':<16} {ident[k]:>10.3f} {current[keys[k]]:>12.3f} {100 * rel[k]:>+10.3f} %")
    print(f"wrote {path}")
    if merged:
        print(merged)
    return 0


def _merge_plant(args: argparse.Namespace, cfg: Any, plant_file: Path) -> str:
    """``--write-config``: axes.AXIS.model = the identified model file (absolute: plant paths are read from
    the working folder). The model, not the plant: what was identified is what the controller should
    believe; the plant stays what the emulated drive plays. Returns the line to print ("" when not asked)."""
    if getattr(args, "write_config", None) is None:
        return ""
    from drivectl.machine.config_io import merge_into, target_file

    target = target_file(args.write_config, args.config)
    backup = merge_into(target, args.axis, {"model": str(plant_file.resolve())})
    return f"merged axes.{args.axis}.model into {target}" + (f" (old file kept as {backup})" if backup else "")

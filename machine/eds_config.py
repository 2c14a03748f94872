"""A machine configuration for one drive, from its EDS (``drivectl config init FILE --eds X.eds [--axis NAME]``).

The axis (default x) is that drive, emulated by default: the emulated drive impersonates the EDS
(plant_emulator/node402.py), so the file runs as it is written, and the same file drives the real one
once ``[bus]`` names the adapter. Every choice is commented: the mode, the PDO mapping and its bus budget,
what the drive lacks and what drivectl does instead, and the rated effort to fill in from the motor's data
(a placeholder that works on the emulated plant). A drive that lacks an essential is refused in one line
(driver/capabilities.py), and no file is written.
"""

from __future__ import annotations

from pathlib import Path

import canopen

from drivectl.driver.axis import AxisConfigError
from drivectl.driver.capabilities import FALLBACKS, MODE_NAMES, assess
from drivectl.driver.pdo_plan import plan
from drivectl.machine.bus_budget import frame_bits

CYCLE_S = 0.001
BITRATE = 1_000_000
#: the placeholder rated effort: 1000 per mille of 0x6071 = 100 N, what the emulated rigid plant is tuned for
PLACEHOLDER_RATED_N = 100.0


def read_eds(path: str | Path, node_id: int = 1) -> canopen.ObjectDictionary:
    try:
        return canopen.import_od(str(path), node_id)
    except FileNotFoundError:
        raise AxisConfigError(f"--eds {path}: no such file") from None
    except Exception as exc:  # canopen raises many types for a bad file
        reason = (str(exc).strip().splitlines() or [type(exc).__name__])[0].rstrip(":")
        raise AxisConfigError(f"--eds {path}: cannot be read: {reason}") from None


def plan_bits(frames: list[tuple[str, int, bool]]) -> tuple[int, int]:
    """(nominal, worst-case) bits per cycle of the cyclic frames of one axis, SYNC not included."""
    bits = [frame_bits(n) for _, n, cyclic in frames if cyclic]
    return sum(b[0] for b in bits), sum(b[1] for b in bits)


def _identity_lines(info: canopen.objectdictionary.DeviceInformation) -> list[str]:
    """The identity check and the values of [DeviceInfo] (0 or absent there: not stated, not checked)."""
    out = ['identity = "vendor+product"     # 0x1018 compared at boot: vendor+product | vendor | off | revision',
           "#   (revision: vendor, product and the exact revision below)"]
    for key, value, what in (("vendor_id", info.vendor_number, "VendorNumber"),
                             ("product_code", info.product_number, "ProductNumber"),
                             ("revision", info.revision_number, "RevisionNumber")):
        if value:
            out.append(f"{key} = 0x{value:08X}".ljust(32) + f"# [DeviceInfo] {what}")
        else:
            out.append(f"# {key}: the EDS's [DeviceInfo] states no {what}: {key.split('_')[0]} not checked")
    out.append('#   a sibling product or another firmware answers other codes: identity = "vendor" then')
    return out


def starter_config(eds: str | Path, axis: str = "x", node_id: int = 1) -> str:
    """The commented configuration text; :class:`~drivectl.driver.capabilities.DriveRefused` (one line) where
    the drive lacks an essential."""
    path = Path(eds).resolve()
    od = read_eds(path, node_id)
    where = f"--eds {eds}"
    caps = assess(od, where)
    pdo = plan(od, "full", node_id, where)
    info = od.device_information
    nominal, bound = plan_bits(pdo.frames())
    sync = frame_bits(0)
    load = 100.0 * (nominal + sync[0]) / (BITRATE * CYCLE_S)
    lines = [
        f"# drivectl machine configuration for the drive of {path.name} (drivectl config init --eds)",
        f"# EDS: vendor {info.vendor_name or '?'} (0x{info.vendor_number or 0:08X}), product "
        f"{info.product_name or '?'} (0x{info.product_number or 0:08X})",
        "# Emulated by default: the emulated drive impersonates this EDS (its objects, limits, PDO rules, modes and",
        "# identity), so `drivectl --config THIS trace --axis " + axis + "` runs before the hardware arrives. For the",
        "# real drive set [bus] to the adapter (interface, channel, bitrate) and fill in what is marked FILL IN.",
        f"cycle_s = {CYCLE_S}                 # servo cycle = SYNC period",
        "",
        "[bus]",
        'interface = "virtual"           # the emulated drive; real: socketcan, slcan, pcan, kvaser, socketcand, ...',
        'channel = "drivectl"            # virtual: any name; socketcan: can0; slcan: the tty',
        f"bitrate = {BITRATE}",
        'pdo_mapping = "full"            # full | compact | minimal | auto (machine/bus_budget.py)',
        "",
        f"[axes.{axis}]",
        f"node_id = {node_id}",
        f'eds = "{path}"',
        *_identity_lines(info),
        f"# mode: {MODE_NAMES[caps.mode]}, from {caps.modes_source} (0x{caps.modes:08X}); the",
        "#   device's own 0x6502 is read again at boot",
        f"# PDO mapping (full), within this drive's limits; bus budget {nominal} bits per cycle for this axis "
        f"({bound} worst case),",
        f"#   {load:.1f} % of {BITRATE / 1e6:g} Mbit/s at {CYCLE_S * 1e3:g} ms with the SYNC:",
        *(f"#   {line}" for line in pdo.lines()),
    ]
    said = dict(FALLBACKS)
    if caps.missing:
        lines.append("# what this drive lacks, and what drivectl does instead:")
        lines.extend(f"#   0x{i:04X} absent: {said[i]}" for i in caps.missing)
    else:
        lines.append("# every optional object drivectl uses is present")
    if caps.rated_effort_from_drive:
        rated = ("# rated_effort: written to the drive's 0x6076; FILL IN from the motor's data (the effort of 1000 "
                 "per mille of 0x6071)")
    else:
        rated = ("# rated_effort: the drive has no 0x6076, so drivectl takes it from here: FILL IN from the motor's "
                 "data (the effort of 1000 per mille of 0x6071)")
    profile = "circle" if axis in ("x", "y") else "short-move"
    lines += [
        rated,
        f"rated_effort = {PLACEHOLDER_RATED_N}           # N; {PLACEHOLDER_RATED_N:g} works on the emulated plant",
        'plant = "rigid-x"               # what the emulated drive plays (built-in name or plant TOML)',
        'controller = "mbc"',
        f'profile = "{profile}"',
        "encoder_m_per_count = 76.29e-9  # FILL IN: metres at the table per count of 0x6064",
        "rpdo_timeout_ms = 2             # the drive's deadline on the cyclic RPDO (0x14xx:05) where it has one",
        "# vendor-specific SDO writes before enable (motor data, a mode sub-select), each written then read back:",
        "# sdo_init = [",
        "#     [0x2000, 0, 1],           # [index, sub-index, value]",
        "# ]",
        f"[axes.{axis}.limits]",
        "position_m = [-0.1, 0.1]        # soft limits",
        "max_effort = 2000.0             # N, clipped here" + (" and by the drive (0x6072)" if 0x6072 in od else
                                                               " (the drive has no 0x6072)"),
        "following_error_m = 0.001",
        "following_time_s = 0.01",
        "",
    ]
    return "\n".join(lines)

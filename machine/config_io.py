"""The configuration file round trip: ``config show`` prints every key in use as TOML that loads back
to the same configuration, and results (``tune``, ``identify``, ``explain``) merge into a
configuration file on request (``--write-config``), with its comments kept (tomlkit) and a backup of
the old file.

What ``config show`` prints: every key the configuration sets, and every key it leaves to a default
or to the drive as a comment with the value in use (``# following_error_m = 0.005  # ...``), so that
the printed text loads back to the very same configuration (the defaults stay defaults, the limits
taken from the drive stay taken from the drive).
"""

from __future__ import annotations

import dataclasses
import math
import os
import shutil
import tomllib
from collections.abc import Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import tomlkit

from drivectl.controllers.runtime.homing import HOMING_KEYS
from drivectl.controllers.runtime.motion import MOTION_KEYS
from drivectl.machine.config import DEFAULT_CONFIG_TOML, ConfigError, MachineConfig, parse_config
from drivectl.tools.health.settings import DEFAULT_PROFILE


def _dotted(limits: dict[str, float]) -> dict[str, dict[str, float]]:
    """"effect.param" -> value as the TOML tables a configuration writes (backlash.width = 2e-05)."""
    out: dict[str, dict[str, float]] = {}
    for key, value in limits.items():
        effect, _, param = key.partition(".")
        out.setdefault(effect, {})[param] = value
    return out


def _plain(value: Any) -> Any:
    import numpy as np

    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, tuple):
        return list(value)
    return value


def _inline(value: Any) -> str:
    return tomlkit.item(_plain(value)).as_string()


def show_document(cfg: MachineConfig) -> tomlkit.TOMLDocument:
    """The configuration in use as a TOML document (see the module docstring)."""
    doc = tomlkit.document()
    doc.add(tomlkit.comment(f"resolved configuration from {cfg.source}"))
    doc.add("cycle_s", cfg.cycle_s)
    if cfg.loop is not None:  # where the wall-clock loop runs (session.connect's loop)
        doc.add("loop", cfg.loop)
    bus = tomlkit.table()
    b = cfg.bus
    bus.add("interface", b.interface)
    bus.add("channel", b.channel)
    bus.add("bitrate", b.bitrate)
    bus.add("host", b.host)
    bus["host"].comment("socketcand only")
    bus.add("port", b.port)
    bus["port"].comment("socketcand only")
    bus.add("load_ceiling_pct", b.load_ceiling_pct)
    bus.add("pdo_mapping", b.pdo_mapping)
    bus.add("sync", b.sync)
    bus["sync"].comment("auto: the transport's periodic SYNC where it has one off the Python thread; loop")
    if b.options:
        bus.add("options", dict(b.options))  # [bus.options]: passed to can.Bus as they are
    doc.add("bus", bus)
    checks = tomlkit.table()
    for f in dataclasses.fields(cfg.checks):
        checks.add(f.name, getattr(cfg.checks, f.name))
    doc.add("checks", checks)
    if cfg.health_store or cfg.health_limits:  # [health]: drivectl health's store and limits (docs/health.md)
        health = tomlkit.table()
        if cfg.health_store:
            health.add("store", cfg.health_store)
        if cfg.health_limits:
            health.add("limits", _dotted(cfg.health_limits))
        doc.add("health", health)
    axes = tomlkit.table(is_super_table=True)
    for name, ac in cfg.axes.items():
        t = tomlkit.table()
        t.add("node_id", ac.node_id)
        t.add("plant", ac.plant)
        t.add("controller", ac.controller)
        t.add("profile", ac.profile)
        t.add("rated_effort", ac.rated_effort)
        t.add("encoder_m_per_count", ac.encoder_m_per_count)
        t.add("eds", ac.eds)
        if ac.model is not None:
            t.add("model", ac.model)
        else:
            t.add(tomlkit.comment(f'model = "{ac.plant}"  (not set: the controller believes the plant)'))
        t.add("max_lost_cycles", ac.max_lost_cycles)
        t.add("last_resort", ac.last_resort)
        if ac.enable_settle_s:
            t.add("enable_settle_ms", ac.enable_settle_s * 1000.0)
        if ac.sdo_init:
            t.add("sdo_init", [list(entry) for entry in ac.sdo_init])
        if ac.identity is not None:
            t.add("identity", ac.identity.check)
            for key in ("vendor_id", "product_code", "revision"):
                value = getattr(ac.identity, key)
                if value is not None:
                    t.add(key, value)
                else:
                    t.add(tomlkit.comment(f"{key} not set: the EDS's [DeviceInfo] (0 or absent there: not checked)"))
        if ac.rpdo_timeout_ms is not None:
            t.add("rpdo_timeout_ms", ac.rpdo_timeout_ms)
        else:
            t.add(tomlkit.comment("rpdo_timeout_ms not set: the RPDO deadline (0x1400:05) is from the physics "
                                  "(docs/timing.md)"))
        settings = tomlkit.table()
        for k, v in ac.controller_settings.items():
            settings.add(k, _plain(v))
        for k, v in _settings_in_use(cfg, name).items():
            if k in ac.controller_settings:
                continue
            try:
                text = _inline(v)
            except (TypeError, ValueError):
                continue
            settings.add(tomlkit.comment(f"{k} = {text}  (not set: {ac.controller}'s value for this axis)"))
        t.add("controller_settings", settings)
        lim = ac.limits
        lt = tomlkit.table()
        drive = ac.limits_from_drive
        if lim.position is not None and "position" not in drive:
            lt.add("position_m", list(lim.position))
        else:
            lt.add(tomlkit.comment("position_m not set: the soft limits are the drive's (0x607D)"
                                   + ("" if lim.position is None else f", {list(lim.position)} when read")))
        if math.isfinite(lim.max_effort):
            lt.add("max_effort", lim.max_effort)
        else:
            lt.add(tomlkit.comment("max_effort not set: unlimited here; the drive's own 0x6072 is kept"))
        for key, attr, obj in (("following_error_m", "following_error", "0x6065"),
                               ("following_time_s", "following_time", "0x6066")):
            if attr in drive:
                lt.add(tomlkit.comment(f"{key} not set: the drive's ({obj}); {getattr(lim, attr)!r} if it has none"))
            else:
                lt.add(key, getattr(lim, attr))
        lt.add("max_speed_m_s", lim.max_speed)
        lt.add("max_jump_m", lim.max_jump)
        t.add("limits", lt)
        _add_keyed(t, "motion", ac.motion, MOTION_KEYS)
        _add_keyed(t, "homing", ac.homing, HOMING_KEYS)
        if ac.emulator is not None:
            _add_keyed(t, "emulator", ac.emulator, EMULATOR_KEYS)
        if ac.health is not None and (ac.health.limits or ac.health.profile != DEFAULT_PROFILE):
            ht = tomlkit.table()  # [axes.NAME.health]: the fingerprint run's profile, this axis's limits
            ht.add("profile", ac.health.profile)
            if ac.health.limits:
                ht.add("limits", _dotted(ac.health.limits))
            t.add("health", ht)
        axes.add(name, t)
    doc.add("axes", axes)
    return doc


#: [axes.NAME.emulator] keys and the fields of controllers/runtime/homing.py's EmulatorIO
EMULATOR_KEYS = {"home_switch_m": "home_switch", "limit_switches_m": "limit_switches", "hard_stops_m": "hard_stops",
                 "brake_release_ms": "brake_release_ms", "brake_engage_ms": "brake_engage_ms"}


def _add_keyed(table: Any, name: str, obj: Any, keys: Mapping[str, str]) -> None:
    """A sub-table of the axis from a parsed object whose fields the configuration's ``keys`` name: every
    key with the value in use (an unset optional one as a comment, so the text still loads back)."""
    if obj is None:
        return
    sub = tomlkit.table()
    for key, attr in keys.items():
        value = getattr(obj, attr)
        if key == "direction":
            value = "negative" if value < 0 else "positive"
        if value is None or (isinstance(value, float) and not math.isfinite(value)):
            sub.add(tomlkit.comment(f"{key} not set"))
        else:
            sub.add(key, _plain(value))
    table.add(name, sub)


def _settings_in_use(cfg: MachineConfig, name: str) -> dict[str, Any]:
    """Every setting of the axis's controller as it is built (its defaults, a paper's column for the
    axis, the plant's model); {} when it cannot be built here (the run would say why)."""
    from drivectl.controllers.registry import make_controller
    from drivectl.plant_emulator.models import load_plant

    ac = cfg.axes[name]
    try:
        model = load_plant(ac.model or ac.plant)
        ctrl = make_controller(ac.controller, cfg.cycle_s, ac.controller_settings, plant=model, axis=name)
        return {k: _plain(v) for k, v in ctrl.settings.as_dict().items()}
    except Exception:  # noqa: BLE001 - a courtesy: the keys the file sets are printed whatever happens
        return {}


def show_text(cfg: MachineConfig) -> str:
    return tomlkit.dumps(show_document(cfg))


# ---------------------------------------------------------------------------------------------- merging
def merge_into(path: str | Path, axis: str, values: Mapping[str, Any] | None = None,
               settings: Mapping[str, Any] | None = None, *, note: str = "", flag: str = "--write-config"
               ) -> Path | None:
    """Merge ``values`` (keys of ``[axes.AXIS]``) and ``settings`` (keys of its controller_settings)
    into the configuration file ``path``: comments and the other keys kept, the result validated as a
    whole before anything is written, the old file kept as ``PATH.STAMP.bak`` (returned; None when the
    file is new, made from the embedded default). Raises ConfigError (one line) and writes nothing when
    the file cannot be read or the merged configuration would not load."""
    from drivectl.tracefile.format import atomic_write_text

    p = Path(path)
    try:
        str(p).encode("utf-8")
    except UnicodeEncodeError:
        raise ConfigError(f"{flag} {os.fsencode(p)!r}: the path is not valid UTF-8; rename the file") from None
    if p.is_dir():
        raise ConfigError(f"{flag} {p}: is a folder (give the configuration file)")
    existed = p.exists()
    try:
        text = p.read_text() if existed else DEFAULT_CONFIG_TOML
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{flag} {p}: cannot read: {exc}") from None
    try:
        doc = tomlkit.parse(text)
    except tomlkit.exceptions.ParseError as exc:
        raise ConfigError(f"{flag} {p}: not valid TOML: {exc}") from None
    axes = doc.get("axes")
    if not isinstance(axes, Mapping) or axis not in axes:
        have = ", ".join(axes) if isinstance(axes, Mapping) else "none"
        raise ConfigError(f"{flag} {p}: axes.{axis}: no such axis to merge into (have {have})")
    table = axes[axis]
    for k, v in (values or {}).items():
        table[k] = _plain(v)
    if settings:
        if "controller_settings" not in table:
            table["controller_settings"] = tomlkit.table()
        st = table["controller_settings"]
        for k, v in settings.items():
            st[k] = _plain(v)
        if note:
            st.comment(note[:200])
    new_text = tomlkit.dumps(doc)
    try:
        parse_config(tomllib.loads(new_text), str(p))
    except tomllib.TOMLDecodeError as exc:  # tomlkit wrote what tomllib does not read: refuse
        raise ConfigError(f"{flag} {p}: the merged file would not load: {exc}") from None
    backup = None
    if existed:
        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
        for n in range(1, 10_000):
            backup = p.with_name(f"{p.name}.{stamp}{f'-{n}' if n > 1 else ''}.bak")
            try:
                fd = os.open(backup, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
            except FileExistsError:
                continue
            os.close(fd)
            shutil.copyfile(p, backup)
            shutil.copymode(p, backup)
            break
    atomic_write_text(p, new_text)
    return backup


def target_file(value: str, args_config: str | None, flag: str = "--write-config") -> Path:
    """``--write-config FILE``, or with no FILE the configuration in use (--config, $DRIVECTL_CONFIG)."""
    if value:
        return Path(value)
    current = args_config or os.environ.get("DRIVECTL_CONFIG")
    if not current:
        raise ConfigError(f"{flag}: no file given and no configuration file in use (the embedded default): "
                          f"give one, e.g. {flag} drivectl.toml")
    return Path(current)

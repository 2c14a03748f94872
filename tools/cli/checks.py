"""Checks of command-line values and outputs, made before a bus opens and anything moves.

Every check raises :class:`drivectl.machine.config.ConfigError` (or a TraceError for the outputs) with
one line naming the flag and the value; the CLI turns it into exit code 2. The rule they serve is the
project's: bad input is refused before the axis moves, and nothing is half-written.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from drivectl.machine.config import ConfigError
from drivectl.tracefile.stream import check_output_folder, estimate_bytes, safe_name

#: python-can Logger formats by suffix (``.gz`` compresses any of them)
BUS_LOG_SUFFIXES = (".asc", ".blf", ".log", ".csv", ".trc")


def parse_axes(text: str, flag: str = "--axis") -> list[str]:
    """``x`` or ``x,y``: each name non-empty, safe as a file name, named once."""
    if not text.strip():
        raise ConfigError(f"{flag} {text!r}: no axis name (give one, or several joined by commas: x,y)")
    names = [a.strip() for a in text.split(",")]
    seen = set()
    for name in names:
        if not name:
            raise ConfigError(f"{flag} {text!r}: an empty axis name (give names joined by commas: x,y)")
        if name in seen:
            raise ConfigError(f"{flag} {text!r}: axis {name} named twice (each axis runs once per cycle)")
        if not safe_name(name):
            raise ConfigError(f"{flag} {text!r}: axis name {name!r}: letters, digits, _ + - only")
        seen.add(name)
    return names


def check_number(flag: str, value: float | None, *, lo: float | None = None, lo_open: bool = False,
                 hi: float | None = None, unit: str = "") -> None:
    """A finite number within its range (None: not given, nothing to check)."""
    if value is None:
        return
    if not math.isfinite(value):
        raise ConfigError(f"{flag} {value}: expected a finite number{f' ({unit})' if unit else ''}")
    if lo is not None and (value <= lo if lo_open else value < lo):
        raise ConfigError(f"{flag} {value:g}: must be {'>' if lo_open else '>='} {lo:g}{f' {unit}' if unit else ''}")
    if hi is not None and value > hi:
        raise ConfigError(f"{flag} {value:g}: must be <= {hi:g}{f' {unit}' if unit else ''}")


def check_seed(seed: int, flag: str = "--seed") -> None:
    if not 0 <= seed < 2**63:
        raise ConfigError(f"{flag} {seed}: expected an integer 0 .. 2^63-1")


def check_bus_log(path: str | None, flag: str = "--bus-log") -> Path | None:
    """The bus log's format (by suffix) and its folder (exists, writable); the file itself is written by
    python-can once the bus opens."""
    if not path:
        return None
    p = Path(path)
    _utf8(flag, p)
    suffixes = [s.lower() for s in p.suffixes]
    suffix = suffixes[-2] if suffixes and suffixes[-1] == ".gz" and len(suffixes) > 1 else \
        (suffixes[-1] if suffixes else "")
    if suffix not in BUS_LOG_SUFFIXES:
        raise ConfigError(f"{flag} {path}: unknown log format (use .asc, .blf, .log, .csv or .trc, optionally .gz)")
    if p.is_dir():
        raise ConfigError(f"{flag} {path}: is a folder (give a file name, e.g. {p / 'bus.asc'})")
    folder = p.parent
    if not folder.is_dir():
        raise ConfigError(f"{flag} {path}: the folder {folder} does not exist")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise ConfigError(f"{flag} {path}: the folder {folder} is not writable")
    return p


def check_outputs(out: str | Path, rows: int, columns: int, axes: int, *, plot: bool, flag: str = "--out") -> Path:
    """``--out`` is a folder we can write, with room for the traces (and the plot)."""
    need = axes * estimate_bytes(rows, columns) + (2_000_000 if plot else 0)
    return check_output_folder(out, flag, need)


def carry_settings(settings: Mapping[str, Any], controller: str) -> tuple[dict[str, Any], list[str]]:
    """The axis's controller settings that ``controller`` also takes (kept), and the names of the others
    (dropped), for ``--controller``."""
    import dataclasses

    from drivectl.controllers.registry import controller_class

    fields = {f.name for f in dataclasses.fields(controller_class(controller).SettingsClass)}
    kept = {k: v for k, v in settings.items() if k in fields}
    return kept, sorted(k for k in settings if k not in fields)


def _utf8(flag: str, path: Path) -> None:
    try:
        str(path).encode("utf-8")
    except UnicodeEncodeError:
        raise ConfigError(f"{flag} {os.fsencode(path)!r}: the path is not valid UTF-8 (it is recorded as text); "
                          "rename it") from None

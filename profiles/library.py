"""Profiles as TOML files, and the built-in library in ``profiles/library/*.toml``.

``load_profile(name_or_path, axis="x")`` takes a library name (a file stem in ``profiles/library/``,
see ``list_profiles()``) or a path to a ``.toml`` file. Every error is a :class:`ProfileError` with one
line naming the file and the key, e.g. ``profiles/library/x.toml: vmax: expected a number > 0, got 'fast'``.

Format
------
A file describes one profile; ``kind`` selects its keys. Units are SI (m, s, m/s, m/s^2, m/s^3, rad).
Every kind also accepts an optional ``description`` string. Unknown keys are errors (a typo such as
``vmx`` must not silently fall back to a default).

``kind = "ptp"``: jerk-limited point-to-point move (:class:`~drivectl.profiles.ptp.PointToPoint`)::

    # seed-000: paper 000's reference (65 mm, 0.1 m/s, 1 m/s^2, 40 m/s^3), held to 2.5 s
    kind = "ptp"
    start = 0.0          # m
    target = 0.065       # m
    vmax = 0.1           # m/s,    > 0
    amax = 1.0           # m/s^2,  > 0
    jmax = 40.0          # m/s^3,  > 0
    t0 = 0.0             # s, optional (default 0): the move starts here, holding start before
    hold_until = 2.5     # s, optional: keep holding target until this time

``kind = "circle"``: one axis of a circle (:class:`~drivectl.profiles.circle.Circle`); which axis
(x = cos, y = sin) is the ``axis`` argument of ``load_profile``, so both axes load the same file::

    kind = "circle"
    radius = 0.04        # m, > 0
    period = 10.0        # s per revolution, > 0
    revolutions = 1.0    # optional (default 1), > 0; duration = revolutions * period + run_in_s / 2
    center = [0.0, 0.0]  # optional (default [0, 0]): [x, y] of the centre, m
    phase = 0.0          # optional (default 0), rad
    run_in_s = 0.2       # optional (default 0: eq (25)'s step to the feed at t = 0), s: the path speed
                         # ramps from rest to the feed along the circle (cycloidal law)

``kind = "dwell"``: stand still: ``position`` (m), ``duration`` (s, >= 0).

``kind = "back-and-forth"``: commissioning run (:func:`~drivectl.profiles.sequence.back_and_forth`):
``start`` (m), ``distance`` (m, non-zero, sign = first direction), ``speeds`` (array of m/s, each > 0),
``amax``, ``jmax`` (> 0), ``dwell`` (s, >= 0), ``repeats`` (optional integer >= 1, default 1).

``kind = "sequence"``: segments played one after another, each an ``[[segments]]`` table of any kind
(nested sequences included)::

    kind = "sequence"
    [[segments]]
    kind = "ptp"
    start = 0.0
    target = 0.01
    vmax = 0.05
    amax = 0.5
    jmax = 20.0
    [[segments]]
    kind = "dwell"
    duration = 0.5       # position omitted: where the previous segment ended

In segments after the first, the start key (``start`` of ptp/back-and-forth, ``position`` of dwell)
may be omitted and then defaults to where the previous segment ended; if given, it must equal that
(within 1e-9 m). Keys inside segments are named ``segments[i].key`` in errors (i counts from 0).
"""

from __future__ import annotations

import math
import os
import re
import tomllib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from drivectl.profiles.base import Profile, ProfileError
from drivectl.profiles.circle import Circle
from drivectl.profiles.dwell import Dwell
from drivectl.profiles.ptp import PointToPoint
from drivectl.profiles.sequence import CONTINUITY_TOLERANCE, Sequence, back_and_forth

LIBRARY_DIR = Path(__file__).with_name("library")
KINDS = ("ptp", "circle", "dwell", "sequence", "back-and-forth")

_REQUIRED = object()  # sentinel: the key has no default


def list_profiles() -> list[str]:
    """Names of the built-in profiles (file stems in profiles/library/), sorted."""
    return sorted(p.stem for p in LIBRARY_DIR.glob("*.toml"))


def load_profile(name_or_path: str | os.PathLike[str], axis: str = "x") -> Profile:
    """Load a library profile by name, or a profile TOML file by path, for ``axis``.

    ``axis`` only matters for circles ("x" or "y"); other kinds ignore it, so any axis name works.
    """
    path, shown = _resolve(name_or_path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ProfileError(f"{shown}: cannot read: {exc.strerror or exc}") from exc
    except UnicodeDecodeError as exc:
        raise ProfileError(f"{shown}: cannot read: not UTF-8 ({exc.reason} at byte {exc.start})") from exc
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ProfileError(f"{shown}: invalid TOML: {_decode_error(exc, text)}") from exc
    ctx = _Ctx(shown, "", path.stem, axis)
    try:
        profile = _build(ctx, data, prev_end=None)
    except ProfileError as exc:
        # The loader validates every key itself; anything a constructor still refuses (e.g. ruckig) gets
        # the file name prepended so the message always says which file.
        if str(exc).startswith(f"{shown}: "):
            raise
        raise ProfileError(f"{shown}: {exc}") from exc
    profile.source = shown  # limit errors (check_limits) then name the file
    return profile


# --------------------------------------------------------------------------------------------------
def _resolve(name_or_path: str | os.PathLike[str]) -> tuple[Path, str]:
    """(file, how to name it in messages). A bare name is a library profile; anything path-like a file."""
    text = os.fspath(name_or_path)
    if isinstance(name_or_path, os.PathLike) or text.endswith(".toml") or "/" in text or os.sep in text:
        return Path(text), text
    path = LIBRARY_DIR / f"{text}.toml"
    if not path.is_file():
        raise ProfileError(
            f"profile {text!r}: no such library profile (available: {', '.join(list_profiles())}); "
            "give a path to a .toml file for your own"
        )
    return path, f"profiles/library/{text}.toml"


def _decode_error(exc: tomllib.TOMLDecodeError, text: str) -> str:
    # tomllib reports "(at line N, column M)"; quoting that line names the offending key for the reader.
    msg = str(exc)
    m = re.search(r"at line (\d+)", msg)
    if m:
        lines = text.splitlines()
        n = int(m.group(1))
        if 1 <= n <= len(lines) and lines[n - 1].strip():
            line = lines[n - 1].strip()
            line = line if len(line) <= 60 else line[:57] + "..."
            msg += f": {line!r}"
    return msg


@dataclass(frozen=True)
class _Ctx:
    """Where we are: the file as shown, the key prefix inside it ("segments[1]."), names for the profile."""

    file: str
    prefix: str
    name: str
    axis: str

    def error(self, key: str, problem: str) -> ProfileError:
        return ProfileError(f"{self.file}: {self.prefix}{key}: {problem}")

    def number(
        self,
        tbl: dict[str, Any],
        key: str,
        *,
        gt: float | None = None,
        ge: float | None = None,
        nonzero: bool = False,
        default: Any = _REQUIRED,
    ) -> Any:
        if key not in tbl:
            if default is _REQUIRED:
                raise self.error(key, f"missing (required for kind {tbl['kind']!r})")
            return default
        return self.check_number(key, tbl[key], gt=gt, ge=ge, nonzero=nonzero)

    def check_number(
        self, key: str, value: Any, *, gt: float | None = None, ge: float | None = None, nonzero: bool = False
    ) -> float:
        want = "a non-zero number" if nonzero else "a number"
        want += f" > {gt:g}" if gt is not None else f" >= {ge:g}" if ge is not None else ""
        ok = not isinstance(value, bool) and isinstance(value, int | float) and math.isfinite(value)
        ok = ok and (gt is None or value > gt) and (ge is None or value >= ge) and (not nonzero or value != 0)
        if not ok:
            raise self.error(key, f"expected {want}, got {value!r}")
        return float(value)


def _build(ctx: _Ctx, tbl: dict[str, Any], prev_end: float | None) -> Profile:
    kind = tbl.get("kind", _REQUIRED)
    if kind is _REQUIRED:
        raise ctx.error("kind", f"missing (one of {', '.join(KINDS)})")
    if kind not in KINDS:
        raise ctx.error("kind", f"expected one of {', '.join(KINDS)}, got {kind!r}")
    builder, keys = _KINDS[kind]
    unknown = [k for k in tbl if k not in keys and k not in ("kind", "description")]
    if unknown:
        allowed = ", ".join((*keys, "description"))
        raise ctx.error(unknown[0], f"unknown key for kind {kind!r} (allowed: {allowed})")
    if "description" in tbl and not isinstance(tbl["description"], str):
        raise ctx.error("description", f"expected a string, got {tbl['description']!r}")
    return builder(ctx, tbl, prev_end)


def _start(ctx: _Ctx, tbl: dict[str, Any], key: str, prev_end: float | None) -> float:
    """A segment's start key: optional after the first segment, and if given it must continue."""
    if prev_end is None:
        return ctx.number(tbl, key)
    value = ctx.number(tbl, key, default=prev_end)
    if abs(value - prev_end) > CONTINUITY_TOLERANCE:
        raise ctx.error(key, f"{value:g} m but the previous segment ends at {prev_end:.9g} m")
    return value


def _ptp(ctx: _Ctx, tbl: dict[str, Any], prev_end: float | None) -> Profile:
    t0 = ctx.number(tbl, "t0", ge=0, default=0.0)
    hold_until = ctx.number(tbl, "hold_until", ge=0, default=None)
    return PointToPoint(
        _start(ctx, tbl, "start", prev_end),
        ctx.number(tbl, "target"),
        ctx.number(tbl, "vmax", gt=0),
        ctx.number(tbl, "amax", gt=0),
        ctx.number(tbl, "jmax", gt=0),
        t0=t0,
        hold_until=hold_until,
        name=ctx.name,
    )


def _circle(ctx: _Ctx, tbl: dict[str, Any], prev_end: float | None) -> Profile:
    if ctx.axis not in ("x", "y"):
        raise ctx.error("axis", f"a circle needs axis 'x' or 'y' (load_profile's axis), got {ctx.axis!r}")
    radius = ctx.number(tbl, "radius", gt=0)
    period = ctx.number(tbl, "period", gt=0)
    revolutions = ctx.number(tbl, "revolutions", gt=0, default=1.0)
    phase = ctx.number(tbl, "phase", default=0.0)
    run_in = ctx.number(tbl, "run_in_s", ge=0, default=0.0)
    center = tbl.get("center", [0.0, 0.0])
    if not isinstance(center, list) or len(center) != 2:
        raise ctx.error("center", f"expected an array of two numbers [x, y], got {center!r}")
    cx, cy = (ctx.check_number(f"center[{i}]", c) for i, c in enumerate(center))
    center_here = cx if ctx.axis == "x" else cy
    circle = Circle(ctx.axis, radius, period, revolutions, center_here, phase, run_in=run_in, name=ctx.name)
    start = circle.start_position
    if prev_end is not None and abs(start - prev_end) > CONTINUITY_TOLERANCE:
        raise ProfileError(
            f"{ctx.file}: {ctx.prefix.rstrip('.')}: the circle starts at {start:.9g} m on axis {ctx.axis} "
            f"but the previous segment ends at {prev_end:.9g} m"
        )
    return circle


def _dwell(ctx: _Ctx, tbl: dict[str, Any], prev_end: float | None) -> Profile:
    return Dwell(_start(ctx, tbl, "position", prev_end), ctx.number(tbl, "duration", ge=0), name=ctx.name)


def _back_and_forth(ctx: _Ctx, tbl: dict[str, Any], prev_end: float | None) -> Profile:
    start = _start(ctx, tbl, "start", prev_end)
    distance = ctx.number(tbl, "distance", nonzero=True)
    if "speeds" not in tbl:
        raise ctx.error("speeds", "missing (required for kind 'back-and-forth')")
    speeds = tbl["speeds"]
    if not isinstance(speeds, list) or not speeds:
        raise ctx.error("speeds", f"expected a non-empty array of numbers > 0, got {speeds!r}")
    speed_list = [ctx.check_number(f"speeds[{i}]", v, gt=0) for i, v in enumerate(speeds)]
    amax = ctx.number(tbl, "amax", gt=0)
    jmax = ctx.number(tbl, "jmax", gt=0)
    dwell = ctx.number(tbl, "dwell", ge=0)
    repeats = tbl.get("repeats", 1)
    if isinstance(repeats, bool) or not isinstance(repeats, int) or repeats < 1:
        raise ctx.error("repeats", f"expected an integer >= 1, got {repeats!r}")
    return back_and_forth(start, distance, speed_list, amax, jmax, dwell, repeats, name=ctx.name)


def _sequence(ctx: _Ctx, tbl: dict[str, Any], prev_end: float | None) -> Profile:
    if "segments" not in tbl:
        raise ctx.error("segments", "missing (required for kind 'sequence': [[segments]] tables)")
    raw = tbl["segments"]
    if not isinstance(raw, list) or not raw or not all(isinstance(s, dict) for s in raw):
        raise ctx.error("segments", f"expected one or more [[segments]] tables, got {raw!r}")
    segments: list[Profile] = []
    end = prev_end
    for i, seg_tbl in enumerate(raw):
        sub = _Ctx(ctx.file, f"{ctx.prefix}segments[{i}].", f"{ctx.name}.segments[{i}]", ctx.axis)
        seg = _build(sub, seg_tbl, end)
        segments.append(seg)
        end = float(seg.sample(np.array([seg.duration]))[0][0])
    try:
        return Sequence(segments, name=ctx.name)
    except ProfileError as exc:  # continuity is checked per segment above; this is a backstop
        raise ProfileError(f"{ctx.file}: {ctx.prefix}segments: {exc}") from exc


_Builder = Callable[[_Ctx, dict[str, Any], float | None], Profile]
_KINDS: dict[str, tuple[_Builder, tuple[str, ...]]] = {
    "ptp": (_ptp, ("start", "target", "vmax", "amax", "jmax", "t0", "hold_until")),
    "circle": (_circle, ("radius", "period", "revolutions", "center", "phase", "run_in_s")),
    "dwell": (_dwell, ("position", "duration")),
    "back-and-forth": (_back_and_forth, ("start", "distance", "speeds", "amax", "jmax", "dwell", "repeats")),
    "sequence": (_sequence, ("segments",)),
}

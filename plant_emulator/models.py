"""Plant models: the dynamics that SimAxis and the emulated CiA 402 drive both step, once per cycle.

A plant is described by a :class:`Design` (bodies, the coupling between them, forces on the table,
the drive's input stage) built from a base model and any effects (``effects.py``), then compiled
for a fixed cycle ``dt`` into a :class:`Plant`. ``Plant.step(state, effort)`` advances a
:class:`PlantState` by one cycle with the effort held constant (zero-order hold, as a cyclic
synchronous torque drive applies it). All units SI; forces in the plant's effort unit.

Integration, and why it is accurate:

* The linear part (masses, viscous friction, springs, the coupling of two bodies) is discretised
  exactly for the substep ``h``: ``s' = A s + B F`` with ``A = expm(Ac h)`` and ``B`` the exact
  zero-order-hold input matrix. The 89 Hz axial mode of ``two-mass`` is therefore integrated without
  any step-size error or artificial damping, at any ``h`` (a purely linear plant uses one substep).
* Coulomb friction (with its direction-dependent level and the Stribeck breakaway) is the one
  discontinuity at v = 0. It is handled as a set-valued force solved implicitly at the end of each
  substep (Moreau's time-stepping): the free motion is computed without it, then the friction
  impulse opposes the end-of-substep velocity, limited to ``fc h``; if that limit can stop the
  body, the body sticks (v = 0 exactly) with the friction that holds it. No chattering around
  v = 0, stiction is exact, and the only error is the timing of a stop within one substep
  (plants with Coulomb friction default to 10 substeps of 100 us at 1 kHz; halving them changes
  the tracking error of a trace by well under 1 %, see tests/test_models.py).
* Forces that depend on position or time (periodic lead error, disturbances, the sign-dependent
  part of viscous friction) are evaluated at the substep's midpoint estimate and held for it.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy.linalg import expm

from drivectl.errors import InputError

PLANTS_DIR = Path(__file__).with_name("plants")

#: substeps per cycle for a plant with Coulomb friction or a dead zone (100 us at 1 kHz)
NONLINEAR_SUBSTEPS = 10


class PlantError(InputError):
    """A plant file or parameter is invalid. The message is one line naming the file and the key."""


# --------------------------------------------------------------------------------------------------
# Design: the pre-compilation description that base models and effects edit
# --------------------------------------------------------------------------------------------------


@dataclass
class Body:
    """A lumped mass with its friction (levels are magnitudes, per direction of motion)."""

    mass: float
    c_pos: float = 0.0
    c_neg: float = 0.0
    fc_pos: float = 0.0
    fc_neg: float = 0.0
    stribeck_excess: float = 0.0
    stribeck_velocity: float = 1.0

    @property
    def has_coulomb(self) -> bool:
        return self.fc_pos > 0.0 or self.fc_neg > 0.0 or self.stribeck_excess > 0.0


@dataclass
class Coupling:
    """Spring and damper between body 0 (driven) and body 1 (table); ``gap`` > 0 makes a dead zone.

    With a gap the spring acts only beyond +-gap/2 (contact), the damper only while in contact.
    """

    stiffness: float
    damping: float
    gap: float = 0.0


@dataclass
class Design:
    """Everything a plant is made of. ``bodies[0]`` takes the effort, ``bodies[-1]`` is measured."""

    bodies: list[Body]
    effort_unit: str
    coupling: Coupling | None = None
    table_stiffness: float = 0.0  # N/m, spring to ground on the table, rest point q = 0
    table_offset: float = 0.0  # constant force on the table, + pushes towards +q
    periodic: list[tuple[float, float, float]] = field(default_factory=list)  # (amplitude, period, phase)
    disturbance_amplitude: float = 0.0  # d1 = d2 = A sin(2 pi f t) on every body (paper 000)
    disturbance_frequency: float = 0.0
    input_delay: float = 0.0  # s, on top of the transport delay
    input_limit: float = math.inf  # the drive clips the applied effort at +-limit

    @property
    def total_mass(self) -> float:
        return sum(b.mass for b in self.bodies)


def rigid_design(params: dict[str, float], effort_unit: str) -> Design:
    """Paper 004 eq (5): one mass, direction-dependent Coulomb and viscous friction."""
    body = Body(
        mass=params["mass"],
        c_pos=params["c_pos"],
        c_neg=params["c_neg"],
        fc_pos=params["fc_pos"],
        fc_neg=params["fc_neg"],
    )
    return Design(bodies=[body], effort_unit=effort_unit)


def two_mass_design(params: dict[str, float], effort_unit: str) -> Design:
    """Paper 000 eq (1): screw side m1 (driven) and table m2, joined by stiffness k and damping n."""
    return Design(
        bodies=[
            Body(mass=params["m1"], c_pos=params["b1"], c_neg=params["b1"]),
            Body(mass=params["m2"], c_pos=params["b2"], c_neg=params["b2"]),
        ],
        effort_unit=effort_unit,
        coupling=Coupling(stiffness=params["k"], damping=params["n"]),
        disturbance_amplitude=params.get("disturbance_amplitude", 0.0),
        disturbance_frequency=params.get("disturbance_frequency", 0.0),
    )


#: base models: name -> (required params, optional params, design builder)
MODELS: dict[str, tuple[tuple[str, ...], tuple[str, ...], Any]] = {
    "rigid": (("mass", "c_pos", "c_neg", "fc_pos", "fc_neg"), (), rigid_design),
    "two-mass": (
        ("m1", "m2", "k", "n", "b1", "b2"),
        ("disturbance_amplitude", "disturbance_frequency"),
        two_mass_design,
    ),
}


# --------------------------------------------------------------------------------------------------
# PlantSpec: a named parameter set with effects, as stored in plants/*.toml
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PlantSpec:
    """A base model, its parameters and the effects added to it (in the order given)."""

    name: str
    model: str
    effort_unit: str
    params: dict[str, float]
    effects: tuple[tuple[str, dict[str, float]], ...] = ()
    source: str = "<memory>"
    #: what identification found out about this model (``[identified]`` in the file: the well-identified
    #: combinations such as total_mass and mode_hz with their uncertainties, the poorly identified
    #: parameters); informational, it changes no dynamics (tools/commissioning/identify_two_mass.py)
    identified: dict[str, Any] = field(default_factory=dict)

    def with_effect(self, name: str, **params: float) -> PlantSpec:
        """A copy with one more effect (validated now, so errors surface at the call)."""
        from drivectl.plant_emulator.effects import validate_effect

        validate_effect(name, params, source=self.source)
        return replace(self, effects=self.effects + ((name, dict(params)),))

    def without_effects(self) -> PlantSpec:
        return replace(self, effects=())

    def design(self) -> Design:
        from drivectl.plant_emulator.effects import apply_effects

        builder = MODELS[self.model][2]
        design = builder(self.params, self.effort_unit)
        apply_effects(design, self.effects, source=self.source)
        return design

    def build(self, dt: float, substeps: int | None = None) -> Plant:
        return Plant(self.design(), dt, substeps=substeps, name=self.name)

    @property
    def nominal_mass(self) -> float:
        return self.design().total_mass

    def to_toml(self, comment: str = "") -> str:
        """The spec as a plant file that ``load_plant`` reads back."""
        lines = [f"# {line}" for line in comment.splitlines()] if comment else []
        lines += [f'model = "{self.model}"', f'effort_unit = "{self.effort_unit}"', "", "[params]"]
        lines += [f"{k} = {_toml_float(v)}" for k, v in self.params.items()]
        for name, params in self.effects:
            lines += ["", "[[effects]]", f'name = "{name}"']
            lines += [f"{k} = {_toml_float(v)}" for k, v in params.items()]
        if self.identified:
            lines += ["", "# what identification found (informational: the dynamics are [params] and [[effects]])",
                      "[identified]"]
            tables = {k: v for k, v in self.identified.items() if isinstance(v, dict)}
            lines += [f"{k} = {_toml_value(v)}" for k, v in self.identified.items() if k not in tables]
            for tname, table in tables.items():
                lines += ["", f"[identified.{tname}]"] + [f"{k} = {_toml_value(v)}" for k, v in table.items()]
        return "\n".join(lines) + "\n"


def _toml_value(v: Any) -> str:
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return _toml_float(v)


def _toml_float(v: float) -> str:
    text = repr(float(v))
    return text if text not in ("inf", "-inf", "nan") else f'"{text}"'


def builtin_plants() -> list[str]:
    return sorted(p.stem for p in PLANTS_DIR.glob("*.toml"))


def load_plant(name_or_path: str | Path) -> PlantSpec:
    """A built-in plant by name (``rigid-x``, ``rigid-y``, ``two-mass``) or a plant TOML file."""
    path = Path(name_or_path)
    if not path.suffix and not path.exists():
        candidate = PLANTS_DIR / f"{name_or_path}.toml"
        if not candidate.exists():
            known = ", ".join(builtin_plants())
            raise PlantError(f"plant {name_or_path!r}: no such built-in plant or file (built-in: {known})")
        path = candidate
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise PlantError(f"{path}: no such plant file") from None
    except OSError as exc:
        raise PlantError(f"{path}: cannot read: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise PlantError(f"{path}: not a text file") from None
    except tomllib.TOMLDecodeError as exc:
        raise PlantError(f"{path}: not valid TOML: {exc}") from None
    name = path.stem if path.parent == PLANTS_DIR else str(path)
    return plant_from_mapping(data, source=str(path), name=name)


def plant_from_mapping(data: dict[str, Any], source: str, name: str) -> PlantSpec:
    """Validate a parsed plant table; every error names ``source`` and the key."""
    from drivectl.plant_emulator.effects import validate_effect

    unknown = set(data) - {"model", "effort_unit", "params", "effects", "name", "identified"}
    if unknown:
        raise PlantError(f"{source}: {sorted(unknown)[0]}: unknown key (expected model, effort_unit, params, effects, "
                         "identified)")
    identified = data.get("identified", {})
    if not isinstance(identified, dict):
        raise PlantError(f"{source}: identified: expected a table [identified]")
    if not isinstance(data.get("name", ""), str):
        raise PlantError(f"{source}: name: expected a string, got {data['name']!r}")
    model = data.get("model")
    if not isinstance(model, str) or model not in MODELS:
        raise PlantError(f"{source}: model: expected one of {', '.join(MODELS)}, got {model!r}")
    unit = data.get("effort_unit", "N")
    if unit not in ("N", "V"):
        raise PlantError(f"{source}: effort_unit: expected \"N\" or \"V\", got {unit!r}")
    required, optional, _ = MODELS[model]
    raw = data.get("params")
    if not isinstance(raw, dict):
        raise PlantError(f"{source}: params: missing table [params]")
    params: dict[str, float] = {}
    for key in raw:
        if key not in required and key not in optional:
            raise PlantError(f"{source}: params.{key}: unknown parameter of model {model!r}")
    for key in required + optional:
        if key not in raw:
            if key in required:
                raise PlantError(f"{source}: params.{key}: missing (model {model!r} needs it)")
            continue
        value = raw[key]
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
            raise PlantError(f"{source}: params.{key}: expected a finite number, got {value!r}")
        positive = key in ("mass", "m1", "m2", "k")
        if value < 0 or (positive and value == 0):
            raise PlantError(f"{source}: params.{key}: must be {'> 0' if positive else '>= 0'}, got {value!r}")
        params[key] = float(value)
    effects: list[tuple[str, dict[str, float]]] = []
    raw_effects = data.get("effects", [])
    if not isinstance(raw_effects, list):
        raise PlantError(f"{source}: effects: expected an array of tables [[effects]]")
    for i, entry in enumerate(raw_effects):
        if not isinstance(entry, dict) or "name" not in entry:
            raise PlantError(f"{source}: effects[{i}].name: missing")
        ename = entry["name"]
        eparams = {k: v for k, v in entry.items() if k != "name"}
        validate_effect(ename, eparams, source=source, key=f"effects[{i}]")
        effects.append((ename, {k: float(v) for k, v in eparams.items()}))
    spec = PlantSpec(
        name=str(data.get("name", name)),
        model=model,
        effort_unit=unit,
        params=params,
        effects=tuple(effects),
        source=source,
        identified=dict(identified),
    )
    spec.design()  # effects that cannot combine fail here, at load time
    return spec


# --------------------------------------------------------------------------------------------------
# The compiled plant
# --------------------------------------------------------------------------------------------------


class PlantState:
    """Everything that evolves: time, positions and velocities, the input history (delay)."""

    __slots__ = ("t", "s", "history")

    def __init__(self, t: float, s: list[float], history: list[float]):
        self.t = t
        self.s = s  # [x0, v0] or [x0, v0, x1, v1]
        self.history = history  # commanded efforts of past cycles, newest last (delay effect)

    def copy(self) -> PlantState:
        return PlantState(self.t, list(self.s), list(self.history))


#: discretisations already computed, by (Ac, Bc, h): explain's fits build the same candidate plants again
#: and again (coarse and fine substeps, refits each round): ~85 % of its expm calls were repeats
_ZOH_CACHE: dict[tuple[bytes, bytes, tuple[int, int], float], tuple[list[list[float]], list[list[float]]]] = {}
_ZOH_CACHE_MAX = 4096


def _discretise(ac: np.ndarray, bc: np.ndarray, h: float) -> tuple[list[list[float]], list[list[float]]]:
    """Exact zero-order-hold discretisation: one expm of the augmented matrix [[Ac, Bc], [0, 0]] h."""
    ac = np.ascontiguousarray(ac, dtype=float)
    bc = np.ascontiguousarray(bc, dtype=float)
    key = (ac.tobytes(), bc.tobytes(), bc.shape, float(h))
    hit = _ZOH_CACHE.get(key)
    if hit is None:
        n, m = bc.shape
        aug = np.zeros((n + m, n + m))
        aug[:n, :n] = ac
        aug[:n, n:] = bc
        e = expm(aug * h)
        hit = (e[:n, :n].tolist(), e[:n, n:].tolist())
        if len(_ZOH_CACHE) >= _ZOH_CACHE_MAX:
            _ZOH_CACHE.clear()
        _ZOH_CACHE[key] = hit
    return [list(r) for r in hit[0]], [list(r) for r in hit[1]]  # copies: a caller may change its own


class Plant:
    """A design compiled for cycle ``dt``: ``step(state, effort)`` advances one cycle."""

    def __init__(self, design: Design, dt: float, substeps: int | None = None, name: str = "plant"):
        if not dt > 0:
            raise PlantError(f"plant {name}: dt: must be > 0, got {dt!r}")
        self.name = name
        self.design = design
        self.dt = float(dt)
        self.effort_unit = design.effort_unit
        nonlinear = any(b.has_coulomb for b in design.bodies) or (
            design.coupling is not None and design.coupling.gap > 0
        )
        needs_sub = nonlinear or design.periodic or design.input_delay > 0
        if substeps is None:
            substeps = NONLINEAR_SUBSTEPS if needs_sub else 1
            if design.coupling is not None and design.coupling.gap > 0:
                substeps = 2 * NONLINEAR_SUBSTEPS  # contact transitions of the 400 Hz lash contact
        if not (isinstance(substeps, int) and substeps >= 1):
            raise PlantError(f"plant {name}: substeps: must be an integer >= 1, got {substeps!r}")
        self.substeps = substeps
        self.h = self.dt / substeps
        self.n_bodies = len(design.bodies)
        self.bodies = design.bodies
        self._coulomb = [b.has_coulomb for b in design.bodies]
        self._any_coulomb = any(self._coulomb)
        # viscous friction depends on the direction of motion: the exact linear part is discretised
        # once per combination of directions, and each substep uses the one it moves in
        self._asym = any(b.c_pos != b.c_neg for b in design.bodies)
        cpl = design.coupling
        self._gap = cpl.gap if cpl else 0.0
        combos = [(1, 1)] if not self._asym else [(a, b) for a in (1, -1) for b in (1, -1)]
        self._mats = {}
        for dirs in combos:
            self._mats[(True, *dirs)] = self._matrices(engaged=True, dirs=dirs)
            if self._gap > 0:
                self._mats[(False, *dirs)] = self._matrices(engaged=False, dirs=dirs)
        self.A, self.B = self._mats[(True, 1, 1)]
        #: one body: (a00, a01, a10, a11, b0, b1) of a substep per direction of motion (the hot path's view)
        self._one_coefs = {} if self.n_bodies != 1 else {
            dirs[0]: (A[0][0], A[0][1], A[1][0], A[1][1], B[0][0], B[1][0])
            for (engaged, *dirs), (A, B) in self._mats.items() if engaged and dirs[1] == 1}
        # delay: split into whole cycles and a fraction, looked up per substep
        d = design.input_delay / self.dt
        self._delay_cycles = int(math.floor(d + 1e-9))
        self._delay_frac = max(0.0, d - self._delay_cycles)
        self._history_len = self._delay_cycles + 2 if design.input_delay > 0 else 0
        self._limit = design.input_limit
        self._dist_w = 2 * math.pi * design.disturbance_frequency
        self._dist_a = design.disturbance_amplitude

    # -- the discretisation, read by the batch simulators (tools/explain/sim.py, plant_emulator/batch.py) --
    @property
    def gap(self) -> float:
        """Backlash width, m (0: the bodies are always engaged)."""
        return self._gap

    @property
    def delay(self) -> tuple[int, float] | None:
        """The input delay as (whole cycles, fraction of a cycle); None without one."""
        return (self._delay_cycles, self._delay_frac) if self._history_len else None

    @property
    def history_len(self) -> int:
        """Applied efforts a state keeps for the input delay (0 without one)."""
        return self._history_len

    def substep_matrices(self, engaged: bool, dir0: int, dir1: int) -> tuple[list[list[float]], list[list[float]]]:
        """(A, B) of one substep, engaged or in the gap, moving in directions ``dir0``/``dir1`` (+-1);
        directions that do not change the matrices (no asymmetric friction) share one pair, as in step."""
        key = (engaged if self._gap else True, dir0 if self._asym else 1,
               dir1 if (self._asym and self.n_bodies == 2) else 1)
        return self._mats[key]

    def _matrices(self, engaged: bool, dirs: tuple[int, int]) -> tuple[list[list[float]], list[list[float]]]:
        d = self.design
        n = self.n_bodies
        ac = np.zeros((2 * n, 2 * n))
        bc = np.zeros((2 * n, n))
        for i, b in enumerate(d.bodies):
            ac[2 * i, 2 * i + 1] = 1.0
            ac[2 * i + 1, 2 * i + 1] = -(b.c_pos if dirs[i] > 0 else b.c_neg) / b.mass
            bc[2 * i + 1, i] = 1.0 / b.mass
        table = n - 1
        ac[2 * table + 1, 2 * table] -= d.table_stiffness / d.bodies[table].mass
        if d.coupling is not None and engaged:
            add_coupling(ac, d.coupling.stiffness, d.coupling.damping, d.bodies[0].mass, d.bodies[1].mass)
        return _discretise(ac, bc, self.h)

    # ---------------------------------------------------------------------------------------------
    def initial_state(self, position: float = 0.0) -> PlantState:
        """At rest at ``position`` (every body, coupling relaxed)."""
        s = [position, 0.0] * self.n_bodies
        return PlantState(0.0, s, [0.0] * self._history_len)

    def position(self, state: PlantState) -> float:
        """Table position (what the encoder measures)."""
        return state.s[-2]

    def velocity(self, state: PlantState) -> float:
        return state.s[-1]

    def applied_effort(self, state: PlantState, effort: float) -> float:
        """The effort the drive actually applies for the cycle starting now (after any limit)."""
        lim = self._limit
        return -lim if effort < -lim else lim if effort > lim else effort

    # ---------------------------------------------------------------------------------------------
    def step(self, state: PlantState, effort: float) -> PlantState:
        """Advance ``state`` by one cycle with ``effort`` held (in place; returns the state)."""
        hist = state.history
        if self._history_len:
            hist.append(effort)
            del hist[0]
        if self.n_bodies == 1 and not self._gap:
            self._step_one(state, effort)
        else:
            self._step_two(state, effort)
        state.t += self.dt
        return state

    def _input(self, state: PlantState, effort: float, i: int) -> float:
        """Effort acting during substep i, after the extra delay and the drive's limit."""
        if self._history_len:
            hist = state.history
            n = self._delay_cycles
            cur, prev = hist[-1 - n], hist[-2 - n]
            # the delayed ZOH signal switches at frac*dt into the cycle: weight each side
            t0 = i * self.h
            w_prev = (self._delay_frac * self.dt - t0) / self.h
            w_prev = 0.0 if w_prev < 0.0 else 1.0 if w_prev > 1.0 else w_prev
            effort = w_prev * prev + (1.0 - w_prev) * cur
        lim = self._limit
        return -lim if effort < -lim else lim if effort > lim else effort

    def _table_force(self, state_t: float, x: float, v: float) -> float:
        """Position- and time-dependent forces on the table at (t, x), midpoint of a substep."""
        d = self.design
        f = d.table_offset
        for amp, period, phase in d.periodic:
            f += amp * math.sin(2 * math.pi * x / period + phase)
        return f

    def _coulomb_limit(self, i: int, v_ref: float, direction: float) -> float:
        """Coulomb (+ Stribeck) magnitude for motion in ``direction`` at speed |v_ref|."""
        b = self.bodies[i]
        fc = b.fc_pos if direction > 0 else b.fc_neg
        if b.stribeck_excess:
            r = v_ref / b.stribeck_velocity
            fc += b.stribeck_excess * math.exp(-r * r)
        return fc

    def _step_one(self, state: PlantState, effort: float) -> None:
        # the per-cycle path of every emulated axis: everything that holds for the cycle is read once,
        # and each substep is the same arithmetic, operation for operation, as tools/explain/sim.py's
        x, v = state.s
        h = self.h
        t = state.t
        design = self.design
        has_forces = bool(design.periodic) or design.table_offset != 0.0
        delayed = bool(self._history_len)
        dist_a = self._dist_a
        asym = self._asym
        coefs = self._one_coefs
        a00, a01, a10, a11, b0, b1 = coefs[1]
        side = 1  # whose coefficients those are
        coulomb = self._coulomb[0]
        body = self.bodies[0]
        fc_pos, fc_neg = body.fc_pos, body.fc_neg
        excess = body.stribeck_excess
        f_in = self._input(state, effort, 0)
        for i in range(self.substeps):
            f = self._input(state, effort, i) if delayed else f_in
            if has_forces:
                f += self._table_force(t + (i + 0.5) * h, x + 0.5 * h * v, v)
            if dist_a:
                f += dist_a * math.sin(self._dist_w * (t + (i + 0.5) * h))
            if asym:
                # direction of motion in this substep: of the velocity, or of the force from rest (its
                # coefficients unpacked again only when it changes)
                going = 1 if (v > 0.0 or (v == 0.0 and f >= 0.0)) else -1
                if going != side:
                    a00, a01, a10, a11, b0, b1 = coefs[going]
                    side = going
            xf = a00 * x + a01 * v + b0 * f
            vf = a10 * x + a11 * v + b1 * f
            if coulomb:
                # Moreau: friction opposes the end-of-substep velocity, impulse limited to fc h
                # (the Coulomb + Stribeck level of _coulomb_limit, written out)
                if vf == 0.0:
                    lam = 0.0
                else:
                    stick_limit = fc_pos if vf > 0.0 else fc_neg
                    if excess:
                        r = v / body.stribeck_velocity
                        stick_limit += excess * math.exp(-r * r)
                    hold = b1 * stick_limit
                    if -hold <= vf <= hold:  # |vf| <= hold, without a call per substep
                        lam = -vf / b1  # holding force: the body stops (or stays) at v = 0
                    else:  # against the motion: -direction * stick_limit, exactly
                        lam = -stick_limit if vf > 0.0 else stick_limit
                xf += b0 * lam
                vf += b1 * lam
                if -1e-15 < vf < 1e-15:
                    vf = 0.0
            x, v = xf, vf
        state.s[0] = x
        state.s[1] = v

    def _step_two(self, state: PlantState, effort: float) -> None:
        s = state.s
        h = self.h
        t = state.t
        d = self.design
        has_forces = bool(d.periodic) or d.table_offset != 0.0
        gap = self._gap
        delayed = bool(self._history_len)
        f_in = self._input(state, effort, 0)
        for i in range(self.substeps):
            x0, v0, x1, v1 = s
            f0 = self._input(state, effort, i) if delayed else f_in
            f1 = 0.0
            if has_forces:
                f1 += self._table_force(t + (i + 0.5) * h, x1 + 0.5 * h * v1, v1)
            if self._dist_a:
                dist = self._dist_a * math.sin(self._dist_w * (t + (i + 0.5) * h))
                f0 += dist
                f1 += dist
            engaged = True
            if gap:
                rel = x0 - x1
                half = 0.5 * gap
                if rel > half:
                    # spring acts on (rel - half): the constant part k*half enters as a force pair
                    kh = d.coupling.stiffness * half
                    f0 += kh
                    f1 -= kh
                elif rel < -half:
                    kh = d.coupling.stiffness * half
                    f0 -= kh
                    f1 += kh
                else:
                    engaged = False
            if self._asym:
                d0 = 1 if (v0 > 0.0 or (v0 == 0.0 and f0 >= 0.0)) else -1
                d1 = 1 if (v1 > 0.0 or (v1 == 0.0 and f1 + f0 >= 0.0)) else -1
                A, B = self._mats[(engaged, d0, d1)]
            else:
                A, B = self._mats[(engaged, 1, 1)]
            new = [
                A[r][0] * x0 + A[r][1] * v0 + A[r][2] * x1 + A[r][3] * v1 + B[r][0] * f0 + B[r][1] * f1
                for r in range(4)
            ]
            if self._any_coulomb:
                # Moreau friction body by body (table first: it carries most friction), each
                # impulse applied through its column of B so the coupled body feels it too
                for body in (1, 0):
                    if not self._coulomb[body]:
                        continue
                    vi = 2 * body + 1
                    vf = new[vi]
                    if vf == 0.0:
                        continue
                    g = B[vi][body]
                    direction = 1.0 if vf > 0.0 else -1.0
                    vref = s[vi]
                    limit = self._coulomb_limit(body, vref, direction)
                    lam = -vf / g if abs(vf) <= g * limit else -direction * limit
                    for r in range(4):
                        new[r] += B[r][body] * lam
                    if abs(new[vi]) < 1e-15:
                        new[vi] = 0.0
            s[0], s[1], s[2], s[3] = new


def add_coupling(ac: np.ndarray, k: float, c: float, m0: float, m1: float) -> None:
    """Add a spring ``k`` and damper ``c`` between body 0 and body 1 to the continuous state matrix ``ac``
    (states x0, v0, x1, v1): force on body 0 -k (x0 - x1) - c (v0 - v1), on body 1 the opposite."""
    ac[1, 0] -= k / m0
    ac[1, 2] += k / m0
    ac[1, 1] -= c / m0
    ac[1, 3] += c / m0
    ac[3, 0] += k / m1
    ac[3, 2] -= k / m1
    ac[3, 1] += c / m1
    ac[3, 3] -= c / m1

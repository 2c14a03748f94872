"""Physical effects that make a machine differ from its model; the vocabulary of `drivectl explain`.

Each effect edits a :class:`~drivectl.plant_emulator.models.Design` and can be added to any plant.
Names, parameters and conventions are the contract of docs/effects.md (SI; force-like
parameters in the plant's effort unit):

============  =======================  ==============================================================
stribeck      excess_force, velocity   extra friction excess_force exp(-(v/velocity)^2) sgn(v);
                                       breakaway at Coulomb + excess_force
backlash      width                    total lost motion between screw and table; screw side 30 % of
                                       the mass with 10 % of the friction, table 70 % with 90 %, dead
                                       zone +-width/2, stiff contact when engaged; the table is measured
periodic      amplitude, period        force amplitude sin(2 pi q / period + phase) on the table
                                       (phase optional, default 0)
mass          mass                     the true total moving mass, kg
viscous       scale, scale_neg (opt.)  both viscous coefficients (c+ and c-) times scale; with
                                       scale_neg, c+ times scale and c- times scale_neg
coulomb       force_pos, force_neg     the true Coulomb friction for motion in + and in - (both >= 0),
                                       replacing the model's fc+ and fc-
delay         delay                    extra delay of the effort, on top of the transport delay
offset        force                    signed constant force, + pushes towards +q
spring        stiffness                force -stiffness q, rest point q = 0
resonance     frequency, damping       the mass becomes two masses (force on the motor side, all
                                       friction and the encoder on the table) joined by a spring and
                                       damper; frequency = sqrt(k / mu) / 2 pi, mu = m1 m2 / (m1 + m2)
saturation    limit                    the drive clips the applied effort at +-limit
============  =======================  ==============================================================

Choices the table leaves open, made here once:

* backlash contact: stiffness for a 400 Hz contact mode on the two split masses, damping ratio 0.7
  (a well-damped, nearly inelastic contact: a ball-nut takes up lash without ringing);
* resonance split: the same 30 % / 70 % mass split as backlash; ``damping`` is the damping ratio
  zeta of the mode, the damper is 2 zeta sqrt(k mu);
* stribeck on a plant with several friction-carrying bodies: the excess is shared in proportion to
  each body's Coulomb friction (on the table when no body has any);
* coulomb on a plant with several bodies: the new level per direction is shared in the proportion
  of the model's Coulomb friction per body (on the table when no body has any), so the total
  Coulomb force for motion in + is force_pos and in - force_neg.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass

from drivectl.plant_emulator.models import Body, Coupling, Design, PlantError

#: screw side of a split axis (backlash, resonance): share of the mass and of the friction
SCREW_MASS_SHARE = 0.30
SCREW_FRICTION_SHARE = 0.10
BACKLASH_CONTACT_HZ = 400.0
BACKLASH_CONTACT_DAMPING = 0.7


@dataclass(frozen=True)
class ParamDef:
    name: str
    unit: str
    lo: float | None = None  # None: any sign
    lo_open: bool = False
    optional: bool = False
    default: float = 0.0


@dataclass(frozen=True)
class Effect:
    name: str
    params: tuple[ParamDef, ...]
    apply: Callable[..., None]
    doc: str

    @property
    def required(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.params if not p.optional)


def _positive(name: str, unit: str) -> ParamDef:
    return ParamDef(name, unit, lo=0.0, lo_open=True)


def _nonneg(name: str, unit: str) -> ParamDef:
    return ParamDef(name, unit, lo=0.0)


# --------------------------------------------------------------------------------------------------
def _split(design: Design, what: str, screw_friction: float) -> tuple[Body, Body]:
    if len(design.bodies) != 1:
        raise PlantError(f"{what}: needs a one-mass plant (this plant already has two bodies)")
    b = design.bodies[0]
    fs = screw_friction
    screw = Body(
        mass=SCREW_MASS_SHARE * b.mass,
        c_pos=fs * b.c_pos,
        c_neg=fs * b.c_neg,
        fc_pos=fs * b.fc_pos,
        fc_neg=fs * b.fc_neg,
        stribeck_excess=fs * b.stribeck_excess,
        stribeck_velocity=b.stribeck_velocity,
    )
    table = Body(
        mass=(1 - SCREW_MASS_SHARE) * b.mass,
        c_pos=(1 - fs) * b.c_pos,
        c_neg=(1 - fs) * b.c_neg,
        fc_pos=(1 - fs) * b.fc_pos,
        fc_neg=(1 - fs) * b.fc_neg,
        stribeck_excess=(1 - fs) * b.stribeck_excess,
        stribeck_velocity=b.stribeck_velocity,
    )
    return screw, table


def _reduced_mass(a: Body, b: Body) -> float:
    return a.mass * b.mass / (a.mass + b.mass)


def _stribeck(d: Design, excess_force: float, velocity: float) -> None:
    shares = [b.fc_pos + b.fc_neg for b in d.bodies]
    total = sum(shares)
    if total == 0:
        shares = [0.0] * (len(d.bodies) - 1) + [1.0]
        total = 1.0
    for b, share in zip(d.bodies, shares, strict=True):
        b.stribeck_excess += excess_force * share / total
        b.stribeck_velocity = velocity


def _backlash(d: Design, width: float) -> None:
    screw, table = _split(d, "backlash", SCREW_FRICTION_SHARE)
    mu = _reduced_mass(screw, table)
    w = 2 * math.pi * BACKLASH_CONTACT_HZ
    k = mu * w * w
    d.bodies = [screw, table]
    d.coupling = Coupling(stiffness=k, damping=2 * BACKLASH_CONTACT_DAMPING * math.sqrt(k * mu), gap=width)


def _periodic(d: Design, amplitude: float, period: float, phase: float = 0.0) -> None:
    d.periodic.append((amplitude, period, phase))


def _mass(d: Design, mass: float) -> None:
    ratio = mass / d.total_mass
    for b in d.bodies:
        b.mass *= ratio
    if d.coupling is not None and d.coupling.gap > 0:
        # keep the contact mode where it was: contact stiffness scales with the masses
        d.coupling.stiffness *= ratio
        d.coupling.damping *= ratio


def _viscous(d: Design, scale: float, scale_neg: float | None = None) -> None:
    neg = scale if scale_neg is None else scale_neg
    for b in d.bodies:
        b.c_pos *= scale
        b.c_neg *= neg


def _coulomb(d: Design, force_pos: float, force_neg: float) -> None:
    for attr, total in (("fc_pos", force_pos), ("fc_neg", force_neg)):
        shares = [getattr(b, attr) for b in d.bodies]
        s = sum(shares)
        if s <= 0:
            shares, s = [0.0] * (len(d.bodies) - 1) + [1.0], 1.0
        for b, share in zip(d.bodies, shares, strict=True):
            setattr(b, attr, total * share / s)


def _delay(d: Design, delay: float) -> None:
    d.input_delay += delay


def _offset(d: Design, force: float) -> None:
    d.table_offset += force


def _spring(d: Design, stiffness: float) -> None:
    d.table_stiffness += stiffness


def _resonance(d: Design, frequency: float, damping: float) -> None:
    screw, table = _split(d, "resonance", 0.0)
    mu = _reduced_mass(screw, table)
    w = 2 * math.pi * frequency
    k = mu * w * w
    d.bodies = [screw, table]
    d.coupling = Coupling(stiffness=k, damping=2 * damping * math.sqrt(k * mu))


def _saturation(d: Design, limit: float) -> None:
    d.input_limit = min(d.input_limit, limit)


EFFECTS: dict[str, Effect] = {
    e.name: e
    for e in (
        Effect("stribeck", (_positive("excess_force", "effort"), _positive("velocity", "m/s")), _stribeck,
               "extra friction near zero speed, breakaway at Coulomb + excess_force"),
        Effect("backlash", (_positive("width", "m"),), _backlash, "lost motion between screw and table"),
        Effect("periodic", (_nonneg("amplitude", "effort"), _positive("period", "m"),
                            ParamDef("phase", "rad", optional=True)), _periodic,
               "position-periodic force on the table (lead error, runout)"),
        Effect("mass", (_positive("mass", "kg"),), _mass, "true total moving mass"),
        Effect("viscous", (_nonneg("scale", "1"), ParamDef("scale_neg", "1", lo=0.0, optional=True)), _viscous,
               "viscous coefficients times scale (c- times scale_neg when given)"),
        Effect("coulomb", (_nonneg("force_pos", "effort"), _nonneg("force_neg", "effort")), _coulomb,
               "the true Coulomb friction per direction of motion"),
        Effect("delay", (_nonneg("delay", "s"),), _delay, "extra delay of the effort"),
        Effect("offset", (ParamDef("force", "effort"),), _offset, "constant force, + towards +q"),
        Effect("spring", (_nonneg("stiffness", "effort/m"),), _spring, "force -stiffness q"),
        Effect("resonance", (_positive("frequency", "Hz"), _nonneg("damping", "1")), _resonance,
               "two masses joined by a spring and damper"),
        Effect("saturation", (_positive("limit", "effort"),), _saturation, "drive clips effort at +-limit"),
    )
}

#: the names `explain` may answer with: the effects, or none
VOCABULARY: tuple[str, ...] = ("none", *EFFECTS)


def validate_effect(name: str, params: Mapping[str, object], source: str = "effect", key: str = "") -> None:
    """Raise PlantError (one line naming source and key) unless ``name`` with ``params`` is valid."""
    where = f"{source}: {key + '.' if key else ''}"
    if not isinstance(name, str) or name not in EFFECTS:
        raise PlantError(f"{where}name: unknown effect {name!r} (known: {', '.join(EFFECTS)})")
    eff = EFFECTS[name]
    defs = {p.name: p for p in eff.params}
    for pname in params:
        if pname not in defs:
            raise PlantError(f"{where}{pname}: not a parameter of {name} (parameters: {', '.join(defs)})")
    for p in eff.params:
        if p.name not in params:
            if p.optional:
                continue
            raise PlantError(f"{where}{p.name}: missing (effect {name} needs {', '.join(eff.required)})")
        value = params[p.name]
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
            raise PlantError(f"{where}{p.name}: expected a finite number, got {value!r}")
        if p.lo is not None and (value <= p.lo if p.lo_open else value < p.lo):
            raise PlantError(f"{where}{p.name}: must be {'>' if p.lo_open else '>='} {p.lo:g}, got {value!r}")


def apply_effects(design: Design, effects: Iterable[tuple[str, Mapping[str, float]]], source: str = "") -> None:
    """Apply each effect to ``design`` in order; errors name ``source``."""
    for name, params in effects:
        validate_effect(name, params, source=source or "effect")
        try:
            EFFECTS[name].apply(design, **params)
        except PlantError as exc:
            raise PlantError(f"{source or 'plant'}: effects: {exc}") from None


def parse_effect(text: str) -> tuple[str, dict[str, float]]:
    """``"backlash:width=20e-6"`` or ``"periodic:amplitude=12,period=0.01"`` -> (name, params)."""
    name, _, rest = text.partition(":")
    name = name.strip()
    params: dict[str, float] = {}
    if rest.strip():
        for item in rest.split(","):
            k, eq, v = item.partition("=")
            if not eq:
                raise PlantError(f"--effect {text}: {item.strip()!r}: expected name=value")
            try:
                params[k.strip()] = float(v)
            except ValueError:
                raise PlantError(f"--effect {text}: {k.strip()}: expected a number, got {v.strip()!r}") from None
    validate_effect(name, params, source=f"--effect {text}")
    return name, params

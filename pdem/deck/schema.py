"""Pydantic models of a pdem deck (TOML), the first validation pass.

Every model forbids unknown keys, rejects non-finite numbers and documents each key with
``Field(description=...)`` (so :func:`pdem.deck.deck_json_schema` documents it for editors). SI units.

Validation is meant to run in pydantic's *strict JSON* mode (``Deck.model_validate_json(text,
strict=True, context=...)``, which is what :func:`pdem.deck.load_deck` does): a string is never
turned into a number, an array becomes a fixed-length tuple, an integer is accepted where a float is
expected.

Checks that involve more than one key (``exactly one of n / volume_fraction``, ``r_min <= r_max``,
names that refer to materials, stages and boundaries …) are *rules*: each model's :meth:`rules`
looks at the raw table and returns ``(relative key path, message)`` pairs. They run through a wrap
validator **whether or not the fields themselves validated**, so a deck with a bad type in one key
and a dangling material name elsewhere reports both at once. Rules therefore never assume that a
raw value has the right type.

Three sections belong to plugins and are validated in a second pass by :mod:`pdem.deck.load` with
the plugin's own ``Params`` model: the keys of ``[contact]`` other than ``law`` (the contact law's
parameters), each ``[[particles]]`` table (the source plugin's parameters) and each
``[boundaries.NAME]`` table (the boundary plugin's parameters). Their models here
(:class:`ContactSection`, :class:`ParticleEntry`, :class:`BoundaryEntry`) are the only ones that
accept extra keys. The periodic-box checks that need the sources' sizes (:func:`periodic_source_checks`)
run in that pass too.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import re
from typing import Annotated, Any, ClassVar, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    SerializeAsAny,
    Strict,
    ValidationError,
    ValidationInfo,
    model_serializer,
    model_validator,
)
from pydantic_core import InitErrorDetails, PydanticCustomError
from pydantic_core.core_schema import ErrorType

from ..contact.stability import STIFFNESS_LIMIT
from ..errors import PdemError
from ..materials import Material
from ..textutil import quote

__all__ = [
    "Deck",
    "RunSection",
    "DomainSection",
    "ContactSection",
    "MaterialSpec",
    "MaterialPair",
    "BoxRegionSpec",
    "CylinderRegionSpec",
    "RegionSpec",
    "SingleSizes",
    "UniformSizes",
    "NormalSizes",
    "TableSizes",
    "SizeSpec",
    "ParticleEntry",
    "BoundaryEntry",
    "StageEnd",
    "OutputCadence",
    "Stage",
    "OutputSection",
    "ContinuumSpec",
    "CONTINUUM_QUANTITIES",
    "MAX_CONTINUUM_POINTS",
    "KNOWN_WRITERS",
    "OUTPUT_FIELDS",
    "THERMO_KEYS",
    "THERMO_DEFAULT",
    "NAME_PATTERN",
    "RULE_ERROR",
    "MAX_TITLE_LENGTH",
    "MAX_STAGE_STEPS",
    "MAX_DEPTH",
    "MAX_ENTRIES",
    "MAX_NAME_LENGTH",
    "MAX_STAGES",
    "MAX_BOUNDARIES",
    "MAX_MATERIALS",
    "MAX_SOURCES",
    "MAX_THERMO_COLUMNS",
    "MAX_SNAPSHOTS_PER_STAGE",
    "MAX_SERIES_ROWS_PER_STAGE",
    "MAX_CHECKPOINTS_PER_STAGE",
    "MAX_MAGNITUDE",
    "RADIUS_RANGE",
    "DENSITY_RANGE",
    "radius_problem",
    "periodic_source_checks",
]

#: writers accepted in ``output.formats`` when the caller passes no list of installed writers
KNOWN_WRITERS: tuple[str, ...] = ("hdf5", "vtk")
#: per-particle fields a snapshot may hold
OUTPUT_FIELDS: tuple[str, ...] = ("x", "v", "w", "r", "material", "f", "contacts", "id")
#: thermo columns besides measured quantities ``<boundary>.<key>``
THERMO_KEYS: tuple[str, ...] = ("step", "time", "dt", "particles", "ke", "ke_trans", "ke_rot", "contacts")
#: thermo columns when ``output.thermo`` is not given
THERMO_DEFAULT: tuple[str, ...] = ("step", "time", "particles", "ke", "contacts")
#: stage and boundary names: a letter or ``_`` first, then letters, digits, ``_`` or ``-``
NAME_PATTERN = r"^[A-Za-z_][A-Za-z0-9_-]*$"
_NAME_RE = re.compile(NAME_PATTERN)
#: pydantic error type of rule violations (the message is final, used verbatim)
RULE_ERROR = "deck_rule"
#: longest ``title`` accepted [characters]; it is copied into every output file's metadata
MAX_TITLE_LENGTH = 1000
#: most steps a stage may take by its end time or max_time at a dt given in the deck: beyond this a
#: run cannot finish (1e10 steps of even a tiny scene take days), so the dt or the time is a mistake
MAX_STAGE_STEPS = 10**10

# Limits on what a deck may ask for (docs/deck.md, "Limits"). A real deck is far inside every one of
# them; beyond them a deck is a mistake or hostile, and would exhaust the stack, the disk or double
# precision rather than run.
#: deepest nesting of tables and arrays (key path length); a real deck needs about 6
MAX_DEPTH = 64
#: most entries of one array or table
MAX_ENTRIES = 100_000
#: longest stage, boundary or material name [characters]: stage and boundary names are parts of
#: output file names (series_<stage>.csv, solver_<stage>.csv, <boundary>.<stage>.csv), which the
#: file system limits to 255 bytes
MAX_NAME_LENGTH = 64
#: most [[stages]]: each stage writes its own series file(s) and a checkpoint when it ends
MAX_STAGES = 1000
#: most [boundaries.NAME]: a boundary's records are one file per stage
MAX_BOUNDARIES = 256
#: most [materials.NAME] (the contact tables hold one entry per pair of materials)
MAX_MATERIALS = 256
#: most [[particles]] tables
MAX_SOURCES = 1000
#: most columns in output.thermo
MAX_THERMO_COLUMNS = 100
#: most snapshots, series rows and periodic checkpoints one stage may write, when its length is
#: known from the deck (a stage that ends only by steps and/or time, at a dt given in the deck)
MAX_SNAPSHOTS_PER_STAGE = 100_000
MAX_SERIES_ROWS_PER_STAGE = 10_000_000
MAX_CHECKPOINTS_PER_STAGE = 10_000
#: largest magnitude of a coordinate or vector component (positions, velocities, gravity, …) and of
#: any number in a plugin's table: beyond it squares and products of lengths, speeds and masses
#: overflow double precision (1.8e308)
MAX_MAGNITUDE = 1e100
#: sphere radii [m] (sources' sizes and packing files): below, a grain's mass and moment of inertia
#: (ρ r⁵) underflow; above, they overflow; atoms and planets are outside it
RADIUS_RANGE = (1e-10, 1e10)
#: material densities [kg/m³]: aerogel-in-air is about 1, osmium 22,590; even mass-scaled
#: quasi-static runs stay far inside
DENSITY_RANGE = (1e-6, 1e20)

_KNOWN_ERROR_TYPES = frozenset(ErrorType.__args__)  # type: ignore[attr-defined]

Loc = tuple[str | int, ...]
Problems = list[tuple[Loc, str]]

# strict scalars: a string is never turned into a number or a boolean, a float never into an integer
# (an integer is accepted where a float is expected); arrays become fixed-length tuples
Float = Annotated[float, Strict()]
Int = Annotated[int, Strict()]
Bool = Annotated[bool, Strict()]
Str = Annotated[str, Strict()]
Count = Annotated[int, Strict(), Field(ge=1)]
_Component = Annotated[float, Strict(), Field(ge=-MAX_MAGNITUDE, le=MAX_MAGNITUDE)]
Vec3 = Annotated[
    tuple[_Component, _Component, _Component],
    Field(description=f"three numbers (x, y, z), each of magnitude at most {MAX_MAGNITUDE:.0e}"),
]


# -------------------------------------------------------------------------------------------------
# helpers for rules (raw values may have any type)
# -------------------------------------------------------------------------------------------------


def _is_num(value: Any) -> bool:
    """A finite int or float (not a bool)."""
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _is_vec3(value: Any) -> bool:
    return isinstance(value, list | tuple) and len(value) == 3 and all(_is_num(c) for c in value)


def _given(data: dict, key: str) -> bool:
    return data.get(key) is not None


def did_you_mean(word: str, choices: list[str] | tuple[str, ...], inline: bool = False) -> str:
    """``"; did you mean 'x'?"`` (or `` " (did you mean 'x'?)"`` when ``inline``) for the closest of
    ``choices`` (difflib), or ``""``."""
    names = [str(c) for c in choices]
    if len(str(word)) > 100 or len(names) > 1000:  # no sensible suggestion; difflib would be slow
        return ""
    close = difflib.get_close_matches(str(word), names, n=1, cutoff=0.6)
    if not close and len(str(word)) >= 3:  # a truncated key: 'clamp' for 'clamp_normal'
        close = [c for c in names if c.startswith(str(word))][:2]
        close = close if len(close) == 1 else []
    if not close:
        return ""
    return f" (did you mean '{close[0]}'?)" if inline else f"; did you mean '{close[0]}'?"


def _listing(names: list[str] | tuple[str, ...], most: int = 20) -> str:
    """``'a', 'b', 'c'``: at most ``most`` names (each quoted briefly), then how many there are."""
    if not names:
        return "(none)"
    shown = ", ".join(quote(str(n), 80) for n in list(names)[:most])
    return shown if len(names) <= most else f"{shown}, … ({len(names):,} in all)"


def _repeated(names: list[str]) -> list[str]:
    """The names that occur more than once, sorted (linear: a list may be long)."""
    seen: set[str] = set()
    twice: set[str] = set()
    for n in names:
        (twice if n in seen else seen).add(n)
    return sorted(twice)


def _q(value: Any) -> str:
    """A value from the deck in single quotes, at most ~200 characters of it."""
    return quote(value if isinstance(value, str) else str(value))


def radius_problem(value: Any, what: str = "radius") -> str | None:
    """A message if ``value``, a sphere radius [m], is a number > 0 outside :data:`RADIUS_RANGE`;
    else None (a value that is not a positive number is the schema's to report)."""
    lo, hi = RADIUS_RANGE
    if not _is_num(value) or value <= 0 or lo <= value <= hi:
        return None
    return (
        f"{what} {value!r} m is outside [{lo:.0e}, {hi:.0e}] m, the sphere radii pdem accepts: a grain's "
        "mass and moment of inertia (ρ r⁵) would leave double precision; give the radius in metres"
    )


def _magnitude_rules(data: dict, keys: tuple[str, ...]) -> Problems:
    """A problem for each of ``keys`` holding a number larger in magnitude than :data:`MAX_MAGNITUDE`."""
    return [
        (
            (key,),
            f"{key} = {data[key]!r} is larger in magnitude than {MAX_MAGNITUDE:.0e}, the most pdem accepts: "
            "the contact forces computed from it would overflow double precision",
        )
        for key in keys
        if _is_num(data.get(key)) and abs(data[key]) > MAX_MAGNITUDE
    ]


def _radius_rules(data: dict, keys: tuple[str, ...]) -> Problems:
    out: Problems = []
    for key in keys:
        value = data.get(key)
        if isinstance(value, list):
            bad = [((key, j), m) for j, v in enumerate(value) if (m := radius_problem(v)) is not None]
            out += bad[:5]  # the first few of a long table are enough
        elif (m := radius_problem(value, key)) is not None:
            out.append(((key,), m))
    return out


def _ctx(info: ValidationInfo | None) -> dict:
    ctx = getattr(info, "context", None)
    return ctx if isinstance(ctx, dict) else {}


def _as_init_error(err: dict) -> InitErrorDetails:
    """Rebuild one entry of ``ValidationError.errors()`` so that it can be raised again."""
    if err["type"] in _KNOWN_ERROR_TYPES:
        out = InitErrorDetails(type=err["type"], loc=err["loc"], input=err.get("input"))
        if "ctx" in err:
            out["ctx"] = err["ctx"]
        return out
    return InitErrorDetails(
        type=PydanticCustomError(err["type"], err["msg"]), loc=err["loc"], input=err.get("input")
    )


class _DeckModel(BaseModel):
    """Base of the deck models: unknown keys and non-finite numbers are errors; rules always run."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    @classmethod
    def rules(cls, data: dict, context: dict) -> Problems:
        """Checks across keys of the raw table ``data``: ``[(relative loc, message), ...]``."""
        return []

    @model_validator(mode="wrap")
    @classmethod
    def _run_rules(cls, data: Any, handler: Any, info: ValidationInfo) -> Any:
        problems: Problems = []
        if isinstance(data, dict):
            try:
                problems = cls.rules(data, _ctx(info))
            except Exception as exc:  # noqa: BLE001 - a rule must never hide the other problems
                problems = [
                    (
                        (),
                        f"internal error while checking this table ({type(exc).__name__}: {exc}); "
                        "please report it",
                    )
                ]
        extra = [
            InitErrorDetails(type=PydanticCustomError(RULE_ERROR, msg), loc=tuple(loc), input=data)
            for loc, msg in problems
        ]
        try:
            out = handler(data)
        except ValidationError as exc:
            if not extra:
                raise
            raise ValidationError.from_exception_data(
                cls.__name__, [_as_init_error(e) for e in exc.errors()] + extra
            ) from None
        if extra:
            raise ValidationError.from_exception_data(cls.__name__, extra)
        return out


# -------------------------------------------------------------------------------------------------
# [run], [contact], [materials], [[material_pairs]]
# -------------------------------------------------------------------------------------------------


class RunSection(_DeckModel):
    """``[run]``: time step, gravity, neighbour skin, blow-up threshold, random seed."""

    dt: Float | None = Field(
        None,
        gt=0,
        description="time step [s]; default: 0.2 of the contact law's stability estimate "
        "(for Hertz-Mindlin the Rayleigh time of the smallest particle)",
    )
    dt_fraction: Float | None = Field(
        None,
        gt=0,
        description="time step as a multiple of the contact law's stability estimate (e.g. 0.2; above 1 "
        "needs force_dt); instead of dt, for step sweeps that follow the material (not for laws without "
        "a stability limit, such as complementarity)",
    )
    force_dt: Bool = Field(
        False, description="allow a dt (here or in a stage) above the law's stability estimate"
    )
    stiffness_limit: Float = Field(
        STIFFNESS_LIMIT,
        ge=0,
        description="DEM-P: stop the run with an instability error when dt exceeds this multiple of the "
        "step the contact network bears, bounded at steps 1, 2, 4, …, 64 and every 100 steps from the "
        "contacts' stiffness, "
        "coordination and friction (docs/deck.md, 'Live step bound'); 0: never stop (the bound is still "
        "recorded in summary.json and a step above it is warned of)",
    )
    gravity: Vec3 = Field(
        (0.0, 0.0, 0.0),
        description="gravitational acceleration (x, y, z) [m/s²]; none unless given (as in Simulation())",
    )
    skin: Float | None = Field(
        None, ge=0, description="Verlet-list skin [m]; default: chosen at every rebuild from the fastest "
        "grain, 0.1-0.4 of the mean particle diameter (DEM-C, periodic boxes: 0.1 of it)"
    )
    max_overlap: Float = Field(
        0.25,
        gt=0,
        lt=1,
        description="overlap, as a fraction of the smaller radius, that counts as a blow-up (the run "
        "stops with an instability error)",
    )
    seed: Int = Field(0, ge=0, description="seed of the random number generator used by random sources")
    decomposition: tuple[Count, Count, Count] | None = Field(
        None,
        description="MPI grid of subdomains (nx, ny, nz), each >= 1, whose product is the number of ranks "
        "(checked when the run starts; `pdem check` cannot know the rank count); default: "
        "chosen from the rank count to minimise the cut area over the particles",
    )
    max_particles: Int | None = Field(
        None,
        ge=1,
        le=2**31 - 1,
        description="most particles the deck's sources may create together (estimated when the deck is "
        "validated, at about 1 kB of memory per particle); default: the validating host's memory / 1 kB, "
        "at most 2^31 - 1 (particle ids)",
    )
    balance_threshold: Float | None = Field(
        1.05,
        gt=1,
        description="under MPI, move the cut planes when the slowest rank's force time exceeds the mean "
        "by this factor (measured between neighbour-list rebuilds); omit or set null to never rebalance",
    )

    @classmethod
    def rules(cls, data: dict, context: dict) -> Problems:
        if _given(data, "dt") and _given(data, "dt_fraction"):
            return [
                (
                    ("dt_fraction",),
                    f"dt_fraction = {data['dt_fraction']!r} and dt = {data['dt']!r} are both given; "
                    "give one: dt (seconds) or dt_fraction (a multiple of the law's stability estimate)",
                )
            ]
        return []


_AXIS_NAMES = ("x", "y", "z")


class DomainSection(_DeckModel):
    """``[domain]``: periodic boundaries.

    Along each axis named in ``periodic`` the box ``lo <= x < hi`` wraps around: a particle leaving
    through one face comes back through the other, and particles near a face interact with the
    images of those near the opposite face. The components of ``lo``/``hi`` along the other axes are
    not used.
    """

    periodic: list[Literal["x", "y", "z"]] = Field(
        default_factory=list,
        description="periodic axes, e.g. ['x', 'y']; default none. Each periodic length hi - lo must be "
        "at least twice the largest pair cutoff 2 r_max + skin",
    )
    lo: Vec3 | None = Field(
        None, description="low corner of the periodic box (x, y, z) [m]; required with periodic axes"
    )
    hi: Vec3 | None = Field(
        None,
        description="high corner of the periodic box (x, y, z) [m]; above lo along every periodic axis; "
        "required with periodic axes",
    )

    @classmethod
    def rules(cls, data: dict, context: dict) -> Problems:
        out: Problems = []
        axes = data.get("periodic")
        names = [a for a in axes if isinstance(a, str)] if isinstance(axes, list) else []
        dup = _repeated(names)
        if dup:
            out.append((("periodic",), f"axis {_listing(dup)} listed more than once"))
        if names:
            for key in ("lo", "hi"):
                if not _given(data, key):
                    out.append(
                        (
                            (key,),
                            f"periodic = {names} needs the box corners lo and hi (three numbers each, "
                            "metres); give domain.lo and domain.hi",
                        )
                    )
        elif isinstance(axes, list) or axes is None:
            extra = [k for k in ("lo", "hi") if _given(data, k)]
            if extra:
                out.append(
                    (
                        (extra[0],),
                        f"domain.{extra[0]} is only used with periodic axes; add periodic = ['x', …] "
                        f"or remove {' and '.join('domain.' + k for k in extra)}",
                    )
                )
        lo, hi = data.get("lo"), data.get("hi")
        if names and _is_vec3(lo) and _is_vec3(hi):
            bad = [a for a in _AXIS_NAMES if a in names and hi["xyz".index(a)] <= lo["xyz".index(a)]]
            if bad:
                out.append(
                    (
                        ("hi",),
                        f"hi = {list(hi)} must exceed lo = {list(lo)} along the periodic axis "
                        f"{', '.join(bad)}",
                    )
                )
        return out

    def box(self):
        """The :class:`pdem.domain.PeriodicBox`, or None without periodic axes."""
        if not self.periodic:
            return None
        from ..domain import PeriodicBox

        return PeriodicBox(self.lo, self.hi, self.periodic)


class ContactSection(_DeckModel):
    """``[contact]``: the contact law and its parameters.

    Every key other than ``law`` is a parameter of the law, validated by the law class's ``Params``
    model in the second pass (so this model accepts extra keys).
    """

    model_config = ConfigDict(extra="allow", allow_inf_nan=False)
    law: Str = Field(
        "hertz_mindlin",
        description="contact law: an entry point of group pdem.contact_laws (see `pdem plugins`); the "
        "other keys of [contact] are that law's parameters",
    )


_MAT_DEFAULTS = {f.name: f.default for f in dataclasses.fields(Material) if f.name != "name"}
#: the contact values of a material that a pair or a stage may override
CONTACT_VALUES = ("restitution", "friction", "rolling_friction", "spinning_friction")


class MaterialSpec(_DeckModel):
    """``[materials.NAME]``: the keys of :class:`pdem.materials.Material` (defaults from it)."""

    density: Float = Field(_MAT_DEFAULTS["density"], gt=0, description="density ρ [kg/m³]")
    youngs_modulus: Float = Field(_MAT_DEFAULTS["youngs_modulus"], gt=0, description="Young's modulus E [Pa]")
    poisson_ratio: Float = Field(
        _MAT_DEFAULTS["poisson_ratio"], gt=-1, lt=0.5, description="Poisson ratio ν [-], in (-1, 0.5)"
    )
    restitution: Float = Field(
        _MAT_DEFAULTS["restitution"], ge=0, le=1, description="coefficient of restitution e [-], in [0, 1]"
    )
    friction: Float = Field(_MAT_DEFAULTS["friction"], ge=0, description="sliding friction coefficient μ [-]")
    rolling_friction: Float = Field(
        _MAT_DEFAULTS["rolling_friction"],
        ge=0,
        description="rolling friction coefficient μ_r [-] (multiplies R* F_n; 0 disables rolling resistance)",
    )
    spinning_friction: Float = Field(
        _MAT_DEFAULTS["spinning_friction"],
        ge=0,
        description="spinning friction coefficient μ_s [-]: the torque about the contact normal is "
        "bounded by μ_s R* F_n (0 disables spinning resistance)",
    )
    rigid: bool = Field(
        False,
        description="a rigid wall material (walls only): infinite stiffness, so a contact's E* is the "
        "grain's alone; give no density, youngs_modulus or poisson_ratio; restitution, friction, "
        "rolling_friction and spinning_friction, when given, are the wall's own (not mixed), else the "
        "grain's apply",
    )

    @classmethod
    def rules(cls, data: dict, context: dict) -> Problems:
        out = _magnitude_rules(data, ("youngs_modulus", *CONTACT_VALUES))
        if data.get("rigid") is True:
            return out + [
                ((k,), f"a rigid material has no {k}; remove it (E* comes from the grain alone)")
                for k in ("density", "youngs_modulus", "poisson_ratio")
                if _given(data, k)
            ]
        rho = data.get("density")
        lo, hi = DENSITY_RANGE
        if _is_num(rho) and rho > 0 and not lo <= rho <= hi:
            out += [
                (
                    ("density",),
                    f"density {rho!r} kg/m³ is outside [{lo:.0e}, {hi:.0e}] kg/m³, the densities pdem "
                    "accepts (aerogel is about 1, osmium 22,590): the grains' masses would leave double "
                    "precision; give the density in kg/m³",
                )
            ]
        return out

    @model_serializer(mode="wrap")
    def _dump(self, handler):
        out = handler(self)
        if self.rigid:  # unset keys stay unset: "the grain's value", also after a resume
            return {k: v for k, v in out.items() if k == "rigid" or k in self.model_fields_set}
        return out

    def to_material(self, name: str) -> Material:
        """The :class:`pdem.materials.Material` called ``name``."""
        if self.rigid:
            own = {k: getattr(self, k) for k in CONTACT_VALUES if k in self.model_fields_set}
            return Material.rigid_wall(name, **own)
        return Material(name=name, **self.model_dump())


class _ContactValues(_DeckModel):
    """Optional restitution / friction / rolling / spinning friction, at least one given (a material
    pair's, or a material's during one stage)."""

    @classmethod
    def rules(cls, data: dict, context: dict) -> Problems:
        if not any(_given(data, k) for k in CONTACT_VALUES):
            return [((), f"give at least one of {', '.join(CONTACT_VALUES)}")]
        return _magnitude_rules(data, CONTACT_VALUES)

    def values(self) -> dict[str, float]:
        """The values that are set."""
        return {k: v for k in CONTACT_VALUES if (v := getattr(self, k)) is not None}


class MaterialPair(_ContactValues):
    """``[[material_pairs]]``: explicit values for one pair of materials (default: the minimum)."""

    materials: tuple[Str, Str] = Field(
        description="the two material names (the same name twice for a self-pair)"
    )
    restitution: Float | None = Field(None, ge=0, le=1, description="restitution of the pair [-], in [0, 1]")
    friction: Float | None = Field(None, ge=0, description="sliding friction of the pair [-]")
    rolling_friction: Float | None = Field(None, ge=0, description="rolling friction of the pair [-]")
    spinning_friction: Float | None = Field(None, ge=0, description="spinning friction of the pair [-]")


# -------------------------------------------------------------------------------------------------
# regions and size distributions
# -------------------------------------------------------------------------------------------------


class BoxRegionSpec(_DeckModel):
    """Axis-aligned box ``lo <= x <= hi``."""

    type: Literal["box"] = Field(description="region kind")
    lo: Vec3 = Field(description="low corner (x, y, z) [m]")
    hi: Vec3 = Field(description="high corner (x, y, z) [m]; every component above lo's")

    @classmethod
    def rules(cls, data: dict, context: dict) -> Problems:
        lo, hi = data.get("lo"), data.get("hi")
        if _is_vec3(lo) and _is_vec3(hi):
            bad = [a for a, lo_c, hi_c in zip("xyz", lo, hi, strict=True) if hi_c <= lo_c]
            if bad:
                return [(("hi",), f"hi = {list(hi)} must exceed lo = {list(lo)} along {', '.join(bad)}")]
        return []

    def build(self):
        """The :class:`pdem.sources.BoxRegion`."""
        from ..sources import BoxRegion

        return BoxRegion(self.lo, self.hi)


class CylinderRegionSpec(_DeckModel):
    """Upright circular cylinder, axis +z from ``base_center``."""

    type: Literal["cylinder"] = Field(description="region kind")
    base_center: Vec3 = Field(description="centre of the bottom face (x, y, z) [m]")
    radius: Float = Field(gt=0, description="radius [m]")
    height: Float = Field(gt=0, description="height along +z [m]")

    def build(self):
        """The :class:`pdem.sources.CylinderRegion`."""
        from ..sources import CylinderRegion

        return CylinderRegion(self.base_center, self.radius, self.height)


RegionSpec = Annotated[BoxRegionSpec | CylinderRegionSpec, Field(discriminator="type")]


class SingleSizes(_DeckModel):
    """Monodisperse: every sphere has ``radius``."""

    type: Literal["single"] = Field(description="distribution kind")
    radius: Float = Field(gt=0, description="sphere radius [m]")

    @classmethod
    def rules(cls, data: dict, context: dict) -> Problems:
        return _radius_rules(data, ("radius",))

    def build(self):
        from ..sources import Single

        return Single(self.radius)


class UniformSizes(_DeckModel):
    """Radius uniform in [r_min, r_max]."""

    type: Literal["uniform"] = Field(description="distribution kind")
    r_min: Float = Field(gt=0, description="smallest radius [m]")
    r_max: Float = Field(gt=0, description="largest radius [m], >= r_min")

    @classmethod
    def rules(cls, data: dict, context: dict) -> Problems:
        lo, hi = data.get("r_min"), data.get("r_max")
        if _is_num(lo) and _is_num(hi) and lo > hi:
            return [(("r_max",), f"r_max = {hi} is smaller than r_min = {lo}; give r_min <= r_max")]
        return _radius_rules(data, ("r_min", "r_max"))

    def build(self):
        from ..sources import Uniform

        return Uniform(self.r_min, self.r_max)


class NormalSizes(_DeckModel):
    """Normal radius distribution truncated to [r_min, r_max] (defaults mean ∓ 3 std)."""

    type: Literal["normal"] = Field(description="distribution kind")
    mean: Float = Field(gt=0, description="mean radius of the untruncated normal [m]")
    std: Float = Field(ge=0, description="standard deviation of the radius [m]")
    r_min: Float | None = Field(
        None, gt=0, description="smallest radius [m]; default mean − 3 std (must be > 0)"
    )
    r_max: Float | None = Field(None, gt=0, description="largest radius [m]; default mean + 3 std")

    @classmethod
    def rules(cls, data: dict, context: dict) -> Problems:
        keys = ("mean", "std", "r_min", "r_max")
        vals = {k: data.get(k) for k in keys}
        out = _radius_rules(data, ("mean", "r_min", "r_max"))
        if out:
            return out
        if not (_is_num(vals["mean"]) and _is_num(vals["std"]) and vals["mean"] > 0 and vals["std"] >= 0):
            return []
        if any(v is not None and not (_is_num(v) and v > 0) for v in (vals["r_min"], vals["r_max"])):
            return []
        from ..sources import Normal

        try:
            Normal(**vals)
        except PdemError as exc:
            return [((), str(exc).removeprefix("Normal: "))]
        return []

    def build(self):
        from ..sources import Normal

        return Normal(self.mean, self.std, self.r_min, self.r_max)


class TableSizes(_DeckModel):
    """Discrete radii with given mass fractions (summing to 1)."""

    type: Literal["table"] = Field(description="distribution kind")
    radii: list[Annotated[Float, Field(gt=0)]] = Field(min_length=1, description="radii [m], each > 0")
    mass_fractions: list[Annotated[Float, Field(ge=0)]] = Field(
        min_length=1, description="mass fraction of each radius [-], each >= 0, summing to 1"
    )

    @classmethod
    def rules(cls, data: dict, context: dict) -> Problems:
        radii, fracs = data.get("radii"), data.get("mass_fractions")
        out = _radius_rules(data, ("radii",))
        if out:
            return out
        if not (isinstance(radii, list) and isinstance(fracs, list) and radii and fracs):
            return []
        if not all(_is_num(v) and v > 0 for v in radii) or not all(_is_num(v) and v >= 0 for v in fracs):
            return []
        if len(radii) != len(fracs):
            return [
                (
                    ("mass_fractions",),
                    f"{len(radii)} radii but {len(fracs)} mass_fractions; give one mass fraction per radius",
                )
            ]
        total = math.fsum(fracs)
        if abs(total - 1.0) > 1e-6:
            return [
                (
                    ("mass_fractions",),
                    f"mass_fractions sum to {total!r}, not 1 (tolerance 1e-6); normalise them",
                )
            ]
        return []

    def build(self):
        from ..sources import Table

        return Table(self.radii, self.mass_fractions)


SizeSpec = Annotated[SingleSizes | UniformSizes | NormalSizes | TableSizes, Field(discriminator="type")]
_REGION_MODELS = {"box": BoxRegionSpec, "cylinder": CylinderRegionSpec}
_SIZE_MODELS = {"single": SingleSizes, "uniform": UniformSizes, "normal": NormalSizes, "table": TableSizes}


def _try_build(models: dict[str, type[_DeckModel]], raw: Any):
    """The runtime object of a raw region/sizes table, or None if the table is not valid."""
    if not isinstance(raw, dict) or not isinstance(raw.get("type"), str) or raw["type"] not in models:
        return None
    try:
        return models[raw["type"]].model_validate(raw, strict=False).build()
    except (ValidationError, PdemError, TypeError, ValueError):
        return None


def _fit_problem(region_raw: Any, largest: float, what: str, key: str) -> Problems:
    """A problem if a sphere of radius ``largest`` cannot fit in the region."""
    region = _try_build(_REGION_MODELS, region_raw)
    if region is None:
        return []
    room = region.max_sphere_radius()
    if largest > room:
        return [
            (
                (key,),
                f"{what} {largest!r} m does not fit in the region (largest radius that fits: "
                f"{room!r} m); use a larger region or smaller spheres",
            )
        ]
    return []


# -------------------------------------------------------------------------------------------------
# [[particles]]
# -------------------------------------------------------------------------------------------------


class ParticleEntry(_DeckModel):
    """``[[particles]]``: one particle source; ``source`` names the plugin, the other keys are its
    parameters (validated by the plugin's ``Params`` model)."""

    model_config = ConfigDict(extra="allow", allow_inf_nan=False)
    source: Str = Field(
        description="particle source: 'random_fill', 'lattice', 'file', 'pluviate' or another installed "
        "entry point of group pdem.sources (see `pdem plugins`); the other keys are its parameters"
    )


# -------------------------------------------------------------------------------------------------
# [boundaries.NAME]
# -------------------------------------------------------------------------------------------------


class BoundaryEntry(_DeckModel):
    """``[boundaries.NAME]``: ``type`` names the plugin; the other keys are its ``Params``."""

    model_config = ConfigDict(extra="allow", allow_inf_nan=False)
    type: Str = Field(
        description="boundary plugin: an entry point of group pdem.boundaries (see `pdem plugins`)"
    )


# -------------------------------------------------------------------------------------------------
# [[stages]] and [output]
# -------------------------------------------------------------------------------------------------

_END_CONDITIONS = ("time", "steps", "kinetic_energy_below", "quantity")


class StageEnd(_DeckModel):
    """``[stages.end]``: the stage ends as soon as ANY condition holds."""

    time: Float | None = Field(None, gt=0, description="stage duration [s]")
    steps: Int | None = Field(None, gt=0, description="number of steps")
    kinetic_energy_below: Float | None = Field(
        None,
        gt=0,
        description="end when the total kinetic energy falls below this [J] (checked every "
        "check_every steps)",
    )
    quantity: Str | None = Field(
        None,
        description="a measured quantity '<boundary>.<key>' (e.g. 'cone.discharged_mass'), compared "
        "with above / below every check_every steps",
    )
    above: Float | None = Field(None, description="end when quantity > above (exactly one of above, below)")
    below: Float | None = Field(None, description="end when quantity < below (exactly one of above, below)")
    max_time: Float | None = Field(
        None, gt=0, description="safety cap [s]: reaching it before another condition holds is an error"
    )
    check_every: Int = Field(
        100, gt=0, description="steps between checks of kinetic_energy_below and quantity"
    )

    @classmethod
    def rules(cls, data: dict, context: dict) -> Problems:
        out: Problems = []
        if not any(_given(data, k) for k in _END_CONDITIONS):
            extra = " (max_time is a safety cap, not an end condition)" if _given(data, "max_time") else ""
            out.append(((), f"a stage needs at least one end condition: {', '.join(_END_CONDITIONS)}{extra}"))
        q, above, below = _given(data, "quantity"), _given(data, "above"), _given(data, "below")
        if q and above == below:
            out.append(
                (
                    ("quantity",),
                    "give exactly one of above / below with quantity; "
                    + ("both given" if above else "neither given"),
                )
            )
        if not q:
            out += [
                ((k,), f"{k} needs quantity = '<boundary>.<key>'")
                for k in ("above", "below")
                if _given(data, k)
            ]
        t, cap = data.get("time"), data.get("max_time")
        others = [k for k in ("steps", "kinetic_energy_below", "quantity") if _given(data, k)]
        if _is_num(t) and _is_num(cap) and t > 0 and cap > 0 and cap <= t and not others:
            out.append(
                (
                    ("max_time",),
                    f"max_time = {cap!r} s is not above time = {t!r} s, the stage's only end condition: the "
                    "stage would always stop with the max_time error before it ends; drop max_time or make "
                    "it larger than time",
                )
            )
        quantity = data.get("quantity")
        if isinstance(quantity, str):
            head, _, tail = quantity.partition(".")
            if not head or not tail:
                out.append(
                    (
                        ("quantity",),
                        f"quantity = '{quantity}' must have the form '<boundary>.<key>', "
                        "e.g. 'cone.discharged_mass'",
                    )
                )
        return out


class OutputCadence(_DeckModel):
    """``[stages.output]``: per-stage override of the output cadence (unset keys follow [output])."""

    every_time: Float | None = Field(None, gt=0, description="snapshot interval [s]")
    every_steps: Int | None = Field(None, gt=0, description="snapshot interval [steps]")
    series_every_steps: Int | None = Field(None, gt=0, description="time-series interval [steps]")
    series_every_time: Float | None = Field(None, gt=0, description="time-series interval [s]")
    checkpoint_every_steps: Int | None = Field(None, gt=0, description="checkpoint interval [steps]")

    @classmethod
    def rules(cls, data: dict, context: dict) -> Problems:
        return _cadence_rules(data)


def _cadence_rules(data: dict) -> Problems:
    """At most one of each pair of cadences, by time or by steps ([output] and [stages.output])."""
    return [
        ((by_time,), f"give at most one of {by_time} [s] and {by_steps}; both given")
        for by_time, by_steps in (("every_time", "every_steps"), ("series_every_time", "series_every_steps"))
        if _given(data, by_time) and _given(data, by_steps)
    ]


class StageMaterial(_ContactValues):
    """``[stages.materials.NAME]``: a material's contact properties during one stage only."""

    restitution: Float | None = Field(None, ge=0, le=1, description="restitution e during this stage [-]")
    friction: Float | None = Field(None, ge=0, description="sliding friction μ during this stage [-]")
    rolling_friction: Float | None = Field(
        None, ge=0, description="rolling friction μ_r during this stage [-]"
    )
    spinning_friction: Float | None = Field(
        None, ge=0, description="spinning friction μ_s during this stage [-]"
    )


class Stage(_DeckModel):
    """``[[stages]]``: one phase of the run, run in deck order."""

    name: Str = Field(
        pattern=NAME_PATTERN,
        description=f"unique name: a letter or '_' first, then letters, digits, '_' or '-'; at most "
        f"{MAX_NAME_LENGTH} characters (it is part of output file names)",
        json_schema_extra={"maxLength": MAX_NAME_LENGTH},  # checked by a rule, with its reason
    )
    dt: Float | None = Field(None, gt=0, description="time step of this stage [s]; default run.dt")
    end: StageEnd = Field(description="end conditions (table [stages.end]); the stage ends when ANY holds")
    output: OutputCadence | None = Field(
        None, description="per-stage override of the output cadence keys (table [stages.output])"
    )
    materials: dict[Str, StageMaterial] = Field(
        {},
        description="contact properties of materials during this stage only (tables "
        "[stages.materials.NAME]: friction, restitution, rolling_friction, spinning_friction), e.g. "
        "frictionless grains "
        "while a dense sample is prepared; the other stages use [materials]",
    )
    contact: dict[Str, Any] = Field(
        {},
        description="the contact law's solver settings during this stage only (table [stages.contact]; "
        "a [stages.contact.<law>] table applies only when contact.law is that law, like "
        "[contact.<law>]): the keys a resume may change, e.g. DEM-C's max_iterations, tolerance, "
        "solver, check_every; the other stages use [contact]",
    )


#: most points a continuum grid may have: its sums take 43 doubles a point on every rank (344 bytes)
MAX_CONTINUUM_POINTS = 4_000_000
#: the quantities a continuum grid may write (pdem.io.continuum.QUANTITIES)
CONTINUUM_QUANTITIES: tuple[str, ...] = (
    "density", "solid_fraction", "number_density", "momentum", "velocity", "kinetic_stress",
    "contact_stress", "stress", "velocity_gradient", "strain_rate", "contact_density", "coordination",
    "fabric", "wall_force_density",
)  # fmt: skip


class ContinuumSpec(_DeckModel):
    """``[output.continuum.<name>]``: coarse-grained fields on a grid (a box's regular grid, a
    cylindrical grid about an upright axis, or a list of points), written beside the grains
    (continuum_<name>.h5 and continuum_<name>.xdmf; docs/fields.md)."""

    type: Literal["box", "cylinder", "points"] = Field(
        "box", description="where the fields are: 'box' (a regular grid, keys lo, hi, counts), 'cylinder' "
        "(a grid in r, θ, z about an upright axis, keys base_center, radius, height, counts, "
        "inner_radius) or 'points' (key points)"
    )
    lo: Vec3 | None = Field(None, description="box: low corner of the grid's box (x, y, z) [m]")
    hi: Vec3 | None = Field(
        None, description="box: high corner of the grid's box (x, y, z) [m]; every component above lo's"
    )
    counts: list[Int] | None = Field(
        None, description="box: cells along x, y and z; cylinder: along r, θ and z (three positive "
        "integers); the fields are at the cells' centres"
    )
    base_center: Vec3 | None = Field(
        None, description="cylinder: centre of the bottom face (x, y, z) [m]; the axis is +z from it"
    )
    radius: Float | None = Field(None, gt=0, description="cylinder: outer radius [m]")
    height: Float | None = Field(None, gt=0, description="cylinder: height [m]")
    inner_radius: Float | None = Field(
        None, ge=0, description="cylinder: inner radius [m]; default 0 (a full disc)"
    )
    points: list[Vec3] | None = Field(
        None, description="points: the points (x, y, z) [m] where the fields are written, e.g. probes "
        "along a line"
    )
    kernel: Literal["gaussian", "lucy"] = Field(
        "gaussian", description="coarse-graining kernel: 'gaussian' (width = its standard deviation) or "
        "'lucy' (width = its cut-off radius)"
    )
    width: Float | None = Field(
        None, gt=0, description="kernel width [m]; default one mean grain diameter (at the first frame)"
    )
    cutoff: Float = Field(3.0, ge=1, le=10, description="the Gaussian's cut-off, in widths")
    quantities: list[Literal[CONTINUUM_QUANTITIES]] | None = Field(  # type: ignore[valid-type]
        None, description="fields to write: any of " + ", ".join(CONTINUUM_QUANTITIES) + "; default all"
    )
    walls: Bool = Field(True, description="include the wall contacts (stress, fabric, wall force density)")
    every_steps: Int | None = Field(
        None, gt=0, description="write interval [steps]; default: with every particle snapshot"
    )
    average_every_steps: Int | None = Field(
        None, gt=0, description="time average: sample every this many steps and write the mean of the "
        "samples since the previous frame; default: no average (each frame one instant)"
    )

    @classmethod
    def rules(cls, data: dict, context: dict) -> Problems:
        out: Problems = []
        kind = data.get("type", "box")
        keys = {"box": ("lo", "hi", "counts"), "cylinder": ("base_center", "radius", "height", "counts"),
                "points": ("points",)}  # fmt: skip
        if kind not in keys:
            return out  # the type's own error says which types there are
        others = {"lo", "hi", "base_center", "radius", "height", "inner_radius", "points", "counts"}
        for key in keys[kind]:
            if data.get(key) is None:
                need = ", ".join(keys[kind])
                out.append(((key,), f"a {kind} grid needs {key} (type = {_q(kind)}: keys {need})"))
        for key in sorted(others - set(keys[kind]) - ({"inner_radius"} if kind == "cylinder" else set())):
            if data.get(key) is not None:
                out.append(
                    ((key,), f"{key} is not a key of a {kind} grid (type = {_q(kind)}: keys "
                     f"{', '.join(keys[kind])}{', inner_radius' if kind == 'cylinder' else ''})")
                )  # fmt: skip
        side = None  # the grid's largest extent [m]
        lo, hi = data.get("lo"), data.get("hi")
        if kind == "box" and _is_vec3(lo) and _is_vec3(hi):
            bad = [a for a, lo_c, hi_c in zip("xyz", lo, hi, strict=True) if hi_c <= lo_c]
            if bad:
                out.append((("hi",), f"hi = {list(hi)} must exceed lo = {list(lo)} along {', '.join(bad)}"))
            side = max(h - low for low, h in zip(lo, hi, strict=True))
        radius, inner = data.get("radius"), data.get("inner_radius") or 0.0
        if kind == "cylinder" and _is_num(radius) and _is_num(inner) and radius > 0:
            if inner >= radius:
                out.append(
                    (("inner_radius",), f"inner_radius = {inner!r} m must be below radius = {radius!r} m")
                )
            height = data.get("height")
            side = max(2.0 * radius, height) if _is_num(height) else 2.0 * radius
        pts = data.get("points")
        n_points = None
        if kind == "points" and isinstance(pts, list):
            n_points = len(pts)
            if not pts:
                out.append((("points",), "points is empty; give at least one point [x, y, z]"))
            elif all(_is_vec3(v) for v in pts):
                arr = [[float(c) for c in v] for v in pts]
                side = max(max(v[a] for v in arr) - min(v[a] for v in arr) for a in range(3))
        width = data.get("width")
        if side is not None and isinstance(width, float) and width > 0:
            reach = width * (data.get("cutoff", 3.0) if data.get("kernel", "gaussian") == "gaussian" else 1.0)
            if side > 0 and reach > 10 * side:
                out.append(
                    (
                        ("width",),
                        f"width = {width!r} m reaches {reach:.3g} m, more than 10 times the grid's largest "
                        f"side ({side:.3g} m): every node would average the same grains, at a cost of "
                        "every node times every grain; give a width of about a grain diameter",
                    )
                )
        counts = data.get("counts")
        axes = "(nr, nθ, nz)" if kind == "cylinder" else "(nx, ny, nz)"
        if kind != "points" and isinstance(counts, list) and all(
            isinstance(c, int) and not isinstance(c, bool) for c in counts
        ):
            if len(counts) != 3 or min(counts, default=0) < 1:
                out.append((("counts",), f"counts = {counts} must be three positive integers {axes}"))
            else:
                n_points = math.prod(counts)
        if n_points is not None and n_points > MAX_CONTINUUM_POINTS:
            key = "points" if kind == "points" else "counts"
            what = f"{n_points:,} points" if kind == "points" else (
                f"counts = {counts} make {n_points:,} points"
            )
            out.append(
                (
                    (key,),
                    f"{what}, more than the {MAX_CONTINUUM_POINTS:,} a grid may "
                    "have (its sums take 344 bytes a point on every rank); use fewer points or several "
                    "smaller grids",
                )
            )
        q = data.get("quantities")
        if isinstance(q, list):
            dup = _repeated([v for v in q if isinstance(v, str)])
            if dup:
                out.append((("quantities",), f"quantities listed more than once: {_listing(dup)}"))
            if not q:
                out.append((("quantities",), "quantities is empty; list some or leave it out (all)"))
        return out


class OutputSection(_DeckModel):
    """``[output]``: where and how often to write."""

    directory: Str | None = Field(
        None,
        description="output directory, relative to the current directory; default 'out/<deck file stem>'",
    )
    formats: list[Str] = Field(
        ["hdf5"], description="snapshot writers (entry points of group pdem.writers): 'hdf5', 'vtk'"
    )
    every_time: Float | None = Field(
        None, gt=0, description="snapshot interval [s] (at most one of every_time, every_steps)"
    )
    every_steps: Int | None = Field(
        None, gt=0, description="snapshot interval [steps]; default 1000 when every_time is not given"
    )
    fields: list[Literal["x", "v", "w", "r", "material", "f", "contacts", "id"]] = Field(
        list(OUTPUT_FIELDS),
        description="per-particle fields in snapshots: x (position), v (velocity), w (angular velocity), "
        "r (radius), material, f (force), contacts (contact count), id; default all",
    )
    series_every_steps: Int | None = Field(
        None, gt=0, description="time-series interval [steps] (one CSV per stage); default 100 when "
        "series_every_time is not given"
    )
    series_every_time: Float | None = Field(
        None, gt=0, description="time-series interval [s]: a row after each step that crosses a multiple "
        "of it, counted from the stage's start (the same sampling in time at any step, e.g. DEM-P's and "
        "DEM-C's); at most one of series_every_time, series_every_steps"
    )
    checkpoint_every_steps: Int | None = Field(
        None, gt=0, description="periodic checkpoint interval [steps]; default: no periodic checkpoints"
    )
    contacts: Bool = Field(
        False,
        description="also write the contact network at every snapshot: contacts/contacts_NNNNNN.vtu (one "
        "line per touching pair with its force, normal force and overlap) and contacts.pvd for ParaView",
    )
    thermo_every: Int | None = Field(
        None,
        gt=0,
        description="print a thermo line on stdout every this many steps (a header line first, as LAMMPS "
        "does); default: none",
    )
    thermo: list[Str] | None = Field(
        None,
        description="thermo columns: any of " + ", ".join(THERMO_KEYS) + ", or a measured quantity "
        "'<boundary>.<key>' (e.g. 'floor.fz', 'hopper.discharged_mass'); default: "
        + ", ".join(THERMO_DEFAULT),
    )
    continuum: dict[Str, ContinuumSpec] = Field(
        {},
        description="coarse-grained fields (density, velocity, stress, strain rate, fabric, …) on regular "
        "grids, one table [output.continuum.<name>] per grid, written beside the particle snapshots "
        "(continuum_<name>.h5 + .xdmf; docs/fields.md)",
    )
    parallel: Literal["auto", "gather", "per_rank"] = Field(
        "auto",
        description="how MPI runs write snapshots: 'gather' (rank 0 writes every particle), 'per_rank' "
        "(each rank writes its own file, rank 0 an index joining them: XDMF / PVTU), 'auto' (per_rank "
        "on more than one rank, so that no rank holds every particle; one file serially)",
    )

    #: snapshot cadence when neither every_time nor every_steps is given
    DEFAULT_EVERY_STEPS: ClassVar[int] = 1000
    #: time-series cadence when neither series_every_time nor series_every_steps is given
    DEFAULT_SERIES_EVERY_STEPS: ClassVar[int] = 100
    def parallel_mode(self, n_particles: int, n_ranks: int) -> str:
        """``"gather"`` or ``"per_rank"``: what ``parallel`` means for a run of ``n_particles`` on
        ``n_ranks`` ranks (``auto``: per rank on more than one rank, whatever the count, so that no
        rank ever holds every particle for a snapshot)."""
        if self.parallel == "auto":
            return "per_rank" if n_ranks > 1 else "gather"
        return self.parallel

    @classmethod
    def rules(cls, data: dict, context: dict) -> Problems:
        out = _cadence_rules(data)
        allowed = tuple(context.get("writers") or KNOWN_WRITERS)
        formats = data.get("formats")
        if isinstance(formats, list):
            seen: set[str] = set()
            for k, fmt in enumerate(formats):
                if isinstance(fmt, str) and fmt not in allowed:
                    hint = did_you_mean(fmt, allowed, True)
                    out.append(
                        (
                            ("formats", k),
                            f"unknown output format {_q(fmt)}{hint}; "
                            f"available writers: {_listing(sorted(allowed))}",
                        )
                    )
                elif isinstance(fmt, str) and fmt in seen:
                    out.append((("formats", k), f"format {_q(fmt)} is listed twice"))
                if isinstance(fmt, str):
                    seen.add(fmt)
        grids = data.get("continuum")
        for name in grids if isinstance(grids, dict) else ():
            if not _NAME_RE.match(name) or len(name) > MAX_NAME_LENGTH:
                out.append(
                    (
                        ("continuum", name),
                        f"continuum grid name {_q(name)} must be a letter or '_' then letters, digits, '_' "
                        f"or '-', at most {MAX_NAME_LENGTH} characters: it names the files "
                        "continuum_<name>.h5 and .xdmf",
                    )
                )
        fields = data.get("fields")
        if isinstance(fields, list):
            dup = _repeated([f for f in fields if isinstance(f, str)])
            if dup:
                out.append((("fields",), f"field(s) listed more than once: {_listing(dup)}"))
        thermo = data.get("thermo")
        if isinstance(thermo, list):
            if len(thermo) > MAX_THERMO_COLUMNS:
                out.append(
                    (
                        ("thermo",),
                        f"{len(thermo):,} thermo columns, more than the {MAX_THERMO_COLUMNS} a thermo line "
                        "may have; keep the ones to watch (summary.json and the series CSVs hold the rest)",
                    )
                )
            else:
                dup = _repeated([c for c in thermo if isinstance(c, str)])
                if dup:
                    out.append((("thermo",), f"column(s) listed more than once: {_listing(dup)}"))
                for k, key in enumerate(thermo):
                    if isinstance(key, str) and key not in THERMO_KEYS and "." not in key:
                        out.append(
                            (
                                ("thermo", k),
                                f"unknown thermo column {_q(key)}{did_you_mean(key, THERMO_KEYS, True)}; "
                                f"give one of {_listing(list(THERMO_KEYS))} or a measured quantity "
                                "'<boundary>.<key>'",
                            )
                        )
            if not _given(data, "thermo_every"):
                out.append((("thermo",), "thermo lists the columns of thermo lines; give thermo_every too"))
        return out

    @model_validator(mode="after")
    def _default_cadence(self) -> OutputSection:
        if self.every_time is None and self.every_steps is None:
            self.every_steps = self.DEFAULT_EVERY_STEPS
        if self.series_every_time is None and self.series_every_steps is None:
            self.series_every_steps = self.DEFAULT_SERIES_EVERY_STEPS
        return self

    def merged(self, override: OutputCadence | None) -> OutputSection:
        """This section with a stage's cadence override applied (every_time / every_steps replace
        each other)."""
        if override is None:
            return self.model_copy()
        update = {k: v for k, v in override.model_dump().items() if v is not None}
        if "every_time" in update:
            update["every_steps"] = None
        elif "every_steps" in update:
            update["every_time"] = None
        if "series_every_time" in update:
            update["series_every_steps"] = None
        elif "series_every_steps" in update:
            update["series_every_time"] = None
        return self.model_copy(update=update)


# -------------------------------------------------------------------------------------------------
# the deck
# -------------------------------------------------------------------------------------------------


def _material_keys(table: dict) -> list[str]:
    """Keys of a plugin table that name a material: ``material`` and ``*_material``."""
    return [k for k in table if k == "material" or k.endswith("_material")]


def _stage_keys(table: dict) -> list[str]:
    """Keys of a plugin table that name stages: ``stage``, ``stages``, ``*_stage`` and ``*_stages``."""
    return [k for k in table if k in ("stage", "stages") or k.endswith(("_stage", "_stages"))]


class Deck(_DeckModel):
    """A pdem deck: the root of the TOML file."""

    title: Str | None = Field(
        None,
        max_length=MAX_TITLE_LENGTH,
        description=f"free-text title of the run, at most {MAX_TITLE_LENGTH:,} characters",
    )
    run: RunSection = Field(default_factory=RunSection, description="time step, gravity, skin, seed")
    domain: DomainSection = Field(
        default_factory=DomainSection, description="periodic boundaries: periodic axes and the box lo, hi"
    )
    contact: ContactSection = Field(
        default_factory=ContactSection, description="the contact law and its parameters"
    )
    materials: dict[Str, MaterialSpec] = Field(
        min_length=1, description="materials by name (tables [materials.NAME]); at least one"
    )
    material_pairs: list[MaterialPair] = Field(
        default_factory=list,
        description="per-pair overrides of restitution, friction, rolling_friction, spinning_friction",
    )
    # after validation each entry is the source plugin's own Params model: serialised as that
    particles: list[SerializeAsAny[ParticleEntry]] = Field(
        default_factory=list, description="particle sources (arrays of tables [[particles]]), by `source`"
    )
    boundaries: dict[Str, BoundaryEntry] = Field(
        default_factory=dict, description="boundaries by name (tables [boundaries.NAME]), by plugin `type`"
    )
    stages: list[Stage] = Field(
        min_length=1,
        description=f"the stages of the run, in order (at least one, at most {MAX_STAGES:,})",
        json_schema_extra={"maxItems": MAX_STAGES},  # checked by a rule, with its reason
    )
    output: OutputSection = Field(default_factory=OutputSection, description="output directory and cadence")

    @classmethod
    def rules(cls, data: dict, context: dict) -> Problems:
        checks = (_count_checks, _cross_checks, _stage_length_checks, _output_volume_checks)
        return [p for check in checks for p in check(data)]

    def stage_names(self) -> list[str]:
        return [s.name for s in self.stages]


def periodic_source_checks(data: dict, extents: dict[int, tuple[float | None, Any, str | None]]) -> Problems:
    """With periodic axes: the box is long enough for the particles (the run checks it again with
    the actual skin), and no source region is wider than the box (it would overlap itself).

    ``data`` is the raw deck; ``extents`` maps the index of each validated ``[[particles]]`` table to
    ``(r_max, bounds, key)``: the largest radius and the ``(lo, hi)`` box of its particles as its
    source plugin reports them (:meth:`pdem.sources.api.Source.r_max`,
    :meth:`~pdem.sources.api.Source.bounds`; None where unknown before the run) and the key a
    too-wide box is reported under (``"region"``, or None for the table itself).
    """
    domain = data.get("domain")
    if not isinstance(domain, dict):
        return []
    axes = domain.get("periodic")
    lo, hi = domain.get("lo"), domain.get("hi")
    if not (isinstance(axes, list) and axes and _is_vec3(lo) and _is_vec3(hi)):
        return []
    periodic = [d for d, a in enumerate("xyz") if a in axes and hi[d] > lo[d]]
    out: Problems = []
    radii = [r for k, (r, _, _) in sorted(extents.items()) if r is not None]
    run = data.get("run")
    skin = run.get("skin") if isinstance(run, dict) else None
    skin = float(skin) if _is_num(skin) and skin >= 0 else 0.0
    if radii:
        cutoff = 2.0 * max(radii) + skin
        for d in periodic:
            length = hi[d] - lo[d]
            if length < 2.0 * cutoff:
                what = "2 r_max + skin" if skin else "2 r_max (+ skin)"
                out.append(
                    (
                        ("domain", "hi"),
                        f"the periodic box is {length:.4g} m long along {'xyz'[d]}, less than twice the "
                        f"largest pair cutoff {what} = {cutoff:.4g} m, so a pair of particles could "
                        f"interact with two images of each other; make it at least {2.0 * cutoff:.4g} m "
                        "long (domain.lo, domain.hi) or use smaller particles",
                    )
                )
    for k, (_, bounds, key) in sorted(extents.items()):
        if bounds is None:
            continue
        rlo, rhi = bounds
        what = "region" if key else "source's extent"
        for d in periodic:
            length = hi[d] - lo[d]
            if rhi[d] - rlo[d] > length * (1 + 1e-12):
                out.append(
                    (
                        ("particles", k, key) if key else ("particles", k),
                        f"the {what} is {rhi[d] - rlo[d]:.4g} m wide along the periodic axis "
                        f"{'xyz'[d]}, wider than the periodic box ({length:.4g} m): wrapped into the box, "
                        f"its particles would overlap; make the {what} at most as wide as the box (it may "
                        "straddle a periodic face: positions are wrapped)",
                    )
                )
    return out


def _stage_length_checks(data: dict) -> Problems:
    """A stage of more than :data:`MAX_STAGE_STEPS` ``steps``, or that may take more than that by its
    end time (or max_time)
    at a dt given in the deck: the run would never finish (``dt = 1e-300``). The stage's bound is
    the least of ``steps``, ``time / dt`` and ``max_time / dt``, so a stage that ends by ``steps``
    (or by ``time``) first is fine whatever its max_time; with dt from the law's estimate (not in
    the deck) nothing is known before the run."""
    run = data.get("run")
    run_dt = run.get("dt") if isinstance(run, dict) else None
    stages = data.get("stages")
    out: Problems = []
    for k, stage in enumerate(stages if isinstance(stages, list) else []):
        if not isinstance(stage, dict) or not isinstance(stage.get("end"), dict):
            continue
        end = stage["end"]
        steps = end.get("steps")
        if isinstance(steps, int) and not isinstance(steps, bool) and steps > MAX_STAGE_STEPS:
            name = stage.get("name") if isinstance(stage.get("name"), str) else str(k)
            out.append(
                (
                    ("stages", k, "end", "steps"),
                    f"stage '{name}': steps = {steps:,} is above the limit of {MAX_STAGE_STEPS:.0e} steps "
                    "per stage (a run that long cannot finish); use fewer steps, or end the stage by time",
                )
            )
        if _is_num(stage.get("dt")):
            dt, dt_key = stage["dt"], f"stages.{k}.dt"
        elif stage.get("dt") is None and _is_num(run_dt):
            dt, dt_key = run_dt, "run.dt"
        else:
            continue
        if dt <= 0:
            continue  # reported by the schema
        by_time = {
            key: end[key] / dt  # may overflow to inf: still above the limit
            for key in ("time", "max_time")
            if _is_num(end.get(key)) and end[key] > 0
        }
        steps = end.get("steps")
        bounds = list(by_time.values())
        if isinstance(steps, int) and not isinstance(steps, bool) and steps > 0:
            bounds.append(steps)
        if not by_time or min(bounds) <= MAX_STAGE_STEPS:
            continue
        name = stage.get("name") if isinstance(stage.get("name"), str) else str(k)
        for key, n in by_time.items():
            out.append(
                (
                    ("stages", k, "end", key),
                    f"stage '{name}': {key} = {_show_num(end[key])} s at dt = {_show_num(dt)} s "
                    f"({dt_key}) is {n:.3g} steps, above the limit of {MAX_STAGE_STEPS:.0e} steps per "
                    f"stage; raise {dt_key} (or leave dt out: the default is 0.2 of the contact "
                    f"law's stability estimate) or shorten stages.{k}.end.{key}",
                )
            )
    return out


def _name_length_message(kind: str, name: str) -> str:
    used = {
        "stage": "it is part of output file names (series_<stage>.csv, solver_<stage>.csv, "
        "<boundary>.<stage>.csv), which file systems limit to 255 bytes",
        "boundary": "it is part of output file names (<boundary>.<stage>.csv), which file systems limit to "
        "255 bytes, and of every column it measures",
        "material": "it is repeated in messages and output metadata",
    }[kind]
    return (
        f"{kind} name {quote(name, 80)} is {len(name):,} characters long, more than the {MAX_NAME_LENGTH} "
        f"allowed: {used}; give a shorter name"
    )


_COUNT_LIMITS = (
    (
        "stages",
        MAX_STAGES,
        "stages",
        "each stage writes its own series file and a checkpoint when it ends; merge consecutive stages "
        "(a stage ends when any of its end conditions holds) or run the rest from a checkpoint "
        "(pdem resume CHECKPOINT --set stages.N.…)",
    ),
    (
        "boundaries",
        MAX_BOUNDARIES,
        "boundaries",
        "a boundary's records are one file per stage; group walls in one boundary (a mesh, a box)",
    ),
    ("materials", MAX_MATERIALS, "materials", "the contact tables hold one entry per pair of materials"),
    ("particles", MAX_SOURCES, "[[particles]] tables", "merge sources, e.g. into one packing file"),
)


def _count_checks(data: dict) -> Problems:
    """At most :data:`MAX_STAGES` stages, :data:`MAX_BOUNDARIES` boundaries, … (docs/deck.md, Limits)."""
    out: Problems = []
    for key, limit, what, why in _COUNT_LIMITS:
        value = data.get(key)
        if isinstance(value, list | dict) and len(value) > limit:
            out.append(
                (
                    (key,),
                    f"{len(value):,} {what}, more than the {limit:,} a deck may have: {why}",
                )
            )
    materials = data.get("materials")
    for name in materials if isinstance(materials, dict) else ():
        if len(name) > MAX_NAME_LENGTH:
            out.append((("materials", name), _name_length_message("material", name)))
        elif not name.isprintable():
            out.append(
                (
                    ("materials", name),
                    f"material name {_q(name)} holds control characters (a new line, a tab, …); give a "
                    "name of printable characters",
                )
            )
    return out


def _number(value: Any) -> float | None:
    return float(value) if _is_num(value) and value > 0 else None


def _large(n: float) -> str:
    return f"{n:,.0f}" if n < 1e15 else f"{n:.3g}"


#: (cadence by steps, by time, limit, what is written, what to raise)
_OUTPUT_VOLUME = (
    ("every_steps", "every_time", MAX_SNAPSHOTS_PER_STAGE, "snapshots"),
    ("series_every_steps", "series_every_time", MAX_SERIES_ROWS_PER_STAGE, "series rows"),
    ("checkpoint_every_steps", None, MAX_CHECKPOINTS_PER_STAGE, "checkpoints"),
)


def _output_volume_checks(data: dict) -> Problems:
    """A stage whose length the deck fixes (it ends only by ``steps`` and/or ``time``, at a dt given
    in the deck for ``time``) may write at most :data:`MAX_SNAPSHOTS_PER_STAGE` snapshots,
    :data:`MAX_SERIES_ROWS_PER_STAGE` series rows and :data:`MAX_CHECKPOINTS_PER_STAGE` periodic
    checkpoints. A stage that may end earlier (``kinetic_energy_below``, ``quantity``) is not
    checked: its length is not known before the run."""
    stages = data.get("stages")
    run = data.get("run") if isinstance(data.get("run"), dict) else {}
    output = data.get("output") if isinstance(data.get("output"), dict) else {}
    out: Problems = []
    for k, stage in enumerate(stages if isinstance(stages, list) else []):
        end = stage.get("end") if isinstance(stage, dict) else None
        if not isinstance(end, dict) or _given(end, "kinetic_energy_below") or _given(end, "quantity"):
            continue
        dt = _number(stage.get("dt")) if _given(stage, "dt") else _number(run.get("dt"))
        steps = end.get("steps")
        steps = steps if isinstance(steps, int) and not isinstance(steps, bool) and steps > 0 else None
        time = _number(end.get("time"))
        by_steps = [float(n) for n in (steps, time / dt if time and dt else None) if n is not None]
        n_steps = min(by_steps) if by_steps else None
        length = time if time is not None else (steps * dt if steps and dt else None)
        if n_steps is None and length is None:
            continue
        own = stage.get("output") if isinstance(stage.get("output"), dict) else {}
        name = stage.get("name") if isinstance(stage.get("name"), str) else str(k)
        for by_step_key, by_time_key, limit, what in _OUTPUT_VOLUME:
            keys = [key for key in (by_step_key, by_time_key) if key is not None]
            source = own if any(_given(own, key) for key in keys) else output
            where: Loc = ("stages", k, "output") if source is own else ("output",)
            every_steps = _number(source.get(by_step_key))
            every_time = _number(source.get(by_time_key)) if by_time_key else None
            if every_steps is None and every_time is None and by_step_key != "checkpoint_every_steps":
                defaults = {"every_steps": OutputSection.DEFAULT_EVERY_STEPS,
                            "series_every_steps": OutputSection.DEFAULT_SERIES_EVERY_STEPS}  # fmt: skip
                every_steps, where = float(defaults[by_step_key]), ()
            if every_steps is not None and n_steps is not None:
                count, key, value = n_steps / every_steps, by_step_key, every_steps
                span = f"{_large(n_steps)} steps"
            elif every_time is not None and length is not None:
                count, key, value = length / every_time, by_time_key, every_time
                span = f"{length:.6g} s"
            else:
                continue
            if count <= limit:
                continue
            shown = f"{int(value):,}" if key.endswith("steps") else f"{value!r} s"
            if where:
                loc: Loc = (*where, key)
                remedy = "raise " + ".".join(str(p) for p in loc)
            else:  # the default cadence
                loc = ("stages", k, "end")
                remedy = f"give a coarser output.{by_step_key} (default {int(every_steps):,})"
            out.append(
                (
                    loc,
                    f"stage {_q(name)} would write about {_large(count)} {what} ({key} = {shown} over "
                    f"{span}), more than the {limit:,} a stage may write; {remedy}",
                )
            )
    return out


def _show_num(value: float) -> str:
    """A number as TOML would write it (``repr`` of a float)."""
    return repr(float(value)) if isinstance(value, float) else str(value)


def _cross_checks(data: dict) -> Problems:
    """Names that refer to materials, stages and boundaries exist; stage names are unique."""
    out: Problems = []
    materials = data.get("materials")
    mat_names = list(materials) if isinstance(materials, dict) and materials else None
    boundaries = data.get("boundaries")
    bnd = boundaries if isinstance(boundaries, dict) else {}

    stages = data.get("stages")
    stage_names: list[str] | None = None
    if isinstance(stages, list):
        names = [s.get("name") if isinstance(s, dict) else None for s in stages]
        first: dict[str, int] = {}
        for k, name in enumerate(names):
            if isinstance(name, str):
                if len(name) > MAX_NAME_LENGTH:
                    out.append((("stages", k, "name"), _name_length_message("stage", name)))
                if name in first:
                    msg = f"duplicate stage name {_q(name)} (also stages.{first[name]}.name)"
                    out.append((("stages", k, "name"), msg + "; give unique names"))
                else:
                    first[name] = k
        if names and all(isinstance(n, str) for n in names):
            stage_names = list(first)

    def check_material(loc: Loc, value: Any) -> None:
        if mat_names is not None and isinstance(value, str) and value not in mat_names:
            hint = did_you_mean(value, mat_names, True)
            out.append((loc, f"unknown material {_q(value)}{hint}; defined materials: {_listing(mat_names)}"))

    def check_stage(loc: Loc, value: Any) -> None:
        if stage_names is not None and isinstance(value, str) and value not in stage_names:
            hint = did_you_mean(value, stage_names, True)
            out.append((loc, f"unknown stage {_q(value)}{hint}; defined stages: {_listing(stage_names)}"))

    def check_names(loc: Loc, table: dict) -> None:
        """A plugin's table: keys naming a material, and keys naming a stage or a list of stages."""
        for key in _material_keys(table):
            check_material((*loc, key), table[key])
        for key in _stage_keys(table):
            value = table[key]
            if isinstance(value, list):
                for j, v in enumerate(value):
                    check_stage((*loc, key, j), v)
            else:
                check_stage((*loc, key), value)

    particles = data.get("particles")
    if isinstance(particles, list):  # any source plugin, like any boundary plugin below
        for k, src in enumerate(particles):
            if isinstance(src, dict):
                check_names(("particles", k), src)

    pairs = data.get("material_pairs")
    if isinstance(pairs, list):
        seen: dict[frozenset, int] = {}
        for k, pair in enumerate(pairs):
            mats = pair.get("materials") if isinstance(pair, dict) else None
            if isinstance(mats, list):
                for j, m in enumerate(mats):
                    check_material(("material_pairs", k, "materials", j), m)
                if len(mats) == 2 and all(isinstance(m, str) for m in mats):
                    key = frozenset(mats)
                    if key in seen:
                        out.append(
                            (
                                ("material_pairs", k, "materials"),
                                f"pair {_listing(mats)} is already given in material_pairs.{seen[key]}",
                            )
                        )
                    seen.setdefault(key, k)

    for name, table in bnd.items():
        if len(name) > MAX_NAME_LENGTH:
            out.append((("boundaries", name), _name_length_message("boundary", name)))
        elif not _NAME_RE.match(name):
            out.append(
                (
                    ("boundaries", name),
                    f"boundary name {_q(name)} must start with a letter or '_' and "
                    "contain only letters, digits, '_' or '-'",
                )
            )
        if isinstance(table, dict):
            check_names(("boundaries", name), table)

    output = data.get("output")
    thermo = output.get("thermo") if isinstance(output, dict) else None
    for k, key in enumerate(thermo if isinstance(thermo, list) else []):
        if isinstance(key, str) and "." in key:
            head = key.split(".", 1)[0]
            if head not in bnd:
                out.append(
                    (
                        ("output", "thermo", k),
                        f"thermo column {_q(key)} names boundary {_q(head)}, which is not defined"
                        f"{did_you_mean(head, list(bnd), True)}; defined boundaries: {_listing(list(bnd))}",
                    )
                )

    if isinstance(stages, list):
        for k, stage in enumerate(stages):
            smats = stage.get("materials") if isinstance(stage, dict) else None
            for name in smats if isinstance(smats, dict) else ():
                check_material(("stages", k, "materials", name), name)
            end = stage.get("end") if isinstance(stage, dict) else None
            quantity = end.get("quantity") if isinstance(end, dict) else None
            if isinstance(quantity, str) and "." in quantity:
                head = quantity.split(".", 1)[0]
                if head and head not in bnd:
                    out.append(
                        (
                            ("stages", k, "end", "quantity"),
                            f"quantity {_q(quantity)} names boundary {_q(head)}, which is not defined"
                            f"{did_you_mean(head, list(bnd), True)}; defined boundaries: "
                            f"{_listing(list(bnd))}",
                        )
                    )
    return out

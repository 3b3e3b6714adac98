"""The boundary-plugin contract (entry-point group ``pdem.boundaries``).

A boundary is anything a deck places around the particles: a wall of a given shape, a composite
device (hopper, shear box, penetrometer, triaxial membrane), a servo controller, a particle sink, a
measurement probe. The entry-point name is the deck's ``type``::

    [boundaries.floor]
    type = "plane"
    point = [0, 0, 0]
    normal = [0, 0, 1]
    material = "steel"

A boundary class declares a pydantic ``Params`` model (derived from :class:`BoundaryParams`; unknown
keys are errors) and overrides the hooks it needs:

* ``build(sim)`` — add walls (``sim.add_wall``) or particles; called once, by ``sim.add_boundary``;
* ``on_stage(sim, stage)`` — called when a stage starts (``sim.set_stage``); the default switches
  the boundary on or off by its ``stages`` and ``off_stages`` keys (``set_active``, which switches its
  own walls);
* ``stage_roles(params, stages)`` (class method) — what the boundary does in each stage, from its
  parameters alone (None: off); a plugin whose ``on_stage`` does more than the default overrides it,
  with ``stage_remedies(params, stage)``, the keys that would say what it does in a stage none of its
  keys names. :mod:`pdem.deck.stage_roles` refuses a stage added on resume that would switch a
  boundary off that way (see "Stage keys" below);
* ``before_step(sim)`` — servo control (set wall velocities, targets) before the step;
* ``apply_forces(sim)`` — add forces and torques to owned particles (``sim.particles.f[:n_owned]``,
  ``.t``) after the contact forces: membranes, pistons, field forces. DEM-P integrates them with the
  contact forces; DEM-C takes them into the free velocity. May be called more than once per step
  (e.g. when the run is prepared): make it a function of the current state;
* ``after_step(sim)`` — particle removal, probes;
* ``measurements(sim) -> dict[str, float]`` — scalars recorded in the time series (as
  ``<name>.<key>``) and usable in stage end conditions;
* ``summary(series) -> dict`` — derived results at the end of the run (e.g. a steady flow rate);
* ``records(sim) -> list[dict]`` — rows a probe sampled since the last call (each with ``step``
  and ``time``), at its own cadence (e.g. every step, finer than the series); the runner drains
  them at every series row and writes them to ``<name>.<stage>.csv`` (rank 0; every rank must
  return the same rows); a resumed run truncates that file at the checkpoint's step like a series;
* ``state()`` / ``restore(state)`` — JSON-serialisable memory kept in checkpoints.

**Describing the boundary to pdem's checks** (class methods, from the parameters alone, no
simulation; ``pdem advise`` and the deck's checks ask them and never look at the ``type``, so a
boundary a user writes gets the same advice as pdem's own). Each default says "nothing known":

* ``loading(name, params, facts) -> list[Loading]`` — what it imposes on the grains and in which
  stages (:class:`Loading`): the fastest speed it gives a wall or a grain (a servo's speed limit, a
  prescribed wall speed, a strain rate × the sample's height, a dropped body's impact speed), the
  normal stress it holds (a servo's target, a confining pressure; ``on_weight`` when it acts on top of
  the grains' weight, as a plate on a bed), the quasi-static loading rate and the key that sets it
  (``rate_key``, ``rate``, ``shear_rate``: the inertial number I = γ̇ d sqrt(ρ/σ) is advised on it and
  ``--apply`` may change that key), the measurements that grow at a known rate (``ends``: a stage that
  ends on ``<name>.<key>`` lasts as long as the key takes to reach the end value), and whether it
  measures a wave (``wave``) or drops a body (``impact``): then the grains' stiffness is left alone.
  ``name`` is the boundary's name in the deck (for the labels ``boundaries.<name>.<key>``) and
  ``facts`` (:class:`SceneFacts`) what the deck says about the grains (sizes, density, gravity, the
  packed height, the stages and their ends). Default: ``[]``.
* ``extent(params) -> Extent | None`` — the region in which the boundary holds the sample
  (:class:`Extent`: its bounding box and the horizontal area the grains pack into), when it holds
  one (a shear box, a triaxial cell, a plate of known area). The advice takes the packed height from
  that area (else from the sources' regions). Default: None.
* ``sample_size(name, params, facts) -> SampleSize | None`` — the minimum sizes of the test the
  boundary runs, with their sources (:class:`SampleSize` of :class:`SizeCheck`: "box width / d_max
  ≥ 10, ASTM D3080"); the advice warns below a minimum. Default: None.
* ``wall_materials(params) -> list[str]`` — the names of the materials of its walls (the advice's
  grain–wall collision times). Default: the ``material`` key, when it is a name.

**Stage keys.** A boundary names the stages it acts in with keys called ``stages``, ``stage`` or
ending in ``_stage`` / ``_stages`` (the deck checks that they name defined stages): ``stages`` (on
in these, default all), ``off_stages`` (off in these, said explicitly) and a device's own roles
(the triaxial cell's ``mould_stages``, ``consolidation_stage``, ``shear_stage``,
``later_shear_stages``). A boundary on in one stage that no key names the next stage for would be
switched off there silently; in a deck its author wrote that is how a device ends, but a stage
added when a finished run is resumed was never seen by the keys, so a resume must name it
(:func:`pdem.deck.stage_roles.check_new_stages`).

**Summaries** get the series of every stage merged in deck order (:func:`merge_series`) with a
``stage`` column (the stage name of each row), so that a result that belongs to one stage (the
triaxial's σ₁ at the end of consolidation) is taken from that stage's rows, whatever stages follow.

The hooks run inside ``Simulation.step`` (under a deck's runner and under ``Simulation.run`` alike),
in the order the boundaries were added, only while the boundary is active; a hook a class does not
override costs nothing. The walls a boundary creates are evaluated by the generic wall loop with
the simulation's contact law; a boundary may use MPI (collectives that every rank calls alike) and
numba kernels of its own, through :mod:`pdem.api`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Annotated, Any, ClassVar, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from ..geometry.walls import ConstantVelocity, Fixed, Motion, Wall

__all__ = [
    "STAGE_COLUMN", "Boundary", "BoundaryParams", "WallBoundaryParams", "MotionSpec", "Vec3", "listed",
    "make_motion", "merge_series", "names_stage", "stage_keys", "stage_rows",
    "Extent", "Loading", "SampleSize", "SceneFacts", "SizeCheck",
]

#: the merged series' column holding each row's stage name (:func:`merge_series`)
STAGE_COLUMN = "stage"

FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
Vec3 = Annotated[
    tuple[FiniteFloat, FiniteFloat, FiniteFloat], Field(description="three finite numbers (x, y, z)")
]


class FixedMotion(BaseModel):
    """The wall does not move."""

    model_config = ConfigDict(extra="forbid")
    type: Literal["fixed"] = "fixed"


class ConstantVelocityMotion(BaseModel):
    """Translation at constant velocity [m/s]."""

    model_config = ConfigDict(extra="forbid")
    type: Literal["constant_velocity"]
    velocity: Vec3


MotionSpec = Annotated[FixedMotion | ConstantVelocityMotion, Field(discriminator="type")]


def make_motion(spec: FixedMotion | ConstantVelocityMotion | None) -> Motion:
    """The :class:`~pdem.geometry.walls.Motion` a deck's ``motion`` table describes."""
    if spec is None or isinstance(spec, FixedMotion):
        return Fixed()
    return ConstantVelocity(tuple(spec.velocity))


class BoundaryParams(BaseModel):
    """Keys every boundary accepts. ``stages``: names of the stages in which it is active (default:
    all); ``off_stages``: stages in which it is switched off, said explicitly."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    type: str = Field(description="the boundary plugin (entry point of group pdem.boundaries)")
    stages: list[str] | None = Field(default=None, description="stages in which it is active (default all)")
    off_stages: list[str] | None = Field(
        default=None,
        description="stages in which it is switched off, said explicitly (it is also off in stages its "
        "stage keys do not name); a stage added when a run is resumed must be named here or by a key "
        "that keeps the boundary on, when the boundary was on in the stage before",
    )

    @model_validator(mode="after")
    def _off_stages_apart(self):
        both = sorted(set(self.stages or ()) & set(self.off_stages or ()))
        if both:
            raise ValueError(
                f"stage(s) {both} are named by both stages and off_stages; a boundary is on or off in a "
                "stage: remove them from one of the two"
            )
        return self


def stage_keys(params: BaseModel) -> list[str]:
    """The keys of a boundary's parameters that name stages (the deck's convention: ``stage``,
    ``stages``, ``*_stage``, ``*_stages``), in declaration order."""
    fields = type(params).model_fields
    return [k for k in fields if k in ("stage", "stages") or k.endswith(("_stage", "_stages"))]


def names_stage(params: BaseModel, stage: str) -> bool:
    """Does any stage key of ``params`` (:func:`stage_keys`) name ``stage``?"""
    for key in stage_keys(params):
        value = getattr(params, key, None)
        if value == stage or (isinstance(value, (list, tuple)) and stage in value):
            return True
    return False


def listed(params: BaseModel, stage: str) -> bool:
    """On in ``stage`` by the generic keys: ``stages`` lists it (or has no list) and ``off_stages``
    does not."""
    stages = getattr(params, "stages", None)
    off = getattr(params, "off_stages", None) or ()
    return (stages is None or stage in stages) and stage not in off


def merge_series(
    series: Mapping[str, Sequence[Mapping[str, float]]], stages: Sequence[str]
) -> dict[str, np.ndarray]:
    """The rows of every stage's series (``{stage: [row, …]}``), in the order of ``stages``, as one
    column per key (NaN where a row lacks it) plus :data:`STAGE_COLUMN`, each row's stage name (an
    object array): what :meth:`Boundary.summary` receives."""
    rows = [(name, r) for name in stages for r in series.get(name, [])]
    keys = sorted({k for _, r in rows for k in r} - {STAGE_COLUMN})
    out = {k: np.array([r.get(k, math.nan) for _, r in rows]) for k in keys}
    out[STAGE_COLUMN] = np.array([name for name, _ in rows], dtype=object)
    return out


def stage_rows(
    series: Mapping[str, np.ndarray], stages: Sequence[str] | str, length: int
) -> np.ndarray | None:
    """Boolean mask of the rows of ``series`` that belong to ``stages`` (a name or names), or None
    when the series has no :data:`STAGE_COLUMN` (a caller that merged it without one) or it does
    not match ``length`` rows."""
    column = series.get(STAGE_COLUMN)
    if column is None or len(column) != length:
        return None
    names = {stages} if isinstance(stages, str) else set(stages)
    return np.array([s in names for s in column], dtype=bool)


class WallBoundaryParams(BoundaryParams):
    """Keys of boundaries that are walls: material, prescribed motion and surface spin."""

    material: str = Field(description="name of a material defined under [materials]")
    motion: MotionSpec | None = Field(default=None, description="prescribed translation (default fixed)")
    omega: Vec3 = Field(default=(0.0, 0.0, 0.0), description="surface spin about the reference point [rad/s]")


# descriptions for pdem's checks (see "Describing the boundary" in the module docstring) --------------


@dataclass(frozen=True)
class SceneFacts:
    """What the deck says about the grains, given to :meth:`Boundary.loading` and
    :meth:`Boundary.sample_size` (SI units; NaN where the deck does not tell).

    ``stages``: the stage names in deck order; ``gravity``: |g| [m/s²]; ``density``: the grains' mean
    density [kg/m³]; ``d_mean`` / ``d_max``: their mean and largest diameters [m]; ``grain_volume``:
    the mean volume of a grain [m³]; ``packed_height``: the height the grains fill once packed [m];
    ``footprint``: the horizontal area they pack into [m²] (None: unknown); ``packing_fraction``: the
    solid fraction assumed for a packed bed; ``ends``: ``{quantity: value}`` of the stages that end
    when a quantity (``"<boundary>.<key>"``) rises above a value (the largest value per quantity).
    """

    stages: tuple[str, ...]
    gravity: float = 0.0
    density: float = math.nan
    d_mean: float = math.nan
    d_max: float = math.nan
    grain_volume: float = math.nan
    packed_height: float = math.nan
    footprint: float | None = None
    packing_fraction: float = 0.6
    ends: Mapping[str, float] = field(default_factory=dict)

    def stages_from(self, stage: str | None) -> tuple[str, ...]:
        """The stages from ``stage`` on (all of them for None or a name not in :attr:`stages`)."""
        if stage is None or stage not in self.stages:
            return tuple(self.stages)
        return tuple(self.stages[self.stages.index(stage):])

    def overburden(self, depth: float) -> float:
        """φ ρ g z: the weight of the packed grains above ``depth`` [Pa] (0 without gravity)."""
        if not (self.gravity > 0 and math.isfinite(self.density) and math.isfinite(depth)):
            return 0.0
        return self.packing_fraction * self.density * self.gravity * depth


@dataclass(frozen=True)
class Loading:
    """One thing a boundary imposes on the grains in ``stages`` (see :meth:`Boundary.loading`).

    Every part is optional (its default: nothing):

    * ``speed`` [m/s] and ``speed_from`` (a label, e.g. ``"boundaries.lid.max_speed (servo)"``): the
      fastest speed it gives a wall or a grain; the advice resolves the collisions at it;
    * ``stress`` [Pa] and ``stress_from``: the normal stress it holds on the grains; ``on_weight``:
      it acts on top of the grains' weight (a plate on a bed), else it is the stress itself (a
      confining pressure); the advice sizes the overlaps at the largest stress of the scene;
    * ``rate_key`` (a key of the boundary's parameters), ``rate`` (its value), ``shear_rate`` [1/s]
      (the shear rate that rate gives the grains) and ``rate_how`` (how, in words): the quasi-static
      loading whose inertial number I = ``shear_rate`` d sqrt(ρ / ``stress``) is advised on, in the
      first of ``stages``; the advice may propose another ``rate_key`` value (the stage's time ends
      scale with it);
    * ``note`` with ``note_source``: what the advice says of the loading rate when there is no
      ``rate_key`` (e.g. a discharge whose rate gravity sets);
    * ``ends``: ``{key: (rate, start)}`` — the measurement ``<name>.<key>`` starts at ``start`` and
      grows at ``rate`` per second in these stages: a stage ending on it lasts (end − start) / rate;
    * ``wave``: the boundary launches or times a wave, whose speed the grains' stiffness sets;
      ``impact``: it drops a body whose impact the advice does not estimate. Either keeps the
      stiffness as the deck gives it.
    """

    stages: tuple[str, ...]
    speed: float = 0.0
    speed_from: str = ""
    stress: float = 0.0
    stress_from: str = ""
    on_weight: bool = False
    rate_key: str | None = None
    rate: float = 0.0
    shear_rate: float = 0.0
    rate_how: str = ""
    note: str = ""
    note_source: str = ""
    ends: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    wave: bool = False
    impact: bool = False


@dataclass(frozen=True)
class Extent:
    """The region in which a boundary holds the sample (see :meth:`Boundary.extent`): ``lo`` and
    ``hi``, the corners of its bounding box [m] (None where unknown, e.g. a plate of infinite extent
    but known loaded area), and ``area``, the horizontal area the grains pack into [m²] (default: the
    box's x–y face)."""

    lo: tuple[float, float, float] | None = None
    hi: tuple[float, float, float] | None = None
    area: float | None = None

    @property
    def footprint(self) -> float | None:
        """``area``, else the x–y face of the box, else None."""
        if self.area is not None:
            return float(self.area)
        if self.lo is not None and self.hi is not None:
            return float((self.hi[0] - self.lo[0]) * (self.hi[1] - self.lo[1]))
        return None


@dataclass(frozen=True)
class SizeCheck:
    """One minimum size: ``label`` (what is compared, e.g. ``"box width / d_max"``), its ``value``,
    the ``minimum`` and the ``source`` of the rule."""

    label: str
    value: float
    minimum: float
    source: str


@dataclass(frozen=True)
class SampleSize:
    """The size checks of a boundary's test (see :meth:`Boundary.sample_size`): ``test`` names it in
    words (``"direct shear"``), ``checks`` are :class:`SizeCheck`, ``grains_min`` is the number of
    grains of a sample at the minimum size (None: not known)."""

    test: str
    checks: tuple[SizeCheck, ...]
    grains_min: float | None = None


class Boundary:
    """Base class of boundary plugins; see the module docstring."""

    Params: ClassVar[type[BoundaryParams]] = BoundaryParams

    def __init__(self, name: str, params: BoundaryParams) -> None:
        self.name = name
        self.params = params
        self.walls: list[Wall] = []
        self.active = True

    # hooks ----------------------------------------------------------------------------------
    def build(self, sim: Any) -> None:
        """Create walls/particles. Default: nothing."""

    def on_stage(self, sim: Any, stage: str) -> None:
        """A stage starts: default, active when the ``stages`` key lists it (or has no list) and
        ``off_stages`` does not (:func:`listed`)."""
        self.set_active(sim, listed(self.params, stage))

    @classmethod
    def stage_roles(cls, params: BaseModel, stages: Sequence[str]) -> list[str | None]:
        """What the boundary does in each of ``stages`` (the deck's stage names, in order), from its
        parameters alone: a short word (``"active"``, or a device's phase such as ``"shear"``), or
        None where it does nothing to the particles. Default: ``"active"`` where :func:`listed`.
        Override it with ``on_stage`` when that does more than the default (roles of a device, "from
        stage X on", a stage key it ignores)."""
        return ["active" if listed(params, s) else None for s in stages]

    @classmethod
    def stage_remedies(cls, params: BaseModel, stage: str) -> list[tuple[str, Any, str]]:
        """Ways to say what the boundary does in ``stage``, a stage none of its keys names: (key, the
        value that names it, what it then does). Default: add it to ``stages`` (when the boundary
        has a list) to keep it on, or to ``off_stages`` to switch it off."""
        out: list[tuple[str, Any, str]] = []
        stages = getattr(params, "stages", None)
        if stages is not None and "stages" in type(params).model_fields:
            out.append(("stages", [*stages, stage], "on"))
        out.append(("off_stages", [*(getattr(params, "off_stages", None) or []), stage], "off"))
        return out

    @classmethod
    def loading(cls, name: str, params: BaseModel, facts: SceneFacts) -> list[Loading]:
        """What the boundary ``name`` imposes on the grains, stage by stage (:class:`Loading`), from
        its parameters and the deck's grains (``facts``). Default: nothing known (``[]``); the
        advice still reads the generic ``motion`` key of a wall."""
        return []

    @classmethod
    def extent(cls, params: BaseModel) -> Extent | None:
        """The region in which the boundary holds the sample (:class:`Extent`), or None (default):
        it holds none, or it is not known."""
        return None

    @classmethod
    def sample_size(cls, name: str, params: BaseModel, facts: SceneFacts) -> SampleSize | None:
        """The published minimum sizes of the test the boundary runs (:class:`SampleSize`), or None
        (default): no such rule."""
        return None

    @classmethod
    def wall_materials(cls, params: BaseModel) -> list[str]:
        """The materials of the boundary's walls (names under ``[materials]``). Default: the
        ``material`` key when it is a string."""
        name = getattr(params, "material", None)
        return [name] if isinstance(name, str) else []

    def set_active(self, sim: Any, active: bool) -> None:
        """Switch the boundary (its hooks and its own walls) on or off."""
        self.active = active
        for wall in self.walls:
            sim.set_wall_active(wall.name, active)

    def before_step(self, sim: Any) -> None:
        """Called before every step of a stage in which the boundary is active."""

    def apply_forces(self, sim: Any) -> None:
        """Add forces/torques to owned particles after the contact forces (see the module docstring)."""

    def after_step(self, sim: Any) -> None:
        """Called after every step of a stage in which the boundary is active."""

    def measurements(self, sim: Any) -> dict[str, float]:
        """Scalars for the time series; default: force and contact count of each own wall, both
        over all ranks (collective)."""
        out: dict[str, float] = {}
        for wall in self.walls:
            prefix = "" if len(self.walls) == 1 else wall.name.split(".", 1)[-1] + "."
            f = wall.force
            out[prefix + "fx"], out[prefix + "fy"], out[prefix + "fz"] = (float(c) for c in f)
            out[prefix + "contacts"] = float(sim.count(int(wall.n_contacts)))  # n_contacts: this rank's
        return out

    def summary(self, series: dict[str, np.ndarray]) -> dict[str, float]:
        """Derived results at the end of the run. Default: none."""
        return {}

    def records(self, sim: Any) -> list[dict[str, float]]:
        """Rows sampled since the last call, for ``<name>.<stage>.csv`` (collective). Default: none."""
        return []

    def state(self) -> dict[str, Any]:
        """JSON-serialisable state a checkpoint must keep (counters, controller memory). Default: none."""
        return {}

    def restore(self, state: dict[str, Any]) -> None:
        """Restore what :meth:`state` returned."""

    # helpers --------------------------------------------------------------------------------
    def add_wall(
        self,
        sim: Any,
        shape: Any,
        suffix: str = "",
        *,
        material: str | None = None,
        motion: Motion | None = None,
        omega=None,
    ) -> Wall:
        """Add a wall named ``<boundary>`` or ``<boundary>.<suffix>`` owned by this boundary."""
        p = self.params
        mat = material if material is not None else getattr(p, "material", None)
        if motion is None:
            motion = make_motion(getattr(p, "motion", None))
        if omega is None:
            omega = getattr(p, "omega", (0.0, 0.0, 0.0))
        wall = sim.add_wall(
            shape, material=mat, name=self.name + (f".{suffix}" if suffix else ""), motion=motion, omega=omega
        )
        self.walls.append(wall)
        return wall

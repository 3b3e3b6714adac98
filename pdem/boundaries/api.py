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
from typing import Annotated, Any, ClassVar, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from ..geometry.walls import ConstantVelocity, Fixed, Motion, Wall

__all__ = [
    "STAGE_COLUMN", "Boundary", "BoundaryParams", "WallBoundaryParams", "MotionSpec", "Vec3", "listed",
    "make_motion", "merge_series", "names_stage", "stage_keys", "stage_rows",
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

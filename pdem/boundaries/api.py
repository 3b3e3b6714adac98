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
  the boundary on or off by its ``stages`` key (``set_active``, which switches its own walls);
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

The hooks run inside ``Simulation.step`` (under a deck's runner and under ``Simulation.run`` alike),
in the order the boundaries were added, only while the boundary is active; a hook a class does not
override costs nothing. Boundaries never touch MPI or numba directly; the walls they create are
evaluated by the generic wall loop with the simulation's contact law.
"""

from __future__ import annotations

from typing import Annotated, Any, ClassVar, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from .walls import ConstantVelocity, Fixed, Motion, Wall

__all__ = ["Boundary", "BoundaryParams", "WallBoundaryParams", "MotionSpec", "Vec3", "make_motion"]

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
    """The :class:`~pdem.boundaries.walls.Motion` a deck's ``motion`` table describes."""
    if spec is None or isinstance(spec, FixedMotion):
        return Fixed()
    return ConstantVelocity(tuple(spec.velocity))


class BoundaryParams(BaseModel):
    """Keys every boundary accepts. ``stages``: names of the stages in which it is active (default:
    all)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    type: str = Field(description="the boundary plugin (entry point of group pdem.boundaries)")
    stages: list[str] | None = Field(default=None, description="stages in which it is active (default all)")


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
        """A stage starts: default, active when the ``stages`` key lists it (or has no list)."""
        stages = getattr(self.params, "stages", None)
        self.set_active(sim, stages is None or stage in stages)

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

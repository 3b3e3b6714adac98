"""A servo-controlled plate that holds a target normal stress on the grains.

An example boundary plugin for pdem (the worked example of docs/plugins.md, "Boundary plugins"):
an infinite plane whose unit ``normal`` points into the grains, moved along its normal every step
by a proportional controller so that the stress the grains put on it, σ = −F·n / ``area``, stays at
``target_stress``:

    v = clip(gain · (σ_target − σ), −max_speed, max_speed) · n

with ``gain`` [m/(s Pa)] by default ``max_speed / target_stress`` (full speed towards the grains
while they do not touch it). Every step the gain is capped so that the loop gain
g = gain (K dt + 2 C) / area stays ≤ 1, K = Σ S_n and C = Σ c_n the normal stiffness and dashpots
of the plate's contacts (:func:`pdem.api.servo_gain`): the load changes by K v dt + C Δv in a step,
and for g > 2 the plate chatters, its velocity alternating every step. Without the cap the deck of
this plugin's tests, run at dt = 1e-5 s instead of 2e-6 s, held its 500 Pa with a mean error of
75 % (g ≈ 2.1, of which the dashpots 1.9); with it, 0.5 %. Below the cap the gain is used as given
(the same results as before the cap); ``loop_gain`` is the last step's g of the given gain,
``gain_used`` the gain applied. That is ``control = "velocity"``, for soft grains (DEM-P). Against rigid
grains (DEM-C) a prescribed velocity into a packing that cannot compress meets an unbounded
reaction: use ``control = "force"``, where the plate is a free rigid body of mass ``mass`` pushed
along its normal by the constant force σ_target · area and held by the grains (solved with them by
DEM-C; explicit in the load for DEM-P), moving along its normal only. Measured every series row:
``stress`` [Pa], ``position`` [m] (the plate's travel along its normal), ``error``
(σ/σ_target − 1). Summary: the mean and the 95th percentile of |error| over the second half of
the stages in which it is active.

Deck::

    [boundaries.lid]
    type = "servo_plate"
    material = "steel"
    point = [0.0, 0.0, 0.03]
    normal = [0.0, 0.0, -1.0]
    area = 1.0e-4            # m²: the cross-section the load acts on
    target_stress = 2000.0   # Pa
    max_speed = 0.05         # m/s

For ``pdem advise`` it describes itself through the boundary contract's hooks: its loading
(:meth:`ServoPlate.loading`: the target stress on the grains' weight, reached at up to
``max_speed``) and the area it holds the grains in (:meth:`ServoPlate.extent`), so the advice sizes
the overlaps and the step for it as for a built-in device's servo plate.

It uses only the public plugin API (:mod:`pdem.api`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from pdem.api import (
    Boundary,
    BoundaryParams,
    Controlled,
    Extent,
    Loading,
    RigidBody,
    SceneFacts,
    Vec3,
    servo_gain,
    shapes,
)
from pydantic import Field, model_validator

__all__ = ["ServoPlate", "ServoPlateParams"]


class ServoPlateParams(BoundaryParams):
    """Keys of ``[boundaries.NAME]`` with ``type = "servo_plate"``."""

    material: str = Field(description="name of a material defined under [materials]")
    point: Vec3 = Field(description="a point of the plate at the start [m]")
    normal: Vec3 = Field(description="normal pointing into the grains (need not be unit)")
    area: float = Field(gt=0, description="the area the stress acts on [m²]")
    target_stress: float = Field(gt=0, description="normal stress to hold [Pa]")
    max_speed: float = Field(gt=0, description="largest plate speed [m/s]")
    gain: float | None = Field(
        default=None, gt=0,
        description="controller gain [m/(s Pa)]; default max_speed / target_stress; capped every step "
        "at area / (K dt + 2 C) from the stiffness K and dashpots C of the plate's contacts",
    )
    control: str = Field(
        "velocity", pattern="^(velocity|force)$",
        description="'velocity' (proportional servo, soft grains) or 'force' (a free plate under the "
        "target load; rigid grains)",
    )
    mass: float | None = Field(
        default=None, gt=0,
        description="plate mass for control = 'force' [kg]; default: target load / (10 m/s²)",
    )

    @model_validator(mode="after")
    def _normal(self):
        n = np.asarray(self.normal, dtype=float)
        if float(np.linalg.norm(n)) == 0.0:
            raise ValueError("normal must not be the zero vector")
        if self.control == "force" and np.count_nonzero(n) != 1:
            raise ValueError("control = 'force' needs a normal along a coordinate axis, e.g. [0, 0, -1]")
        return self


class ServoPlate(Boundary):
    """See the module docstring."""

    Params = ServoPlateParams

    @classmethod
    def loading(cls, name: str, params: ServoPlateParams, facts: SceneFacts) -> list[Loading]:
        """The plate holds ``target_stress`` on top of the grains' weight, moving at up to
        ``max_speed``, in every stage it is on in."""
        return [Loading(
            stages=tuple(facts.stages),
            speed=params.max_speed, speed_from=f"boundaries.{name}.max_speed (servo)",
            stress=params.target_stress, stress_from=f"boundaries.{name}.target_stress", on_weight=True,
        )]  # fmt: skip

    @classmethod
    def extent(cls, params: ServoPlateParams) -> Extent:
        """The grains pack under the plate's loaded ``area`` (the plane itself is unbounded)."""
        return Extent(area=params.area)

    def build(self, sim: Any) -> None:
        p = self.params
        self.n = np.asarray(p.normal, dtype=float) / float(np.linalg.norm(p.normal))
        self.gain = p.gain if p.gain is not None else p.max_speed / p.target_stress
        self.gain_used = self.gain  # this step's gain, after the cap
        self.loop_gain = 0.0  # g = gain (K dt + 2 C) / area of the given gain (nan: no stiffness)
        if p.control == "force":
            load = p.target_stress * p.area
            axis = "xyz"[int(np.flatnonzero(self.n)[0])]
            self.motion = RigidBody(
                mass=p.mass if p.mass is not None else load / 10.0,
                force=tuple(load * self.n),
                fixed_translation="xyz".replace(axis, ""),
            )
        else:
            self.motion = Controlled()
        self.plate = self.add_wall(sim, shapes.Plane(p.point, self.n), motion=self.motion)

    def stress(self) -> float:
        """σ = −F·n / area [Pa] (F: the grains' force on the plate; a collective read under MPI)."""
        return float(-(self.plate.force @ self.n) / self.params.area)

    def before_step(self, sim: Any) -> None:
        p = self.params
        if p.control == "force":
            return
        # capped so that gain (K dt + 2 C) / area <= 1 for the plate's contacts (pdem.api.servo_gain)
        gain, self.loop_gain = servo_gain(sim, self.plate, self.gain, p.area)
        self.gain_used = gain
        speed = float(np.clip(gain * (p.target_stress - self.stress()), -p.max_speed, p.max_speed))
        self.motion.velocity = speed * self.n

    def measurements(self, sim: Any) -> dict[str, float]:
        sigma = self.stress()
        return {
            "stress": sigma,
            "position": float(self.plate.offset @ self.n),
            "error": sigma / self.params.target_stress - 1.0,
            "contacts": float(self.plate.n_contacts),
        }

    def summary(self, series: dict[str, np.ndarray]) -> dict[str, float]:
        err = series.get(f"{self.name}.error")
        if err is None or len(err) < 4:
            return {}
        err = np.abs(err[~np.isnan(err)][len(err) // 2 :])
        return {"mean_abs_error": float(err.mean()), "p95_abs_error": float(np.percentile(err, 95))}

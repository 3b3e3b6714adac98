"""Triaxial cell: a cylindrical specimen between two platens, confined by a flexible membrane.

**Membrane** (why this design): the confining pressure acts on the grains of the lateral surface
as the gradient of σ₃ V, V the volume the membrane encloses: V = Σ_c ½ R_c² Δθ Δz over an (θ, z)
grid of cells about one grain diameter wide, R_c the membrane's radius at the centre of cell c. R_c
is a smooth maximum (width ``membrane_smoothing`` × the mean radius) over the caps of the grains
nearby: a grain of outer radius s = ρ + r reaches s within one grain radius of the centre
laterally (the membrane bridges gaps of that size) and falls off as a sphere beyond. Each grain's
load is then σ₃ × the share of the patches it holds up, along the surface's normal, and

* the load is conservative: over any closed path of the grains it does no net work. The first
  design loaded the outermost grain of each cell (``membrane_smoothing = 0``, kept for comparison).
  Its load jumps from grain to grain as they overtake one another or change cells, and with a
  finite step each jump lags the motion a little, always in the direction that feeds energy in: a
  frictionless elastic specimen under pressure gained 19 % of its energy in 3,000 steps (0.05 %
  with the smooth membrane, tests/test_triaxial.py). In the triaxial deck that heating kept the
  grains moving at 10–30 times the platen speed and made the peak strength depend on the test's
  duration.
* nothing holds the grains radially but these loads, so the specimen is free to bulge;
* the radial virial of the loads is exactly σ₃ × 2V (a uniform pressure on a cylinder); the maxima
  are exact and the weights are summed in fixed point, so every rank count gives bitwise the same
  result;
* it needs no membrane elements and no bonds (the bonded-ball membrane of Qu et al. 2019 adds its
  own elasticity), and works with both methods (DEM-C takes the loads into the free velocity).

Its limits: the enclosed volume is that of the cells' radii (the specimen volume to within a
grain's roughness); the cells are counted at the first step of each stage (``membrane_grid``) and
stretch with the specimen after that; the surface grains carry a small axial squeeze from the caps'
slopes (their own moments, which the platens do not feel; see the Love–Weber check).

**Platens**: horizontal planes; the bottom one is fixed. The top one is servo-controlled to σ₃
during consolidation (a velocity servo for soft grains; for rigid grains, ``control = "force"``, a
free plate under the load σ₃ A, solved with the grains by DEM-C), then driven down at a constant
axial strain rate during shearing (v = ε̇ H₀). The velocity servo is proportional, v = clip(gain
(σ_target − σ₁), ±max_speed) with gain = max_speed / σ₃ (max_speed / seating stress while seating),
capped every step at A / (K dt + 2 C), K and C the normal stiffness and dashpots of the
platen's contacts (:func:`pdem.contact.stability.servo_gain`): past a loop gain
gain (K dt + 2 C) / A of 2 the platen chatters. At the default max_speed the tests' specimen
(300 beads, σ₃ = 20 kPa) stays at g ≈ 0.15, uncapped; at max_speed = 1 m/s (g ≈ 2.5) it ended
consolidation with σ₁ 113 % above σ₃ without the cap and within 0.13 % with it.

**Membrane ends**: ``membrane_ends = "free"`` (default) leaves them open on infinite platens; with
frictionless platens the end grains then slide outwards and the specimen flares at its ends (an
hourglass). ``"tied"`` seals the membrane to the platens as in a laboratory cell: a rigid ring of
the platen radius, ``tie_length`` high (one mean diameter by default), stands on each platen while
the membrane acts (the top one follows the top platen); the specimen barrels instead, the rings'
radial loads are part of the grains' own stress (Love–Weber), not of σ₃, and σ₁ is read from the
cap (the top platen and its ring) as a laboratory reads it (:meth:`TriaxialCell._sigma1`).

**Stages**: the cell holds the specimen in ``mould_stages`` (the mould and the seating platen),
``consolidation_stage`` and ``shear_stage``, and shears on through ``later_shear_stages`` (at the
same strain rate, strains still from the start of ``shear_stage``: e.g. a stage added when a
finished run is resumed). In any other stage it stands idle: the platens stay as walls, but no
mould, membrane or servo holds the specimen, which springs apart if it was under pressure; so a stage
added on resume after a stage the cell held must be named, by ``later_shear_stages`` or
``off_stages`` (:mod:`pdem.deck.stage_roles`). The summary takes every value from the rows of the
stage it belongs to.

**Preparation**: an optional rigid mould (a cylinder wall of the specimen's radius) is active in the
stages listed in ``mould_stages`` (e.g. while grains are poured and settle), while the top platen is
servoed down to a small seating stress; the membrane takes over in ``consolidation_stage`` (its
pressure rising over ``ramp_time``) and ``shear_stage``.

Measured every series row: ``sigma1`` (from the top platen's force F and the current mean
cross-section A = V/H: with tied ends as a laboratory reads it, σ₃ + (F − σ₃ π R²)/A, the deviator
load over the volume-corrected area; with free ends F/A), ``sigma3``
(realised: total radial membrane force / lateral area), ``eps_a`` (axial strain from the start of
shearing, compression positive), ``eps_v`` (volumetric strain, from the membrane's enclosed volume),
``q`` = σ₁ − σ₃, ``p`` = (σ₁ + 2σ₃)/3, ``height``, ``radius`` (mean of the cells), and the average
stress of the grains from their contacts (Love–Weber, ``lw_szz``, ``lw_srr``): σ = (1/V) Σ_c l_c ⊗ f_c
over pair contacts (branch vectors), platen contacts and membrane forces (levers from the grain
centres), an independent check of the boundary stresses; ``end_overhang``, how far the end grains'
centres (within one mean diameter of a platen) stand beyond the platen radius plus their own radius
(positive: a grain past the platen's edge); with tied ends ``ring_srr``, the rings' part of the
grains' mean radial stress (lw_srr ≈ σ₃ + ring_srr). Lengths in m, stresses in Pa.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from pydantic import BaseModel, Field, model_validator

from pdem.api import (
    Boundary,
    BoundaryParams,
    Controlled,
    Extent,
    Follow,
    InstabilityError,
    Loading,
    RigidBody,
    SampleSize,
    SceneFacts,
    SizeCheck,
    Vec3,
    all_max,
    all_max_array,
    all_sum_int_array,
    listed,
    servo_gain,
    shapes,
    stage_rows,
)
from pdem.boundaries import triaxial_membrane as _mb

__all__ = ["TriaxialCell", "TriaxialParams"]

#: the minimum sizes of a triaxial specimen (the advice's sample-size check): (minimum, source)
SIZE_DIAMETER = (6.0, "ASTM D7181 / D4767: specimen diameter ≥ 6 × the largest grain diameter")
SIZE_DIAMETER_DEM = (
    15.0,
    "DEM practice, a rule of thumb: ≥ ~15 grains across the specimen for a representative peak",
)
SIZE_SLENDERNESS = (2.0, "ASTM D7181 / D4767: specimen height between 2 and 2.5 diameters")


class TriaxialParams(BoundaryParams):
    """Keys of ``[boundaries.NAME]`` with ``type = "triaxial"``."""

    material: str = Field(description="material of the platens (and of the mould)")
    base_center: Vec3 = Field(description="centre of the bottom platen [m]; the axis is +z")
    radius: float = Field(gt=0, description="initial specimen radius (the mould's) [m]")
    height: float = Field(gt=0, description="initial specimen height (the top platen's start) [m]")
    sigma3: float = Field(gt=0, description="confining pressure σ₃ [Pa]")
    strain_rate: float = Field(gt=0, description="axial strain rate during shearing [1/s]")
    consolidation_stage: str = Field(description="stage in which the specimen is consolidated to σ₃")
    shear_stage: str = Field(description="stage in which it is sheared at constant axial strain rate")
    mould_stages: list[str] = Field(
        default_factory=list, description="stages with the rigid mould in place"
    )
    later_shear_stages: list[str] | None = Field(
        default=None,
        description="stages after shear_stage in which the shearing goes on at the same strain rate, the "
        "axial and volumetric strains still counted from the start of shear_stage (e.g. a stage added "
        "when a finished run is resumed)",
    )
    cell_size: float | None = Field(
        default=None, gt=0,
        description="membrane cell size [m] along z and around; default one mean diameter",
    )
    membrane_smoothing: float = Field(
        0.1, ge=0,
        description="width b of the membrane's smooth maximum, as a fraction of the mean grain radius: "
        "each cell's surface radius is R = b log Σ h exp(s / b) over the grains near it (s = ρ + r, h "
        "their hat-function weight in the cell), and the load on every grain is the gradient of σ₃ × "
        "the enclosed volume, so the membrane does no net work over a closed path (conservative); 0 "
        "loads only the outermost grain of each cell (a load that jumps from grain to grain, which the "
        "time step turns into a steady heating of the specimen)",
    )
    membrane_grid: str = Field(
        "stage", pattern="^(stage|step)$",
        description="the membrane's (θ, z) cell counts: 'stage' fixes them at the first step of each "
        "stage (cells then stretch with the specimen); 'step' recomputes them every step from the "
        "current height and outer radius (a count that changes moves every cell's load at once)",
    )
    membrane_ends: str = Field(
        "free", pattern="^(free|tied)$",
        description="'tied': the membrane is sealed to the platens, as in a laboratory cell: a rigid ring "
        "of the platen radius (``radius``) and ``tie_length`` high stands on each platen while the "
        "membrane acts, so the end grains cannot spread past the platens' edges (with frictionless "
        "platens they otherwise slide outwards and the specimen flares at its ends); 'free': the "
        "membrane's ends are open and the platens are infinite planes",
    )
    membrane_load: str = Field(
        "gradient", pattern="^(gradient|radial)$",
        description="'gradient' (default): each grain's load is −σ₃ ∂V/∂x, along the membrane's normal "
        "(conservative); 'radial': only its radial part, scaled to the same pressure (the membrane as a "
        "locally straight cylinder; not conservative). DEM-C runs the gradient with its mass scaling of "
        "grains under stiff loads (contact.complementarity.load_mass_scaling, default; "
        "docs/experiments/triaxial.md)",
    )
    tie_length: float | None = Field(
        default=None, gt=0,
        description="height of the rings of tied membrane ends above and below the platens [m]; "
        "default one mean grain diameter",
    )
    control: str = Field(
        "auto", pattern="^(auto|velocity|force)$",
        description="top platen while seating and consolidating: 'velocity' servo (soft grains), "
        "'force' (a free plate under the seating stress, then σ₃ A, solved with the grains; rigid "
        "grains, on which a velocity servo reads impulses and overloads them); 'auto': by the contact law",
    )
    max_speed: float = Field(
        0.05, gt=0,
        description="largest platen speed of the velocity servo [m/s]; its gain is max_speed / σ₃ "
        "(max_speed / seating stress while seating), capped every step at A / (K dt + 2 C) from the "
        "stiffness K and dashpots C of the platen's contacts",
    )
    platen_mass: float | None = Field(
        default=None, gt=0,
        description="mass of the force-controlled top platen (a free plate while seating and "
        "consolidating: control = 'force', DEM-C's default) [kg]; default the specimen's grain mass (the "
        "total mass of the grains in the cell). A plate thousands of grain masses heavy (its load / 10 m/s², "
        "the earlier default) leaves DEM-C's solve unconverged and the plate bouncing",
    )
    seating_stress: float | None = Field(
        default=None, ge=0,
        description="during the mould stages the top platen is servoed down onto the specimen to this "
        "axial stress [Pa] (seating); default 0.05 sigma3",
    )
    ramp_time: float = Field(
        0.0, ge=0,
        description="the membrane pressure rises linearly from 0 to sigma3 over this time at the start of "
        "consolidation [s] (0: at once)",
    )

    @model_validator(mode="after")
    def _stages(self):
        if self.consolidation_stage == self.shear_stage:
            raise ValueError("consolidation_stage and shear_stage must be different stages")
        later = set(self.later_shear_stages or ())
        clash = sorted(later & {self.consolidation_stage, self.shear_stage, *self.mould_stages})
        if clash:
            raise ValueError(
                f"later_shear_stages names {clash}, which consolidation_stage, shear_stage or mould_stages "
                "name already; a stage has one role: list only the stages after shear_stage"
            )
        if self.tie_length is not None and self.tie_length >= 0.5 * self.height:
            raise ValueError(
                f"tie_length = {self.tie_length!r} m must be below half the height "
                f"({0.5 * self.height!r} m): the rings stand on the platens, about one grain diameter "
                "high (the default)"
            )
        return self


class TriaxialCell(Boundary):
    """See the module docstring."""

    Params = TriaxialParams

    def __init__(self, name: str, params: BoundaryParams) -> None:
        super().__init__(name, params)
        self.phase = "off"
        self._stage_t0 = 0.0
        self.force_control = False  # set per stage by on_stage
        self._seated = False
        self._size = None
        self.h0 = self.v0 = None
        self._cells: tuple | None = None
        self._membrane_force = np.zeros(3)
        self._lateral_area = 0.0
        self._volume = math.nan
        self._radius = math.nan
        self.loop_gain = 0.0  # the velocity servo's uncapped loop gain, last step (servo_gain)

    # ------------------------------------------------------------------ building, stages
    def build(self, sim: Any) -> None:
        p = self.params
        c = np.asarray(p.base_center, dtype=float)
        self.axis_xy = c[:2].copy()
        self.z0 = float(c[2])
        self.bottom = self.add_wall(sim, shapes.Plane(c, (0, 0, 1)), "bottom")
        self.motion = Controlled()
        top = shapes.Plane(c + (0, 0, p.height), (0, 0, -1))
        self.top = self.add_wall(sim, top, "top", motion=self.motion)
        mould = shapes.Cylinder(c, (0, 0, 1), p.radius)
        self.mould = self.add_wall(sim, mould, "mould") if p.mould_stages else None
        self.rings: tuple = ()
        if p.membrane_ends == "tied":  # sized when the membrane starts (one mean diameter by default)
            length = p.tie_length or 0.1 * p.radius
            low = self.add_wall(sim, shapes.CylinderTube(c, (0, 0, 1), p.radius, length), "tie_bottom")
            tube = shapes.CylinderTube(c + (0, 0, p.height - length), (0, 0, 1), p.radius, length)
            high = self.add_wall(sim, tube, "tie_top", motion=Follow(self.top))
            self.rings = (low, high)
        self._comm = sim.comm

    @classmethod
    def stage_roles(cls, params: BaseModel, stages: Sequence[str]) -> list[str | None]:
        """``"mould"``, ``"consolidate"``, ``"shear"`` in the stages the cell holds the specimen,
        None where it is off or idle (a stage none of its role keys names: the platens stand, but
        nothing confines the specimen)."""
        p = params
        shear = {p.shear_stage, *(p.later_shear_stages or ())}
        out: list[str | None] = []
        for s in stages:
            if not listed(p, s):
                out.append(None)
            elif s == p.consolidation_stage:
                out.append("consolidate")
            elif s in shear:
                out.append("shear")
            elif s in p.mould_stages:
                out.append("mould")
            else:
                out.append(None)
        return out

    @classmethod
    def loading(cls, name: str, params: BaseModel, facts: SceneFacts) -> list[Loading]:
        """The platen's servo (up to ``max_speed``) in the mould stages and the consolidation; σ₃
        from the consolidation on; the shear at ``strain_rate`` (the platen at ``strain_rate`` ×
        ``height``), whose axial strain ``eps_a`` grows from 0 in ``shear_stage``."""
        p = params
        sigma3 = {"stress": p.sigma3, "stress_from": f"boundaries.{name}.sigma3"}
        later = tuple(p.later_shear_stages or ())
        speed = {"speed": p.strain_rate * p.height, "speed_from": f"boundaries.{name}.strain_rate × height"}
        out = [
            Loading(stages=(*p.mould_stages, p.consolidation_stage), speed=p.max_speed,
                    speed_from=f"boundaries.{name}.max_speed (servo)"),
            Loading(stages=(p.consolidation_stage,), **sigma3),
            Loading(stages=(p.shear_stage,), **sigma3, **speed, rate_key="strain_rate", rate=p.strain_rate,
                    shear_rate=p.strain_rate,
                    rate_how="I = ε̇ d sqrt(ρ/σ₃) (the boundary's own 'inertial' at the start of the shear)",
                    ends={"eps_a": (p.strain_rate, 0.0)}),
        ]  # fmt: skip
        if later:
            out.append(Loading(stages=later, **sigma3, **speed))
        return out

    @classmethod
    def extent(cls, params: BaseModel) -> Extent:
        """The mould: ``radius`` around the axis, ``height`` above ``base_center``."""
        p = params
        x, y, z = (float(c) for c in p.base_center)
        r = float(p.radius)
        return Extent(lo=(x - r, y - r, z), hi=(x + r, y + r, z + p.height), area=math.pi * r * r)

    @classmethod
    def sample_size(cls, name: str, params: BaseModel, facts: SceneFacts) -> SampleSize:
        """ASTM D7181 / D4767's diameter and slenderness, and DEM practice's grains across (the
        height estimated as the packed height)."""
        dmax, dmean = facts.d_max, facts.d_mean
        diameter = 2 * params.radius
        dd = max(SIZE_DIAMETER[0] * dmax, SIZE_DIAMETER_DEM[0] * dmean)
        n_min = facts.packing_fraction * math.pi / 4 * dd**2 * SIZE_SLENDERNESS[0] * dd / facts.grain_volume
        return SampleSize("triaxial", (
            SizeCheck("diameter / d_max", diameter / dmax, *SIZE_DIAMETER),
            SizeCheck("diameter / d_mean", diameter / dmean, *SIZE_DIAMETER_DEM),
            SizeCheck("height / diameter (packed, estimated)", facts.packed_height / diameter,
                      *SIZE_SLENDERNESS),
        ), n_min)  # fmt: skip

    @classmethod
    def stage_remedies(cls, params: BaseModel, stage: str) -> list[tuple[str, Any, str]]:
        """Shear on in ``stage`` (``later_shear_stages``) or switch the cell off (``off_stages``)."""
        later = [*(params.later_shear_stages or []), stage]
        off = [*(params.off_stages or []), stage]
        return [
            ("later_shear_stages", later, "the shearing goes on at strain_rate, strains counted from the "
             f"start of '{params.shear_stage}'"),
            ("off_stages", off, "the cell is off: platens, membrane and servo"),
        ]  # fmt: skip

    def _shear_stages(self) -> tuple[str, ...]:
        return (self.params.shear_stage, *(self.params.later_shear_stages or ()))

    def on_stage(self, sim: Any, stage: str) -> None:
        p = self.params
        resumed = getattr(self, "_restored", None)
        self._restored = None
        carried = None  # a later shear stage after a checkpoint at the end of a shear stage: its strains
        if resumed is not None and resumed.get("stage") != stage:
            if resumed.get("stage") in self._shear_stages():
                carried = resumed
            resumed = None  # the checkpoint was taken at the end of an earlier stage
        self._size = None
        self._grid = tuple(resumed["grid"]) if resumed is not None and resumed.get("grid") else None
        self.active = listed(p, stage)
        for wall in (self.bottom, self.top):
            sim.set_wall_active(wall.name, self.active)
        if self.mould is not None:
            sim.set_wall_active(self.mould.name, self.active and stage in p.mould_stages)
        membrane = self.active and stage in (p.consolidation_stage, *self._shear_stages())
        for ring in self.rings:
            sim.set_wall_active(ring.name, membrane)
        if membrane and self.rings:
            self._tie(sim)
        if not self.active:
            self.phase = "off"
            if isinstance(self.top.motion, RigidBody):  # a free top plate stays put while the cell is off
                self.top.motion.hold()
            return
        control = p.control
        if control == "auto":
            control = "force" if sim.law.rigid else "velocity"
        self.force_control = control == "force"
        self._seated = bool(resumed.get("seated", False)) if resumed is not None else False
        if stage == p.consolidation_stage:
            self.phase = "consolidate"
            if self.force_control:
                area = math.pi * p.radius**2
                body = RigidBody(mass=self._platen_mass(sim), force=(0.0, 0.0, -p.sigma3 * area),
                                 fixed_translation="xy")  # fmt: skip
                if resumed is not None and "body_velocity" in resumed:
                    body.restore({"velocity": np.array(resumed["body_velocity"]),
                                  "angular_velocity": np.zeros(3)})  # fmt: skip
                sim.set_wall_motion(self.top.name, body)
            else:
                self.motion = Controlled()
                sim.set_wall_motion(self.top.name, self.motion)
        elif stage in self._shear_stages():
            self.phase = "shear"
            self.motion = Controlled()
            sim.set_wall_motion(self.top.name, self.motion)
            if stage == p.shear_stage:
                self.h0 = self.v0 = None  # taken at the first step of shearing
            elif carried is not None:  # a later shear stage, resumed: the strains' references
                self.h0, self.v0 = carried.get("h0"), carried.get("v0")
            # (a later shear stage in the same run keeps them)
        else:
            self.phase = "prepare"
            if self.force_control and self._seated:  # resumed after the plate came down
                self._seat_body(sim, resumed)
            else:
                self.motion = Controlled()
                sim.set_wall_motion(self.top.name, self.motion)
        self._stage_t0 = sim.time
        if resumed is not None:  # continue the stage where the checkpoint left it
            self._stage_t0 = resumed["stage_t0"]
            self.h0, self.v0 = resumed["h0"], resumed["v0"]
        self._stage = stage

    def _tie(self, sim: Any) -> None:
        """Size the tied ends' rings (``tie_length``, default one mean diameter) and stand the top
        one on the top platen, which it follows from then on."""
        length = self.params.tie_length or self._mean_diameter(sim)
        low, high = self.rings
        for ring in self.rings:
            if ring.sizes["length"] != length:
                ring.resize("length", length)
        # the top ring spans [h − L, h]: its base is L below the platen, wherever the platen stands
        # (from the built poses alone, so a resumed stage finds the same bits)
        delta = np.array([0.0, 0.0, self.top.shape.reference_point[2] - length - high.shape.base_center[2]])
        high.motion = Follow(self.top, delta)
        high.set_offset(self.top.offset + delta)
        sim.set_wall_motion(high.name, high.motion)

    def _platen_mass(self, sim: Any) -> float:
        """The free plate's mass: ``platen_mass``, or the grains' total mass (an exact sum:
        the same on any rank count and after a resume). Collective.

        Why not heavier: DEM-C solves the plate with the grains, and a plate of N grain masses
        makes the problem's mass ratio N. With the earlier default (load / 10 m/s², about 6,000 grain
        masses when seating 300 grains at 2 kPa; 80,000 consolidating the reduced deck at 100 kPa)
        APGD stopped at its cap far from the solution and the plate bounced: the seating load read
        10-14,000 Pa in peaks and 1,375 Pa on average for a target of 2,000. With the grains' mass
        (300 grain masses) it reads 2,008 Pa (tests/test_triaxial.py)."""
        if self.params.platen_mass is not None:
            return float(self.params.platen_mass)
        p, n, live = self._own(sim)
        total = sim.particle_sum(p.mass[:n][live])
        return total if total > 0.0 else 1.0

    def _seat_body(self, sim: Any, resumed: dict | None = None) -> None:
        """Force control while seating: the top platen becomes a free plate (mass: ``platen_mass``)
        pressed down by the seating stress over the mould's cross-section, at rest unless
        resumed."""
        load = self._seat_stress() * math.pi * self.params.radius**2
        body = RigidBody(mass=self._platen_mass(sim), force=(0.0, 0.0, -load), fixed_translation="xy")
        if resumed is not None and "body_velocity" in resumed:
            body.restore({"velocity": np.array(resumed["body_velocity"]), "angular_velocity": np.zeros(3)})
        sim.set_wall_motion(self.top.name, body)

    def after_step(self, sim: Any) -> None:
        # force control while seating: the platen comes down at max_speed until the grains push it,
        # then it is a free plate under the seating load (from the next step on)
        if self.phase == "prepare" and self.force_control and not self._seated and self.mould is not None:
            if self.mould.active and float(self.top.force[2]) > 0.0:  # collective
                self._seated = True
                self._seat_body(sim)

    def state(self) -> dict[str, Any]:
        """What a resumed stage needs: the stage, its start time (pressure ramp), the height and
        volume at the start of shearing (strain references), a load-controlled plate's velocity, and
        the membrane's last geometry (the next step's platen load and servo read its area before the
        membrane is found again)."""
        out = {"stage": getattr(self, "_stage", None), "stage_t0": self._stage_t0, "h0": self.h0,
               "v0": self.v0, "seated": self._seated,
               "grid": list(self._grid) if self._grid is not None else None,
               "geometry": [self._volume, self._lateral_area, self._radius]}  # fmt: skip
        if isinstance(self.top.motion, RigidBody):
            out["body_velocity"] = self.top.motion.velocity_now.tolist()
        return out

    def restore(self, state: dict[str, Any]) -> None:
        self._restored = dict(state) if state else None
        if state and state.get("geometry") is not None:  # whichever stage the checkpoint ended
            self._volume, self._lateral_area, self._radius = (float(v) for v in state["geometry"])

    # ------------------------------------------------------------------ geometry
    def height(self) -> float:
        return float(self.top.reference_point[2] - self.bottom.reference_point[2])

    def _own(self, sim):
        p = sim.particles
        n = p.n_owned
        live = p.motion[:n] != 3  # not removed
        return p, n, live

    # ------------------------------------------------------------------ hooks
    def _area(self) -> float:
        """Current cross-section: the membrane's enclosed volume / height (the mould's before)."""
        vol = self._volume
        return vol / self.height() if vol == vol else math.pi * self.params.radius**2

    def _tied(self) -> bool:
        """True while tied membrane ends hold the specimen (their rings stand on the platens)."""
        return bool(self.rings) and self.rings[0].active

    def _cap_load(self) -> float:
        """The axial force the grains exert on the top cap [N]: the top platen's, plus its ring's
        with tied ends (the ring is fixed to the platen, as a laboratory cap's side is; its rim
        carries part of the axial load once the specimen barrels below it). Collective."""
        force = float(self.top.force[2])
        if self._tied():
            force += float(self.rings[1].force[2])
        return force

    def _sigma1(self, force: float, sigma3: float, area: float) -> float:
        """The axial stress σ₁ read from the top cap's force ``force``, as a laboratory reads it.

        Tied ends (the membrane sealed to caps of radius R): the load cell measures the deviator
        load P = F − σ₃ π R² (the cell pressure presses on the cap), spread over the specimen's
        current mean cross-section A = V/H (the volume-corrected area of ASTM D7181), so
        σ₁ = σ₃ + (F − σ₃ π R²) / A; for a membrane that meets the caps at R this is, by
        equilibrium, the mean axial stress of a cylinder of section A. Free ends (no cap: the
        membrane meets infinite platens wherever the end grains stand): σ₁ = F / A."""
        if self._tied():
            return sigma3 + (force - sigma3 * math.pi * self.params.radius**2) / area
        return force / area

    def _servo(self, sim: Any, target: float, area: float, scale: float, sigma3: float = 0.0) -> None:
        """Top platen velocity from the axial stress (grains push it up): proportional, with the
        gain max_speed / ``scale`` (full speed while nothing touches it), capped every step so that
        the loop gain gain (K dt + 2 C) / area of the platen's contacts stays ≤ 1
        (:func:`pdem.contact.stability.servo_gain`; :attr:`loop_gain` keeps the uncapped one).
        ``sigma3``: the cell pressure now, for σ₁ as read with tied ends (:meth:`_sigma1`)."""
        sigma1 = self._sigma1(self._cap_load(), sigma3, area)
        vmax = self.params.max_speed
        gain, self.loop_gain = servo_gain(sim, self.top, vmax / max(scale, 1e-300), area)
        v = float(np.clip(gain * (target - sigma1), -vmax, vmax))
        self.motion.velocity = np.array([0.0, 0.0, -v])

    def before_step(self, sim: Any) -> None:
        # consolidation is isotropic: the platen's target follows the membrane's pressure ramp (a
        # platen driven to the full σ₃ at once overloads the few chains that first carry it)
        if self.phase == "consolidate" and isinstance(self.top.motion, RigidBody):
            # (tied ends: a deviator load of nil, F = σ₃ π R² on the cap; free ends: σ₃ over the section)
            area = math.pi * self.params.radius**2 if self._tied() else self._area()
            self.top.motion.force = (0.0, 0.0, -self.pressure(sim) * area)
        elif self.phase == "prepare" and self.mould is not None and self.mould.active:
            seat = self._seat_stress()
            if not self.force_control:
                self._servo(sim, seat, math.pi * self.params.radius**2, seat)
            elif not self._seated:  # force control: come down at full speed until the grains are met
                self.motion.velocity = np.array([0.0, 0.0, -self.params.max_speed])
        elif self.phase == "consolidate" and isinstance(self.top.motion, Controlled):
            pressure = self.pressure(sim)
            self._servo(sim, max(pressure, self._seat_stress()), self._area(), self.params.sigma3, pressure)
        elif self.phase == "shear":
            if self.h0 is None:
                self.h0 = self.height()
            self.motion.velocity = np.array([0.0, 0.0, -self.params.strain_rate * self.h0])

    def apply_forces(self, sim: Any) -> None:
        if self.phase not in ("consolidate", "shear"):
            return
        self._membrane(sim, apply=True)
        if self.phase == "shear" and self.v0 is None:  # on the shear stage's own membrane grid
            self.v0 = self._volume

    def _membrane(self, sim: Any, apply: bool) -> tuple[float, float, float]:
        """Find the outermost grain of every (θ, z) cell (globally) and, with ``apply``, load it
        (owned grains). Returns the (volume, lateral area, mean radius) of the cells."""
        p, n, live = self._own(sim)
        x, r, ids = p.x[:n][live], p.r[:n][live], p.id[:n][live]
        rows = np.flatnonzero(live)
        h = self.height()
        size = self.params.cell_size
        if size is None:  # one mean diameter (exact sums: the same on any rank count), once a stage
            size = self._mean_diameter(sim)
        dx = x[:, 0] - self.axis_xy[0]
        dy = x[:, 1] - self.axis_xy[1]
        rho = np.hypot(dx, dy)
        # cells of about one `size` around the outermost radius (an exact global max), counted at the
        # stage's first step and kept (stored in checkpoints), or counted anew every step
        if self._grid is None or self.params.membrane_grid == "step":  # alike on every rank
            r_out = all_max(sim.comm, float(np.max(rho + r)) if r.size else 0.0)
            nz, nt = max(int(round(h / size)), 1), max(int(round(2 * math.pi * r_out / size)), 6)
            if apply:  # (a measurement before the stage's first step does not fix the grid)
                self._grid = (nz, nt)
        else:
            nz, nt = self._grid
        theta = np.arctan2(dy, dx)
        zrel = x[:, 2] - self.bottom.reference_point[2]
        b = self.params.membrane_smoothing * 0.5 * size
        if b > 0.0:
            return self._smooth_membrane(sim, apply, b, size, nz, nt, h, theta, zrel, rho, r, rows, dx, dy)
        kt = np.minimum(((theta + math.pi) / (2 * math.pi) * nt).astype(np.int64), nt - 1)
        kz = np.clip((zrel / h * nz).astype(np.int64), 0, nz - 1)
        cell = kz * nt + kt
        val = rho + r
        order = np.lexsort((ids, -val, cell))
        first = np.ones(order.size, dtype=bool)
        first[1:] = cell[order][1:] != cell[order][:-1]
        win = order[first]
        local = (cell[win], val[win], ids[win])
        if sim.comm.size > 1:  # the outermost grain of a cell may be on another rank: global max
            parts = sim.comm.allgather(local)
            cells = np.concatenate([q[0] for q in parts])
            vals = np.concatenate([q[1] for q in parts])
            wids = np.concatenate([q[2] for q in parts])
            o = np.lexsort((wids, -vals, cells))
            f1 = np.ones(o.size, dtype=bool)
            f1[1:] = cells[o][1:] != cells[o][:-1]
            gcell, gval, gid = cells[o][f1], vals[o][f1], wids[o][f1]
        else:
            gcell, gval, gid = local
            o = np.argsort(gcell, kind="stable")
            gcell, gval, gid = gcell[o], gval[o], gid[o]
        R = np.full(nz * nt, np.nan)
        R[gcell] = gval
        dz = h / nz
        dth = 2 * math.pi / nt
        filled = np.isfinite(R)
        geometry = (
            float(0.5 * np.sum(R[filled] ** 2) * dth * dz),  # enclosed volume
            float(np.sum(R[filled]) * dth * dz),  # lateral area
            float(np.mean(R[filled])) if filled.any() else math.nan,  # mean radius
        )
        if not apply:  # measuring: leave the state the dynamics read untouched
            return geometry
        self._volume, self._lateral_area, self._radius = geometry
        self._cells = (nz, nt, int(filled.sum()))
        # the global winners this rank owns, loaded with σ3 × their patch along the inward normal
        owner = np.full(nz * nt, -1, dtype=np.int64)
        owner[gcell] = gid
        w = win[owner[cell[win]] == ids[win]]
        share = np.ones(w.size)
        k = cell[w]
        rhat = np.stack([dx[w], dy[w], np.zeros(w.size)], axis=1) / np.maximum(rho[w], 1e-300)[:, None]
        f = -self.pressure(sim) * (share * R[k] * dth * dz)[:, None] * rhat
        p.f[rows[w]] += f
        # kept for the measurements: the load, its moment (lever r ρ̂) and radial virial per grain
        lever = r[w][:, None] * rhat
        vir = np.einsum("ij,ij->i", (np.stack([dx[w], dy[w], np.zeros(w.size)], axis=1) + lever), f)
        self._applied = (f, np.einsum("ka,kb->kab", lever, f).reshape(-1, 9), vir)
        self._applied_volume = self._volume
        self._axial_virial = np.zeros(0)  # radial loads only
        return geometry

    def _smooth_membrane(self, sim, apply, b, size, nz, nt, h, theta, zrel, rho, r, rows, dx, dy):
        """The membrane as the gradient of σ₃ V, V = Σ_c ½ R_c² Δθ Δz over the (θ, z) cells.

        R_c, the membrane's radius at the centre (θ_c, z_c) of cell c, is a smooth maximum of the
        grains' caps there: a grain of outer radius s_i = ρ_i + r_i reaches s_i − d²/(2 r_i) at a
        lateral distance d (arc ρ_i Δθ and Δz; a parabolic cap of the sphere), and

            R_c = M_c + b log Σ_i exp((s_i − d_ic²/(2 r_i) − M_c) / b),   M_c = max_i (…) (exact),

        over the grains of the cell and its eight neighbours (caps more than 20 b below M_c are
        dropped: e^-20). R is smooth in every grain position, including a grain passing from one cell
        to the next, so the load F_i = −σ₃ ∂V/∂x_i does no net work over a closed path: a surface that
        changes hands does not pump energy into the specimen (a load that jumps from grain to grain
        does, in steady heating). Along the cap's slope the load has a tangential part, as a membrane
        draped over the grains pushes along its own normal. The weights of a cell sum to one
        (Σ_i ∂R_c/∂s_i = 1), so the radial load is σ₃ × the lateral area Σ R_c Δθ Δz exactly. The
        sums are exact in any order (maxima; weights in fixed point): bitwise the same on any number
        of ranks."""
        # rows of sample points from platen to platen (z = k dz): a grain near a platen then has rows
        # on both sides, as inside, and the membrane does not push the end grains axially
        nz += 1
        ncell = nz * nt
        dth, dz = 2 * math.pi / nt, h / (nz - 1)
        wrow = np.full(nz, dz)
        wrow[0] = wrow[-1] = 0.5 * dz  # trapezoids: V = ∫ ½ R² dθ dz over the height
        kz, kt = _mb.cells_of(theta, zrel, nz, nt, dth, dz)
        # the outermost surface per cell (an exact global max) and its smallest over each cell's
        # 3 × 3 neighbourhood: a grain deeper than that by the cut and a diameter (plus 2 r) reaches
        # no cell centre within the cut
        # (with two more maxima: how far a grain stands outside the specimen radially and axially)
        out_r = float(np.max(rho + r)) if r.size else 0.0
        out_z = float(np.max(np.maximum(-zrel, zrel - h))) if r.size else -math.inf
        mb = all_max_array(sim.comm, np.append(_mb.binned_max(rho + r, kz, kt, nt, ncell), [out_r, out_z]))
        out_r, out_z, mb = float(mb[-2]), float(mb[-1]), mb[:-2]
        if out_r > 2.0 * self.params.radius or out_z > size:
            self._runaway(sim, out_r, out_z, size)
        low = _mb.neighbourhood_min(mb, nz, nt)
        cut = 20.0 * b
        depth = cut + 2.0 * size
        q, cell, dtheta, ga, gw, M = _mb.caps(theta, zrel, rho, r, kz, kt, low, depth, nz, nt, dth, dz)
        M = all_max_array(sim.comm, M)
        e, zsum = _mb.weights(q, cell, M, cut, b)
        Z = all_sum_int_array(sim.comm, zsum) / _mb.FIXED
        filled = Z > 0.0
        R = np.full(ncell, np.nan)
        R[filled] = M[filled] + b * np.log(Z[filled])
        wc = np.repeat(wrow, nt)[filled]
        geometry = (
            float(0.5 * np.sum(R[filled] ** 2 * wc) * dth),
            float(np.sum(R[filled] * wc) * dth),
            float(np.mean(R[filled])) if filled.any() else math.nan,
        )
        if not apply:
            return geometry
        self._volume, self._lateral_area, self._radius = geometry
        self._cells = (nz, nt, int(filled.sum()))
        # loads at σ₃ = 1
        want_k = sim.load_stiffness_wanted  # (DEM-P does not use it: not computed)
        f, mom, vir, kst = _mb.loads(e, cell, dtheta, ga, gw, R, Z, r, dx, dy, rho, dth, wrow, nt, b, want_k)
        if self.params.membrane_load == "radial":
            # each grain keeps the radial part of its load, acting through its centre at ρ + r
            u = np.stack([dx, dy], axis=1) / np.maximum(rho, 1e-300)[:, None]
            fr = np.einsum("ij,ij->i", f[:, :2], u)
            f = np.zeros_like(f)
            f[:, :2] = fr[:, None] * u
            mom = np.zeros_like(mom)
            mom[:, :2, :2] = (r * fr)[:, None, None] * np.einsum("ia,ib->iab", u, u)
            vir = (rho + r) * fr
        loaded = np.flatnonzero(np.any(e > 0.0, axis=1))
        # the pressure the grains feel is the loads' radial virial over 2V, slightly less than the
        # pressure on V (the smooth maximum stands a little outside the grains); scale to σ₃ there
        unit = -sim.exact_sum(vir[loaded]) / (2.0 * self._volume)
        scale = self.pressure(sim) / unit if unit > 0.0 else 0.0
        f *= scale
        mom *= scale
        vir *= scale
        sim.particles.f[rows[loaded]] += f[loaded]
        # how fast each grain's load changes as it moves (DEM-C scales the masses of the grains whose
        # load is too stiff for its step: Simulation.add_load_stiffness)
        if want_k:
            sim.add_load_stiffness(rows[loaded], kst[loaded] * scale)
        self._applied = (f[loaded], mom[loaded].reshape(-1, 9), vir[loaded])
        self._applied_volume = self._volume
        # the loads' axial virial Σ (z + lever_z) f_z (z from the bottom platen): the membrane's part
        # of the specimen's mean σ_zz (it pushes along its normal, which tilts on a barrel)
        self._axial_virial = zrel[loaded] * f[loaded, 2] + mom[loaded, 2, 2]
        return geometry

    def _runaway(self, sim: Any, out_r: float, out_z: float, size: float) -> None:
        """A grain left the specimen (collective: every rank sees the same maxima and raises)."""
        p = sim.particles
        n = p.n_owned
        vmax = all_max(sim.comm, float(np.max(np.linalg.norm(p.v[:n], axis=1))) if n else 0.0)
        where = (
            f"{out_r:.4g} m from the axis (twice the specimen radius {self.params.radius:g} m)"
            if out_r > 2.0 * self.params.radius
            else f"{out_z:.4g} m beyond a platen (more than a mean diameter, {size:.3g} m)"
        )
        dem_c = getattr(sim.law, "kind", "") == "complementarity"
        remedy = (
            "with DEM-C keep contact.complementarity.load_mass_scaling = true (the membrane's loads are "
            "too stiff for the step without it) or give a smaller run.dt"
            if dem_c else "reduce run.dt (or run.dt_fraction)"
        )
        raise InstabilityError(
            f"boundary '{self.name}': a grain left the triaxial specimen at step {sim.step_count} "
            f"(t = {sim.time:.6g} s): it stands {where}; the fastest grain moves at {vmax:.3g} m/s. "
            f"The run went unstable; {remedy}"
        )

    # ------------------------------------------------------------------ measuring
    def measurements(self, sim: Any) -> dict[str, float]:
        if self.phase in ("consolidate", "shear"):
            vol, _area, radius = self._membrane(sim, apply=False)
        else:
            vol, radius = self._volume, self._radius
        h = self.height()
        area = vol / h if vol == vol and h > 0 else math.pi * self.params.radius**2
        # realised σ3: the pressure the membrane forces exert (their radial virial, exact over ranks)
        sigma3 = self._membrane_pressure(sim)
        cap = self._cap_load()
        sigma1 = self._sigma1(cap, sigma3 if sigma3 == sigma3 else self.pressure(sim), area)
        # the specimen's mean σ_zz from its boundary loads (equilibrium): the top platen at h, the
        # membrane's loads at their points; equals σ1 for a straight specimen. Tied ends: the rings'
        # axial loads, taken at their rims (h − L and L), where they carry them
        axial = getattr(self, "_axial_virial", np.zeros(0))
        vol_applied = getattr(self, "_applied_volume", math.nan)
        rings_zz = 0.0
        if self._tied():
            low, high = self.rings
            length = high.sizes["length"]
            rings_zz = float(high.force[2]) * (h - length) + float(low.force[2]) * length
        szz_boundary = (
            (float(self.top.force[2]) * h + rings_zz - sim.exact_sum(axial)) / vol_applied
            if self.phase in ("consolidate", "shear") and vol_applied > 0 else sigma1
        )
        out = {
            "sigma1": sigma1,
            "sigma3": sigma3,
            "szz_boundary": szz_boundary,
            "q": sigma1 - sigma3,
            "p": (sigma1 + 2 * sigma3) / 3,
            "height": h,
            "radius": radius,
            "volume": vol,
            "eps_a": (self.h0 - h) / self.h0 if self.h0 else 0.0,
            "eps_v": (self.v0 - vol) / self.v0 if self.v0 else 0.0,
        }
        out.update(self._love_weber(sim, vol))
        if self.active:
            out["end_overhang"] = self._end_overhang(sim)
        if self._tied():  # the top ring's share of the cap's axial load (its rim)
            out["ring_axial_share"] = float(self.rings[1].force[2]) / cap if cap > 0 else math.nan
        # inertial number of the loading, I = ε̇ d sqrt(ρ/p) (grain density from their mass and volume)
        # (a column of every shear row, also the first after a resume: a series keeps its columns)
        if self.phase == "shear":
            prt = sim.particles
            n = prt.n_owned
            rho = sim.exact_sum(prt.mass[:n]) / sim.exact_sum(4.0 / 3.0 * math.pi * prt.r[:n] ** 3)
            d = self._mean_diameter(sim)
            pm = out["p"]
            out["inertial"] = self.params.strain_rate * d * math.sqrt(rho / pm) if pm > 0 else math.nan
        return out

    def _end_overhang(self, sim: Any) -> float:
        """How far the end grains' centres stand beyond the platens' edge plus their own radius,
        max(ρ − r − R) over the grains whose centres lie within one mean diameter of a platen [m]:
        positive when an end grain's centre is further out than the platen radius plus its radius,
        i.e. when the grain stands past the platen's edge, which a laboratory cell does not allow;
        −inf with no end grain (exact maximum over ranks)."""
        p, n, live = self._own(sim)
        x, r = p.x[:n][live], p.r[:n][live]
        d = self._mean_diameter(sim)
        zb, zt = self.bottom.reference_point[2], self.top.reference_point[2]
        ends = (x[:, 2] - zb < d) | (zt - x[:, 2] < d)
        rho = np.hypot(x[ends, 0] - self.axis_xy[0], x[ends, 1] - self.axis_xy[1])
        local = float(np.max(rho - r[ends])) - self.params.radius if rho.size else -math.inf
        return all_max(sim.comm, local)

    def _mean_diameter(self, sim) -> float:
        """The mean diameter of the grains in the cell (exact sums: the same on any rank count),
        taken once a stage (and again after a resume)."""
        if self._size is None:
            p, n, live = self._own(sim)
            r = p.r[:n][live]
            self._size = 2.0 * sim.exact_sum(r) / max(sim.count(r.size), 1)
        return self._size

    def summary(self, series: dict[str, np.ndarray]) -> dict[str, float]:
        """Peak deviator and where, final volumetric strain, servo accuracy of σ₃ and of σ₁ at the end
        of consolidation, agreement of the boundary and Love–Weber stresses during shearing."""
        key = lambda k: series.get(f"{self.name}.{k}")  # noqa: E731
        ea, q, s1, s3 = key("eps_a"), key("q"), key("sigma1"), key("sigma3")
        if ea is None or q is None or len(ea) < 3:
            return {}
        p = self.params
        # each value from the rows of its own stage (the series' stage column): a stage after the
        # shearing, with the cell off or idle, must not count as shearing nor as consolidation
        in_shear = stage_rows(series, self._shear_stages(), len(ea))
        shear = ea > 0 if in_shear is None else in_shear & (ea > 0)
        consolidating = stage_rows(series, p.consolidation_stage, len(ea))
        out: dict[str, float] = {}
        if shear.any():
            k = int(np.nanargmax(np.where(shear, q, -np.inf)))
            out["q_peak"] = float(q[k])
            out["eps_a_at_peak"] = float(ea[k])
            out["q_over_p_peak"] = float(q[k] / key("p")[k])
            out["eps_a_final"] = float(ea[shear][-1])
            out["eps_v_final"] = float(key("eps_v")[shear][-1])
            err3 = np.abs(s3[shear] / self.params.sigma3 - 1)
            out["sigma3_error_mean"] = float(np.nanmean(err3))
            out["sigma3_error_p95"] = float(np.nanpercentile(err3, 95))
            lz, lr = key("lw_szz"), key("lw_srr")
            if lz is not None:
                # the grains' own stress against the boundary's: the realised σ₁ and σ₃
                e1, e3 = _rel_error(lz[shear], s1[shear]), _rel_error(lr[shear], s3[shear])
                out["lw_sigma1_error_mean"], out["lw_sigma1_error_p95"] = _error_stats(e1)
                out["lw_sigma3_error_mean"], out["lw_sigma3_error_p95"] = _error_stats(e3)
                sb = key("szz_boundary")
                if sb is not None:  # against the full axial boundary load (platen + membrane)
                    eb = _rel_error(lz[shear], sb[shear])
                    out["lw_szz_boundary_error_mean"], out["lw_szz_boundary_error_p95"] = _error_stats(eb)
            over = key("end_overhang")
            if over is not None and np.isfinite(over[shear]).any():  # > 0: an end grain past the platen
                out["end_overhang_max"] = float(np.nanmax(over[shear]))
            ring = key("ring_srr")
            if ring is not None and np.isfinite(ring[shear]).any():  # tied ends: the rings' radial share
                share = ring[shear] / s3[shear]
                out["ring_srr_share_mean"] = float(np.nanmean(share))
                out["ring_srr_share_max"] = float(np.nanmax(share))
            axial = key("ring_axial_share")
            if axial is not None and np.isfinite(axial[shear]).any():  # tied ends: the top ring's rim
                out["ring_axial_share_mean"] = float(np.nanmean(axial[shear]))
                out["ring_axial_share_max"] = float(np.nanmax(axial[shear]))
            inert = key("inertial")
            if inert is not None and np.isfinite(inert[shear]).any():
                out["inertial_number_max"] = float(np.nanmax(inert[shear]))
        before = (~shear if consolidating is None else consolidating) & np.isfinite(s1)
        if before.any():
            out["sigma1_end_of_consolidation"] = float(s1[before][-1])
        return out

    def _seat_stress(self) -> float:
        seat = self.params.seating_stress
        return 0.05 * self.params.sigma3 if seat is None else seat

    def pressure(self, sim: Any) -> float:
        """The membrane pressure now: σ₃, ramped over ``ramp_time`` at the start of consolidation."""
        ramp = self.params.ramp_time
        if self.phase == "consolidate" and ramp > 0:
            return self.params.sigma3 * min(1.0, (sim.time - self._stage_t0) / ramp)
        return self.params.sigma3

    def _membrane_pressure(self, sim) -> float:
        """The pressure the membrane forces of the last evaluation exert: −Σ (ρ + lever)·F / (2 V),
        the radial virial (ρ and F horizontal) over twice the enclosed volume (a uniform pressure p
        on a cylinder's side gives −p · 2V); exact over ranks."""
        _f, _mom, vir = getattr(self, "_applied", (None, None, np.zeros(0)))
        vol = getattr(self, "_applied_volume", math.nan)
        return -sim.exact_sum(vir) / (2.0 * vol) if vol > 0 else math.nan

    def _love_weber(self, sim: Any, vol: float) -> dict[str, float]:
        """Average stress of the grains, compression positive: −(1/V) Σ lever ⊗ force over every
        force on every grain (pairs: −l ⊗ f with the branch vector; platens; rings; membrane). Each
        rank adds the terms of its own contacts and grains; the sums are exact, so the result is the
        same on any rank count and no rank holds every contact (collective)."""
        if not (vol == vol and vol > 0):
            return {"lw_szz": math.nan, "lw_srr": math.nan}
        c = sim.own_contacts()
        levers, forces = [c["branch"]], [-c["force"]]  # Σ (x_i − x_j) ⊗ f_j
        wc = sim.own_wall_contacts()
        names = list(sim.walls)
        for wall, sign in ((self.bottom, -1.0), (self.top, 1.0)):
            sel = wc["wall"] == names.index(wall.name)
            lever = np.zeros((int(sel.sum()), 3))
            lever[:, 2] = sign * (wc["r"][sel] - 0.5 * wc["overlap"][sel])
            levers.append(lever)
            forces.append(-wc["force"][sel])
        radial = np.zeros(0)  # the grains' outward push on the rings [N], one term per contact
        for ring in self.rings:  # tied ends: the lever points to the nearest point of the ring
            sel = wc["wall"] == names.index(ring.name)
            if not ring.active:
                continue
            xc = wc["x"][sel]
            d = xc[:, :2] - self.axis_xy
            rho = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-300)
            zb = ring.shape.base_center[2] + ring.offset[2]
            near = np.empty_like(xc)
            near[:, :2] = self.axis_xy + d * (ring.sizes["radius"] / rho)[:, None]
            near[:, 2] = np.clip(xc[:, 2], zb, zb + ring.sizes["length"])
            n = near - xc
            n /= np.maximum(np.linalg.norm(n, axis=1), 1e-300)[:, None]
            levers.append(n * (wc["r"][sel] - 0.5 * wc["overlap"][sel])[:, None])
            forces.append(-wc["force"][sel])
            push = np.einsum("ka,ka->k", wc["force"][sel][:, :2], d / rho[:, None])
            radial = np.concatenate([radial, push])
        lever, force = np.concatenate(levers), np.concatenate(forces)
        terms = np.einsum("ka,kb->kab", lever, force).reshape(-1, 9)
        # membrane forces act on owned grains: their lever ⊗ force terms, one row per grain
        _f, membrane, _vir = getattr(self, "_applied", (None, np.zeros((0, 9)), None))
        membrane = np.asarray(membrane, dtype=float).reshape(-1, 9)
        col = np.zeros((len(terms) + len(membrane) + len(radial), 10))  # 9 components, the rings' push
        col[: len(terms), :9] = terms
        col[len(terms) : len(terms) + len(membrane), :9] = membrane
        col[len(terms) + len(membrane) :, 9] = radial
        total = sim.exact_column_sums(col)
        sigma = -total[:9].reshape(3, 3) / vol
        out = {"lw_szz": float(sigma[2, 2]), "lw_srr": float(0.5 * (sigma[0, 0] + sigma[1, 1]))}
        if self._tied():
            # the rings' share of the grains' mean radial stress: their radial virial R Σ f_out over 2V
            # (the membrane's is σ₃ 2V), so that lw_srr ≈ σ₃ + ring_srr
            out["ring_srr"] = self.params.radius * float(total[9]) / (2.0 * vol)
        return out


def _rel_error(value: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """|value / ref − 1|, NaN where the reference is zero or not finite (no division warnings);
    summaries take nan-means of it."""
    out = np.full(value.shape, np.nan)
    ok = np.isfinite(ref) & (ref != 0.0)
    out[ok] = np.abs(value[ok] / ref[ok] - 1)
    return out


def _error_stats(e: np.ndarray) -> tuple[float, float]:
    """Mean and 95th percentile of the finite values (NaN, NaN if there are none)."""
    e = e[np.isfinite(e)]
    if e.size == 0:
        return math.nan, math.nan
    return float(np.mean(e)), float(np.percentile(e, 95))

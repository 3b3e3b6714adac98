"""The direct shear box (``type = "shear_box"``): a split box, a servo-controlled top plate, and the
measurements of a direct shear test (experiments.md §3).

Geometry (lengths in m; x is the shearing direction, z is up)::

            top plate (servo, σ_n)                 corner = (x0, y0, z0)
          ┌──────────────────────┐ ← moves with the upper half during shear
    ══════│    upper half        │               upper walls: z2 … z2 + upper_height
     flange    (Controlled, +x)  │               z2 = z1 + gap
          ├ ─ ─ ─ gap ─ ─ ─ ─ ─ ─┤══════         z1 = z0 + lower_height
          │    lower half        │ flange
          │    (fixed)           │
          └──────────────────────┘ floor at z0

Every wall is a finite two-sided plate (:class:`shapes.Rectangle`), so the two halves can slide past
each other. The lower half (floor, four side walls) is fixed; the upper half (four side walls) moves
along +x with one :class:`Controlled` velocity, at rest until the stage ``shear_stage`` starts and
at ``shear_speed`` from then on, until ``max_displacement``. What keeps grains in:

* **the gap** between the halves (``gap``, a fraction of a grain diameter) is narrower than any
  grain: a grain centred in it touches the edges of both plates and is pushed back (a grain whose
  diameter is not larger than the gap is an error when the consolidation starts);
* **two flanges**, horizontal plates level with the halves' rims, close the openings that shearing
  creates: a fixed one at the lower rim (z1) beyond the leading end (x0 + L … x0 + L +
  max_displacement + margin), the floor of the part of the upper half that overhangs the lower one;
  and one moving with the upper half at its lower rim (z2) behind its trailing wall, the lid over the
  strip of the lower half that the upper half uncovers. The only openings left are the gap-wide
  slots between rims, flanges and walls;
* the plates meet edge to edge (the top plate spans the upper half's footprint exactly).

The **top plate** holds the normal stress ``normal_stress`` = N / (length × width), N the vertical
load of the grains on it, from the stage ``consolidation_stage`` on (before that it stays where it
was built, out of the way of a fill). ``control = "velocity"``: a proportional servo on its vertical
velocity, v_z = −clip(gain (σ_target − σ), ±max_speed), for soft grains (DEM-P), its gain capped
every step at A / (K dt + 2 C), K and C the normal stiffness and dashpots of the plate's
contacts (:func:`pdem.contact.stability.servo_gain`: past a loop gain gain (K dt + 2 C) / A of 2 the
plate chatters; 150 beads of 2 mm at 50 Pa with max_speed = 0.3 m/s were held to 0.09 % at
dt = 5e-6 s and missed by 235 % at dt = 1e-5 s without the cap, 0.7 % with it). ``control =
"force"``: a free rigid body (:class:`RigidBody`, mass ``plate_mass``) pushed down by σ_target ×
area and held by the grains, for rigid grains (DEM-C, solved with the grains; explicit in its load
for DEM-P). ``control = "auto"`` (default) picks force with ``complementarity`` and velocity
otherwise. Either way the plate belongs to the upper half: it moves along x with it (velocity
control: the same x velocity; force control: a stiff, critically damped spring-damper on its x
position towards the upper half's, time constant 10 steps, so the lag is µN/k ≈ 1e-5 m).

Measured every series row (``NAME.key``): ``displacement`` u [m] (of the upper half); ``shear_force``
[N] the load the grains put on the upper half along −x (upper side walls, upper flange and top
plate: what the drive must push), positive when it resists; ``lower_force`` [N] the grains' load on
the lower half along +x (the same in quasi-static shear: a check); ``side_friction`` [N] the part of
``shear_force`` carried by the two upper walls parallel to x (wall friction, not sample strength);
``normal_force`` N [N]; ``normal_stress`` [Pa] = N / (length × width); ``error`` = σ/σ_target − 1;
``tau`` [Pa] = shear_force / ((length − u) × width), the corrected area (the overlap of the two
halves, the shear plane the force crosses); ``ratio`` = shear_force / N (= τ/σ_n whichever area is
used for both, so the friction ratio does not depend on that choice); ``height`` [m] of the top
plate above the floor; ``dilation`` [m] = height − height when the shear started; ``outside``: the
number of grains whose centre is outside the box (they leaked).

Summary (rows of the shear stage, u > 0): ``peak_ratio`` and ``peak_tau`` (and the displacement
where the ratio peaks), ``residual_ratio`` and ``residual_tau`` (means over the last 20 % of the
displacement), ``max_dilation``, ``final_dilation``, and the normal-stress accuracy during shear:
``mean_abs_error`` and ``p95_abs_error`` of |σ/σ_target − 1|.

Deck::

    [boundaries.box]
    type = "shear_box"
    material = "wall"               # walls (and top plate): their own friction, e.g. rigid = true
    corner = [0.0, 0.0, 0.0]
    length = 0.12
    width = 0.12
    lower_height = 0.03
    upper_height = 0.05
    gap = 0.002                     # < the smallest grain diameter
    normal_stress = 3100.0
    shear_speed = 1.0e-3
    max_displacement = 0.012
    consolidation_stage = "consolidate"
    shear_stage = "shear"

It uses only the public plugin API (:mod:`pdem.api`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pydantic import BaseModel, Field, model_validator

from pdem.api import (
    REMOVED,
    STAGE_COLUMN,
    Boundary,
    BoundaryParams,
    Controlled,
    Extent,
    Fixed,
    InputError,
    Loading,
    RigidBody,
    SampleSize,
    SceneFacts,
    SizeCheck,
    Vec3,
    listed,
    servo_gain,
    shapes,
    stage_rows,
)

__all__ = ["ShearBox", "ShearBoxParams"]

_X, _Y, _Z = np.eye(3)

#: the minimum sizes of a direct shear specimen (the advice's sample-size check): (minimum, source)
SIZE_WIDTH = (10.0, "ASTM D3080: box width ≥ 10 × the largest grain diameter")
SIZE_HEIGHT = (6.0, "ASTM D3080: initial specimen thickness ≥ 6 × the largest grain diameter")
#: thickness of the shear band, in mean grain diameters (the inertial number's shear rate v / band)
BAND_GRAINS = 10.0


class ShearBoxParams(BoundaryParams):
    """Keys of ``[boundaries.NAME]`` with ``type = "shear_box"``."""

    material: str = Field(description="material of the box walls and flanges (their friction on grains)")
    plate_material: str | None = Field(
        default=None, description="the top plate's material (default: material)"
    )
    corner: Vec3 = Field(default=(0.0, 0.0, 0.0), description="the lower half's floor corner (x0, y0, z0)")
    length: float = Field(gt=0, description="inner length along x, the shearing direction [m]")
    width: float = Field(gt=0, description="inner width along y [m]")
    lower_height: float = Field(gt=0, description="height of the lower half's walls [m]")
    upper_height: float = Field(gt=0, description="height of the upper half's walls, above the gap [m]")
    gap: float = Field(gt=0, description="gap between the halves [m]; below the smallest grain diameter")
    normal_stress: float = Field(gt=0, description="normal stress the top plate holds [Pa]")
    shear_speed: float = Field(gt=0, description="speed of the upper half along +x during shear [m/s]")
    max_displacement: float = Field(
        gt=0, description="shear displacement the flanges are built for; the upper half stops there [m]"
    )
    plate_height: float | None = Field(
        default=None, gt=0,
        description="initial height of the top plate above the floor [m]; default the upper walls' top",
    )
    control: str = Field(
        default="auto", pattern="^(auto|velocity|force)$",
        description="top plate: 'velocity' (proportional servo, soft grains), 'force' (a free plate "
        "under the target load, rigid grains) or 'auto' (force with complementarity, else velocity)",
    )
    max_speed: float = Field(default=0.05, gt=0, description="largest vertical speed of the velocity servo")
    gain: float | None = Field(
        default=None, gt=0,
        description="velocity servo gain [m/(s Pa)]; default max_speed / normal_stress; capped every step "
        "at A / (K dt + 2 C) from the stiffness K and dashpots C of the plate's contacts",
    )
    plate_mass: float | None = Field(
        default=None, gt=0, description="mass of a force-controlled plate [kg]; default load / (10 m/s²)"
    )
    consolidation_stage: str | None = Field(
        default=None, description="the top plate's servo starts with this stage (default: the first stage)"
    )
    shear_stage: str = Field(description="the upper half starts moving when this stage starts")

    @model_validator(mode="after")
    def _geometry(self):
        if self.plate_height is not None and self.plate_height <= self.lower_height + self.gap:
            raise ValueError(
                f"plate_height = {self.plate_height} must be above the gap (lower_height + gap = "
                f"{self.lower_height + self.gap})"
            )
        if self.max_displacement >= self.length:
            raise ValueError(f"max_displacement = {self.max_displacement} must be below length {self.length}")
        return self


class ShearBox(Boundary):
    """See the module docstring."""

    Params = ShearBoxParams

    @classmethod
    def loading(cls, name: str, params: BaseModel, facts: SceneFacts) -> list[Loading]:
        """The top plate's servo holds ``normal_stress`` (on the grains' weight) at up to
        ``max_speed`` from ``consolidation_stage`` on; the upper half moves at ``shear_speed`` in
        ``shear_stage``, shearing a band :data:`BAND_GRAINS` grains thick."""
        p = params
        servo = Loading(
            stages=facts.stages_from(p.consolidation_stage),
            speed=p.max_speed, speed_from=f"boundaries.{name}.max_speed (servo)",
            stress=p.normal_stress, stress_from=f"boundaries.{name}.normal_stress", on_weight=True,
        )  # fmt: skip
        shear = Loading(
            stages=(p.shear_stage,),
            speed=p.shear_speed, speed_from=f"boundaries.{name}.shear_speed",
            stress=p.normal_stress, stress_from=f"boundaries.{name}.normal_stress", on_weight=True,
            rate_key="shear_speed", rate=p.shear_speed,
            shear_rate=p.shear_speed / (BAND_GRAINS * facts.d_mean),
            rate_how=f"I = (v / {BAND_GRAINS:g} d) d sqrt(ρ/σ_n): a shear band {BAND_GRAINS:g} grains thick "
            "(the boundary's own 'inertial')",
            ends={"displacement": (p.shear_speed, 0.0)},
        )  # fmt: skip
        return [servo, shear]

    @classmethod
    def extent(cls, params: BaseModel) -> Extent:
        """The box's inside, from the floor to the top of the upper walls."""
        p = params
        lo = tuple(float(c) for c in p.corner)
        size = (p.length, p.width, p.lower_height + p.gap + p.upper_height)
        return Extent(lo=lo, hi=tuple(a + b for a, b in zip(lo, size, strict=True)), area=p.length * p.width)

    @classmethod
    def sample_size(cls, name: str, params: BaseModel, facts: SceneFacts) -> SampleSize:
        """ASTM D3080's minimum width and thickness (the thickness estimated as the packed height)."""
        p, dmax = params, facts.d_max
        width = min(p.length, p.width)
        n_min = facts.packing_fraction * (10 * dmax) ** 2 * 6 * dmax / facts.grain_volume
        return SampleSize("direct shear", (
            SizeCheck("box width / d_max", width / dmax, *SIZE_WIDTH),
            SizeCheck("sample height / d_max", facts.packed_height / dmax, *SIZE_HEIGHT),
        ), n_min)  # fmt: skip

    @classmethod
    def wall_materials(cls, params: BaseModel) -> list[str]:
        """``material`` and ``plate_material``."""
        return [m for m in (params.material, params.plate_material) if m]

    def __init__(self, name: str, params: BoundaryParams) -> None:
        super().__init__(name, params)
        self.servo_on = False
        self.loop_gain = 0.0  # the velocity servo's uncapped loop gain, last step (servo_gain)
        self.shearing = False
        self.height0: float | None = None  # plate height when the shear started
        self.upper: list[Any] = []
        self.lower: list[Any] = []
        self.sides: list[Any] = []  # upper walls parallel to x

    # ------------------------------------------------------------------ geometry
    def build(self, sim: Any) -> None:
        p = self.params
        x0, y0, z0 = (float(c) for c in p.corner)
        L, W, g = p.length, p.width, p.gap
        z1 = z0 + p.lower_height
        z2 = z1 + g
        h1, h2 = p.lower_height, p.upper_height
        flange = p.max_displacement + 0.05 * L
        self.x0, self.y0, self.z0, self.z1, self.z2 = x0, y0, z0, z1, z2
        self.area = L * W
        self.load = p.normal_stress * self.area
        xc, yc = x0 + 0.5 * L, y0 + 0.5 * W
        R = shapes.Rectangle
        fixed = Fixed()

        def lower(shape, suffix):
            self.lower.append(self.add_wall(sim, shape, suffix, motion=fixed))

        lower(R((xc, yc, z0), _Z, _X, (0.5 * L, 0.5 * W)), "floor")
        lower(R((x0, yc, z0 + 0.5 * h1), _X, _Y, (0.5 * W, 0.5 * h1)), "lower_xlo")
        lower(R((x0 + L, yc, z0 + 0.5 * h1), -_X, _Y, (0.5 * W, 0.5 * h1)), "lower_xhi")
        lower(R((xc, y0, z0 + 0.5 * h1), _Y, _X, (0.5 * L, 0.5 * h1)), "lower_ylo")
        lower(R((xc, y0 + W, z0 + 0.5 * h1), -_Y, _X, (0.5 * L, 0.5 * h1)), "lower_yhi")
        lower(R((x0 + L + 0.5 * flange, yc, z1), _Z, _X, (0.5 * flange, 0.5 * W)), "lower_flange")

        self.frame = Controlled()  # one motion, the same velocity for every wall of the upper half

        def upper(shape, suffix):
            wall = self.add_wall(sim, shape, suffix, motion=self.frame)
            self.upper.append(wall)
            return wall

        zu = z2 + 0.5 * h2
        upper(R((x0, yc, zu), _X, _Y, (0.5 * W, 0.5 * h2)), "upper_xlo")
        upper(R((x0 + L, yc, zu), -_X, _Y, (0.5 * W, 0.5 * h2)), "upper_xhi")
        self.sides.append(upper(R((xc, y0, zu), _Y, _X, (0.5 * L, 0.5 * h2)), "upper_ylo"))
        self.sides.append(upper(R((xc, y0 + W, zu), -_Y, _X, (0.5 * L, 0.5 * h2)), "upper_yhi"))
        self.lid = upper(R((x0 - 0.5 * flange, yc, z2), -_Z, _X, (0.5 * flange, 0.5 * W)), "upper_flange")

        control = p.control
        if control == "auto":
            control = "force" if sim.law.rigid else "velocity"
        self.control = control
        self.gain = p.gain if p.gain is not None else p.max_speed / p.normal_stress
        zp = z0 + (p.plate_height if p.plate_height is not None else h1 + g + h2)
        self.zp0 = zp
        if control == "force":
            self.plate_motion = RigidBody(
                mass=p.plate_mass if p.plate_mass is not None else self.load / 10.0, fixed_translation="y"
            )
        else:
            self.plate_motion = Controlled()
        self.plate = self.add_wall(
            sim, R((xc, yc, zp), -_Z, _X, (0.5 * L, 0.5 * W)), "plate",
            material=p.plate_material or p.material, motion=self.plate_motion,
        )  # fmt: skip
        self.upper.append(self.plate)

    # ------------------------------------------------------------------ stages
    def on_stage(self, sim: Any, stage: str) -> None:
        p = self.params
        if p.consolidation_stage is None or stage in (p.consolidation_stage, p.shear_stage):
            if not self.servo_on:
                self._check_gap(sim)
            self.servo_on = True
        if stage == p.shear_stage and not self.shearing:
            self.shearing = True
            self.height0 = self.height()
        super().on_stage(sim, stage)
        if isinstance(self.plate_motion, RigidBody):  # a free plate stays put while the box is off
            if self.active:
                self.plate_motion.release()
            else:
                self.plate_motion.hold()

    def _check_gap(self, sim: Any) -> None:
        """Grains not wider than the gap would leak between the halves: an error, said early."""
        part = sim.particles
        n = part.n_owned
        small = (2.0 * part.r[:n] <= self.params.gap) & (part.motion[:n] != REMOVED)
        if sim.count(int(np.count_nonzero(small))):
            raise InputError(
                f"shear box '{self.name}': gap = {self.params.gap} m is not smaller than the diameter of "
                f"{sim.count(int(np.count_nonzero(small)))} grain(s); they would leak between the halves. "
                "Give a gap below the smallest grain diameter (a fraction of it, e.g. 0.3 d)"
            )

    # ------------------------------------------------------------------ control
    @property
    def displacement(self) -> float:
        """Shear displacement u of the upper half [m]."""
        return float(self.upper[0].offset[0])

    def height(self) -> float:
        """The top plate's height above the floor [m]."""
        return float(self.plate.reference_point[2] - self.z0)

    def normal_force(self) -> float:
        """N: the grains' upward load on the top plate [N] (collective under MPI)."""
        return float(self.plate.force[2])

    def before_step(self, sim: Any) -> None:
        p = self.params
        u = self.displacement
        vx = p.shear_speed if self.shearing else 0.0
        dt = sim.dt
        if vx > 0.0 and u + vx * dt > p.max_displacement:
            vx = max(0.0, (p.max_displacement - u) / dt)
        self.frame.velocity = vx * _X
        sigma = self.normal_force() / self.area
        if self.control == "velocity":
            vz = 0.0
            if self.servo_on:
                # capped so that gain (K dt + 2 C) / area ≤ 1 for the plate's contacts (servo_gain)
                gain, self.loop_gain = servo_gain(sim, self.plate, self.gain, self.area)
                vz = -float(np.clip(gain * (p.normal_stress - sigma), -p.max_speed, p.max_speed))
                if self.height() + vz * dt < 0.0:  # an empty box: do not fall through the floor
                    vz = 0.0
            self.plate_motion.velocity = np.array([vx, 0.0, vz])
            return
        # force control: a critically damped spring-damper keeps the plate's x on the upper half's
        # (and, before the servo starts, its z where it was built); time constant 10 steps
        m = self.plate_motion.mass
        om = 0.1 / dt
        v = self.plate_motion.velocity_now
        off = self.plate.offset
        fx = m * (om * om * (u + vx * dt - off[0]) + 2.0 * om * (vx - v[0]))
        if self.servo_on:
            fz = -self.load
        else:
            fz = m * (om * om * (0.0 - off[2]) - 2.0 * om * v[2])
        self.plate_motion.force = (fx, 0.0, fz)

    # ------------------------------------------------------------------ measurements
    def _outside(self, sim: Any) -> int:
        part = sim.particles
        n = part.n_owned
        x = part.x[:n]
        live = (part.motion[:n] != REMOVED) & (part.inv_m[:n] > 0)
        p, u = self.params, self.displacement
        in_y = (x[:, 1] > self.y0) & (x[:, 1] < self.y0 + p.width)
        xs, zs = x[:, 0] - self.x0, x[:, 2]
        low = (xs > 0.0) & (xs < p.length) & (zs > self.z0) & (zs < self.z2)
        top = self.plate.reference_point[2]
        up = (xs > u) & (xs < p.length + u) & (zs > self.z1) & (zs < top)
        return sim.count(int(np.count_nonzero(live & ~(in_y & (low | up)))))

    def measurements(self, sim: Any) -> dict[str, float]:
        p = self.params
        u = self.displacement
        upper = [w.force for w in self.upper]  # every rank reads every load (collective)
        lower = [w.force for w in self.lower]
        shear = -math.fsum(f[0] for f in upper)
        side = -math.fsum(w.force[0] for w in self.sides)
        n_force = self.normal_force()
        sigma = n_force / self.area
        h = self.height()
        n_plane = self.plane_normal_force(sim)
        inertial = math.nan
        if self.shearing and sigma > 0:
            # I = γ̇ d sqrt(ρ/σ_n) with the shear band taken as 10 grain diameters thick (γ̇ = v / 10 d),
            # so I = (v / 10) sqrt(ρ/σ_n); grain density from their mass and volume (collective)
            prt = sim.particles
            n = prt.n_owned
            live = prt.inv_m[:n] > 0
            vol = sim.exact_sum(4.0 / 3.0 * math.pi * prt.r[:n][live] ** 3)
            if vol > 0:
                rho = sim.exact_sum(prt.mass[:n][live]) / vol
                inertial = 0.1 * p.shear_speed * math.sqrt(rho / sigma)
        return {
            "displacement": u,
            "shear_force": shear,
            "lower_force": math.fsum(f[0] for f in lower),
            "side_friction": side,
            "normal_force": n_force,
            "normal_stress": sigma,
            "error": sigma / p.normal_stress - 1.0,
            "tau": shear / ((p.length - u) * p.width),
            "ratio": shear / n_force if n_force > 0 else math.nan,
            "height": h,
            "dilation": h - self.height0 if self.height0 is not None else 0.0,
            "outside": float(self._outside(sim)),
            "plate_contacts": float(sim.count(int(self.plate.n_contacts))),  # collective
            "inertial": inertial,
            "plane_normal_force": n_plane,
            "plane_normal_stress": n_plane / ((p.length - u) * p.width),
            "plane_ratio": shear / n_plane if n_plane > 0 else math.nan,
        }

    def plane_normal_force(self, sim: Any) -> float:
        """The normal force across the shear plane, from the equilibrium of the lower grains (centre
        below the lower rim): the floor's and lower walls' vertical load, less the lower grains'
        weight and the upper flange's push down on them. It adds to the plate's load the weight of
        the upper grains and takes off what the upper walls carry by friction (collective)."""
        load = -math.fsum(float(w.force[2]) for w in self.lower[:5])  # floor and lower walls, not the flange
        load -= float(self.lid.force[2])
        gz = float(sim.gravity[2])
        if gz != 0.0:
            prt = sim.particles
            n = prt.n_owned
            x = prt.x[:n]
            below = (prt.inv_m[:n] > 0) & (x[:, 2] < self.z1)
            load += gz * sim.exact_sum(prt.mass[:n][below])
        return load

    def summary(self, series: dict[str, np.ndarray]) -> dict[str, float]:
        key = f"{self.name}."
        if key + "displacement" not in series:
            return {}
        u = np.asarray(series[key + "displacement"], float)
        sel = u > 0.0
        names = series.get(STAGE_COLUMN)
        if names is not None:  # rows of the stages in which the box is on (not one switched off after)
            on = stage_rows(series, [s for s in dict.fromkeys(names) if listed(self.params, s)], len(u))
            if on is not None:
                sel &= on
        if sel.sum() < 3 or not np.any(np.isfinite(series[key + "ratio"][sel])):
            return {}
        u = u[sel]
        ratio, tau = series[key + "ratio"][sel], series[key + "tau"][sel]
        dil, err = series[key + "dilation"][sel], np.abs(series[key + "error"][sel])
        i = int(np.nanargmax(ratio))
        late = u >= u[-1] - 0.2 * (u[-1] - u[0])
        plane = series.get(key + "plane_ratio")
        plane_out = {}
        if plane is not None and np.any(np.isfinite(plane[sel])):
            pr, ps = plane[sel], series[key + "plane_normal_stress"][sel]
            plane_out = {
                "peak_plane_ratio": float(np.nanmax(pr)),
                "residual_plane_ratio": float(np.nanmean(pr[late])),
                "plane_normal_stress_mean": float(np.nanmean(ps)),
            }
        return {
            "peak_ratio": float(ratio[i]),
            "peak_tau": float(np.nanmax(tau)),
            "peak_displacement": float(u[i]),
            "residual_ratio": float(np.nanmean(ratio[late])),
            "residual_tau": float(np.nanmean(tau[late])),
            "final_displacement": float(u[-1]),
            "max_dilation": float(np.nanmax(dil)),
            "final_dilation": float(dil[-1]),
            "mean_abs_error": float(np.nanmean(err)),
            "p95_abs_error": float(np.nanpercentile(err, 95)),
            "max_outside": float(np.nanmax(series[key + "outside"][sel])),
            **plane_out,
            **({"inertial_number_max": float(np.nanmax(inert[sel]))}
               if (inert := series.get(key + "inertial")) is not None and np.any(np.isfinite(inert[sel]))
               else {}),  # fmt: skip
        }

    # ------------------------------------------------------------------ checkpoints
    def state(self) -> dict[str, Any]:
        return {"servo_on": self.servo_on, "shearing": self.shearing, "height0": self.height0}

    def restore(self, state: dict[str, Any]) -> None:
        self.servo_on = bool(state.get("servo_on", False))
        self.shearing = bool(state.get("shearing", False))
        self.height0 = state.get("height0")

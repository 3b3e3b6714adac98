"""Penetrometer (``type = "penetrometer"``): a cone-tipped rod or a sphere pushed into a granular bed
at constant speed, or dropped onto it as a free rigid body (experiments.md §2).

**Body.** ``tip = "cone"``: a rod of diameter D (default from the standard cone base area 323 mm²,
D = 20.3 mm) with a conical tip of apex angle ``apex_deg`` (60° standard, 30° the sharp cone), the
apex down on the axis (x, y) = ``axis``; the cone is L_c = (D/2) / tan(apex/2) long, the shaft above
it ``shaft_length`` (0: a bare cone), closed by a flat cap. All of it is one triangle-mesh wall
(``segments`` facets around): the cone's fan of ``segments`` triangles first, then the shaft's
2 × ``segments``, then the cap's ``segments`` (so a body sunk deeper than its length stays
closed). A mesh rather than a Frustum and a
CylinderTube wall: a grain at the rim where cone and shaft meet is within reach of both surfaces'
edges (the same circle), and two analytic walls would load it twice; the mesh wall counts one
contact per grain (:mod:`pdem.geometry._mesh`). With 48 segments the flat facets lie within
R (1 − cos(π/48)) = 0.2 % of R of the true cone, 0.02 mm for D = 20.3 mm. The **tip force** is the
load on the cone's facets, the **shaft force** the load on the shaft's and the cap's (rows of the same wall,
each row's load an exact sum, added in row order, so the split is the same on any number of
ranks). ``tip = "sphere"``: a ball of diameter ``diameter`` (default 1 inch), all of it "tip".

**Placing it.** The body is built where the deck says nothing about the bed (it is switched off)
and placed when stage ``penetration_stage`` starts, from the bed as it is then:

* the **bed surface** z_s is the mean, over a square grid of columns (side ``surface_cell``, default
  two of the largest grain diameters) whose centres lie within ``surface_radius`` of the axis
  (default 1.5 D), of each column's highest grain top (z + r). Why: the tip meets the surface near
  the axis, so the box walls' boundary layer and a surface that is not quite flat far away should
  not count; the top of each column is what a probe lowered onto the bed would touch, and the mean
  over columns does not follow one grain sticking up. At the start of the stage the rod has not
  touched anything, so no column is disturbed. It is taken once (a global max per column, an
  exact sum over columns in column order: the same on any rank count) and kept for the stage;
* ``mode = "push"``: the tip is placed ``start_gap`` above the highest grain top under the body's
  footprint (so it touches nothing), then driven down at ``speed`` (``approach_speed`` until it
  first touches a grain, default ``speed``) until the tip is ``max_depth`` below z_s (if given),
  where it stops;
* ``mode = "drop"``: the tip (the apex; the sphere's lowest point) is placed ``release_height`` H
  above z_s, at rest, and released: a :class:`RigidBody` of mass ``mass`` (default ρ × volume, ρ =
  ``density``; the cone and the shaft, or the ball) under gravity (``run.gravity``), moving along the
  axis only, by the grains' load (DEM-P: explicit in last step's load; DEM-C: solved with the
  grains). With ``fall = "analytic"`` (default) the fall through the air is not stepped: the body
  starts ``start_gap`` above the highest grain under it, moving down at sqrt(2 g Δz), the speed of a
  free fall from H (tested: the stepped fall is ballistic); ``"integrate"`` steps it. It has come
  to rest when its speed stayed below ``rest_speed`` for ``rest_time``.

Measured every series row (``NAME.key``; NaN before the penetration stage): ``depth`` [m] = z_s −
z_tip (negative above the surface), ``tip_force`` [N] and ``shaft_force`` [N] (the vertical load of
the grains on the cone, on the shaft; positive when it resists the descent), ``qc`` [Pa] =
tip_force / base area (π D²/4), ``total_force`` [N], ``velocity`` [m/s] (vertical; negative down),
``tip_z`` [m], ``surface`` [m] (z_s), ``at_rest`` (1 when a dropped body has come to rest),
``contacts`` (grains touching the body, all ranks).

Summary: ``push``: ``qc_mean``, ``qc_std`` [Pa] over the steady part (depth ≥ ``steady_from``,
default the larger of the cone length and half the final depth, so the tip is buried and the start
transient is left out), its depth range, ``qc_slope`` [Pa/m] (least squares over the same part),
``shaft_force_mean``, ``final_depth``; ``drop``: ``final_depth`` (at the end of the run),
``max_depth``, ``release_height`` H, ``total_drop`` = H + final depth, ``impact_velocity``
(the body's vertical velocity as it first touches a grain, before that contact acts: the same
quantity for a soft contact that builds up over many steps and a rigid one that acts within its
first step), ``mass``, ``rest_time``.

It uses only the public plugin API (:mod:`pdem.api`).
"""

from __future__ import annotations

import math
from typing import Any, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from pdem.api import (
    REMOVED,
    Boundary,
    BoundaryParams,
    Controlled,
    InputError,
    Loading,
    RigidBody,
    SampleSize,
    SceneFacts,
    SizeCheck,
    shapes,
)

__all__ = ["Penetrometer", "PenetrometerParams", "cone_mesh"]

STANDARD_BASE_AREA = (
    323e-6  # m², the standard cone (ISO 22476-1: 10 cm² is the large one; 323 mm² the study's)
)
INCH = 0.0254

#: the stress near a pushed cone's tip as a multiple of the overburden φ ρ g z (the advice's stress
#: and inertial number): pdem's reduced bed measured q_c ≈ 1.0 kPa at 1.8–2 cm where φ ρ g z ≈
#: 0.28 kPa (3.7×, docs/experiments/cone_penetration.md); 5 is a rounded-up rule of thumb
TIP_FACTOR = 5.0
#: the minimum sizes of a cone penetration test (the advice's sample-size check): (minimum, source)
SIZE_CONE_GRAIN = (
    20.0,
    "a rule of thumb from centrifuge tests (Bolton et al., Géotechnique 49, 543, 1999): cone "
    "diameter ≥ ~20 grain diameters for a grain-size-free q_c",
)
SIZE_CHAMBER = (
    20.0,
    "a rule of thumb from calibration-chamber studies (e.g. Salgado, Mitchell & Jamiolkowski, "
    "J. Geotech. Geoenviron. Eng. 124, 878, 1998): chamber width ≥ ~20 cone diameters, wall "
    "effects persist beyond in dense sand",
)


def body_diameter(params: Any) -> float:
    """The diameter of the cone's rod (default from ``base_area``) or of the sphere (default 1 inch)."""
    if params.diameter is not None:
        return float(params.diameter)
    return math.sqrt(4.0 * params.base_area / math.pi) if params.tip == "cone" else INCH


class PenetrometerParams(BoundaryParams):
    """Keys of ``[boundaries.NAME]`` with ``type = "penetrometer"``."""

    material: str = Field(description="material of the penetrometer (its friction on the grains)")
    penetration_stage: str = Field(
        description="stage at whose start the body is placed over the bed and pushed or released; "
        "before it the body is switched off"
    )
    tip: Literal["cone", "sphere"] = Field("cone", description="'cone' (a cone-tipped rod) or 'sphere'")
    mode: Literal["push", "drop"] = Field(
        "push", description="'push' at constant speed, or 'drop' as a free rigid body"
    )
    axis: tuple[float, float] = Field(
        (0.0, 0.0), description="(x, y) of the vertical axis the body moves along [m]"
    )
    apex_deg: float = Field(60.0, description="cone apex angle [deg], in (0, 180): 60 standard, 30 sharp")
    base_area: float = Field(
        STANDARD_BASE_AREA,
        description="cone base area [m²] (default 323 mm², D = 20.3 mm); q_c = tip force / it",
    )
    diameter: float | None = Field(
        default=None,
        description="cone/rod diameter [m] (default from base_area) or sphere diameter (default 1 inch)",
    )
    shaft_length: float = Field(
        0.1, ge=0, description="length of the rod above the cone [m] (0: a bare cone)"
    )
    segments: int = Field(48, ge=8, le=720, description="facets around the cone and the rod")
    speed: float = Field(0.02, gt=0, description="push speed [m/s]")
    approach_speed: float | None = Field(
        default=None,
        gt=0,
        description="push speed until the body first touches a grain [m/s] (default speed)",
    )
    start_gap: float = Field(
        0.002, ge=0, description="push: the tip starts this far above the highest grain under the body [m]"
    )
    max_depth: float | None = Field(
        default=None, gt=0, description="push: the body stops when the tip is this deep below the surface [m]"
    )
    release_height: float = Field(
        0.1, gt=0, description="drop: height H of the tip above the bed surface at release [m]"
    )
    fall: Literal["analytic", "integrate"] = Field(
        "analytic",
        description="drop: 'analytic' starts the body start_gap above the highest grain under it with the "
        "free-fall speed from H (saves the steps of the fall); 'integrate' releases it at rest from H",
    )
    density: float = Field(
        700.0, gt=0, description="drop: density of the body [kg/m³] (its mass = density × volume)"
    )
    mass: float | None = Field(default=None, gt=0, description="drop: mass [kg] instead of density × volume")
    rest_speed: float = Field(1e-3, gt=0, description="drop: at rest below this speed [m/s] ...")
    rest_time: float = Field(0.02, ge=0, description="... kept for this long [s]")
    surface_radius: float | None = Field(
        default=None,
        gt=0,
        description="columns within this distance of the axis define the surface [m] (default 1.5 D)",
    )
    surface_cell: float | None = Field(
        default=None,
        gt=0,
        description="column size for the surface [m] (default two largest grain diameters)",
    )
    steady_from: float | None = Field(
        default=None,
        ge=0,
        description="push summary: q_c is averaged over depths from here on [m] (default max(cone length, "
        "half the final depth))",
    )

    @field_validator("apex_deg")
    @classmethod
    def _apex(cls, v: float) -> float:
        if not (0.0 < v < 180.0) or not math.isfinite(v):
            raise ValueError(
                f"apex_deg = {v!r} is not a cone's apex angle; give a value in (0, 180) degrees, e.g. 60 "
                "(the standard cone) or 30 (the sharp one)"
            )
        return v

    @field_validator("base_area", "diameter")
    @classmethod
    def _positive(cls, v: float | None, info) -> float | None:
        if v is not None and not (v > 0 and math.isfinite(v)):
            raise ValueError(
                f"{info.field_name} = {v!r} must be positive and finite [m or m²]; the standard cone has "
                "base_area = 3.23e-4 (D = 20.3 mm)"
            )
        return v

    @model_validator(mode="after")
    def _consistent(self):
        # a resolved deck (stored in every checkpoint) writes the default out: only another angle is
        # a user's mistake
        default = type(self).model_fields["apex_deg"].default
        if self.tip == "sphere" and "apex_deg" in self.model_fields_set and self.apex_deg != default:
            raise ValueError("apex_deg applies to tip = 'cone' only; remove it or set tip = 'cone'")
        return self


def cone_mesh(diameter: float, apex_deg: float, shaft_length: float, segments: int):
    """Vertices and triangles of a cone (apex at the origin, opening along +z) topped by a rod of the
    same diameter and closed by a flat cap: the cone's ``segments`` triangles first, then the rod's
    2 × ``segments`` (none if ``shaft_length`` is 0), then the cap's ``segments``. Returns
    (vertices, triangles, cone length)."""
    radius = 0.5 * diameter
    length = radius / math.tan(math.radians(0.5 * apex_deg))
    phi = 2.0 * math.pi * np.arange(segments) / segments
    ring = np.stack([radius * np.cos(phi), radius * np.sin(phi), np.full(segments, length)], axis=1)
    verts = [np.zeros((1, 3)), ring]
    k = np.arange(segments)
    nxt = (k + 1) % segments
    tris = [np.stack([np.zeros(segments, dtype=np.int64), 1 + k, 1 + nxt], axis=1)]
    top_ring = 1 + k
    if shaft_length > 0:
        top = ring.copy()
        top[:, 2] += shaft_length
        verts.append(top)
        b0, b1 = 1 + k, 1 + nxt
        t0, t1 = 1 + segments + k, 1 + segments + nxt
        quads = np.empty((2 * segments, 3), dtype=np.int64)
        quads[0::2] = np.stack([b0, b1, t1], axis=1)
        quads[1::2] = np.stack([b0, t1, t0], axis=1)
        tris.append(quads)
        top_ring = t0
    centre = sum(len(v) for v in verts)
    verts.append(np.array([[0.0, 0.0, length + shaft_length]]))
    tris.append(np.stack([np.full(segments, centre), top_ring, np.roll(top_ring, -1)], axis=1))
    return np.concatenate(verts), np.concatenate(tris).astype(np.int64), length


class Penetrometer(Boundary):
    """See the module docstring."""

    Params = PenetrometerParams

    def __init__(self, name: str, params: BoundaryParams) -> None:
        super().__init__(name, params)
        p = self.params
        if p.tip == "cone":
            self.diameter = p.diameter if p.diameter is not None else math.sqrt(4.0 * p.base_area / math.pi)
            self.cone_length = 0.5 * self.diameter / math.tan(math.radians(0.5 * p.apex_deg))
            r = 0.5 * self.diameter
            self.volume = math.pi * r * r * (self.cone_length / 3.0 + p.shaft_length)
            self.area = math.pi * r * r if p.diameter is not None else p.base_area
        else:
            self.diameter = p.diameter if p.diameter is not None else INCH
            self.cone_length = 0.0
            self.volume = math.pi * self.diameter**3 / 6.0
            self.area = math.pi * self.diameter**2 / 4.0
        self.mass = p.mass if p.mass is not None else p.density * self.volume
        self.phase = "off"
        self.surface = math.nan
        self.touched = False
        self.rest_clock = 0.0
        self.impact_velocity = math.nan
        self._v_before = math.nan  # the body's velocity at the start of the step (drop, until it touches)
        self._stage_t0 = 0.0
        self._restored: dict | None = None
        self._cache: tuple[int, dict] | None = None

    # ------------------------------------------------------------------ building, stages
    def build(self, sim: Any) -> None:
        p = self.params
        ax, ay = p.axis
        if p.tip == "cone":
            verts, tris, _ = cone_mesh(self.diameter, p.apex_deg, p.shaft_length, p.segments)
            verts = verts + (ax, ay, 0.0)
            self.n_tip_rows = p.segments
            shape = shapes.TriangleMesh(verts, tris, reference_point=(ax, ay, 0.0), name_hint="penetrometer")
            self._tip0 = 0.0  # tip z relative to the reference point
        else:
            r = 0.5 * self.diameter
            self.n_tip_rows = 1
            shape = shapes.Sphere((ax, ay, r), r)
            self._tip0 = -r
        self.motion = Controlled()
        self.body = self.add_wall(sim, shape, motion=self.motion)
        self._comm = sim.comm

    def tip_z(self) -> float:
        return float(self.body.reference_point[2] + self._tip0)

    @classmethod
    def loading(cls, name: str, params: Any, facts: SceneFacts) -> list[Loading]:
        """From ``penetration_stage`` on: pushed, the body moves at ``speed`` (``approach_speed``
        until it touches), loads the grains near its tip with :data:`TIP_FACTOR` × φ ρ g z at its
        deepest depth z, shears them at speed / D, and its ``depth`` grows from −``start_gap``;
        dropped, it hits the bed at sqrt(2 g ``release_height``) (an impact the advice does not
        estimate)."""
        p = params
        stages = facts.stages_from(p.penetration_stage)
        if p.mode == "drop":
            speed = math.sqrt(2 * max(facts.gravity, 9.81) * p.release_height)
            drop = f"boundaries.{name}: drop from release_height"
            return [Loading(stages=stages, speed=speed, speed_from=drop, impact=True)]
        depth = facts.ends.get(f"{name}.depth")
        if depth is None:
            depth = p.max_depth or (0.5 * facts.packed_height if math.isfinite(facts.packed_height) else 0.01)
        tip = TIP_FACTOR * facts.overburden(depth)
        stress = {}
        if tip > 0:
            at = f"boundaries.{name}: {TIP_FACTOR:g} × φ ρ g z at the tip (z = {depth:.3g} m)"
            stress = {"stress": tip, "stress_from": at}
        return [Loading(
            stages=stages, speed=max(p.speed, p.approach_speed or 0.0), speed_from=f"boundaries.{name}.speed",
            **stress, rate_key="speed", rate=p.speed, shear_rate=p.speed / body_diameter(p),
            rate_how=f"I = (v / D_cone) d sqrt(ρ/σ_v), σ_v = φ ρ g z at the deepest tip z = {depth:.3g} m "
            "(a rule of thumb: the stress near the tip is a few times σ_v)",
            ends={"depth": (p.speed, -p.start_gap)},
        )]  # fmt: skip

    @classmethod
    def sample_size(cls, name: str, params: Any, facts: SceneFacts) -> SampleSize:
        """Grains across the body, and the bed's width (the square root of its footprint) in body
        diameters."""
        diameter = body_diameter(params)
        width = math.sqrt(facts.footprint) if facts.footprint else math.nan
        return SampleSize("cone penetration", (
            SizeCheck("cone D / d_mean", diameter / facts.d_mean, *SIZE_CONE_GRAIN),
            SizeCheck("bed width / cone D", width / diameter, *SIZE_CHAMBER),
        ))  # fmt: skip

    @classmethod
    def stage_roles(cls, params: Any, stages: Any) -> list[str | None]:
        """Off before ``penetration_stage``, its ``mode`` in it, ``"hold"`` after it (the body stays
        where it is), off from a stage ``off_stages`` names on."""
        out: list[str | None] = []
        phase: str | None = None
        off = set(params.off_stages or ())
        for s in stages:
            if s in off:
                phase = None
            elif s == params.penetration_stage:
                phase = params.mode
            elif phase is not None:
                phase = "hold"
            out.append(phase)
        return out

    def on_stage(self, sim: Any, stage: str) -> None:
        p = self.params
        resumed, self._restored = self._restored, None
        if stage in (p.off_stages or ()):  # said off: the body is gone from then on
            self.phase = "off"
            self.set_active(sim, False)
            if isinstance(getattr(self, "motion", None), RigidBody):  # a dropped body stays put while off
                self.motion.hold()
        elif stage == p.penetration_stage:
            self.set_active(sim, True)
            if resumed is not None and resumed.get("phase") in ("push", "drop"):
                self._resume(sim, resumed)
            else:
                self._place(sim)
            self.phase = p.mode
            self._stage_t0 = sim.time if resumed is None else resumed.get("stage_t0", sim.time)
        elif self.phase in ("push", "drop", "hold"):  # a later stage: the body stays where it is, still
            self.set_active(sim, True)
            self.motion = Controlled()
            sim.set_wall_motion(self.body.name, self.motion)
            if resumed is not None:
                self.surface = resumed.get("surface", self.surface)
            self.phase = "hold"
        else:
            self.phase = "off"
            self.set_active(sim, False)
            if isinstance(getattr(self, "motion", None), RigidBody):  # a dropped body stays put while off
                self.motion.hold()

    def _grains(self, sim: Any):
        prt = sim.particles
        n = prt.n_owned
        live = prt.motion[:n] != REMOVED
        return prt.x[:n][live], prt.r[:n][live]

    def _measure_surface(self, sim: Any) -> tuple[float, float]:
        """(surface z_s, highest grain top under the body's footprint): see the module docstring."""
        p = self.params
        x, r = self._grains(sim)
        comm = sim.comm
        rmax = float(np.max(r)) if r.size else 0.0
        if comm.size > 1:
            rmax = max(comm.allgather(rmax))
        if rmax <= 0.0:
            raise InputError(
                f"boundaries.{self.name}: no grains to penetrate when stage '{p.penetration_stage}' starts; "
                "insert the bed in an earlier stage (or before the first)"
            )
        cell = p.surface_cell if p.surface_cell is not None else 4.0 * rmax
        reach = p.surface_radius if p.surface_radius is not None else 1.5 * self.diameter
        dx, dy = x[:, 0] - p.axis[0], x[:, 1] - p.axis[1]
        ix = np.floor(dx / cell).astype(np.int64)
        iy = np.floor(dy / cell).astype(np.int64)
        cx, cy = (ix + 0.5) * cell, (iy + 0.5) * cell
        near = cx * cx + cy * cy <= reach * reach
        top = x[:, 2] + r
        key = (ix[near] + 1_000_000) * 2_000_003 + (iy[near] + 1_000_000)
        order = np.lexsort((-top[near], key))
        ks, ts = key[order], top[near][order]
        first = np.ones(ks.size, dtype=bool)
        first[1:] = ks[1:] != ks[:-1]
        local = (ks[first], ts[first])
        foot = np.hypot(dx, dy) < 0.5 * self.diameter + r
        high = float(np.max(top[foot])) if foot.any() else -math.inf
        if comm.size > 1:
            parts = comm.allgather(local)
            ks = np.concatenate([q[0] for q in parts])
            ts = np.concatenate([q[1] for q in parts])
            order = np.lexsort((-ts, ks))
            ks, ts = ks[order], ts[order]
            first = np.ones(ks.size, dtype=bool)
            first[1:] = ks[1:] != ks[:-1]
            ts = ts[first]
            high = max(comm.allgather(high))
        else:
            ts = local[1]
        if ts.size == 0:
            raise InputError(
                f"boundaries.{self.name}: no grain column within surface_radius = {reach:.4g} m of the axis "
                f"{tuple(p.axis)}; put the axis over the bed or enlarge surface_radius"
            )
        return math.fsum(ts.tolist()) / ts.size, high

    def _place(self, sim: Any) -> None:
        p = self.params
        self.surface, high = self._measure_surface(sim)
        if p.mode == "push":
            z_tip = max(high, self.surface) + p.start_gap
        else:
            z_tip = self.surface + p.release_height
            if z_tip <= high:
                raise InputError(
                    f"boundaries.{self.name}.release_height = {p.release_height!r} m puts the body into the "
                    f"grains (the highest grain under it reaches {high - self.surface:.4g} m above the mean "
                    "surface); give a larger release_height"
                )
        v0 = 0.0
        if p.mode == "drop" and p.fall == "analytic":
            # skip the free fall: start just above the grains with the speed of a fall from z_tip
            z_start = min(z_tip, high + p.start_gap)
            g = -_gravity(sim)[2]
            v0 = -math.sqrt(2.0 * max(g, 0.0) * (z_tip - z_start))
            z_tip = z_start
        off = self.body.offset.copy()
        off[2] += z_tip - self.tip_z()
        self.body.set_offset(off)
        self.touched = False
        self.rest_clock = 0.0
        self.impact_velocity = math.nan
        if p.mode == "push":
            self.motion = Controlled()
            sim.set_wall_motion(self.body.name, self.motion)
        else:
            self.motion = RigidBody(mass=self.mass, gravity=_gravity(sim), velocity=(0.0, 0.0, v0),
                                    fixed_translation="xy")  # fmt: skip
            sim.set_wall_motion(self.body.name, self.motion)

    def _resume(self, sim: Any, st: dict) -> None:
        """A checkpoint inside the penetration stage: the wall's pose came with it; the rest here."""
        self.surface = st["surface"]
        self.touched = bool(st.get("touched", False))
        self.rest_clock = float(st.get("rest_clock", 0.0))
        self.impact_velocity = float(st.get("impact_velocity", math.nan))
        if self.params.mode == "push":
            self.motion = Controlled()
        else:
            self.motion = RigidBody(mass=self.mass, gravity=_gravity(sim), fixed_translation="xy")
            self.motion.restore({"velocity": np.array(st["body_velocity"]), "angular_velocity": np.zeros(3)})
        sim.set_wall_motion(self.body.name, self.motion)

    def state(self) -> dict[str, Any]:
        out = {"phase": self.phase, "surface": self.surface, "touched": self.touched,
               "rest_clock": self.rest_clock, "impact_velocity": self.impact_velocity,
               "stage_t0": self._stage_t0}  # fmt: skip
        if isinstance(self.motion, RigidBody):
            out["body_velocity"] = self.motion.velocity_now.tolist()
        return out

    def restore(self, state: dict[str, Any]) -> None:
        self._restored = dict(state) if state else None

    # ------------------------------------------------------------------ hooks
    def before_step(self, sim: Any) -> None:
        if self.phase == "drop" and math.isnan(self.impact_velocity):
            self._v_before = self._velocity()
        if self.phase != "push":
            return
        p = self.params
        if not self.touched:
            self.touched = bool(np.any(self.body.force != 0.0))  # collective: every rank reads it
        speed = p.speed if (self.touched or p.approach_speed is None) else p.approach_speed
        if p.max_depth is not None and self.surface - self.tip_z() >= p.max_depth:
            speed = 0.0
        self.motion.velocity = np.array([0.0, 0.0, -speed])

    def _velocity(self) -> float:
        """The body's vertical velocity: a free body's own (set at release, before any step), else
        the wall's."""
        if isinstance(self.motion, RigidBody):
            return float(self.motion.velocity_now[2])
        return float(self.body.velocity[2])

    def after_step(self, sim: Any) -> None:
        if self.phase != "drop":
            return
        v = self._velocity()
        if math.isnan(self.impact_velocity) and bool(np.any(self.body.force != 0.0)):  # collective
            self.impact_velocity = self._v_before
        if not self.touched and self.tip_z() <= self.surface:
            self.touched = True
        if self.touched and abs(v) < self.params.rest_speed:
            self.rest_clock += sim.dt
        else:
            self.rest_clock = 0.0

    # ------------------------------------------------------------------ measuring
    def measurements(self, sim: Any) -> dict[str, float]:
        keys = ("depth", "tip_force", "shaft_force", "qc", "total_force", "velocity", "tip_z", "surface",
                "at_rest", "contacts")  # fmt: skip
        if self.phase == "off":
            return dict.fromkeys(keys, math.nan)
        if self._cache is not None and self._cache[0] == sim.step_count:
            return dict(self._cache[1])
        loads = self.body.facet_loads()  # collective; each row's load an exact sum
        fz = loads[:, 2].tolist()
        tip = math.fsum(fz[: self.n_tip_rows])
        shaft = math.fsum(fz[self.n_tip_rows :])
        out = {
            "depth": self.surface - self.tip_z(),
            "tip_force": tip,
            "shaft_force": shaft,
            "qc": tip / self.area,
            "total_force": float(self.body.force[2]),
            "velocity": self._velocity(),
            "tip_z": self.tip_z(),
            "surface": self.surface,
            "at_rest": float(
                self.phase == "drop" and self.rest_clock >= self.params.rest_time and self.touched
            ),
            "contacts": float(sim.count(int(self.body.n_contacts))),
        }
        self._cache = (sim.step_count, out)
        return dict(out)

    def summary(self, series: dict[str, np.ndarray]) -> dict[str, float]:
        key = lambda k: series.get(f"{self.name}.{k}")  # noqa: E731
        depth, qc = key("depth"), key("qc")
        if depth is None or qc is None:
            return {}
        ok = np.isfinite(depth)
        if ok.sum() < 2:
            return {}
        p = self.params
        depth, qc = depth[ok], qc[ok]
        shaft = key("shaft_force")[ok]
        out: dict[str, float] = {"final_depth": float(depth[-1]), "max_depth": float(np.max(depth)),
                                 "base_area": self.area, "diameter": self.diameter}  # fmt: skip
        if p.mode == "push":
            final = float(np.max(depth))
            start = p.steady_from if p.steady_from is not None else max(self.cone_length, 0.5 * final)
            sel = depth >= start
            out["steady_from"] = float(start)
            if sel.sum() >= 2:
                out["qc_mean"] = float(np.mean(qc[sel]))
                out["qc_std"] = float(np.std(qc[sel]))
                out["qc_slope"] = float(np.polyfit(depth[sel], qc[sel], 1)[0])
                out["shaft_force_mean"] = float(np.mean(shaft[sel]))
                out["steady_rows"] = int(sel.sum())
        else:
            out["release_height"] = p.release_height
            out["total_drop"] = p.release_height + float(depth[-1])
            out["impact_velocity"] = self.impact_velocity
            out["mass"] = self.mass
            out["rest_time"] = self.rest_clock
        return out


def _gravity(sim: Any) -> tuple[float, float, float]:
    """The simulation's gravity [m/s²] as set (``run.gravity``), zero if none."""
    g = getattr(sim, "gravity", None)
    if g is None:
        return (0.0, 0.0, 0.0)
    return tuple(float(c) for c in np.broadcast_to(np.asarray(g, dtype=float), (3,)))

"""Built-in boundary plugins, registered through pdem's own entry points (group ``pdem.boundaries``).

Walls of every primitive shape (``plane``, ``rectangle``, ``disk``, ``annulus``, ``cylinder_tube``,
``frustum``, ``cylinder``, ``box``), a particle sink (``outflow``) and a conical ``hopper`` with its
discharge measurement. Lengths in m, angles in degrees where the key says so.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pydantic import Field, model_validator

from pdem.api import (
    Boundary,
    BoundaryParams,
    GeometryError,
    Loading,
    SampleSize,
    SceneFacts,
    SizeCheck,
    Vec3,
    WallBoundaryParams,
    column_partials,
    njit,
    shapes,
)

__all__ = [
    "PlaneBoundary",
    "RectangleBoundary",
    "DiskBoundary",
    "AnnulusBoundary",
    "CylinderTubeBoundary",
    "FrustumBoundary",
    "CylinderBoundary",
    "BoxBoundary",
    "OutflowBoundary",
    "HopperBoundary",
]


def _check_shape(shape_cls: Any, params: Any, keys: tuple[str, ...]) -> None:
    """Build the shape once so that geometry errors surface at deck validation, not at run time."""
    try:
        shape_cls(**{k: getattr(params, k) for k in keys})
    except GeometryError as exc:
        raise ValueError(str(exc)) from None


class _ShapeBoundary(Boundary):
    """A single wall of one primitive shape; the shape is built from the params' geometric keys."""

    shape_cls: Any = None
    geometric_keys: tuple[str, ...] = ()

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        shape_cls, keys, params_cls = cls.shape_cls, cls.geometric_keys, cls.Params

        class Checked(params_cls):  # same keys, plus a geometry check
            @model_validator(mode="after")
            def _geometry(self):
                _check_shape(shape_cls, self, keys)
                return self

        Checked.__name__ = Checked.__qualname__ = params_cls.__name__
        Checked.__doc__ = params_cls.__doc__
        cls.Params = Checked

    def build(self, sim: Any) -> None:
        p = self.params
        kwargs = {k: getattr(p, k) for k in self.geometric_keys}
        self.add_wall(sim, self.shape_cls(**kwargs))


class PlaneParams(WallBoundaryParams):
    point: Vec3 = Field(description="a point of the plane [m]")
    normal: Vec3 = Field(description="normal pointing into the side where particles live")


class PlaneBoundary(_ShapeBoundary):
    """Infinite one-sided plane."""

    Params = PlaneParams
    shape_cls = shapes.Plane
    geometric_keys = ("point", "normal")


class RectangleParams(WallBoundaryParams):
    center: Vec3
    normal: Vec3
    u_axis: Vec3 = Field(description="in-plane direction of the first half-extent")
    half_extents: tuple[float, float] = Field(description="half-lengths along u and n × u [m]")


class RectangleBoundary(_ShapeBoundary):
    """Finite two-sided plate."""

    Params = RectangleParams
    shape_cls = shapes.Rectangle
    geometric_keys = ("center", "normal", "u_axis", "half_extents")


class DiskParams(WallBoundaryParams):
    center: Vec3
    normal: Vec3
    radius: float = Field(gt=0)


class DiskBoundary(_ShapeBoundary):
    """Two-sided disk."""

    Params = DiskParams
    shape_cls = shapes.Disk
    geometric_keys = ("center", "normal", "radius")


class AnnulusParams(WallBoundaryParams):
    center: Vec3
    normal: Vec3
    r_inner: float = Field(ge=0)
    r_outer: float = Field(gt=0)


class AnnulusBoundary(_ShapeBoundary):
    """Two-sided flat ring."""

    Params = AnnulusParams
    shape_cls = shapes.Annulus
    geometric_keys = ("center", "normal", "r_inner", "r_outer")


class CylinderTubeParams(WallBoundaryParams):
    base_center: Vec3
    axis: Vec3
    radius: float = Field(gt=0)
    length: float = Field(gt=0)


class CylinderTubeBoundary(_ShapeBoundary):
    """Finite open tube (two-sided)."""

    Params = CylinderTubeParams
    shape_cls = shapes.CylinderTube
    geometric_keys = ("base_center", "axis", "radius", "length")


class FrustumParams(WallBoundaryParams):
    apex_side_center: Vec3 = Field(description="centre of the r0 end (the apex of a cone) [m]")
    axis: Vec3 = Field(description="from the r0 end towards the r1 end")
    r0: float = Field(ge=0)
    r1: float = Field(ge=0)
    length: float = Field(gt=0)


class FrustumBoundary(_ShapeBoundary):
    """Cone or frustum surface (two-sided, open ends)."""

    Params = FrustumParams
    shape_cls = shapes.Frustum
    geometric_keys = ("apex_side_center", "axis", "r0", "r1", "length")


class CylinderParams(WallBoundaryParams):
    point: Vec3
    axis: Vec3
    radius: float = Field(gt=0)
    inside: bool = Field(default=True, description="particles live inside (true) or outside")


class CylinderBoundary(_ShapeBoundary):
    """Infinite one-sided cylinder."""

    Params = CylinderParams
    shape_cls = shapes.Cylinder
    geometric_keys = ("point", "axis", "radius", "inside")


class BoxParams(WallBoundaryParams):
    lo: Vec3
    hi: Vec3
    open_faces: list[str] = Field(
        default_factory=list, description="faces to leave out: any of xlo, xhi, ylo, yhi, zlo, zhi"
    )

    @model_validator(mode="after")
    def _faces(self):
        bad = sorted(set(self.open_faces) - set(_FACES))
        if bad:
            raise ValueError(f"unknown face(s) {bad}; allowed: {list(_FACES)}")
        try:
            shapes.box_planes(self.lo, self.hi)
        except GeometryError as exc:
            raise ValueError(str(exc)) from None
        return self


_FACES = ("xlo", "xhi", "ylo", "yhi", "zlo", "zhi")


class BoxBoundary(Boundary):
    """Six inward-facing planes of an axis-aligned box (walls ``<name>.xlo`` … ``<name>.zhi``)."""

    Params = BoxParams

    def build(self, sim: Any) -> None:
        for face, plane in zip(_FACES, shapes.box_planes(self.params.lo, self.params.hi), strict=True):
            if face not in self.params.open_faces:
                self.add_wall(sim, plane, face)


class OutflowParams(BoundaryParams):
    point: Vec3 = Field(description="a point of the sink plane [m]")
    normal: Vec3 = Field(description="normal pointing towards the particles; those behind are removed")


class OutflowBoundary(Boundary):
    """Removes particles whose centres cross a plane; counts them and their mass."""

    Params = OutflowParams

    def __init__(self, name: str, params: BoundaryParams) -> None:
        super().__init__(name, params)
        #: terms whose exact sum is this rank's removed mass: its removals' masses, after a resume also
        #: the partials the checkpoint kept (summed exactly over ranks, the same value either way)
        self.removed_masses: list[float] = []
        self.removed_here = 0  # this rank's removals (and, after a resume on rank 0, the earlier ones)
        self._comm = None
        n = np.asarray(params.normal, dtype=float)
        self._n = n / np.linalg.norm(n)
        self._p = np.asarray(params.point, dtype=float)

    def build(self, sim: Any) -> None:
        self._comm = sim.comm

    def after_step(self, sim: Any) -> None:
        self._comm = sim.comm
        n = sim.particles.n_owned  # rows, removed ones included
        x = sim.particles.x[:n]
        # a kernel first (every step, ~1 µs per 1,000 grains); the NumPy mask it replaced took
        # ~60 µs a step on the hopper, ~5 % of a DEM-P step
        if not _any_below(x, sim.particles.inv_m[:n], self._p, self._n):
            return
        gone = ((x - self._p) @ self._n < 0.0) & (sim.particles.inv_m[:n] > 0)
        if gone.any():
            self.removed_masses.extend(float(m) for m in sim.particles.mass[:n][gone])
            self.removed_here += int(gone.sum())
            sim.remove_particles(gone)

    def measurements(self, sim: Any) -> dict[str, float]:
        return {
            "removed_count": float(sim.count(self.removed_here)),
            "removed_mass": sim.exact_sum(self.removed_masses),
        }

    def state(self) -> dict[str, Any]:
        """All ranks' removals (collective), so a checkpoint resumes on any number of ranks: their
        count, and a few partials per rank whose exact sum is the removed mass's (not one term per
        removed grain: a hopper that drains 10⁸ grains keeps a short list)."""
        terms = np.asarray(self.removed_masses, dtype=np.float64).reshape(-1, 1)
        partials, _ = column_partials(terms, 0)  # (masses are finite: no special term)
        partials, count = [float(v) for v in partials if v != 0.0], self.removed_here
        if self._comm is not None and self._comm.size > 1:
            parts = self._comm.allgather((partials, count))
            partials = [v for q in parts for v in q[0]]
            count = sum(q[1] for q in parts)
        return {"removed_partials": partials, "removed_count": int(count)}

    def restore(self, state: dict[str, Any]) -> None:
        rank = 0 if self._comm is None else self._comm.rank
        if "removed_masses" in state:  # a checkpoint that kept every removed mass
            terms, count = list(state["removed_masses"]), len(state["removed_masses"])
        else:
            terms, count = list(state.get("removed_partials", [])), int(state.get("removed_count", 0))
        self.removed_masses, self.removed_here = (terms, count) if rank == 0 else ([], 0)


@njit
def _any_below(x, inv_m, p, n):
    """Whether any free particle may be on the negative side of the plane through p with normal n: a
    pre-check for the mask in :meth:`OutflowBoundary.after_step`, which decides. It answers yes from
    1e-9 m above the plane, so rounding differences between the two (NumPy's matmul may sum in
    another order) never leave a particle the mask would remove."""
    for i in range(x.shape[0]):
        d = (x[i, 0] - p[0]) * n[0] + (x[i, 1] - p[1]) * n[1] + (x[i, 2] - p[2]) * n[2]
        if d < 1e-9 and inv_m[i] > 0:
            return True
    return False


class HopperParams(WallBoundaryParams):
    orifice_center: Vec3 = Field(description="centre of the circular orifice [m]; the axis is +z")
    orifice_diameter: float = Field(gt=0, description="orifice diameter D [m]")
    half_angle_deg: float = Field(gt=0, lt=90, description="cone half-angle from the vertical [deg]")
    top_diameter: float = Field(gt=0, description="diameter of the cone's top and of the barrel [m]")
    barrel_height: float = Field(ge=0, description="height of the cylindrical barrel above the cone [m]")
    open_at_stage: str = Field(description="the orifice plug is removed when this stage starts")
    outflow_depth: float = Field(gt=0, description="particles this far below the orifice are removed [m]")

    @model_validator(mode="after")
    def _geometry(self):
        if self.top_diameter <= self.orifice_diameter:
            raise ValueError(
                f"top_diameter = {self.top_diameter} must exceed orifice_diameter = {self.orifice_diameter}"
            )
        return self


#: the orifice size Beverloo's law holds above (the advice's sample-size check): (minimum, source)
SIZE_ORIFICE = (6.0, "Beverloo et al., Chem. Eng. Sci. 15, 260 (1961): the law holds for D/d ≳ 6")
SIZE_FILL = (1.0, "experiments.md §5: Beverloo's law needs a fill height above ~D")


class HopperBoundary(Boundary):
    """Conical hopper: cone from the orifice up to ``top_diameter``, a barrel above it, a plug disk
    that closes the orifice until stage ``open_at_stage``, and a sink ``outflow_depth`` below.

    Measurements: ``discharged_mass`` [kg] (mass removed by the sink plus free particles below the
    orifice plane) and ``discharged_count``. Summary: the steady flow rate W [kg/s], the slope of a
    least-squares line through discharged mass vs time between 20 % and 80 % of the final discharged
    mass (excludes the start transient and the final emptying).
    """

    Params = HopperParams

    @classmethod
    def loading(cls, name: str, params: Any, facts: SceneFacts) -> list[Loading]:
        """From ``open_at_stage`` on, grains fall through the orifice, from the packed height down to
        the sink, at sqrt(2 g (H + outflow_depth)); a discharge, whose rate gravity sets."""
        g = facts.gravity
        h = facts.packed_height if math.isfinite(facts.packed_height) else 0.0
        fall = {}
        if g > 0:
            fall = {"speed": math.sqrt(2 * g * (h + params.outflow_depth)),
                    "speed_from": f"boundaries.{name}: grains falling through the orifice"}  # fmt: skip
        return [Loading(
            stages=facts.stages_from(params.open_at_stage), **fall,
            note="a hopper discharge is a dense inertial flow (I ~ d/D near the orifice), not a quasi-static "
            "test: its rate is set by gravity, nothing to change", note_source="GDR MiDi 2004",
        )]  # fmt: skip

    @classmethod
    def sample_size(cls, name: str, params: Any, facts: SceneFacts) -> SampleSize:
        """Beverloo's orifice size and a fill above the orifice diameter."""
        d = params.orifice_diameter
        return SampleSize("hopper", (
            SizeCheck("orifice D / d_max", d / facts.d_max, *SIZE_ORIFICE),
            SizeCheck("fill height / D", facts.packed_height / d, *SIZE_FILL),
        ))  # fmt: skip

    def __init__(self, name: str, params: BoundaryParams) -> None:
        super().__init__(name, params)
        self._z0 = float(params.orifice_center[2])
        self._opened = False
        self.plug = None
        self._sink = OutflowBoundary(
            name + ".outflow",
            OutflowParams(
                type="outflow",
                point=tuple(np.asarray(params.orifice_center) - (0, 0, params.outflow_depth)),
                normal=(0, 0, 1),
            ),
        )

    def build(self, sim: Any) -> None:
        self._sink.build(sim)
        p = self.params
        c = np.asarray(p.orifice_center, dtype=float)
        r0, r1 = 0.5 * p.orifice_diameter, 0.5 * p.top_diameter
        cone_h = (r1 - r0) / math.tan(math.radians(p.half_angle_deg))
        self.add_wall(sim, shapes.Frustum(c, (0, 0, 1), r0, r1, cone_h), "cone")
        if p.barrel_height > 0:
            barrel = shapes.CylinderTube(c + (0, 0, cone_h), (0, 0, 1), r1, p.barrel_height)
            self.add_wall(sim, barrel, "barrel")
        self.plug = self.add_wall(sim, shapes.Disk(c, (0, 0, 1), r0 * 1.05), "plug")

    def on_stage(self, sim: Any, stage: str) -> None:
        if stage == self.params.open_at_stage:
            self._opened = True
        super().on_stage(sim, stage)

    def set_active(self, sim: Any, active: bool) -> None:
        super().set_active(sim, active)
        if self._opened and self.plug is not None:
            sim.set_wall_active(self.plug.name, False)

    def after_step(self, sim: Any) -> None:
        self._sink.after_step(sim)

    def state(self) -> dict[str, Any]:
        return {"opened": self._opened, "sink": self._sink.state()}

    def restore(self, state: dict[str, Any]) -> None:
        self._opened = bool(state.get("opened", False))
        self._sink.restore(state.get("sink", {}))

    def measurements(self, sim: Any) -> dict[str, float]:
        out = super().measurements(sim)
        n = sim.particles.n_owned  # rows, removed ones included
        below = (sim.particles.x[:n, 2] < self._z0) & (sim.particles.inv_m[:n] > 0)
        masses = np.concatenate(
            [np.asarray(self._sink.removed_masses, dtype=float), sim.particles.mass[:n][below]]
        )
        out["discharged_mass"] = sim.exact_sum(masses)
        out["discharged_count"] = float(sim.count(self._sink.removed_here + int(below.sum())))
        return out

    def summary(self, series: dict[str, np.ndarray]) -> dict[str, float]:
        key = f"{self.name}.discharged_mass"
        if key not in series or len(series[key]) < 3:
            return {}
        t, m = series["time"], series[key]
        final = m[-1]
        sel = (m >= 0.2 * final) & (m <= 0.8 * final)
        if final <= 0 or sel.sum() < 3:
            return {"discharged_mass": float(final)}
        slope, _ = np.polyfit(t[sel], m[sel], 1)
        return {"discharged_mass": float(final), "flow_rate": float(slope)}

r"""Wall shapes: user-facing classes that produce ``(kind, params)`` for the contact kernels.

Each shape validates its inputs (raising :class:`pdem.errors.GeometryError` with the argument, the
bad value and a remedy), normalises its direction vectors and exposes

* ``kind`` — the integer kind of :mod:`pdem.geometry._kernels`,
* ``name_hint`` — a short default name ("plane", "disk", …),
* ``params(offset=(0, 0, 0))`` — the float64 parameter vector (length ``N_PARAMS``) of the shape
  translated rigidly by ``offset`` (used for moving walls),
* ``reference_point`` — the point about which torques on the wall are reported,
* ``bounding_box(offset=(0, 0, 0))`` — ``(lo, hi)`` of the wall *surface* (±inf for infinite
  extents).

Surfaces of revolution (kind ``KIND_REVOLVED``) are parametrised by a meridian segment
(s0, ρ0)–(s1, ρ1) along the unit axis E from an axis point A; the side on which a centre lying
exactly on the surface is placed is the "+m side", m = (ρ1 − ρ0, −(s1 − s0))/|·| in (s, ρ)
coordinates (see the module docstring of :mod:`pdem.geometry._kernels`). For the shapes below:
Disk and Annulus → the +normal side; CylinderTube and Frustum → the inside.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from pdem.errors import GeometryError
from pdem.geometry._kernels import (
    KIND_CYLINDER,
    KIND_PLANE,
    KIND_RECTANGLE,
    KIND_REVOLVED,
    KIND_SPHERE,
    KIND_TRIANGLE,
    N_PARAMS,
)

__all__ = [
    "WallShape",
    "Plane",
    "Rectangle",
    "Revolved",
    "Disk",
    "Annulus",
    "CylinderTube",
    "Frustum",
    "Cylinder",
    "Sphere",
    "TriangleMesh",
    "box_planes",
]

# |u·n| above this is rejected as "not perpendicular"; below it u is re-orthogonalised exactly.
_PERP_TOL = 1e-6

ArrayLike3 = Sequence[float] | np.ndarray


# ---------------------------------------------------------------------------------------------
# validation helpers
# ---------------------------------------------------------------------------------------------


def _vec3(cls: str, name: str, value: object) -> np.ndarray:
    """A finite float64 3-vector, or GeometryError naming ``cls.name``."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise GeometryError(
            f"{cls}: {name} must be a 3-vector of numbers, got {value!r}; give three coordinates in metres"
        ) from exc
    if arr.shape != (3,):
        raise GeometryError(
            f"{cls}: {name} must be a 3-vector, got {value!r} (shape {arr.shape}); give exactly three numbers"
        )
    if not np.all(np.isfinite(arr)):
        raise GeometryError(f"{cls}: {name} must be finite, got {value!r}; replace inf/nan by finite numbers")
    return arr.copy()


def _unit(cls: str, name: str, value: object) -> np.ndarray:
    """Normalised direction vector; zero length raises GeometryError."""
    arr = _vec3(cls, name, value)
    norm = math.sqrt(float(arr @ arr))
    if not norm > 0.0:
        raise GeometryError(
            f"{cls}: {name} has zero length, got {value!r}; give a non-zero direction vector "
            f"(it is normalised automatically)"
        )
    return arr / norm


def _scalar(cls: str, name: str, value: object) -> float:
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError) as exc:
        raise GeometryError(f"{cls}: {name} must be a number, got {value!r}") from exc
    if not math.isfinite(v):
        raise GeometryError(f"{cls}: {name} must be finite, got {value!r}; give a finite length in metres")
    return v


def _positive(cls: str, name: str, value: object) -> float:
    v = _scalar(cls, name, value)
    if not v > 0.0:
        raise GeometryError(f"{cls}: {name} must be > 0, got {value!r}; give a positive length in metres")
    return v


def _nonnegative(cls: str, name: str, value: object) -> float:
    v = _scalar(cls, name, value)
    if v < 0.0:
        raise GeometryError(
            f"{cls}: {name} must be >= 0, got {value!r}; give a non-negative radius in metres"
        )
    return v


def _offset(offset: object) -> np.ndarray:
    return _vec3("offset", "offset", offset)


def _circle_halfwidth(axis: np.ndarray, radius: float) -> np.ndarray:
    """Half-extent per coordinate of a circle of ``radius`` perpendicular to the unit ``axis``.

    ρ sqrt(1 − E_k²) for each coordinate k.
    """
    return radius * np.sqrt(np.maximum(0.0, 1.0 - axis * axis))


# ---------------------------------------------------------------------------------------------
# base class
# ---------------------------------------------------------------------------------------------


class WallShape:
    """Base class of wall shapes; subclasses fill ``kind``, ``name_hint`` and ``_base_params``."""

    kind: int
    name_hint: str
    _base_params: np.ndarray
    _ref: np.ndarray

    def params(self, offset: ArrayLike3 = (0.0, 0.0, 0.0)) -> np.ndarray:
        """Parameter vector (length ``N_PARAMS``) of the shape translated by ``offset`` [m].

        Only the anchor point p[0:3] moves; directions and lengths are translation-invariant.
        """
        p = self._base_params.copy()
        p[0:3] += _offset(offset)
        return p

    @property
    def reference_point(self) -> np.ndarray:
        """Point about which torques on this wall are reported [m] (untranslated)."""
        return self._ref.copy()

    def bounding_box(self, offset: ArrayLike3 = (0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box ``(lo, hi)`` of the surface translated by ``offset`` [m]."""
        lo, hi = self._bbox()
        off = _offset(offset)
        return lo + off, hi + off

    def _bbox(self) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - abstract
        raise NotImplementedError

    #: named sizes a motion may change: name → parameter slots that hold it
    size_slots: dict[str, tuple[int, ...]] = {}

    def sizes(self) -> dict[str, float]:
        """The shape's named sizes [m] (``Wall.resize`` changes them)."""
        return {name: float(self._base_params[slots[0]]) for name, slots in self.size_slots.items()}

    def apply_size(self, rows: np.ndarray, name: str, value: float) -> None:
        """Write size ``name`` = ``value`` into the packed rows."""
        for slot in self.size_slots[name]:
            rows[:, slot] = value

    def __repr__(self) -> str:
        return f"{type(self).__name__}(kind={self.kind}, params={self._base_params[:11].tolist()})"


# ---------------------------------------------------------------------------------------------
# flat shapes
# ---------------------------------------------------------------------------------------------


class Plane(WallShape):
    """Infinite plane, one-sided: particles live on the side the unit ``normal`` points to.

    Params: [point(3), normal(3)]. A centre on the wrong side gets a large overlap and is pushed
    back along ``normal``. Reference point: ``point``.
    """

    kind = KIND_PLANE

    def __init__(self, point: ArrayLike3, normal: ArrayLike3, *, name_hint: str = "plane") -> None:
        self.point = _vec3("Plane", "point", point)
        self.normal = _unit("Plane", "normal", normal)
        self.name_hint = name_hint
        p = np.zeros(N_PARAMS)
        p[0:3] = self.point
        p[3:6] = self.normal
        self._base_params = p
        self._ref = self.point.copy()

    def _bbox(self) -> tuple[np.ndarray, np.ndarray]:
        lo = np.full(3, -np.inf)
        hi = np.full(3, np.inf)
        nz = np.flatnonzero(self.normal != 0.0)
        if nz.size == 1:  # axis-aligned plane: bounded in that coordinate
            k = int(nz[0])
            lo[k] = hi[k] = self.point[k]
        return lo, hi


class Rectangle(WallShape):
    """Finite flat plate (two-sided thin shell).

    Centre C, unit normal N, unit in-plane axis U (must be perpendicular to N), V = N × U,
    ``half_extents`` = (h_u, h_v) > 0: the plate is {C + a U + b V : |a| ≤ h_u, |b| ≤ h_v}.
    Params: [C(3), N(3), U(3), h_u, h_v]. Reference point: C.
    """

    kind = KIND_RECTANGLE
    size_slots = {"half_u": (9,), "half_v": (10,)}

    def __init__(
        self,
        center: ArrayLike3,
        normal: ArrayLike3,
        u_axis: ArrayLike3,
        half_extents: Sequence[float] | np.ndarray,
        *,
        name_hint: str = "rectangle",
    ) -> None:
        cls = "Rectangle"
        self.center = _vec3(cls, "center", center)
        self.normal = _unit(cls, "normal", normal)
        u = _unit(cls, "u_axis", u_axis)
        cosang = float(u @ self.normal)
        if abs(cosang) > _PERP_TOL:
            raise GeometryError(
                f"{cls}: u_axis {u_axis!r} is not perpendicular to normal {normal!r} "
                f"(cos angle = {cosang:.3g}); give an in-plane axis with u_axis . normal = 0"
            )
        u = u - cosang * self.normal
        self.u_axis = u / math.sqrt(float(u @ u))
        self.v_axis = np.cross(self.normal, self.u_axis)
        try:
            he = np.asarray(half_extents, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise GeometryError(f"{cls}: half_extents must be two numbers, got {half_extents!r}") from exc
        if he.shape != (2,):
            raise GeometryError(
                f"{cls}: half_extents must be two numbers (h_u, h_v), got {half_extents!r}; "
                f"give the half-lengths along u_axis and normal x u_axis"
            )
        self.half_extents = np.array(
            [_positive(cls, "half_extents[0]", he[0]), _positive(cls, "half_extents[1]", he[1])]
        )
        self.name_hint = name_hint
        p = np.zeros(N_PARAMS)
        p[0:3] = self.center
        p[3:6] = self.normal
        p[6:9] = self.u_axis
        p[9:11] = self.half_extents
        self._base_params = p
        self._ref = self.center.copy()

    def _bbox(self) -> tuple[np.ndarray, np.ndarray]:
        ext = self.half_extents[0] * np.abs(self.u_axis) + self.half_extents[1] * np.abs(self.v_axis)
        return self.center - ext, self.center + ext


# ---------------------------------------------------------------------------------------------
# surfaces of revolution
# ---------------------------------------------------------------------------------------------


class Revolved(WallShape):
    """General surface of revolution of the meridian segment (s0, ρ0)–(s1, ρ1) (two-sided, open).

    ``point`` A on the axis, unit ``axis`` E; s is measured along E from A, ρ ≥ 0 from the axis.
    Params: [A(3), E(3), s0, ρ0, s1, ρ1]. Reference point: A unless given.
    """

    kind = KIND_REVOLVED
    size_slots = {"s0": (6,), "rho0": (7,), "s1": (8,), "rho1": (9,)}

    def __init__(
        self,
        point: ArrayLike3,
        axis: ArrayLike3,
        s0: float,
        rho0: float,
        s1: float,
        rho1: float,
        *,
        name_hint: str = "revolved",
        reference_point: ArrayLike3 | None = None,
        _cls: str = "Revolved",
    ) -> None:
        self.point = _vec3(_cls, "point", point)
        self.axis = _unit(_cls, "axis", axis)
        self.s0 = _scalar(_cls, "s0", s0)
        self.s1 = _scalar(_cls, "s1", s1)
        self.rho0 = _nonnegative(_cls, "rho0", rho0)
        self.rho1 = _nonnegative(_cls, "rho1", rho1)
        if self.rho0 == 0.0 and self.rho1 == 0.0:
            raise GeometryError(
                f"{_cls}: rho0 = rho1 = 0 makes the surface degenerate into a segment of the axis; "
                f"give a positive radius at one end at least"
            )
        if self.s0 == self.s1 and self.rho0 == self.rho1:
            raise GeometryError(
                f"{_cls}: meridian segment ({self.s0}, {self.rho0})-({self.s1}, {self.rho1}) has zero "
                f"length; give two distinct end points"
            )
        self.name_hint = name_hint
        p = np.zeros(N_PARAMS)
        p[0:3] = self.point
        p[3:6] = self.axis
        p[6:10] = (self.s0, self.rho0, self.s1, self.rho1)
        self._base_params = p
        self._ref = (
            self.point.copy() if reference_point is None else _vec3(_cls, "reference_point", reference_point)
        )

    def _bbox(self) -> tuple[np.ndarray, np.ndarray]:
        # ρ and the circle centre are linear along the segment: the extremes are at the end circles
        c0 = self.point + self.s0 * self.axis
        c1 = self.point + self.s1 * self.axis
        w0 = _circle_halfwidth(self.axis, self.rho0)
        w1 = _circle_halfwidth(self.axis, self.rho1)
        return np.minimum(c0 - w0, c1 - w1), np.maximum(c0 + w0, c1 + w1)


class Disk(Revolved):
    """Flat disk of ``radius`` > 0 centred at ``center`` with unit ``normal`` (two-sided).

    Meridian (0, 0)–(0, R) about the normal. Reference point: ``center``.
    """

    def __init__(
        self, center: ArrayLike3, normal: ArrayLike3, radius: float, *, name_hint: str = "disk"
    ) -> None:
        radius = _positive("Disk", "radius", radius)
        super().__init__(center, normal, 0.0, 0.0, 0.0, radius, name_hint=name_hint, _cls="Disk")
        self.center = self.point
        self.normal = self.axis
        self.radius = radius

    size_slots = {"radius": (9,)}


class Annulus(Revolved):
    """Flat ring r_inner ≤ ρ ≤ r_outer centred at ``center`` with unit ``normal`` (two-sided).

    Requires 0 ≤ r_inner < r_outer. Meridian (0, r_inner)–(0, r_outer). Reference point: ``center``.
    """

    def __init__(
        self,
        center: ArrayLike3,
        normal: ArrayLike3,
        r_inner: float,
        r_outer: float,
        *,
        name_hint: str = "annulus",
    ) -> None:
        ri = _nonnegative("Annulus", "r_inner", r_inner)
        ro = _positive("Annulus", "r_outer", r_outer)
        if not ri < ro:
            raise GeometryError(
                f"Annulus: r_inner = {r_inner!r} must be < r_outer = {r_outer!r}; swap them or "
                f"use a Disk for r_inner = 0"
            )
        super().__init__(center, normal, 0.0, ri, 0.0, ro, name_hint=name_hint, _cls="Annulus")
        self.center = self.point
        self.normal = self.axis
        self.r_inner = ri
        self.r_outer = ro

    size_slots = {"r_inner": (7,), "r_outer": (9,)}


class CylinderTube(Revolved):
    """Finite open cylinder tube (two-sided, no caps) of ``radius`` and ``length``.

    Axis from ``base_center`` along the unit ``axis`` for ``length`` > 0: meridian (0, R)–(L, R).
    Reference point: the middle of the axis, base_center + (L/2) axis.
    """

    def __init__(
        self,
        base_center: ArrayLike3,
        axis: ArrayLike3,
        radius: float,
        length: float,
        *,
        name_hint: str = "tube",
    ) -> None:
        cls = "CylinderTube"
        radius = _positive(cls, "radius", radius)
        length = _positive(cls, "length", length)
        e = _unit(cls, "axis", axis)
        base = _vec3(cls, "base_center", base_center)
        super().__init__(
            base, e, 0.0, radius, length, radius, name_hint=name_hint,
            reference_point=base + 0.5 * length * e, _cls=cls,
        )  # fmt: skip
        self.base_center = self.point
        self.radius = radius
        self.length = length

    size_slots = {"radius": (7, 9), "length": (8,)}


class Frustum(Revolved):
    """Open conical frustum (two-sided, no caps); a cone when ``r0`` = 0.

    The end of radius ``r0`` is the circle centred at ``apex_side_center``; the end of radius ``r1``
    is centred at apex_side_center + ``length`` · axis (unit ``axis``, ``length`` > 0). So for a
    cone (r0 = 0) ``apex_side_center`` is the apex and the cone opens along +axis; a hopper with
    its outlet down is e.g. ``Frustum(outlet_center, (0, 0, 1), r_outlet, r_top, height)``.
    r0, r1 ≥ 0, not both zero; r0 = r1 gives a tube. Meridian (0, r0)–(L, r1).
    Reference point: ``apex_side_center``.
    """

    def __init__(
        self,
        apex_side_center: ArrayLike3,
        axis: ArrayLike3,
        r0: float,
        r1: float,
        length: float,
        *,
        name_hint: str = "frustum",
    ) -> None:
        cls = "Frustum"
        r0 = _nonnegative(cls, "r0", r0)
        r1 = _nonnegative(cls, "r1", r1)
        length = _positive(cls, "length", length)
        if r0 == 0.0 and r1 == 0.0:
            raise GeometryError(
                f"{cls}: r0 = r1 = 0 makes the surface degenerate into a line; give r1 > 0 for a cone "
                f"(apex at apex_side_center)"
            )
        super().__init__(apex_side_center, axis, 0.0, r0, length, r1, name_hint=name_hint, _cls=cls)
        self.apex_side_center = self.point
        self.r0 = r0
        self.r1 = r1
        self.length = length

    size_slots = {"r0": (7,), "r1": (9,), "length": (8,)}


# ---------------------------------------------------------------------------------------------
# infinite cylinder
# ---------------------------------------------------------------------------------------------


class Cylinder(WallShape):
    """Infinite circular cylinder, one-sided.

    ``inside=True``: particles live inside (ρ < R) and are pushed inwards; ``inside=False``: they
    live outside and are pushed outwards. Params: [point(3), axis(3), R, side = ±1].
    Reference point: ``point``.
    """

    kind = KIND_CYLINDER
    size_slots = {"radius": (6,)}

    def __init__(
        self,
        point: ArrayLike3,
        axis: ArrayLike3,
        radius: float,
        inside: bool = True,
        *,
        name_hint: str = "cylinder",
    ) -> None:
        cls = "Cylinder"
        self.point = _vec3(cls, "point", point)
        self.axis = _unit(cls, "axis", axis)
        self.radius = _positive(cls, "radius", radius)
        self.inside = bool(inside)
        self.name_hint = name_hint
        p = np.zeros(N_PARAMS)
        p[0:3] = self.point
        p[3:6] = self.axis
        p[6] = self.radius
        p[7] = 1.0 if self.inside else -1.0
        self._base_params = p
        self._ref = self.point.copy()

    def _bbox(self) -> tuple[np.ndarray, np.ndarray]:
        lo = np.full(3, -np.inf)
        hi = np.full(3, np.inf)
        bounded = self.axis == 0.0  # the surface is bounded only across the axis
        lo[bounded] = self.point[bounded] - self.radius
        hi[bounded] = self.point[bounded] + self.radius
        return lo, hi


# ---------------------------------------------------------------------------------------------
# sphere and triangle meshes
# ---------------------------------------------------------------------------------------------


class Sphere(WallShape):
    """Sphere of ``radius`` centred at ``center``, one-sided: particles live outside (``inside=False``,
    a ball: a penetrometer tip, an impactor) or inside (``inside=True``, a spherical container).
    Params: [C(3), R, side = +1 outside / −1 inside]. Reference point: the centre."""

    kind = KIND_SPHERE
    size_slots = {"radius": (3,)}

    def __init__(
        self, center: ArrayLike3, radius: float, inside: bool = False, *, name_hint: str = "sphere"
    ) -> None:
        cls = "Sphere"
        self.center = _vec3(cls, "center", center)
        self.radius = _positive(cls, "radius", radius)
        self.inside = bool(inside)
        self.name_hint = name_hint
        p = np.zeros(N_PARAMS)
        p[0:3] = self.center
        p[3] = self.radius
        p[4] = -1.0 if self.inside else 1.0
        self._base_params = p
        self._ref = self.center.copy()

    def _bbox(self) -> tuple[np.ndarray, np.ndarray]:
        return self.center - self.radius, self.center + self.radius


class TriangleMesh(WallShape):
    """A surface of triangles (two-sided facets): ``vertices`` (m, 3) [m] and ``triangles`` (k, 3)
    vertex indices, or a file read with meshio (:meth:`from_file`: STL, OBJ, VTK/VTU, PLY, … —
    triangles only; quads are split in two). Each facet is one row of the wall: its load is
    reported per facet (``Wall.facet_loads``), and a grain touching several facets of the mesh
    counts once (face contacts first; an edge or vertex contact only when the grain touches no face,
    and then only the closest). ``reference_point`` (default: the vertices' centroid) is where
    torques are reported and rotations turn about."""

    kind = KIND_TRIANGLE

    def __init__(self, vertices, triangles, *, reference_point: ArrayLike3 | None = None,
                 name_hint: str = "mesh") -> None:  # fmt: skip
        cls = "TriangleMesh"
        v = np.asarray(vertices, dtype=np.float64)
        t = np.asarray(triangles)
        if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] < 3 or not np.all(np.isfinite(v)):
            raise GeometryError(f"{cls}: vertices must be finite, of shape (m >= 3, 3); got {v.shape}")
        if t.ndim != 2 or t.shape[1] != 3 or t.shape[0] < 1 or not np.issubdtype(t.dtype, np.integer):
            raise GeometryError(
                f"{cls}: triangles must be integer vertex indices of shape (k, 3); got {t.shape}"
            )
        if t.min() < 0 or t.max() >= v.shape[0]:
            raise GeometryError(f"{cls}: triangle vertex indices must lie in [0, {v.shape[0] - 1}]")
        a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
        area2 = np.linalg.norm(np.cross(b - a, c - a), axis=1)
        scale = float(np.max(np.ptp(v, axis=0))) or 1.0
        bad = np.flatnonzero(area2 <= 1e-12 * scale * scale)
        if bad.size:
            raise GeometryError(
                f"{cls}: {bad.size} degenerate (zero-area) triangle(s), first #{int(bad[0])}; remove them "
                "from the mesh"
            )
        self.vertices = v
        self.triangles = t.astype(np.int64)
        self.name_hint = name_hint
        self._rows = np.zeros((t.shape[0], N_PARAMS))
        self._rows[:, 0:3] = a
        self._rows[:, 3:6] = b - a
        self._rows[:, 6:9] = c - a
        self._base_params = self._rows[0]
        self._ref = (
            v.mean(axis=0) if reference_point is None else _vec3(cls, "reference_point", reference_point)
        )

    @classmethod
    def from_file(cls, path, *, scale: float = 1.0, translate: ArrayLike3 = (0.0, 0.0, 0.0),
                  reference_point: ArrayLike3 | None = None,
                  name_hint: str = "mesh") -> TriangleMesh:  # fmt: skip
        """Read a triangle mesh with meshio; coordinates × ``scale`` + ``translate`` [m]."""
        import meshio

        try:
            mesh = meshio.read(path)
        except Exception as exc:  # noqa: BLE001 - any reader failure is a bad input file
            raise GeometryError(f"cannot read mesh file {path}: {type(exc).__name__}: {exc}") from None
        tris = [c.data for c in mesh.cells if c.type == "triangle"]
        tris += [c.data[:, [0, 1, 2]] for c in mesh.cells if c.type == "quad"]
        tris += [c.data[:, [0, 2, 3]] for c in mesh.cells if c.type == "quad"]
        if not tris:
            kinds = sorted({c.type for c in mesh.cells})
            raise GeometryError(f"mesh file {path} has no triangles (cell types: {kinds or 'none'})")
        pts = np.asarray(mesh.points, dtype=float)[:, :3] * float(scale) + np.asarray(translate, float)
        return cls(pts, np.concatenate(tris), reference_point=reference_point, name_hint=name_hint)

    def rows(self) -> tuple[np.ndarray, np.ndarray]:
        return np.full(self._rows.shape[0], KIND_TRIANGLE, dtype=np.int64), self._rows.copy()

    def params(self, offset: ArrayLike3 = (0.0, 0.0, 0.0)) -> np.ndarray:
        raise GeometryError("a TriangleMesh has one row per facet: use rows()")

    def _bbox(self) -> tuple[np.ndarray, np.ndarray]:
        return self.vertices.min(axis=0), self.vertices.max(axis=0)

    def __repr__(self) -> str:
        return f"TriangleMesh({self.vertices.shape[0]} vertices, {self.triangles.shape[0]} triangles)"


# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------


def box_planes(lo: ArrayLike3, hi: ArrayLike3) -> list[Plane]:
    """The six inward-facing one-sided planes of the axis-aligned box [lo, hi].

    Order: x-min (normal +x), x-max (−x), y-min, y-max, z-min, z-max; name hints
    ``"xmin"``, ``"xmax"``, ….
    """
    lo_a = _vec3("box_planes", "lo", lo)
    hi_a = _vec3("box_planes", "hi", hi)
    if not np.all(lo_a < hi_a):
        raise GeometryError(
            f"box_planes: lo = {lo_a.tolist()} must be < hi = {hi_a.tolist()} in every coordinate; "
            f"give the lower corner first"
        )
    planes: list[Plane] = []
    for k, ax in enumerate("xyz"):
        n = np.zeros(3)
        n[k] = 1.0
        planes.append(Plane(lo_a, n, name_hint=f"{ax}min"))
        planes.append(Plane(hi_a, -n, name_hint=f"{ax}max"))
    return planes

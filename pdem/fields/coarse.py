r"""Coarse-grained continuum fields of a :class:`pdem.Simulation` (the method of Goldhirsch 2010 and
Weinhart et al. 2012, as MercuryDPM's MercuryCG computes it).

A field at a point r is a sum over grains (or contacts) of a quantity times a kernel φ(r − x):

* density ρ = Σ m_i φ_i, solid fraction Σ V_i φ_i (V_i = 4/3 π r_i³), number density n = Σ φ_i;
* momentum density p = Σ m_i v_i φ_i, velocity V = p / ρ (0 where ρ = 0);
* kinetic stress σᵏ = Σ m_i v'_i ⊗ v'_i φ_i with v'_i = v_i − V(r), the fluctuation relative to the
  field velocity at the point r (Weinhart et al. 2012: the definition for which the momentum balance
  below holds exactly), evaluated as Σ m v ⊗ v φ − p ⊗ p / ρ from the exact sums;
* contact stress σᶜ_ab = Σ_pairs f_a b_b ∫₀¹ φ(r − x_i − s b) ds, f the force on grain j, b = x_j − x_i
  the branch vector (id_i < id_j, through the periodic face where they meet there), and for every
  wall contact σᶜ_ab += F_a l_b ∫₀¹ φ(r − x − s l) ds, F the force on the wall, l = (r − δ/2) n the
  lever from the grain centre x to the contact point (n the unit normal into the wall, δ the
  overlap: the point in the middle of the overlap, as the triaxial's Love–Weber sum takes it);
* stress σ = σᵏ + σᶜ; the wall force density t = Σ_wall contacts (−F) φ(r − c) (c the contact
  point), the force the walls apply to the material;
* velocity gradient (∇V)_ab = ∂_b V_a = (∂_b p_a − V_a ∂_b ρ) / ρ and strain rate
  D = (∇V + ∇Vᵀ) / 2, from the analytic kernel gradient ∇φ: the exact derivative of the CG field
  (no finite differences);
* contact density Σ_ends φ(r − x_end) (each pair counted at both grains' centres, a wall contact at
  its grain's), coordination Z = contact density / n, fabric F = Σ_ends n ⊗ n φ / n (trace Z).

Sign convention: **compression positive**, as pdem's triaxial measurement (``lw_szz``: Love–Weber
σ = (1/V) Σ branch ⊗ force over the pairs) has it, so an isotropically compressed packing has a
positive pressure. Weinhart et al. and the MercuryCG formulas write σ = −Σ m v'v' φ − Σ f_ij ⊗ r_ij ∫φ
with tension positive; pdem's σ is the negative of that. The first index is the force's, the
divergence is taken on the second: ∂_t p_a + ∂_b(ρ V_a V_b) = −∂_b σ_ab + ρ g_a + t_a holds exactly
for the CG fields whenever each grain's m a is the sum of its contact forces, its wall forces and its
weight (forces a boundary applies through ``apply_forces``, e.g. a membrane's, are in none of the
fields); at rest ∂_b σ_ab = ρ g_a + t_a.
The pair's order in σᶜ is the transpose of the triaxial's branch ⊗ force; their symmetric parts are
equal.

Kernels: :class:`GaussianKernel` (width w, cut off at ``cutoff`` widths, default 3, and normalised
after the cut so that it integrates to 1 over 3-D space) and :class:`LucyKernel` (Lucy's quartic
polynomial 105/(16π c³) (1 − 6q² + 8q³ − 3q⁴), q = |r|/c, of cut-off radius c; C² at the cut-off).
The line integral ∫₀¹ φ ds of a contact is computed **exactly** for both, in closed form: the chord of
the segment inside the cut-off sphere, then the Gaussian's erf (erfc on one side of the foot) or
Lucy's polynomial (its q³ term through asinh).

Partition-independent, exact sums
---------------------------------
Every field value is a sum of terms from grains and contacts that sit on different ranks. Each rank
adds only what it owns: its grains (``own_particles``), the pairs it counts (``own_contacts``: each
touching pair on exactly one rank) and its grains' wall contacts (``own_wall_contacts``). Every
point's sum is **exact**: the terms go into pdem's fixed-point accumulator
(:func:`pdem.parallel.exact.exact_add_many`), whose value does not depend on the order of the terms,
and the result is the correctly rounded value of their exact sum. So the fields are bitwise the same
on any rank count, any partition and any storage order.

Memory: an accumulator is 72 int64 (576 bytes). One per point and column (43 columns) would be
25 kB a point, 0.7 GB for a 30³ grid, so none is kept per point: the points are binned in cells of the
kernel's cut-off radius, every item (grain, contact line, contact end, wall contact point, and their
periodic images) is listed in the cells its support box overlaps, and the points are visited one at
a time, each with **one** set of accumulators (24 columns at most, 14 kB, reused) over the items of
its cell, in four passes (grains, contact lines, contact ends, wall contact points). When a point
is done each column's sum is rounded once, or, on several ranks, reduced to the few doubles whose
sum it is (its nonzero 32-bit digits, typically 2–5).

On several ranks the cells (the same on every rank: they depend on the points and the kernel only)
tell who may reach a point: one small ``Allgather`` of a bit per cell and pass says which cells hold
items of more than one rank. A point of a cell only one rank has items in is rounded by that rank
at once. The partials of the points of shared cells (the ranks' cut planes ± a kernel radius) go to
the point's owner (the points are cut into one block per rank; one ``alltoall``), which rounds the
exact sum of all ranks' partials (``math.fsum``'s algorithm, :func:`pdem.fields._kernels.fsum_exact`).
Every value is then held by exactly one rank and is 0.0 on the others, so one ``Allreduce`` (or
``Reduce`` to ``root``) sum of the (m, 43) array hands it on unchanged (x + 0.0 = x). Cost per rank:
the item lists (each item in ~27 cells, 8 bytes an entry), the (m, 43) result array, and the partials
of the shared cells' points it reached (~4 doubles and 2 words per point and column); nothing scales
with the product of points and items. Time: per term a kernel evaluation and one fixed-point
addition (~4 ns), per point and column a rounding (~0.3 µs); contact lines cost most (a closed-form
line integral, ~0.15 µs each); see ``docs/fields.md``.

Periodic boxes (``sim.box``) are handled: positions are wrapped into the box (exactly, on pdem's
position grid) and every item whose support reaches the points through a periodic face is repeated
at its images (x + k L), so a grain near a face contributes to points across it, and points outside
the box see the periodic continuation. The field is the periodic one even when the cut-off exceeds
half the box (several images then reach a point).

DEM-C (law ``complementarity``): ``own_contacts`` and ``own_wall_contacts`` report forces, the last
step's impulses divided by the step h (``complementarity/_kernels.py: contact_forces``), as DEM-P
reports its penalty forces; the fields use them alike. Both methods end a step with the ghosts
(other ranks' grains, periodic images) at their owners' positions, so branch vectors to ghosts are
the same on every rank count.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, fields

import numpy as np

from ..errors import InputError
from ..parallel.comm import any_rank
from ..state.particles import REMOVED
from . import _kernels as _k

__all__ = [
    "GaussianKernel", "LucyKernel", "Grid", "CylindricalGrid", "cylindrical_components", "Fields",
    "CoarseGraining", "TimeAverage", "coarse_grain",
]  # fmt: skip

#: raw column layout: (name, first column, number of columns)
_GRAIN0, _LINE0, _END0, _POINT0 = 0, 24, 33, 40
N_RAW = 43
#: every field a :class:`CoarseGraining` computes, in :class:`Fields` order
QUANTITIES = (
    "density", "solid_fraction", "number_density", "momentum", "velocity", "kinetic_stress",
    "contact_stress", "stress", "velocity_gradient", "strain_rate", "contact_density", "coordination",
    "fabric", "wall_force_density",
)  # fmt: skip
#: the grains' columns (a prefix) each field needs beyond ρ, φ and n (3)
_GRAIN_COLUMNS = {
    "momentum": 6, "velocity": 6, "kinetic_stress": 12, "stress": 12, "velocity_gradient": 24,
    "strain_rate": 24,
}  # fmt: skip
#: the pass beyond the grains' that each field needs (GRAIN: none)
_NEEDS = {q: _k.GRAIN for q in QUANTITIES} | {
    "contact_stress": _k.LINE, "stress": _k.LINE, "contact_density": _k.END, "coordination": _k.END,
    "fabric": _k.END, "wall_force_density": _k.POINT,
}  # fmt: skip
_SYM = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))  # order of the 6 symmetric components
_MAX_ITEMS = 50_000_000  # items after periodic images; beyond, refuse (memory)


def _positive(name: str, value, remedy: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} = {value!r} is not a number; {remedy}") from None
    if not (math.isfinite(v) and v > 0.0):
        raise InputError(f"{name} = {value!r} must be positive and finite; {remedy}")
    return v


# ---------------------------------------------------------------------------------------------
# kernels
# ---------------------------------------------------------------------------------------------


class GaussianKernel:
    """φ(r) = A exp(−|r|²/(2w²)) for |r| < ``cutoff`` w, 0 beyond; A makes ∫φ dV = 1 after the cut:
    1/A = 4π w³ (√(π/2) erf(C/√2) − C e^{−C²/2}), C = ``cutoff``.

    ``width`` w [m]: typically the grain radius to diameter. ``cutoff`` [widths]: 3 by default (the
    kernel then jumps by 1.1 % of its peak at the cut); a larger value makes the fields smooth to
    round-off (9: a jump of 3·10⁻¹⁸)."""

    kind = _k.GAUSS

    def __init__(self, width: float, cutoff: float = 3.0) -> None:
        self.width = _positive(
            "GaussianKernel width", width, "give the kernel width in metres, e.g. the grain radius"
        )
        self.cutoff = _positive("GaussianKernel cutoff", cutoff, "give the cut-off in widths, e.g. 3")
        if self.cutoff < 1.0:
            raise InputError(
                f"GaussianKernel cutoff = {cutoff!r} widths is below 1: the kernel would be nearly flat "
                "inside its support; give at least 1 (3 is usual), or use LucyKernel(radius)"
            )
        cc = self.cutoff
        inner = math.sqrt(0.5 * math.pi) * math.erf(cc / math.sqrt(2.0)) - cc * math.exp(-0.5 * cc * cc)
        self.norm = 1.0 / (4.0 * math.pi * self.width**3 * inner)

    @property
    def radius(self) -> float:
        """The support's radius [m]: cutoff × width."""
        return self.cutoff * self.width

    def __call__(self, r) -> np.ndarray:
        """φ at distances ``r`` [m] (a NumPy reference, for scripts and tests)."""
        r = np.asarray(r, dtype=float)
        return np.where(r < self.radius, self.norm * np.exp(-0.5 * (r / self.width) ** 2), 0.0)

    def __repr__(self) -> str:
        return f"GaussianKernel(width={self.width!r}, cutoff={self.cutoff!r})"


class LucyKernel:
    """Lucy's polynomial φ(r) = 105/(16π c³) (1 − 6q² + 8q³ − 3q⁴), q = |r|/c < 1 (0 beyond): it
    integrates to 1, and it and its first two derivatives vanish at the cut-off radius c [m]. Its
    standard deviation along an axis is c/√12: the Gaussian of width w has the same for c = √12 w."""

    kind = _k.LUCY
    width = 0.0  #: unused (the kernels' common interface: a Gaussian's width)

    def __init__(self, radius: float) -> None:
        self._radius = _positive(
            "LucyKernel radius", radius, "give the cut-off radius in metres, e.g. 2 grain diameters"
        )
        self.norm = 105.0 / (16.0 * math.pi * self._radius**3)

    @property
    def radius(self) -> float:
        return self._radius

    def __call__(self, r) -> np.ndarray:
        q = np.asarray(r, dtype=float) / self._radius
        return np.where(q < 1.0, self.norm * (1.0 - 6.0 * q**2 + 8.0 * q**3 - 3.0 * q**4), 0.0)

    def __repr__(self) -> str:
        return f"LucyKernel(radius={self._radius!r})"


# ---------------------------------------------------------------------------------------------
# where the fields are evaluated
# ---------------------------------------------------------------------------------------------


class Grid:
    """A regular grid: the centres of ``counts`` = (nx, ny, nz) equal cells dividing the box
    ``lo``–``hi`` [m], lo + (i + ½) (hi − lo)/n along each axis. Fields on it have the shape
    (nx, ny, nz, …) (C order: z fastest). The mean of a field over the nodes is its midpoint-rule
    average over the box."""

    def __init__(self, lo: Sequence[float], hi: Sequence[float], counts: Sequence[int]) -> None:
        lo_a = np.asarray(lo, dtype=float).reshape(-1) if _is_numeric(lo) else None
        hi_a = np.asarray(hi, dtype=float).reshape(-1) if _is_numeric(hi) else None
        if lo_a is None or lo_a.shape != (3,) or not np.all(np.isfinite(lo_a)):
            raise InputError(f"Grid lo = {lo!r} must be three finite numbers (x, y, z) [m]")
        if hi_a is None or hi_a.shape != (3,) or not np.all(np.isfinite(hi_a)):
            raise InputError(f"Grid hi = {hi!r} must be three finite numbers (x, y, z) [m]")
        if not np.all(hi_a > lo_a):
            raise InputError(f"Grid hi = {hi!r} must exceed lo = {lo!r} along every axis; swap or widen them")
        n = _counts(counts, "Grid", "(nx, ny, nz)")
        self.lo, self.hi, self.counts = lo_a, hi_a, n
        self.spacing = (hi_a - lo_a) / np.array(n)

    @property
    def shape(self) -> tuple[int, int, int]:
        return self.counts

    @property
    def cell_volume(self) -> float:
        return float(np.prod(self.spacing))

    def axes(self) -> list[np.ndarray]:
        """The node coordinates along x, y and z."""
        return [self.lo[a] + (np.arange(self.counts[a]) + 0.5) * (self.hi[a] - self.lo[a]) / self.counts[a]
                for a in range(3)]  # fmt: skip

    def points(self) -> np.ndarray:
        """The nodes, (nx·ny·nz, 3), z fastest."""
        gx, gy, gz = np.meshgrid(*self.axes(), indexing="ij")
        return np.ascontiguousarray(np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1))

    def __repr__(self) -> str:
        return f"Grid(lo={self.lo.tolist()}, hi={self.hi.tolist()}, counts={self.counts})"


class CylindricalGrid:
    """A cylindrical grid about an upright axis (the triaxial cell's, a hopper's, a cone's): the
    centres of ``counts`` = (nr, nθ, nz) equal cells in r, θ and z of the ring ``inner_radius`` ≤ r ≤
    ``radius``, 0 ≤ θ < 2π, of height ``height`` above ``base_center`` (x, y, z) [m] (as the deck's
    cylinder region). Node (i, j, k) is at r = r_in + (i + ½) Δr, θ = (j + ½) 2π/nθ (from +x towards
    +y), z = z₀ + (k + ½) Δz. Fields on it have the shape (nr, nθ, nz, …) (C order: z fastest), in
    Cartesian components; :meth:`cylindrical` turns vectors and tensors into (r, θ, z) ones. A node
    stands for the volume :meth:`node_volumes` (r Δr Δθ Δz), so Σ f·V over the nodes is the
    midpoint-rule integral over the ring."""

    def __init__(
        self,
        base_center: Sequence[float],
        radius: float,
        height: float,
        counts: Sequence[int],
        inner_radius: float = 0.0,
    ) -> None:
        c = np.asarray(base_center, dtype=float).reshape(-1) if _is_numeric(base_center) else None
        if c is None or c.shape != (3,) or not np.all(np.isfinite(c)):
            raise InputError(
                f"CylindricalGrid base_center = {base_center!r} must be three finite numbers (x, y, z) [m]"
            )
        self.radius = _positive("CylindricalGrid radius", radius, "give the outer radius in metres")
        self.height = _positive("CylindricalGrid height", height, "give the height in metres")
        try:
            r_in = float(inner_radius)
        except (TypeError, ValueError):
            r_in = math.nan
        if not (math.isfinite(r_in) and 0.0 <= r_in < self.radius):
            raise InputError(
                f"CylindricalGrid inner_radius = {inner_radius!r} must be at least 0 and below radius = "
                f"{radius!r} m"
            )
        n = _counts(counts, "CylindricalGrid", "(nr, nθ, nz)")
        self.base_center = c
        self.inner_radius = r_in
        self.counts = n
        self.spacing = np.array([(self.radius - r_in) / n[0], 2.0 * math.pi / n[1], self.height / n[2]])

    @property
    def shape(self) -> tuple[int, int, int]:
        return self.counts

    def axes(self) -> list[np.ndarray]:
        """The node coordinates along r [m], θ [rad] and z [m]."""
        nr, nt, nz = self.counts
        return [
            self.inner_radius + (np.arange(nr) + 0.5) * (self.radius - self.inner_radius) / nr,
            (np.arange(nt) + 0.5) * (2.0 * math.pi / nt),
            self.base_center[2] + (np.arange(nz) + 0.5) * self.height / nz,
        ]

    def points(self) -> np.ndarray:
        """The nodes in x, y, z, (nr·nθ·nz, 3), z fastest."""
        r, t, z = np.meshgrid(*self.axes(), indexing="ij")
        x = self.base_center[0] + r * np.cos(t)
        y = self.base_center[1] + r * np.sin(t)
        return np.ascontiguousarray(np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1))

    def node_volumes(self) -> np.ndarray:
        """The volume each node stands for, r Δr Δθ Δz [m³], shape (nr, nθ, nz)."""
        r = self.axes()[0]
        v = r * float(np.prod(self.spacing))
        return np.broadcast_to(v[:, None, None], self.counts).copy()

    def cylindrical(self, values: np.ndarray) -> np.ndarray:
        """Vectors (nr, nθ, nz, 3) or tensors (nr, nθ, nz, 3, 3) of this grid in the local (r, θ, z)
        components: v' = Q v, T' = Q T Qᵀ with the rows of Q the unit vectors e_r, e_θ, e_z."""
        return cylindrical_components(values, self.points().reshape(*self.counts, 3), self.base_center)

    def __repr__(self) -> str:
        return (
            f"CylindricalGrid(base_center={self.base_center.tolist()}, radius={self.radius!r}, "
            f"height={self.height!r}, counts={self.counts}, inner_radius={self.inner_radius!r})"
        )


def cylindrical_components(values, points, center) -> np.ndarray:
    """Vectors (…, 3) or tensors (…, 3, 3) at ``points`` (…, 3) in the local cylindrical components
    (r, θ, z) about the upright axis through ``center`` (x, y[, z]): v' = Q v and T' = Q T Qᵀ, the
    rows of Q being e_r = (cos θ, sin θ, 0), e_θ = (−sin θ, cos θ, 0) and e_z. On the axis itself
    (r = 0) θ is taken as 0."""
    v = np.asarray(values, dtype=float)
    p = np.asarray(points, dtype=float)
    c = np.asarray(center, dtype=float).reshape(-1)
    theta = np.arctan2(p[..., 1] - c[1], p[..., 0] - c[0])
    cos, sin = np.cos(theta), np.sin(theta)
    q = np.zeros((*theta.shape, 3, 3))
    q[..., 0, 0], q[..., 0, 1] = cos, sin
    q[..., 1, 0], q[..., 1, 1] = -sin, cos
    q[..., 2, 2] = 1.0
    lead = theta.ndim
    if v.shape == (*theta.shape, 3):
        return np.einsum("...ab,...b->...a", q, v)
    if v.shape == (*theta.shape, 3, 3):
        return np.einsum("...ab,...bc,...dc->...ad", q, v, q)
    raise InputError(
        f"cylindrical_components: values of shape {v.shape} must be vectors {(*theta.shape, 3)} or "
        f"tensors {(*theta.shape, 3, 3)} at the {lead}-dimensional points' shape {theta.shape}"
    )


def _counts(counts, what: str, axes: str) -> tuple[int, int, int]:
    """A grid's three positive cell counts, or an InputError naming them."""
    try:
        n = [int(c) for c in counts]
        ok = len(n) == 3 and all(int(c) == c for c in counts)
    except (TypeError, ValueError):
        ok = False
    if not ok or min(n) < 1:
        raise InputError(f"{what} counts = {counts!r} must be three positive integers {axes}")
    return tuple(n)


def _is_numeric(v) -> bool:
    try:
        np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        return False
    return True


def _points_of(where) -> tuple[np.ndarray, tuple[int, ...]]:
    if isinstance(where, Grid | CylindricalGrid):
        return where.points(), where.shape
    if not _is_numeric(where):
        raise InputError(
            f"where = {where!r}: give a Grid(lo, hi, counts), a CylindricalGrid(base_center, radius, "
            "height, counts) or an (m, 3) array of points [m]"
        )
    pts = np.asarray(where, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] < 1:
        raise InputError(
            f"where: points of shape {pts.shape} must be an (m, 3) array with m ≥ 1, "
            "or use Grid(lo, hi, counts)"
        )
    if not np.all(np.isfinite(pts)):
        raise InputError("where: the points must be finite (one or more is NaN or infinite)")
    return np.ascontiguousarray(pts), (pts.shape[0],)


# ---------------------------------------------------------------------------------------------
# results
# ---------------------------------------------------------------------------------------------


@dataclass
class Fields:
    """Coarse-grained fields at the points (shape ``shape`` = the grid's (nx, ny, nz) or (m,) for
    points; vectors add an axis of 3, tensors two). SI units; stresses compression positive; tensor
    index order: σ_ab = Σ f_a l_b … (module docstring). A field the :class:`CoarseGraining` was not
    asked for (``quantities``) is None."""

    points: np.ndarray  #: (…, 3) [m]
    density: np.ndarray  #: ρ [kg/m³]
    solid_fraction: np.ndarray  #: Σ V φ [-]
    number_density: np.ndarray  #: Σ φ [1/m³]
    momentum: np.ndarray  #: p = Σ m v φ [kg/(m² s)]
    velocity: np.ndarray  #: V = p/ρ [m/s] (0 where ρ = 0)
    kinetic_stress: np.ndarray  #: σᵏ [Pa]
    contact_stress: np.ndarray  #: σᶜ [Pa] (pairs and walls)
    stress: np.ndarray  #: σᵏ + σᶜ [Pa]
    velocity_gradient: np.ndarray  #: ∂_b V_a [1/s] (0 where ρ = 0)
    strain_rate: np.ndarray  #: (∇V + ∇Vᵀ)/2 [1/s]
    contact_density: np.ndarray  #: Σ_ends φ [1/m³]
    coordination: np.ndarray  #: contact density / number density [-] (0 where n = 0)
    fabric: np.ndarray  #: Σ_ends n ⊗ n φ / n [-] (trace: coordination)
    wall_force_density: np.ndarray  #: Σ (−F_wall) φ(r − c) [N/m³]
    time: float = 0.0  #: the simulation time [s]
    step: int = 0  #: the step count

    def arrays(self) -> dict[str, np.ndarray]:
        """Every field by name (the points included)."""
        return {
            f.name: getattr(self, f.name)
            for f in fields(self)
            if isinstance(getattr(self, f.name), np.ndarray)
        }


def _derive(
    raw: np.ndarray, points: np.ndarray, shape: tuple[int, ...], time: float, step: int,
    quantities: Sequence[str] = QUANTITIES,
) -> Fields:
    """The fields from the exact sums (elementwise arithmetic only: the same bits wherever done);
    those not in ``quantities`` are None."""
    m = raw.shape[0]
    want = set(quantities)
    rho, solid, num = raw[:, 0], raw[:, 1], raw[:, 2]
    mom = raw[:, 3:6]
    pos = rho > 0.0
    safe = np.where(pos, rho, 1.0)
    has_n = num > 0.0
    nsafe = np.where(has_n, num, 1.0)
    got: dict[str, np.ndarray] = {"density": rho, "solid_fraction": solid, "number_density": num}
    got["momentum"] = mom
    if want & {"velocity", "kinetic_stress", "stress", "velocity_gradient", "strain_rate"}:
        got["velocity"] = vel = np.where(pos[:, None], mom / safe[:, None], 0.0)
    if want & {"kinetic_stress", "stress"}:
        pp = mom[:, :, None] * mom[:, None, :]
        kin = _sym_full(raw[:, 6:12])
        got["kinetic_stress"] = np.where(pos[:, None, None], kin - pp / safe[:, None, None], 0.0)
    if want & {"contact_stress", "stress"}:
        got["contact_stress"] = raw[:, _LINE0 : _LINE0 + 9].reshape(m, 3, 3)
    if "stress" in want:
        got["stress"] = got["kinetic_stress"] + got["contact_stress"]
    if want & {"velocity_gradient", "strain_rate"}:
        grho = raw[:, 12:15]
        gmom = raw[:, 15:24].reshape(m, 3, 3)
        got["velocity_gradient"] = grad = np.where(
            pos[:, None, None], (gmom - vel[:, :, None] * grho[:, None, :]) / safe[:, None, None], 0.0
        )
        got["strain_rate"] = 0.5 * (grad + grad.transpose(0, 2, 1))
    got["contact_density"] = ncont = raw[:, _END0]
    if "coordination" in want:
        got["coordination"] = np.where(has_n, ncont / nsafe, 0.0)
    if "fabric" in want:
        fab = _sym_full(raw[:, _END0 + 1 : _END0 + 7])
        got["fabric"] = np.where(has_n[:, None, None], fab / nsafe[:, None, None], 0.0)
    got["wall_force_density"] = raw[:, _POINT0 : _POINT0 + 3]
    tails = {"momentum": (3,), "velocity": (3,), "wall_force_density": (3,)}

    def s(name: str) -> np.ndarray | None:
        if name not in want:
            return None
        a = got[name]
        tail = tails.get(name, (3, 3) if a.ndim == 3 else ())
        return np.ascontiguousarray(a.reshape(*shape, *tail))

    return Fields(
        points=np.ascontiguousarray(points.reshape(*shape, 3)),
        **{q: s(q) for q in QUANTITIES},
        time=float(time),
        step=int(step),
    )


def _sym_full(six: np.ndarray) -> np.ndarray:
    out = np.empty((six.shape[0], 3, 3))
    for c, (a, b) in enumerate(_SYM):
        out[:, a, b] = six[:, c]
        out[:, b, a] = six[:, c]
    return out


# ---------------------------------------------------------------------------------------------
# the computation
# ---------------------------------------------------------------------------------------------


class CoarseGraining:
    """Fields of a simulation with ``kernel`` (:class:`GaussianKernel` or :class:`LucyKernel`) at
    ``where`` (a :class:`Grid`, a :class:`CylindricalGrid` or an (m, 3) array of points [m]);
    ``walls``: include the wall contacts (stress, contact density, fabric, wall force density). The
    points are binned once; call the object with a simulation for each snapshot."""

    def __init__(self, kernel, where, *, walls: bool = True, quantities=None) -> None:
        if not isinstance(kernel, GaussianKernel | LucyKernel):
            raise InputError(
                f"kernel = {kernel!r}: give GaussianKernel(width, cutoff=3) or LucyKernel(radius) "
                "from pdem.fields"
            )
        self.kernel = kernel
        self.where = where
        self.walls = bool(walls)
        if quantities is None:
            self.quantities = QUANTITIES
        else:
            names = [quantities] if isinstance(quantities, str) else list(quantities)
            bad = [q for q in names if q not in QUANTITIES]
            if bad or not names:
                raise InputError(
                    f"quantities = {quantities!r}: give some of {', '.join(QUANTITIES)} (or None: all)"
                )
            self.quantities = tuple(q for q in QUANTITIES if q in names)
        #: the grains' columns the quantities need (a prefix of the 24: ρ, φ, n; p; Σ m v v; ∇)
        self.grain_columns = max(_GRAIN_COLUMNS.get(q, 3) for q in self.quantities)
        #: the passes the quantities need: the grains always, the contact lines for the contact
        #: stress, the contact ends for the contact density and fabric, the wall points for the wall
        #: force density; the contacts are not even listed when no pass needs them
        self.kinds = tuple(
            kind for kind in (_k.GRAIN, _k.LINE, _k.END, _k.POINT)
            if kind == _k.GRAIN or any(_NEEDS[q] == kind for q in self.quantities)
        )  # fmt: skip
        self.points, self.shape = _points_of(where)
        self._bin_points()

    def _bin_points(self) -> None:
        pts = self.points
        self.lo = pts.min(axis=0)
        self.hi = pts.max(axis=0)
        s = self.kernel.radius
        span = self.hi - self.lo
        while True:  # cells of the cut-off radius, fewer than ~4 per point (scattered points)
            per_axis = np.floor(span / s) + 1.0  # in floats: a far-flung grid would overflow int64
            if float(np.prod(per_axis)) <= 4 * pts.shape[0] + 64:
                ncell = per_axis.astype(np.int64)
                break
            s *= 2.0
        self.cell = s
        self.ncell = ncell
        cells = _k.bin_points(pts, self.lo, 1.0 / s, ncell)
        self.order = np.argsort(cells, kind="stable")
        count = np.bincount(cells, minlength=int(np.prod(ncell)))
        self.pstart = np.concatenate([[0], np.cumsum(count)]).astype(np.int64)

    # ------------------------------------------------------------------ items of this rank
    def _items(self, sim) -> dict[int, np.ndarray]:
        """This rank's items by kind (rows as in :mod:`pdem.fields._kernels`), before images."""
        if self.kinds == (_k.GRAIN,):  # the grains in storage order (the sums do not depend on it)
            st = sim.particles
            n = st.n_owned
            live = st.motion[:n] != REMOVED
            p = {"x": st.x[:n][live], "id": st.id[:n][live], "r": st.r[:n][live], "mass": st.mass[:n][live],
                 "v": st.v[:n][live]}  # fmt: skip
        else:
            p = sim.own_particles()  # by id: the contacts' grains are found by their ids
        x = np.ascontiguousarray(p["x"], dtype=float)
        if sim.box is not None:
            sim.box.wrap(x)  # exact (pdem's position grid): the same bits whatever the partition
        ids, r = p["id"], p["r"]
        grains = np.empty((len(ids), 8))
        grains[:, 0:3] = x
        grains[:, 3] = p["mass"]
        grains[:, 4] = (4.0 / 3.0) * math.pi * r**3
        grains[:, 5:8] = p["v"]

        def rows_of(want: np.ndarray) -> np.ndarray:
            k = np.searchsorted(ids, want)
            if want.size and (k.max() >= ids.size or not np.array_equal(ids[k], want)):
                raise RuntimeError("coarse graining: a counted contact's grain is not owned by this rank")
            return k

        if self.kinds == (_k.GRAIN,):  # no contact is needed: none is listed
            none = np.zeros((0, 15))
            return {_k.GRAIN: grains, _k.LINE: none, _k.END: none[:, :6], _k.POINT: none[:, :6]}
        c = sim.own_contacts()
        xi = x[rows_of(c["id_i"])]
        b = np.asarray(c["branch"], dtype=float)
        f = np.asarray(c["force"], dtype=float)
        lines = [np.concatenate([xi, b, (f[:, :, None] * b[:, None, :]).reshape(-1, 9)], axis=1)]
        bl = np.linalg.norm(b, axis=1)
        nrm = b / np.where(bl > 0.0, bl, 1.0)[:, None]
        ends = [np.concatenate([xi, nrm], axis=1), np.concatenate([xi + b, nrm], axis=1)]
        pts = [np.zeros((0, 6))]
        if self.walls and len(sim.walls):
            wc = sim.own_wall_contacts()
            if wc["id"].size:
                walls = list(sim.walls.values())
                kinds = np.array(
                    [walls[k].kinds[q] for k, q in zip(wc["wall"], wc["row"], strict=True)], np.int64
                )
                params = np.ascontiguousarray(
                    [walls[k].rows[q] for k, q in zip(wc["wall"], wc["row"], strict=True)]
                )
                xw = np.ascontiguousarray(x[rows_of(wc["id"])])
                rw = np.ascontiguousarray(wc["r"], dtype=float)
                nw = _k.wall_normals(kinds, params, xw, rw)
                lever = (rw - 0.5 * wc["overlap"])[:, None] * nw
                fw = np.asarray(wc["force"], dtype=float)
                lines.append(
                    np.concatenate([xw, lever, (fw[:, :, None] * lever[:, None, :]).reshape(-1, 9)], axis=1)
                )
                ends.append(np.concatenate([xw, nw], axis=1))
                pts.append(np.concatenate([xw + lever, -fw], axis=1))
        return {
            _k.GRAIN: grains,
            _k.LINE: np.concatenate(lines),
            _k.END: np.concatenate(ends),
            _k.POINT: np.concatenate(pts),
        }

    def _support(self, kind: int, data: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        reach = self.kernel.radius * (1.0 + 1e-12)
        lo, hi = data[:, 0:3].copy(), data[:, 0:3].copy()
        if kind == _k.LINE:
            end = data[:, 0:3] + data[:, 3:6]
            lo, hi = np.minimum(lo, end), np.maximum(hi, end)
        return lo - reach, hi + reach

    def _images(self, sim, kind: int, data: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The items and their periodic images that reach the points' box, with support boxes; None
        if there would be more than :data:`_MAX_ITEMS`."""
        lo, hi = self._support(kind, data)
        box = sim.box
        if box is None or not np.any(box.periodic):  # one mask: the items whose support meets the box
            keep = np.all((hi >= self.lo) & (lo <= self.hi), axis=1)
            return np.ascontiguousarray(data[keep]), lo[keep], hi[keep]
        for a in range(3):
            if box is not None and box.periodic[a]:
                length = float(box.length[a])
                kmin = np.ceil((self.lo[a] - hi[:, a]) / length).astype(np.int64)
                kmax = np.floor((self.hi[a] - lo[:, a]) / length).astype(np.int64)
                count = np.maximum(kmax - kmin + 1, 0)
                total = int(count.sum())
                if total > _MAX_ITEMS:
                    return None  # refused on every rank by the caller
                rep = np.repeat(np.arange(len(data)), count)
                start = np.concatenate([[0], np.cumsum(count)[:-1]]) if len(count) else np.zeros(0, np.int64)
                k = kmin[rep] + (np.arange(total) - start[rep])
                shift = k * length
                moved = k != 0
                data, lo, hi = data[rep], lo[rep], hi[rep]
                for arr in (data, lo, hi):
                    arr[moved, a] = arr[moved, a] + shift[moved]
            else:
                keep = (hi[:, a] >= self.lo[a]) & (lo[:, a] <= self.hi[a])
                data, lo, hi = data[keep], lo[keep], hi[keep]
        return np.ascontiguousarray(data), lo, hi

    # ------------------------------------------------------------------ the fields
    def __call__(self, sim, *, root: int | None = None) -> Fields | None:
        """The fields of ``sim``'s current state (collective: every rank calls it). ``root``: None
        gives every rank the fields; a rank number gives them to that rank only (the others get
        None). Prepares the simulation if needed (the first forces) and checks a deferred step."""
        comm = sim.comm
        if root is not None and not (isinstance(root, int | np.integer) and 0 <= int(root) < comm.size):
            raise InputError(f"root = {root!r} must be None or a rank number from 0 to {comm.size - 1}")
        raw, parts = self._raw(sim)
        if comm.size > 1:
            raw = _reduce_over_ranks(comm, raw, parts, root, self.block_bounds(comm.size))
        if raw is None:
            return None
        raw += 0.0  # −0.0 → +0.0, as an MPI sum with other ranks' zeros makes it: the same bits anywhere
        return _derive(raw, self.points, self.shape, sim.time, sim.step_count, self.quantities)

    def _raw(self, sim) -> tuple[np.ndarray, list]:
        """This rank's sums (collective): the (m, N_RAW) values it rounded (points only it reaches)
        and the partials of the points of shared cells, per pass."""
        comm = sim.comm
        sim.prepare()
        sim.check_deferred()
        items = self._items(sim)
        kern = self.kernel
        m = self.points.shape[0]
        inv_s = 1.0 / self.cell
        ncells = self.pstart.size - 1
        passes = []
        col0s = {_k.GRAIN: _GRAIN0, _k.LINE: _LINE0, _k.END: _END0, _k.POINT: _POINT0}
        for kind in self.kinds:
            col0 = col0s[kind]
            imaged = self._images(sim, kind, items[kind])
            if imaged is None:
                break
            data, lo, hi = imaged
            istart, lists = _k.bin_items(lo, hi, self.lo, inv_s, self.ncell)
            passes.append((kind, col0, data, istart, lists))
        if any_rank(comm, len(passes) < len(self.kinds)):
            box = sim.box.length[sim.box.periodic] if sim.box is not None else ()
            raise InputError(
                f"coarse graining: more than {_MAX_ITEMS} items with their periodic images (kernel radius "
                f"{kern.radius:.3g} m, periodic lengths {', '.join(f'{v:.3g}' for v in box)} m); use a "
                "smaller kernel, or points closer to the box"
            )
        shared = _shared_cells(comm, [np.diff(ps[3]) > 0 for ps in passes], ncells)
        raw = np.zeros((m, N_RAW))
        parts = []
        for (kind, col0, data, istart, lists), sh in zip(passes, shared, strict=True):
            ncols = self.grain_columns if kind == _k.GRAIN else _k.N_COLUMNS[kind]
            res = _k.accumulate(
                kind, kern.kind, kern.norm, kern.width, kern.radius, self.points, self.order, self.pstart,
                istart, lists, data, sh, raw, col0, ncols,
            )  # fmt: skip
            parts.append((col0, ncols, res))
        return raw, parts

    def block_bounds(self, size: int) -> np.ndarray:
        """The points' cut into ``size`` blocks, one per rank: point indices ``bounds[k]`` to
        ``bounds[k + 1]`` are rank k's. On a grid the cuts fall between planes of its first axis (x,
        or r), so that each block is a slab of whole planes (a grid of its own); otherwise into equal
        counts."""
        m = self.points.shape[0]
        if len(self.shape) == 3:  # a Grid or a CylindricalGrid
            nx = self.shape[0]
            plane = m // nx
            return np.array([(nx * k // size) * plane for k in range(size + 1)], dtype=np.int64)
        return np.array([m * k // size for k in range(size + 1)], dtype=np.int64)

    def block(self, sim, *, overlap: bool = True) -> tuple[Fields, int]:
        """This rank's block of the fields (collective): ``(fields, first)``, the fields at points
        ``first`` to ``first + n`` of the flattened points (on a grid, the slab of first-axis planes
        ``first // (ny nz)`` on, of shape (planes, ny, nz, …)). No rank holds another's block: the
        ranks' sums meet at the blocks' owners (one ``Reduce_scatter``). ``overlap``: on a grid, a
        block also holds the next non-empty block's first plane, so that slabs drawn side by side
        leave no gap. The values are bitwise those of ``self(sim)`` at the same points on any rank
        count. Serially the block is every point."""
        comm = sim.comm
        size = comm.size
        bounds = self.block_bounds(size)
        if size == 1:
            return self(sim), 0
        raw = self._raw_block(sim, bounds)
        b0 = int(bounds[comm.rank])
        grid = len(self.shape) == 3  # a Grid or a CylindricalGrid: blocks of whole planes
        plane = self.points.shape[0] // self.shape[0] if grid else 0
        if grid and overlap:
            counts = np.diff(bounds)
            nonempty = [k for k in range(size) if counts[k] > 0]
            send: list = [None] * size
            me = comm.rank
            if me in nonempty and nonempty.index(me) > 0:
                send[nonempty[nonempty.index(me) - 1]] = raw[:plane].copy()
            got = comm.alltoall(send)
            extra = [g for g in got if g is not None]
            if extra:
                raw = np.concatenate([raw, extra[0]])
        n = raw.shape[0]
        shape = (n // plane, *self.shape[1:]) if grid else (n,)
        raw += 0.0
        fields = _derive(raw, self.points[b0 : b0 + n], shape, sim.time, sim.step_count, self.quantities)
        return fields, b0

    def _raw_block(self, sim, bounds: np.ndarray) -> np.ndarray:
        """The exact sums of this rank's block of points, ``bounds[rank]`` to ``bounds[rank + 1]``."""
        comm = sim.comm
        raw, parts = self._raw(sim)
        return _reduce_over_ranks(comm, raw, parts, "blocks", bounds)


def _shared_cells(comm, has: list[np.ndarray], ncells: int) -> list[np.ndarray]:
    """Per item kind, the cells where more than one rank has items (uint8 flags; one collective)."""
    if comm.size == 1:
        return [np.zeros(ncells, dtype=np.uint8) for _ in has]
    mine = np.packbits(np.concatenate(has).astype(np.uint8))
    every = np.empty((comm.size, mine.size), dtype=np.uint8)
    comm.Allgather(mine, every)
    count = np.unpackbits(every, axis=1, count=len(has) * ncells).sum(axis=0, dtype=np.int64)
    return [
        np.ascontiguousarray(count[k * ncells : (k + 1) * ncells] > 1).astype(np.uint8)
        for k in range(len(has))
    ]


def _reduce_over_ranks(comm, raw: np.ndarray, parts, root, bounds: np.ndarray) -> np.ndarray | None:
    """The fields of every point from the ranks' shares (module docstring): a point only one rank
    reaches (its cell has no other rank's items) was rounded by that rank; the partials of the
    points of shared cells go to the point's owner (one block of points per rank), which rounds
    their exact sum. Every value is then held by exactly one rank (the others hold 0.0), so an MPI
    sum gives it unchanged. ``bounds``: the owners' blocks (:meth:`CoarseGraining.block_bounds`);
    ``root``: None (every rank gets every value), a rank (that rank only), or ``"blocks"`` (each rank
    its own block, by ``Reduce_scatter``)."""
    size = comm.size
    pts, cols, cnts, vals, specs = [], [], [], [], []
    for col0, nq, (tp, cnt, val, spc) in parts:
        pts.append(np.repeat(tp, nq))
        cols.append(np.tile(np.arange(col0, col0 + nq, dtype=np.int64), tp.size))
        cnts.append(cnt)
        vals.append(val)
        specs.append(spc)
    pt, col, cnt = np.concatenate(pts), np.concatenate(cols), np.concatenate(cnts)
    val, spc = np.concatenate(vals), np.concatenate(specs)
    dest = np.searchsorted(bounds, pt, side="right") - 1
    vdest = np.repeat(dest, cnt)
    send = []
    for d in range(size):
        sel = dest == d
        send.append((pt[sel], col[sel], cnt[sel], val[vdest == d], spc[sel]))
    got = comm.alltoall(send)
    rpt = np.concatenate([g[0] for g in got])
    rcol = np.concatenate([g[1] for g in got])
    rcnt = np.concatenate([g[2] for g in got])
    rval = np.concatenate([g[3] for g in got])
    rspc = np.concatenate([g[4] for g in got])
    keys = rpt * N_RAW + rcol
    ptr = np.concatenate([[0], np.cumsum(rcnt)]).astype(np.int64)
    flat = raw.reshape(-1)
    _k.combine_rows(keys, ptr, rval, rspc, np.argsort(keys, kind="stable"), flat)
    from mpi4py import MPI

    if root is None:
        comm.Allreduce(MPI.IN_PLACE, flat, op=MPI.SUM)
        return raw
    if root == "blocks":
        counts = np.diff(bounds) * N_RAW
        mine = np.empty(int(counts[comm.rank]))
        comm.Reduce_scatter(flat, mine, recvcounts=counts.tolist(), op=MPI.SUM)
        return mine.reshape(-1, N_RAW)
    if comm.rank == root:
        comm.Reduce(MPI.IN_PLACE, flat, op=MPI.SUM, root=root)
        return raw
    comm.Reduce(flat, None, op=MPI.SUM, root=root)
    return None


def coarse_grain(
    sim, kernel, where, *, walls: bool = True, root: int | None = None, quantities=None
) -> Fields | None:
    """The coarse-grained fields of ``sim`` with ``kernel`` at ``where`` (a :class:`Grid`, a
    :class:`CylindricalGrid` or an (m, 3) array of points) — :class:`CoarseGraining` for one
    snapshot (collective)."""
    return CoarseGraining(kernel, where, walls=walls, quantities=quantities)(sim, root=root)


# ---------------------------------------------------------------------------------------------
# time averages
# ---------------------------------------------------------------------------------------------


class TimeAverage:
    """The mean of every field over snapshots: ``add(sim)`` at each snapshot (collective), then
    ``mean()``. Each field is averaged as it is (so the mean kinetic stress is the mean of the
    snapshots' fluctuations about their own field velocity, as MercuryCG's time averages are); the
    sums run in snapshot order, on the bits every rank count gives, so the means are the same on
    any rank count too."""

    def __init__(self, kernel, where, *, walls: bool = True, quantities=None) -> None:
        self.cg = CoarseGraining(kernel, where, walls=walls, quantities=quantities)
        self.count = 0
        self._sum: dict[str, np.ndarray] | None = None
        self.t_first = math.nan
        self.t_last = math.nan

    def add(self, sim) -> Fields:
        """Adds the fields of ``sim``'s current state (collective); returns them."""
        f = self.cg(sim)
        arrays = f.arrays()
        if self._sum is None:
            self._sum = {k: v.copy() for k, v in arrays.items()}
            self.t_first = f.time
        else:
            for k, v in arrays.items():
                self._sum[k] += v
        self.t_last = f.time
        self.count += 1
        return f

    def mean(self) -> Fields:
        """The mean fields (``time``: the mean snapshot time; ``step``: the number of snapshots)."""
        if self._sum is None:
            raise InputError("TimeAverage.mean(): no snapshot was added; call add(sim) first")
        arrays = {k: v / self.count for k, v in self._sum.items() if k != "points"}
        arrays |= {q: None for q in QUANTITIES if q not in arrays}
        arrays["points"] = self.cg.points.reshape(*self.cg.shape, 3).copy()
        return Fields(**arrays, time=0.5 * (self.t_first + self.t_last), step=self.count)

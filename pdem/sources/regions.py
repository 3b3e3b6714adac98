"""Regions that particle sources fill: an axis-aligned box and an upright cylinder.

A region knows its volume and bounding box, tests whether spheres lie *fully* inside it
(vectorised) and draws uniform random points in it. :func:`spatial_order` is the one ordering
rule every source uses so that particle ids (assigned in array order) are spatially coherent.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pdem.errors import GeometryError, InputError

__all__ = ["Region", "BoxRegion", "CylinderRegion", "spatial_order"]


def _vec3(value: ArrayLike, name: str) -> NDArray[np.float64]:
    """``value`` as a finite float64 3-vector, or an :class:`InputError` naming ``name``."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(
            f"{name} = {value!r} is not a 3-vector of numbers; give three coordinates in metres, "
            f"e.g. {name}=(0.0, 0.0, 0.0)"
        ) from None
    if arr.shape != (3,):
        raise InputError(
            f"{name} = {value!r} has shape {arr.shape}, expected 3 coordinates (x, y, z) in metres"
        )
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name} = {value!r} contains a non-finite coordinate; give finite values")
    return arr


def _positive(value: float, name: str) -> float:
    """``value`` as a finite float > 0, or an :class:`InputError` naming ``name``."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} = {value!r} is not a number; give a positive length in metres") from None
    if not math.isfinite(v) or v <= 0.0:
        raise InputError(f"{name} = {value!r} must be a finite length > 0 (metres)")
    return v


def _sphere_args(x: ArrayLike, r: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Broadcast centres ``x`` (n,3) or (3,) and radii ``r`` (n,) or scalar to (n,3), (n,)."""
    xa = np.asarray(x, dtype=np.float64)
    if xa.ndim == 1:
        xa = xa[None, :]
    if xa.ndim != 2 or xa.shape[1] != 3:
        raise InputError(f"x has shape {np.shape(x)}, expected (n, 3) sphere centres")
    ra = np.broadcast_to(np.asarray(r, dtype=np.float64), (xa.shape[0],))
    return xa, ra


class Region:
    """Base class of fillable regions (see :class:`BoxRegion`, :class:`CylinderRegion`)."""

    @property
    def volume(self) -> float:  # pragma: no cover - abstract
        """Volume in m³."""
        raise NotImplementedError

    @property
    def bounds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:  # pragma: no cover
        """Axis-aligned bounding box ``(lo, hi)``, each a float64 3-vector."""
        raise NotImplementedError

    def contains_spheres(self, x: ArrayLike, r: ArrayLike, tol: float = 0.0) -> NDArray[np.bool_]:
        """Whether each sphere (centre ``x`` (n,3), radius ``r``) lies fully inside (n,) bool.

        ``tol`` (m) loosens the test so that spheres touching the boundary to within round-off
        count as inside.
        """
        raise NotImplementedError  # pragma: no cover

    def sample(self, rng: np.random.Generator, n: int) -> NDArray[np.float64]:
        """``n`` points drawn uniformly in the region, (n,3) float64."""
        raise NotImplementedError  # pragma: no cover

    def max_sphere_radius(self) -> float:
        """Radius of the largest sphere that fits in the region."""
        raise NotImplementedError  # pragma: no cover

    def _rsa_spec(self) -> tuple[int, NDArray[np.float64]]:
        """``(kind, params)`` describing the region to the random-fill kernel."""
        raise NotImplementedError  # pragma: no cover


class BoxRegion(Region):
    """Axis-aligned box ``lo <= x <= hi`` (metres)."""

    __slots__ = ("lo", "hi")

    def __init__(self, lo: Sequence[float] | ArrayLike, hi: Sequence[float] | ArrayLike) -> None:
        lo_a = _vec3(lo, "lo")
        hi_a = _vec3(hi, "hi")
        if np.any(hi_a <= lo_a):
            bad = "xyz"[int(np.argmax(hi_a <= lo_a))]
            raise GeometryError(
                f"BoxRegion: hi = {hi_a.tolist()} is not above lo = {lo_a.tolist()} along {bad}; "
                "every component of hi must exceed the matching component of lo"
            )
        self.lo = lo_a
        self.hi = hi_a
        self.lo.setflags(write=False)
        self.hi.setflags(write=False)

    def __repr__(self) -> str:
        return f"BoxRegion(lo={self.lo.tolist()}, hi={self.hi.tolist()})"

    @property
    def volume(self) -> float:
        """Volume in m³."""
        return float(np.prod(self.hi - self.lo))

    @property
    def bounds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``(lo, hi)`` copies."""
        return self.lo.copy(), self.hi.copy()

    def contains_spheres(self, x: ArrayLike, r: ArrayLike, tol: float = 0.0) -> NDArray[np.bool_]:
        """Whether each sphere lies fully inside the box (within ``tol`` metres)."""
        xa, ra = _sphere_args(x, r)
        rr = ra[:, None] - tol
        return np.all((xa - rr >= self.lo) & (xa + rr <= self.hi), axis=1)

    def sample(self, rng: np.random.Generator, n: int) -> NDArray[np.float64]:
        """``n`` uniform points in the box."""
        return self.lo + rng.random((int(n), 3)) * (self.hi - self.lo)

    def max_sphere_radius(self) -> float:
        """Half the smallest edge."""
        return float(0.5 * np.min(self.hi - self.lo))

    def _rsa_spec(self) -> tuple[int, NDArray[np.float64]]:
        return 0, np.concatenate([self.lo, self.hi])


class CylinderRegion(Region):
    """Upright circular cylinder: axis along +z from ``base_center``, given radius and height."""

    __slots__ = ("base_center", "radius", "height")

    def __init__(self, base_center: Sequence[float] | ArrayLike, radius: float, height: float) -> None:
        self.base_center = _vec3(base_center, "base_center")
        self.base_center.setflags(write=False)
        self.radius = _positive(radius, "radius")
        self.height = _positive(height, "height")

    def __repr__(self) -> str:
        return (
            f"CylinderRegion(base_center={self.base_center.tolist()}, radius={self.radius!r}, "
            f"height={self.height!r})"
        )

    @property
    def volume(self) -> float:
        """π R² h in m³."""
        return math.pi * self.radius**2 * self.height

    @property
    def bounds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Bounding box of the cylinder."""
        c = self.base_center
        lo = np.array([c[0] - self.radius, c[1] - self.radius, c[2]])
        hi = np.array([c[0] + self.radius, c[1] + self.radius, c[2] + self.height])
        return lo, hi

    def contains_spheres(self, x: ArrayLike, r: ArrayLike, tol: float = 0.0) -> NDArray[np.bool_]:
        """Whether each sphere lies fully inside the cylinder (within ``tol`` metres)."""
        xa, ra = _sphere_args(x, r)
        c = self.base_center
        rr = ra - tol
        rho2 = (xa[:, 0] - c[0]) ** 2 + (xa[:, 1] - c[1]) ** 2
        room = self.radius - rr
        radial = (room >= 0.0) & (rho2 <= room * room)
        axial = (xa[:, 2] - rr >= c[2]) & (xa[:, 2] + rr <= c[2] + self.height)
        return radial & axial

    def sample(self, rng: np.random.Generator, n: int) -> NDArray[np.float64]:
        """``n`` uniform points in the cylinder (area-uniform in the disc, uniform in z)."""
        u = rng.random((int(n), 3))
        rho = self.radius * np.sqrt(u[:, 0])
        theta = 2.0 * math.pi * u[:, 1]
        c = self.base_center
        out = np.empty((int(n), 3))
        out[:, 0] = c[0] + rho * np.cos(theta)
        out[:, 1] = c[1] + rho * np.sin(theta)
        out[:, 2] = c[2] + self.height * u[:, 2]
        return out

    def max_sphere_radius(self) -> float:
        """min(R, h/2)."""
        return min(self.radius, 0.5 * self.height)

    def _rsa_spec(self) -> tuple[int, NDArray[np.float64]]:
        c = self.base_center
        return 1, np.array([c[0], c[1], c[2], self.radius, self.height])


def spatial_order(
    positions: ArrayLike, cell_size: float, origin: ArrayLike | None = None
) -> NDArray[np.int64]:
    """Permutation that sorts points by cell (z, then y, then x), then by z, y, x inside a cell.

    ``cell_size`` (m) is the edge of the cubic cells, ``origin`` their corner (defaults to the
    minimum of the points). The result is deterministic: equal inputs give equal permutations,
    and ties are broken by the original index (stable sort).
    """
    x = np.asarray(positions, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3:
        raise InputError(f"positions has shape {x.shape}, expected (n, 3)")
    if x.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    h = _positive(cell_size, "cell_size")
    o = x.min(axis=0) if origin is None else _vec3(origin, "origin")
    cells = np.floor((x - o) / h).astype(np.int64)
    order = np.lexsort((x[:, 0], x[:, 1], x[:, 2], cells[:, 0], cells[:, 1], cells[:, 2]))
    return order.astype(np.int64)

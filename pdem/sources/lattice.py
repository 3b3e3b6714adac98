"""Regular packings of equal spheres: simple cubic, fcc, hcp in a region, hexagonal in a plane.

``spacing`` is the centre-to-centre distance of nearest neighbours and defaults to ``2 * radius``
(touching spheres). The 3-D lattices are anchored so that a sphere touches the low corner of the
region's bounding box (centre at ``lo + radius``) and keep only spheres fully inside the region.
Points are generated layer by layer (z, then y, then x), which is the id order.

All functions return ``(positions, radii)``: (n,3) and (n,) float64 arrays.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pdem.errors import GeometryError, InputError

from .regions import Region, _vec3

__all__ = ["simple_cubic", "fcc", "hcp", "hex2d", "lattice_layers"]

_Arrays = tuple[NDArray[np.float64], NDArray[np.float64]]


def _check_radius_spacing(radius: float, spacing: float | None) -> tuple[float, float]:
    try:
        r = float(radius)
    except (TypeError, ValueError):
        raise InputError(f"radius = {radius!r} is not a number; give a radius in metres (> 0)") from None
    if not math.isfinite(r) or r <= 0.0:
        raise InputError(f"radius = {radius!r} must be a finite radius > 0 (metres)")
    if spacing is None:
        return r, 2.0 * r
    try:
        s = float(spacing)
    except (TypeError, ValueError):
        raise InputError(f"spacing = {spacing!r} is not a number; give a distance in metres") from None
    if not math.isfinite(s) or s <= 0.0:
        raise InputError(f"spacing = {spacing!r} must be a finite distance > 0 (metres)")
    if s < 2.0 * r * (1.0 - 1e-12):
        raise GeometryError(
            f"spacing = {s!r} is smaller than the diameter 2*radius = {2.0 * r!r}: neighbouring "
            "spheres would overlap; use spacing >= 2*radius (or omit it for touching spheres)"
        )
    return r, s


def _check_region(region: Region) -> None:
    if not isinstance(region, Region):
        raise InputError(f"region = {region!r} is not a pdem region; pass a BoxRegion or CylinderRegion")


def _n_steps(length: float, step: float) -> int:
    """Number of lattice steps that fit in ``length`` (>= -1; -1 means nothing fits)."""
    return int(math.floor(length / step + 1e-9))


def _finish(
    region: Region, name: str, radius: float, spacing: float, idx: NDArray[np.int64], pos: NDArray[np.float64]
) -> _Arrays:
    """Sort by integer lattice index (z, y, x), keep spheres inside ``region``."""
    order = np.lexsort((idx[:, 0], idx[:, 1], idx[:, 2]))
    pos = pos[order]
    keep = region.contains_spheres(pos, radius, tol=1e-9 * spacing)
    pos = np.ascontiguousarray(pos[keep])
    if pos.shape[0] == 0:
        raise GeometryError(
            f"{name}: no sphere of radius {radius!r} fits in {region!r} with spacing {spacing!r}; "
            "use a larger region or smaller spheres"
        )
    return pos, np.full(pos.shape[0], radius, dtype=np.float64)


def _index_grid(n: NDArray[np.int64]) -> NDArray[np.int64]:
    """All integer triples 0 <= (i, j, k) <= n, as (m, 3), z-major."""
    k, j, i = np.meshgrid(np.arange(n[2] + 1), np.arange(n[1] + 1), np.arange(n[0] + 1), indexing="ij")
    return np.stack([i.ravel(), j.ravel(), k.ravel()], axis=1).astype(np.int64)


def _setup(region: Region, radius: float, spacing: float | None, name: str):
    _check_region(region)
    r, s = _check_radius_spacing(radius, spacing)
    lo, hi = region.bounds
    room = hi - lo - 2.0 * r
    if np.any(room < -1e-9 * s):
        raise GeometryError(
            f"{name}: a sphere of radius {r!r} does not fit in {region!r} (bounding box edges "
            f"{(hi - lo).tolist()} m); use a larger region or smaller spheres"
        )
    return r, s, lo + r, np.maximum(room, 0.0)


def simple_cubic(region: Region, radius: float, spacing: float | None = None) -> _Arrays:
    """Simple cubic lattice of spheres (6 neighbours at ``spacing``) filling ``region``."""
    r, s, origin, room = _setup(region, radius, spacing, "simple_cubic")
    n = np.array([_n_steps(L, s) for L in room], dtype=np.int64)
    idx = _index_grid(n)
    pos = origin + idx * s
    return _finish(region, "simple_cubic", r, s, idx, pos)


def fcc(region: Region, radius: float, spacing: float | None = None) -> _Arrays:
    """Face-centred cubic lattice (12 neighbours at ``spacing``; φ = π/(3√2) when touching).

    Cube faces are aligned with the axes; the cubic cell edge is ``spacing * √2``.
    """
    r, s, origin, room = _setup(region, radius, spacing, "fcc")
    h = s / math.sqrt(2.0)  # half the cubic cell edge
    n = np.array([_n_steps(L, h) for L in room], dtype=np.int64)
    idx = _index_grid(n)
    idx = idx[(idx.sum(axis=1) % 2) == 0]
    pos = origin + idx * h
    return _finish(region, "fcc", r, s, idx, pos)


def hcp(region: Region, radius: float, spacing: float | None = None) -> _Arrays:
    """Hexagonal close packing, ABAB stacking along z (12 neighbours at ``spacing``).

    Inside a layer, rows run along x (pitch ``spacing``), are ``spacing·√3/2`` apart in y and
    odd rows are shifted by ``spacing/2``; B layers are shifted by ``(spacing/2, spacing·√3/6)``
    and layers are ``spacing·√(2/3)`` apart.
    """
    r, s, origin, room = _setup(region, radius, spacing, "hcp")
    dy = s * math.sqrt(3.0) / 2.0
    dz = s * math.sqrt(2.0 / 3.0)
    nx = _n_steps(room[0], s)
    ny = _n_steps(room[1], dy)
    nz = _n_steps(room[2], dz)
    # one extra column so that shifted rows can still reach the +x side of the box
    idx = _index_grid(np.array([nx + 1, ny + 1, nz], dtype=np.int64))
    i, j, k = idx[:, 0], idx[:, 1], idx[:, 2]
    kb = k % 2
    pos = np.empty(idx.shape, dtype=np.float64)
    pos[:, 0] = origin[0] + (i + 0.5 * ((j + kb) % 2)) * s
    pos[:, 1] = origin[1] + (j + kb / 3.0) * dy
    pos[:, 2] = origin[2] + k * dz
    return _finish(region, "hcp", r, s, idx, pos)


_PLANES = {"xy": (0, 1), "xz": (0, 2), "yz": (1, 2)}


def hex2d(
    n_cols: int,
    n_rows: int,
    radius: float,
    origin: ArrayLike = (0.0, 0.0, 0.0),
    plane: str = "xz",
    spacing: float | None = None,
) -> _Arrays:
    """2-D hexagonal close packing of ``n_rows`` × ``n_cols`` spheres in a coordinate plane.

    ``plane`` names the column axis then the row axis (``"xz"``: rows run along x and are stacked
    along z). Sphere ``(col, row)`` has its centre at ``origin + (col + (row % 2)/2) * spacing``
    along the first axis and ``origin + row * spacing·√3/2`` along the second; every row holds
    ``n_cols`` spheres, odd rows shifted by half a spacing. Order: row by row, then column.
    """
    r, s = _check_radius_spacing(radius, spacing)
    for name, v in (("n_cols", n_cols), ("n_rows", n_rows)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise InputError(f"hex2d: {name} = {v!r} must be an integer >= 1")
    if plane not in _PLANES:
        raise InputError(f"hex2d: plane = {plane!r} is not one of {sorted(_PLANES)}")
    o = _vec3(origin, "origin")
    a0, a1 = _PLANES[plane]
    row, col = np.meshgrid(np.arange(n_rows), np.arange(n_cols), indexing="ij")
    row = row.ravel()
    col = col.ravel()
    pos = np.tile(o, (row.size, 1))
    pos[:, a0] += (col + 0.5 * (row % 2)) * s
    pos[:, a1] += row * (s * math.sqrt(3.0) / 2.0)
    return pos, np.full(row.size, r, dtype=np.float64)


def lattice_layers(kind: str, region: Region, radius: float, spacing: float | None = None):
    """The spheres of :func:`simple_cubic`, :func:`fcc` or :func:`hcp` (``kind`` "sc", "fcc", "hcp"),
    one layer of constant lattice index k (z) at a time, in their id order: concatenated, the
    layers' positions are bitwise the function's (tests check it). Yields (n, 3) position arrays
    (possibly empty); memory is one layer's, so a partitioned source can place 10⁸ spheres."""
    if kind not in ("sc", "fcc", "hcp"):
        raise InputError(f"lattice_layers: kind = {kind!r} is not one of 'sc', 'fcc', 'hcp'")
    name = {"sc": "simple_cubic", "fcc": "fcc", "hcp": "hcp"}[kind]
    r, s, origin, room = _setup(region, radius, spacing, name)
    if kind == "sc":
        n = np.array([_n_steps(L, s) for L in room], dtype=np.int64)
        step = s
    elif kind == "fcc":
        step = s / math.sqrt(2.0)
        n = np.array([_n_steps(L, step) for L in room], dtype=np.int64)
    else:
        dy, dz = s * math.sqrt(3.0) / 2.0, s * math.sqrt(2.0 / 3.0)
        n = np.array([_n_steps(room[0], s) + 1, _n_steps(room[1], dy) + 1, _n_steps(room[2], dz)], np.int64)
    j, i = np.meshgrid(np.arange(n[1] + 1), np.arange(n[0] + 1), indexing="ij")
    i, j = i.ravel().astype(np.int64), j.ravel().astype(np.int64)  # (j, i) order: y rows, then x
    for k in range(int(n[2]) + 1):
        kk = np.full(i.shape, k, dtype=np.int64)
        if kind == "hcp":
            kb = kk % 2
            pos = np.empty((i.shape[0], 3), dtype=np.float64)
            pos[:, 0] = origin[0] + (i + 0.5 * ((j + kb) % 2)) * s
            pos[:, 1] = origin[1] + (j + kb / 3.0) * dy
            pos[:, 2] = origin[2] + kk * dz
        else:
            idx = np.stack([i, j, kk], axis=1)
            if kind == "fcc":
                idx = idx[(idx.sum(axis=1) % 2) == 0]
            pos = origin + idx * step
        keep = region.contains_spheres(pos, r, tol=1e-9 * s)
        yield np.ascontiguousarray(pos[keep])

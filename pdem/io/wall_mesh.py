r"""Triangle meshes of walls for visualisation.

:func:`wall_triangles` turns a wall (``kind`` + 16-float ``params``, see
:mod:`pdem.geometry._kernels`) into ``(points, triangles)``:

* plane (infinite): the section of the plane by the scene box ``bounds`` — a convex polygon of
  3 to 6 vertices, triangulated as a fan from its first vertex; triangles face the particle side
  (+N). A plane that misses the box gives an empty mesh.
* rectangle: its 4 corners, 2 triangles facing +N.
* revolved segment (disk, annulus, tube, cone, frustum): ``resolution`` segments around the axis;
  an end of radius 0 is a single apex vertex. One band of triangles along the meridian (the
  surface is ruled, so this is exact up to the polygonal approximation of the circles).
* infinite cylinder: a tube covering the axial extent of ``bounds`` (the range of (corner − A)·E
  over the 8 box corners).

Circles are inscribed polygons, so areas are slightly low: the relative deficit is about
(2π/resolution)²/6 for flat disks (0.29 % at 48) and (π/resolution)²/6 for tubes (0.07 %).
All lengths are in metres.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ..errors import OutputError
from ..geometry._kernels import (
    KIND_CYLINDER,
    KIND_NAMES,
    KIND_PLANE,
    KIND_RECTANGLE,
    KIND_REVOLVED,
    KIND_SPHERE,
    KIND_TRIANGLE,
    N_PARAMS,
)

__all__ = ["wall_triangles", "mesh_area"]

# The 12 edges of a box whose corner k has coordinates (k & 1, k >> 1 & 1, k >> 2 & 1).
_BOX_EDGES = [(a, a | bit) for bit in (1, 2, 4) for a in range(8) if not a & bit]


def _empty() -> tuple[np.ndarray, np.ndarray]:
    return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)


def _perp_frame(e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors U, V with (U, V, E) right-handed; U is ``unit_perp(E)`` of the kernels."""
    a = np.abs(e)
    k = 0 if (a[0] <= a[1] and a[0] <= a[2]) else (1 if a[1] <= a[2] else 2)
    q = -e[k] * e
    q[k] += 1.0
    u = q / math.sqrt(float(q @ q))
    return u, np.cross(e, u)


def _check_bounds(kind: int, bounds: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    what = f"{KIND_NAMES[kind]} wall"
    try:
        lo = np.asarray(bounds[0], dtype=np.float64).reshape(3)
        hi = np.asarray(bounds[1], dtype=np.float64).reshape(3)
    except (TypeError, ValueError, IndexError) as exc:
        raise OutputError(
            f"cannot draw an infinite {what}: bounds {bounds!r} are not two 3-vectors (lo, hi); "
            f"give the scene box as (lo, hi) in metres"
        ) from exc
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo < hi)):
        raise OutputError(
            f"cannot draw an infinite {what}: the scene bounds lo = {lo.tolist()}, hi = {hi.tolist()} "
            f"must be finite with lo < hi in every coordinate; set a finite scene box (domain) so "
            f"that planes and infinite cylinders can be clipped to it"
        )
    return lo, hi


def _box_corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    k = np.arange(8)
    bits = np.stack([k & 1, (k >> 1) & 1, (k >> 2) & 1], axis=1).astype(bool)
    return np.where(bits, hi, lo)


def _plane_patch(p: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    point = p[0:3]
    n = p[3:6]
    corners = _box_corners(lo, hi)
    diag = float(np.linalg.norm(hi - lo))
    tol = 1e-10 * diag
    d = (corners - point) @ n
    d[np.abs(d) <= tol] = 0.0  # corners on the plane (a plane on a face of the box) count as hits
    cand: list[np.ndarray] = []
    for a, b in _BOX_EDGES:
        if d[a] == 0.0:
            cand.append(corners[a])
        if d[b] == 0.0:
            cand.append(corners[b])
        if d[a] * d[b] < 0.0:
            t = d[a] / (d[a] - d[b])
            cand.append(corners[a] + t * (corners[b] - corners[a]))
    pts: list[np.ndarray] = []
    for q in cand:
        q = q - float((q - point) @ n) * n  # exactly onto the plane
        if all(float(np.linalg.norm(q - k)) > 1e-9 * diag for k in pts):
            pts.append(q)
    if len(pts) < 3:
        return _empty()
    poly = np.array(pts)
    u, v = _perp_frame(n)
    rel = poly - poly.mean(axis=0)
    order = np.argsort(np.arctan2(rel @ v, rel @ u), kind="stable")
    poly = poly[order]
    m = poly.shape[0]
    tri = np.array([[0, i, i + 1] for i in range(1, m - 1)], dtype=np.int64)
    if mesh_area(poly, tri) <= (1e-9 * diag) ** 2:  # the plane only touches an edge or a corner
        return _empty()
    return poly, tri


def _rectangle(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c, n, u = p[0:3], p[3:6], p[6:9]
    hu, hv = float(p[9]), float(p[10])
    v = np.cross(n, u)
    pts = np.array([c - hu * u - hv * v, c + hu * u - hv * v, c + hu * u + hv * v, c - hu * u + hv * v])
    return pts, np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int64)


def _revolved(
    a: np.ndarray, e: np.ndarray, s0: float, r0: float, s1: float, r1: float, resolution: int
) -> tuple[np.ndarray, np.ndarray]:
    u, v = _perp_frame(e)
    theta = 2.0 * math.pi * np.arange(resolution) / resolution
    radial = np.cos(theta)[:, None] * u + np.sin(theta)[:, None] * v  # (res, 3)

    def ring(s: float, rho: float) -> np.ndarray:
        if rho == 0.0:
            return (a + s * e)[None, :]
        return a + s * e + rho * radial

    ring0 = ring(s0, r0)
    ring1 = ring(s1, r1)
    n0 = ring0.shape[0]
    i = np.arange(resolution)
    j = (i + 1) % resolution
    if n0 == 1:  # apex at end 0
        tri = np.stack([np.zeros(resolution, dtype=np.int64), 1 + j, 1 + i], axis=1)
    elif ring1.shape[0] == 1:  # apex at end 1
        tri = np.stack([i, j, np.full(resolution, n0)], axis=1)
    else:
        tri = np.concatenate(
            [np.stack([i, j, n0 + j], axis=1), np.stack([i, n0 + j, n0 + i], axis=1)], axis=0
        )
    return np.concatenate([ring0, ring1], axis=0), tri.astype(np.int64)


def wall_triangles(
    kind: int, params: np.ndarray, bounds: Sequence[np.ndarray], resolution: int = 48
) -> tuple[np.ndarray, np.ndarray]:
    """Triangulated surface of one wall.

    Parameters
    ----------
    kind : wall kind (``KIND_PLANE``, ``KIND_RECTANGLE``, ``KIND_REVOLVED``, ``KIND_CYLINDER``).
    params : the wall's parameter vector (length 16, current position) [m].
    bounds : scene box (lo, hi) [m]; used only for infinite walls (plane, infinite cylinder),
        which must then be finite with lo < hi.
    resolution : number of segments around the axis of revolved walls and cylinders (≥ 3).

    Returns
    -------
    (points, triangles): float64 (m, 3) vertices [m] and int64 (k, 3) vertex indices. Empty
    arrays ((0, 3)) when a plane misses the box.

    Raises
    ------
    OutputError
        unknown kind, malformed params, bad resolution, or bounds unusable for an infinite wall.
    """
    p = np.asarray(params, dtype=np.float64)
    if p.ndim == 2 and p.shape[1] == N_PARAMS:  # a wall of several rows (a mesh): all facets
        parts = [wall_triangles(kind, row, bounds, resolution) for row in p]
        pts = np.concatenate([q[0] for q in parts]) if parts else np.zeros((0, 3))
        offsets = np.cumsum([0] + [q[0].shape[0] for q in parts[:-1]])
        tris = [q[1] + o for q, o in zip(parts, offsets, strict=True)]
        return pts, (np.concatenate(tris) if tris else np.zeros((0, 3), dtype=np.int64))
    if p.shape != (N_PARAMS,) or not np.all(np.isfinite(p)):
        raise OutputError(
            f"wall_triangles: params must be {N_PARAMS} finite floats, got shape {p.shape}; pass the "
            f"wall's parameter vector (WallShape.params(offset))"
        )
    if int(resolution) != resolution or resolution < 3:
        raise OutputError(f"wall_triangles: resolution must be an integer >= 3, got {resolution!r}")
    resolution = int(resolution)
    if kind == KIND_PLANE:
        lo, hi = _check_bounds(kind, bounds)
        return _plane_patch(p, lo, hi)
    if kind == KIND_RECTANGLE:
        return _rectangle(p)
    if kind == KIND_REVOLVED:
        return _revolved(p[0:3], p[3:6], float(p[6]), float(p[7]), float(p[8]), float(p[9]), resolution)
    if kind == KIND_CYLINDER:
        lo, hi = _check_bounds(kind, bounds)
        s = (_box_corners(lo, hi) - p[0:3]) @ p[3:6]
        radius = float(p[6])
        return _revolved(p[0:3], p[3:6], float(s.min()), radius, float(s.max()), radius, resolution)
    if kind == KIND_TRIANGLE:
        pts = np.array([p[0:3], p[0:3] + p[3:6], p[0:3] + p[6:9]])
        return pts, np.array([[0, 1, 2]], dtype=np.int64)
    if kind == KIND_SPHERE:
        return _sphere(p[0:3], float(p[3]), resolution)
    known = ", ".join(f"{k} ({v})" for k, v in KIND_NAMES.items())
    raise OutputError(f"wall_triangles: unknown wall kind {kind!r}; known kinds: {known}")


def _sphere(c: np.ndarray, radius: float, resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """A UV sphere: ``resolution`` segments around, ``resolution // 2`` from pole to pole."""
    nu, nv = resolution, max(resolution // 2, 2)
    th = np.linspace(0.0, math.pi, nv + 1)[1:-1]
    ph = np.linspace(0.0, 2 * math.pi, nu, endpoint=False)
    t, f = np.meshgrid(th, ph, indexing="ij")
    ring = np.stack([np.sin(t) * np.cos(f), np.sin(t) * np.sin(f), np.cos(t)], -1).reshape(-1, 3)
    pts = c + radius * np.concatenate([[[0.0, 0.0, 1.0]], ring, [[0.0, 0.0, -1.0]]])
    tris = []
    last = pts.shape[0] - 1
    for j in range(nu):
        k = (j + 1) % nu
        tris.append([0, 1 + j, 1 + k])
        base = 1 + (nv - 2) * nu
        tris.append([last, base + k, base + j])
    for i in range(nv - 2):
        for j in range(nu):
            k = (j + 1) % nu
            a, b = 1 + i * nu + j, 1 + i * nu + k
            c2, d = a + nu, b + nu
            tris += [[a, c2, b], [b, c2, d]]
    return pts, np.array(tris, dtype=np.int64)


def mesh_area(points: np.ndarray, triangles: np.ndarray) -> float:
    """Total area of a triangle mesh [m²]."""
    pts = np.asarray(points, dtype=np.float64)
    tri = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    if tri.shape[0] == 0:
        return 0.0
    a, b, c = pts[tri[:, 0]], pts[tri[:, 1]], pts[tri[:, 2]]
    return float(0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum())

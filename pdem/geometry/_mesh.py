"""Numba kernels of triangle-mesh walls: candidate search and one contact per grain and mesh.

A grain near a mesh is within reach of several facets: on a flat part made of two triangles, a
grain over one triangle is also within reach of the shared edge of the other. Counting both would
double its load. :func:`filter_mesh_candidates` keeps, per grain and mesh, the contacts whose
closest point lies inside a face (several faces: a concave corner, all genuine), and, if the grain
touches no face, only its closest edge or vertex contact (the first facet among equals within
1e-9 of the radius, so the choice does not depend on rounding): a convex edge is touched once.
A genuinely separate second edge contact of the same grain (a grain wedged in a narrow convex
feature of its own size) is set aside too; meshes are meant to be coarse next to the grains.

Contact history is keyed by (facet, grain). A grain sliding from one facet onto a coplanar
neighbour would lose its tangential spring; the filter hands the history over instead: a new
contact (zero history) of a grain that, on a facet of the same mesh with the same plane, has a
history it no longer uses takes that history. On flat parts a mesh then behaves as the plane.
"""

from __future__ import annotations

import math

import numpy as np

from pdem._jit import njit

from ._kernels import triangle_contact

__all__ = ["filter_mesh_candidates", "triangle_candidates"]


@njit
def _face_normal(p):
    fx = p[4] * p[8] - p[5] * p[7]
    fy = p[5] * p[6] - p[3] * p[8]
    fz = p[3] * p[7] - p[4] * p[6]
    fn = math.sqrt(fx * fx + fy * fy + fz * fz)
    return fx / fn, fy / fn, fz / fn


@njit
def filter_mesh_candidates(params, cstart, cand, step, a, b, x, r, inv_m, reach, hist):
    """Mark in ``step`` (a copy of ``cand``) the candidates of rows [a, b) set aside this step as
    ``-1 - i``, and hand history over between coplanar facets (``hist``: rows by candidate). A
    contact counts when its gap is below ``reach`` (0 for DEM-P, the envelope for DEM-C).
    Candidates already negative in ``cand`` (removed particles) stay set aside."""
    n = x.shape[0]
    has_face = np.zeros(n, dtype=np.bool_)
    best_gap = np.full(n, np.inf)
    best_row = np.full(n, -1, dtype=np.int64)
    orphan = np.full(n, -1, dtype=np.int64)  # a candidate row with history the grain no longer uses
    orphan_k = np.full(n, -1, dtype=np.int64)
    hsize = hist.shape[1]
    for k in range(a, b):
        p = params[k]
        for q in range(cstart[k], cstart[k + 1]):
            i = cand[q]
            if i < 0:  # set aside until the next rebuild (a removed particle)
                continue
            gap, _nx, _ny, _nz, _cx, _cy, _cz, inside = triangle_contact(p, x[i, 0], x[i, 1], x[i, 2], r[i])
            if gap >= reach:
                continue
            if inside:
                has_face[i] = True
            elif gap < best_gap[i] - 1e-9 * r[i]:
                best_gap[i] = gap
                best_row[i] = k
    for k in range(a, b):
        p = params[k]
        for q in range(cstart[k], cstart[k + 1]):
            i = cand[q]
            if i < 0:
                continue
            gap, _nx, _ny, _nz, _cx, _cy, _cz, inside = triangle_contact(p, x[i, 0], x[i, 1], x[i, 2], r[i])
            kept = gap < reach and (inside or (not has_face[i] and best_row[i] == k))
            if gap < reach and not kept:
                step[q] = -1 - i
            if not kept:
                used = False
                for h in range(hsize):
                    if hist[q, h] != 0.0:
                        used = True
                if used:
                    orphan[i] = q
                    orphan_k[i] = k
    # hand over: a new contact takes the unused history of a coplanar facet of the same grain
    for k in range(a, b):
        p = params[k]
        for q in range(cstart[k], cstart[k + 1]):
            i = cand[q]
            if i < 0:
                continue
            o = orphan[i]
            if o < 0 or step[q] < 0:
                continue
            fresh = True
            for h in range(hsize):
                if hist[q, h] != 0.0:
                    fresh = False
            if not fresh:
                continue
            gap = triangle_contact(p, x[i, 0], x[i, 1], x[i, 2], r[i])[0]
            if gap >= reach:
                continue
            n1x, n1y, n1z = _face_normal(p)
            n2x, n2y, n2z = _face_normal(params[orphan_k[i]])
            if abs(n1x * n2x + n1y * n2y + n1z * n2z) < 1.0 - 1e-12:
                continue
            for h in range(hsize):
                hist[q, h] = hist[o, h]
                hist[o, h] = 0.0
            orphan[i] = -1


@njit
def _bisect_left(xs, v):
    lo = 0
    hi = xs.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if xs[mid] < v:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit
def _facet_box(p, pad):
    lo = np.empty(3)
    hi = np.empty(3)
    for c in range(3):
        v0 = p[c]
        v1 = p[c] + p[3 + c]
        v2 = p[c] + p[6 + c]
        lo[c] = min(v0, min(v1, v2)) - pad
        hi[c] = max(v0, max(v1, v2)) + pad
    return lo, hi


@njit
def _scan(rows, x, r, order, xs, skin, pad, counts, out, fill):
    total = 0
    for k in range(rows.shape[0]):
        p = rows[k]
        lo, hi = _facet_box(p, pad)
        start = _bisect_left(xs, lo[0])
        c = 0
        for s in range(start, xs.shape[0]):
            if xs[s] > hi[0]:
                break
            i = order[s]
            if x[i, 1] < lo[1] or x[i, 1] > hi[1] or x[i, 2] < lo[2] or x[i, 2] > hi[2]:
                continue
            gap = triangle_contact(p, x[i, 0], x[i, 1], x[i, 2], r[i])[0]
            if gap < skin:
                if fill:
                    out[total] = i
                total += 1
                c += 1
        counts[k] = c
    return total


def triangle_candidates(rows: np.ndarray, x: np.ndarray, r: np.ndarray, skin: float) -> list[np.ndarray]:
    """For every facet row, the particles (storage rows of ``x``) whose gap is below ``skin``: a sweep
    over the particles sorted by x, then a box test, then the exact gap."""
    n = x.shape[0]
    if n == 0:
        return [np.zeros(0, dtype=np.int64) for _ in range(rows.shape[0])]
    order = np.argsort(x[:, 0], kind="stable").astype(np.int64)
    xs = np.ascontiguousarray(x[order, 0])
    pad = float(r.max()) + max(skin, 0.0)
    if not math.isfinite(pad):
        pad = 0.0
    counts = np.zeros(rows.shape[0], dtype=np.int64)
    dummy = np.zeros(1, dtype=np.int64)
    total = _scan(rows, x, r, order, xs, skin, pad, counts, dummy, False)
    out = np.empty(max(total, 1), dtype=np.int64)
    _scan(rows, x, r, order, xs, skin, pad, counts, out, True)
    ends = np.cumsum(counts)
    return [np.sort(out[e - c : e]) for e, c in zip(ends, counts, strict=True)]

"""numba kernels of the coarse-grained fields (:mod:`pdem.fields.coarse`).

Every kernel takes arrays and scalars. A field value at a point is an exact sum: each point's terms
go, 1024 at a time, into a fixed-point accumulator (:func:`pdem.parallel.exact.exact_add_many`)
whose value is exact whatever the order of the terms; it is then rounded once
(:func:`fsum_exact`, CPython's ``math.fsum`` algorithm) or, on several ranks, handed on as the few
doubles (:func:`pdem.parallel.exact.exact_partials`) whose sum it is.

Items (one row of ``data`` each, periodic images already expanded):

``GRAIN``  x, y, z, m, V, vx, vy, vz: columns ρ, solid fraction, number density, momentum (3), Σ m v v φ
           (6: xx yy zz xy xz yz), ∇ρ (3), ∇p (9, row-major: ∂_b p_a at 3 a + b);
``LINE``   x, y, z (start), bx, by, bz (segment), T (9, row-major): columns T ∫₀¹ φ(r − x − s b) ds;
``END``    x, y, z, nx, ny, nz: columns φ, n n φ (6, as above);
``POINT``  x, y, z, fx, fy, fz: columns f φ.
"""

from __future__ import annotations

import math

import numpy as np

from pdem.api import wall_contact
from pdem.parallel.exact import EXACT_MANY_MAX, exact_accumulator, exact_add_many, exact_bins, exact_partials

from .._jit import njit

GAUSS = 0
LUCY = 1

GRAIN = 0
LINE = 1
END = 2
POINT = 3

#: columns each item kind adds to, in the order of the module docstring
N_COLUMNS = {GRAIN: 24, LINE: 9, END: 7, POINT: 3}
N_COLUMNS_ARR = np.array(
    [N_COLUMNS[GRAIN], N_COLUMNS[LINE], N_COLUMNS[END], N_COLUMNS[POINT]], dtype=np.int64
)

_SQRT_HALF_PI = math.sqrt(0.5 * math.pi)
_SQRT2 = math.sqrt(2.0)


# ---------------------------------------------------------------------------------------------
# correctly rounded sums
# ---------------------------------------------------------------------------------------------


@njit
def fsum_exact(x, n):
    """The correctly rounded sum of the finite doubles x[0:n]: CPython's ``math.fsum`` (Shewchuk's
    partials, then the round-half-even fix across partials), line for line, so that the value is
    the one ``math.fsum`` and :func:`pdem.parallel.exact.exact_reduce` give."""
    p = np.empty(n + 1)
    np_ = 0
    for idx in range(n):
        xv = x[idx]
        i = 0
        for j in range(np_):
            y = p[j]
            if abs(xv) < abs(y):
                t = xv
                xv = y
                y = t
            hi = xv + y
            yr = hi - xv
            lo = y - yr
            if lo != 0.0:
                p[i] = lo
                i += 1
            xv = hi
        np_ = i
        if xv != 0.0:
            p[np_] = xv
            np_ += 1
    hi = 0.0
    lo = 0.0
    if np_ > 0:
        np_ -= 1
        hi = p[np_]
        while np_ > 0:
            xv = hi
            np_ -= 1
            y = p[np_]
            hi = xv + y
            yr = hi - xv
            lo = y - yr
            if lo != 0.0:
                break
        if np_ > 0 and ((lo < 0.0 and p[np_ - 1] < 0.0) or (lo > 0.0 and p[np_ - 1] > 0.0)):
            y = lo * 2.0
            xv = hi + y
            yr = xv - hi
            if y == yr:
                hi = xv
    return hi


@njit
def combine_rows(keys, ptr, vals, special, order, out):
    """out[key] = the correctly rounded sum of the partials of every row with that key (rows of
    several ranks), or the sum of their non-finite terms if any; ``order`` sorts the keys."""
    n = keys.shape[0]
    buf = np.empty(64)
    a = 0
    while a < n:
        key = keys[order[a]]
        b = a
        m = 0
        sp = 0.0
        while b < n and keys[order[b]] == key:
            r = order[b]
            sp += special[r]
            c = ptr[r + 1] - ptr[r]
            if m + c > buf.shape[0]:
                nb = np.empty(2 * (m + c))
                nb[:m] = buf[:m]
                buf = nb
            for q in range(c):
                buf[m + q] = vals[ptr[r] + q]
            m += c
            b += 1
        out[key] = sp if (sp != 0.0 or sp != sp) else fsum_exact(buf, m)
        a = b


# ---------------------------------------------------------------------------------------------
# kernels and their line integrals
# ---------------------------------------------------------------------------------------------


@njit(inline="always")
def _value_grad(kern, a, w, c, d2):
    """(φ, g) at squared distance d2 < c²: the kernel value and the factor g with ∇φ = g (r − x)."""
    if kern == GAUSS:
        phi = a * math.exp(-0.5 * d2 / (w * w))
        return phi, -phi / (w * w)
    rho = math.sqrt(d2)
    q = rho / c
    phi = a * (1.0 + q * q * (-6.0 + q * (8.0 - 3.0 * q)))
    e = c - rho
    return phi, -12.0 * a * e * e / (c * c * c * c)


@njit(inline="always")
def _value(kern, a, w, c, d2):
    if kern == GAUSS:
        return a * math.exp(-0.5 * d2 / (w * w))
    q = math.sqrt(d2) / c
    return a * (1.0 + q * q * (-6.0 + q * (8.0 - 3.0 * q)))


@njit(inline="always")
def _lucy_antiderivative(u, e2):
    """∫ (1 − 6 q² + 8 q³ − 3 q⁴) du with q² = u² + e² (lengths in units of the cut-off radius)."""
    s2 = u * u + e2
    g = u * (2.0 * u * u + 5.0 * e2) * math.sqrt(s2) / 8.0
    e4 = e2 * e2
    if e4 > 0.0:
        g += 0.375 * e4 * math.asinh(u / math.sqrt(e2))
    u3 = u * u * u
    return u - 6.0 * (u3 / 3.0 + e2 * u) + 8.0 * g - 3.0 * (u3 * u * u / 5.0 + 2.0 * e2 * u3 / 3.0 + e4 * u)


@njit(inline="always")
def line_integral(kern, a, w, c, dx, dy, dz, bx, by, bz):
    """∫₀¹ φ(d − s b) ds exactly (closed forms), d = r − x the point relative to the segment's start,
    b the segment: the chord of the segment inside the cut-off sphere, then ∫ of the Gaussian (erf,
    erfc) or of Lucy's polynomial (its q³ term by asinh) along it. A segment shorter than 10⁻⁸ c
    takes the kernel at its midpoint (an error of order (|b|/c)²)."""
    b2 = bx * bx + by * by + bz * bz
    c2 = c * c
    if b2 < 1e-16 * c2:
        mx = dx - 0.5 * bx
        my = dy - 0.5 * by
        mz = dz - 0.5 * bz
        m2 = mx * mx + my * my + mz * mz
        return _value(kern, a, w, c, m2) if m2 < c2 else 0.0
    db = dx * bx + dy * by + dz * bz
    sc = min(max(db / b2, 0.0), 1.0)  # the segment's point closest to r: out of reach, nothing
    ex = dx - sc * bx
    ey = dy - sc * by
    ez = dz - sc * bz
    if not ex * ex + ey * ey + ez * ez < c2:
        return 0.0
    bl = math.sqrt(b2)
    cx = dy * bz - dz * by
    cy = dz * bx - dx * bz
    cz = dx * by - dy * bx
    h2 = (cx * cx + cy * cy + cz * cz) / b2  # squared distance from r to the segment's line
    if h2 >= c2:
        return 0.0
    t0 = -db / bl  # the arc length along the line, 0 at the foot of r
    t1 = t0 + bl
    half = math.sqrt(c2 - h2)
    ta = max(t0, -half)
    tb = min(t1, half)
    if not tb > ta:
        return 0.0
    if kern == GAUSS:
        s = w * _SQRT2
        xa = ta / s
        xb = tb / s
        if xa >= 0.0:
            diff = math.erfc(xa) - math.erfc(xb)
        elif xb <= 0.0:
            diff = math.erfc(-xb) - math.erfc(-xa)
        else:
            diff = math.erf(xb) - math.erf(xa)
        return a * math.exp(-0.5 * h2 / (w * w)) * w * _SQRT_HALF_PI * diff / bl
    e2 = h2 / c2
    return a * c * (_lucy_antiderivative(tb / c, e2) - _lucy_antiderivative(ta / c, e2)) / bl


@njit
def line_integrals(kern, a, w, c, d, b):
    """:func:`line_integral` over rows of d and b (n, 3) (for tests and scripts)."""
    n = d.shape[0]
    out = np.empty(n)
    for k in range(n):
        out[k] = line_integral(kern, a, w, c, d[k, 0], d[k, 1], d[k, 2], b[k, 0], b[k, 1], b[k, 2])
    return out


# ---------------------------------------------------------------------------------------------
# geometry helpers
# ---------------------------------------------------------------------------------------------


@njit
def wall_normals(kinds, params, x, r):
    """Unit normals from each grain centre into its wall (:func:`pdem.api.wall_contact`)."""
    n = x.shape[0]
    out = np.empty((n, 3))
    for k in range(n):
        _g, nx, ny, nz, _cx, _cy, _cz = wall_contact(kinds[k], params[k], x[k, 0], x[k, 1], x[k, 2], r[k])
        out[k, 0] = nx
        out[k, 1] = ny
        out[k, 2] = nz
    return out


@njit
def bin_points(points, lo, inv_s, ncell):
    """Cell of each point (C order over ``ncell``, int64), clamped into the grid of cells."""
    n = points.shape[0]
    out = np.empty(n, dtype=np.int64)
    for k in range(n):
        idx = 0
        for a in range(3):
            f = (points[k, a] - lo[a]) * inv_s
            i = int(min(max(math.floor(f), 0.0), float(ncell[a] - 1)))
            idx = idx * ncell[a] + i
        out[k] = idx
    return out


@njit
def bin_items(ilo, ihi, lo, inv_s, ncell):
    """Cells overlapped by each item's support box [ilo, ihi]: (start per cell, item indices), the
    items of a cell in item order. Boxes outside the grid of cells are left out."""
    n = ilo.shape[0]
    ntot = ncell[0] * ncell[1] * ncell[2]
    rng = np.empty((n, 6), dtype=np.int64)
    count = np.zeros(ntot + 1, dtype=np.int64)
    for k in range(n):
        inside = True
        for a in range(3):
            f0 = math.floor((ilo[k, a] - lo[a]) * inv_s)
            f1 = math.floor((ihi[k, a] - lo[a]) * inv_s)
            top = float(ncell[a] - 1)
            if f1 < 0.0 or f0 > top:
                inside = False
            rng[k, 2 * a] = int(min(max(f0, 0.0), top))
            rng[k, 2 * a + 1] = int(min(max(f1, 0.0), top))
        if not inside:
            rng[k, 0] = 1
            rng[k, 1] = 0
            continue
        for i in range(rng[k, 0], rng[k, 1] + 1):
            for j in range(rng[k, 2], rng[k, 3] + 1):
                for m in range(rng[k, 4], rng[k, 5] + 1):
                    count[(i * ncell[1] + j) * ncell[2] + m + 1] += 1
    for q in range(ntot):
        count[q + 1] += count[q]
    items = np.empty(count[ntot], dtype=np.int64)
    fill = count[:ntot].copy()
    for k in range(n):
        for i in range(rng[k, 0], rng[k, 1] + 1):
            for j in range(rng[k, 2], rng[k, 3] + 1):
                for m in range(rng[k, 4], rng[k, 5] + 1):
                    cell = (i * ncell[1] + j) * ncell[2] + m
                    items[fill[cell]] = k
                    fill[cell] += 1
    return count, items


# ---------------------------------------------------------------------------------------------
# the accumulation pass
# ---------------------------------------------------------------------------------------------


@njit(inline="always")
def _flush(acc, bins, tb, special, nq, m):
    for q in range(nq):
        special[q] += exact_add_many(acc[q], bins, tb[q], m)


@njit
def _grow(a, need):
    if need <= a.shape[0]:
        return a
    out = np.empty(max(need, 2 * a.shape[0]), dtype=a.dtype)
    out[: a.shape[0]] = a
    return out


@njit
def accumulate(kind, kern, a, w, c, points, order, pstart, istart, items, data, shared, out, col0, ncols):
    """Every point's exact sums of the terms of the items of one kind (``kind``, the module
    docstring's layout) within the kernel's reach.

    ``order``/``pstart``: the points by cell; ``istart``/``items``: the items overlapping each cell.
    In a cell no other rank has items of this kind in (``shared[cell] == 0``; always on one rank):
    out[point, col0 + q] = the correctly rounded sum (points no item reaches are left as they are).
    The points of shared cells are returned as this rank's partial sums of the points it reached:
    (points, counts per (point, column), partials, non-finite sums per (point, column)), each
    point's columns in order. ``ncols``: sum only the kind's first ``ncols`` columns (the grains'
    come in the order their fields need them: ρ, φ, n; p; Σ m v v; the gradients)."""
    nq = min(ncols, N_COLUMNS_ARR[kind])
    acc0, _buf, _bits = exact_accumulator()
    nb = acc0.shape[0]
    acc = np.zeros((nq, nb), dtype=np.int64)
    bins = exact_bins()
    tb = np.empty((N_COLUMNS_ARR[kind], EXACT_MANY_MAX))  # every term is computed; nq are summed
    special = np.zeros(nq)
    c2 = c * c
    ncells = istart.shape[0] - 1
    # partial sums (several ranks)
    tp = np.empty(16, dtype=np.int64)
    cnt = np.empty(16 * nq, dtype=np.int64)
    spc = np.empty(16 * nq)
    vals = np.empty(64)
    ntp = 0
    nv = 0
    for cell in range(ncells):
        ia = istart[cell]
        ib = istart[cell + 1]
        if ia == ib:
            continue
        for pp in range(pstart[cell], pstart[cell + 1]):
            pt = order[pp]
            rx = points[pt, 0]
            ry = points[pt, 1]
            rz = points[pt, 2]
            m = 0
            hit = False
            for it in range(ia, ib):
                k = items[it]
                dx = rx - data[k, 0]
                dy = ry - data[k, 1]
                dz = rz - data[k, 2]
                if kind == LINE:
                    li = line_integral(kern, a, w, c, dx, dy, dz, data[k, 3], data[k, 4], data[k, 5])
                    if li == 0.0:
                        continue
                    for q in range(9):
                        tb[q, m] = data[k, 6 + q] * li
                else:
                    d2 = dx * dx + dy * dy + dz * dz
                    if not d2 < c2:
                        continue
                    if kind == GRAIN:
                        phi, g = _value_grad(kern, a, w, c, d2)
                        mass = data[k, 3]
                        vx = data[k, 5]
                        vy = data[k, 6]
                        vz = data[k, 7]
                        mp = mass * phi
                        px = mp * vx
                        py = mp * vy
                        pz = mp * vz
                        gx = g * dx
                        gy = g * dy
                        gz = g * dz
                        mvx = mass * vx
                        mvy = mass * vy
                        mvz = mass * vz
                        tb[0, m] = mp
                        tb[1, m] = data[k, 4] * phi
                        tb[2, m] = phi
                        tb[3, m] = px
                        tb[4, m] = py
                        tb[5, m] = pz
                        tb[6, m] = px * vx
                        tb[7, m] = py * vy
                        tb[8, m] = pz * vz
                        tb[9, m] = px * vy
                        tb[10, m] = px * vz
                        tb[11, m] = py * vz
                        tb[12, m] = mass * gx
                        tb[13, m] = mass * gy
                        tb[14, m] = mass * gz
                        tb[15, m] = mvx * gx
                        tb[16, m] = mvx * gy
                        tb[17, m] = mvx * gz
                        tb[18, m] = mvy * gx
                        tb[19, m] = mvy * gy
                        tb[20, m] = mvy * gz
                        tb[21, m] = mvz * gx
                        tb[22, m] = mvz * gy
                        tb[23, m] = mvz * gz
                    elif kind == END:
                        phi = _value(kern, a, w, c, d2)
                        nx = data[k, 3]
                        ny = data[k, 4]
                        nz = data[k, 5]
                        tb[0, m] = phi
                        tb[1, m] = nx * nx * phi
                        tb[2, m] = ny * ny * phi
                        tb[3, m] = nz * nz * phi
                        tb[4, m] = nx * ny * phi
                        tb[5, m] = nx * nz * phi
                        tb[6, m] = ny * nz * phi
                    else:
                        phi = _value(kern, a, w, c, d2)
                        tb[0, m] = data[k, 3] * phi
                        tb[1, m] = data[k, 4] * phi
                        tb[2, m] = data[k, 5] * phi
                m += 1
                hit = True
                if m == EXACT_MANY_MAX:
                    _flush(acc, bins, tb, special, nq, m)
                    m = 0
            if not hit:
                continue
            if m > 0:
                _flush(acc, bins, tb, special, nq, m)
            if shared[cell] == 0:
                for q in range(nq):
                    dg = exact_partials(acc[q])
                    sp = special[q]
                    out[pt, col0 + q] = sp if (sp != 0.0 or sp != sp) else fsum_exact(dg, dg.shape[0])
                    acc[q, :] = 0
                    special[q] = 0.0
                continue
            tp = _grow(tp, ntp + 1)
            cnt = _grow(cnt, (ntp + 1) * nq)
            spc = _grow(spc, (ntp + 1) * nq)
            tp[ntp] = pt
            for q in range(nq):
                dg = exact_partials(acc[q])
                nd = dg.shape[0]
                vals = _grow(vals, nv + nd)
                for e in range(nd):
                    vals[nv + e] = dg[e]
                nv += nd
                cnt[ntp * nq + q] = nd
                spc[ntp * nq + q] = special[q]
                acc[q, :] = 0
                special[q] = 0.0
            ntp += 1
    return tp[:ntp].copy(), cnt[: ntp * nq].copy(), vals[:nv].copy(), spc[: ntp * nq].copy()
